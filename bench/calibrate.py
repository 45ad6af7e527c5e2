"""Benchmark: calibrate + divide on a 2048 x 2048 white frame of the Table 1 camera, and its accuracy.

    python bench/calibrate.py [--rays-per-pixel 50] [--seed 1] [--no-noise] [--repeat 5]
                              [--raw FILE [--config C]] [--threads N] [--no-truth]

The frame is rendered once (about 20-35 s at 50 rays/pixel) and kept in ~/.cache/mlaqc-bench, or read
from --raw (any file mlaqc.rawio.load_raw reads). Timings: wall clock and process CPU, best and median
of --repeat runs after one warm-up. Accuracy (rendered frames only): per-lens measured centres and grid
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

import mlaqc.calibrate as calibration  # noqa: E402
from mlaqc.calibrate import calibrate  # noqa: E402
from mlaqc.config import default_config, load_config  # noqa: E402
from mlaqc.rawio import load_raw, normalized, suppress_hot_pixels  # noqa: E402
from mlaqc.subimages import divide  # noqa: E402


def rendered_frame(rpp: float, seed: int, noise: bool) -> np.ndarray:
    """Raw counts of the default camera's white image, rendered once and cached."""
    cfg = default_config()
    key = hashlib.sha256(f"{rpp}-{seed}-{noise}".encode()).hexdigest()[:12]
    cache = Path.home() / ".cache" / "mlaqc-bench"
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / f"white-table1-{key}.npy"
    if not path.exists():
        from mlaqc.simulate import simulate

        t = time.perf_counter()
        sim = simulate(cfg, rays_per_pixel=rpp, seed=seed, noise=noise)
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rays-per-pixel", type=float, default=50.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-noise", action="store_true")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--raw", help="a white raw file instead of the rendered one")
    ap.add_argument("--config", help="camera config of --raw (default: Table 1)")
    ap.add_argument("--threads", type=int, help="worker threads of the disc fit (default: one per core, max 4)")
    ap.add_argument("--no-truth", action="store_true", help="skip the accuracy figures")
    args = ap.parse_args()
    cfg = load_config(args.config) if args.raw else default_config()
    if args.threads:
        calibration._workers = lambda: args.threads  # noqa: E731
    if args.raw:
        frame = load_raw(args.raw)
        img, _ = suppress_hot_pixels(normalized(frame), frame.cfa)
        source = args.raw
    else:
        from calib_images import normalize

        img = normalize(rendered_frame(args.rays_per_pixel, args.seed, not args.no_noise), cfg)
        source = f"rendered, {args.rays_per_pixel:g} rays/pixel, seed {args.seed}, noise {'off' if args.no_noise else 'on'}"
    kw = dict(expected_pitch_px=cfg.layout.subimage_pitch_px, expected_shape=(cfg.mla.count_h, cfg.mla.count_w))
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

    tx, ty = true_centres(cfg)
    pitch_true = float(np.mean(np.hypot(np.diff(tx, axis=1), np.diff(ty, axis=1))))
    print("accuracy:")
    report("ray-traced sub-image centres", tx, ty)
    report("first-order layout (p(b+f)/b)", *layout_centres(cfg))
    print(f"  pitch: measured {grid.pitch_px[0]:.5f} / {grid.pitch_px[1]:.5f} px, ray-traced mean spacing "
          f"{pitch_true:.5f}, layout {cfg.layout.subimage_pitch_px:.5f}; rotation {grid.rotation_deg:+.5f} deg (true 0)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
