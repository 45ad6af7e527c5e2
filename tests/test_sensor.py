"""Sensor model: photon transfer (QE, shot noise, full well, read noise, gain, black level), CFA."""

import dataclasses

import numpy as np
import pytest

from mlaqc.optics.config import Sensor
from mlaqc.optics.sensor import cfa_site_colours, expose, white_level


def test_noise_free_exposure_is_the_photon_transfer_line():
    s = Sensor(qe=0.5, gain_dn_per_e=0.25, black_level_dn=64, bit_depth=12, full_well_e=10000, read_noise_e=0.0)
    photons = np.array([[0.0, 400.0, 4000.0, 1e6]])
    dn = expose(photons, s, seed=0, noise=False)
    assert dn.tolist() == [[64, 64 + 50, 64 + 500, min(4095, 64 + 2500)]]
    assert dn.dtype == np.uint16
    assert white_level(s) == 64 + 2500


def test_shot_noise_variance_equals_mean_in_electrons():
    s = Sensor(qe=1.0, gain_dn_per_e=1.0, black_level_dn=0, bit_depth=16, read_noise_e=0.0, full_well_e=1e6)
    dn = expose(np.full((400, 400), 900.0), s, seed=3).astype(float)
    assert dn.mean() == pytest.approx(900, rel=0.005)
    assert dn.var() == pytest.approx(900, rel=0.03)


def test_read_noise_adds_in_quadrature():
    s = Sensor(qe=1.0, gain_dn_per_e=1.0, black_level_dn=1000, bit_depth=16, read_noise_e=20.0, full_well_e=1e6)
    dn = expose(np.full((400, 400), 400.0), s, seed=4).astype(float)
    assert dn.var() == pytest.approx(400 + 400, rel=0.04)


def test_saturation_and_seeded_reproducibility():
    s = Sensor(full_well_e=1000, gain_dn_per_e=1.0, bit_depth=12, black_level_dn=10, qe=1.0, read_noise_e=3.0)
    dn = expose(np.full((10, 10), 1e5), s, seed=1)
    assert white_level(s) == 1010 - 9
    assert np.all(dn == white_level(s))  # saturated pixels read exactly the white level
    a = expose(np.full((50, 50), 500.0), s, seed=9)
    assert np.array_equal(a, expose(np.full((50, 50), 500.0), s, seed=9))
    assert not np.array_equal(a, expose(np.full((50, 50), 500.0), s, seed=10))


@pytest.mark.parametrize("cfa, top_left", [("RGGB", [[0, 1], [1, 2]]), ("BGGR", [[2, 1], [1, 0]]),
                                           ("GRBG", [[1, 0], [2, 1]]), ("GBRG", [[1, 2], [0, 1]])])
def test_cfa_sites_follow_the_pattern(cfa, top_left):
    sites = cfa_site_colours(cfa, 4, 6)
    assert sites[:2, :2].tolist() == top_left
    assert np.array_equal(sites[2:4, 2:4], sites[:2, :2])
    s = dataclasses.replace(Sensor(), cfa=cfa, cfa_qe=(0.2, 0.5, 0.8), gain_dn_per_e=1.0, black_level_dn=0, bit_depth=16)
    dn = expose(np.full((4, 6), 1000.0), s, seed=0, noise=False)
    assert np.array_equal(dn, np.array([200, 500, 800])[sites])
