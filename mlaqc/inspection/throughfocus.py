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
in which one lens carries a radius error eps (every 0.5 % out to +-15 %) among healthy ones, one lens per
shell (lenses at the same distance from their pinhole), on the axis and at FIELD_POINTS field radii.

Pixel sampling. A spot of about a pixel (Table 1: 1-2 px at u = +-10 mm f/8, 1-2.5 px at +-5 mm f/11)
is undersampled, and that is what limited the sizing (issue #12: at +-5 mm f/11, seeds 2-4, -3 % errors
read 0.76-0.99 of their size, median 0.88). Two things, both measured on frames with a third of the
lenses seeded over -12..+12 %:
- its measured second moment depends on where it falls on the pixels, by up to +-0.25 px^2 (x + y), and
  how much depends on its size (binned, a uniform square 1.0 px wide reads 0.5 px^2 apart over its
  positions, one 1.3 px wide 0.11), so the pattern's amplitude swings with a period of about 4 % in eps,
  and a lens whose error changes its spots' sizes has a pattern of its own (the typical lens' fitted
  pattern, applied to it, added 0.2-0.6 % of scatter to the readings of seeded lenses; healthy 0.1 %);
- its measured centroid locks to the pixel's centre, the more the smaller the spot (the model: 0.08-0.24
  px rms over the positions for the smaller spot of a lens 3-11 % off, <= 0.03 px for the larger spot
  of any lens). A sub-pixel pattern fitted on the spots' own centroids is then not zero-mean over the
  lenses whose spot is smaller than the typical one: it took 0.1-0.3 px^2 off D for -8..-2 % lenses
  (the -3 % bias above; the model's curvature between its old nodes at 0 and +-5 % was worth 2 %).
So the model is the measurement's, not the geometric moment: for every shell, field radius and eps, the
traced rays of both frames' spots are binned into pixels with the spot's centre at P x P sub-pixel
positions, put through the config's image formation (as `apply_formation`: diffraction and crosstalk
on the binned image) and read by the same window and moment code as a frame (ModelCurves.spot_m2). Each
lens is read on its own model: its spots' centres from the larger spot's centroid and the smoothly
fitted offset between its two frames' spots (`true_phases`), its D against the model at its shell,
field radius (orientation mirrored onto the traced one) and those phases, less a constant per shell
group (the typical lens' offset: a defocus common to all lenses, the sensor distance, is not read, as
in the white frame's `measure_lenses`; the MLA's slow trend over the array is kept), less what the
typical lenses still show of a first-harmonic phase pattern; the eps of the lens' own curve that
explains it (the mean under its likelihood within BRACKET_NODES nodes of the phase-averaged reading,
with its sd: where a pixel-sized spot's moment stalls over a few % of eps at its phase, as at +-10 mm,
the reading says so) is turned into Δf/f by the thick-lens power of a lens with both radii scaled by
1 + eps (as `measure_lenses` reports). Measured (bench/throughfocus_accuracy.py, +-5 mm f/11, 4 lenses,
seeds 2-6): +-3/5/10 % radius errors sized within 15 % 120 of 120 (was 109), healthy lenses' sd 0.092-
0.094 % (was 0.114-0.116 %) with each frame scaled to 80 % of full well, 0.104-0.106 % at the protocol's
own exposure (50 %, mlaqc.optics.throughfocus.FILL_FRACTION; still 120 of 120), none flagged; at +-10 mm
f/8, 9 lenses (seeds 2-4, 80 %): 58 of 72 (was 33).
`model="paraxial"` reads on the paraxial D instead (spots that are scaled apertures: no aberrations),
with the sub-pixel pattern fitted on the typical spots (`reference_fit`).

Measurement. Each lens' spot is found in its sub-image window (the white frame's grid): the brightest
3 x 3 sum, then the centroid and second moment in a square window of half-width WINDOW_SIGMAS sigma (at
least MIN_WINDOW_PX) around the centroid, iterated, background (the median of the window's outer ring)
subtracted. Window edges weigh pixels by the share of them inside, so the moments move smoothly with the
spot. Both frames of a lens use one window (the larger), so the floor cancels. Lenses not fully lit in
both frames (nearer the disc's traced rim than RIM_MARGIN_LENSES), saturated, off the sensor or unlit are
left out of that pair; a lens read in several pairs gets their inverse-variance mean.

Hex arrays (mla.packing = "hex"): the pinholes sit on the hex sub-lattice (mlaqc.optics.throughfocus), a
lens' nearest pinhole and its (dx, dy) offset come from the Lattice positions (dx in half pitches, dy in
rows of sqrt(3)/2), its shell is dq^2 + dr^2 + dq dr in axial steps (0, 1, 3, 4, 7, ...), the lit aperture
is the hexagonal cell (or the circle of `aperture = "circle"`), and the model is traced on a hex patch
with its centre lens under the pinhole: per shell the lens at 0-30 degrees from the field direction, and
that lens turned 60 degrees for the field's orientation term. A lens is mapped onto the traced one by the
same mirrors and x / y swap as on a square array; the swap turns a hexagonal cell by 90 degrees, which
keeps its second moment (a regular hexagon's is isotropic) but not its exact pixel pattern: the shipped
protocol (every lens read under its own pinhole) sizes ±5 / ±10 % within 15 % on the small hex camera
(tests/test_hex_throughfocus.py, bench/throughfocus_accuracy.py -c fixtures/hex_small_camera.toml).

Frames: prepare them with `prepare_spots` (black-subtracted and normalized, nothing else): the pipeline's
`prepare` suppresses hot pixels, and a focused spot's peak is one to it.

Uncertainty: the moments' shot and read noise (the sensor's electrons per unit from the config, the read
noise from the frame's unlit pixels), propagated, plus (traced model) what the typical lenses scatter
about their models beyond it; through the lens' own curve; scaled up (never down) by a Birge ratio, the
robust spread of the readings of each |u| over their sigmas, so that what the noise model leaves out (a
render's Monte-Carlo noise) is counted.

Speed: a frame is kept as stored (`SpotFrame`; an uncompressed TIFF mapped from its file), and only
the spots' windows are cut and normalized; cutting, the ring median, the first guess and the moments are
compiled (mlaqc.inspection.throughfocus_kernels), the pairs run on a thread per core, the model is cached
on disk (and shipped for the Table 1 camera's protocols): bench/throughfocus_accuracy.py prints the
times, bench/inspection.py --through-focus the whole white + 32-frame inspection.

Optical centre (Shack-Hartmann): a lens' spot centroid moves by d s P (d its optical-centre shift, s P =
1 - c0 ≈ 1) whatever u is. It is read against the paraxial chief ray (through the lens' centre from the
pinhole's image, against the white sub-image centre), the typical lens at the same (dx, dy) from its
pinhole (the main lens' aberrations) and a smooth field over the frame's pinhole positions (the mask's
placement, the main lens' distortion), averaged over the frames.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from mlaqc.errors import InputError
from mlaqc.inspection.calibrate import Grid
from mlaqc.inspection.throughfocus_fits import _class_centred, _clipped_rms, _field_removed, _robust_sigma, reference_fit
from mlaqc.inspection.throughfocus_geometry import coverage, offset_classes, shell_of
from mlaqc.inspection.throughfocus_inputs import _check_exposure, _check_inputs
from mlaqc.inspection.throughfocus_model import model_curves, paraxial_curves
from mlaqc.inspection.throughfocus_optics import Optics, focal_rel_of_radius, optics
from mlaqc.inspection.throughfocus_reading import _invert, read_traced
from mlaqc.inspection.throughfocus_results import PairReading, ThroughFocusResult
from mlaqc.inspection.throughfocus_spots import RING_PX, _spot_window, moments, spots
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.throughfocus import ThroughFocus, lens_centres_mm, pair_radius_lenses, pinhole_lenses
from mlaqc.parallel import thread_map

MIN_FLUX = 0.25  # a spot with less than this share of the pair's median flux is not read (no lens there)


def pair_spots(frames: Sequence[tuple[np.ndarray, ThroughFocus]], grid: Grid, cfg: CameraConfig) -> list[dict]:
    """Check the frames (`_check_inputs`) and measure every +u / -u pair's spots: per pair a dict of the
    per-lens arrays of the lenses it reads (flat index, m2 of both frames, D, its variance, spot
    centroids, shell, offset from the pinhole and the pinhole's index)."""
    pairs = _check_inputs(frames, grid, cfg)
    opt = optics(cfg)
    half = int(math.floor(cfg.layout.subimage_pitch_px / 2))
    if half <= RING_PX + 1:
        raise InputError(f"the sub-images are {cfg.layout.subimage_pitch_px:.3g} px apart: the through-focus "
                         f"analysis needs at least {2 * (RING_PX + 2)} px for a spot window inside its background ring")
    h_img, w_img = grid.image_shape
    gx, gy = grid.grid_x_px.ravel(), grid.grid_y_px.ravel()
    with np.errstate(invalid="ignore"):
        inside = (np.isfinite(gx) & np.isfinite(gy) & (np.rint(gx) - half >= 0) & (np.rint(gy) - half >= 0)
                  & (np.rint(gx) + half <= w_img - 1) & (np.rint(gy) + half <= h_img - 1))

    def one(pair) -> dict | None:
        u, off, plus, minus = pair
        lit, near, dxy = coverage(cfg, plus[1])
        idx = np.flatnonzero(lit.ravel() & inside)
        if idx.size == 0:
            return None
        meas = []
        for img, rec, k in (plus, minus):
            sp = spots(img, gx[idx], gy[idx], half)
            name = f"{k + 1} of the through-focus series (u = {rec.focus_offset_mm:+g} mm, offset {off})"
            _check_exposure(img, sp, name)
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
        return dict(u=u, off=off, rec=plus[1], idx=idx[good], d=(m2p - m2m)[good], var=(vp + vm)[good],
                    m2=np.stack([m2p, m2m], axis=1)[good],
                    shell=shell_of(dxy).ravel()[idx[good]],
                    dxy=dxy.reshape(-1, 2)[idx[good]], pin=near.ravel()[idx[good]], pos=pos,
                    grid_xy=np.stack([gx[idx[good]], gy[idx[good]]], axis=1),
                    saturated=int(sat.sum()), window=float(np.median(w_common)))

    # the pairs are independent and NumPy lets go of the GIL in the array work: one thread per core
    # (results in the pairs' order, and the first pair's error first, as a loop would raise it)
    got = [p for p in thread_map(one, pairs) if p is not None]
    if not got or sum(len(p["idx"]) for p in got) == 0:
        raise InputError("no lens is fully lit (and unsaturated) in both frames of any +u / -u pair: check the "
                         "pinhole offsets, the focus offset u and the exposure")
    return got


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
    got = pair_spots(frames, grid, cfg)
    opt = optics(cfg)
    rows, cols = grid.rows, grid.cols
    t_moments = time.perf_counter() - t0

    # D against the typical lens of its shell (the main lens' field effects on it removed), phase
    # pattern removed, per |u| (all pairs of that u), read on the model's D(eps)
    for u in sorted({p["u"] for p in got}):
        group = [p for p in got if p["u"] == u]
        shells = np.unique(np.concatenate([p["shell"] for p in group]))
        curves = (model_curves(cfg, u, group[0]["rec"].f_number, pair_radius_lenses(cfg, group[0]["rec"]))
                  if model == "traced" else paraxial_curves(cfg, u, shells))
        pin_mm = [lens_centres_mm(cfg, pinhole_lenses(cfg, p["rec"])[p["pin"]]) for p in group]
        cat = {k: np.concatenate([p[k] for p in group]) for k in ("m2", "var", "pos", "shell", "dxy")}
        if model == "traced":
            frame_of = np.concatenate([np.full(len(p["d"]), j) for j, p in enumerate(group)])
            eps_all, sig_all, rel = read_traced(curves, cat["m2"], cat["var"], cat["pos"], cat["shell"], cat["dxy"],
                                                np.concatenate(pin_mm), frame_of)
        else:
            field_d = np.concatenate([curves.field_offset(p["shell"], p["dxy"], q) for p, q in zip(group, pin_mm)])
            rel = reference_fit(cat["m2"], cat["shell"], cat["pos"] - np.rint(cat["pos"]), field_d)
            eps_all, slope_all = _invert(curves, cat["shell"], rel)
            sig_all = np.sqrt(cat["var"]) / np.abs(slope_all)
        start = 0
        for p in group:
            sl = slice(start, start + len(p["d"]))
            start += len(p["d"])
            p["rel"], p["eps"] = rel[sl], eps_all[sl]
            p["eps_sig"] = sig_all[sl]
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
        cls = offset_classes(np.concatenate([p["dxy"] for p, _ in items]))
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


__all__ = ["measure_through_focus", "pair_spots"]
