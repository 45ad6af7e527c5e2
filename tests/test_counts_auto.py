"""count_w = count_h = "auto": an array larger than the frame (a microscope's MLA, a cropped region of
interest). The frame's border lenses are cut and never flagged for it; a crop at any offset flags the same
lenses as the full frame where both see them whole."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mlaqc.cli import main
from mlaqc.errors import InputError
from mlaqc.inspection.pipeline import inspect_file
from mlaqc.inspection.rawio import write_raw
from mlaqc.optics.config import config_from_dict, config_to_toml
from mlaqc.optics.errormap import random_defects
from mlaqc.optics.sensor import white_level
from mlaqc.optics.simulate import simulate


def auto_camera(width: int, height: int):
    return config_from_dict({"mla": {"count_w": "auto", "count_h": "auto"},
                             "sensor": {"width_px": width, "height_px": height}})


def test_auto_counts_cover_the_sensor_and_round_trip():
    cfg = auto_camera(496, 300)
    pitch = cfg.layout.subimage_pitch_px
    assert cfg.mla.count_w * pitch >= 496 + pitch and cfg.mla.count_h * pitch >= 300 + pitch
    assert cfg.mla.count_w * pitch <= 496 + 3 * pitch
    assert config_from_dict(tomllib.loads(config_to_toml(cfg))) == cfg
    assert config_from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(InputError, match="mla.count_h"):
        config_from_dict({"mla": {"count_w": "auto"}})


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """A 496 x 496 frame of an array larger than it, with 8 defects, and its crop at offset (51, 37)."""
    tmp = tmp_path_factory.mktemp("auto")
    cfg = auto_camera(496, 496)
    errors = random_defects(cfg.mla.count_h, cfg.mla.count_w, 8, 4, types=("pitch", "radius"))
    sim = simulate(cfg, None, errors, rays_per_pixel=50, seed=4)
    s = cfg.sensor
    out = []
    for name, (y0, x0) in (("full", (0, 0)), ("crop", (37, 51))):
        raw = sim.raw[y0:, x0:]
        path = tmp / f"{name}.tiff"
        write_raw(path, raw, bits=s.bit_depth, black_level=s.black_level_dn, white_level=white_level(s))
        crop_cfg = auto_camera(raw.shape[1], raw.shape[0])
        out.append((inspect_file(path, crop_cfg), (x0, y0)))
    return out


def _flagged_at(result, origin, min_score: float = 0.0):
    """Flagged lenses (score at least `min_score`) by their sub-image centre in the full frame's pixels, and
    the centres of the grid's lenses seen whole."""
    g = result.grid
    ox, oy = origin
    flagged = [(g.grid_x_px[d.m - 1, d.n - 1] + ox, g.grid_y_px[d.m - 1, d.n - 1] + oy) for d in result.defects
               if d.score >= min_score]
    whole = ~np.asarray(g.clipped, bool) & ~np.asarray(g.missing, bool)
    return np.array(flagged).reshape(-1, 2), np.column_stack([g.grid_x_px[whole] + ox, g.grid_y_px[whole] + oy])


def _near(pts, ref, tol_px: float = 5.0) -> np.ndarray:
    if not len(pts) or not len(ref):
        return np.zeros(len(pts), bool)
    return cKDTree(ref).query(pts)[0] < tol_px


def test_cut_lenses_are_never_flagged(frames):
    for result, _ in frames:
        g = result.grid
        assert g.clipped.any()  # the frame cuts lenses on every side
        assert not any(g.clipped[d.m - 1, d.n - 1] for d in result.defects)


def test_a_crop_flags_the_same_lenses_where_both_see_them_whole(frames):
    """Every lens one frame flags clearly (z >= 12: pitch 2.4-3.4 µm, radius +12 % here) and the other sees
    whole, the other flags too. (Near its limit a frame may differ: the crop, 625 lenses, states +11 % as its
    radius limit where the full frame, 729, states +5.6 %; a +6.5 % lens is flagged by the full frame alone.)"""
    (full, o_full), (crop, o_crop) = frames
    _, whole_full = _flagged_at(full, o_full)
    _, whole_crop = _flagged_at(crop, o_crop)
    clear_full, _ = _flagged_at(full, o_full, 12.0)
    clear_crop, _ = _flagged_at(crop, o_crop, 12.0)
    all_full, _ = _flagged_at(full, o_full)
    all_crop, _ = _flagged_at(crop, o_crop)
    shared_full = clear_full[_near(clear_full, whole_crop)]
    shared_crop = clear_crop[_near(clear_crop, whole_full)]
    assert len(shared_full) >= 4 and len(shared_crop) >= 4
    assert _near(shared_full, all_crop).all() and _near(shared_crop, all_full).all()


def test_inspect_auto_counts_from_the_cli(frames, tmp_path, capsys):
    cfg_path = tmp_path / "auto.toml"
    cfg_path.write_text('[mla]\ncount_w = "auto"\ncount_h = "auto"\n[sensor]\nwidth_px = 496\nheight_px = 496\n')
    raw = tmp_path / "w.tiff"
    cfg = auto_camera(496, 496)
    s = cfg.sensor
    write_raw(raw, simulate(cfg, rays_per_pixel=20, seed=1).raw, bits=s.bit_depth, black_level=s.black_level_dn,
              white_level=white_level(s))
    assert main(["inspect", str(raw), "-c", str(cfg_path), "--out", str(tmp_path / "r")]) == 0
    assert json.loads((tmp_path / "r" / "report.json").read_text())["verdict"] == "PASS"
