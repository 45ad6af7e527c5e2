"""The paper's nine example errors in one white frame, inspected with a config as a user would run it
(issue #22 part 3 bars): pitch 1 / 1.5 / 2 µm, decenter 5 / 7 / 10 µm, radius −10 / +5 / +8 %, on nine
lenses six apart around the array's centre (five healthy lenses between two seeded ones), in several
directions. The frame is rendered with the config's lens-boundary model (by default the physical
sag-intersection one), realistic image formation and sensor noise, cached in /tmp, and inspected.

    python bench/paper_examples.py                                     # Table 1, 1000 rays/pixel
    python bench/paper_examples.py --config fixtures/small_camera.toml # the 24 x 24 camera
    python bench/paper_examples.py --config fixtures/hex_camera.toml --rays-per-pixel 600  # hex bar
    python bench/paper_examples.py --render-boundaries sag-intersection --inspect-boundaries grid

Prints per seeded lens: the reported type, magnitude and direction, and whether each is right (type;
magnitude within 5 %, 15 % on hex; direction within 1°), then the healthy lenses flagged and the frame's detection limit.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mlaqc.inspection.pipeline import inspect_image, load_frame
from mlaqc.inspection.results import detection_limit_text
from mlaqc.models.reference import config_key
from mlaqc.optics.config import BOUNDARY_CHOICES, load_config
from mlaqc.optics.errormap import ErrorMap, lens_error_fields
from mlaqc.optics.simulate import simulate, write_simulation

# (kind, magnitude, direction deg): the paper's nine; directions spread over the circle (the paper's
# Δp = 1 µm and δ = 10 µm point at 90°)
NINE = (("pitch", 1.0, 90.0), ("pitch", 1.5, 30.0), ("pitch", 2.0, 225.0),
        ("decenter", 5.0, 0.0), ("decenter", 7.0, 135.0), ("decenter", 10.0, 90.0),
        ("radius", -0.10, None), ("radius", 0.05, None), ("radius", 0.08, None))
MAG_TOL = {"square": 0.05, "hex": 0.15}  # relative: the bars
DIR_TOL_DEG = 1.0
SPACING = 6


def placements(rows: int, cols: int, packing: str = "square") -> list[tuple[int, int]]:
    """Nine U(m, n) (1-based) on a 3 x 3 lattice SPACING apart (closer on arrays too small for it, at least
    one lens from the edge), centred on the array; on hex the rows SPACING + 1 apart so that the nine sit
    on rows of both parities (even rows are the shifted ones)."""
    step = max(2, min(SPACING, (min(rows, cols) - 3) // 2))
    row_step = step + 1 if packing == "hex" and step + 1 <= (rows - 3) // 2 else step
    cm, cn = (rows + 1) // 2, (cols + 1) // 2
    return [(cm + row_step * i, cn + step * j) for i in (-1, 0, 1) for j in (-1, 0, 1)]


def error_map(rows: int, cols: int, which: range = range(9), packing: str = "square") -> tuple[ErrorMap, dict]:
    em = ErrorMap.zeros(rows, cols, packing)
    truth = {}
    for k, ((m, n), (kind, mag, d)) in enumerate(zip(placements(rows, cols, packing), NINE)):
        if k not in which:
            continue
        em = em.with_lens(m, n, **lens_error_fields(kind, mag, d))
        truth[(m, n)] = (kind, mag, d)
    return em, truth


def with_boundaries(cfg, boundaries: str | None):
    return cfg if boundaries is None else dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, boundaries=boundaries))


def angle_diff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def report(result, truth: dict, mag_tol: float) -> tuple[int, int]:
    """Print the nine and the false flags; (seeded right on all three counts, healthy flagged)."""
    defects = {(d.m, d.n): d for d in result.defects}
    right = 0
    for (m, n), (kind, mag, d) in truth.items():
        seeded = f"{kind} {mag * 100:+.0f} %" if kind == "radius" else f"{kind} {mag:g} µm at {d:g}°"
        got = defects.get((m, n))
        if got is None:
            print(f"  U({m},{n}) {seeded:<24} not flagged")
            continue
        value = got.magnitude
        type_ok = got.error_type == kind
        mag_ok = abs(value - mag) <= mag_tol * abs(mag) if type_ok else False
        if kind == "radius":
            dir_ok, read = True, f"{got.error_type} {value * 100:+.2f} %"
        else:
            dd = angle_diff(got.direction_deg, d) if got.direction_deg is not None else float("nan")
            dir_ok = dd <= DIR_TOL_DEG
            read = f"{got.error_type} {value:.3g} µm at {got.direction_deg:.1f}° (Δ {dd:.1f}°)"
            if got.error_type == "position":
                read += " [" + ", ".join(f"{t} {v:.3g}" for t, v, _u, _a in got.alternatives) + "]"
        ok = type_ok and mag_ok and dir_ok
        right += ok
        print(f"  U({m},{n}) {seeded:<24} {read:<52} type {'ok' if type_ok else 'WRONG'}, "
              f"magnitude {'ok' if mag_ok else 'off'} ({100 * (abs(value) / abs(mag) - 1):+.1f} %), "
              f"direction {'ok' if dir_ok else 'off'}  z {got.score:.1f}")
    false = [d for d in result.defects if (d.m, d.n) not in truth]
    for d in false:
        near = min(max(abs(d.m - m), abs(d.n - n)) for m, n in truth)
        print(f"  healthy U({d.m},{d.n}) flagged: {d.error_type} {d.magnitude:.3g} {d.unit} z {d.score:.1f} "
              f"({near} lens(es) from the nearest seeded one)")
    return right, len(false)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", "-c", help="camera config TOML (default: the built-in default, Table 1)")
    ap.add_argument("--rays-per-pixel", type=float, default=1000.0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--render-boundaries", choices=BOUNDARY_CHOICES, help="render with this model (default: the config's)")
    ap.add_argument("--inspect-boundaries", choices=BOUNDARY_CHOICES, help="inspect with this model (default: the config's)")
    ap.add_argument("--per-frame", type=int, default=9, help="seeded examples per frame (9: all in one frame; "
                    "fewer spreads them over several frames, each of its own seed)")
    args = ap.parse_args()
    cfg = load_config(args.config)
    render_cfg = with_boundaries(cfg, args.render_boundaries)
    inspect_cfg = with_boundaries(cfg, args.inspect_boundaries)
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    total_right = total_typed = total_false = total_healthy = 0
    for first in range(0, 9, args.per_frame):
        which = range(first, min(first + args.per_frame, 9))
        seed = args.seed + first
        em, truth = error_map(rows, cols, which, cfg.mla.packing)
        tag = "" if args.per_frame == 9 else f"_{which.start}-{which.stop - 1}"
        path = Path(tempfile.gettempdir()) / (f"mlaqc_paper9_{config_key(cfg)}_{render_cfg.mla.boundaries}_"
                                              f"{args.rays_per_pixel:g}_{seed}{tag}.tif")
        if not path.exists():
            t0 = time.perf_counter()
            write_simulation(path, simulate(render_cfg, None, em, rays_per_pixel=args.rays_per_pixel, seed=seed),
                             render_cfg)
            print(f"rendered {path.name} in {time.perf_counter() - t0:.0f} s", flush=True)
        t0 = time.perf_counter()
        result = inspect_image(load_frame(path, inspect_cfg), inspect_cfg)
        print(f"{rows} x {cols} lenses, {args.rays_per_pixel:g} rays/pixel + formation and sensor noise, seed {seed}; "
              f"rendered with {render_cfg.mla.boundaries} boundaries, inspected with {inspect_cfg.mla.boundaries} "
              f"(report: {result.lens_boundaries}) in {time.perf_counter() - t0:.1f} s")
        right, false = report(result, truth, MAG_TOL[cfg.mla.packing])
        total_right += right
        total_typed += sum(1 for d in result.defects if truth.get((d.m, d.n), ("",))[0] == d.error_type)
        total_false += false
        total_healthy += rows * cols - len(truth)
        print(f"this frame {detection_limit_text(result.detection_limit)}")
    frames = (8 + args.per_frame) // args.per_frame
    print(f"nine examples right (type, magnitude within {MAG_TOL[cfg.mla.packing]:.0%}, direction within {DIR_TOL_DEG:g}°): "
          f"{total_right}/9; typed right {total_typed}/9; healthy lenses flagged: {total_false} of {total_healthy} "
          f"({frames} frame{'s' if frames > 1 else ''})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
