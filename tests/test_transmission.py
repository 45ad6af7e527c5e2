"""A dim lens (a transmission loss, its sub-image's shape kept) is typed 'dim' with its loss, never as a
radius or thickness error; a lens whose sub-image changes shape is not typed dim. On frames of the
independent analytic model (tests/analytic_frames.py), where a 'dim' anomaly scales one disc's light."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import analytic_frames as am
from calib_images import SMALL
from mlaqc.inspection.pipeline import inspect_file
from mlaqc.models.signatures import FEATURES, KINDS, signature_table
from mlaqc.models.transmission import DIM, with_dim

ANOMALIES = (am.Anomaly(6, 6, "dim", 0.85), am.Anomaly(6, 12, "dim", 0.7), am.Anomaly(6, 18, "dim", 0.92),
             am.Anomaly(12, 6, "size", 0.95), am.Anomaly(12, 12, "size", 1.05), am.Anomaly(18, 18, "blur", 2.0),
             am.Anomaly(18, 6, "shift", 0.5, 30.0))


@pytest.fixture(scope="module", params=[0.0, 0.01])
def result(request, tmp_path_factory):
    model = am.AnalyticModel(shape=(SMALL.sensor.height_px, SMALL.sensor.width_px), lenses=(24, 24),
                             rotation_deg=0.3, phase_px=(0.3, 0.6)).with_anomalies(ANOMALIES)
    rng = np.random.default_rng(1)
    counts = am.to_counts(am.expose(model.render(), request.param, rng), 16)
    path = am.write_container(Path(tmp_path_factory.mktemp("dim")) / "frame.tif", counts, 16, 0)
    res = inspect_file(path, SMALL)
    return {(d.m, d.n): d for d in res.defects}


@pytest.mark.parametrize("m, n, loss", [(7, 7, 0.15), (7, 13, 0.30), (7, 19, 0.08)])
def test_a_dim_lens_is_typed_dim_with_its_loss(result, m, n, loss):
    d = result[(m, n)]
    assert d.error_type == "dim" and d.unit == "rel"
    assert d.magnitude == pytest.approx(-loss, abs=0.015)


def test_lenses_that_change_shape_are_not_dim(result):
    for key in ((13, 7), (13, 13), (19, 19), (19, 7)):
        assert key in result and result[key].error_type != "dim"


def test_the_dim_curve_changes_the_flux_alone_and_is_never_rendered():
    table = with_dim(signature_table(SMALL).tables[0])
    feats = table.features["dim"]
    flux = FEATURES.index("flux")
    assert np.array_equal(feats[:, flux], np.asarray(DIM.magnitudes))
    assert not np.delete(feats, flux, axis=1).any() and not table.rings["dim"].any()
    assert "dim" not in {k.name for k in KINDS}
