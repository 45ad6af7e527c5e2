"""Sensor-side image formation against independent optics: the Fraunhofer PSF of a square aperture is
sinc² in each axis, energy is conserved, crosstalk and PRNU do exactly what they say, off means off."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from scipy.integrate import quad

from mlaqc.optics.config import Formation, config_from_dict, default_config
from mlaqc.optics.formation import (KERNEL_HALF_PX, aperture_corner_radius_um, apply_formation, crosstalk_kernel,
                                    diffraction_psf, formation_kernels)
from mlaqc.errors import InputError

CFG = default_config()


def _clear(cfg):
    return replace(cfg, mla=replace(cfg.mla, corners="clear"))


def test_corner_radius_is_where_the_two_sags_use_up_the_thickness():
    mla = CFG.mla  # symmetric biconvex: each sag is half the thickness there
    r = abs(mla.radius_front_um)
    expected = np.sqrt(r ** 2 - (r - mla.thickness_um / 2) ** 2)
    assert aperture_corner_radius_um(CFG) == pytest.approx(expected, rel=1e-9)
    assert aperture_corner_radius_um(_clear(CFG)) == np.inf


def test_square_aperture_kernel_is_sinc_squared_low_passed_to_the_pixel_grid():
    cfg = _clear(CFG)
    kern = diffraction_psf(cfg)
    lam_um = cfg.geometry.wavelength_nm * 1e-3
    z_um = cfg.layout.sensor_gap_mm * 1e3 + 0.5 * cfg.mla.thickness_um
    scale = cfg.mla.pitch_um / (lam_um * z_um) * cfg.sensor.pixel_um  # the PSF is sinc²(x·scale) per axis, x in px

    def tap(j):  # the Fraunhofer PSF seen through the pixel grid's ideal low-pass: ∫ sinc²(x s) sinc(j - x) dx
        return quad(lambda x: np.sinc(x * scale) ** 2 * np.sinc(j - x), -6.0, 6.0, limit=400)[0]

    line = np.array([tap(j) for j in range(-KERNEL_HALF_PX, KERNEL_HALF_PX + 1)])
    expected = np.outer(line, line)
    expected /= expected.sum()
    assert kern.shape == (2 * KERNEL_HALF_PX + 1,) * 2
    assert np.abs(kern - expected).max() < 2e-3 * kern.max()
    assert kern.sum() == pytest.approx(1.0)


def test_blurring_a_rendered_edge_matches_the_fine_grid_truth():
    """A rendered frame holds pixel integrals; blurring those is an approximation of blurring the light
    before the pixels integrate it. Against a 15x finer reference it errs by under 5 % of the signal."""
    cfg = replace(CFG, formation=Formation(diffraction=True, crosstalk=0.0, prnu_rms=0.0))
    fine = 15
    worst = 0.0
    for edge_px in (20.0, 20.2, 20.5, 20.8):
        x = (np.arange(48 * fine) + 0.5) / fine - 0.5  # fine sample centres; pixel j covers [j - 1/2, j + 1/2]
        light = (x > edge_px).astype(float)[None, :].repeat(3 * fine, axis=0)
        psf = diffraction_psf(cfg, 1.0 / fine)
        blurred = cv2.filter2D(light, -1, psf, borderType=cv2.BORDER_REPLICATE)
        truth = blurred.reshape(3, fine, 48, fine).mean(axis=(1, 3))
        pixels = light.reshape(3, fine, 48, fine).mean(axis=(1, 3))
        got = apply_formation(np.pad(pixels, ((8, 8), (0, 0)), mode="edge"), cfg)[8:-8]
        worst = max(worst, np.abs(got - truth)[1, 8:-8].max())
    assert worst < 0.05


def test_cut_corners_keep_the_psf_symmetric_and_change_it():
    psf = diffraction_psf(CFG)
    assert np.allclose(psf, psf.T) and np.allclose(psf, psf[::-1]) and np.allclose(psf, psf[:, ::-1])
    assert np.abs(psf - diffraction_psf(_clear(CFG))).max() > 1e-4


def test_energy_is_kept_away_from_the_border_and_switches_turn_each_effect_off():
    rng = np.random.default_rng(3)
    img = np.zeros((64, 64))
    img[20:44, 20:44] = rng.uniform(0.5, 1.0, (24, 24))
    off = replace(CFG, formation=Formation(diffraction=False, crosstalk=0.0, prnu_rms=0.0))
    assert np.array_equal(apply_formation(img, off), img)
    blur_only = replace(CFG, formation=Formation(diffraction=True, crosstalk=0.0, prnu_rms=0.0))
    out = apply_formation(img, blur_only)
    assert out.sum() == pytest.approx(img.sum(), rel=1e-9)
    assert out.max() < img.max()


def test_crosstalk_moves_the_stated_fraction_to_each_neighbour():
    img = np.zeros((9, 9))
    img[4, 4] = 1.0
    cfg = replace(CFG, formation=Formation(diffraction=False, crosstalk=0.03, prnu_rms=0.0))
    out = apply_formation(img, cfg)
    assert out[4, 4] == pytest.approx(0.88)
    assert out[3, 4] == out[5, 4] == out[4, 3] == out[4, 5] == pytest.approx(0.03)
    assert crosstalk_kernel(0.03).sum() == pytest.approx(1.0)


def test_prnu_is_a_fixed_pattern_of_the_stated_rms():
    cfg = replace(CFG, formation=Formation(diffraction=False, crosstalk=0.0, prnu_rms=0.01, prnu_seed=5))
    a = formation_kernels(cfg, (256, 256)).prnu
    b = formation_kernels(cfg, (256, 256)).prnu
    assert np.array_equal(a, b)
    assert np.std(a) == pytest.approx(0.01, rel=0.05) and np.mean(a) == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize("table, what", [({"crosstalk": 0.5}, "formation.crosstalk"),
                                         ({"prnu_rms": -0.1}, "formation.prnu_rms"),
                                         ({"diffraction": 1}, "formation.diffraction")])
def test_bad_formation_config_is_one_sentence(table, what):
    with pytest.raises(InputError, match=what):
        config_from_dict({"formation": table})


def _psf_and_scale(cfg):
    """The fine PSF of `cfg`'s aperture (formation._fine_psf) and its sample step in µm on the sensor."""
    from mlaqc.optics.formation import _fine_psf, aperture_shape

    lam_um = cfg.geometry.wavelength_nm * 1e-3
    z_um = cfg.layout.sensor_gap_mm * 1e3 + 0.5 * cfg.mla.thickness_um
    psf, fine_px = _fine_psf(lam_um, z_um, cfg.sensor.pixel_um, cfg.mla.pitch_um, aperture_corner_radius_um(cfg),
                             aperture_shape(cfg), cfg.mla.aperture_diameter_um or 0.0)
    return psf, fine_px * cfg.sensor.pixel_um, lam_um, z_um


def test_circle_aperture_psf_is_the_airy_pattern():
    """A 90 µm circular aperture: I(r) / I(0) = (2 J1(k) / k)^2 with k = pi D r / (lambda z), first dark
    ring at 1.22 lambda z / D."""
    from scipy.special import j1

    cfg = config_from_dict({"mla": {"aperture": "circle", "aperture_diameter_um": 90.0}})
    psf, step_um, lam_um, z_um = _psf_and_scale(cfg)
    c = psf.shape[0] // 2
    r_um = np.arange(1, 40) * step_um
    k = np.pi * 90.0 * r_um / (lam_um * z_um)
    airy = (2 * j1(k) / k) ** 2
    for profile in (psf[c, c + 1:c + 40], psf[c + 1:c + 40, c]):  # along x and along y: round
        assert np.allclose(profile / psf[c, c], airy, rtol=0, atol=0.01)
    first = 1.22 * lam_um * z_um / 90.0
    ring = (r_um > 0.5 * first) & (r_um < 1.5 * first)
    zero = r_um[ring][np.argmin(psf[c, c + 1:c + 40][ring])]
    assert zero == pytest.approx(first, abs=step_um)


def test_hex_cell_psf_has_the_hexagons_sixfold_symmetry_and_differs_from_the_square():
    """The hexagonal cell's PSF is unchanged by rotations of 60° and 120° (the aperture is; the square's
    is not), and it is not the square cell's PSF."""
    from scipy.ndimage import map_coordinates

    cfg = config_from_dict({"mla": {"packing": "hex", "corners": "clear"}})
    psf, step_um, lam_um, z_um = _psf_and_scale(cfg)
    c = psf.shape[0] // 2
    rr, th = np.meshgrid(np.arange(2, 40, 0.5), np.radians(np.arange(0, 360, 7.5)))
    for turn in (60.0, 120.0):
        a = map_coordinates(psf, [c + rr * np.sin(th), c + rr * np.cos(th)], order=3)
        b = map_coordinates(psf, [c + rr * np.sin(th + np.radians(turn)), c + rr * np.cos(th + np.radians(turn))],
                            order=3)
        assert np.abs(a - b).max() < 0.02 * psf[c, c]
    square, _, _, _ = _psf_and_scale(_clear(CFG))
    assert np.abs(psf - square).max() > 0.05 * psf.max()
