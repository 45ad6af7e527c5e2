"""Tracer benchmark: end-to-end rays/s (source -> main lens -> MLA with per-lens errors -> sensor) and
peak memory on the default camera, for each engine and thread count; then the issue's full-frame bar.

    python bench/trace.py            # all figures (about a minute on 2 cores)
    python bench/trace.py --quick    # fewer rays
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
import tracemalloc

from mlaqc.config import default_config
from mlaqc.errormap import random_defects
from mlaqc.render import Renderer
from mlaqc.scene import WhiteScene


def rate(renderer: Renderer, rays: int, threads: int) -> tuple[float, float]:
    """(M rays/s, seconds) for one white render."""
    t = time.perf_counter()
    renderer.render(WhiteScene(), rays=rays, seed=1, threads=threads)
    dt = time.perf_counter() - t
    return rays / dt / 1e6, dt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    cfg = default_config()
    errors = random_defects(102, 102, 200, seed=3, types=("pitch", "decenter", "radius", "thickness"))
    cores = os.cpu_count() or 1
    print(f"machine: {cores} cores; camera: Table 1 (102x102 lenses, 2048x2048 px), 200 defective lenses, Fresnel on")
    print(f"{'engine':8s} {'threads':>7s} {'rays':>12s} {'M rays/s':>9s} {'seconds':>8s}")
    rays = 10_000_000 if args.quick else 40_000_000
    for engine in ("numba", "numpy"):
        r = Renderer(cfg, errors, engine=engine)
        r.render(WhiteScene(), rays=200_000, seed=0)  # compile / warm up
        n = rays if engine == "numba" else rays // 8
        for threads in sorted({1, cores}):
            mrs, dt = rate(r, n, threads)
            print(f"{engine:8s} {threads:7d} {n:12,d} {mrs:9.2f} {dt:8.2f}")
    r = Renderer(cfg, errors)
    print("\npeak traced memory vs rays (numba, all cores):")
    for n in ((1_000_000, 10_000_000) if args.quick else (1_000_000, 10_000_000, 100_000_000)):
        tracemalloc.start()
        mrs, dt = rate(r, n, cores)
        peak = tracemalloc.get_traced_memory()[1] / 2 ** 20
        tracemalloc.stop()
        print(f"  {n:>12,d} rays: {peak:7.1f} MiB peak (image itself 32 MiB), {mrs:6.2f} M rays/s")
    rpp = 10 if args.quick else 50
    t = time.perf_counter()
    res = r.render(WhiteScene(), rays_per_pixel=rpp, seed=2)
    dt = time.perf_counter() - t
    print(f"\nfull 2048x2048 white image at {rpp} rays/pixel: {res.rays_traced:,} rays in {dt:.1f} s "
          f"({res.rays_traced / dt / 1e6:.2f} M rays/s), {100 * res.rays_landed / res.rays_traced:.1f} % landed")
    print(f"process max RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
