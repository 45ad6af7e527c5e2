"""Bit depth and black level of containers that do not say them (resolve_levels), and the checks after."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import tifffile

from mlaqc.errors import InputError
from mlaqc.inspection.rawio import Levels, check_exposure, load_raw, normalized, resolve_levels, write_raw


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
