"""V4L2 camera driver against a fake at the adapter boundary: formats bit-exact, controls, faults, reopen.

Expected bytes come from `ref_pack_row`, a per-pixel transcription of the kernel's V4L2 format tables,
written independently of the vectorized codec under test.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from drivers.camera import open_camera
from drivers.camera.fake_v4l2 import (
    FakeV4L2Bus,
    FakeV4L2Device,
    PlantedFrame,
    default_controls,
    relative_iris_control,
    uvc_iris_control,
)
from drivers.camera.formats import FORMATS, lookup_format
from drivers.camera.v4l2 import V4L2Camera
from drivers.camera.v4l2_adapter import (
    BUF_FLAG_ERROR,
    CID_AUTOGAIN,
    CID_EXPOSURE,
    CID_EXPOSURE_ABSOLUTE,
    CID_EXPOSURE_AUTO,
    CID_GAIN,
    CID_IRIS_ABSOLUTE,
    CID_IRIS_RELATIVE,
    ControlInfo,
)
from drivers.camera.v4l2_iris import IrisMap
from mlaqc.errors import DeviceError, InputError

pytestmark = pytest.mark.timeout(10)

# name -> (bits, layout, cfa), transcribed from pixfmt-yuv-luma.rst and pixfmt-srggb*.rst
SPEC = {
    "GREY": (8, "u8", None), "Y10": (10, "le", None), "Y12": (12, "le", None), "Y14": (14, "le", None),
    "Y16": (16, "le", None), "Y16_BE": (16, "be", None), "Y012": (12, "msb", None),
    "Y10P": (10, "p10", None), "Y12P": (12, "p12", None), "Y14P": (14, "p14", None), "Y10B": (10, "bpack", None),
    "BA81": (8, "u8", "BGGR"), "GBRG": (8, "u8", "GBRG"), "GRBG": (8, "u8", "GRBG"), "RGGB": (8, "u8", "RGGB"),
    "BG10": (10, "le", "BGGR"), "GB10": (10, "le", "GBRG"), "BA10": (10, "le", "GRBG"), "RG10": (10, "le", "RGGB"),
    "BG12": (12, "le", "BGGR"), "GB12": (12, "le", "GBRG"), "BA12": (12, "le", "GRBG"), "RG12": (12, "le", "RGGB"),
    "BG14": (14, "le", "BGGR"), "GB14": (14, "le", "GBRG"), "GR14": (14, "le", "GRBG"), "RG14": (14, "le", "RGGB"),
    "BYR2": (16, "le", "BGGR"), "GB16": (16, "le", "GBRG"), "GR16": (16, "le", "GRBG"), "RG16": (16, "le", "RGGB"),
    "pBAA": (10, "p10", "BGGR"), "pGAA": (10, "p10", "GBRG"), "pgAA": (10, "p10", "GRBG"), "pRAA": (10, "p10", "RGGB"),
    "pBCC": (12, "p12", "BGGR"), "pGCC": (12, "p12", "GBRG"), "pgCC": (12, "p12", "GRBG"), "pRCC": (12, "p12", "RGGB"),
    "pBEE": (14, "p14", "BGGR"), "pGEE": (14, "p14", "GBRG"), "pgEE": (14, "p14", "GRBG"), "pREE": (14, "p14", "RGGB"),
}


def _groups(row: list[int], n: int) -> list[list[int]]:
    padded = row + [0] * (-len(row) % n)
    return [padded[i:i + n] for i in range(0, len(padded), n)]


def ref_pack_row(row: list[int], layout: str) -> bytes:
    """One row encoded pixel by pixel as the kernel documentation's byte tables say."""
    out: list[int] = []
    if layout == "u8":
        out = list(row)
    elif layout == "le":
        for v in row:
            out += [v & 0xFF, v >> 8]
    elif layout == "be":
        for v in row:
            out += [v >> 8, v & 0xFF]
    elif layout == "msb":
        for v in row:
            out += [(v << 4) & 0xFF, v >> 4]
    elif layout == "p10":
        for p in _groups(row, 4):
            out += [p[0] >> 2, p[1] >> 2, p[2] >> 2, p[3] >> 2,
                    (p[0] & 3) | (p[1] & 3) << 2 | (p[2] & 3) << 4 | (p[3] & 3) << 6]
    elif layout == "p12":
        for p in _groups(row, 2):
            out += [p[0] >> 4, p[1] >> 4, (p[0] & 0xF) | (p[1] & 0xF) << 4]
    elif layout == "p14":
        for p in _groups(row, 4):
            lo = [v & 0x3F for v in p]
            out += [p[0] >> 6, p[1] >> 6, p[2] >> 6, p[3] >> 6,
                    lo[0] | (lo[1] & 0x3) << 6, lo[1] >> 2 | (lo[2] & 0xF) << 4, lo[2] >> 4 | lo[3] << 2]
    elif layout == "bpack":
        for p in _groups(row, 4):
            word = (p[0] << 30) | (p[1] << 20) | (p[2] << 10) | p[3]
            out += list(word.to_bytes(5, "big"))
    return bytes(out)


def ref_pack(image: np.ndarray, layout: str, bytes_per_line: int) -> bytes:
    """A whole image, each row padded with 0xEE filler up to the stride (padding must be ignored)."""
    rows = [ref_pack_row([int(v) for v in row], layout) for row in image]
    return b"".join(r + b"\xee" * (bytes_per_line - len(r)) for r in rows)


def y16(image: np.ndarray) -> bytes:
    """Y16 bytes (little-endian words)."""
    return np.asarray(image, dtype="<u2").tobytes()


@pytest.fixture
def world(tmp_path):
    """A by-id directory, a node with a Y16 8x6 fake camera, and the bus mapping nodes to devices."""
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    dev = FakeV4L2Device(tmp_path / "video0", formats=("Y16", "Y10", "GREY"), width=8, height=6)
    link = by_id / "usb-Acme_MLA_Cam_1234-video-index0"
    link.symlink_to(tmp_path / "video0")
    return {"dev": dev, "bus": FakeV4L2Bus(dev), "by_id": by_id, "link": link, "tmp": tmp_path}


def make_camera(world, query: str = "", **kwargs) -> V4L2Camera:
    """An opened camera on the world's fake device, from a real URL."""
    url = f"v4l2://{world['tmp'] / 'video0'}" + (f"?{query}" if query else "")
    return open_camera(url, adapter_factory=world["bus"], by_id_dir=world["by_id"], **kwargs)


# --------------------------------------------------------------------------- formats, bit-exact


@pytest.mark.parametrize("name, pixels, expected", [
    ("GREY", [0, 255, 7], b"\x00\xff\x07"),
    ("Y10", [0x3FF, 0x001, 0x200], b"\xff\x03\x01\x00\x00\x02"),
    ("Y16", [0x1234, 0xFFFF], b"\x34\x12\xff\xff"),
    ("Y16_BE", [0x1234, 0x00FF], b"\x12\x34\x00\xff"),
    ("Y012", [0xABC], b"\xc0\xab"),
    ("Y10P", [0x3FF, 0x000, 0x155, 0x2AA], bytes([0xFF, 0x00, 0x55, 0xAA, 0x93])),
    ("Y12P", [0xABC, 0x123], bytes([0xAB, 0x12, 0x3C])),
    ("Y14P", [0x3FFF, 0x0001, 0x2000, 0x1555], bytes([0xFF, 0x00, 0x80, 0x55, 0x7F, 0x00, 0x54])),
    ("Y10B", [0x3FF, 0x000, 0x3FF, 0x000], bytes([0xFF, 0xC0, 0x0F, 0xFC, 0x00])),
    ("pRAA", [0x3FF, 0x000, 0x155, 0x2AA], bytes([0xFF, 0x00, 0x55, 0xAA, 0x93])),
])
def test_hand_computed_byte_vectors_decode_and_encode(name, pixels, expected):
    fmt = lookup_format(name)
    assert fmt.unpack(expected, len(pixels), 1).tolist() == [pixels]
    assert fmt.pack(np.array([pixels])) == expected
    assert ref_pack_row(pixels, SPEC[name][1]) == expected


def test_format_table_matches_spec_and_linuxpy_codes():
    linuxpy_raw = pytest.importorskip("linuxpy.video.raw")
    assert {f.name for f in FORMATS} == set(SPEC)
    for f in FORMATS:
        assert (f.bits, f.cfa) == SPEC[f.name][::2], f.name
        kernel_names = [n for n in (f.name, *f.aliases) if n in linuxpy_raw.PixelFormat.__members__]
        assert kernel_names, f.name
        assert all(linuxpy_raw.PixelFormat[n].value == f.code for n in kernel_names), f.name


@pytest.mark.parametrize("name", sorted(SPEC))
def test_every_format_captured_bit_exact(tmp_path, name):
    bits, layout, cfa = SPEC[name]
    width, height = 10, 4  # 10 is not a multiple of the 4-pixel packing groups: exercises the partial group
    dev = FakeV4L2Device(tmp_path / "video0", formats=(name,), width=width, height=height, stride_pad=3)
    rng = np.random.default_rng(bits)
    image = rng.integers(0, 1 << bits, (height, width))
    image[0, 0], image[-1, -1] = 0, (1 << bits) - 1
    cam = open_camera(f"v4l2://{tmp_path / 'video0'}?format={name}", adapter_factory=FakeV4L2Bus(dev),
                      by_id_dir=tmp_path)
    stride = dev.format.bytes_per_line
    dev.plant(ref_pack(image, layout, stride), sequence=0)
    dev.plant(ref_pack(image[::-1], layout, stride), sequence=1)
    frame = cam.capture(timeout_s=2)
    assert frame.data.dtype == np.uint16 and frame.data.shape == (height, width)
    assert np.array_equal(frame.data, image)
    assert (frame.bits, frame.cfa, frame.pixel_format) == (bits, cfa, name)
    assert cam.bit_depth == bits
    cam.close()


def test_codec_roundtrip_odd_sizes_and_short_buffer():
    rng = np.random.default_rng(1)
    for fmt in FORMATS:
        image = rng.integers(0, 1 << fmt.bits, (3, 7)).astype(np.uint16)
        stride = fmt.min_bytes_per_line(7) + 5
        assert np.array_equal(fmt.unpack(fmt.pack(image, stride), 7, 3, stride), image), fmt.name
    y10 = lookup_format("Y10")
    with pytest.raises(ValueError, match="needs 12 bytes"):
        y10.unpack(b"\x00" * 11, 3, 2)
    with pytest.raises(ValueError, match="10-bit"):
        y10.pack(np.array([[1024]]))


# --------------------------------------------------------------------------- controls


def test_exposure_and_gain_switch_auto_off_and_read_back(world):
    dev = world["dev"]
    cam = make_camera(world, settle_frames=0)
    assert dev.values[CID_EXPOSURE_AUTO] == 3 and dev.values[CID_AUTOGAIN] == 1
    assert cam.set_exposure_us(5130) == 5100.0  # 100 µs units: 51.3 -> 51
    assert dev.values[CID_EXPOSURE_AUTO] == 1 and dev.values[CID_EXPOSURE_ABSOLUTE] == 51
    assert cam.set_gain(42) == 42.0
    assert dev.values[CID_AUTOGAIN] == 0 and dev.values[CID_GAIN] == 42
    s = cam.settings()
    assert (s["exposure_us"], s["exposure_auto"], s["gain"], s["gain_auto"]) == (5100.0, False, 42.0, False)
    dev.plant(y16(np.zeros((6, 8))), sequence=0)
    frame = cam.capture(timeout_s=2)
    assert (frame.exposure_us, frame.gain) == (5100.0, 42.0)
    dev.values[CID_GAIN] = 7  # changed behind our back: frames report what the device says now
    dev.plant(y16(np.zeros((6, 8))), sequence=1)
    assert cam.capture(timeout_s=2).gain == 7.0


def test_url_controls_applied_at_open(world):
    cam = make_camera(world, "exposure_us=5000&gain=3&format=Y10")
    assert world["dev"].values[CID_EXPOSURE_ABSOLUTE] == 50 and world["dev"].values[CID_GAIN] == 3
    assert cam.settings()["pixel_format"] == "Y10" and cam.bit_depth == 10


def test_control_values_rejected_or_unavailable(world, tmp_path):
    cam = make_camera(world)
    with pytest.raises(InputError, match=r"exposure 2e\+06 µs is outside .*100\.\.1e\+06 µs"):
        cam.set_exposure_us(2e6)
    with pytest.raises(InputError, match="exposure_us must be a positive"):
        cam.set_exposure_us(-5)
    with pytest.raises(InputError, match="gain 101 is outside"):
        cam.set_gain(101)
    lines_only = {CID_EXPOSURE: ControlInfo(CID_EXPOSURE, "Exposure", 4, 3000, 1, 100)}
    dev = FakeV4L2Device(tmp_path / "video9", controls=lines_only)
    bare = open_camera(f"v4l2://{dev.node}", adapter_factory=FakeV4L2Bus(dev), by_id_dir=tmp_path)
    with pytest.raises(InputError, match="exposure_unit_us"):
        bare.set_exposure_us(1000)
    with pytest.raises(InputError, match="has no gain control"):
        bare.set_gain(1)
    assert np.isnan(bare.settings()["exposure_us"])
    scaled = open_camera(f"v4l2://{dev.node}?exposure_unit_us=14.8", adapter_factory=FakeV4L2Bus(dev),
                         by_id_dir=tmp_path)
    assert scaled.set_exposure_us(1480) == pytest.approx(1480)


def test_format_roi_and_size_requests(world, tmp_path):
    dev = world["dev"]
    cam = make_camera(world)
    assert cam.settings()["pixel_format"] == "Y16"
    assert cam.set_format("GREY") == "GREY" and cam.bit_depth == 8
    with pytest.raises(InputError, match="does not offer pixel format RG10; it offers GREY, Y10, Y16"):
        cam.set_format("RG10")
    assert cam.settings()["pixel_format"] == "GREY"
    with pytest.raises(InputError, match="unknown or unsupported raw pixel format 'MJPG'"):
        cam.set_format("MJPG")
    assert cam.set_roi(3, 1, 5, 4) == (2, 1, 4, 4)  # driver aligns x and width to 2: read back
    assert (cam.settings()["width"], cam.settings()["height"], cam.settings()["roi"]) == (4, 4, (2, 1, 4, 4))
    dev.plant(bytes(range(16)), sequence=0)
    assert cam.capture(timeout_s=2).data.shape == (4, 4)
    with pytest.raises(InputError, match="ROI for camera .* must be four integers"):
        cam.set_roi(0, 0, 0, 4)
    nocrop = FakeV4L2Device(tmp_path / "video7", crop_supported=False)
    cam2 = open_camera(f"v4l2://{nocrop.node}", adapter_factory=FakeV4L2Bus(nocrop), by_id_dir=tmp_path)
    with pytest.raises(InputError, match="does not support a region of interest"):
        cam2.set_roi(0, 0, 4, 4)
    assert cam2.settings()["roi"] is None
    with pytest.raises(DeviceError, match="is busy while setting the pixel format; another program"):
        make_camera(world)  # `cam` is still streaming on the same device
    cam.close()
    with pytest.raises(InputError, match=r"cannot deliver 4096x4096 in GREY; the nearest it offers is 8x6"):
        make_camera(world, "width=4096&height=4096")


def test_best_raw_format_picked_and_non_raw_camera_refused(tmp_path):
    mjpg = int.from_bytes(b"MJPG", "little")
    dev = FakeV4L2Device(tmp_path / "video0", formats=("GREY", "pRAA", "Y12"), extra_codes=[mjpg])
    dev.format = dev._make_format(8, 6, mjpg)  # the camera powers up in MJPG
    cam = open_camera(f"v4l2://{dev.node}", adapter_factory=FakeV4L2Bus(dev), by_id_dir=tmp_path)
    assert cam.settings()["pixel_format"] == "Y12"
    webcam = FakeV4L2Device(tmp_path / "video1", formats=(), extra_codes=[mjpg])
    with pytest.raises(InputError, match="offers no raw monochrome or Bayer format \\(it offers MJPG\\)"):
        open_camera(f"v4l2://{webcam.node}", adapter_factory=FakeV4L2Bus(webcam), by_id_dir=tmp_path)


# --------------------------------------------------------------------------- waits and faults


def test_timeout_raises_within_deadline(world):
    cam = make_camera(world)
    start = time.monotonic()
    with pytest.raises(DeviceError, match=r"camera 'Fake Camera' at .*video0 timed out after 0.2 s waiting "
                                          r"for a frame while capturing a frame"):
        cam.capture(timeout_s=0.2)
    assert 0.19 <= time.monotonic() - start < 1.0
    assert cam.timeouts == 1
    world["dev"].plant(y16(np.ones((6, 8))), sequence=5)  # the camera recovers: no reopen needed
    assert cam.capture(timeout_s=2).sequence == 5


def test_late_frame_wakes_the_select(world):
    cam = make_camera(world, settle_frames=0)
    world["dev"].plant(y16(np.zeros((6, 8))), sequence=0)
    cam.capture(timeout_s=2)  # streaming now
    late = PlantedFrame(y16(np.full((6, 8), 9)), sequence=1)
    timer = threading.Timer(0.05, world["dev"].plant_ready, args=(late,))
    start = time.monotonic()
    timer.start()
    frame = cam.stream(timeout_s=3).__next__()
    timer.join()
    assert frame.sequence == 1 and frame.data[0, 0] == 9
    assert time.monotonic() - start < 1.0


def test_sequence_gaps_recorded_and_counted(world):
    dev = world["dev"]
    cam = make_camera(world, settle_frames=0)
    for seq in (10, 11, 14, 15, 20):
        dev.plant(y16(np.full((6, 8), seq)), sequence=seq)
    stream = cam.stream(timeout_s=2)
    frames = [next(stream) for _ in range(5)]
    assert [f.sequence for f in frames] == [10, 11, 14, 15, 20]
    assert [f.extra["sequence_gap"] for f in frames] == [0, 0, 2, 0, 4]
    assert frames[-1].extra["dropped_frames_total"] == 6 and cam.dropped_frames == 6
    assert cam.settings()["dropped_frames"] == 6
    assert frames[2].data[0, 0] == 14 and frames[2].host_timestamp_s <= time.time()


def test_error_flagged_and_short_frames_discarded_within_deadline(world):
    dev = world["dev"]
    cam = make_camera(world, settle_frames=0)
    dev.plant(y16(np.full((6, 8), 1)), sequence=0)
    dev.plant_error(sequence=1)
    dev.plant(y16(np.full((6, 8), 2))[:50], sequence=2)  # short: the driver cut the transfer
    dev.plant(y16(np.full((6, 8), 3)), sequence=3, flags=BUF_FLAG_ERROR)
    dev.plant(y16(np.full((6, 8), 4)), sequence=4)
    assert cam.capture(timeout_s=2).sequence == 0
    frame = cam.capture(timeout_s=2)
    assert frame.sequence == 4 and frame.data[0, 0] == 4
    assert frame.extra["error_frames_discarded"] == 3 and frame.extra["sequence_gap"] == 0
    assert cam.error_frames == 3


def test_only_error_frames_until_deadline(world):
    dev = world["dev"]
    cam = make_camera(world)
    for seq in range(3):
        dev.plant_error(sequence=seq)
    start = time.monotonic()
    with pytest.raises(DeviceError, match=r"timed out after 0.3 s .*\(3 error-flagged or short frames discarded\)"):
        cam.capture(timeout_s=0.3)
    assert time.monotonic() - start < 1.0


def test_stale_frames_flushed_and_idle_drops_not_reported(world):
    dev = world["dev"]
    cam = make_camera(world, settle_frames=0)
    dev.plant(y16(np.zeros((6, 8))), sequence=0)
    cam.capture(timeout_s=2)
    for seq in range(1, 5):  # all four buffers filled while nobody read: the driver then drops frames
        dev.plant_ready(PlantedFrame(y16(np.full((6, 8), seq)), seq))
    dev.plant(y16(np.full((6, 8), 30)), sequence=30)
    frame = cam.capture(timeout_s=2)
    assert frame.sequence == 30 and frame.extra["sequence_gap"] == 0 and cam.dropped_frames == 0
    dev.plant_ready(PlantedFrame(y16(np.zeros((6, 8))), 31))  # one stale frame: buffers were available
    dev.plant(y16(np.zeros((6, 8))), sequence=33)
    frame = cam.capture(timeout_s=2)
    assert frame.sequence == 33 and frame.extra["sequence_gap"] == 1 and cam.dropped_frames == 1


def test_settle_frame_dropped_after_a_setting_changes_while_streaming(world):
    dev = world["dev"]
    cam = make_camera(world, "exposure_us=1000")  # settle_frames defaults to 1
    for seq in range(3):
        dev.plant(y16(np.full((6, 8), seq)), sequence=seq)
    frame = cam.capture(timeout_s=2)  # set before streaming started: nothing to settle
    assert frame.sequence == 0 and frame.extra["settle_frames_discarded"] == 0
    cam.set_exposure_us(2000)  # the frame in flight mixes old and new exposure
    frame = cam.capture(timeout_s=2)
    assert frame.sequence == 2 and frame.extra["settle_frames_discarded"] == 1
    dev.plant(y16(np.full((6, 8), 3)), sequence=3)
    assert cam.capture(timeout_s=2).extra["settle_frames_discarded"] == 0


def test_disconnect_mid_stream_then_reopen_by_id(world):
    dev, tmp = world["dev"], world["tmp"]
    cam = make_camera(world, "exposure_us=3000&gain=4", settle_frames=0)
    assert cam.settings()["by_id_path"] == str(world["link"])
    for seq in range(2):
        dev.plant(y16(np.full((6, 8), seq)), sequence=seq)
    dev.plant_disconnect()
    stream = cam.stream(timeout_s=2)
    assert [next(stream).sequence for _ in range(2)] == [0, 1]
    start = time.monotonic()
    with pytest.raises(DeviceError, match=r"camera 'Fake Camera' at .*video0 was disconnected while "
                                          r"streaming frames \(ENODEV\); reconnect it and call reopen\(\)"):
        next(stream)
    assert time.monotonic() - start < 1.0
    assert not cam.is_open
    with pytest.raises(DeviceError, match="is disconnected; reconnect it and call reopen"):
        cam.capture(timeout_s=1)
    # re-plugged: the kernel gives it a new node, udev re-points the by-id link; power-on control values
    dev.replug(tmp / "video2")
    world["link"].unlink()
    world["link"].symlink_to(tmp / "video2")
    cam.reopen(timeout_s=2)
    assert dev.values[CID_EXPOSURE_ABSOLUTE] == 30 and dev.values[CID_GAIN] == 4  # settings re-applied
    dev.plant(y16(np.full((6, 8), 7)), sequence=0)
    frame = cam.capture(timeout_s=2)
    assert frame.data[0, 0] == 7 and frame.exposure_us == 3000.0
    assert cam.settings()["device_node"].endswith("video2")


def test_node_vanishing_without_error_is_a_disconnect(world):
    cam = make_camera(world)
    world["dev"].plant(y16(np.zeros((6, 8))), sequence=0)
    cam.capture(timeout_s=2)
    (world["tmp"] / "video0").unlink()
    with pytest.raises(DeviceError, match="was disconnected while capturing a frame \\(its device node vanished\\)"):
        cam.capture(timeout_s=0.2)


def test_reopen_gives_up_at_its_deadline(world):
    cam = make_camera(world)
    world["dev"].unplug()
    start = time.monotonic()
    with pytest.raises(DeviceError, match=r"did not reappear at .*usb-Acme_MLA_Cam_1234-video-index0 within 0.3 s"):
        cam.reopen(timeout_s=0.3)
    assert 0.29 <= time.monotonic() - start < 1.5


def test_open_errors_name_the_camera(world, tmp_path):
    with pytest.raises(DeviceError, match=r"camera .*video5 was not found while opening the device"):
        open_camera(f"v4l2://{tmp_path / 'video5'}", adapter_factory=world["bus"], by_id_dir=world["by_id"])
    cam = make_camera(world)
    cam.close()
    cam.close()
    with pytest.raises(DeviceError, match="is not open; open it before capturing a frame"):
        cam.capture(timeout_s=1)
    with pytest.raises(InputError, match="timeout_s must be a positive"):
        make_camera(world).capture(timeout_s=0)


def test_context_manager_and_settings(world):
    cam = V4L2Camera.from_url(f"v4l2://{world['tmp'] / 'video0'}?buffers=3",
                              adapter_factory=world["bus"], by_id_dir=world["by_id"])
    with cam as c:
        assert c.is_open
        s = c.settings()
        for key in ("url", "name", "card", "driver", "bus_info", "pixel_format", "bits", "width", "height",
                    "exposure_us", "gain", "buffers", "dropped_frames", "error_frames"):
            assert key in s
        assert (s["card"], s["buffers"], s["width"], s["height"]) == ("Fake Camera", 3, 8, 6)
    assert not cam.is_open
    assert world["dev"].streaming is False


def test_real_linuxpy_adapter_refuses_a_non_v4l2_node():
    pytest.importorskip("linuxpy.video.device")
    with pytest.raises(DeviceError, match="/dev/null is not a V4L2 video device"):
        open_camera("v4l2:///dev/null")


# --------------------------------------------------------------------------- iris (main lens f-number)


def iris_camera(tmp_path, query: str = "", controls=None, **device):
    """An opened camera on a fake with an iris control (default: a UVC lens, f/2..f/16 as f-number x 100)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    dev = FakeV4L2Device(tmp_path / "video3", controls=default_controls() | (controls or uvc_iris_control()), **device)
    url = f"v4l2://{dev.node}?settle_frames=0" + (f"&{query}" if query else "")
    return dev, open_camera(url, adapter_factory=FakeV4L2Bus(dev), by_id_dir=tmp_path)


def test_iris_control_ids_match_the_kernel_header_via_linuxpy():
    device = pytest.importorskip("linuxpy.video.device")
    assert (device.ControlID.IRIS_ABSOLUTE, device.ControlID.IRIS_RELATIVE) == (CID_IRIS_ABSOLUTE, CID_IRIS_RELATIVE)


def test_uvc_iris_is_f_number_times_100_read_back_and_checked(tmp_path):
    dev, cam = iris_camera(tmp_path)
    dev.values[CID_EXPOSURE_AUTO] = 0  # Auto: UVC refuses iris writes, so the driver switches to manual
    assert cam.set_f_number(8) == 8.0
    assert dev.values[CID_IRIS_ABSOLUTE] == 800 and dev.values[CID_EXPOSURE_AUTO] == 1
    assert cam.set_f_number(11.04) == pytest.approx(11.0)  # snapped to the 0.1 step: 1100
    assert cam.f_number == pytest.approx(11.0)
    s = cam.settings()
    assert s["f_number"] == pytest.approx(11.0) and s["iris"]["control"] == "absolute"
    assert s["iris"]["f_number_range"] == [2.0, 16.0] and "UVC" in s["iris"]["mapping"]
    dev.plant(y16(np.zeros((6, 8))), sequence=0)
    assert cam.capture(timeout_s=2).extra["f_number"] == pytest.approx(11.0)
    with pytest.raises(InputError, match=r"f/22 is outside camera 'Fake Camera' at .*video3's iris range "
                                         r"f/2\.\.f/16 \(control 'Iris, Absolute' 200\.\.1600, f-number x 100"):
        cam.set_f_number(22)
    with pytest.raises(InputError, match="f/1.4 is outside"):
        cam.set_f_number(1.4)
    with pytest.raises(InputError, match="f_number must be a positive"):
        cam.set_f_number(-8)
    assert dev.values[CID_IRIS_ABSOLUTE] == 1100  # nothing written by the refusals
    _, cam2 = iris_camera(tmp_path / "coarse", controls=uvc_iris_control(step=100), card="Coarse")
    with pytest.raises(InputError, match=r"iris cannot be set to f/8\.5: its nearest settings are f/8 and f/9"):
        cam2.set_f_number(8.5)


def test_iris_mapping_is_configurable_by_unit_or_table(tmp_path):
    dev, cam = iris_camera(tmp_path / "a", "iris_unit=0.1", controls=uvc_iris_control(20, 160, 1, 20))
    assert cam.set_f_number(8) == pytest.approx(8.0) and dev.values[CID_IRIS_ABSOLUTE] == 80
    # a driver that follows the V4L2 wording (larger values open wider): a table, read in stops between points
    dev, cam = iris_camera(tmp_path / "b", "iris_table=0:16,100:2", controls=uvc_iris_control(0, 100, 1, 100))
    assert cam.set_f_number(4) == pytest.approx(4.0, rel=0.01) and dev.values[CID_IRIS_ABSOLUTE] == 67
    assert cam.set_f_number(16) == 16.0 and dev.values[CID_IRIS_ABSOLUTE] == 0
    assert IrisMap(table=((0, 16.0), (100, 2.0))).value(5.656854) == pytest.approx(50.0)  # half-way in stops
    for query, message in [("iris_unit=0.1&iris_table=0:16,100:2", "both iris_unit and iris_table"),
                           ("iris_table=0:16", "iris_table='0:16'"),
                           ("iris_table=0:2,50:4,100:2", "all rise or all fall"),
                           ("iris_unit=-1", "iris_unit"), ("iris=uvc", "unknown parameter 'iris'")]:
        with pytest.raises(InputError, match=message):
            V4L2Camera.from_url(f"v4l2://{dev.node}?{query}")


def test_camera_without_iris_says_so_in_one_sentence(world):
    cam = make_camera(world)
    with pytest.raises(InputError, match=r"has no iris control \(V4L2_CID_IRIS_ABSOLUTE or _RELATIVE\), so it cannot "
                                         r"set f/8; set the lens by hand \(through_focus.iris = 'manual'\)"):
        cam.set_f_number(8)
    assert cam.settings()["iris"] is None and np.isnan(cam.f_number) and np.isnan(cam.settings()["f_number"])


def test_motorized_iris_is_polled_and_a_jammed_one_times_out(tmp_path):
    dev, cam = iris_camera(tmp_path / "slow", iris_lag_reads=3)
    assert cam.set_f_number(5.6) == pytest.approx(5.6) and dev.values[CID_IRIS_ABSOLUTE] == 560
    dev, cam = iris_camera(tmp_path / "jammed", "iris_timeout_s=0.1", iris_lag_reads=None)
    start = time.monotonic()
    with pytest.raises(DeviceError, match=r"iris did not reach f/8 within 0\.1 s \(it reads f/2\)"):
        cam.set_f_number(8)
    assert time.monotonic() - start < 1.0


def test_f_number_from_the_url_is_applied_at_open_and_after_a_replug(tmp_path):
    dev, cam = iris_camera(tmp_path, "f_number=8")
    assert dev.values[CID_IRIS_ABSOLUTE] == 800
    dev.unplug()
    dev.replug(dev.node)  # power-on values: the iris is wide open again
    assert dev.values[CID_IRIS_ABSOLUTE] == 200
    cam.reopen(timeout_s=2)
    assert dev.values[CID_IRIS_ABSOLUTE] == 800 and cam.f_number == 8.0


def test_relative_only_iris_is_driven_by_counted_steps(tmp_path):
    stops = "iris_table=0:2,1:2.8,2:4,3:5.6,4:8,5:11,6:16"
    dev, cam = iris_camera(tmp_path / "a", controls=relative_iris_control())
    with pytest.raises(InputError, match="has only a relative iris control.*iris_table=0:2.8,1:4"):
        cam.set_f_number(8)
    dev, cam = iris_camera(tmp_path / "b", stops, controls=relative_iris_control(), iris_travel=8, iris_default_step=7)
    assert np.isnan(cam.f_number)  # a write-only control: unknown until the driver has moved it
    assert cam.set_f_number(8) == 8.0 and dev.iris_step == 4  # opened to the stop, then closed 4 steps
    writes = [c[2] for c in dev.calls if c[:2] == ("s_ctrl", CID_IRIS_RELATIVE)]
    assert writes == [1] * 8 + [-1] * 4
    assert cam.set_f_number(4) == 4.0 and dev.iris_step == 2 and cam.f_number == 4.0
    assert cam.settings()["iris"]["read_back"] == "counted steps"
    with pytest.raises(InputError, match="cannot be set to f/9: it is between its steps f/8 and f/11"):
        cam.set_f_number(9)
    with pytest.raises(InputError, match="cannot be set to f/22: it is outside its iris table f/2..f/16"):
        cam.set_f_number(22)
    cam.close()
    dev.iris_step = 6  # moved by hand while closed: the driver finds the stop again
    cam.open()
    assert dev.iris_step == 2 and cam.f_number == 4.0
    dev, cam = iris_camera(tmp_path / "c", stops, controls=relative_iris_control(0, 0))  # as uvcvideo reports it
    with pytest.raises(InputError, match=r"accepts only 0\.\.0, not the \+1/-1 steps that move it"):
        cam.set_f_number(8)
