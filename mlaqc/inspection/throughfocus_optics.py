"""The camera's first-order facts the through-focus reading uses (`Optics`), the lit aperture's moment and Δf/f of a radius error."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np

from mlaqc.optics.config import CameraConfig
from mlaqc.optics.formation import aperture_corner_radius_um
from mlaqc.optics.lattice import hex_edge
from mlaqc.optics.paraxial import thick_lens
from mlaqc.optics.sensor import white_level

@dataclass(frozen=True)
class Optics:
    """What the analysis needs of the camera: distances in mm, the aperture's moment in px^2."""

    s_mm: float  # rear principal plane to sensor
    front_to_mid_mm: float  # front principal plane to the MLA mid-plane (u is measured from the mid-plane)
    pupil_mm: float  # main lens' rear principal plane to the MLA mid-plane (white sub-image centres)
    pixel_mm: float
    aperture_i_px2: float  # per-axis second moment of the lit aperture, in sensor px^2 (unscaled)
    c0: float  # 1 - s P of the design lens
    e_per_unit: float  # electrons per normalized unit (white - black level) of a prepared frame

    def u_prime(self, u_mm: float) -> float:
        return u_mm + self.front_to_mid_mm

    def g(self, u_mm: float) -> float:
        return self.s_mm / abs(self.u_prime(u_mm))


@functools.lru_cache(maxsize=8)
def optics(cfg: CameraConfig) -> Optics:
    """The first-order facts of `cfg` the reading uses."""
    lay, mla, s = cfg.layout, cfg.mla, cfg.sensor
    micro = lay.micro
    s_mm = lay.sensor_gap_mm + micro.rear_principal  # H' lies rear_principal before the rear vertex
    pixel_mm = cfg.pixel_at_mla_um * 1e-3
    span = white_level(s) - s.black_level_dn
    return Optics(s_mm=s_mm, front_to_mid_mm=0.5 * mla.thickness_um * 1e-3 - micro.front_principal,
                  pupil_mm=lay.pupil_to_mla_mm, pixel_mm=pixel_mm,
                  aperture_i_px2=aperture_moment_mm2(cfg) / pixel_mm ** 2, c0=1.0 - s_mm / micro.efl,
                  e_per_unit=span / s.gain_dn_per_e)


def aperture_moment_mm2(cfg: CameraConfig, samples: int = 801) -> float:
    """Per-axis second moment (mm^2, about its centre) of one lens' lit aperture: its cell (less the black
    matrix) or its circular aperture, where both surfaces exist (inside the radius where they cross). With
    'clear' corners or gaps the light through them passes unfocused and lands outside the spot, so the spot
    is made by the same aperture."""
    mla = cfg.mla
    r_um = aperture_corner_radius_um(replace(cfg, mla=replace(mla, corners="opaque")))
    if mla.packing == "hex":
        half = mla.pitch_um / math.sqrt(3.0)  # the hexagon's corner (its flats are half a pitch out)
    elif mla.aperture == "circle":
        half = 0.5 * mla.pitch_um
    else:
        half = 0.5 * (mla.pitch_um - mla.black_matrix_um)  # the square box is the cell
    x = (np.arange(samples) + 0.5) / samples * 2 * half - half
    xx, yy = np.meshgrid(x, x)
    inside = xx * xx + yy * yy <= r_um * r_um
    if mla.aperture == "circle":
        inside &= np.hypot(xx, yy) <= 0.5 * mla.aperture_diameter_um
    elif mla.packing == "hex":
        inside &= hex_edge(xx / mla.pitch_um, yy / mla.pitch_um) >= 0.5 * mla.black_matrix_um / mla.pitch_um
    return float(np.sum(xx[inside] ** 2) / inside.sum()) * 1e-6


def focal_rel_of_radius(cfg: CameraConfig, radius_rel) -> np.ndarray:
    """Δf/f of the microlens with both radii scaled by 1 + radius_rel, thickness kept (thick-lens power)."""
    m = cfg.mla
    k = 1.0 + np.asarray(radius_rel, dtype=np.float64)
    f = thick_lens(m.radius_front_um * k, m.radius_back_um * k, m.thickness_um, m.refractive_index).efl
    return f / thick_lens(m.radius_front_um, m.radius_back_um, m.thickness_um, m.refractive_index).efl - 1.0


__all__ = ["optics", "aperture_moment_mm2", "focal_rel_of_radius"]
