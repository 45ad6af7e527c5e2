"""Mock camera: wafer geometry and truth, frames that follow the stage, render cache, Camera API, faults."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from drivers.camera import camera_from_url, open_camera
from drivers.camera.mock import MockCamera, parse_faults, publish_stage, unpublish_stage
from drivers.stage import open_stage
from drivers.wafer import Wafer, array_seed, default_pitch_mm
from mlaqc.errors import DeviceError, InputError
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import random_defects

FAST = "mock://?rpp=0.5&seed=3"


def grid_shift_px(before: np.ndarray, after: np.ndarray, period: float, axis: int) -> float:
    """Shift of the sub-image grid along image x (axis=1) or y (axis=0), from the phase of its fundamental.

    Valid for |shift| < period / 2; the vignetting envelope does not move and barely bends the phase."""
    profiles = []
    for img in (before, after):
        prof = img.astype(np.float64).sum(axis=1 - axis)
        k = np.arange(prof.size)
        window = np.hanning(prof.size)
        profiles.append(np.sum(prof * window * np.exp(-2j * np.pi * k / period)))
    return float(-np.angle(profiles[1] / profiles[0]) * period / (2 * np.pi))


def left_edge_px(img: np.ndarray) -> float:
    """First column where the column profile rises above half its median plateau."""
    prof = img.astype(np.float64).sum(axis=0)
    return float(np.argmax(prof > 0.5 * np.median(prof)))


@pytest.fixture(scope="module")
def stage():
    st = open_stage("mock://")
    st.home()
    yield st
    st.close()


# --------------------------------------------------------------------------------------------- wafer


def test_wafer_geometry_seeds_and_truth():
    cfg = load_config("fixtures/small_camera.toml")
    assert default_pitch_mm(cfg) == 5.0  # 2.4 mm array + 2.48 mm field, rounded up
    wafer = Wafer(cfg, cols=3, rows=2, origin_mm=(10.0, 20.0), defects=4, seed=9)
    assert wafer.centre_mm(2, 3) == (20.0, 25.0)
    arr, offset = wafer.locate(15.03, 19.98)
    assert arr.name == "W(1,2)" and offset == pytest.approx((-30.0, 20.0))
    assert wafer.nearest(-100, 500).name == "W(2,1)"  # clamped to the wafer
    truth = wafer.truth()
    assert truth["format"] == "mlaqc-mock-wafer" and len(truth["arrays"]) == 6
    a = truth["arrays"][5]
    assert (a["m"], a["n"], a["name"], a["centre_mm"]) == (2, 3, "W(2,3)", [20.0, 25.0])
    expected = random_defects(24, 24, 4, array_seed(9, 2, 3))
    assert a["error_map"] == expected.to_json_dict() and len(a["error_map"]["lenses"]) == 4
    assert truth["arrays"][0]["error_map"] != a["error_map"]  # each array its own defects
    assert Wafer(cfg, cols=3, rows=2, origin_mm=(10.0, 20.0), defects=4, seed=9).truth_digest() == wafer.truth_digest()
    with pytest.raises(InputError, match="pitch_mm"):
        Wafer(cfg, cols=2, pitch_mm=1.0)


# --------------------------------------------------------------------------------------------- URL and API


def test_url_defaults_and_registry():
    cam = open_camera("mock://")
    assert isinstance(cam, MockCamera) and cam.is_open
    s = cam.settings()
    assert (s["pixel_format"], s["bits"], s["width"], s["height"], s["cfa"]) == ("Y16", 12, 496, 496, None)
    assert s["exposure_us"] == 5000.0 and s["gain"] == 1.0 and s["wafer"]["cols"] == 1
    assert cam.position_mm() == ((10.0, 10.0), "fixed")  # W(1,1) centred by default
    cam.close()
    assert not cam.is_open
    cam.close()  # twice is fine


@pytest.mark.parametrize("url, needle", [
    ("mock://?bogus=1", "bogus"),
    ("mock://?wafer=3", "wafer"),
    ("mock://?wafer=0x2", "wafer"),
    ("mock://?rpp=-1", "rpp"),
    ("mock://?pos_mm=1", "pos_mm"),
    ("mock://?defects=many", "defects"),
    ("mock://?config=/no/such/camera.toml", "does not exist"),
    ("mock://?wafer=2x2&pitch_mm=1", "pitch_mm"),
    ("mock://?faults=melt@3", "melt@3"),
    ("mock://?faults=timeout@0", "timeout@0"),
    ("mock://?exposure_us=1e12", "exposure"),
    ("mock://?defect_types=warp", "warp"),
    ("mock:///dev/video0", "device path"),
])
def test_bad_url_parameters_name_the_parameter(url, needle):
    with pytest.raises(InputError, match=needle):
        camera_from_url(url)


def test_frames_sequence_timestamps_format_and_settings_read_back():
    cam = open_camera(FAST)
    frames = [cam.capture(1.0) for _ in range(3)]
    assert [f.sequence for f in frames] == [1, 2, 3]
    assert all(f.data.dtype == np.uint16 and f.data.shape == (496, 496) for f in frames)
    assert all((f.bits, f.pixel_format, f.cfa, f.device) == (12, "Y16", None, FAST) for f in frames)
    assert frames[0].device_timestamp_s < frames[1].device_timestamp_s < frames[2].device_timestamp_s
    assert abs(frames[0].host_timestamp_s - time.time()) < 60
    assert not np.array_equal(frames[0].data, frames[1].data)  # fresh noise per frame
    assert frames[0].extra["black_level"] == 64 and frames[0].extra["sequence_gap"] == 0
    assert cam.set_exposure_us(1234.4) == 1234.0 and cam.set_gain(1.234) == 1.23
    assert cam.capture().exposure_us == 1234.0 and cam.capture().gain == 1.23
    assert cam.set_format("Y16") == "Y16"
    with pytest.raises(InputError, match="Y16"):
        cam.set_format("Y12")
    with pytest.raises(InputError, match="range"):
        cam.set_gain(100)
    with pytest.raises(InputError):
        cam.set_exposure_us(float("nan"))
    stream = cam.stream(1.0)
    seqs = [next(stream).sequence for _ in range(2)]
    assert seqs[1] == seqs[0] + 1
    cam.close()
    with pytest.raises(DeviceError, match="not open"):
        cam.capture()


def test_exposure_and_gain_scale_the_signal():
    cam = open_camera("mock://?rpp=4&seed=3&exposure_us=2000")  # no pixel near full well

    def signal():
        return float(cam.capture().data.astype(np.float64).mean()) - 64.0

    base = signal()
    cam.set_exposure_us(1000)
    assert signal() / base == pytest.approx(0.5, rel=0.02)
    cam.set_exposure_us(2000)
    cam.set_gain(0.5)
    assert signal() / base == pytest.approx(0.5, rel=0.02)
    assert cam.capture().extra["white_level"] < cam.settings()["black_level"] + 2100  # white level follows gain


# --------------------------------------------------------------------------------------------- stage coupling


def test_frames_move_with_the_stage_by_the_subimage_pitch(stage):
    cam = open_camera("mock://?rpp=4&seed=5")
    cam.attach_stage(stage)
    period = cam.cfg.layout.subimage_pitch_px  # 20.048 px per 100 µm lens pitch
    px_per_um = period / cam.cfg.mla.pitch_um
    stage.move_to(10.0, 10.0)
    f0 = cam.capture()
    assert f0.extra["truth"]["offset_um"] == [0.0, 0.0] and f0.extra["truth"]["position_source"] == "stage"
    stage.move_to(10.025, 10.0)  # stage +25 µm in x: the array appears 25 µm to the left
    fx = cam.capture()
    assert fx.extra["truth"]["offset_um"] == pytest.approx([-25.0, 0.0])
    assert grid_shift_px(f0.data, fx.data, period, axis=1) == pytest.approx(-25 * px_per_um, abs=0.1)
    assert abs(grid_shift_px(f0.data, fx.data, period, axis=0)) < 0.3
    stage.move_to(10.0, 9.96)  # stage -40 µm in y: the array moves 40 µm down (y down, as in the image)
    fy = cam.capture()
    assert grid_shift_px(f0.data, fy.data, period, axis=0) == pytest.approx(40 * px_per_um, abs=0.1)
    assert abs(grid_shift_px(f0.data, fy.data, period, axis=1)) < 0.3
    stage.move_to(9.9, 10.0)  # one whole lens pitch: the array's edge moves by one sub-image pitch
    fp = cam.capture()
    assert left_edge_px(fp.data) - left_edge_px(f0.data) == pytest.approx(period, abs=1.5)
    cam.close()


def test_wafer_array_under_the_stage_and_out_of_view(stage):
    cam = open_camera("mock://?wafer=3x2&rpp=0.5&seed=1")
    cam.attach_stage(lambda: stage.last_position)
    stage.move_to(20.0, 15.0)
    f = cam.capture()
    t = f.extra["truth"]
    assert (t["array"], t["m"], t["n"], t["offset_um"], t["in_view"]) == ("W(2,3)", 2, 3, [0.0, 0.0], True)
    assert t["error_map"] == cam.wafer.array(2, 3).errors.to_json_dict()
    assert cam.truth()["arrays"][5]["name"] == "W(2,3)"
    renders = cam.stats["renders"]
    stage.move_to(17.5, 12.5)  # half-way between four arrays: nothing in the field of view
    dark = cam.capture()
    assert dark.extra["truth"]["in_view"] is False and cam.stats["renders"] == renders  # no render needed
    assert dark.data.mean() < 70  # black level 64 plus read noise
    cam.attach_stage(None)
    assert cam.capture().extra["truth"]["array"] == "W(1,1)"  # back to the fixed position


def test_published_stage_by_name():
    pos = [(15.0, 10.0)]
    cam = open_camera("mock://?wafer=2x1&rpp=0.5&stage=bench-test")
    with pytest.raises(DeviceError, match="bench-test"):
        cam.capture()
    publish_stage("bench-test", lambda: pos[0])
    try:
        assert cam.capture().extra["truth"]["array"] == "W(1,2)"
        assert cam.settings()["position_source"] == "published:bench-test"
    finally:
        unpublish_stage("bench-test")


def test_render_cache_hits_are_quantized():
    """A repeated position is served from the cache (no render), a move below 1 µm too (tests never
    time it: the render counter says it)."""
    pos = [(10.0, 10.0)]
    cam = MockCamera(rays_per_pixel=4, stage=lambda: pos[0])
    cam.open()
    first = cam.capture()
    second = cam.capture()
    assert first.extra["mock"]["cache_hit"] is False and second.extra["mock"]["cache_hit"] is True
    assert cam.cache_info()["renders"] == 1
    pos[0] = (10.0004, 10.0)  # 0.4 µm: below the 1 µm quantum, same render
    assert cam.capture().extra["mock"]["cache_hit"] is True
    pos[0] = (10.002, 10.0)
    assert cam.capture().extra["mock"]["cache_hit"] is False
    info = cam.cache_info()
    assert (info["entries"], info["renders"], info["hits"]) == (2, 2, 2)
    assert np.array_equal(cam.expected_photons((10.0, 10.0)), cam.expected_photons((10.0, 10.0)))


def test_cache_is_bounded():
    pos = [(10.0, 10.0)]
    cam = MockCamera(rays_per_pixel=0.2, stage=lambda: pos[0], cache_mb=2.5)  # 496x496 float32 = 0.98 MB each
    cam.open()
    for dx in range(5):
        pos[0] = (10.0 + dx * 0.01, 10.0)
        cam.capture()
    assert cam.cache_info()["entries"] == 2 and cam.cache_info()["bytes"] <= 2.5e6


# --------------------------------------------------------------------------------------------- faults


def test_fault_timeout_waits_the_deadline_then_recovers():
    cam = open_camera(FAST)
    cam.inject_fault("timeout")
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match="timed out after 0.3 s"):
        cam.capture(0.3)
    assert 0.28 < time.monotonic() - t0 < 2.0
    assert cam.capture(0.3).sequence == 1  # no frame was produced by the timed-out attempt
    assert cam.stats["timeouts"] == 1


def test_fault_timeout_is_cut_short_by_close():
    cam = open_camera(FAST)
    cam.inject_fault("timeout")
    threading.Timer(0.1, cam.close).start()
    t0 = time.monotonic()
    with pytest.raises(DeviceError):
        cam.capture(5.0)
    assert time.monotonic() - t0 < 2.0


def test_fault_disconnect_until_reopen():
    cam = open_camera(FAST)
    cam.capture()
    cam.inject_fault("disconnect", count=3)  # unplugged: the next two opens fail too
    with pytest.raises(DeviceError, match="disconnected"):
        cam.capture()
    assert not cam.is_open
    with pytest.raises(DeviceError, match="reopen"):
        cam.capture()
    with pytest.raises(DeviceError, match="reopen"):
        cam.set_exposure_us(1000)
    for _ in range(2):
        with pytest.raises(DeviceError, match="not found"):
            cam.reopen()
    cam.reopen()
    assert cam.is_open and cam.capture().sequence == 2


def test_fault_drop_black_saturated_and_url_schedule():
    cam = open_camera(FAST + "&faults=black@2,drop@3x4,saturated@4x2")
    f1, f2, f3, f4, f5, f6 = (cam.capture() for _ in range(6))
    assert f1.data.mean() > 300 and f1.extra["mock"]["fault"] is None
    assert f2.extra["mock"]["fault"] == "black" and abs(f2.data.mean() - 64) < 1 and f2.data.max() < 80
    assert (f3.sequence, f3.extra["sequence_gap"]) == (7, 4)  # four frames lost before it
    wl = f4.extra["white_level"]
    assert np.all(f4.data == wl) and np.all(f5.data == wl) and f6.data.mean() < wl * 0.9
    assert cam.stats["dropped_frames"] == 4 and cam.stats["saturated_frames"] == 2
    cam.inject_fault("black", at=8)
    cam.capture()
    assert cam.capture().extra["mock"]["fault"] == "black"
    cam.inject_fault("timeout")
    cam.clear_faults()
    assert cam.capture(0.2).extra["mock"]["fault"] is None
    with pytest.raises(InputError):
        cam.inject_fault("explode")
    assert parse_faults("u", "timeout@5, black@9x2") == [("timeout", 5, 1), ("black", 9, 2)]


def test_light_off_gives_dark_frames():
    cam = open_camera(FAST + "&light=0")
    assert not cam.light and cam.capture().data.mean() < 66
    cam.set_light(True)
    assert cam.capture().data.mean() > 300
