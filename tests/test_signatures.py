"""Feature vectors of the inverse model: projections along and across a lens' shift."""

import numpy as np
import pytest

from mlaqc.models.signatures import FEATURES, lens_features


def metrics_with(dx: float, dy: float, ax: float, ay: float) -> dict[str, np.ndarray]:
    m = {k: np.zeros((3, 3)) for k in ("offset_x_px", "offset_y_px", "asym_x", "asym_y", "blur", "flux", "ssim", "sharpness")}
    m["offset_x_px"][1, 1], m["offset_y_px"][1, 1], m["asym_x"][1, 1], m["asym_y"][1, 1] = dx, dy, ax, ay
    return m


def test_projection_along_the_lens_own_shift():
    # shift of 0.3 px towards the image top-right (y down): along = 0.3, across = 0
    f = dict(zip(FEATURES, lens_features(metrics_with(0.3 / np.sqrt(2), -0.3 / np.sqrt(2), 0.1, 0.0), 1, 1)))
    assert f["shift_par"] == pytest.approx(0.3) and f["shift_perp"] == pytest.approx(0.0, abs=1e-15)
    assert f["asym_par"] == pytest.approx(0.1 / np.sqrt(2))


def test_projection_along_a_given_direction():
    f = dict(zip(FEATURES, lens_features(metrics_with(0.0, -0.2, 0.0, 0.0), 1, 1, direction_deg=90.0)))
    assert f["shift_par"] == pytest.approx(0.2) and f["shift_perp"] == pytest.approx(0.0, abs=1e-15)


def test_a_lens_without_any_shift_has_zero_projections():
    """A lens equal to its neighbourhood median has exactly zero shift; no direction, no crash."""
    v = lens_features(metrics_with(0.0, 0.0, 0.05, 0.0), 1, 1)
    assert np.all(np.isfinite(v)) and v[0] == v[1] == v[2] == v[3] == 0.0


def test_signature_set_is_matched_to_the_frame_rim_width():
    """At a variant's own rim width its table comes back unchanged; between two, the features are their
    linear mix; outside the rendered widths, the nearest end; an unknown width, the modelled camera's."""
    import math

    from mlaqc.models.signatures import SignatureSet
    from mlaqc.optics.config import default_config
    from mlaqc.inspection.pipeline import _models

    tables = _models(default_config())[1]
    assert isinstance(tables, SignatureSet)
    widths = tables.edge_widths()
    assert np.all(np.diff(widths) > 0)  # sharpest first, each blur wider
    a, b = tables.tables[1], tables.tables[2]
    assert np.allclose(tables.matched(widths[1]).features["pitch"], a.features["pitch"])
    mid = tables.matched(0.25 * widths[1] + 0.75 * widths[2])
    assert np.allclose(mid.features["radius"], 0.25 * a.features["radius"] + 0.75 * b.features["radius"])
    assert np.allclose(mid.rings["radius"], 0.25 * a.rings["radius"] + 0.75 * b.rings["radius"])
    assert np.allclose(tables.matched(widths[-1] * 3).features["decenter"], tables.tables[-1].features["decenter"])
    assert tables.matched(math.nan).settings["extra_blur_px"] == 0.0
