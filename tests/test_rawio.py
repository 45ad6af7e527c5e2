"""Tests for mlaqc.inspection.rawio: bit-exact round trips, every bad input as InputError, exposure and hot-pixel checks."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import rawpy
import tifffile

from mlaqc.errors import InputError
from mlaqc.inspection.raw_levels import check_exposure, normalized, suppress_hot_pixels
from mlaqc.inspection.raw_write import write_raw
from mlaqc.inspection.rawio import CFA_PATTERNS, RawFrame, load_raw

H, W = 64, 96


def _random(bits: int = 16, seed: int = 0, dtype=np.uint16) -> np.ndarray:
    """Seeded random counts using the full `bits` range."""
    return np.random.default_rng(seed).integers(0, 1 << bits, (H, W), dtype=np.int64).astype(dtype)


def _raises(path: Path, **kw) -> str:
    """Assert load_raw raises InputError naming the file; return the message."""
    with pytest.raises(InputError) as info:
        load_raw(path, **kw)
    msg = str(info.value)
    assert str(path) in msg
    assert "\n" not in msg and msg.endswith(".")
    return msg


def _dir_listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


# ------------------------------------------------------------------ DNG through rawpy (LibRaw)


@pytest.mark.parametrize("cfa", CFA_PATTERNS)
def test_cfa_dng_reads_back_bit_exactly_through_rawpy(tmp_path: Path, cfa: str) -> None:
    data = _random(12, seed=1)
    path = tmp_path / f"{cfa}.dng"
    write_raw(path, data, bits=12, cfa=cfa, black_level=64, white_level=4000)
    with rawpy.imread(str(path)) as raw:  # independent of load_raw: LibRaw itself
        assert np.array_equal(raw.raw_image, data)
        assert list(raw.black_level_per_channel) == [64] * 4
        assert raw.white_level == 4000
        desc = raw.color_desc.decode()
        assert "".join(desc[i] for i in raw.raw_pattern.ravel()) == cfa
    frame = load_raw(path)
    assert frame.data.dtype == np.uint16 and np.array_equal(frame.data, data)
    assert (frame.bits, frame.cfa, frame.black_level, frame.white_level) == (12, cfa, 64, 4000)
    assert frame.source == str(path)


def test_mono_dng_reads_back_bit_exactly_through_rawpy(tmp_path: Path) -> None:
    data = _random(16, seed=2)
    path = tmp_path / "mono.dng"
    write_raw(path, data, black_level=100)
    with tifffile.TiffFile(path) as tif:
        assert tif.pages[0].photometric == 34892  # LinearRaw, one sample
    with rawpy.imread(str(path)) as raw:
        assert np.array_equal(raw.raw_image, data)
        assert raw.num_colors == 1
        assert raw.white_level == 65535
    frame = load_raw(path)
    assert np.array_equal(frame.data, data)
    assert (frame.bits, frame.cfa, frame.black_level, frame.white_level) == (16, None, 100, 65535)


def test_8bit_dng_round_trip(tmp_path: Path) -> None:
    data = _random(8, seed=3, dtype=np.uint8)
    write_raw(tmp_path / "a.dng", data, cfa="GRBG")
    frame = load_raw(tmp_path / "a.dng")
    assert frame.data.dtype == np.uint16 and np.array_equal(frame.data, data)
    assert (frame.bits, frame.cfa, frame.white_level) == (8, "GRBG", 255)


def test_dng_metadata_round_trip_and_tags(tmp_path: Path) -> None:
    meta = {"exposure_us": 1250, "operator": "Zoë", "lens": {"pitch_um": 100.0, "ids": [1, 2]}}
    write_raw(tmp_path / "m.dng", _random(), cfa="RGGB", metadata=meta)
    frame = load_raw(tmp_path / "m.dng")
    assert {k: frame.metadata[k] for k in meta} == meta
    assert frame.metadata["tags"]["UniqueCameraModel"] == "mlaqc"
    json.dumps(frame.metadata)  # whatever comes back must be JSON-safe for reports


def test_vendor_suffix_goes_through_libraw(tmp_path: Path) -> None:
    """LibRaw identifies by content: a DNG named .nef exercises the vendor-raw path (no real NEF fixture)."""
    data = _random(14, seed=30)
    write_raw(tmp_path / "a.dng", data, bits=14, cfa="GRBG", black_level=600)
    (tmp_path / "a.nef").write_bytes((tmp_path / "a.dng").read_bytes())
    frame = load_raw(tmp_path / "a.nef")
    assert np.array_equal(frame.data, data) and (frame.bits, frame.cfa, frame.black_level) == (14, "GRBG", 600)


def test_truncated_vendor_raw_is_input_error(tmp_path: Path) -> None:
    write_raw(tmp_path / "a.dng", _random(seed=31), cfa="RGGB")
    blob = (tmp_path / "a.dng").read_bytes()
    (tmp_path / "a.nef").write_bytes(blob[: len(blob) // 2])  # no pre-check for vendor raws: LibRaw decides
    assert "truncated" in _raises(tmp_path / "a.nef")


def test_non_bayer_cfa_is_input_error(tmp_path: Path) -> None:
    tags = [(50706, 1, 4, (1, 4, 0, 0), True), (33421, 3, 2, (2, 2), True), (33422, 1, 4, (0, 1, 2, 1), True)]
    tifffile.imwrite(tmp_path / "odd.dng", _random(), photometric=32803, extratags=tags, metadata=None)
    assert "RGBG" in _raises(tmp_path / "odd.dng")


def test_dng_read_as_tiff_keeps_cfa_and_levels(tmp_path: Path) -> None:
    tags = [(33421, 3, 2, (2, 2), True), (33422, 1, 4, (2, 1, 1, 0), True), (50714, 4, 1, (256,), True),
            (50717, 4, 1, (60000,), True)]
    data = _random(seed=32)
    tifffile.imwrite(tmp_path / "f.tif", data, photometric=32803, extratags=tags, metadata=None)
    frame = load_raw(tmp_path / "f.tif")
    assert np.array_equal(frame.data, data)
    assert (frame.cfa, frame.black_level, frame.white_level) == ("BGGR", 256, 60000)


def test_rawframe_rejects_inconsistent_fields() -> None:
    with pytest.raises(InputError):
        RawFrame(np.zeros((4, 4), np.uint16), 12, "RGGB", 100, 100, {}, "x")
    with pytest.raises(InputError):
        RawFrame(np.zeros((4, 4), np.uint16), 12, "RGBW", 0, 4095, {}, "x")
    with pytest.raises(InputError):
        RawFrame(np.zeros(4, np.uint16), 12, None, 0, 4095, {}, "x")


# ------------------------------------------------------------------ TIFF, PNG, NPY


@pytest.mark.parametrize("suffix", [".tif", ".tiff"])
def test_tiff_16bit_round_trip_with_metadata(tmp_path: Path, suffix: str) -> None:
    data = _random(14, seed=4)
    meta = {"frame": 3}
    write_raw(tmp_path / f"a{suffix}", data, bits=14, cfa="BGGR", black_level=512, metadata=meta)
    frame = load_raw(tmp_path / f"a{suffix}")
    assert frame.data.dtype == np.uint16 and np.array_equal(frame.data, data)
    assert (frame.bits, frame.cfa, frame.black_level, frame.white_level) == (14, "BGGR", 512, 16383)
    assert frame.metadata == {"frame": 3}


def test_tiff_8bit_round_trip(tmp_path: Path) -> None:
    data = _random(8, seed=5, dtype=np.uint8)
    write_raw(tmp_path / "a.tif", data)
    with tifffile.TiffFile(tmp_path / "a.tif") as tif:
        assert tif.pages[0].bitspersample == 8
    frame = load_raw(tmp_path / "a.tif")
    assert np.array_equal(frame.data, data) and (frame.bits, frame.white_level, frame.cfa) == (8, 255, None)


@pytest.mark.parametrize("layout", ["plain", "big-endian", "compressed", "strips", "8-bit"])
def test_mapped_tiff_reads_the_same_pixels_and_outlives_a_replaced_file(tmp_path: Path, layout: str) -> None:
    """load_raw(mapped=True) gives the plain load's pixels and levels for every TIFF layout (mapped where
    the pixels are one native block, read otherwise), and a frame written in place of the file
    (os.replace, as mlaqc writes) leaves the loaded frame as it was."""
    path = tmp_path / "f.tif"
    if layout == "plain":
        data = _random(12, seed=21)
        write_raw(path, data, bits=12, black_level=64)
    else:
        data = _random(8, seed=21, dtype=np.uint8) if layout == "8-bit" else _random(16, seed=21)
        kw = {"big-endian": dict(byteorder=">"), "compressed": dict(compression="zlib"),
              "strips": dict(rowsperstrip=7), "8-bit": {}}[layout]
        tifffile.imwrite(path, data, metadata=None, **kw)
    plain, mapped = load_raw(path), load_raw(path, mapped=True)
    assert np.array_equal(mapped.data, plain.data) and np.array_equal(mapped.data, data)
    assert mapped.data.dtype == plain.data.dtype and mapped.data.dtype.isnative
    assert (mapped.bits, mapped.black_level, mapped.white_level) == (plain.bits, plain.black_level, plain.white_level)
    assert isinstance(mapped.data.base, np.memmap) == (layout in ("plain", "strips"))
    write_raw(tmp_path / "g.tif", np.zeros((H, W), np.uint16), bits=12)
    os.replace(tmp_path / "g.tif", path)
    assert np.array_equal(mapped.data, data)


def test_mapped_tiff_checks_truncation_first(tmp_path: Path) -> None:
    path = tmp_path / "t.tif"
    write_raw(path, _random(seed=10))
    path.write_bytes(path.read_bytes()[:-1000])
    with pytest.raises(InputError, match="truncated"):
        load_raw(path, mapped=True)


def test_foreign_tiff_without_record(tmp_path: Path) -> None:
    data = _random(16, seed=6)
    tifffile.imwrite(tmp_path / "f.tif", data, description="bench camera 7", metadata=None)
    frame = load_raw(tmp_path / "f.tif")
    assert np.array_equal(frame.data, data)
    assert (frame.bits, frame.cfa, frame.black_level, frame.white_level) == (16, None, 0, 65535)
    assert frame.metadata["tags"]["ImageDescription"] == "bench camera 7"


@pytest.mark.parametrize("dtype,bits", [(np.uint16, 16), (np.uint16, 10), (np.uint8, 8)])
def test_png_round_trip_with_sidecar(tmp_path: Path, dtype, bits: int) -> None:
    data = _random(bits, seed=7, dtype=dtype)
    meta = {"note": "white image"}
    write_raw(tmp_path / "a.png", data, bits=bits, cfa="GBRG", black_level=2, metadata=meta)
    assert (tmp_path / "a.png.json").is_file()
    assert np.array_equal(cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED), data)
    frame = load_raw(tmp_path / "a.png")
    assert frame.data.dtype == np.uint16 and np.array_equal(frame.data, data)
    assert (frame.bits, frame.cfa, frame.black_level, frame.white_level) == (bits, "GBRG", 2, (1 << bits) - 1)
    assert frame.metadata == meta


def test_npy_round_trip(tmp_path: Path) -> None:
    data = _random(12, seed=8)
    write_raw(tmp_path / "a.npy", data, bits=12, white_level=4000, metadata={"k": [1, 2]})
    frame = load_raw(tmp_path / "a.npy")
    assert frame.data.dtype == np.uint16 and np.array_equal(frame.data, data)
    assert (frame.bits, frame.cfa, frame.white_level, frame.metadata) == (12, None, 4000, {"k": [1, 2]})


def test_npy_floats_kept_as_float32_and_foreign_sidecar_kept(tmp_path: Path) -> None:
    data = np.random.default_rng(9).random((H, W)) * 1000.0
    np.save(tmp_path / "f.npy", data)
    (tmp_path / "f.npy.json").write_text(json.dumps({"camera": "X"}))
    frame = load_raw(tmp_path / "f.npy")
    assert frame.data.dtype == np.float32 and np.array_equal(frame.data, data.astype(np.float32))
    assert frame.metadata == {"sidecar": {"camera": "X"}}


def test_expected_shape_accepts_match(tmp_path: Path) -> None:
    write_raw(tmp_path / "a.npy", _random())
    assert load_raw(tmp_path / "a.npy", expected_shape=(H, W)).shape == (H, W)


# ------------------------------------------------------------------ bad inputs -> InputError naming the file


def test_missing_file(tmp_path: Path) -> None:
    assert "does not exist" in _raises(tmp_path / "nope.dng")


@pytest.mark.parametrize("suffix", [".dng", ".nef", ".tif", ".png", ".npy"])
def test_empty_file(tmp_path: Path, suffix: str) -> None:
    (tmp_path / f"e{suffix}").write_bytes(b"")
    assert "empty (0 bytes)" in _raises(tmp_path / f"e{suffix}")


def test_directory_and_unknown_suffix(tmp_path: Path) -> None:
    (tmp_path / "d.dng").mkdir()
    assert "directory" in _raises(tmp_path / "d.dng")
    (tmp_path / "x.jpg").write_bytes(b"\xff\xd8\xff")
    assert "unsupported type" in _raises(tmp_path / "x.jpg")


@pytest.mark.parametrize(
    "suffix,cfa", [(".dng", "RGGB"), (".dng", None), (".tif", None), (".png", None), (".npy", None)]
)
def test_truncated_file(tmp_path: Path, suffix: str, cfa: str | None, capfd) -> None:
    path = tmp_path / f"t{suffix}"
    write_raw(path, _random(seed=10), cfa=cfa)
    blob = path.read_bytes()
    path.write_bytes(blob[: len(blob) // 2])
    assert "truncated" in _raises(path)
    assert capfd.readouterr().err == ""  # caught before LibRaw/OpenCV could print to stderr


@pytest.mark.parametrize("suffix", [".dng", ".cr2", ".tif", ".png", ".npy"])
def test_random_garbage_file(tmp_path: Path, suffix: str, capfd) -> None:
    path = tmp_path / f"g{suffix}"
    path.write_bytes(np.random.default_rng(11).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    _raises(path)
    assert capfd.readouterr().err == ""


def test_corrupt_png_body(tmp_path: Path, capfd) -> None:
    write_raw(tmp_path / "c.png", _random(seed=18))
    blob = bytearray((tmp_path / "c.png").read_bytes())
    blob[60:400] = bytes(340)  # zero out compressed pixel data, keep header and end chunk
    (tmp_path / "c.png").write_bytes(bytes(blob))
    assert "corrupt PNG" in _raises(tmp_path / "c.png")
    assert capfd.readouterr().err == ""


def test_garbage_after_valid_tiff_header(tmp_path: Path) -> None:
    path = tmp_path / "h.dng"
    path.write_bytes(b"II*\x00" + np.random.default_rng(12).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    _raises(path)


def test_rgb_png_is_not_2d(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((H, W, 3), np.uint8))
    msg = _raises(tmp_path / "rgb.png")
    assert "3-channel (colour or alpha)" in msg and "2-D" in msg


def test_rgb_tiff_and_3d_npy_are_not_2d(tmp_path: Path) -> None:
    tifffile.imwrite(tmp_path / "rgb.tif", np.zeros((H, W, 3), np.uint8), photometric="rgb")
    assert "single-channel 2-D" in _raises(tmp_path / "rgb.tif")
    np.save(tmp_path / "cube.npy", np.zeros((2, H, W), np.uint16))
    assert "must be 2-D" in _raises(tmp_path / "cube.npy")


def test_wrong_size(tmp_path: Path) -> None:
    write_raw(tmp_path / "a.dng", _random(), cfa="RGGB")
    msg = _raises(tmp_path / "a.dng", expected_shape=(2048, 2048))
    assert "64x96" in msg and "2048x2048" in msg


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_inf_in_npy(tmp_path: Path, bad: float) -> None:
    data = np.ones((H, W), np.float32)
    data[5, 7] = bad
    np.save(tmp_path / "n.npy", data)
    assert "NaN or infinite" in _raises(tmp_path / "n.npy")


@pytest.mark.parametrize("dtype", [np.int32, np.uint32, np.complex64, np.bool_])
def test_unsupported_dtype_npy(tmp_path: Path, dtype) -> None:
    np.save(tmp_path / "d.npy", np.zeros((H, W), dtype))
    assert "only uint8 and uint16" in _raises(tmp_path / "d.npy")


def test_unsupported_dtype_tiff_and_object_npy(tmp_path: Path) -> None:
    tifffile.imwrite(tmp_path / "f.tif", np.zeros((H, W), np.float32))
    assert "float32" in _raises(tmp_path / "f.tif")
    np.save(tmp_path / "o.npy", np.array([[object()]], dtype=object), allow_pickle=True)
    assert "Python objects" in _raises(tmp_path / "o.npy")


def test_bad_sidecar(tmp_path: Path) -> None:
    write_raw(tmp_path / "a.png", _random())
    (tmp_path / "a.png.json").write_text("{not json")
    with pytest.raises(InputError, match="a.png.json"):
        load_raw(tmp_path / "a.png")


# ------------------------------------------------------------------ write_raw: validation and atomicity


@pytest.mark.parametrize(
    "kwargs",
    [
        {"data": np.zeros((H, W), np.float32)},
        {"data": np.zeros((H, W), np.int16)},
        {"data": np.zeros((2, H, W), np.uint16)},
        {"data": [[1, 2], [3, 4]]},
        {"cfa": "RGBG"},
        {"bits": 17},
        {"bits": 12},  # data use the full 16-bit range
        {"bits": 9, "data": np.zeros((H, W), np.uint8)},
        {"black_level": 70000},
        {"black_level": 10, "white_level": 10},
        {"metadata": {"f": object()}},
        {"metadata": {"tags": 1}},
        {"metadata": "not a dict"},
    ],
)
@pytest.mark.parametrize("suffix", [".dng", ".tif", ".png", ".npy"])
def test_write_bad_args_leave_nothing_behind(tmp_path: Path, suffix: str, kwargs: dict) -> None:
    kwargs = {"data": _random(seed=13), **kwargs}
    path = tmp_path / f"w{suffix}"
    with pytest.raises(InputError, match="w" + suffix.replace(".", r"\.")):
        write_raw(path, **kwargs)
    assert _dir_listing(tmp_path) == []


@pytest.mark.parametrize("shape", [(21, 96), (64, 21)])
def test_write_dng_too_small_for_libraw(tmp_path: Path, shape: tuple[int, int]) -> None:
    with pytest.raises(InputError, match="22..64000"):
        write_raw(tmp_path / "s.dng", np.zeros(shape, np.uint16))
    write_raw(tmp_path / "s.dng", np.ones((22, 23), np.uint16), cfa="RGGB")  # the smallest LibRaw accepts
    assert np.array_equal(load_raw(tmp_path / "s.dng").data, np.ones((22, 23), np.uint16))


def test_odd_sized_cfa_dng(tmp_path: Path) -> None:
    data = _random(seed=19)[:63, :95]
    write_raw(tmp_path / "o.dng", data, cfa="GBRG")
    frame = load_raw(tmp_path / "o.dng")
    assert np.array_equal(frame.data, data) and frame.cfa == "GBRG"


def test_write_bad_suffix_and_missing_dir(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="suffix"):
        write_raw(tmp_path / "a.jpg", _random())
    with pytest.raises(InputError, match="cannot write|Cannot write"):
        write_raw(tmp_path / "no" / "such" / "a.dng", _random())
    assert _dir_listing(tmp_path) == []


@pytest.mark.parametrize("suffix", [".dng", ".tif", ".png", ".npy"])
def test_failed_write_never_clobbers_existing_file(tmp_path: Path, suffix: str, monkeypatch) -> None:
    path = tmp_path / f"keep{suffix}"
    good = _random(seed=14)
    write_raw(path, good, cfa="RGGB")
    before = _dir_listing(tmp_path)
    with pytest.raises(InputError):
        write_raw(path, np.zeros((H, W), np.float64))
    # an encoder crashing half-way must not leave a partial file in place either
    real_imwrite, real_save, real_imencode = tifffile.imwrite, np.save, cv2.imencode

    def half_then_crash(target, *args, **kwargs):
        Path(target if not hasattr(target, "write") else target.name).write_bytes(b"partial")
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(tifffile, "imwrite", half_then_crash)
    monkeypatch.setattr(np, "save", half_then_crash)
    monkeypatch.setattr(cv2, "imencode", lambda *a, **k: (False, None))
    with pytest.raises((RuntimeError, InputError)):
        write_raw(path, _random(seed=15))
    monkeypatch.setattr(tifffile, "imwrite", real_imwrite)
    monkeypatch.setattr(np, "save", real_save)
    monkeypatch.setattr(cv2, "imencode", real_imencode)
    assert _dir_listing(tmp_path) == before
    frame = load_raw(path)
    assert np.array_equal(frame.data, good) and frame.cfa == "RGGB"


def test_overwrite_replaces_whole_file(tmp_path: Path) -> None:
    write_raw(tmp_path / "a.dng", _random(seed=16), cfa="RGGB", metadata={"v": 1})
    new = _random(10, seed=17)
    write_raw(tmp_path / "a.dng", new, bits=10, metadata={"v": 2})
    frame = load_raw(tmp_path / "a.dng")
    assert np.array_equal(frame.data, new) and frame.cfa is None and frame.metadata["v"] == 2
    assert _dir_listing(tmp_path) == ["a.dng"]


# ------------------------------------------------------------------ check_exposure


def _frame(data: np.ndarray, *, black: int = 64, white: int = 4095, cfa: str | None = None) -> RawFrame:
    return RawFrame(data, 12, cfa, black, white, {}, "mem.dng")


def _white_image(rng: np.random.Generator, level: float = 2500.0, black: int = 64, pitch: int = 20) -> np.ndarray:
    """A synthetic MLA white image: 20 px cells (the reference camera), vignetted sub-images, shot + read noise."""
    yy, xx = np.mgrid[0:H, 0:W]
    c = (pitch - 1) / 2
    cell = np.clip(1.0 - ((yy % pitch - c) ** 2 + (xx % pitch - c) ** 2) / (0.5 * pitch**2), 0.0, None)
    mean = black + level * cell
    return np.clip(rng.poisson(mean - black) + black + rng.normal(0, 3, (H, W)), 0, 4095).astype(np.uint16)


def test_check_exposure_accepts_normal_frame() -> None:
    check_exposure(_frame(_white_image(np.random.default_rng(20))))
    check_exposure(_frame(_random(12, seed=21)))  # full-range random data is not "black"


@pytest.mark.parametrize("offset", [0, 5])
def test_check_exposure_rejects_black_frame(offset: int) -> None:
    dark = np.random.default_rng(22).normal(64 + offset, 4, (H, W)).round().astype(np.uint16)
    dark[3, 3] = 4095  # a hot pixel is not a signal
    with pytest.raises(InputError, match="mem.dng is black"):
        check_exposure(_frame(dark))


def test_check_exposure_rejects_saturated_frame() -> None:
    data = _white_image(np.random.default_rng(23))
    data[:, : W // 5] = 4095  # 20 % at the white level
    with pytest.raises(InputError, match="mem.dng is saturated"):
        check_exposure(_frame(data))
    check_exposure(_frame(data), max_saturated_fraction=0.25)


# ------------------------------------------------------------------ normalized


def test_normalized_mono_is_plain_scaling() -> None:
    data = np.full((H, W), 64 + 2016, np.uint16)
    out = normalized(_frame(data, white=64 + 4032))
    assert out.dtype == np.float32 and np.allclose(out, 0.5)


@pytest.mark.parametrize("cfa", CFA_PATTERNS)
def test_normalized_cfa_equalises_channels_of_a_white_scene(cfa: str) -> None:
    rng = np.random.default_rng(24)
    scene = (_white_image(rng).astype(np.float64) - 64) / 2500.0  # 0..1 flat-field shape
    gains = {"R": 0.45, "G": 0.8, "B": 0.6}
    site = np.empty((H, W), "U1")
    for i, (r, c) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        site[r::2, c::2] = cfa[i]
    g = np.vectorize(gains.get)(site)
    data = (64 + 3000 * scene * g).round().astype(np.uint16)
    out = normalized(_frame(data, cfa=cfa))
    expected = 3000 * scene * gains["G"] / (4095 - 64)
    assert np.abs(out - expected).max() < 0.01  # all four sites on the green scale; rounding only


def test_normalized_dark_cfa_frame_falls_back_to_plain() -> None:
    data = np.full((H, W), 70, np.uint16)
    out = normalized(_frame(data, cfa="RGGB"))
    assert np.allclose(out, 6 / (4095 - 64))


# ------------------------------------------------------------------ hot pixels


@pytest.mark.parametrize("cfa", [*CFA_PATTERNS, None])
def test_hot_pixels_removed_against_ground_truth(cfa: str | None) -> None:
    rng = np.random.default_rng(25)
    clean = _white_image(rng)
    dirty = clean.copy()
    spots = [(0, 0), (1, 0), (10, 13), (33, 47), (40, 41), (63, 95), (20, 94), (5, 2)]
    truth = np.zeros((H, W), bool)
    for i, (r, c) in enumerate(spots):
        dirty[r, c] = 4095 if i % 3 else 0  # hot pixels, and a couple of dead ones in bright areas
        truth[r, c] = abs(int(dirty[r, c]) - int(clean[r, c])) > 600
    cleaned, mask = suppress_hot_pixels(dirty, cfa)
    assert cleaned.dtype == dirty.dtype and mask.shape == dirty.shape
    assert truth.sum() == 7 and np.array_equal(mask, truth)  # every planted outlier found, nothing else
    step = 1 if cfa is None else 2  # same-channel neighbours are 2 px apart under a CFA
    for r, c in zip(*np.nonzero(truth)):
        nb = [clean[r + dr, c + dc] for dr in (-step, 0, step) for dc in (-step, 0, step)
              if (dr or dc) and 0 <= r + dr < H and 0 <= c + dc < W]
        assert min(nb) <= cleaned[r, c] <= max(nb)  # replaced by a value among its same-channel neighbours
    untouched = ~mask
    assert np.array_equal(cleaned[untouched], dirty[untouched])


@pytest.mark.parametrize("cfa", ["RGGB", None])
def test_hot_pixels_clean_frame_unchanged(cfa: str | None) -> None:
    clean = _white_image(np.random.default_rng(26))
    cleaned, mask = suppress_hot_pixels(clean, cfa)
    assert not mask.any() and np.array_equal(cleaned, clean)


def test_hot_pixels_keep_sharp_structure() -> None:
    """Hard-edged bright squares with 1-px dark gaps (100 % fill MLA) must survive untouched."""
    img = np.full((H, W), 3000, np.uint16)
    img[::10, :] = 100
    img[:, ::10] = 100
    cleaned, mask = suppress_hot_pixels(img, None)
    assert not mask.any() and np.array_equal(cleaned, img)


def test_hot_pixels_float_image() -> None:
    clean = normalized(_frame(_white_image(np.random.default_rng(27))))
    dirty = clean.copy()
    dirty[30, 30] = 5.0
    cleaned, mask = suppress_hot_pixels(dirty, "RGGB")
    assert mask[30, 30] and mask.sum() == 1 and abs(cleaned[30, 30] - clean[30, 30]) < 0.1


def test_hot_pixels_bad_arguments() -> None:
    with pytest.raises(InputError):
        suppress_hot_pixels(np.zeros((2, 3, 3)), None)
    with pytest.raises(InputError):
        suppress_hot_pixels(np.zeros((8, 8)), "XYZW")


def _filter_outliers(plane: np.ndarray, nsigma: float, integer: bool) -> tuple[np.ndarray, np.ndarray]:
    """The scipy.ndimage formulation of one plane's outlier test (the oracle of the compiled kernel)."""
    from scipy import ndimage

    x = plane.astype(np.float64)
    ring = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], dtype=bool)
    kx = np.array([[-1.0, 0.0, 1.0]] * 3)
    s1 = ndimage.correlate(x, ring.astype(float), mode="mirror")
    s2 = ndimage.correlate(x * x, ring.astype(float), mode="mirror")
    gx = ndimage.correlate(x, kx, mode="mirror") / 6.0
    gy = ndimage.correlate(x, kx.T, mode="mirror") / 6.0
    nb_max = ndimage.maximum_filter(x, footprint=ring, mode="mirror")
    nb_min = ndimage.minimum_filter(x, footprint=ring, mode="mirror")
    resid = (plane.astype(np.float32) - (s1 / 8.0).astype(np.float32))[::3, ::3]
    noise = 1.4826 * float(np.median(np.abs(resid - np.median(resid)))) / np.sqrt(1.125)
    noise = max(noise, 1.0 if integer else 1e-6 * float(np.ptp(x) or 1.0))
    structure = np.sqrt(np.maximum(s2 - s1 * s1 / 8.0 - 6.0 * (gx * gx + gy * gy), 0.0) / 5.0)
    limit = nsigma * np.maximum(noise, structure)
    bad = (x - nb_max > limit) | (nb_min - x > limit)
    med = ndimage.median_filter(x, size=3, mode="mirror")
    return bad, med


@pytest.mark.parametrize("cfa", ["GBRG", None])
@pytest.mark.parametrize("kind", ["uint16", "float32", "float64"])
def test_hot_pixels_match_the_filter_formulation(cfa: str | None, kind: str) -> None:
    """Compiled kernel == ndimage filters: discs with dark gaps (structure), gradients, noise, outliers."""
    rng = np.random.default_rng(31)
    yy, xx = np.mgrid[0:130, 0:150]
    img = 200 + 2500 * ((np.hypot(xx % 20 - 9.5, yy % 20 - 9.5) < 8) * (1 + xx / 300)) + rng.normal(0, 30, yy.shape)
    spots = rng.integers(0, 130, 120), rng.integers(0, 150, 120)
    img[spots] = rng.choice([0, 4095, 1500], 120)
    img = np.clip(img, 0, 4095).astype(np.uint16)
    data = img if kind == "uint16" else (img / 4095).astype(kind)
    cleaned, mask = suppress_hot_pixels(data, cfa)
    want_mask = np.zeros(data.shape, bool)
    want = data.copy()
    for sl in [(slice(None), slice(None))] if cfa is None else [(slice(r, None, 2), slice(c, None, 2)) for r in (0, 1) for c in (0, 1)]:
        bad, med = _filter_outliers(data[sl].astype(np.float32), 6.0, kind == "uint16")
        want_mask[sl] = bad
        want[sl][bad] = med[bad].astype(np.float32).astype(data.dtype)
    assert 5 < mask.sum() < 120  # outliers found, structure left alone
    assert np.array_equal(mask, want_mask)
    assert cleaned.dtype == data.dtype and np.array_equal(cleaned, want)
    again, mask2 = suppress_hot_pixels(data.copy(), cfa, inplace=True)
    assert np.array_equal(again, want) and np.array_equal(mask2, mask)


def test_exposure_statistics_from_the_histogram_match_numpy() -> None:
    """check_exposure reads its order statistics from the histogram of integer counts: the same values as
    np.percentile / np.median on the black-subtracted sample."""
    from mlaqc.inspection.raw_levels import _integer_sample_stats

    rng = np.random.default_rng(40)
    for trial in range(60):
        n = int(rng.integers(1, 5000))
        sample = [rng.integers(0, 4096, n), rng.poisson(rng.uniform(0.3, 40), n),
                  rng.integers(0, 4, n) * 1000 + 64][trial % 3]
        sample = (sample % 256).astype(np.uint8) if trial % 7 == 0 else sample.astype(np.uint16)
        black = int(rng.integers(0, 80))
        excess = sample.astype(np.float32) - np.float32(black)
        median = float(np.median(excess))
        lower = excess[excess <= median]
        want = (float(np.percentile(excess, 99.9)), median, 1.4826 * float(np.median(median - lower)))
        np.testing.assert_allclose(_integer_sample_stats(sample.reshape(1, -1), black), want, rtol=1e-6, atol=1e-6)
