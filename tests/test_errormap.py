"""Error maps: JSON keyed by U(m,n), validation naming lens and field, seeded random defects."""

import json

import numpy as np
import pytest

from mlaqc.errors import InputError
from mlaqc.optics.errormap import ErrorMap, error_map_from_dict, load_error_map, random_defects


def test_json_round_trip_keeps_every_field(tmp_path):
    em = ErrorMap.zeros(10, 12).with_lens(1, 1, pitch_um=2.5, pitch_dir_deg=30).with_lens(
        10, 12, decenter_um=7, decenter_dir_deg=200, radius_front_rel=0.1, radius_back_rel=-0.05,
        tilt_x_deg=1, tilt_y_deg=-2, thickness_um=-1).with_globals(mla_rotation_deg=0.3, mla_sensor_distance_um=-4)
    em.save(tmp_path / "map.json")
    back = load_error_map(tmp_path / "map.json", (10, 12))
    for k, v in em.lens.items():
        assert np.array_equal(back.lens[k], v), k
    assert back.globals == em.globals
    data = json.loads((tmp_path / "map.json").read_text())
    assert [(e["m"], e["n"]) for e in data["lenses"]] == [(1, 1), (10, 12)]  # U(m,n), 1-based


def test_u_mn_indexing_is_row_from_top_column_from_left():
    em = ErrorMap.zeros(3, 4).with_lens(1, 4, pitch_um=1)
    assert em.lens["pitch_um"][0, 3] == 1 and em.defective().sum() == 1


def _doc(**over):
    doc = {"format": "mlaqc-error-map", "version": 1, "shape": {"rows": 5, "cols": 5}, "global": {}, "lenses": []}
    doc.update(over)
    return doc


@pytest.mark.parametrize("doc, match", [
    (_doc(format="other"), "not an mlaqc error map"),
    (_doc(version=9), "version"),
    (_doc(shape={"rows": 0, "cols": 5}), "shape"),
    (_doc(lenses=[{"m": 6, "n": 1, "pitch_um": 1}]), r"m in 1\.\.5"),
    (_doc(lenses=[{"m": 2, "n": 3, "pich_um": 1}]), r"U\(2,3\).*pich_um"),
    (_doc(lenses=[{"m": 2, "n": 3, "pitch_um": "big"}]), r"U\(2,3\).*pitch_um"),
    (_doc(lenses=[{"m": 2, "n": 3, "pitch_um": 500}]), r"U\(2,3\).*pitch_um.*outside"),
    (_doc(lenses=[{"m": 2, "n": 3, "radius_front_rel": -0.9}]), "radius_front_rel"),
    (_doc(**{"global": {"mla_spin": 1}}), "mla_spin"),
    (_doc(lenses="all"), "must be a list"),
])
def test_malformed_maps_are_refused_with_the_entry_named(doc, match):
    with pytest.raises(InputError, match=match):
        error_map_from_dict(doc, "map.json")


def test_shape_must_match_the_camera_and_files_must_parse(tmp_path):
    p = tmp_path / "m.json"
    p.write_text(json.dumps(_doc()))
    with pytest.raises(InputError, match="5x5 MLA but the camera has 102x102"):
        load_error_map(p, (102, 102))
    p.write_text("{not json")
    with pytest.raises(InputError, match="not readable JSON"):
        load_error_map(p)


def test_random_defects_are_seeded_separated_and_in_range():
    a = random_defects(30, 30, 40, seed=5, types=("pitch", "decenter", "radius", "tilt", "thickness"))
    b = random_defects(30, 30, 40, seed=5, types=("pitch", "decenter", "radius", "tilt", "thickness"))
    c = random_defects(30, 30, 40, seed=6)
    for k in a.lens:
        assert np.array_equal(a.lens[k], b.lens[k])
    assert not np.array_equal(a.defective(), c.defective())
    d = a.defective()
    assert d.sum() == 40 and not d[0].any() and not d[:, -1].any()
    idx = np.argwhere(d)
    dist = np.abs(idx[:, None, :] - idx[None, :, :]).max(axis=2) + np.eye(len(idx), dtype=int) * 9
    assert dist.min() >= 2  # no two defects touch
    assert set(a.lens_type()[d]) <= {"pitch", "decenter", "radius", "tilt", "thickness"}
    p = a.lens["pitch_um"][a.lens["pitch_um"] > 0]
    assert p.min() >= 1.0 and p.max() <= 5.0
    with pytest.raises(InputError):
        random_defects(5, 5, 20, seed=1)
    with pytest.raises(InputError, match="unknown defect type"):
        random_defects(5, 5, 1, seed=1, types=("warp",))
