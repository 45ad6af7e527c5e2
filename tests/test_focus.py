"""The defocus test on the ring profile: a whitened matched filter, checked against its analytic SNR,
and end to end on a rendered lens whose radius error hardly changes the older indexes."""

from pathlib import Path

import numpy as np
import pytest

from mlaqc.inspection.detection import FOCUS_KINDS, focus_score, ring_noise
from mlaqc.inspection.identify import fit_all
from mlaqc.inspection.pipeline import _models, inspect_image, prepare
from mlaqc.inspection.rawio import RawFrame
from mlaqc.inspection.results import LensMetrics
from mlaqc.models.signatures import FEATURES, RINGS
from mlaqc.optics.config import default_config, load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene
from mlaqc.optics.sensor import expose, white_level

SMALL = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")


def _correlated_rings(shape, cov, seed):
    rng = np.random.default_rng(seed)
    return rng.multivariate_normal(np.zeros(len(RINGS)), cov, size=shape)


@pytest.fixture(scope="module")
def table():
    return _models(default_config())[1].matched(float("nan"))  # the camera's own blur (formation)


def test_focus_score_reaches_the_analytic_matched_filter_snr(table):
    """Correlated Gaussian ring noise with a known covariance, one lens carrying a table signature: its
    score is the signature's SNR sqrt(t' C^-1 t) up to unit noise, and pure noise stays below 5."""
    rng = np.random.default_rng(4)
    a = rng.normal(size=(len(RINGS), len(RINGS)))
    cov = (a @ a.T + len(RINGS) * np.eye(len(RINGS))) * 1e-6
    rings = _correlated_rings((60, 60), cov, seed=5)
    t = table.rings["radius"][list(table.magnitudes["radius"]).index(-0.05)]
    snr = float(np.sqrt(t @ np.linalg.solve(cov, t)))
    scale = 8.0 / snr  # a signature 8 sigma strong
    rings[30, 30] += scale * t
    metrics = LensMetrics({r: rings[..., k] for k, r in enumerate(RINGS)})
    z = focus_score(ring_noise(metrics), table)
    assert z[30, 30] == pytest.approx(8.0, abs=1.5)
    noise = np.delete(z.ravel(), 30 * 60 + 30)
    assert noise.max() < 5.0 and abs(np.median(noise)) < 1.5


def test_the_fit_with_rings_returns_the_injected_radius(table):
    """A lens whose ring profile is exactly the table's -10 % radius signature (other features at their
    table values) is fitted as radius -10 %, not as its opposite sign."""
    i = list(table.magnitudes["radius"]).index(-0.1)
    vec = np.concatenate([table.features["radius"][i], table.rings["radius"][i]])
    sigmas = np.abs(table.features["radius"][i]) + 1e-3
    whiten = np.diag(1.0 / (np.abs(table.rings["radius"][i]) * 0.1 + 1e-4))
    fits = fit_all(table, vec[None], sigmas, whiten)[0]
    assert min(fits, key=lambda k: fits[k][1]) == "radius"
    assert fits["radius"][0] == pytest.approx(-0.1, abs=0.005)
    assert set(FOCUS_KINDS) <= set(table.rings) and len(vec) == len(FEATURES) + len(RINGS)


def test_a_plus_15_percent_radius_lens_is_found_and_sized():
    """+15 % radius: the sub-image is barely blurrier by the older indexes' measure (they found 5 of 6 such
    lenses), but light moves across its rim: the ring test alone flags it
    (ideal matched filter 12.7 sigma at 50 rays/pixel); found as a radius error within 25 %, and no
    other lens flagged."""
    em = ErrorMap.zeros(24, 24).with_lens(12, 9, radius_front_rel=0.15, radius_back_rel=0.15)
    ph = Renderer(SMALL, em).render(WhiteScene(), rays_per_pixel=50, seed=31).photons
    s = SMALL.sensor
    frame = RawFrame(expose(ph, s, seed=32), s.bit_depth, None, s.black_level_dn, white_level(s), {}, "test")
    result = inspect_image(prepare(frame), SMALL)
    assert [(d.m, d.n) for d in result.defects] == [(12, 9)]
    d = result.defects[0]
    assert d.error_type == "radius" and d.magnitude == pytest.approx(0.15, rel=0.25)
    z = focus_score(ring_noise(result.metrics), _models(SMALL)[1].matched(result.grid.edge_width_px))
    assert z[11, 8] > SMALL.qc.detect_sigma
    assert np.delete(z.ravel(), 11 * 24 + 8).max() < SMALL.qc.detect_sigma
