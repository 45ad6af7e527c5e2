"""The MLA's assembly errors in physical units, read from the calibrated grid through the camera model.

Model (the tracer's, mlaqc/optics/raytrace.py `Camera`): lens U(m,n)'s design centre on the MLA is
(x_l, y_l) = ((n - 1/2) p - N_W p / 2, (m - 1/2) p - N_H p / 2) about the optical axis. The MLA is
turned by R = Rz(-rotation) Ry(tilt_y) Rx(tilt_x) about its centre and shifted by (shift_x, shift_y);
the sensor sits f' + distance behind the MLA mid-plane (f' the design gap). A white sub-image's centre
is the projection of the lens' centre from the main lens' exit pupil (b in front of the MLA) onto the
sensor, so the sub-image pitch is p (b + f')/b (the grid's scale reads the distance), a tilt makes the
local scale vary across the field (the grid's projective terms), a rotation turns the grid, and a shift
moves it by shift (b + f')/b. The six readings are a least-squares fit of this projection to every
found lens' measured centre; sigmas are the fit's covariance scaled by its residual variance.

Assumptions (stated once with the readings): main lens, MLA pitch and sensor (pixel size, sensor centred on
the optical axis) at their design values; the exit pupil is where the rim centre of the ray fan reaching a
lens comes from through the real main lens (`pupil_distance_mm`); the shift is the MLA centre's offset
from the sensor centre (zero = design position); the distance is the change of the MLA-sensor gap from
its design value. The sigmas are statistical only: on rendered Table 1 frames the distance reads about
+2.3 µm high at every size (the pupil model's zero point) and the tilts 3-6 % high, far above their sigma.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FIELDS = ("mla_sensor_distance_um", "mla_rotation_deg", "mla_tilt_x_deg", "mla_tilt_y_deg",
          "mla_shift_x_um", "mla_shift_y_um")
UNITS = {"mla_sensor_distance_um": "µm", "mla_rotation_deg": "deg", "mla_tilt_x_deg": "deg",
         "mla_tilt_y_deg": "deg", "mla_shift_x_um": "µm", "mla_shift_y_um": "µm"}
ASSUMPTIONS = ("main lens, MLA pitch and sensor (pixel size, centred on the optical axis) at their design values, "
               "exit pupil from the traced main lens; sigmas statistical only (a pupil-model bias of about +2 µm "
               "in distance is not in them); distance = change of the MLA-sensor gap from design; shift = MLA centre "
               "against the sensor centre (zero: design position); rotation about the optical axis, tilts about "
               "the sensor's x (right) and y (down) axes; read from the calibrated grid's lens centres")
# QC keys ([qc]) bounding each reading (absolute value; tilt and shift bound both components)
QC_KEYS = {"mla_sensor_distance_um": "assembly_distance_um", "mla_rotation_deg": "assembly_rotation_deg",
           "mla_tilt_x_deg": "assembly_tilt_deg", "mla_tilt_y_deg": "assembly_tilt_deg",
           "mla_shift_x_um": "assembly_shift_um", "mla_shift_y_um": "assembly_shift_um"}


@dataclass(frozen=True)
class Assembly:
    """The six global readings (error-map units) with their 1-sigma uncertainties."""

    mla_sensor_distance_um: float
    mla_rotation_deg: float
    mla_tilt_x_deg: float
    mla_tilt_y_deg: float
    mla_shift_x_um: float
    mla_shift_y_um: float
    sigma: dict  # field -> 1-sigma
    lenses_used: int = 0
    rms_residual_px: float = float("nan")

    def value(self, name: str) -> float:
        return float(getattr(self, name))

    def to_json_dict(self) -> dict:
        out = {k: {"value": _num(self.value(k)), "sigma": _num(self.sigma[k])} for k in FIELDS}
        out["assumptions"] = ASSUMPTIONS
        out["lenses_used"] = int(self.lenses_used)
        return out

    def out_of_bounds(self, qc) -> list[str]:
        """One line per reading beyond its `[qc]` bound (bounds None: unbounded)."""
        lines = []
        for k in FIELDS:
            bound = getattr(qc, QC_KEYS[k], None)
            v = self.value(k)
            if bound is not None and math.isfinite(v) and abs(v) > bound:
                lines.append(f"assembly {k} = {v:+.4g} {UNITS[k]} exceeds qc.{QC_KEYS[k]} = {bound:g}")
        return lines

    def summary_line(self) -> str:
        s = self.sigma
        return (f"  assembly: distance {self.mla_sensor_distance_um:+.2f} ± {s['mla_sensor_distance_um']:.2f} µm, "
                f"rotation {self.mla_rotation_deg:+.4f} ± {s['mla_rotation_deg']:.4f} deg, "
                f"tilt {self.mla_tilt_x_deg:+.3f} ± {s['mla_tilt_x_deg']:.3f} / "
                f"{self.mla_tilt_y_deg:+.3f} ± {s['mla_tilt_y_deg']:.3f} deg, "
                f"shift {self.mla_shift_x_um:+.2f} ± {s['mla_shift_x_um']:.2f} / "
                f"{self.mla_shift_y_um:+.2f} ± {s['mla_shift_y_um']:.2f} µm")


def _num(v: float):
    return float(v) if math.isfinite(v) else None


def _rot(rx, ry, rz):
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    mx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    my = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    mz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return mz @ my @ mx


def _project(params, xl, yl, b, gap, pixel, width, height):
    """Sub-image centres (pixels) of design lens centres (mm) for params (distance µm, rot, tx, ty deg, sx, sy µm)."""
    d, rot, tx, ty, sx, sy = params
    r = _rot(math.radians(tx), math.radians(ty), -math.radians(rot))
    x = r[0, 0] * xl + r[0, 1] * yl + sx * 1e-3
    y = r[1, 0] * xl + r[1, 1] * yl + sy * 1e-3
    z = r[2, 0] * xl + r[2, 1] * yl  # relative to the design MLA plane
    t = (b + gap + d * 1e-3) / (b + z)  # pupil centre at (0, 0, -b)
    xs, ys = x * t, y * t
    return xs / pixel + 0.5 * width - 0.5, ys / pixel + 0.5 * height - 0.5


def pupil_distance_mm(cfg) -> float:
    """Effective exit-pupil distance in front of the MLA. The calibrated disc centre is its rim's centre,
    so from MLA points at 1/4 and 1/2 of the array's half-width trace a fan over the main lens' rear
    aperture back through the real main lens (its two rims vignette, aberrations included), take the mid
    slope of the rays that get through, and b_eff = x / slope (paraxially: the rear principal plane, b)."""
    from mlaqc.optics.raytrace import MainLens, Rays

    lay = cfg.layout
    main = MainLens(cfg)
    half = 0.5 * cfg.main_lens.diameter_mm
    g = (np.arange(201) + 0.5) / 201 * 2 - 1
    ax, ay = (a.ravel() * half for a in np.meshgrid(g, g))
    inside = ax * ax + ay * ay <= half * half
    ax, ay = ax[inside], ay[inside]
    z_aim = cfg.main_lens.thickness_mm
    bs = []
    for frac in (0.25, 0.5):
        xl = frac * cfg.mla.count_w * cfg.mla.pitch_um * 1e-3
        dx, dy, dz = ax - xl, ay, np.full(ax.shape, z_aim - lay.z_mla_mm)
        norm = np.sqrt(dx * dx + dy * dy + dz * dz)
        r = Rays(np.full(ax.shape, xl), np.zeros(ax.shape), np.full(ax.shape, lay.z_mla_mm), dx / norm, dy / norm,
                 dz / norm, np.ones(ax.shape))
        main.trace_back(r)
        lit = np.nan_to_num(r.w) > 0
        sl = ((xl - ax) / (lay.z_mla_mm - z_aim))[lit]
        bs.append(xl / (0.5 * (sl.min() + sl.max())))
    return float(np.mean(bs))


def measure_assembly(grid, cfg) -> Assembly:
    """The six assembly readings from a calibrated `grid` (mlaqc.inspection.calibrate.Grid) of `cfg`'s camera."""
    lay = cfg.layout
    mla, s = cfg.mla, cfg.sensor
    b = pupil_distance_mm(cfg)
    gap = lay.z_sensor_mm - lay.z_mla_mm
    p = mla.pitch_um * 1e-3
    pixel = s.pixel_um * 1e-3
    rows, cols = grid.shape
    m, n = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    xl = (n + 0.5) * p - 0.5 * mla.count_w * p
    yl = (m + 0.5) * p - 0.5 * mla.count_h * p
    mx, my = np.asarray(grid.measured_x_px, float), np.asarray(grid.measured_y_px, float)
    ok = np.isfinite(mx) & np.isfinite(my) & ~np.asarray(grid.missing, bool) & ~np.asarray(grid.clipped, bool)
    if rows == mla.count_h and cols == mla.count_w and ok.sum() >= 12:
        xl, yl, mx, my = xl[ok], yl[ok], mx[ok], my[ok]
    else:
        nan = float("nan")
        return Assembly(nan, nan, nan, nan, nan, nan, {k: nan for k in FIELDS}, 0)
    args = (xl, yl, b, gap, pixel, s.width_px, s.height_px)
    # the design camera's own projection is the zero reference: the model is linearised about it
    x0, y0 = _project(np.zeros(6), *args)
    resid_target = np.concatenate([mx - x0, my - y0])
    params = np.zeros(6)
    steps = np.array([1.0, 0.01, 0.05, 0.05, 1.0, 1.0])
    keep = np.ones(resid_target.size, bool)
    for it in range(6):  # Gauss-Newton with a numeric Jacobian, then a 5-sigma outlier cut
        px, py = _project(params, *args)
        r = np.concatenate([mx - px, my - py])
        jac = np.empty((r.size, 6))
        for k in range(6):
            dp = params.copy()
            dp[k] += steps[k]
            qx, qy = _project(dp, *args)
            jac[:, k] = (np.concatenate([qx, qy]) - np.concatenate([px, py])) / steps[k]
        delta, *_ = np.linalg.lstsq(jac[keep], r[keep], rcond=None)
        params = params + delta
        if it >= 2:
            px, py = _project(params, *args)
            r = np.concatenate([mx - px, my - py])
            mad = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
            keep = np.abs(r) < 5 * max(mad, 1e-6)
    px, py = _project(params, *args)
    r = np.concatenate([mx - px, my - py])[keep]
    dof = max(r.size - 6, 1)
    var = float(r @ r) / dof
    cov = np.linalg.pinv(jac[keep].T @ jac[keep]) * var
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    return Assembly(*(float(v) for v in params), sigma=dict(zip(FIELDS, (float(v) for v in sig))),
                    lenses_used=int(ok.sum()), rms_residual_px=math.sqrt(var))
