"""Benchmark: calibrate + divide on a 2048 x 2048 white frame of the Table 1 camera, and its accuracy.

    python bench/calibrate.py [--rays-per-pixel 50] [--seed 1] [--no-noise] [--rotation-deg A]
                              [--vignetting F] [--repeat 5] [--steps] [--raw FILE [--config C]]
                              [--threads N] [--no-truth] [--packing hex [--noise N]] [--bars]

--packing hex calibrates a hexagonal array of the Table 1 size (102 columns x 116 rows at the Table 1
sub-image pitch on 2048 x 2048) rendered by the independent analytic model (tests/analytic_frames.py,
--noise: relative shot noise at full signal, default 0) against its exact centres. --bars prints the hex
bars: on that model, noise-free and noisy, hex against the square 102 x 102 array (every lens found, per-lens
centre RMS per axis, calibration time and the hex / square ratio).

The frame is rendered once (about 20-35 s at 50 rays/pixel; --rotation-deg renders a rotated MLA) and
kept in ~/.cache/mlaqc-bench, or read from --raw (any file mlaqc.inspection.rawio.load_raw reads). --vignetting F
multiplies the frame by 1 - F r^2 (r = distance from the centre / half the height; F = 0.3 leaves 40 %
in the corners). Timings: wall clock and process CPU, best and median of --repeat runs after one
warm-up; --steps adds the best wall time of each calibration step. Accuracy (rendered frames only): per-lens measured centres and grid
centres against the ray-traced sub-image centres of tests/calib_images.py, and against the first-order
layout (p(b+f)/b spacing about the sensor centre) for comparison.
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import mlaqc.inspection.calibrate as calibration  # noqa: E402
import mlaqc.inspection.disc_fit as disc_fit  # noqa: E402
import mlaqc.inspection.fourier_lattice as fourier_lattice  # noqa: E402
from mlaqc.inspection.calibrate import calibrate  # noqa: E402
from mlaqc.inspection.raw_levels import normalized, suppress_hot_pixels  # noqa: E402
from mlaqc.inspection.rawio import load_raw  # noqa: E402
from mlaqc.inspection.subimages import divide  # noqa: E402
from mlaqc.optics.config import default_config, load_config  # noqa: E402


def mla_errors(rotation_deg: float):
    """The rendered MLA's global errors (None: a perfect MLA)."""
    if not rotation_deg:
        return None
    from mlaqc.optics.errormap import ErrorMap

    cfg = default_config()
    return ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w).with_globals(mla_rotation_deg=rotation_deg)


def rendered_frame(rpp: float, seed: int, noise: bool, rotation_deg: float = 0.0) -> np.ndarray:
    """Raw counts of the default camera's white image, rendered once and cached."""
    cfg = default_config()
    tag = f"{rpp}-{seed}-{noise}" + (f"-rot{rotation_deg:g}" if rotation_deg else "")
    key = hashlib.sha256(tag.encode()).hexdigest()[:12]
    cache = Path.home() / ".cache" / "mlaqc-bench"
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / f"white-table1-{key}.npy"
    if not path.exists():
        from mlaqc.optics.simulate import simulate

        t = time.perf_counter()
        sim = simulate(cfg, None, mla_errors(rotation_deg), rays_per_pixel=rpp, seed=seed, noise=noise)
        print(f"rendered the white frame ({rpp} rays/pixel, seed {seed}) in {time.perf_counter() - t:.1f} s -> {path}")
        np.save(path.with_suffix(".part.npy"), sim.raw)
        path.with_suffix(".part.npy").replace(path)
    return np.load(path)


def timed(fn, repeat: int):
    fn()  # warm-up (imports, thread pool, page faults)
    wall, cpu, out = [], [], None
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return out, wall, cpu


# calibration steps timed by --steps (calibrate's module functions, called from calibrate(), and disc-fit methods;
# nested ones included in their callers)
STEPS = ("_check_levels", "_fft_lattice", "_candidates", "_radius_guess", "_measure", "_DiscFit._normals",
         "_DiscFit.iterate", "_assemble", "_fit_model")


def step_times(fn, repeat: int) -> dict[str, float]:
    """Best wall seconds of each of STEPS (summed over its calls within one run) over `repeat` runs of fn."""
    acc: dict[str, float] = {}
    saved = []

    def wrap(owner, attr, label):
        f = getattr(owner, attr)
        saved.append((owner, attr, f))

        def timed_call(*a, **k):
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                acc[label] = acc.get(label, 0.0) + time.perf_counter() - t

        setattr(owner, attr, timed_call)

    for label in STEPS:
        owner, _, attr = label.rpartition(".")
        wrap(getattr(disc_fit, owner) if owner else calibration, attr, label)
    best: dict[str, float] = {}
    try:
        for _ in range(repeat):
            acc.clear()
            t = time.perf_counter()
            fn()
            acc["total"] = time.perf_counter() - t
            for k, v in acc.items():
                best[k] = min(best.get(k, float("inf")), v)
    finally:
        for owner, attr, f in saved:
            setattr(owner, attr, f)
    return best


def analytic_frame(packing: str, noise: float, seed: int = 1, rotation_deg: float = 0.3):
    """(model, normalized float32 frame) of the Table 1 size array on the analytic model: square 102 x 102,
    hex 102 columns x 116 rows; the model's centre at 80 % of full scale."""
    from analytic_frames import AnalyticModel, expose

    lenses = (116, 102) if packing == "hex" else (102, 102)
    model = AnalyticModel(shape=(2048, 2048), lenses=lenses, packing=packing, rotation_deg=rotation_deg,
                          phase_px=(0.21, -0.4))
    img = (0.8 * expose(model.render(), noise, np.random.default_rng(seed))).astype(np.float32)
    return model, img


def analytic_figures(model, img, packing: str, repeat: int) -> dict[str, float]:
    """Calibrate `img` (timed: best of `repeat`) and measure against the model's exact centres."""
    kw = dict(expected_pitch_px=model.pitch_px, expected_shape=model.lenses, packing=packing)
    grid, wall, _ = timed(lambda: calibrate(img, **kw), repeat)
    x, y = model.centres()
    sel = model.inside() & ~grid.clipped
    ex, ey = (grid.measured_x_px - x)[sel], (grid.measured_y_px - y)[sel]
    gx, gy = (grid.grid_x_px - x)[sel], (grid.grid_y_px - y)[sel]
    return {"lenses": grid.rows * grid.cols, "found": grid.lenses_found,
            "missing_on_sensor": int(np.count_nonzero(grid.missing & model.inside())),
            "rms_axis": float(np.sqrt(np.nanmean(np.concatenate([ex, ey]) ** 2))),
            "max": float(np.nanmax(np.hypot(ex, ey))),
            "grid_rms_axis": float(np.sqrt(np.mean(np.concatenate([gx, gy]) ** 2))),
            "time_s": min(wall), "time_median_s": statistics.median(wall),
            "pitch": grid.pitch_px, "rotation": grid.rotation_deg, "shear": grid.shear_deg}


def print_figures(label: str, f: dict) -> None:
    print(f"  {label:28s} {f['found']:5d}/{f['lenses']} found ({f['missing_on_sensor']} on the sensor missing), "
          f"centres RMS {f['rms_axis']:.4f} px per axis (max {f['max']:.3f}), grid {f['grid_rms_axis']:.4f}; "
          f"pitch {f['pitch'][0]:.4f} x {f['pitch'][1]:.4f}, rotation {f['rotation']:+.4f}, shear {f['shear']:+.4f} deg; "
          f"calibrate best {f['time_s'] * 1e3:.0f} ms (median {f['time_median_s'] * 1e3:.0f})")


def bars(repeat: int) -> int:
    """The hex bars on the analytic model (noise-free and noisy), hex against square."""
    print("analytic model (tests/analytic_frames.py), 2048 x 2048, rotation 0.3 deg, Gaussian rim 0.5 px, "
          "radius 9.75 px, cos^4 vignetting, PRNU 0.5 %, crosstalk 2 %")
    out = {}
    for noise in (0.0, 0.01, 0.05):
        print(f"noise {noise:g} (relative, at full signal):")
        for packing in ("square", "hex"):
            model, img = analytic_frame(packing, noise)
            out[packing, noise] = f = analytic_figures(model, img, packing, repeat)
            print_figures(f"{packing} {model.lenses[1]} x {model.lenses[0]}", f)
    clean = out["hex", 0.0]
    print("bars:")
    print(f"  noise-free hex: every lens on the sensor found: {clean['missing_on_sensor'] == 0}; per-lens centre RMS "
          f"{clean['rms_axis']:.4f} px per axis (bar <= 0.01): {clean['rms_axis'] <= 0.01}")
    for noise in (0.01, 0.05):
        h, q = out["hex", noise]["rms_axis"], out["square", noise]["rms_axis"]
        print(f"  noise {noise:g}: per-lens centre RMS hex {h:.4f} / square {q:.4f} px per axis (ratio {h / q:.2f})")
    ratios = [out["hex", n]["time_s"] / out["square", n]["time_s"] for n in (0.0, 0.01, 0.05)]
    print(f"  calibration time hex / square (best of {repeat}) at noise 0 / 0.01 / 0.05: "
          + " / ".join(f"{r:.2f}" for r in ratios) + " (bar: inspection within 1.2x; "
          f"{out['hex', 0.0]['lenses']} / {out['square', 0.0]['lenses']} lenses = "
          f"{out['hex', 0.0]['lenses'] / out['square', 0.0]['lenses']:.2f})")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rays-per-pixel", type=float, default=50.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-noise", action="store_true")
    ap.add_argument("--rotation-deg", type=float, default=0.0, help="render an MLA rotated by this much")
    ap.add_argument("--vignetting", type=float, default=0.0, help="multiply the frame by 1 - F r^2")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--steps", action="store_true", help="also time each calibration step")
    ap.add_argument("--raw", help="a white raw file instead of the rendered one")
    ap.add_argument("--config", help="camera config of --raw (default: Table 1)")
    ap.add_argument("--threads", type=int, help="worker threads of the disc fit (default: one per core, max 4)")
    ap.add_argument("--no-truth", action="store_true", help="skip the accuracy figures")
    ap.add_argument("--packing", choices=("square", "hex"), default="square",
                    help="hex: the Table 1 size hex array on the analytic model (see above)")
    ap.add_argument("--noise", type=float, default=0.0, help="with --packing hex: relative noise at full signal")
    ap.add_argument("--bars", action="store_true", help="print the hex bars (analytic model, hex vs square)")
    args = ap.parse_args()
    if args.threads:
        disc_fit._workers = fourier_lattice._workers = lambda: args.threads  # noqa: E731
    if args.bars:
        return bars(args.repeat)
    if args.packing == "hex":
        model, img = analytic_frame("hex", args.noise, args.seed, args.rotation_deg or 0.3)
        print(f"frame: 2048x2048 px (analytic model, hex {model.lenses[1]} x {model.lenses[0]}, noise {args.noise:g}, "
              f"rotation {model.rotation_deg:g} deg)")
        print_figures("hex", analytic_figures(model, img, "hex", args.repeat))
        return 0
    cfg = load_config(args.config) if args.raw else default_config()
    if args.raw:
        frame = load_raw(args.raw)
        img, _ = suppress_hot_pixels(normalized(frame), frame.cfa)
        source = args.raw
    else:
        from calib_images import normalize

        img = normalize(rendered_frame(args.rays_per_pixel, args.seed, not args.no_noise, args.rotation_deg), cfg)
        source = (f"rendered, {args.rays_per_pixel:g} rays/pixel, seed {args.seed}, "
                  f"noise {'off' if args.no_noise else 'on'}, rotation {args.rotation_deg:g} deg")
    if args.vignetting:
        h, w = img.shape
        yy, xx = np.mgrid[0:h, 0:w]
        r2 = ((xx - 0.5 * (w - 1)) ** 2 + (yy - 0.5 * (h - 1)) ** 2) / (0.5 * h) ** 2
        img = img * (1.0 - args.vignetting * r2).astype(np.float32)
        source += f", vignetting 1 - {args.vignetting:g} r^2"
    kw = dict(expected_pitch_px=cfg.layout.subimage_pitch_px, expected_shape=(cfg.mla.count_h, cfg.mla.count_w),
              packing=cfg.mla.packing)
    grid, cal_wall, cal_cpu = timed(lambda: calibrate(img, **kw), args.repeat)
    sub, div_wall, div_cpu = timed(lambda: divide(img, grid), args.repeat)
    both = [a + b for a, b in zip(cal_wall, div_wall)]
    print(f"frame: {img.shape[1]}x{img.shape[0]} px ({source})")
    print(f"grid: {grid.rows}x{grid.cols} lenses, {grid.lenses_found} found, {grid.lenses_missing} missing, "
          f"pitch {grid.pitch_px[0]:.5f} x {grid.pitch_px[1]:.5f} px, rotation {grid.rotation_deg:+.5f} deg, "
          f"rms residual {grid.rms_residual_px:.4f} px; sub-images {sub.data.shape}")
    for name, wall, cpu in (("calibrate", cal_wall, cal_cpu), ("divide", div_wall, div_cpu), ("both", both, None)):
        extra = f", cpu median {statistics.median(cpu) * 1e3:6.1f} ms" if cpu else ""
        print(f"  {name:9s} wall best {min(wall) * 1e3:6.1f} ms, median {statistics.median(wall) * 1e3:6.1f} ms{extra}")
    if args.steps:
        for name, best in step_times(lambda: calibrate(img, **kw), args.repeat).items():
            print(f"    {name:28s} {best * 1e3:6.1f} ms")
    if args.raw or args.no_truth:
        return 0
    from calib_images import layout_centres, true_centres

    def report(label, tx, ty):
        ex, ey = grid.measured_x_px - tx, grid.measured_y_px - ty
        gx, gy = grid.grid_x_px - tx, grid.grid_y_px - ty
        per_axis = np.sqrt(np.nanmean(np.concatenate([ex.ravel(), ey.ravel()]) ** 2))
        print(f"  vs {label:34s} measured: RMS {np.sqrt(np.nanmean(ex ** 2 + ey ** 2)):.4f} px "
              f"({per_axis:.4f} per axis), max {np.nanmax(np.hypot(ex, ey)):.3f}; "
              f"grid: RMS {np.sqrt(np.mean(gx ** 2 + gy ** 2)):.4f}, max {np.max(np.hypot(gx, gy)):.4f} px")

    tx, ty = true_centres(cfg, mla_errors(args.rotation_deg))
    pitch_true = float(np.mean(np.hypot(np.diff(tx, axis=1), np.diff(ty, axis=1))))
    print("accuracy:")
    report("ray-traced sub-image centres", tx, ty)
    report("first-order layout (p(b+f)/b)", *layout_centres(cfg))
    print(f"  pitch: measured {grid.pitch_px[0]:.5f} / {grid.pitch_px[1]:.5f} px, ray-traced mean spacing "
          f"{pitch_true:.5f}, layout {cfg.layout.subimage_pitch_px:.5f}; rotation {grid.rotation_deg:+.5f} deg "
          f"(true {args.rotation_deg:g})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
