"""Inspection benchmark on the Table 1 camera (2048 x 2048 px, 10,404 lenses): seconds per stage for
load + calibrate + divide + indexes + identify, self-calibrated and with the grid reused from a white
image, against the bars of issue #11 (<= 0.25 s including calibration, <= 0.12 s with it reused; issue #6 had 0.5 and 0.25).

    python bench/inspection.py [--runs 7]   # renders two frames once (cached in /tmp), then times

Wall-clock figures on a shared machine are noisy: each stage is the best of the runs, the totals are
the best whole run, and the CPU seconds of that run (all threads) and the median run are printed beside
them. Every lens' reference image is computed when a report reads it (results.LazyReferences), so it is
not part of these figures.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from mlaqc.inspection.calibrate import calibrate
from mlaqc.inspection.pipeline import inspect_image, load_frame
from mlaqc.optics.config import default_config
from mlaqc.optics.errormap import ErrorMap, random_defects
from mlaqc.optics.simulate import simulate, write_simulation

BAR_SELF_S = 0.25  # issue #11: one frame including its calibration
BAR_REUSED_S = 0.12  # issue #11: one frame, calibration reused from a white image


def frame_path(cfg) -> Path:
    """A 50 rays/pixel DNG with 40 seeded defects, rendered once and kept in the temp folder."""
    path = Path(tempfile.gettempdir()) / "mlaqc_bench_inspect.dng"
    if not path.exists():
        sim = simulate(cfg, None, random_defects(102, 102, 40, seed=77), rays_per_pixel=50, seed=77)
        write_simulation(path, sim, cfg)
    return path


def white_path(cfg) -> Path:
    """A defect-free 50 rays/pixel white DNG (the calibration frame), rendered once into the temp folder."""
    path = Path(tempfile.gettempdir()) / "mlaqc_bench_white.dng"
    if not path.exists():
        sim = simulate(cfg, None, ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w), rays_per_pixel=50, seed=78)
        write_simulation(path, sim, cfg)
    return path


def timed_runs(path: Path, cfg, grid, runs: int) -> tuple[dict[str, float], float, float, float, object]:
    """Best seconds per stage over `runs`, the best total, that run's CPU seconds, the median total, and
    the last result."""
    stages: dict[str, float] = {}
    best_total, best_cpu, res = float("inf"), float("nan"), None
    totals = []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        img = load_frame(path, cfg)
        load_s = time.perf_counter() - t0
        res = inspect_image(img, cfg, grid=grid)
        total, cpu = time.perf_counter() - t0, time.process_time() - c0
        for k, v in {"load": load_s, **res.timings_s}.items():
            stages[k] = min(stages.get(k, float("inf")), v)
        if total < best_total:
            best_total, best_cpu = total, cpu
        totals.append(total)
    return stages, best_total, best_cpu, statistics.median(totals), res


def report(title: str, stages: dict[str, float], total: float, cpu: float, median: float, bar: float) -> None:
    """Print one configuration's per-stage seconds and its total against its bar."""
    print(title)
    for k, v in stages.items():
        print(f"  {k:10s} {v:7.3f} s")
    verdict = "meets" if total <= bar else "MISSES"
    print(f"  {'total':10s} {total:7.3f} s   (CPU {cpu:.3f} s over all threads; median run {median:.3f} s)  "
          f"bar <= {bar:.2f} s: {verdict}")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args()
    cfg = default_config()
    path, white = frame_path(cfg), white_path(cfg)
    inspect_image(load_frame(path, cfg), cfg)  # warm caches (reference, signatures, FFT plans, compiled kernels)
    print(f"frame: {path} (2048x2048, 10,404 lenses, 40 seeded defects); best of {args.runs} runs per figure")
    stages, total, cpu, median, res = timed_runs(path, cfg, None, args.runs)
    report("self-calibrated: load + calibrate + divide + indexes + identify", stages, total, cpu, median, BAR_SELF_S)
    grid = calibrate(load_frame(white, cfg), expected_pitch_px=cfg.layout.subimage_pitch_px,
                     expected_shape=(cfg.mla.count_h, cfg.mla.count_w))
    stages, total, cpu, median, res = timed_runs(path, cfg, grid, args.runs)
    report(f"grid reused from a white image ({white.name}): load + divide + indexes + identify",
           stages, total, cpu, median, BAR_REUSED_S)
    print(f"  flagged {len(res.defects)}, verdict {res.verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
