"""A small frame states the detection limit it reaches: on 12 x 12 and 24 x 24 frames of the independent
analytic model (tests/analytic_frames.py), every lens shifted by at least the pitch limit its report states
(the inner lenses', or the edge zone's where it sits there: the three outer rings and the corner zones) is flagged; a healthy frame flags nothing;
the array's corner lenses are said not to be judged. bench/small_frames.py measures the same over more
seeds, noise levels and the 102 x 102 frame."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

import analytic_frames as am
from mlaqc.inspection.detection_limits import edge_zone
from mlaqc.inspection.pipeline import inspect_file
from mlaqc.optics.config import load_config

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
UM_TO_PX = (am.TABLE1_B_MM + am.TABLE1_F_MM) / am.TABLE1_B_MM / am.TABLE1_PIXEL_UM  # a pitch error's shift


def camera(lenses: int):
    cfg = load_config(FIXTURES / "small_camera.toml")
    side = 16 * math.ceil((lenses * cfg.layout.subimage_pitch_px + 8) / 16)
    return dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, count_w=lenses, count_h=lenses),
                               sensor=dataclasses.replace(cfg.sensor, width_px=side, height_px=side))


def inspect(cfg, model, noise: float, tmp: Path, seed: int):
    counts = am.to_counts(am.expose(model.render(), noise, np.random.default_rng(seed)), 12)
    return inspect_file(am.write_container(tmp / "frame.tif", counts, 12, 0), cfg)


@pytest.mark.parametrize("lenses,noise", [(12, 0.0), (12, 0.01), (24, 0.01)])
def test_every_shift_at_the_stated_limit_is_flagged(tmp_path, lenses, noise):
    cfg = camera(lenses)
    model = am.AnalyticModel(shape=(cfg.sensor.height_px, cfg.sensor.width_px), lenses=(lenses, lenses),
                             rotation_deg=0.7, phase_px=(0.21, -0.33))
    healthy = inspect(cfg, model, noise, tmp_path, 1)
    assert healthy.defects == ()  # measured: 0 on 5 seeds of each (17 in 3 12 x 12 frames at 1 % before)
    assert any("corner lenses are not judged" in n for n in healthy.notes)
    limit = healthy.detection_limit
    inner, border = limit["pitch_um"], limit["border"]["pitch_um"]
    assert border >= inner  # the edge zone's spreads are their own: wider
    zone = edge_zone((lenses, lenses))
    rng = np.random.default_rng(4)
    seeded = {}
    sites = {(m, n) for m in range(0, lenses, 4) for n in range(0, lenses, 4)} | {(2, 6), (3, 3), (lenses - 3, 5)}
    for m, n in sorted(sites):  # every ring, the second and third ring and a corner zone among them
        if m in (0, lenses - 1) and n in (0, lenses - 1):
            continue  # a corner: not judged
        if any(abs(m - a) <= 1 and abs(n - b) <= 1 for a, b in seeded):
            continue  # two lenses apart
        stated = border if zone[m, n] else inner
        um = stated * (1.0 if (m + n) % 8 == 0 else 1.25)
        seeded[(m, n)] = am.Anomaly(m, n, "shift", um * UM_TO_PX, float(rng.uniform(0, 360)))
    result = inspect(cfg, model.with_anomalies(seeded.values()), noise, tmp_path, 2)
    own = result.detection_limit
    flagged = {(d.m - 1, d.n - 1) for d in result.defects}
    for (m, n), a in seeded.items():
        stated = own["border"]["pitch_um"] if zone[m, n] else own["pitch_um"]
        if a.magnitude / UM_TO_PX >= stated - 1e-9:  # at or above what this frame's report states
            assert (m, n) in flagged, ((m, n), a.magnitude / UM_TO_PX, stated)
    assert flagged <= set(seeded), sorted(flagged - set(seeded))


# --- a small hex array's edge columns ---------------------------------------------------------------------

def hex_camera(lenses: int):
    """hex_small_camera.toml's optics with `lenses` columns and the rows filling a square sensor."""
    cfg = load_config(FIXTURES / "hex_small_camera.toml")
    p = cfg.layout.subimage_pitch_px
    rows = 2 * round(lenses / math.sqrt(3.0))
    side = 16 * math.ceil((max(lenses * p, ((rows - 1) * math.sqrt(3.0) / 2 + 1) * p) + 8) / 16)
    return dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, count_w=lenses, count_h=rows),
                               sensor=dataclasses.replace(cfg.sensor, width_px=side, height_px=side))


@pytest.mark.parametrize("noise,rotation_deg,phase_px", [  # bench/small_frames.py's draws that flagged lenses
    (0.0, -0.040, (0.273, -0.329)), (0.0, -0.043, (-0.186, -0.482)), (0.0, -0.323, (-0.278, 0.123)),
    (0.0, -0.100, (0.421, -0.353)), (0.01, -0.173, (-0.153, -0.150)), (0.01, 0.282, (-0.421, 0.426))])
def test_a_healthy_small_hex_frame_flags_nothing(tmp_path, noise, rotation_deg, phase_px):
    """12 x 14 hex: each side's edge column holds 6 row ends of each kind (sticking out, sitting in), under
    EDGE_GROUP_MIN. Their sub-pixel pattern was read against the inner lenses' spread (measured: 26 false
    flags in 30 of bench/small_frames.py's frames, all on the edge columns); now against the two sides'
    pooled spread of their kind, raised to a side's own (HEX_EDGE_GROUP_MIN): 0 in 90."""
    cfg = hex_camera(12)
    model = am.AnalyticModel(shape=(cfg.sensor.height_px, cfg.sensor.width_px),
                             lenses=(cfg.mla.count_h, cfg.mla.count_w), packing="hex",
                             rotation_deg=rotation_deg, phase_px=phase_px)
    result = inspect(cfg, model, noise, tmp_path, 5)
    assert result.defects == (), [(d.m, d.n, d.error_type) for d in result.defects]


def test_the_end_lenses_of_a_hex_edge_column_are_judged():
    """A hex edge column's running median is taken over the lenses of one row parity, corners left out;
    its end lenses' windows slide inward instead of repeating the end lens, whose median was then always
    its own value: a defect there read 0 and was never flagged."""
    from mlaqc.inspection.baselines import local_deviation

    for rows, cols in ((14, 12), (15, 12)):  # 15: one parity with no corner, the other with two
        values = np.random.default_rng(0).normal(0.0, 0.01, (rows, cols))
        lines = [[r for r in range(parity, rows, 2) if r not in (0, rows - 1)] for parity in (0, 1)]
        ends = {(line[i], c) for line in lines for i in (0, -1) for c in (0, cols - 1)}
        for r, c in sorted(ends):  # each row parity's first and last lenses between the corners, both sides
            for axis in ("", "x"):
                bumped = values.copy()
                bumped[r, c] += 1.0
                dev = local_deviation(bumped, axis=axis, packing="hex")
                assert dev[r, c] > 0.9, (rows, r, c, axis, dev[r, c])
