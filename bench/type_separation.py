"""What a white image, and candidate second measurements, can tell at all: ideal-observer (matched-filter)
detection and type separation of one lens' error at the modelled sensor's noise. No detector can beat these.

Question: a white image cannot tell pitch from surface decenter below ~10 µm, and radius errors of +5..+10 %
are nearly invisible (the microlens' spherical aberration puts best focus near +5 %, so the sign of a
radius error is ambiguous). Which extra frame (or series) of the same array in the same camera fixes that?
Candidates (bench/protocols.py): the white image stopped down (f/8, f/16), at a second wavelength (450,
850 nm), a pinhole grid imaged onto lens centres / edge midpoints / corners (f/8, least-rms focus), and
a through-focus series (one pinhole, its image u mm behind/before the MLA: a Shack-Hartmann frame).

Method. The centre lens of a 5 x 5-lens patch of the Table 1 camera (mlaqc.models.signatures.patch_config,
geometry frozen at the f-number-matched layout) carries the error; the region is all 5 x 5 lenses (a
sag-intersection pitch error changes the neighbours' apertures; the share of z^2 outside the inner 3 x 3
is printed, ~0 everywhere). Every hypothesis is rendered (default Sobol sampler) in two independent
halves, seeds shared with the nominal's halves (common random numbers: the difference carries only the
changed rays' noise). Only the light an error of the centre lens can change is traced for the differences
(`LocalRenderer`: the Sobol rays of the 3 x 3 MLA cells around it, or the pinholes whose spots reach
them): the difference equals a full render's with the same keys to 1e-11, at 9/49 of the rays.
Sensor noise: the modelled camera (QE 0.6, full well 20000 e-, read 3 e-), per-pixel variance in e- =
signal + read^2, exposure per frame set so the brightest nominal pixel sits at 80 % of full well.
All figures are in that noise's units; the Monte-Carlo noise energy of every difference or fit residual
is estimated from its two halves ((h1 - h2)^2 / 4) and subtracted, so they are ideal-observer figures:

  detection z   = || d_target ||                           (error known; sqrt of the chi^2)
  separation z  = min over the other family || d_target - d_family(m, direction) ||
                  family fits: magnitude m continuous (cubic spline through the rendered magnitudes and 0)
                  and direction (free coefficients on the m-basis at the target's direction and +90 deg,
                  as the old bench did for pitch: a superset of the physical family, so conservative)
  radius sign z = || d(+x %) - nearest negative radius error || (magnitudes 0..30 %, spline), and vice versa
  (each z printed with '~' if its rough Monte-Carlo 1-sigma, from the two halves' own estimates, exceeds
  a quarter of it; --fits prints the best-fitting magnitudes and those uncertainties)

Frames of a protocol add as chi^2 with ONE error hypothesis fitted to all of them jointly (e.g. white +
f/16: the same decenter must explain both). The lens lies on the optical axis, where every frame is
symmetric under the square's rotations: a 90 deg error's signature is the 0 deg one rotated (used for the
perpendicular basis), so 90 deg equals 0 deg and is not printed separately.

Two image models are printed: the geometric tracer alone, and with the sensor-side formation (microlens
diffraction at the frame's wavelength + 2 % crosstalk, mlaqc.optics.formation; PRNU is a fixed pattern
a flat-field removes and is left out).

    python bench/type_separation.py                      # the study (both boundary models if the tracer has them)
    python bench/type_separation.py --quick              # ~3 min: white, pinhole grids, TF u=±2.5 mm; fewer rays
    python bench/type_separation.py --boundaries grid --frames W,S16,T-5,T+5
    python bench/type_separation.py --legacy [--rays-per-pixel 50] [--truth-rpp 3000]   # the old white-image table
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
from scipy.interpolate import CubicSpline

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import protocols as pr

from mlaqc.models.signatures import patch_config
from mlaqc.optics.config import default_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.formation import apply_formation, formation_kernels
from mlaqc.optics.render import Renderer, _Job, add_chunk
from mlaqc.optics.scene import PointScene, WhiteScene
from mlaqc.optics.sensor import expose

LENSES = 5  # patch (the 5 x 5 region is the whole patch bar its 8-px margin)
C = LENSES // 2  # centre lens, 0-based
REGION_LENSES = 5
SEEDS = (11, 12)
FILL = 0.8  # brightest nominal pixel at this fraction of full well

# error grids (µm, relative); the separation targets must be on them
# knots ~0.25 µm apart where the best fits fall (a coarser spline through the signatures fits the other
# family better than any real error does: 1 µm knots over-stated decenter-vs-pitch separations up to 3x)
FULL = dict(pitch0=(1.0, 2.0, 2.25, 2.5, 2.75, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5, 6.0, 8.0),
            dec0=(0.25, 0.5, 1.0, 1.5, 1.75, 1.875, 2.0, 2.125, 2.25, 2.5, 3.0, 5.0, 10.0),
            dec45=(0.25, 0.5, 1.0, 1.5, 1.75, 1.875, 2.0, 2.125, 2.25, 2.5),
            radius=(0.02, 0.03, 0.05, 0.07, 0.10, 0.125, 0.15, 0.20, 0.30))
QUICK = FULL
RADIUS_TARGETS = (-0.10, -0.05, -0.03, 0.03, 0.05, 0.10)
DEC_TARGETS = (5.0, 10.0)
TARGETS = {"P0_1", "P45_1", "D0_5", "D0_10"} | {f"R_{e:+g}" for e in RADIUS_TARGETS}

# protocols: name -> frame keys (each also printed with the white image added)
FULL_FRAMES = "W,S8,S16,L450,L850,PC,PE,PK,T-5,T-2.5,T+2.5,T+5"
QUICK_FRAMES = "W,PE,PK,T-2.5,T+2.5"
TF_OFFSETS = (-5.0, -2.5, 2.5, 5.0)


def hypotheses(grids: dict) -> list[tuple[str, dict]]:
    """(name, error fields) of every render besides the nominal."""
    out = [(f"P0_{m:g}", dict(pitch_um=m, pitch_dir_deg=0.0)) for m in grids["pitch0"]]
    out.append(("P45_1", dict(pitch_um=1.0, pitch_dir_deg=45.0)))
    out += [(f"D0_{m:g}", dict(decenter_um=m, decenter_dir_deg=0.0)) for m in grids["dec0"]]
    out += [(f"D45_{m:g}", dict(decenter_um=m, decenter_dir_deg=45.0)) for m in grids["dec45"]]
    out += [(rname(s * e), dict(radius_front_rel=s * e, radius_back_rel=s * e))
            for e in grids["radius"] for s in (-1.0, 1.0)]
    return out


def rname(e: float) -> str:
    return f"R_{e:+g}"


# --- rendering and whitening -------------------------------------------------------------------------------

@dataclasses.dataclass
class FrameData:
    """Whitened (noise-unit) difference vectors of one frame and their Gram matrices (per image model)."""

    names: list[str]
    gm: dict[str, np.ndarray]  # model -> Gram of the half-means
    gd: dict[str, np.ndarray]  # model -> Gram of the half-differences
    gx: dict[str, np.ndarray]  # model -> cross Gram means x differences (for the per-half estimates)
    info: dict[str, dict]  # model -> exposure and checks


def region_slices(side: int, pitch_px: float, lenses: int) -> tuple[slice, slice]:
    w = int(round(lenses * pitch_px))
    w -= (w - side) % 2  # same parity as the sensor: the region is centred exactly (D4 symmetry)
    lo = (side - w) // 2
    return (slice(lo, lo + w),) * 2


class LocalRenderer:
    """Renders of one frame restricted to the light an error of the centre lens can change: for plane
    scenes the Sobol rays of the 3 x 3 MLA cells around it (a ray starting in a cell crosses at most that
    cell's neighbours' lenses, and in sag-intersection mode the centre lens' errors move only boundaries
    between it and its neighbours), for pinhole grids the pinholes whose spots can reach those lenses.
    Rays of every other cell or pinhole are the same with and without the error (same keys), so the
    difference image is exactly that of a full render with these keys, at a fraction of the rays.
    Falls back to full renders if the tracer's job API changes."""

    def __init__(self, frame: pr.Frame, cfg, per_cell: int | None) -> None:
        self.frame, self.cfg, self.per_cell = frame, cfg, per_cell
        self.scene, self.rays = frame.scene, frame.rays
        if isinstance(frame.scene, PointScene) and len(frame.scene.points_mm) > 1:
            m, p = pr.magnification(cfg), cfg.mla.pitch_um * 1e-3
            near = tuple(q for q in frame.scene.points_mm if max(abs(q[0]), abs(q[1])) * m <= 1.5 * p + 1e-9)
            self.scene = PointScene(points_mm=near, photons=frame.scene.photons)
            self.rays = frame.rays // len(frame.scene.points_mm) * len(near)

    def render(self, errors: ErrorMap, seed: int) -> np.ndarray:
        r = Renderer(self.cfg, errors)
        if isinstance(self.scene, WhiteScene) and self.per_cell and r.sampler == "sobol" and r.fast is not None:
            try:
                return self._cells(r, seed)
            except (AttributeError, TypeError):  # the private job API moved: full renders
                self.per_cell = None
        return r.render(self.scene, rays=self.rays, seed=seed).photons

    def _cells(self, r: Renderer, seed: int) -> np.ndarray:
        k = self.per_cell
        span = max(1, r.cfg.trace.batch_rays // 9)
        jobs = [_Job(i, 9 * min(span, k - j0), None, None, (C - 1, C - 1, 3, 3, j0))
                for i, j0 in enumerate(range(0, k, span))]
        key = int(np.random.SeedSequence(seed).generate_state(1, np.uint64)[0])  # = a full render's key
        image = np.zeros((r.cfg.sensor.height_px, r.cfg.sensor.width_px))
        with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
            for part in pool.map(lambda j: r._trace_job(self.scene, j, key), jobs):
                add_chunk(image, part)
        total = k * r.cells.padded_rows * r.cells.padded_cols  # the full render's normalization
        return image * r.photons_per_weight(self.scene, total)


def render_frame(frame: pr.Frame, hyps: list[tuple[str, dict]], boundaries: str | None, per_cell: int | None,
                 log=lambda s: None) -> FrameData:
    cfg = frame.cfg
    if boundaries is not None:
        cfg = replace(cfg, mla=replace(cfg.mla, boundaries=boundaries))
    side = cfg.sensor.width_px
    cut = region_slices(side, cfg.layout.subimage_pitch_px, REGION_LENSES)
    inner = region_slices(cut[0].stop - cut[0].start, cfg.layout.subimage_pitch_px, 3)
    kern = formation_kernels(cfg, (side, side), with_prnu=False)
    models = {"geo": lambda img: img, "form": lambda img: apply_formation(img, cfg, kern)}
    local = LocalRenderer(frame, cfg, per_cell)

    def errors(fields: dict) -> ErrorMap:
        em = ErrorMap.zeros(LENSES, LENSES)
        return em.with_lens(C + 1, C + 1, **fields) if fields else em

    def render(fields: dict, seed: int) -> dict[str, np.ndarray]:
        img = local.render(errors(fields), seed)
        return {k: f(img)[cut] for k, f in models.items()}

    t0 = time.perf_counter()
    full = [Renderer(cfg, errors({})).render(frame.scene, rays=frame.rays, seed=s).photons for s in SEEDS]
    nominal_full = {k: 0.5 * (f(full[0]) + f(full[1]))[cut] for k, f in models.items()}
    nominal = [render({}, s) for s in SEEDS]
    sensor = cfg.sensor
    info, scale, sd = {}, {}, {}
    for k in models:
        mean = nominal_full[k]
        scale[k] = FILL * sensor.full_well_e / (sensor.qe * mean.max())  # photons per rendered photon
        sig_e = sensor.qe * scale[k] * np.clip(mean, 0.0, None)
        sd[k] = np.sqrt(sig_e + sensor.read_noise_e ** 2)
        info[k] = {"scale": scale[k], "lit_fraction": float(np.mean(sig_e > 0.05 * sig_e.max())),
                   "peak_max": 0.0, "peak_name": "", "outer_share": {}}
    vecs = {k: {} for k in models}  # model -> name -> (mean image, delta image), noise units
    for name, fields in hyps:
        halves = [render(fields, s) for s in SEEDS]
        for k in models:
            h = [sensor.qe * scale[k] * (hv[k] - nv[k]) / sd[k] for hv, nv in zip(halves, nominal)]
            vecs[k][name] = (0.5 * (h[0] + h[1]), h[0] - h[1])
            if name in TARGETS:
                diff = 0.5 * ((halves[0][k] - nominal[0][k]) + (halves[1][k] - nominal[1][k]))
                peak = float(np.max(sensor.qe * scale[k] * (nominal_full[k] + diff)) / sensor.full_well_e)
                if peak > info[k]["peak_max"]:
                    info[k]["peak_max"], info[k]["peak_name"] = peak, name
    n_rays = local.per_cell * 9 if (local.per_cell and isinstance(local.scene, WhiteScene)) else local.rays
    log(f"{frame.key} [{boundaries or 'grid'}]: {2 * (len(hyps) + 1)} renders of {n_rays / 1e6:.1f} M rays "
        f"in {time.perf_counter() - t0:.0f} s")
    names = [name for name, _ in hyps]
    directional = [n for n in names if n.startswith(("P", "D"))]
    gm, gd, gx = {}, {}, {}
    for k in models:
        for n in directional:  # the square's symmetry: +90 deg = the image rotated counterclockwise
            m_img, d_img = vecs[k][n]
            vecs[k][n + "+90"] = (np.rot90(m_img), np.rot90(d_img))
        all_names = names + [n + "+90" for n in directional]
        mats = np.stack([vecs[k][n][0].ravel() for n in all_names])
        dels = np.stack([vecs[k][n][1].ravel() for n in all_names])
        gm[k], gd[k], gx[k] = mats @ mats.T, dels @ dels.T, mats @ dels.T
        for n in ("P0_1", "D0_5", rname(0.03), rname(-0.03)):  # detection energy outside the inner 3 x 3
            if n in vecs[k]:
                m_img, d_img = vecs[k][n]
                tot = np.sum(m_img ** 2) - np.sum(d_img ** 2) / 4
                inn = np.sum(m_img[inner] ** 2) - np.sum(d_img[inner] ** 2) / 4
                info[k]["outer_share"][n] = 1.0 - inn / tot if tot > 0 else float("nan")
    return FrameData(names + [n + "+90" for n in directional], gm, gd, gx, info)


# --- ideal-observer figures on Gram matrices ---------------------------------------------------------------

class Stats:
    """Gram matrices of one protocol (its frames' summed) for one image model."""

    def __init__(self, names: list[str], gm: np.ndarray, gd: np.ndarray, gx: np.ndarray) -> None:
        self.idx = {n: i for i, n in enumerate(names)}
        self.gm, self.gd = gm, gd
        sym = 0.5 * (gx + gx.T)
        self.gh = (gm + sym + gd / 4, gm - sym + gd / 4)  # Grams of half 1 (mean + d/2) and half 2 (mean - d/2)

    def detect(self, t: str) -> float:
        i = self.idx[t]
        return float(np.sqrt(max(self.gm[i, i] - self.gd[i, i] / 4, 0.0)))

    def detect_spread(self, t: str) -> float:
        i = self.idx[t]
        noise = self.gd[i, i] / 4
        return spread_z(self.gm[i, i] - noise, [g[i, i] - 2 * noise for g in self.gh])

    def noise(self, t: str) -> float:
        """Monte-Carlo noise energy subtracted from a detection (noise units squared)."""
        i = self.idx[t]
        return float(self.gd[i, i] / 4)

    def separate(self, t: str, knots: list[tuple[float, str]], perp: bool, fine: int = 400):
        """min over the family's magnitude (spline through 0 and the knots) of the noise-corrected
        residual energy; with `perp` the coefficients on the m-basis and its +90 deg twin are free.
        Returns (z, best magnitude, at the grid's end?)."""
        ms = np.array([0.0] + [m for m, _ in knots])
        order = np.argsort(ms)
        ms = ms[order]
        grid = np.linspace(ms[0], ms[-1], fine)
        w = CubicSpline(ms, np.eye(len(ms)), axis=0)(grid)  # (fine, K): spline weights, linear in the data
        keep = [j for j, o in enumerate(order) if o != 0]  # drop the zero knot (a zero vector)
        w = w[:, keep]
        names = [n for _, n in sorted(knots)]
        ti = self.idx[t]
        a_idx = [self.idx[n] for n in names]
        b_idx = [self.idx[n + "+90"] for n in names] if perp else []

        def quad(g):
            def blk(r, c):
                return np.einsum("fk,kl,fl->f", w, g[np.ix_(r, c)], w)
            out = {"aa": blk(a_idx, a_idx), "at": w @ g[a_idx, ti], "tt": g[ti, ti]}
            if perp:
                out.update(ab=blk(a_idx, b_idx), bb=blk(b_idx, b_idx), bt=w @ g[b_idx, ti])
            return out

        qm, qd = quad(self.gm), quad(self.gd)
        if perp:
            det = qm["aa"] * qm["bb"] - qm["ab"] ** 2
            det = np.where(np.abs(det) > 1e-12, det, 1e-12)
            ca = (qm["bb"] * qm["at"] - qm["ab"] * qm["bt"]) / det
            cb = (qm["aa"] * qm["bt"] - qm["ab"] * qm["at"]) / det
        else:
            ca, cb = np.ones(len(grid)), np.zeros(len(grid))

        def energy(q):
            e = q["tt"] - 2 * ca * q["at"] + ca * ca * q["aa"]
            if perp:
                e = e - 2 * cb * q["bt"] + 2 * ca * cb * q["ab"] + cb * cb * q["bb"]
            return e

        noise = energy(qd) / 4
        z2 = energy(qm) - noise
        k = int(np.argmin(z2))
        # Monte-Carlo spread: the same residual from each half alone (noise energy 2 x the mean's)
        halves = [energy(quad(g))[k] - 2 * noise[k] for g in self.gh]
        return (float(np.sqrt(max(z2[k], 0.0))), float(grid[k]), k == len(grid) - 1, float(noise[k]),
                spread_z(z2[k], halves))


def spread_z(z2: float, halves: list[float]) -> float:
    """Rough 1-sigma Monte-Carlo uncertainty of z from the two halves' own estimates of z^2."""
    sd2 = 0.5 * abs(halves[0] - halves[1])
    z = np.sqrt(max(z2, 0.0))
    return float(min(sd2 / (2 * z), np.sqrt(sd2))) if z > 0 else float(np.sqrt(sd2))


def sum_stats(frames: list[FrameData], model: str) -> Stats:
    names = frames[0].names
    return Stats(names, sum(f.gm[model] for f in frames), sum(f.gd[model] for f in frames),
                 sum(f.gx[model] for f in frames))


def figures(st: Stats, grids: dict) -> dict:
    """Every number of one table row."""
    out = {}
    dec0 = [(m, f"D0_{m:g}") for m in grids["dec0"]]
    dec45 = [(m, f"D45_{m:g}") for m in grids["dec45"]]
    pit0 = [(m, f"P0_{m:g}") for m in grids["pitch0"]]
    out["p1_0"] = st.separate("P0_1", dec0, perp=True)
    out["p1_45"] = st.separate("P45_1", dec45, perp=True)
    for d in DEC_TARGETS:
        out[f"d{d:g}"] = st.separate(f"D0_{d:g}", pit0, perp=True)
    neg = [(e, rname(-e)) for e in grids["radius"]]
    pos = [(e, rname(e)) for e in grids["radius"]]
    for e in RADIUS_TARGETS:
        out[f"det{e:+g}"] = (st.detect(rname(e)), st.detect_spread(rname(e)))
        out[f"sign{e:+g}"] = st.separate(rname(e), pos if e < 0 else neg, perp=False)
    out["det_p1"] = st.detect("P0_1")
    out["det_d5"] = st.detect("D0_5")
    return out


# --- output ------------------------------------------------------------------------------------------------

def col(v: float, edge: bool = False, spread: float = 0.0, width: int = 7) -> str:
    """A number right-aligned in width - 1 characters, then '*' if the fit ended at its grid's end, or '~'
    if its Monte-Carlo uncertainty exceeds a quarter of it (or 0.5 when it is small)."""
    text = ">999" if v > 999 else f"{v:.1f}"
    flag = "*" if edge else "~" if spread > max(0.25 * v, 0.5) else " "
    return f"{text:>{width - 1}s}" + flag


def cell(fit: tuple) -> str:
    return col(fit[0], fit[2], fit[4])


def print_table(title: str, rows: list[tuple[str, dict]]) -> None:
    rt = [f"{100 * e:+.0f}%" for e in RADIUS_TARGETS]
    w = 7 * len(RADIUS_TARGETS)
    print(f"\n{title}")
    print(f"{'':34s}|{'pitch 1µm vs dec.':^14s}|{'dec. vs pitch':^14s}|{'radius detection z':^{w}s}|{'radius sign separation z':^{w}s}|")
    print(f"{'protocol':34s}|{'0°=90°':>6s} {'45°':>6s} |{'5 µm':>6s} {'10 µm':>6s} |"
          + "".join(f"{r:>6s} " for r in rt) + "|" + "".join(f"{r:>6s} " for r in rt) + "|")
    print("-" * 34 + "+" + "-" * 14 + "+" + "-" * 14 + "+" + "-" * w + "+" + "-" * w + "+")
    for label, f in rows:
        line = f"{label:34s}|" + cell(f["p1_0"]) + cell(f["p1_45"]) + "|"
        line += "".join(cell(f[f"d{d:g}"]) for d in DEC_TARGETS) + "|"
        line += "".join(col(*f[f"det{e:+g}"][:1], spread=f[f"det{e:+g}"][1]) for e in RADIUS_TARGETS) + "|"
        line += "".join(cell(f[f"sign{e:+g}"]) for e in RADIUS_TARGETS) + "|"
        print(line)


def print_fits(rows: list[tuple[str, dict]]) -> None:
    """The best-fitting magnitude of the other family and the Monte-Carlo uncertainty of each z."""
    print("  best fit of the other family (± rough Monte-Carlo 1-sigma of the z above): pitch 1 µm @0°/@45° -> "
          "decenter µm, decenter 5/10 µm -> pitch µm, radius -10..+10 % -> opposite-sign radius %")
    keys = ["p1_0", "p1_45"] + [f"d{d:g}" for d in DEC_TARGETS]
    for label, f in rows:
        line = " ".join(f"{f[k][1]:4.2f}±{f[k][4]:<4.1f}" for k in keys) + " | "
        line += " ".join(f"{100 * f[f'sign{e:+g}'][1]:4.1f}±{f[f'sign{e:+g}'][4]:<4.1f}" for e in RADIUS_TARGETS)
        print(f"  {label:32s} {line}")


def protocol_rows(keys: list[str]) -> list[tuple[str, list[str]]]:
    """(label, frame keys): each candidate alone and with the white image; through-focus as pairs."""
    labels = {"W": "white f/2.5", "S8": "stop f/8", "S16": "stop f/16", "L450": "λ 450 nm", "L850": "λ 850 nm",
              "PC": "points→centres f/8", "PE": "points→edges f/8", "PK": "points→corners f/8"}
    singles = [k for k in keys if not k.startswith("T")]
    tf = sorted((k for k in keys if k.startswith("T")), key=lambda k: float(k[1:]))
    groups = [(labels.get(k, k), [k]) for k in singles if k != "W"]
    if "L450" in keys and "L850" in keys:
        groups.append(("λ 450+850 nm", ["L450", "L850"]))
    offs = sorted({abs(float(k[1:])) for k in tf})
    for u in offs:
        pair = [k for k in tf if abs(float(k[1:])) == u]
        groups.append(("TF u=" + "/".join(f"{float(k[1:]):+g}" for k in pair), pair))
    if len(offs) > 1:
        groups.append(("TF u=" + "/".join(f"{float(k[1:]):+g}" for k in tf), tf))
    if "PK" in keys and tf:  # the two strongest in grid mode together
        near = [k for k in tf if abs(float(k[1:])) == offs[0]]
        groups.append(("corners + TF u=" + "/".join(f"{float(k[1:]):+g}" for k in near), ["PK"] + near))
    rows = []
    if "W" in keys:
        rows.append(("white f/2.5 (baseline)", ["W"]))
    for label, ks in groups:
        rows.append((label, ks))
    if "W" in keys:
        for label, ks in groups:
            rows.append(("white + " + label, ["W"] + ks))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="~3 min: fewer frames (white, pinholes, TF ±2.5 mm), fewer rays")
    ap.add_argument("--boundaries", choices=("grid", "sag-intersection", "both"), default=None,
                    help="lens boundary model(s) (default: both if the tracer has mla.boundaries, else grid)")
    ap.add_argument("--frames", default=None, help=f"comma list of frames (default {FULL_FRAMES!r}; quick {QUICK_FRAMES!r})")
    ap.add_argument("--white-rpp", type=float, default=None, help="rays/pixel of the full nominal white-type renders (1000)")
    ap.add_argument("--lens-rays", type=float, default=None,
                    help="white-type difference renders: rays per MLA cell of the 3 x 3 around the lens, per half (2e6; quick 1e6)")
    ap.add_argument("--point-rays", type=float, default=None, help="rays per pinhole per half (2e5; quick 1e5)")
    ap.add_argument("--tf-rays", type=float, default=None, help="rays per through-focus half (6e6; quick 3e6)")
    ap.add_argument("--mla-abbe", type=float, default=pr.MLA_ABBE, help="Abbe number of the MLA material (Cauchy)")
    ap.add_argument("--fits", action="store_true", help="also print the best-fitting magnitudes")
    ap.add_argument("--legacy", action="store_true", help="the old bench: white-image detection table at a ray budget")
    ap.add_argument("--rays-per-pixel", type=float, default=50.0, help="--legacy: budget of the frame judged")
    ap.add_argument("--truth-rpp", type=float, default=3000.0, help="--legacy: rays/pixel of each truth half")
    args = ap.parse_args()
    if args.legacy:
        return legacy(args)
    t_start = time.perf_counter()
    grids = QUICK if args.quick else FULL
    keys = (args.frames or (QUICK_FRAMES if args.quick else FULL_FRAMES)).split(",")
    white_rpp = args.white_rpp or 1000.0
    per_cell = int(args.lens_rays or (1e6 if args.quick else 2e6))
    point_rays = int(args.point_rays or (1e5 if args.quick else 2e5))
    tf_rays = int(args.tf_rays or (3e6 if args.quick else 6e6))
    base = default_config()
    has_b = hasattr(base.mla, "boundaries")
    if args.boundaries in (None, "both"):
        models = ["grid", "sag-intersection"] if has_b else [None]
    else:
        if not has_b and args.boundaries != "grid":
            print("this tracer has no mla.boundaries: only 'grid' is available", file=sys.stderr)
            return 2
        models = [args.boundaries if has_b else None]
    cfg = patch_config(pr.frozen(base), LENSES)
    side = cfg.sensor.width_px
    frames = {}
    frames.update(pr.white_frames(cfg, int(white_rpp * side * side), args.mla_abbe))
    frames.update(pr.point_frames(cfg, point_rays, reach=C))
    frames.update(pr.through_focus_frames(cfg, TF_OFFSETS, tf_rays))
    unknown = [k for k in keys if k not in frames]
    if unknown:
        print(f"unknown frame(s) {unknown}; choose from {sorted(frames)}", file=sys.stderr)
        return 2
    hyps = hypotheses(grids)

    def log(s: str) -> None:
        print(f"  [{time.perf_counter() - t_start:6.0f} s] {s}", file=sys.stderr, flush=True)

    preamble(cfg, frames, keys)
    print(f"\nrenders: {len(hyps) + 1} per frame x 2 halves (seeds {SEEDS}); white-type {white_rpp:g} rays/pixel "
          f"({white_rpp * side * side / 1e6:.0f} M rays), pinholes {point_rays / 1e3:g} k rays each, through-focus "
          f"{tf_rays / 1e6:g} M rays; {LENSES} x {LENSES}-lens patch, {REGION_LENSES} x {REGION_LENSES}-lens region")
    print(f"grids: pitch {grids['pitch0']} µm (0°), decenter {grids['dec0']} µm (0°), {grids['dec45']} µm (45°), "
          f"radius ±{tuple(round(100 * e, 2) for e in grids['radius'])} %")
    for bmodel in models:
        data = {k: render_frame(frames[k], hyps, bmodel, per_cell, log) for k in keys}
        bname = bmodel or "grid (tracer without mla.boundaries)"
        print(f"\n=== lens boundaries: {bname} " + "=" * 60)
        print("frames (exposure for 80 % of full well at the brightest nominal pixel; geometric / with formation):")
        for k in keys:
            f, d = frames[k], data[k]
            g, fo = d.info["geo"], d.info["form"]
            unit = ("photons/px at relative irradiance 1" if isinstance(f.scene, WhiteScene)
                    else "photons per pinhole into the pupil")
            base_exp = f.cfg.sensor.exposure_photons if isinstance(f.scene, WhiteScene) else f.scene.photons
            sh = fo["outer_share"]
            print(f"  {k:6s} {f.label:26s} exposure {base_exp * g['scale']:9.3g} / {base_exp * fo['scale']:9.3g} {unit}; "
                  f"lit {100 * g['lit_fraction']:4.1f} % of px; brightest target {fo['peak_name']} {100 * fo['peak_max']:3.0f} % FW; "
                  f"z² outside 3x3: " + ", ".join(f"{n} {100 * v:.1f} %" for n, v in sh.items()))
        rows = protocol_rows(keys)
        for model, title in (("form", "with diffraction + crosstalk (mlaqc.optics.formation at each frame's wavelength)"),
                             ("geo", "geometric tracer alone")):
            table = [(label, figures(sum_stats([data[k] for k in ks], model), grids)) for label, ks in rows]
            print_table(f"[{bname}] ideal z, {title}", table)
            if args.fits:
                print_fits(table)
        if rows and rows[0][1] == ["W"]:
            f = figures(sum_stats([data["W"]], "form"), grids)
            print(f"  (white f/2.5 detection z with formation: pitch 1 µm {f['det_p1']:.0f}, decenter 5 µm {f['det_d5']:.0f})")
    print("\n* = best fit at the end of the family's grid (the true minimum may lie beyond: the figure is an upper bound); "
          "~ = Monte-Carlo uncertainty above a quarter of the figure (--fits prints it)")
    print(f"runtime {time.perf_counter() - t_start:.0f} s")
    return 0


def preamble(cfg, frames: dict, keys: list[str]) -> None:
    lay = cfg.layout
    print(f"camera: Table 1, geometry frozen at the matched layout (object {lay.object_distance_mm:.2f} mm, MLA "
          f"{lay.mla_distance_mm:.2f} mm from the rear vertex), sub-image pitch {lay.subimage_pitch_px:.3f} px")
    print("main lens point spot at the MLA (on axis; rms / r80 radius, µm; best = least-rms plane, + = towards the sensor):")
    for n in (2.5, 8.0, 16.0):
        c = pr.stopped(cfg, n)
        s0 = pr.spot_stats(c)
        dz = pr.best_focus_offset_mm(c, 15.0 if n < 4 else 2.0)
        sb = pr.spot_stats(c, dz_mm=dz)
        print(f"  f/{n:<4g} at the MLA rms {s0['rms_um']:7.1f} r80 {s0['r80_um']:7.1f}; best {dz:+.2f} mm: rms "
              f"{sb['rms_um']:6.1f} r80 {sb['r80_um']:6.1f}; Airy radius 1.22 λ N = {1.22 * 0.6328 * n:.1f}")
    pc, u = pr.point_focus(cfg)
    s = pr.spot_stats(pc)
    pts = pr.grid_points_mm(pc, "edges", C)
    m = pr.magnification(pc)
    err = pr.point_landing_error_um(pc, pts[:6], [(-x * m, -y * m) for x, y in pts[:6]])
    print(f"pinhole frames: f/8, object at {pc.geometry.object_distance_mm:.2f} mm (paraxial image {u:+.2f} mm behind the "
          f"MLA), spot on the MLA rms {s['rms_um']:.1f} µm, r80 {s['r80_um']:.1f} µm; object positions from the paraxial "
          f"magnification {m:.4f}; traced centroids land within {err:.2f} µm of the targets")
    for n in (8.0, 16.0):
        sc = pr.stop_check(pr.frozen(default_config()), n, 5.1)
        print(f"stop check f/{n:g}: share of the front-rim rays the rear rim cuts: on axis {100 * sc['axis']:.2f} %, "
              f"at the MLA corner (5.1, 5.1 mm) {100 * sc['corner']:.1f} % (the patch: 0)")
    for k in keys:
        f = frames[k]
        if f.note:
            print(f"  {k:6s} {f.label:26s} {f.note}")


def legacy(args) -> int:
    """The previous bench, unchanged: white image, 9 x 9 patch, 3 x 3 lenses, frame noise at a ray budget."""
    radius = (-0.1, -0.05, -0.03, 0.03, 0.05, 0.08, 0.1, 0.12, 0.15)
    c0 = 4
    cfg = patch_config(default_config())
    pitch_px = cfg.layout.subimage_pitch_px
    side = cfg.sensor.width_px
    lo = int(round((side - 1) / 2 - 1.5 * pitch_px))
    cut = (slice(lo, lo + int(round(3 * pitch_px))),) * 2

    def render(errors: ErrorMap, rpp: float, seed: int) -> np.ndarray:
        return Renderer(cfg, errors).render(WhiteScene(), rays_per_pixel=rpp, seed=seed).photons

    nominal = [render(ErrorMap.zeros(9, 9), args.truth_rpp, s) for s in (11, 12)]
    scale = float(np.median(nominal[0][cut]))
    frames = [expose(render(ErrorMap.zeros(9, 9), args.rays_per_pixel, s), cfg.sensor, seed=s).astype(float)
              for s in (21, 22)]
    black = cfg.sensor.black_level_dn
    frames = [(f - black) / np.median((f - black)[cut]) for f in frames]
    level = np.clip(0.5 * (nominal[0] + nominal[1])[cut] / scale, 0.0, None)
    pair_var = 0.5 * (frames[0][cut] - frames[1][cut]) ** 2
    gain, floor = np.linalg.lstsq(np.stack([level.ravel(), np.ones(level.size)], 1), pair_var.ravel(), rcond=None)[0]
    var = np.maximum(gain * level + floor, 1e-3 * gain)

    def difference(**fields) -> tuple[np.ndarray, float]:
        em = ErrorMap.zeros(9, 9).with_lens(c0 + 1, c0 + 1, **fields)
        halves = [(render(em, args.truth_rpp, s) - n)[cut] / scale for s, n in zip((11, 12), nominal)]
        return 0.5 * (halves[0] + halves[1]), float(np.sum((halves[0] - halves[1]) ** 2 / var)) / 4

    def z(d: np.ndarray, noise_energy: float) -> float:
        return float(np.sqrt(max(np.sum(d * d / var) - noise_energy, 0.0)))

    print(f"frame noise {100 * np.sqrt(gain + floor):.2f} % of the white level per white pixel at {args.rays_per_pixel:g} rays/pixel "
          f"(render + sensor); truth renders 2 x {args.truth_rpp:g} rays/pixel; 3 x 3 lenses, {cut[0].stop - lo} px square")
    print("ideal detection z of one lens' error (matched filter, error known):")
    for r in radius:
        print(f"  radius {100 * r:+5.0f} %: {z(*difference(radius_front_rel=r, radius_back_rel=r)):6.1f}")
    pitch = {(m, a): difference(pitch_um=m, pitch_dir_deg=a) for m in (1.0, 2.0, 3.0) for a in (0.0, 90.0)}
    for m in (1.0, 2.0, 3.0):
        print(f"  pitch {m:g} µm: {z(*pitch[(m, 0.0)]):6.1f}")
    for m in (2.0, 5.0, 10.0):
        dec, e_dec = difference(decenter_um=m, decenter_dir_deg=0.0)
        best = np.inf
        for p in (1.0, 2.0, 3.0):
            (b0, e0), (b90, e90) = pitch[(p, 0.0)], pitch[(p, 90.0)]
            basis = np.stack([b0.ravel(), b90.ravel()], axis=1)
            wt = 1.0 / np.sqrt(var.ravel())
            coef, *_ = np.linalg.lstsq(basis * wt[:, None], dec.ravel() * wt, rcond=None)
            rest = (dec.ravel() - basis @ coef).reshape(dec.shape)
            best = min(best, z(rest, e_dec + coef[0] ** 2 * e0 + coef[1] ** 2 * e90))
        print(f"  decenter {m:g} µm: detection {z(dec, e_dec):6.1f}, separation from the best pitch {best:6.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
