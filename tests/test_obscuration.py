"""A local obscuration (dust, residue, a dig: part of a sub-image darkened, the rest unchanged) is typed
'obscuration' with its area, depth and where it sits, never as a shape error; on frames of the independent
analytic model (tests/analytic_frames.py 'spot'), square and hex, noise-free and at 1 % noise."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import analytic_frames as am
from mlaqc.inspection.pipeline import inspect_file
from mlaqc.optics.config import load_config

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"


@pytest.fixture(scope="module", params=[("small_camera", 0.0), ("small_camera", 0.01), ("hex_small_camera", 0.0), ("hex_small_camera", 0.01)],
                ids=lambda p: f"{p[0]}-noise{p[1]:.0%}")
def frame(request, tmp_path_factory):
    """16 lenses, each with a spot over 25 % of its disc at 10 % loss, in random directions."""
    name, noise = request.param
    cfg = load_config(FIXTURES / f"{name}.toml")
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    rng = np.random.default_rng(5)
    seeded = [am.Anomaly(m, n, "spot", 0.10, float(rng.uniform(0, 360)), 0.25)
              for m in range(4, rows - 3, 5) for n in range(4, cols - 3, 5)][:16]
    model = am.AnalyticModel(shape=(cfg.sensor.height_px, cfg.sensor.width_px), lenses=(rows, cols),
                             packing=cfg.mla.packing, rotation_deg=0.3, phase_px=(0.3, 0.6))
    found = []
    for anomalies in (seeded, ()):  # with the spots, and the same frame without them
        counts = am.to_counts(am.expose(model.with_anomalies(anomalies).render(), noise, np.random.default_rng(1)), 16)
        path = am.write_container(Path(tmp_path_factory.mktemp("spots")) / "frame.tif", counts, 16, 0)
        found.append({(d.m, d.n): d for d in inspect_file(path, cfg).defects})
    return {(a.row + 1, a.col + 1): a for a in seeded}, found[0], set(found[1])


def test_every_spot_is_flagged_as_an_obscuration_and_nothing_else(frame):
    """Every spot is an obscuration; the only other lenses flagged are those the frame flags without spots
    (the analytic hex frame's two left-edge lenses at rows 3 and 25)."""
    seeded, found, without = frame
    assert set(seeded) <= set(found), sorted(set(seeded) - set(found))
    assert set(found) - set(seeded) <= without, sorted(set(found) - set(seeded) - without)
    assert {found[k].error_type for k in seeded} == {"obscuration"}


def test_the_spot_is_sized_and_placed(frame):
    seeded, found, _ = frame
    for key, a in seeded.items():
        d = found[key]
        # measured: area 0.22-0.26 square, 0.18-0.21 hex; depth 0.100-0.107; direction within 3 deg
        assert d.unit == "area" and 0.15 <= d.magnitude <= 0.32, (key, d.magnitude)
        assert 0.08 <= d.indexes["spot_depth"] <= 0.12, (key, d.indexes["spot_depth"])
        off = (d.direction_deg - a.direction_deg + 180.0) % 360.0 - 180.0
        assert abs(off) < 15.0, (key, d.direction_deg, a.direction_deg)
        assert not d.within_tolerance  # 25 % of the disc, beyond qc.obscuration_area = 10 %
