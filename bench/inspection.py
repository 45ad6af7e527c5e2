"""Inspection benchmark on the Table 1 camera (2048 x 2048 px, 10,404 lenses): seconds per stage for
load + calibrate + divide + indexes + identify, with and without a calibration reused from a white image.

    python bench/inspection.py        # renders one frame (cached in /tmp), then times 3 runs
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path


from mlaqc.calibrate import calibrate
from mlaqc.config import default_config
from mlaqc.errormap import random_defects
from mlaqc.inspect import inspect_image, load_frame
from mlaqc.simulate import simulate, write_simulation


def frame_path(cfg) -> Path:
    """A 50 rays/pixel DNG with 40 seeded defects, rendered once and kept in the temp folder."""
    path = Path(tempfile.gettempdir()) / "mlaqc_bench_inspect.dng"
    if not path.exists():
        sim = simulate(cfg, None, random_defects(102, 102, 40, seed=77), rays_per_pixel=50, seed=77)
        write_simulation(path, sim, cfg)
    return path


def main() -> int:
    cfg = default_config()
    path = frame_path(cfg)
    inspect_image(load_frame(path, cfg), cfg)  # warm caches (reference, signatures, FFT plans)
    rows = []
    for _ in range(3):
        t0 = time.perf_counter()
        img = load_frame(path, cfg)
        load_s = time.perf_counter() - t0
        res = inspect_image(img, cfg)
        total = time.perf_counter() - t0
        rows.append(({"load": load_s, **res.timings_s}, total))
    best = min(rows, key=lambda r: r[1])
    print(f"frame: {path} (2048x2048, 10,404 lenses); best of 3 runs")
    for k, v in best[0].items():
        print(f"  {k:10s} {v:7.3f} s")
    print(f"  {'total':10s} {best[1]:7.3f} s   (load + calibrate + divide + indexes + identify)")
    img = load_frame(path, cfg)
    grid = calibrate(img, expected_pitch_px=cfg.layout.subimage_pitch_px, expected_shape=(102, 102))
    t0 = time.perf_counter()
    res = inspect_image(img, cfg, grid=grid)
    print(f"  with the grid reused from a white image: {time.perf_counter() - t0:.3f} s "
          f"({', '.join(f'{k} {v:.3f}' for k, v in res.timings_s.items())})")
    print(f"  flagged {len(res.defects)}, verdict {res.verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
