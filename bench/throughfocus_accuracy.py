"""How well the through-focus pair reads each microlens' focal length, with its sign (mlaqc.inspection.throughfocus),
on the Table 1 camera: seeded radius errors of ±3, ±5 and ±10 % (both radii scaled: the focal error of a
symmetric lens, truth from the thick-lens power), frames rendered through the tracer with the realistic
formation (microlens diffraction, 2 % crosstalk, PRNU) and read out by the sensor model with its shot and
read noise, at the protocol's own exposure (`pinhole_photons`: the pair's brightest healthy spot pixel at
FILL_FRACTION of full well, the same for every frame, as on a bench; a defective lens focused by its error
peaks higher, and a clipped spot is left out of its pair, as it would be), what `mlaqc simulate` does:
render -> `apply_formation` -> `expose`.

For each focus offset |u| (default: the shipped protocol, ±5 mm, f/11, pinholes 4 lenses apart) the frames are the +u / -u
pairs of the `coverage_offsets` that light a seeded lens fully (u = 5 mm reads only the lens under each
pinhole: 16 offsets cover the array at spacing 4, the bench takes those it needs, at least --min-pairs), the white
frame's grid calibrated on a white render. Printed per |u|:

- per seeded size: lenses read / found (|reading| > qc.detect_sigma sigma) / sign right / within 15 % of the truth,
  and the median ratio reading / truth;
- healthy lenses: scatter of focal_rel (sd, robust sd) and the detection limit it implies
  (qc.detect_sigma x sd), the median quoted sigma; the optical-centre readings' scatter (their truth is 0);
- the model gain (traced dD/dc over the paraxial one) and the analysis times: tracing the model (what
  a cold cache costs: no file in the package or in ~/.cache/mlaqc), the first analysis in the process
  (the model read from its file) and a warm one, with the stages' split.

    python bench/throughfocus_accuracy.py                 # ~10 min on 2 cores
    python bench/throughfocus_accuracy.py --quick         # ~3 min: fewer seeds and rays
    python bench/throughfocus_accuracy.py --u 5 --per-size 6 --rays-per-lens 50000
    python bench/throughfocus_accuracy.py -c fixtures/hex_small_camera.toml   # any camera: hex arrays too
    # the shipped protocol (issue #12), every pair rendered (the analysis time of a whole array):
    python bench/throughfocus_accuracy.py --per-size 4 --rays-per-lens 1e4 --white-rpp 20 --seed 2 --u 5 \
        --f-number 11 --spacing 4 --all-pairs
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mlaqc.inspection.calibrate import calibrate_for  # noqa: E402
from mlaqc.inspection.pipeline import prepare  # noqa: E402
from mlaqc.inspection.rawio import RawFrame  # noqa: E402
from mlaqc.inspection.throughfocus import measure_through_focus  # noqa: E402
from mlaqc.inspection.throughfocus_geometry import coverage  # noqa: E402
from mlaqc.inspection.throughfocus_model import trace_model  # noqa: E402
from mlaqc.inspection.throughfocus_optics import focal_rel_of_radius  # noqa: E402
from mlaqc.inspection.throughfocus_spots import SpotFrame, prepare_spots  # noqa: E402
from mlaqc.optics.config import default_config, load_config  # noqa: E402
from mlaqc.optics.errormap import ErrorMap  # noqa: E402
from mlaqc.optics.formation import apply_formation, formation_kernels  # noqa: E402
from mlaqc.optics.render import Renderer  # noqa: E402
from mlaqc.optics.sensor import expose, white_level  # noqa: E402
from mlaqc.optics.simulate import simulate  # noqa: E402
from mlaqc.optics.throughfocus import F_NUMBER, FILL_FRACTION, FOCUS_OFFSET_MM, SPACING_LENSES, ThroughFocus, blur_radius_mm, coverage_offsets, frame_config, inner_radius_lenses, pair_radius_lenses, scene  # noqa: E402

SIZES = (-0.10, -0.05, -0.03, 0.03, 0.05, 0.10)


def seeded_map(cfg, per_size: int, seed: int) -> tuple[ErrorMap, dict[tuple[int, int], float]]:
    """Random lenses (two in from the edge, three apart) with both radii scaled by 1 + eps."""
    rng = np.random.default_rng(seed)
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    em, truth, taken = ErrorMap.zeros(rows, cols, cfg.mla.packing), {}, np.zeros((rows, cols), bool)
    tries = 0
    for eps in SIZES:
        k = 0
        while k < per_size:
            tries += 1
            if tries > 100_000:
                raise SystemExit(f"cannot place {per_size} lenses per size, three apart, on a {rows} x {cols} array: "
                                 "use a smaller --per-size")
            m, n = int(rng.integers(2, rows - 2)), int(rng.integers(2, cols - 2))
            if taken[max(m - 3, 0):m + 4, max(n - 3, 0):n + 4].any():
                continue
            taken[m, n] = True
            em = em.with_lens(m + 1, n + 1, radius_front_rel=eps, radius_back_rel=eps)
            truth[(m, n)] = eps
            k += 1
    return em, truth


def white_grid(cfg, rpp: float, seed: int):
    t = time.perf_counter()
    sim = simulate(cfg, rays_per_pixel=rpp, seed=seed)
    s = cfg.sensor
    img = prepare(RawFrame(sim.raw, s.bit_depth, None, s.black_level_dn, white_level(s)))
    grid = calibrate_for(img, cfg)
    print(f"white frame: {rpp:g} rays/pixel, calibrated in {time.perf_counter() - t:.1f} s "
          f"(grid rms residual {grid.rms_residual_px:.4f} px)", flush=True)
    return grid


def frame(cfg, em, tf: ThroughFocus, rays: int, seed: int, kernels) -> SpotFrame:
    """Render at the protocol's exposure (the scene's derived photons per pinhole), form, expose, prepare
    for the spot reading."""
    s = cfg.sensor
    ph = Renderer(frame_config(cfg, tf), em).render(scene(cfg, tf), rays=rays, seed=seed).photons
    ph = apply_formation(ph, cfg, kernels)
    raw = expose(ph, s, seed=seed + 1, noise=True)
    return prepare_spots(RawFrame(raw, s.bit_depth, None, s.black_level_dn, white_level(s)))


def run_u(cfg, grid, em, truth, u: float, rays_per_lens: float, min_pairs: int, seed: int, kernels,
          f_number: float = F_NUMBER, spacing: int = SPACING_LENSES, all_pairs: bool = False) -> None:
    tf0 = ThroughFocus(focus_offset_mm=u, f_number=f_number, spacing_lenses=spacing)
    offsets = coverage_offsets(cfg, tf0)
    read_all = np.zeros((cfg.mla.count_h, cfg.mla.count_w), bool)
    for off in offsets:  # what the analysis itself reads (its rim margin) when every offset is run
        read_all |= coverage(cfg, replace(tf0, offset_lenses=off))[0]
    r_pm = [blur_radius_mm(cfg, replace(tf0, focus_offset_mm=v)) / (cfg.mla.pitch_um * 1e-3) for v in (u, -u)]
    print(f"\n|u| = {u:g} mm, f/{f_number:g}, spacing {spacing}: disc radius +u {r_pm[0]:.2f} / -u {r_pm[1]:.2f} lenses "
          f"(discs {'overlap' if 2 * max(r_pm) >= spacing else 'apart'}), inner radius "
          f"{min(inner_radius_lenses(cfg, replace(tf0, focus_offset_mm=v)) for v in (u, -u)):.2f}, analysis pair radius "
          f"{pair_radius_lenses(cfg, tf0):.2f}; {len(offsets)} coverage offsets = {2 * len(offsets)} frames to cover, "
          f"which let the analysis read {read_all.mean():.2%} of the lenses ({(~read_all).sum()} missed)", flush=True)
    if grid is None:
        return
    useful, rest = [], []
    for off in offsets:
        lit = coverage(cfg, replace(tf0, offset_lenses=off))[0]
        (useful if any(lit[k] for k in truth) else rest).append(off)
    rng = np.random.default_rng(seed)
    extra = [rest[i] for i in rng.permutation(len(rest))[:max(0, min_pairs - len(useful))]]
    chosen = list(offsets) if all_pairs else useful + extra
    r_disc = max(blur_radius_mm(cfg, replace(tf0, focus_offset_mm=v)) for v in (u, -u)) / (cfg.mla.pitch_um * 1e-3)
    rays_per_pinhole = int(rays_per_lens * np.pi * r_disc ** 2)
    print(f"|u| = {u:g} mm: {len(offsets)} coverage offsets, {len(chosen)} pairs rendered ({len(useful)} light a seeded "
          f"lens); disc radius {r_disc:.2f} lenses, {rays_per_pinhole / 1e3:.0f} k rays per pinhole", flush=True)
    frames = []
    t = time.perf_counter()
    for j, off in enumerate(chosen):
        for sign in (1, -1):
            tf = replace(tf0, focus_offset_mm=sign * u, offset_lenses=off)
            n_pins = len(scene(cfg, tf).points_mm)
            frames.append((frame(cfg, em, tf, rays_per_pinhole * n_pins, seed + 2 * j + (sign < 0), kernels), tf))
    render_s = time.perf_counter() - t
    t = time.perf_counter()
    trace_model(cfg, u, f_number, pair_radius_lenses(cfg, tf0))  # what the first use on a cold cache adds
    trace_s = time.perf_counter() - t
    t = time.perf_counter()
    res = measure_through_focus(frames, grid, cfg)
    first_s = time.perf_counter() - t
    warm = []
    for _ in range(3):  # the model is in memory now: the per-array cost
        t = time.perf_counter()
        res = measure_through_focus(frames, grid, cfg)
        warm.append(time.perf_counter() - t)
    again_s = float(np.median(warm))
    print(f"rendered {len(frames)} frames in {render_s:.0f} s; analysis of the {len(chosen)} pairs: first in this process "
          f"{first_s:.2f} s (the model read from the package or ~/.cache/mlaqc; tracing it, on a cold cache, adds "
          f"{trace_s:.1f} s), warm {again_s:.3f} s (median of 3) = {1e3 * again_s / len(chosen):.0f} ms per frame pair; "
          f"stages {res.timings_s}", flush=True)
    z_limit = cfg.qc.detect_sigma
    print(f"  {'seeded eps':>10} {'focal':>7} {'read':>5} {'found':>6} {'sign':>5} {'<=15%':>6} {'median read/truth':>18}")
    for eps in SIZES:
        keys = [k for k, v in truth.items() if v == eps]
        truth_f = float(focal_rel_of_radius(cfg, eps))
        read = [k for k in keys if res.covered[k]]
        vals = np.array([res.focal_rel[k] for k in read])
        sig = np.array([res.focal_sigma_rel[k] for k in read])
        found = int(np.sum(np.abs(vals) > z_limit * sig))
        sign = int(np.sum(np.sign(vals) == np.sign(truth_f)))
        within = int(np.sum(np.abs(vals - truth_f) <= 0.15 * abs(truth_f)))
        ratio = f"{np.median(vals / truth_f):.3f}" if len(vals) else "-"
        print(f"  {100 * eps:>+9.0f}% {100 * truth_f:>+6.2f}% {len(read):>2}/{len(keys):<2} {found:>6} {sign:>5} {within:>6} {ratio:>18}")
    healthy = res.covered.copy()
    for k in truth:
        healthy[k] = False
    f = res.focal_rel[healthy]
    sd = float(np.std(f))
    rsd = 1.4826 * float(np.median(np.abs(f - np.median(f))))
    false = int(np.sum(np.abs(f) > z_limit * res.focal_sigma_rel[healthy]))
    print(f"  healthy lenses read: {healthy.sum()}; focal_rel sd {100 * sd:.3f} % (robust {100 * rsd:.3f} %), max |.| "
          f"{100 * np.abs(f).max():.3f} %, median quoted sigma {100 * np.median(res.focal_sigma_rel[healthy]):.3f} % "
          f"-> detection limit ({z_limit:g} sd) {100 * z_limit * sd:.2f} %; flagged (beyond {z_limit:g} quoted sigma) {false}")
    cx, cy = res.centre_dx_um[healthy], res.centre_dy_um[healthy]
    ok = np.isfinite(cx) & np.isfinite(cy)
    if ok.any():
        print(f"  optical-centre readings of healthy lenses (truth 0): rms {np.sqrt(np.mean(cx[ok] ** 2 + cy[ok] ** 2) / 2):.3f} µm "
              f"per axis, median quoted sigma {np.nanmedian(res.centre_sigma_um[healthy]):.3f} µm")
    p = res.pairs[0]
    print(f"  model gain {p.gain:.3f} (traced dD/dc over paraxial), Birge ratio {p.birge:.2f}, median window "
          f"{np.median([q.window_px for q in res.pairs]):.2f} px, saturated spots {sum(q.saturated for q in res.pairs)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--u", default=f"{FOCUS_OFFSET_MM:g}", help="focus offsets |u| in mm, comma-separated (default: the "
                    "shipped protocol's)")
    ap.add_argument("--per-size", type=int, default=None,
                    help="seeded lenses per error size (default 4; 2 on arrays of fewer than 2500 lenses, which hold no more three apart)")
    ap.add_argument("--rays-per-lens", type=float, default=20000.0, help="rays per lit lens (default 2e4)")
    ap.add_argument("--min-pairs", type=int, default=9, help="render at least this many pairs per |u| (default 9)")
    ap.add_argument("--white-rpp", type=float, default=50.0, help="rays per pixel of the white frame (default 50)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--f-number", type=float, default=F_NUMBER, help=f"main lens stopped to f/N (default {F_NUMBER:g})")
    ap.add_argument("--spacing", type=int, default=SPACING_LENSES,
                    help=f"pinhole lattice spacing in lens pitches (default {SPACING_LENSES})")
    ap.add_argument("--all-pairs", action="store_true",
                    help="render every coverage offset's pair (a whole array's analysis time), not only those lighting a seeded lens")
    ap.add_argument("--geometry-only", action="store_true",
                    help="print the coverage geometry of each |u| (offsets, frames to cover, lenses read) and stop")
    ap.add_argument("-c", "--config", default=None, help="camera config TOML (default: Table 1)")
    ap.add_argument("--quick", action="store_true", help="2 lenses per size, 1e4 rays per lens, 20 rays/pixel white")
    args = ap.parse_args()
    if args.quick:
        args.per_size, args.rays_per_lens, args.white_rpp = 2, 1e4, 20.0
    cfg = load_config(args.config) if args.config else default_config()
    if args.per_size is None:
        args.per_size = 4 if cfg.mla.count_h * cfg.mla.count_w >= 2500 else 2
    name = args.config or "Table 1 camera"
    if args.geometry_only:
        for u in (float(v) for v in args.u.split(",")):
            run_u(cfg, None, None, {}, u, 0.0, 0, 0, None, args.f_number, args.spacing)
        return
    em, truth = seeded_map(cfg, args.per_size, args.seed)
    print(f"{name} ({cfg.mla.packing}, {cfg.mla.count_w} x {cfg.mla.count_h} lenses), f/{args.f_number:g}, pinholes {args.spacing} lenses apart; {len(truth)} seeded lenses ({args.per_size} per size), "
          f"{args.rays_per_lens:g} rays per lit lens, formation + sensor noise at the protocol's exposure "
          f"(healthy peak {FILL_FRACTION:.0%} of full well)", flush=True)
    grid = white_grid(cfg, args.white_rpp, args.seed + 100)
    kernels = formation_kernels(cfg, (cfg.sensor.height_px, cfg.sensor.width_px))
    for u in (float(v) for v in args.u.split(",")):
        run_u(cfg, grid, em, truth, u, args.rays_per_lens, args.min_pairs, args.seed + 1000, kernels,
              args.f_number, args.spacing, args.all_pairs)


if __name__ == "__main__":
    main()
