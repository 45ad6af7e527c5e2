"""The projection fit behind the assembly readings: every found lens' measured sub-image centre against
its design centre projected through the camera's geometry.

The geometry (the tracer's, mlaqc/optics/raytrace.py `Camera`): lens U(m,n)'s design centre
on the MLA is its lattice position about the optical axis (`Lattice.centres`: square ((n - 1/2) p - N_W p / 2,
(m - 1/2) p - N_H p / 2); hex with its rows sqrt(3)/2 p apart and every other one shifted p/2). The
MLA is turned by R = Rz(-rotation) Ry(tilt_y) Rx(tilt_x) about its centre and shifted by (shift_x,
shift_y); the sensor sits f' + distance behind the MLA mid-plane (f' the design gap). A white sub-image's
centre is close to the projection of the lens' centre from the main lens' exit pupil (b in front of the
MLA) onto the sensor: the sub-image pitch is p (b + f')/b (the grid's scale reads the distance), a tilt
makes the local scale vary across the field (the grid's projective terms), a rotation turns the grid and
a shift moves it by shift (b + f')/b. A Gauss-Newton least-squares fit of this projection to every found
lens' measured centre gives six raw readings and their covariance (scaled by the residual variance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mlaqc.optics.lattice import Lattice
from mlaqc.optics.raytrace import _rotation

FIELDS = ("mla_sensor_distance_um", "mla_rotation_deg", "mla_tilt_x_deg", "mla_tilt_y_deg",
          "mla_shift_x_um", "mla_shift_y_um")
MIN_LENSES = 12
OUTLIER_FLOOR_PX = 1e-3  # the outlier cut's smallest spread: a noise-free frame keeps its lenses


@dataclass(frozen=True)
class Lenses:
    """The read lenses' design centres (mm) and what their projection onto the sensor needs."""

    xl: np.ndarray
    yl: np.ndarray
    pupil_mm: float
    gap_mm: float
    pixel_mm: float
    width: int
    height: int


def _project(params, lenses: Lenses):
    """Sub-image centres (pixels) of the lenses for params (distance µm, rot, tx, ty deg, sx, sy µm): the
    lens centre seen from the exit pupil's centre."""
    d, rot, tx, ty, sx, sy = params
    r = _rotation(tx, ty, -rot)  # the tracer's MLA rotation (Camera)
    xl, yl, b = lenses.xl, lenses.yl, lenses.pupil_mm
    x = r[0, 0] * xl + r[0, 1] * yl + sx * 1e-3
    y = r[1, 0] * xl + r[1, 1] * yl + sy * 1e-3
    z = r[2, 0] * xl + r[2, 1] * yl  # relative to the design MLA plane, towards the sensor
    t = (b + lenses.gap_mm + d * 1e-3) / (b + z) / lenses.pixel_mm  # pupil centre at (0, 0, -b)
    return x * t + 0.5 * lenses.width - 0.5, y * t + 0.5 * lenses.height - 0.5


def pupil_distance_mm(cfg) -> float:
    """Effective exit-pupil distance in front of the MLA. The calibrated disc centre is its rim's centre,
    so from MLA points at 1/4 and 1/2 of the array's half-width trace a fan over the main lens' rear
    aperture back through the real main lens (its two rims vignette, aberrations included), take the mid
    slope of the rays that get through, and b_eff = x / slope (paraxially: the rear principal plane, b)."""
    from mlaqc.optics.raytrace import MainLens, Rays

    lay = cfg.layout
    if cfg.main_lens.ideal:  # its exit pupil is where image-side rays start: exactly that distance
        return lay.pupil_to_mla_mm
    main = MainLens(cfg)
    half = 0.5 * cfg.main_lens.diameter_mm
    g = (np.arange(201) + 0.5) / 201 * 2 - 1
    ax, ay = (a.ravel() * half for a in np.meshgrid(g, g))
    inside = ax * ax + ay * ay <= half * half
    ax, ay = ax[inside], ay[inside]
    z_aim = cfg.main_lens.thickness_mm
    bs = []
    square = cfg.mla.packing == "square"
    width_mm = cfg.mla.count_w * cfg.mla.pitch_um * 1e-3 if square else Lattice.of(cfg).extent[0]
    for frac in (0.25, 0.5):
        xl = frac * width_mm
        dx, dy, dz = ax - xl, ay, np.full(ax.shape, z_aim - lay.z_mla_mm)
        norm = np.sqrt(dx * dx + dy * dy + dz * dz)
        r = Rays(np.full(ax.shape, xl), np.zeros(ax.shape), np.full(ax.shape, lay.z_mla_mm), dx / norm, dy / norm,
                 dz / norm, np.ones(ax.shape))
        main.trace_back(r)
        lit = np.nan_to_num(r.w) > 0
        sl = ((xl - ax) / (lay.z_mla_mm - z_aim))[lit]
        bs.append(xl / (0.5 * (sl.min() + sl.max())))
    return float(np.mean(bs))




def lens_centres(grid, cfg, pupil_mm: float) -> tuple[Lenses, np.ndarray, np.ndarray]:
    """The lenses fit to be read (found, whole) and their measured sub-image centres (px)."""
    mla, sensor = cfg.mla, cfg.sensor
    if mla.packing == "square":  # (the arithmetic the shipped assembly calibrations were read with)
        p = mla.pitch_um * 1e-3
        m, n = np.meshgrid(np.arange(grid.rows), np.arange(grid.cols), indexing="ij")
        xl = (n + 0.5) * p - 0.5 * mla.count_w * p
        yl = (m + 0.5) * p - 0.5 * mla.count_h * p
    else:
        xl, yl = Lattice.of(cfg).centres()
    # as the disc fit read them: the shipped calibrations take in each edge line's offset from the grid
    mx, my = grid.uncorrected_centres()
    ok = np.isfinite(mx) & np.isfinite(my) & ~np.asarray(grid.missing, bool) & ~np.asarray(grid.clipped, bool)
    lenses = Lenses(xl[ok], yl[ok], pupil_mm, cfg.layout.z_sensor_mm - cfg.layout.z_mla_mm, cfg.pixel_at_mla_um * 1e-3,
                    sensor.width_px, sensor.height_px)
    return lenses, mx[ok], my[ok]


def fit_projection(grid, cfg, pupil_mm: float):
    """Raw readings (6, FIELDS order), their covariance (6 x 6), lenses used (both coordinates within the
    outlier cut) and rms residual (px) of the projection fit to `grid`'s measured centres; None when too
    few lenses were found."""
    lenses, mx, my = lens_centres(grid, cfg, pupil_mm)
    if mx.size < MIN_LENSES:
        return None
    params = np.zeros(6)
    steps = np.array([1.0, 0.01, 0.05, 0.05, 1.0, 1.0])
    measured = np.concatenate([mx, my])
    keep = np.ones(measured.size, bool)
    for it in range(6):  # Gauss-Newton with a numeric Jacobian, then a 5-sigma outlier cut
        here = np.concatenate(_project(params, lenses))
        r = measured - here
        jac = np.empty((r.size, 6))
        for k in range(6):
            dp = params.copy()
            dp[k] += steps[k]
            jac[:, k] = (np.concatenate(_project(dp, lenses)) - here) / steps[k]
        delta, *_ = np.linalg.lstsq(jac[keep], r[keep], rcond=None)
        params = params + delta
        if it >= 2:
            r = measured - np.concatenate(_project(params, lenses))
            mad = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
            keep = np.abs(r) < 5 * max(mad, OUTLIER_FLOOR_PX)
    r = (measured - np.concatenate(_project(params, lenses)))[keep]
    var = float(r @ r) / max(r.size - 6, 1)
    cov = np.linalg.pinv(jac[keep].T @ jac[keep]) * var
    return params, cov, int((keep[:mx.size] & keep[mx.size:]).sum()), math.sqrt(var)


def focus_radius(grid) -> tuple[float, float]:
    """Median sub-image radius (px) of the found lenses and its 1-sigma (robust scatter / sqrt(N))."""
    r = np.asarray(grid.radius_px, float)
    r = r[np.isfinite(r) & ~np.asarray(grid.missing, bool) & ~np.asarray(grid.clipped, bool)]
    if r.size < MIN_LENSES:
        return float("nan"), float("nan")
    med = float(np.median(r))
    spread = 1.4826 * float(np.median(np.abs(r - med)))
    return med, 1.2533 * spread / math.sqrt(r.size)


def raw_components(grid, cfg, pupil_mm: float):
    """The raw components the assembly model calibrates: the projection fit's six readings and the median
    sub-image radius (7,), their covariance (7 x 7), lenses used and the fit's rms residual; None when too
    few lenses were found."""
    fit = fit_projection(grid, cfg, pupil_mm)
    if fit is None:
        return None
    params, cov, used, rms = fit
    r, r_sigma = focus_radius(grid)
    cov7 = np.zeros((7, 7))
    cov7[:6, :6] = cov
    cov7[6, 6] = r_sigma ** 2
    return np.append(params, r), cov7, used, rms
