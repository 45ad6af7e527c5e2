"""Sensor model: expected photons per pixel -> raw digital numbers (QE, shot noise, full well, read
noise, gain, black level, bit depth, optional Bayer CFA), reproducible from a seed."""

from __future__ import annotations

import numpy as np

from mlaqc.optics.config import Sensor

_CFA_INDEX = {"R": 0, "G": 1, "B": 2}


def cfa_site_colours(cfa: str, height: int, width: int) -> np.ndarray:
    """(H, W) array of colour indices (0=R, 1=G, 2=B) for a 2x2 pattern such as 'RGGB' (top-left first)."""
    tile = np.array([[_CFA_INDEX[cfa[0]], _CFA_INDEX[cfa[1]]], [_CFA_INDEX[cfa[2]], _CFA_INDEX[cfa[3]]]])
    return np.tile(tile, ((height + 1) // 2, (width + 1) // 2))[:height, :width]


def qe_map(sensor: Sensor, height: int, width: int) -> np.ndarray | float:
    """Quantum efficiency per pixel: a scalar for a monochrome sensor, per CFA site otherwise."""
    if sensor.cfa == "none":
        return sensor.qe
    return np.asarray(sensor.cfa_qe)[cfa_site_colours(sensor.cfa, height, width)]


def expose(photons: np.ndarray, sensor: Sensor, seed: int | None, noise: bool = True) -> np.ndarray:
    """Convert expected photons per pixel to raw counts (uint16) as the sensor would read them out.

    With noise=False the result is the rounded expectation (no shot or read noise): the ideal frame.
    """
    electrons = photons * qe_map(sensor, *photons.shape)
    if noise:
        rng = np.random.default_rng(seed)
        electrons = rng.poisson(electrons).astype(np.float64)
    electrons = np.minimum(electrons, sensor.full_well_e)
    if noise and sensor.read_noise_e > 0:
        electrons += rng.normal(0.0, sensor.read_noise_e, electrons.shape)
    dn = np.rint(electrons * sensor.gain_dn_per_e + sensor.black_level_dn)
    return np.clip(dn, 0, white_level(sensor)).astype(np.uint16)  # saturated pixels read the white level


def white_level(sensor: Sensor) -> int:
    """The clip level of the raw counts (saturation in the raw file).

    Set 3 sigma of read noise below full well, as camera makers set their white point, so a saturated
    pixel always reads exactly this value; never above the ADC's range."""
    top = (sensor.full_well_e - 3.0 * sensor.read_noise_e) * sensor.gain_dn_per_e + sensor.black_level_dn
    return int(min(2 ** sensor.bit_depth - 1, np.floor(top)))
