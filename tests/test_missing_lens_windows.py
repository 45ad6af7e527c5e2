"""A missing lens' neighbours lack its light: their indexes deviate (an echo, not a defect), and the
baseline windows of the lenses two and three away hold them. Behind Airy rims on a rotated array every
index carries a strong sub-pixel phase pattern, so a window's median moves a whole rank step of that
pattern per echo in it: those lenses read deviations of 6 sigma unless the echoes are left out of the
baselines (issue #22: the hex full robustness matrix, asymmetry z 6.1-6.3 three lenses from a missing
one). Checked on the analytic image model (not the tracer) against its seeded truth."""

from __future__ import annotations

from pathlib import Path

import analytic_frames as am
import numpy as np

from mlaqc.inspection.pipeline import inspect_image
from mlaqc.optics.config import load_config

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
HEX = load_config(FIXTURES / "hex_camera.toml")


def test_missing_lenses_on_a_rotated_airy_hex_frame_flag_only_themselves():
    model = am.AnalyticModel(shape=(HEX.sensor.height_px, HEX.sensor.width_px),
                             lenses=(HEX.mla.count_h, HEX.mla.count_w), packing="hex", rim="airy",
                             rotation_deg=-1.3, phase_px=(0.5, 0.5))
    rng = np.random.default_rng(26)
    spots = [(m, n) for m in range(8, HEX.mla.count_h - 8, 14) for n in range(8, HEX.mla.count_w - 8, 14)]
    model = model.with_anomalies([am.Anomaly(m, n, "missing", 0.0) for m, n in spots])
    counts = am.to_counts(am.expose(model.render(), 0.01, rng), 12, 0, white_fraction=0.8)
    result = inspect_image(counts.astype(np.float64) / 4095.0, HEX)
    flagged = {(d.m - 1, d.n - 1) for d in result.defects}
    assert {(d.m - 1, d.n - 1) for d in result.defects if d.error_type == "missing"} == set(spots)
    assert flagged == set(spots)
