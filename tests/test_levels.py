"""Bit depth and black level of containers that do not say them (resolve_levels), and the checks after."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import tifffile

from mlaqc.errors import InputError
from mlaqc.inspection.raw_levels import Levels, check_exposure, normalized, resolve_levels, unlit_level
from mlaqc.inspection.raw_write import write_raw
from mlaqc.inspection.rawio import load_raw


def _discs(bits: int, black: int, peak_fraction: float = 0.8, shape=(240, 240), pitch: int = 20) -> np.ndarray:
    """Lit discs on a dark grid, as a white plenoptic frame: black between them, peak at a fraction of
    full scale, in a uint16 container."""
    y, x = np.mgrid[: shape[0], : shape[1]]
    r = np.hypot((x % pitch) - (pitch - 1) / 2, (y % pitch) - (pitch - 1) / 2)
    signal = np.clip(8.5 - r, 0, 1)
    full = (1 << bits) - 1
    return np.round(black + signal * peak_fraction * (full - black)).astype(np.uint16)


def _bare_tiff(path, data):
    tifffile.imwrite(path, data)  # no BlackLevel / WhiteLevel tags: only the 16-bit container
    return load_raw(path)


def test_twelve_bit_data_in_a_bare_16_bit_tiff_reads_as_12_bit(tmp_path):
    frame = _bare_tiff(tmp_path / "f.tif", _discs(12, 64))
    assert frame.levels_from == "container" and frame.white_level == 65535
    from_data = resolve_levels(frame)
    assert (from_data.bits, from_data.black_level, from_data.white_level, from_data.levels_from) == (12, 64, 4095, "data")
    check_exposure(from_data)
    assert normalized(from_data).max() == pytest.approx(0.8, abs=1e-3)
    from_config = resolve_levels(frame, sensor=Levels(12, 64))
    assert (from_config.bits, from_config.black_level, from_config.levels_from) == (12, 64, "config")


def test_config_levels_are_used_only_where_the_data_agree(tmp_path):
    frame = _bare_tiff(tmp_path / "f.tif", _discs(14, 0))  # 14-bit counts, black 0
    got = resolve_levels(frame, sensor=Levels(12, 64))  # the config's 12 bits cannot hold them
    assert (got.bits, got.black_level, got.white_level, got.levels_from) == (14, 0, 16383, "data")
    below = resolve_levels(_bare_tiff(tmp_path / "g.tif", _discs(12, 0)), sensor=Levels(12, 64))
    assert below.black_level == 0  # dark pixels at 0 contradict the config's black level 64


def test_stated_levels_win_and_impossible_ones_are_refused(tmp_path):
    frame = _bare_tiff(tmp_path / "f.tif", _discs(12, 64))
    got = resolve_levels(frame, Levels(bits=14, black=100), Levels(12, 64))
    assert (got.bits, got.black_level, got.white_level, got.levels_from) == (14, 100, 16383, "option")
    with pytest.raises(InputError, match="more than 10 bits"):
        resolve_levels(frame, Levels(bits=10))
    with pytest.raises(InputError, match="outside 8..16"):
        Levels(bits=20)


def test_levels_from_file_tags_are_kept(tmp_path):
    data = _discs(12, 64)
    write_raw(tmp_path / "f.tif", data, bits=12, black_level=64, white_level=4095)
    frame = load_raw(tmp_path / "f.tif")
    assert frame.levels_from == "file"
    assert resolve_levels(frame, sensor=Levels(16, 0)) is frame


def test_a_frame_without_dark_pixels_keeps_black_zero(tmp_path):
    flat = np.full((64, 64), 3000, np.uint16)
    got = resolve_levels(_bare_tiff(tmp_path / "f.tif", flat))
    assert (got.bits, got.black_level) == (12, 0)


def test_cli_bit_depth_too_small_is_one_sentence_and_exit_2(tmp_path):
    path = tmp_path / "f.tif"
    tifffile.imwrite(path, _discs(12, 64, shape=(2048, 2048)))
    out = subprocess.run([sys.executable, "-m", "mlaqc.cli", "inspect", str(path), "--out", str(tmp_path / "r"),
                          "--bit-depth", "10"], capture_output=True, text=True)
    assert out.returncode == 2, out.stderr
    assert "more than 10 bits" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "r").exists()


# ------------------------------------------------------------------- gaps lit by stray light, 0..1 floats


def _lit_gaps(bits: int, black: int, noise: float, seed: int = 3, stray: float = 0.01) -> np.ndarray:
    """Lit discs whose wide gaps are lit too: stray light of 0.7-1 x `stray` of white across the frame (as
    veiling glare falls off from the centre) and the rims' blurred tails; read noise of `noise` counts.
    No pixel shows the black."""
    from scipy.ndimage import gaussian_filter

    y, x = np.mgrid[:480, :480]
    r = np.hypot((x % 20) - 9.5, (y % 20) - 9.5)
    glare = stray * (1.0 - 0.3 * np.hypot(x - 240, y - 240) / 340)
    signal = gaussian_filter(np.clip(7.5 - r, 0, 1), 0.8) + glare
    full = (1 << bits) - 1
    counts = black + signal * 0.8 * (full - black) + np.random.default_rng(seed).normal(0, noise, signal.shape)
    return np.clip(np.round(counts), 0, full).astype(np.uint16)


@pytest.mark.parametrize("bits, black, noise", [(14, 512, 0.0), (14, 512, 20.0), (16, 0, 150.0), (12, 64, 3.0)])
def test_black_from_data_of_lit_gaps_stays_near_the_darkest_pixels(tmp_path, bits, black, noise):
    """Where the gaps are lit, their median is light, not black: the estimate is capped at three times
    the pixel-to-pixel noise above the darkest 0.1 % (on an independent generator's frames the gaps'
    median read 888 for a black of 512, now 744). It never goes below the true black, and the frame stays
    lit. (Light that lies on every pixel cannot be told from black: only tags, the config or
    --black-level can.)"""
    data = _lit_gaps(bits, black, noise)
    got = resolve_levels(_bare_tiff(tmp_path / "f.tif", data))
    assert got.bits == bits and got.levels_from == "data"
    sample = data[::3, ::3]
    darkest, top = np.percentile(sample, [0.1, 99.0])
    gaps = float(np.median(sample[sample <= darkest + 0.02 * (top - darkest)]))
    assert black <= got.black_level <= gaps
    if noise == 0:  # without noise: the level of the darkest pixels
        assert got.black_level <= darkest + 0.001 * (1 << bits) < gaps
    check_exposure(got)


@pytest.mark.parametrize("black", [0, 64, 512])
def test_dark_gaps_and_frames_without_unlit_pixels_are_read_as_before(tmp_path, black):
    """The cap only binds where the darkest pixels are lit: truly dark gaps still give the black exactly,
    and a frame with no unlit pixels still gives 0."""
    assert resolve_levels(_bare_tiff(tmp_path / "d.tif", _discs(14, black))).black_level == black
    noisy = _discs(12, black).astype(float) + np.random.default_rng(2).normal(0, 4.0, (240, 240))
    got = resolve_levels(_bare_tiff(tmp_path / "n.tif", np.clip(np.round(noisy), 0, 4095).astype(np.uint16)))
    assert abs(got.black_level - black) <= 2
    assert unlit_level(np.full((240, 240), black + 700, np.uint16)) == 0.0


def test_a_float_frame_within_0_1_reads_as_normalized(tmp_path):
    """Floats all within [0, 1] (not all integers) are a normalized frame: black 0, white 1, lit; floats of
    counts, and a float frame of only 0 and 1, are read as before (16-bit counts)."""
    unit = _discs(16, 0).astype(np.float32) / 65535.0
    np.save(tmp_path / "u.npy", unit)
    frame = resolve_levels(load_raw(tmp_path / "u.npy"))
    assert (frame.black_level, frame.white_level, frame.levels_from) == (0, 1, "normalized")
    check_exposure(frame)
    assert np.allclose(normalized(frame), unit)
    counts = _discs(12, 64).astype(np.float32)
    np.save(tmp_path / "c.npy", counts)
    assert (load_raw(tmp_path / "c.npy").white_level, load_raw(tmp_path / "c.npy").levels_from) == (65535, "container")
    binary = (unit > 0.5).astype(np.float32)
    np.save(tmp_path / "b.npy", binary)
    assert load_raw(tmp_path / "b.npy").white_level == 65535
    # a black normalized frame is still black
    np.save(tmp_path / "k.npy", np.abs(np.random.default_rng(1).normal(0, 1e-4, (240, 240))).astype(np.float32))
    with pytest.raises(InputError, match="is black"):
        check_exposure(resolve_levels(load_raw(tmp_path / "k.npy")))
