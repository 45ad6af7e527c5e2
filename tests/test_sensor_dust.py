"""A shadow on the sensor stays at its pixels while the array moves; the array's own defects move with it.
Two frames of the independent analytic model (tests/analytic_frames.py) at stage positions three lenses
apart, with a cover-glass shadow and an array spot: the shadow is reported once as the sensor's and
flags no lens; the array's spot stays flagged in both frames, on the same lens."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import analytic_frames as am
from mlaqc.cli import main
from mlaqc.inspection.pipeline import inspect_file
from mlaqc.inspection.sensor_dust import sensor_shadows
from mlaqc.optics.config import load_config

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
SHADOW = am.SensorSpot(250.3, 200.7, 4.0, 0.2)  # a cover-glass dust shadow: 40 % of a sub-image's disc, 20 % deep
ARRAY_SPOT = am.Anomaly(10, 4, "spot", 0.15, 200.0, 0.25)  # dust on the array (0-based lens 10, 4)


def camera_toml(count: str = "20") -> str:
    """The Table 1 small camera's config with `count` lenses a side on its 496 px sensor: 20 leaves room to
    move three lenses; '"auto"' numbers the lenses a larger array puts on the frame."""
    return (FIXTURES / "small_camera.toml").read_text().replace("= 24", f"= {count}")


def camera(tmp: Path, count: str = "20"):
    (tmp / "camera.toml").write_text(camera_toml(count))
    return load_config(tmp / "camera.toml")


def frames(tmp: Path, lenses: int, moves_px: tuple[float, ...], noise: float, shadow=True) -> list[Path]:
    """One frame per array position (x offset of the array, px), the shadow fixed on the sensor."""
    paths = []
    for k, dx in enumerate(moves_px):
        model = am.AnalyticModel(shape=(496, 496), lenses=(lenses, lenses), rotation_deg=0.2, phase_px=(dx, 0.4),
                                 anomalies=(ARRAY_SPOT,), sensor_spots=(SHADOW,) if shadow else ())
        counts = am.to_counts(am.expose(model.render(), noise, np.random.default_rng(k)), 16)
        paths.append(am.write_container(tmp / f"pos{k}.tif", counts, 16, 0))
    return paths


THREE = 3 * am.table1_pitch_px()


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_a_shadow_that_stays_while_the_array_moves_is_the_sensors(tmp_path, noise):
    cfg = camera(tmp_path)
    paths = frames(tmp_path, 20, (-THREE / 2 + 0.2, THREE / 2 + 0.2), noise)
    results = [inspect_file(p, cfg) for p in paths]
    # both frames flag the shadow against some lens (different ones) and the array's spot on the same lens
    under = [{(d.m, d.n) for d in r.defects if abs(d.indexes.get("spot_x_px", -99) - SHADOW.x_px) < 2} for r in results]
    assert all(len(u) == 1 for u in under) and under[0] != under[1], under
    shadows, cleared, _ = sensor_shadows(results, [{}, {}], cfg)
    assert len(shadows) == 1
    s = shadows[0]
    assert abs(s.x_px - SHADOW.x_px) < 0.5 and abs(s.y_px - SHADOW.y_px) < 0.5, (s.x_px, s.y_px)
    assert 0.15 <= s.depth <= 0.25 and {f for f, _, _ in s.lenses} == {str(p) for p in paths}
    for r in cleared:
        # nothing against any lens from the shadow; the array's spot stays, on its own lens U(11, 5)
        assert {(d.m, d.n, d.error_type) for d in r.defects} == {(11, 5, "obscuration")}, r.defects
        assert any(n.startswith("sensor shadow at x 250.3") for n in r.notes)


def test_a_spot_on_the_same_lens_in_repeated_frames_stays_the_lens(tmp_path):
    """The array did not move: a dark region at the same pixels is on the same lens, which may be the
    array's (a second frame cannot tell): nothing is taken off."""
    cfg = camera(tmp_path)
    paths = frames(tmp_path, 20, (0.2, 0.2), 0.01)
    results = [inspect_file(p, cfg) for p in paths]
    shadows, cleared, notes = sensor_shadows(results, [{}, {}], cfg)
    assert shadows == [] and len(notes) == 1 and "kept as the lenses' defects" in notes[0]
    assert [len(r.defects) for r in cleared] == [len(r.defects) for r in results] == [2, 2]


def test_with_lenses_numbered_from_the_frame_the_sidecars_stage_positions_decide(tmp_path):
    """counts 'auto' (an array larger than the sensor): the lens numbers follow the frame, so only the
    stage positions in the frames' sidecars tell that the array moved."""
    cfg = camera(tmp_path, '"auto"')
    paths = frames(tmp_path, 30, (0.3, THREE + 0.3), 0.01)
    results = [inspect_file(p, cfg) for p in paths]
    assert all(any(abs(d.indexes.get("spot_x_px", -99) - SHADOW.x_px) < 2 for d in r.defects) for r in results)
    shadows, _, notes = sensor_shadows(results, [{}, {}], cfg)
    assert shadows == [] and notes  # not known to have moved
    stage = [{"stage_position_mm": [10.0, 5.0]}, {"stage_position_mm": [10.3, 5.0]}]  # 3 lenses of 100 µm
    shadows, cleared, notes = sensor_shadows(results, stage, cfg)
    assert len(shadows) == 1 and notes == ()
    assert not any(abs(d.indexes.get("spot_x_px", -99) - SHADOW.x_px) < 2 for r in cleared for d in r.defects)


def test_the_batch_writes_the_shadow_once_and_a_single_frame_is_refused(tmp_path, capsys):
    cfg_path = tmp_path / "cam20.toml"
    cfg_path.write_text(camera_toml())
    paths = frames(tmp_path, 20, (-THREE / 2 + 0.2, THREE / 2 + 0.2), 0.01)
    out = tmp_path / "out"
    assert main(["inspect", *map(str, paths), "-c", str(cfg_path), "--sensor-dust", "-o", str(out), "-q"]) == 1
    doc = json.loads((out / "sensor_dust.json").read_text())
    assert len(doc["shadows"]) == 1 and len(doc["shadows"][0]["lenses"]) == 2
    for p in paths:
        report = json.loads((out / p.stem / "report.json").read_text())
        assert [(d["row"], d["col"]) for d in report["defects"]] == [(11, 5)]
    lone = tmp_path / "lone"
    assert main(["inspect", str(paths[0]), "-c", str(cfg_path), "--sensor-dust", "-o", str(lone)]) == 2
    assert "--sensor-dust compares the frames of a batch" in capsys.readouterr().err and not lone.exists()


def test_a_bad_frame_in_the_batch_is_one_error_row_and_the_others_are_still_judged(tmp_path):
    """A truncated raw among the frames: its row says why (exit 2), the two good frames are still compared
    and reported, and a sidecar whose stage position is malformed counts as none."""
    cfg_path = tmp_path / "cam20.toml"
    cfg_path.write_text(camera_toml())
    paths = frames(tmp_path, 20, (-THREE / 2 + 0.2, THREE / 2 + 0.2), 0.01)
    bad = tmp_path / "bad.tif"
    bad.write_bytes(paths[0].read_bytes()[:5000])
    (tmp_path / "pos0.tif.meta.json").write_text('{"stage_position_mm": ["x", null]}')
    out = tmp_path / "out"
    assert main(["inspect", str(paths[0]), str(bad), str(paths[1]), "-c", str(cfg_path), "--sensor-dust",
                 "-o", str(out), "-q"]) == 2
    rows = (out / "batch.csv").read_text().splitlines()
    assert rows[2].startswith(str(bad)) and ",ERROR," in rows[2]
    doc = json.loads((out / "sensor_dust.json").read_text())
    assert len(doc["shadows"]) == 1 and doc["frames"] == 3  # fixed counts: a different lens under it decides
    assert not (out / "bad").exists() and (out / "pos0" / "report.json").is_file()
