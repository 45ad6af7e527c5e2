"""Through-focus analysis: every microlens' focal-length error, with its sign, from +u / -u pinhole frames
(the protocol: mlaqc.optics.throughfocus), and its optical-centre displacement from the spot positions.

Physics. Lens power P = 1/f', sensor a distance s behind its rear principal plane. A pinhole imaged u'
behind the lens' front principal plane (u' < 0: in front) sends it a wave of vergence 1/u'; leaving the
lens the vergence is V = P + 1/u', and the ray at aperture height h lands h (1 - s V) from the spot's
centre. The geometric spot is the lit aperture (the square cell less the corners where the two
surfaces cross) scaled by c - g (+u frame) or c + g (-u frame), c = 1 - s P the lens' own defocus,
g = s / |u'|. Its second moment (x + y) is 2 I (c -/+ g)^2 + floor, I the aperture's per-axis second
moment, the floor the blur the lens' defocus does not change (diffraction, pixel, crosstalk). Measured in
the same window in both frames the floor cancels in the difference

    D = m2(+) - m2(-) = 2 I [g+^2 - g-^2 - 2 c (g+ + g-)]

which is linear in c: the paraxial gain dD/dc = -4 I (g+ + g-). Spherical aberration adds a |h|^2 h
term to each ray: the microlens' own shifts D alike for all lenses, but it changes with the lens' radius,
so it also steepens the slope (Table 1: D moves 8-10 % more than the paraxial defocus alone, traced: the
"gain"); the main lens' matters when a lenslet spans much of the pinhole's disc (1.45x at u = 3 mm) and
makes g vary over the disc; off the axis its field curvature and astigmatism move the typical lens' D
(Table 1 at u = 5 mm: by the equivalent of 1.4 % of focal length at the array's corner). All three come
from the camera's own optics: `model_curves` traces a pinhole through the config's main lens and an MLA
whose lenses all carry a radius error eps, and takes the exact geometric second moments of one lens per
shell (lenses at the same distance from their pinhole), D(eps) on the axis and D(0) at four field radii.
A lens' reading is its D, less the model's field offset for its disc and orientation, against the
typical lens of its shell (the median over every disc and pair of that |u|), inverted on the model's
D(eps) - D(0) and turned into Δf/f by the thick-lens power of a lens with both radii scaled by 1 + eps
(as the white frame's `measure_lenses` reports). The typical lens is the reference, as there: the MLA's
slow trend over the array is kept, a defocus common to all lenses (the sensor distance) is not read.
`model="paraxial"` reads on the paraxial D instead (spots that are scaled apertures: no aberrations).

Pixel sampling. A spot of about a pixel (Table 1, f/8: 1-2 px at u = ±10 mm, 1-2.5 px at ±5 mm) is
undersampled: its measured second moment depends on where it falls on the pixel grid, by up to about
±0.1 px^2 per axis, the scale of 1 % of focal length at u = 10 mm. What that does to the typical spots
is fitted (the first Fourier harmonic of each frame's sub-pixel phases, over all lenses of that |u|,
robustly) and removed, with the amplitude of each spot's own size (interpolated between the typical +u
and -u spots, whose sizes differ: a lens whose error swaps them gets the other frame's pattern). What is
left is smaller at small |u| (larger spots, and more signal per unit of focal error): u = ±5 mm reads
2-3x more accurately than ±10 mm (bench/throughfocus_accuracy.py).

Measurement. Each lens' spot is found in its sub-image window (the white frame's grid): the brightest
3 x 3 sum, then the centroid and second moment in a square window of half-width WINDOW_SIGMAS sigma (at
least MIN_WINDOW_PX) around the centroid, iterated, background (the median of the window's outer ring)
subtracted. Window edges weigh pixels by the share of them inside, so the moments move smoothly with the
spot. Both frames of a lens use one window (the larger), so the floor cancels. Lenses not fully lit in
both frames (nearer the disc's traced rim than RIM_MARGIN_LENSES), saturated, off the sensor or unlit are
left out of that pair; a lens read in several pairs gets their inverse-variance mean.

Frames: prepare them with `prepare_spots` (black-subtracted and normalized, nothing else): the pipeline's
`prepare` suppresses hot pixels, and a focused spot's peak is one to it.

Uncertainty: the moments' shot and read noise (the sensor's electrons per unit from the config, the read
noise from the frame's unlit pixels), propagated; scaled up (never down) by a Birge ratio, the robust
spread of the readings of each |u| over their sigmas, so that what the noise model leaves out (pixel
sampling, a render's Monte-Carlo noise) is counted.

Optical centre (Shack-Hartmann): a lens' spot centroid moves by d s P (d its optical-centre shift, s P =
1 - c0 ≈ 1) whatever u is. It is read against the paraxial chief ray (through the lens' centre from the
pinhole's image, against the white sub-image centre), the typical lens at the same (dx, dy) from its
pinhole (the main lens' aberrations) and a smooth field over the frame's pinhole positions (the mask's
placement, the main lens' distortion), averaged over the frames.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import ndimage

from mlaqc.errors import InputError
from mlaqc.inspection.calibrate import Grid
from mlaqc.inspection.rawio import RawFrame, check_exposure, normalized
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.formation import aperture_corner_radius_um
from mlaqc.optics.paraxial import thick_lens
from mlaqc.optics.sensor import white_level
from mlaqc.optics.throughfocus import (RIM_MARGIN_LENSES, ThroughFocus, frame_config, inner_radius_lenses,  # noqa: F401
                                      lens_centres_mm, pair_radius_lenses, pinhole_lenses)

WINDOW_SIGMAS = 4.0  # moment window half-width, in the spot's per-axis rms
MIN_WINDOW_PX = 2.0  # never narrower: a spot smaller than a pixel still has the pixel's own width
MIN_FLUX = 0.25  # a spot with less than this share of the pair's median flux is not read (no lens there)
SATURATED = 0.999  # a prepared (normalized) pixel at or above this is at the white level
RING_PX = 2  # the sub-image window's outer ring this wide gives the background
MIN_SHELL_LENSES = 5  # a shell's reference needs this many lenses (else the |u| group's median)
PHASE_MIN_LENSES = 12  # the phase-pattern fit needs this many lenses per fitted term
MODEL_EPS = (-0.10, -0.05, 0.0, 0.05, 0.10)  # radius errors the model curve is traced at
MODEL_RAYS = 1_000_000  # pupil rays per frame of the model (only those reaching a shell's lens are traced on)


def prepare_spots(frame: RawFrame) -> np.ndarray:
    """A through-focus frame for `measure_through_focus`: black-subtracted, normalized float32 (CFA sites
    balanced), without the hot-pixel pass of `pipeline.prepare` (which takes a focused spot's peak pixel
    for a hot pixel and cuts it)."""
    return normalized(frame).astype(np.float32, copy=False)


# ---------------------------------------------------------------------------------------------- results

# per-lens readings as lenses.csv / report.json name them: column -> (ThroughFocusResult field, unit, meaning)
TF_MEASUREMENTS: dict[str, tuple[str, str, str]] = {
    "tf_focal_rel": ("focal_rel", "1", "focal-length error Δf/f from the through-focus pinhole pairs, vs the typical lens"),
    "tf_focal_sigma_rel": ("focal_sigma_rel", "1", "1-sigma uncertainty of tf_focal_rel"),
    "tf_radius_rel": ("radius_rel", "1", "the same reading as the radius error (both radii scaled) it equals"),
    "tf_centre_dx_um": ("centre_dx_um", "µm", "optical-centre displacement along x from the spot positions (Shack-Hartmann)"),
    "tf_centre_dy_um": ("centre_dy_um", "µm", "optical-centre displacement along y (down) from the spot positions"),
    "tf_centre_sigma_um": ("centre_sigma_um", "µm", "1-sigma uncertainty of each tf centre component"),
}



@dataclass(frozen=True)
class PairReading:
    """One +u / -u pair: what it read and the figures it was read with."""

    focus_offset_mm: float  # |u|
    offset_lenses: tuple[int, int]
    lenses: int  # lenses read in this pair
    g_plus: float  # s / |u'| of the +u frame
    g_minus: float
    gain: float  # the traced model's dD/dc over the paraxial -4 I (g+ + g-), at the design lens
    birge: float  # the sigma scale (>= 1) of this |u|'s readings
    window_px: float  # median moment window half-width
    saturated: int  # lenses left out because a pixel of their spot was saturated


@dataclass(frozen=True)
class ThroughFocusResult:
    """Per-lens (rows, cols) arrays; NaN (or False) where a lens was not read."""

    focal_rel: np.ndarray  # Δf/f against the array's typical lens
    focal_sigma_rel: np.ndarray  # its 1-sigma
    radius_rel: np.ndarray  # the reading as the radius error (both radii scaled by 1 + eps) it equals
    covered: np.ndarray  # bool: read in at least one pair
    delta_px2: np.ndarray  # D - D(typical lens of its shell), px^2, phase pattern removed (mean over pairs)
    centre_dx_um: np.ndarray  # optical-centre displacement, x right, MLA plane, vs the typical lens
    centre_dy_um: np.ndarray  # y down
    centre_sigma_um: np.ndarray  # 1-sigma of each component
    pairs: tuple[PairReading, ...]
    focal_length_um: float  # the design microlens' effective focal length
    timings_s: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """Array-wide figures: coverage, median focal error and sigma, and each pair's figures."""
        ok = self.covered & np.isfinite(self.focal_rel)

        def num(x) -> float | None:
            return float(x) if x is not None and np.isfinite(x) else None

        return {"lenses_covered": int(ok.sum()), "coverage": float(ok.mean()),
                "focal_rel_median": num(np.median(self.focal_rel[ok])) if ok.any() else None,
                "focal_sigma_rel_median": num(np.median(self.focal_sigma_rel[ok])) if ok.any() else None,
                "centre_sigma_um_median": (num(np.nanmedian(self.centre_sigma_um))
                                           if np.isfinite(self.centre_sigma_um).any() else None),
                "focal_length_um": self.focal_length_um,
                "pairs": [{"u_mm": p.focus_offset_mm, "offset": list(p.offset_lenses), "lenses": p.lenses,
                           "gain": p.gain, "birge": p.birge, "window_px": p.window_px,
                           "saturated": p.saturated} for p in self.pairs]}


# ---------------------------------------------------------------------------------------------- optics


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
    pixel_mm = s.pixel_um * 1e-3
    span = white_level(s) - s.black_level_dn
    return Optics(s_mm=s_mm, front_to_mid_mm=0.5 * mla.thickness_um * 1e-3 - micro.front_principal,
                  pupil_mm=lay.pupil_to_mla_mm, pixel_mm=pixel_mm,
                  aperture_i_px2=aperture_moment_mm2(cfg) / pixel_mm ** 2, c0=1.0 - s_mm / micro.efl,
                  e_per_unit=span / s.gain_dn_per_e)


def aperture_moment_mm2(cfg: CameraConfig, samples: int = 801) -> float:
    """Per-axis second moment (mm^2, about its centre) of one lens' lit aperture: the square cell (less
    the black matrix) where both surfaces exist (inside the radius where they cross). With 'clear'
    corners the light through the corners passes unfocused and lands outside the spot, so the spot is
    made by the same aperture."""
    mla = cfg.mla
    r_um = aperture_corner_radius_um(replace(cfg, mla=replace(mla, corners="opaque")))
    half = 0.5 * (mla.pitch_um - mla.black_matrix_um)
    x = (np.arange(samples) + 0.5) / samples * 2 * half - half
    xx, yy = np.meshgrid(x, x)
    inside = xx * xx + yy * yy <= r_um * r_um
    return float(np.sum(xx[inside] ** 2) / inside.sum()) * 1e-6


def focal_rel_of_radius(cfg: CameraConfig, radius_rel) -> np.ndarray:
    """Δf/f of the microlens with both radii scaled by 1 + radius_rel, thickness kept (thick-lens power)."""
    m = cfg.mla
    k = 1.0 + np.asarray(radius_rel, dtype=np.float64)
    f = thick_lens(m.radius_front_um * k, m.radius_back_um * k, m.thickness_um, m.refractive_index).efl
    return f / thick_lens(m.radius_front_um, m.radius_back_um, m.thickness_um, m.refractive_index).efl - 1.0


# --------------------------------------------------------------------------------------- model curves


@dataclass(frozen=True)
class ModelCurves:
    """The traced (or paraxial) D of the typical lens, per shell (squared distance from its pinhole, in
    lenses): D(eps) - D(0) in px^2 at MODEL_EPS on the axis, and how D(0) changes over the field: at
    field radius r, D(0; r) - D(0; 0) = a(r) + b(r) cos 2 phi, phi the angle between the lens' offset
    from its pinhole and the field direction (the main lens' field curvature and astigmatism)."""

    eps: np.ndarray
    shells: np.ndarray  # (S,) int
    curves: np.ndarray  # (S, E) px^2
    gain: float  # the centre shell's slope at eps = 0 over the paraxial one
    field_mm: np.ndarray = field(default_factory=lambda: np.zeros(1))  # (R,) field radii, from 0
    field_a: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))  # (S, R) px^2
    field_b: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))  # (S, R) px^2

    def field_offset(self, shell: np.ndarray, dxy: np.ndarray, pin_mm: np.ndarray) -> np.ndarray:
        """D(0) of each lens' disc position and orientation minus its shell's on-axis D(0), px^2."""
        k = np.abs(shell[:, None] - self.shells[None, :]).argmin(axis=1)
        r = np.hypot(pin_mm[:, 0], pin_mm[:, 1])
        a, b = np.zeros(len(r)), np.zeros(len(r))
        for j in np.unique(k):  # a few shells
            sel = k == j
            a[sel] = np.interp(r[sel] ** 2, self.field_mm ** 2, self.field_a[j])
            b[sel] = np.interp(r[sel] ** 2, self.field_mm ** 2, self.field_b[j])
        d2 = (dxy[:, 0] ** 2 + dxy[:, 1] ** 2).astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            along = (dxy[:, 0] * pin_mm[:, 0] + dxy[:, 1] * pin_mm[:, 1]) ** 2
            cos2 = np.where((d2 > 0) & (r > 0), 2.0 * along / (d2 * r * r) - 1.0, 0.0)
        return a + b * cos2


def model_curves(cfg: CameraConfig, u_mm: float, f_number: float, r_in: float) -> ModelCurves:
    """The geometric D of the camera's lenses, shell by shell out to `r_in` lenses, traced: D(eps) on the
    axis and D(0) over the field (cached per camera and pair geometry; a few seconds)."""
    return _model_curves(cfg, abs(float(u_mm)), float(f_number), round(max(float(r_in), 0.0), 4))


SPOT_REACH_MM = 0.03  # a model spot's rays are those within this of its centroid (|1 - sV| <= 0.5)
FIELD_POINTS = 4  # field radii the model's D(0) is traced at, 0 to the array's corner, even in r^2


def _trace_moments(patch: CameraConfig, tf: ThroughFocus, field_mm: float, targets: np.ndarray, eps: np.ndarray,
                   rays: int) -> np.ndarray:
    """(E, T) geometric second moments x + y (mm^2) of the spots of lenses `targets` (flat indices of the
    patch MLA, whose centre lens sits `field_mm` along x from the axis, under the pinhole there) for
    every lens of the MLA carrying the radius error eps."""
    targets, back = np.unique(targets, return_inverse=True)
    from mlaqc.optics import lowdisc
    from mlaqc.optics.errormap import ErrorMap
    from mlaqc.optics.raytrace import Camera, MicrolensArray, Rays
    from mlaqc.optics.render import source_region
    from mlaqc.optics.scene import sample_points
    from mlaqc.optics.throughfocus import magnification

    n = patch.mla.count_w
    zero = ErrorMap.zeros(n, n).with_globals(mla_shift_x_um=1e3 * field_mm)
    fc = frame_config(patch, tf)
    cam = Camera(fc, zero)
    x_obj = -field_mm / magnification(fc)  # the main lens inverts
    r = sample_points(source_region(cam), lowdisc.batch_uniforms(0x7F0C, rays, 2), x_obj, 0.0, square=True)
    cam.main.trace(r)
    cam.to_mla(r)
    zf = cam.mla.z_front
    with np.errstate(invalid="ignore", divide="ignore"):
        cell, on = cam.mla.cell_of(r.x + (zf - r.z) * r.L / r.N, r.y + (zf - r.z) * r.M / r.N)
    keep = on & (r.w > 0) & np.isin(cell, targets)
    lens = np.searchsorted(targets, cell[keep])
    base = [a[keep] for a in (r.x, r.y, r.z, r.L, r.M, r.N, r.w)]
    out = np.zeros((len(eps), len(targets)))
    for j, e in enumerate(eps):
        em = ErrorMap(zero.shape, {**zero.lens, "radius_front_rel": np.full((n, n), e),
                                   "radius_back_rel": np.full((n, n), e)}, zero.globals)
        rr = Rays(*(a.copy() for a in base))
        MicrolensArray(fc, em).trace(rr)
        t = (cam.z_sensor - cam.z_mla - rr.z) / rr.N
        w = np.where(np.isfinite(rr.w) & np.isfinite(t), rr.w, 0.0)
        x, y = np.where(w > 0, rr.x + t * rr.L, 0.0), np.where(w > 0, rr.y + t * rr.M, 0.0)
        for cut in (True, False):  # a ray the vertex-plane cell gave to the wrong lens lands a pitch away
            sw = np.bincount(lens, w, len(targets))
            mx, my = np.bincount(lens, w * x, len(targets)) / sw, np.bincount(lens, w * y, len(targets)) / sw
            dx, dy = x - mx[lens], y - my[lens]
            if cut:
                w = np.where((np.abs(dx) < SPOT_REACH_MM) & (np.abs(dy) < SPOT_REACH_MM), w, 0.0)
        out[j] = np.bincount(lens, w * (dx * dx + dy * dy), len(targets)) / sw
    return out[:, back]


@functools.lru_cache(maxsize=16)
def _model_curves(cfg: CameraConfig, u_mm: float, f_number: float, r_in: float) -> ModelCurves:
    from mlaqc.models.signatures import patch_config

    reach = int(math.floor(r_in))
    n = 2 * reach + 3
    patch = patch_config(cfg, n)  # the pinhole's image on the centre lens
    opt = optics(cfg)
    # one lens per shell, (a, b) with a >= b >= 0 (a along x), and its mirror (b, a) for the field's
    # orientation term
    uniq = {}
    for a in range(reach + 1):
        for b in range(a + 1):
            if a * a + b * b <= r_in * r_in:
                uniq.setdefault(a * a + b * b, (a, b))
    shells = np.array(sorted(uniq))
    c = n // 2
    along = np.array([(c + uniq[s][1]) * n + (c + uniq[s][0]) for s in shells])  # row c + b, col c + a
    across = np.array([(c + uniq[s][0]) * n + (c + uniq[s][1]) for s in shells])
    eps = np.array(MODEL_EPS)
    zero = int(np.flatnonzero(eps == 0.0)[0])
    tf = ThroughFocus(focus_offset_mm=u_mm, f_number=f_number)
    plus, minus = replace(tf, focus_offset_mm=u_mm), replace(tf, focus_offset_mm=-u_mm)
    d = (_trace_moments(patch, plus, 0.0, along, eps, MODEL_RAYS)
         - _trace_moments(patch, minus, 0.0, along, eps, MODEL_RAYS)).T / opt.pixel_mm ** 2  # (S, E)
    curves = d - d[:, zero:zero + 1]
    slope = (curves[0, zero + 1] - curves[0, zero - 1]) / (eps[zero + 1] - eps[zero - 1])
    dc = (focal_rel_of_radius(cfg, eps[zero + 1]) - focal_rel_of_radius(cfg, eps[zero - 1])) \
        / (eps[zero + 1] - eps[zero - 1]) * (1.0 - opt.c0)  # dc/deps of c = 1 - s P at the design lens
    paraxial = -4.0 * opt.aperture_i_px2 * (opt.g(u_mm) + opt.g(-u_mm)) * dc
    # D(0) over the field: field curvature and astigmatism of the main lens
    p = cfg.mla.pitch_um * 1e-3
    corner = 0.5 * p * math.hypot(cfg.mla.count_w - 1, cfg.mla.count_h - 1)
    radii = corner * np.sqrt(np.linspace(0.0, 1.0, FIELD_POINTS))
    both = np.concatenate([along, across])
    d0 = np.zeros((len(radii), 2 * len(shells)))
    for i, rf in enumerate(radii):
        d0[i] = (_trace_moments(patch, plus, rf, both, eps[zero:zero + 1], MODEL_RAYS // 2)[0]
                 - _trace_moments(patch, minus, rf, both, eps[zero:zero + 1], MODEL_RAYS // 2)[0]) / opt.pixel_mm ** 2
    d0 -= d0[:1]
    d_along, d_across = d0[:, :len(shells)].T, d0[:, len(shells):].T  # (S, R)
    cos2 = np.array([(uniq[s][0] ** 2 - uniq[s][1] ** 2) / s if s else 0.0 for s in shells])
    field_b = np.where(np.abs(cos2)[:, None] > 1e-9, (d_along - d_across) / (2.0 * np.where(cos2 == 0, 1.0, cos2))[:, None], 0.0)
    field_a = 0.5 * (d_along + d_across)
    return ModelCurves(eps, shells, curves, float(slope / paraxial), radii, field_a, field_b)


def paraxial_curves(cfg: CameraConfig, u_mm: float, shells: np.ndarray) -> ModelCurves:
    """The paraxial D(eps) - D(0) (a scaled-aperture spot, no aberrations), the same for every shell."""
    opt = optics(cfg)
    eps = np.array(MODEL_EPS)
    c = 1.0 - (1.0 - opt.c0) / (1.0 + focal_rel_of_radius(cfg, eps))
    gp, gm = opt.g(u_mm), opt.g(-u_mm)
    d = 2.0 * opt.aperture_i_px2 * ((c - gp) ** 2 - (c + gm) ** 2)
    d = d - d[eps == 0.0]
    flat = np.zeros((len(shells), 1))
    return ModelCurves(eps, np.asarray(shells), np.tile(d, (len(shells), 1)), 1.0, np.zeros(1), flat, flat)


def _invert(curves: ModelCurves, shell: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """eps with curve_shell(eps) = x (piecewise linear, extended linearly past the ends) and the curve's
    slope there; a shell the model lacks takes the nearest one."""
    k = np.abs(shell[:, None] - curves.shells[None, :]).argmin(axis=1)
    cv = curves.curves[k]  # (L, E), decreasing in eps
    e = curves.eps
    # segment: where x falls between consecutive curve points (the ends extend)
    seg = np.sum(cv[:, 1:-1] >= x[:, None], axis=1)  # 0 .. E-2
    lo = np.take_along_axis(cv, seg[:, None], 1)[:, 0]
    hi = np.take_along_axis(cv, seg[:, None] + 1, 1)[:, 0]
    slope = (hi - lo) / (e[seg + 1] - e[seg])
    with np.errstate(invalid="ignore", divide="ignore"):
        out = e[seg] + (x - lo) / slope
    return out, slope


# ---------------------------------------------------------------------------------------------- inputs


def _check_inputs(frames, grid: Grid, cfg: CameraConfig):
    """Validate, and group the frames into +u / -u pairs by (|u|, offset): [(u, offset, plus, minus)]."""
    if not isinstance(grid, Grid):
        raise InputError("the through-focus analysis needs the white frame's calibrated Grid")
    if (grid.rows, grid.cols) != (cfg.mla.count_h, cfg.mla.count_w):
        raise InputError(f"the grid has {grid.rows} x {grid.cols} lenses but the camera's MLA has "
                         f"{cfg.mla.count_h} x {cfg.mla.count_w}")
    frames = list(frames)
    if len(frames) < 2:
        raise InputError("a through-focus reading needs at least one +u / -u pair of frames")
    shape = tuple(grid.image_shape)
    checked = []
    for k, item in enumerate(frames):
        try:
            img, rec = item
        except (TypeError, ValueError):
            raise InputError(f"through-focus frame {k + 1} must be an (image, ThroughFocus) pair") from None
        if not isinstance(rec, ThroughFocus):
            raise InputError(f"through-focus frame {k + 1} has no ThroughFocus record")
        img = np.asarray(img)
        if img.ndim != 2 or img.dtype.kind not in "fiu":
            raise InputError(f"through-focus frame {k + 1} must be a 2-D numeric image")
        if img.shape != shape:
            raise InputError(f"through-focus frame {k + 1} is {img.shape[1]}x{img.shape[0]} px but the white "
                             f"frame's grid is {shape[1]}x{shape[0]} px")
        if not np.isfinite(img).all():
            raise InputError(f"through-focus frame {k + 1} holds NaN or infinite pixels")
        if img.max() > 2.0:
            raise InputError(f"through-focus frame {k + 1} reaches {float(img.max()):g}, not a normalized frame "
                             "(white level 1): prepare it with prepare_spots")
        checked.append((np.asarray(img, dtype=np.float32), rec))
    first = checked[0][1]
    for k, (_, rec) in enumerate(checked):
        if rec.f_number != first.f_number or rec.spacing_lenses != first.spacing_lenses:
            raise InputError(f"through-focus frame {k + 1} was taken at f/{rec.f_number:g} with pinholes "
                             f"{rec.spacing_lenses} lenses apart, frame 1 at f/{first.f_number:g} and "
                             f"{first.spacing_lenses}: all frames of a series must share both")
    groups: dict[tuple[float, tuple[int, int]], dict[int, tuple]] = {}
    for k, (img, rec) in enumerate(checked):
        key = (abs(rec.focus_offset_mm), tuple(int(v) for v in rec.offset_lenses))
        sign = 1 if rec.focus_offset_mm > 0 else -1
        slot = groups.setdefault(key, {})
        if sign in slot:
            raise InputError(f"through-focus frames {slot[sign][2] + 1} and {k + 1} are both u = "
                             f"{rec.focus_offset_mm:+g} mm at offset {key[1]}: give each frame once")
        slot[sign] = (img, rec, k)
    pairs = []
    for (u, off), slot in sorted(groups.items()):
        if len(slot) != 2:
            have = next(iter(slot.values()))
            raise InputError(f"through-focus frame {have[2] + 1} (u = {have[1].focus_offset_mm:+g} mm, offset "
                             f"{off}) has no partner of the other sign at the same offset")
        pairs.append((u, off, slot[1], slot[-1]))
    return pairs


def _check_exposure(cells: np.ndarray, name: str) -> None:
    """The rawio black/saturation checks, on the sub-image windows that should be lit (a pinhole frame
    lights a few per cent of the sensor: the whole frame's percentiles would call it black)."""
    flat = np.ascontiguousarray(cells.reshape(-1, cells.shape[-1]), dtype=np.float32)
    check_exposure(RawFrame(flat, 16, None, 0, 1, source=name, levels_from="normalized"))


# ---------------------------------------------------------------------------------------------- geometry


def coverage(cfg: CameraConfig, tf: ThroughFocus) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For a +u / -u pair at tf's offset: per lens (rows, cols) whether it is fully lit in both frames,
    the index of its nearest pinhole (into `pinhole_lenses`) and its (dx, dy) offset from it in lenses."""
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    pins = pinhole_lenses(cfg, tf)
    r_in = pair_radius_lenses(cfg, tf)
    m, n = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    if len(pins) == 0 or r_in < 0:
        z = np.zeros((rows, cols), np.int64)
        return np.zeros((rows, cols), bool), z, np.stack([z, z], axis=-1)
    d2 = (m[..., None] - pins[:, 0]) ** 2 + (n[..., None] - pins[:, 1]) ** 2
    near = np.argmin(d2, axis=-1)
    dxy = np.stack([n - pins[near, 1], m - pins[near, 0]], axis=-1)
    lit = np.take_along_axis(d2, near[..., None], axis=-1)[..., 0] <= r_in * r_in
    return lit, near, dxy


# --------------------------------------------------------------------------------------------- moments


@dataclass(frozen=True)
class Spots:
    """One frame's windows around L lenses; window pixel coordinates are relative to the centre pixel."""

    cells: np.ndarray  # (L, n, n) background-subtracted
    ix: np.ndarray  # (L,) frame column of the window's centre pixel
    iy: np.ndarray
    background: np.ndarray  # (L,)
    bg_sigma: float  # the frame's unlit-pixel noise (normalized units)
    saturated: np.ndarray  # (L,) bool


def spots(img: np.ndarray, x_px: np.ndarray, y_px: np.ndarray, half: int) -> Spots:
    """Cut every lens' window (centred on the pixel nearest (x, y), inside the frame), subtract its
    background (the median of its outer ring) and note saturation."""
    ix = np.rint(x_px).astype(np.int64)
    iy = np.rint(y_px).astype(np.int64)
    off = np.arange(-half, half + 1)
    cells = img[(iy[:, None] + off)[:, :, None], (ix[:, None] + off)[:, None, :]]
    n = 2 * half + 1
    ring = np.ones((n, n), bool)
    ring[RING_PX:n - RING_PX, RING_PX:n - RING_PX] = False
    outer = cells[:, ring]
    bg = np.median(outer, axis=1)
    resid = outer - bg[:, None]
    bg_sigma = 1.4826 * float(np.median(np.abs(resid))) if resid.size else 0.0
    sat = (cells >= SATURATED).any(axis=(1, 2))
    return Spots((cells - bg[:, None, None]).astype(np.float64), ix, iy, bg, bg_sigma, sat)


def _window_weights(centre: np.ndarray, w: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """(L, n): the share of each pixel [k - 1/2, k + 1/2] inside [centre - w, centre + w]."""
    return np.clip(w[:, None] + 0.5 - np.abs(coords[None, :] - centre[:, None]), 0.0, 1.0)


def moments(sp: Spots, cx: np.ndarray, cy: np.ndarray, w: np.ndarray, e_per_unit: float, refine: int = 2):
    """Centroid (window coordinates), second moment x + y (px^2), its variance and the flux of every
    spot in a window of half-width `w` around (cx, cy); the window follows the centroid `refine` times.
    Returns (mx, my, m2, m2_var, flux, w)."""
    n = sp.cells.shape[1]
    half = n // 2
    k = np.arange(n) - half
    limit = half - RING_PX - 0.5
    w = np.clip(w, 0.5, limit)
    for it in range(refine + 1):
        wx = _window_weights(cx, w, k)
        wy = _window_weights(cy, w, k)
        flux = np.einsum("lij,li,lj->l", sp.cells, wy, wx)
        with np.errstate(invalid="ignore", divide="ignore"):
            mx = np.einsum("lij,li,lj,j->l", sp.cells, wy, wx, k) / flux
            my = np.einsum("lij,li,lj,i->l", sp.cells, wy, wx, k) / flux
        if it < refine:
            cx = np.clip(np.where(np.isfinite(mx), mx, cx), -half + 1, half - 1)
            cy = np.clip(np.where(np.isfinite(my), my, cy), -half + 1, half - 1)
            w = np.clip(np.minimum(w, limit - np.maximum(np.abs(cx), np.abs(cy)) + RING_PX), 0.5, limit)
    dx2 = (k[None, :] - mx[:, None]) ** 2
    dy2 = (k[None, :] - my[:, None]) ** 2
    r2 = dy2[:, :, None] + dx2[:, None, :]  # (L, n, n)
    wgt = wy[:, :, None] * wx[:, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        m2 = np.einsum("lij,lij,lij->l", sp.cells, wgt, r2) / flux
        # delta method: d m2 / d v_ij = w_ij (r2_ij - m2) / flux (the centroid's own derivative is zero)
        var_pix = np.maximum(sp.cells + sp.background[:, None, None], 0.0) / e_per_unit + sp.bg_sigma ** 2
        lever = wgt * (r2 - m2[:, None, None])
        m2_var = np.einsum("lij,lij->l", lever ** 2, var_pix) / flux ** 2
        ring = n * n - (n - 2 * RING_PX) ** 2
        m2_var += (np.pi / 2) * sp.bg_sigma ** 2 / ring * (lever.sum(axis=(1, 2)) / flux) ** 2  # the ring median
    return mx, my, m2, m2_var, flux, w


def _first_guess(sp: Spots) -> tuple[np.ndarray, np.ndarray]:
    """The brightest 3 x 3 sum inside the ring of every window (window coordinates)."""
    c = sp.cells
    s = sum(c[:, i:c.shape[1] - 2 + i, j:c.shape[2] - 2 + j] for i in range(3) for j in range(3))
    n = c.shape[1]
    inner = s[:, RING_PX - 1:n - 1 - RING_PX, RING_PX - 1:n - 1 - RING_PX]
    iy, ix = np.divmod(inner.reshape(len(c), -1).argmax(axis=1), inner.shape[2])
    return (ix + RING_PX - n // 2).astype(np.float64), (iy + RING_PX - n // 2).astype(np.float64)


def _spot_window(sp: Spots, e_per_unit: float):
    """Each spot's centroid and a window of WINDOW_SIGMAS of its per-axis rms (at least MIN_WINDOW_PX)."""
    cx, cy = _first_guess(sp)
    w = np.full(len(cx), 3.0)
    for _ in range(2):
        cx, cy, m2, _, _, _ = moments(sp, cx, cy, w, e_per_unit, refine=1)
        sig = np.sqrt(np.clip(0.5 * np.where(np.isfinite(m2), m2, 1.0), 0.0, None))
        w = np.maximum(WINDOW_SIGMAS * sig, MIN_WINDOW_PX)
    return cx, cy, w


# ------------------------------------------------------------------------------------------- the reading


def _robust_sigma(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    if x.size < 2:
        return float("nan")
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def _phase_terms(frac: np.ndarray) -> np.ndarray:
    """First Fourier harmonic of the spots' sub-pixel phases, x and y summed (a symmetric spot samples
    alike along both), for both frames: (L, 4). frac: (L, 4) phases of (+x, +y, -x, -y)."""
    a = 2.0 * np.pi * frac
    return np.stack([np.cos(a[:, 0]) + np.cos(a[:, 1]), np.sin(a[:, 0]) + np.sin(a[:, 1]),
                     np.cos(a[:, 2]) + np.cos(a[:, 3]), np.sin(a[:, 2]) + np.sin(a[:, 3])], axis=1)


def _shell_groups(shell: np.ndarray) -> np.ndarray:
    """Group index per lens: its shell, or one pooled group for shells with fewer than MIN_SHELL_LENSES."""
    _, inv, cnt = np.unique(shell, return_inverse=True, return_counts=True)
    return np.unique(np.where(cnt[inv] >= MIN_SHELL_LENSES, inv, -1), return_inverse=True)[1]


def _group_median(v: np.ndarray, grp: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Per lens the median of v over the lenses of its group where `use` (all of the group if none)."""
    out = np.full(v.shape, np.nan)
    for j in np.unique(grp):
        sel = grp == j
        pick = sel & use
        vals = v[pick] if pick.any() else v[sel & np.isfinite(v)]
        if vals.size:
            out[sel] = np.median(vals)
    return out


def reference_fit(m2: np.ndarray, shell: np.ndarray, frac: np.ndarray | None,
                  offset: np.ndarray | None = None) -> np.ndarray:
    """D = m2(+) - m2(-) against its typical value, per lens. m2: (L, 2) second moments of the +u and
    -u spots; frac: (L, 4) their sub-pixel phases (+x, +y, -x, -y), or None; offset: what the typical
    lens' D is known to differ by from lens to lens (the field's, `ModelCurves.field_offset`).

    The typical D is the median of the lens' shell (lenses at its distance from their pinhole, all discs
    and pairs of this |u|; shells with fewer than MIN_SHELL_LENSES lenses pooled). Before that, the
    sub-pixel phase pattern of the typical spots is fitted to what the shells leave (the first harmonic
    of each frame's phases, shell means removed from the terms; robust: twice more without the lenses
    beyond 4 sigma, so defective lenses do not bend it) and removed where it is significant. Its
    amplitude depends on the spot's size, and the fit sees two sizes, the typical +u spot and the
    typical -u spot: a lens' spot is corrected with the amplitude of its own size, linearly between the
    two (held beyond them), so a lens whose focal error swaps the two sizes (c near g) gets the other
    frame's pattern."""
    d = m2[:, 0] - m2[:, 1] - (0.0 if offset is None else offset)
    grp = _shell_groups(shell)
    ok = np.isfinite(d)
    resid = d - _group_median(d, grp, ok)
    s0 = max(_robust_sigma(resid[ok]), 1e-12) if ok.sum() >= 2 else np.inf  # a floor: noise-free frames work
    keep = ok & (np.abs(resid) <= 4.0 * s0)
    corrected = d
    if frac is not None and keep.sum() >= PHASE_MIN_LENSES * (len(np.unique(grp)) + 4):
        terms = _phase_terms(frac)  # (L, 4): (+ cos, + sin, - cos, - sin)
        centred = terms - np.stack([_group_median(t, grp, keep) for t in terms.T], axis=1)
        coef = np.zeros(4)
        for _ in range(3):
            a = centred[keep]
            if len(a) < 4 * PHASE_MIN_LENSES or np.linalg.cond(a) > 1e3:  # the phases do not vary independently of the shells: nothing to fit
                coef[:] = 0.0
                break
            coef, *_ = np.linalg.lstsq(a, resid[keep], rcond=None)
            r = resid - centred @ coef
            keep = ok & (np.abs(r) <= 4.0 * max(_robust_sigma(r[keep]), 1e-12))
        # significant (3 sigma of the coefficients) and physical (a pixel-sized spot: <= 0.3 px^2 per frame)
        sig = _robust_sigma(resid[keep] - centred[keep] @ coef) * np.sqrt(np.diag(np.linalg.pinv(centred[keep].T @ centred[keep])))
        coef = np.where((np.abs(coef) > 3.0 * sig) & (np.abs(coef) < 0.3), coef, 0.0)
        amp_p, amp_m = coef[:2], -coef[2:]  # the m2 patterns of the typical +u and -u spots
        size_p, size_m = np.median(m2[keep, 0]), np.median(m2[keep, 1])
        if abs(size_p - size_m) > 1e-6:
            t = np.clip((m2 - size_m) / (size_p - size_m), 0.0, 1.0)  # (L, 2): 0 = the typical -u size
            amp_plus = amp_m[None, :] + t[:, :1] * (amp_p - amp_m)[None, :]
            amp_minus = amp_m[None, :] + t[:, 1:] * (amp_p - amp_m)[None, :]
        else:
            amp_plus, amp_minus = np.broadcast_to(amp_p, (len(d), 2)), np.broadcast_to(amp_m, (len(d), 2))
        corrected = d - (np.sum(amp_plus * terms[:, :2], axis=1) - np.sum(amp_minus * terms[:, 2:], axis=1))
    return corrected - _group_median(corrected, grp, keep)


def measure_through_focus(frames: Sequence[tuple[np.ndarray, ThroughFocus]], grid: Grid, cfg: CameraConfig,
                          *, model: str = "traced") -> ThroughFocusResult:
    """Every microlens' focal-length error (with its sign) and optical-centre displacement from prepared
    through-focus frames (`prepare_spots`), each with its ThroughFocus record, on the white frame's `grid`
    (see the module note). `model`: 'traced' reads D on the camera's traced D(eps) (aberrations
    included), 'paraxial' on the paraxial one (spots that are scaled apertures). Raises InputError on
    frames that do not fit the grid, pairs without both signs, records that disagree, black or saturated
    frames, or when no lens is fully lit in any pair."""
    t0 = time.perf_counter()
    if model not in ("traced", "paraxial"):
        raise InputError(f"the through-focus model must be 'traced' or 'paraxial', not {model!r}")
    pairs = _check_inputs(frames, grid, cfg)
    opt = optics(cfg)
    rows, cols = grid.rows, grid.cols
    half = int(math.floor(cfg.layout.subimage_pitch_px / 2))
    h_img, w_img = grid.image_shape
    gx, gy = grid.grid_x_px.ravel(), grid.grid_y_px.ravel()
    with np.errstate(invalid="ignore"):
        inside = (np.isfinite(gx) & np.isfinite(gy) & (np.rint(gx) - half >= 0) & (np.rint(gy) - half >= 0)
                  & (np.rint(gx) + half <= w_img - 1) & (np.rint(gy) + half <= h_img - 1))

    got = []  # per pair: dict of per-lens arrays
    for u, off, plus, minus in pairs:
        lit, near, dxy = coverage(cfg, plus[1])
        idx = np.flatnonzero(lit.ravel() & inside)
        if idx.size == 0:
            continue
        meas = []
        for img, rec, k in (plus, minus):
            sp = spots(img, gx[idx], gy[idx], half)
            name = f"{k + 1} of the through-focus series (u = {rec.focus_offset_mm:+g} mm, offset {off})"
            _check_exposure(sp.cells + sp.background[:, None, None], name)
            if sp.saturated.mean() > 0.5:
                raise InputError(f"Frame {name} is saturated: {int(sp.saturated.sum())} of {len(idx)} spots reach "
                                 "the white level; reduce the exposure or the light")
            meas.append((sp, *_spot_window(sp, opt.e_per_unit)))
        w_common = np.maximum(meas[0][3], meas[1][3])
        res = []
        for sp, cx, cy, _ in meas:
            mx, my, m2, m2_var, flux, _ = moments(sp, cx, cy, w_common, opt.e_per_unit)
            res.append((m2, m2_var, flux, sp.saturated, sp.ix + mx, sp.iy + my))
        (m2p, vp, fp, sp_, xp, yp), (m2m, vm, fm, sm_, xm, ym) = res
        sat = sp_ | sm_
        with np.errstate(invalid="ignore"):  # a lens that throws no spot (missing, opaque): not read
            lit_p, lit_m = fp > MIN_FLUX * np.nanmedian(fp), fm > MIN_FLUX * np.nanmedian(fm)
        good = np.isfinite(m2p) & np.isfinite(m2m) & np.isfinite(vp) & np.isfinite(vm) & lit_p & lit_m & ~sat
        pos = np.stack([xp, yp, xm, ym], axis=1)[good]
        got.append(dict(u=u, off=off, rec=plus[1], idx=idx[good], d=(m2p - m2m)[good], var=(vp + vm)[good],
                        m2=np.stack([m2p, m2m], axis=1)[good],
                        shell=(dxy[..., 0] ** 2 + dxy[..., 1] ** 2).ravel()[idx[good]],
                        dxy=dxy.reshape(-1, 2)[idx[good]], pin=near.ravel()[idx[good]], pos=pos,
                        grid_xy=np.stack([gx[idx[good]], gy[idx[good]]], axis=1),
                        saturated=int(sat.sum()), window=float(np.median(w_common))))
    if not got or sum(len(p["idx"]) for p in got) == 0:
        raise InputError("no lens is fully lit (and unsaturated) in both frames of any +u / -u pair: check the "
                         "pinhole offsets, the focus offset u and the exposure")
    t_moments = time.perf_counter() - t0

    # D against the typical lens of its shell (the main lens' field effects on it removed), phase
    # pattern removed, per |u| (all pairs of that u), read on the model's D(eps)
    for u in sorted({p["u"] for p in got}):
        group = [p for p in got if p["u"] == u]
        shells = np.unique(np.concatenate([p["shell"] for p in group]))
        curves = (model_curves(cfg, u, group[0]["rec"].f_number, pair_radius_lenses(cfg, group[0]["rec"]))
                  if model == "traced" else paraxial_curves(cfg, u, shells))
        field_d = np.concatenate([curves.field_offset(p["shell"], p["dxy"],
                                                      lens_centres_mm(cfg, pinhole_lenses(cfg, p["rec"])[p["pin"]]))
                                  for p in group])
        frac = np.concatenate([p["pos"] - np.rint(p["pos"]) for p in group])
        rel = reference_fit(np.concatenate([p["m2"] for p in group]), np.concatenate([p["shell"] for p in group]),
                            frac, field_d)
        start = 0
        for p in group:
            p["rel"] = rel[start:start + len(p["d"])]
            start += len(p["d"])
            p["eps"], slope = _invert(curves, p["shell"], p["rel"])
            p["eps_sig"] = np.sqrt(p["var"]) / np.abs(slope)
            p["gain"] = curves.gain
    t_model = time.perf_counter() - t0 - t_moments

    readings = []
    num, den, dsum = np.zeros(rows * cols), np.zeros(rows * cols), np.zeros(rows * cols)
    birge = {}
    for u in {p["u"] for p in got}:  # the Birge ratio of each |u|: all its pairs' lenses
        z = np.concatenate([p["eps"] / p["eps_sig"] for p in got if p["u"] == u])
        k = _robust_sigma(z) if np.isfinite(z).sum() >= 20 else 1.0
        birge[u] = max(1.0, k if np.isfinite(k) else 1.0)
    for p in got:
        ok = np.isfinite(p["eps"]) & np.isfinite(p["eps_sig"]) & (p["eps_sig"] > 0)
        k = birge[p["u"]]
        wgt = 1.0 / (k * p["eps_sig"][ok]) ** 2
        np.add.at(num, p["idx"][ok], wgt * p["eps"][ok])
        np.add.at(den, p["idx"][ok], wgt)
        np.add.at(dsum, p["idx"][ok], wgt * p["rel"][ok])
        readings.append(PairReading(float(p["u"]), p["off"], int(ok.sum()), opt.g(p["u"]), opt.g(-p["u"]),
                                    float(p["gain"]), float(k), p["window"], p["saturated"]))
    covered = (den > 0).reshape(rows, cols)
    with np.errstate(invalid="ignore", divide="ignore"):
        eps = np.where(den > 0, num / den, np.nan).reshape(rows, cols)
        eps_sig = np.where(den > 0, 1.0 / np.sqrt(den), np.nan).reshape(rows, cols)
        delta = np.where(den > 0, dsum / den, np.nan).reshape(rows, cols)
    focal = focal_rel_of_radius(cfg, eps)
    dfde = (focal_rel_of_radius(cfg, eps + 1e-4) - focal_rel_of_radius(cfg, eps - 1e-4)) / 2e-4
    cdx, cdy, csig = _centres(got, rows, cols, opt, cfg)
    return ThroughFocusResult(focal, eps_sig * np.abs(dfde), eps, covered, delta, cdx, cdy, csig, tuple(readings),
                              cfg.layout.micro.efl * 1e3,
                              {"moments": round(t_moments, 4), "model": round(t_model, 4),
                               "total": round(time.perf_counter() - t0, 4)})


def _centres(got: list[dict], rows: int, cols: int, opt: Optics, cfg: CameraConfig):
    """Optical-centre displacement per lens (µm, MLA plane): each frame's spot centroid minus its white
    sub-image centre, minus the median of the lenses at the same (dx, dy) from their pinhole (all frames
    of that signed u: the main lens' aberrations over a disc), minus each frame's constant (the mask's
    placement) and a smooth field common to the frames of that u (`_field_removed`: the main lens'
    distortion); averaged over the lens' frames; sigma from the residuals' spread (`_clipped_rms`)."""
    by_u: dict[float, list] = {}
    for p in got:
        by_u.setdefault(p["u"], []).append((p, 0))
        by_u.setdefault(-p["u"], []).append((p, 2))
    sx, sy, cnt = np.zeros(rows * cols), np.zeros(rows * cols), np.zeros(rows * cols)
    resid_all = []
    for u, items in by_u.items():
        d = np.concatenate([p["dxy"] for p, _ in items])
        reach = int(np.abs(d).max()) if d.size else 0
        cls = (d[:, 1] + reach) * (2 * reach + 1) + (d[:, 0] + reach)
        pins = [lens_centres_mm(cfg, pinhole_lenses(cfg, p["rec"])[p["pin"]]) for p, _ in items]
        lens = [lens_centres_mm(cfg, np.stack(np.divmod(p["idx"], cols), axis=1)) for p, _ in items]
        # the paraxial chief ray through the lens' centre from the pinhole's image, against the white
        # sub-image centre (the chief ray from the exit pupil): what is left is the same for every disc
        pred = [((xp - xl) * (opt.s_mm / opt.u_prime(u)) - xl * (opt.s_mm / opt.pupil_mm)) / opt.pixel_mm
                for xp, xl in zip(pins, lens)]
        ox = _class_centred(np.concatenate([p["pos"][:, j] - p["grid_xy"][:, 0] - q[:, 0]
                                            for (p, j), q in zip(items, pred)]), cls)
        oy = _class_centred(np.concatenate([p["pos"][:, j + 1] - p["grid_xy"][:, 1] - q[:, 1]
                                            for (p, j), q in zip(items, pred)]), cls)
        frame_of = np.concatenate([np.full(len(p["idx"]), j) for j, (p, _) in enumerate(items)])
        pin_all = np.concatenate(pins)
        rx, ry = (_field_removed(v, pin_all, frame_of) for v in (ox, oy))
        idx = np.concatenate([p["idx"] for p, _ in items])
        ok = np.isfinite(rx) & np.isfinite(ry)
        np.add.at(sx, idx[ok], rx[ok])
        np.add.at(sy, idx[ok], ry[ok])
        np.add.at(cnt, idx[ok], 1.0)
        resid_all.append(np.concatenate([rx[ok], ry[ok]]))
    um = opt.pixel_mm * 1e3 / (1.0 - opt.c0)  # µm in the MLA plane per px of spot motion
    spread = _clipped_rms(np.concatenate(resid_all)) if resid_all else float("nan")
    with np.errstate(invalid="ignore", divide="ignore"):
        dx = np.where(cnt > 0, sx / cnt, np.nan).reshape(rows, cols) * um
        dy = np.where(cnt > 0, sy / cnt, np.nan).reshape(rows, cols) * um
        sig = np.where(cnt > 0, spread / np.sqrt(np.maximum(cnt, 1)), np.nan).reshape(rows, cols) * um
    return dx, dy, sig


def _clipped_rms(r: np.ndarray) -> float:
    """RMS of r within 5 robust sigma: the tails of pixel sampling counted, displaced lenses not."""
    r = r[np.isfinite(r)]
    if r.size < 2:
        return float("nan")
    keep = np.abs(r - np.median(r)) <= 5.0 * max(_robust_sigma(r), 1e-12)
    return float(np.sqrt(np.mean(r[keep] ** 2)))


def _field_removed(v: np.ndarray, xy: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """v minus its robust least-squares fit on a constant per frame (the mask's placement) plus a
    polynomial of the pinhole positions xy (L, 2) common to all frames of this u (the main lens'
    distortion; quadratic, cubic from 200 values): twice more without the values beyond 4 sigma."""
    ok = np.isfinite(v)
    if not ok.any():
        return v
    x, y = xy[:, 0], xy[:, 1]
    frames = np.unique(frame)
    cols = [(frame == f).astype(np.float64) for f in frames]
    cols += [x, y, x * x, x * y, y * y]
    if ok.sum() >= 200:
        cols += [x ** 3, x * x * y, x * y * y, y ** 3]
    a = np.stack(cols, axis=1)
    keep = ok.copy()
    out = v - np.median(v[ok])
    for _ in range(3):
        if keep.sum() <= a.shape[1]:
            break
        beta, *_ = np.linalg.lstsq(a[keep], v[keep], rcond=None)
        out = v - a @ beta
        keep = ok & (np.abs(out) <= 4.0 * max(_robust_sigma(out[keep]), 1e-12))
    return out


def _class_centred(v: np.ndarray, cls: np.ndarray, min_count: int = MIN_SHELL_LENSES) -> np.ndarray:
    """v minus the median of its class; classes with fewer than `min_count` members become NaN."""
    out = np.full(v.shape, np.nan)
    ok = np.isfinite(v)
    if not ok.any():
        return out
    labels, inv, cnt = np.unique(cls[ok], return_inverse=True, return_counts=True)
    med = np.asarray(ndimage.median(v[ok], cls[ok], labels), dtype=np.float64)
    vals = v[ok] - med[inv]
    vals[cnt[inv] < min_count] = np.nan
    out[ok] = vals
    return out


__all__ = ["ThroughFocusResult", "PairReading", "ModelCurves", "measure_through_focus", "prepare_spots",
           "model_curves", "paraxial_curves", "optics", "aperture_moment_mm2", "coverage", "pair_radius_lenses",
           "focal_rel_of_radius", "reference_fit"]
