"""Detection limits against the array's size (issue #22 part 4): the same optics (Table 1's) on 12 x 12,
24 x 24 and 102 x 102 arrays at the same rays per pixel, each with the paper's nine seeded around its
centre as bench/paper_examples.py seeds them (six lenses apart, four on 12 x 12), rendered by the tracer
with formation and sensor noise (cached in /tmp under paper_examples.py's names) and inspected as a user
would. Prints each frame's detection limits side by side with the largest over the smallest (the bar:
1.5), the healthy lenses flagged and, among them, the seeded lenses' neighbours.

    python bench/size_limits.py                     # 1000 rays/pixel (102 x 102: 4.2 G rays, rendered once)
    python bench/size_limits.py --rays-per-pixel 100 --sizes 12 24
    python bench/size_limits.py --clean             # healthy arrays: nothing seeded

The 102 x 102 frame is rendered whole: a frame's noise is measured over all its inner lenses, across the
main lens' field, so a central crop would be another statistic (and is the 24 x 24 camera anyway). The
12 x 12 camera is fixtures/small_camera.toml with 12 lenses a side on a 256 x 256 sensor.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
import time
from pathlib import Path

from paper_examples import error_map

from mlaqc.inspection.pipeline import inspect_image, load_frame
from mlaqc.models.reference import config_key
from mlaqc.optics.config import CameraConfig, load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.lattice import Lattice
from mlaqc.optics.simulate import simulate, write_simulation

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
LIMITS = (("pitch_um", "pitch µm"), ("decenter_um", "decenter µm"), ("radius_rel_neg", "radius − %"),
          ("radius_rel_pos", "radius + %"), ("thickness_um_neg", "thickness − µm"), ("thickness_um_pos", "thickness + µm"))
BAR = 1.5


def camera(lenses: int) -> CameraConfig:
    """Table 1's optics with `lenses` x `lenses` lenses: fixtures/paper_table1.toml at 102, else the small
    camera's with that count on the smallest sensor of a multiple of 16 px holding the array and 4 px a side."""
    if lenses == 102:
        return load_config(FIXTURES / "paper_table1.toml")
    cfg = load_config(FIXTURES / "small_camera.toml")
    side = 16 * math.ceil((lenses * cfg.layout.subimage_pitch_px + 8) / 16)
    return dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, count_w=lenses, count_h=lenses),
                               sensor=dataclasses.replace(cfg.sensor, width_px=side, height_px=side))


def frame(cfg: CameraConfig, rays_per_pixel: float, seed: int, clean: bool) -> tuple[Path, dict]:
    """The rendered frame's path (rendered now unless cached) and its seeded lenses {(m, n): kind}."""
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    em, truth = (ErrorMap.zeros(rows, cols), {}) if clean else error_map(rows, cols)
    name = "clean" if clean else "paper9"
    path = Path(tempfile.gettempdir()) / (f"mlaqc_{name}_{config_key(cfg)}_{cfg.mla.boundaries}_"
                                          f"{rays_per_pixel:g}_{seed}.tif")
    if not path.exists():
        t0 = time.perf_counter()
        write_simulation(path, simulate(cfg, None, em, rays_per_pixel=rays_per_pixel, seed=seed), cfg)
        print(f"  rendered {path.name} in {time.perf_counter() - t0:.0f} s", flush=True)
    return path, {k: v[0] for k, v in truth.items()}


def neighbours_of(truth: dict, cfg: CameraConfig) -> set[tuple[int, int]]:
    """U(m, n) of every lattice neighbour of a seeded lens (1-based)."""
    lat = Lattice(cfg.mla.packing, cfg.mla.count_h, cfg.mla.count_w)
    nbr = lat.neighbours(diagonal=True)
    out = set()
    for m, n in truth:
        for f in nbr[(m - 1) * lat.cols + (n - 1)]:
            if f >= 0:
                out.add((int(f) // lat.cols + 1, int(f) % lat.cols + 1))
    return out - set(truth)


def measure(lenses: int, rays_per_pixel: float, seed: int, clean: bool) -> dict:
    """One size's limits, seeded lenses found and healthy lenses flagged."""
    cfg = camera(lenses)
    path, truth = frame(cfg, rays_per_pixel, seed, clean)
    result = inspect_image(load_frame(path, cfg), cfg)
    flagged = {(d.m, d.n): d.error_type for d in result.defects}
    false = set(flagged) - set(truth)
    return {"limits": result.detection_limit, "found": sum(p in flagged for p in truth), "seeded": len(truth),
            "typed": sum(flagged.get(p) == kind for p, kind in truth.items()),
            "false": len(false), "false_next": len(false & neighbours_of(truth, cfg)),
            "healthy": lenses * lenses - len(truth)}


def shown(key: str, value) -> str:
    """A limit in its row's unit ('—' where not detectable)."""
    if value is None:
        return "—"
    return f"{100 * value:.3g}" if key.startswith("radius") else f"{value:.3g}"


def table(sizes: list[int], runs: list[dict]) -> bool:
    """Print the limits side by side with max / min; whether every row holds the bar."""
    print(f"\n{'limit':<16}" + "".join(f"{f'{s} x {s}':>12}" for s in sizes) + f"{'max / min':>12}")
    ok = True
    for key, label in LIMITS:
        vals = [r["limits"].get(key) for r in runs]
        if all(v is None for v in vals) and key not in runs[0]["limits"]:
            continue
        finite = [v for v in vals if v is not None]
        ratio = max(finite) / min(finite) if len(finite) == len(vals) and min(finite) > 0 else float("inf")
        ok &= ratio <= BAR
        print(f"{label:<16}" + "".join(f"{shown(key, v):>12}" for v in vals) + f"{ratio:>11.2f}{'' if ratio <= BAR else ' !'}")
    for label, fmt in (("seeded found", lambda r: f"{r['found']}/{r['seeded']}"),
                       ("seeded typed", lambda r: f"{r['typed']}/{r['seeded']}"),
                       ("healthy flagged", lambda r: f"{r['false']}/{r['healthy']}"),
                       ("  next to seeded", lambda r: str(r["false_next"]))):
        print(f"{label:<16}" + "".join(f"{fmt(r):>12}" for r in runs))
    return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[12, 24, 102], help="lenses a side (102: Table 1's frame)")
    ap.add_argument("--rays-per-pixel", type=float, default=1000.0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--clean", action="store_true", help="no seeded lens (the healthy arrays' limits)")
    args = ap.parse_args()
    runs = []
    for lenses in args.sizes:
        print(f"{lenses} x {lenses} lenses, {args.rays_per_pixel:g} rays/pixel, seed {args.seed}"
              f"{', nothing seeded' if args.clean else ', the paper nine'}", flush=True)
        runs.append(measure(lenses, args.rays_per_pixel, args.seed, args.clean))
    ok = table(args.sizes, runs)
    false = sum(r["false"] for r in runs)
    print(f"\nlimits within {BAR}x over the sizes: {'yes' if ok else 'NO'}; healthy lenses flagged: {false}")
    return 0 if ok and not false else 1


if __name__ == "__main__":
    sys.exit(main())
