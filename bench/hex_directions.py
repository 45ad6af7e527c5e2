"""Direction accuracy of lens shifts over the circle: one kind and size seeded in 24 directions (15° apart)
on lenses 6 apart, one white frame rendered by the tracer (cached in /tmp), inspected as a user would.
Prints the types read, the false flags and the direction error (rms, mean |err|, max, and its mean per
direction modulo 180°: a pull towards the rows shows as - at 15-75° and + at 105-165°).

    python bench/hex_directions.py                                   # hex Table 1, decenter 7 µm, 200 rays/pixel
    python bench/hex_directions.py --kind pitch --size 2 --seed 6
    python bench/hex_directions.py -c fixtures/paper_table1.toml     # square, for comparison
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from mlaqc.inspection.pipeline import inspect_image, load_frame
from mlaqc.models.reference import config_key
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap, lens_error_fields
from mlaqc.optics.simulate import simulate, write_simulation

DIRECTIONS_DEG = np.arange(0.0, 360.0, 15.0)
SPACING = 6


def seeded(cfg, kind: str, size: float) -> tuple[ErrorMap, dict]:
    """Lenses SPACING apart from U(4,4) (rows SPACING + 1 apart, so that on hex the seeded rows take both
    parities: even rows are the shifted ones), each at one of the 24 directions, spread so that rows of
    both parities hold every direction."""
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    em, truth = ErrorMap.zeros(rows, cols, cfg.mla.packing), {}
    lenses = [(m, n) for m in range(4, rows - 2, SPACING + 1) for n in range(4, cols - 2, SPACING)]
    for i, (m, n) in enumerate(lenses):
        d = float(DIRECTIONS_DEG[(7 * i + m) % len(DIRECTIONS_DEG)])
        em = em.with_lens(m, n, **lens_error_fields(kind, size, d))
        truth[(m, n)] = d
    return em, truth


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", "-c", default=str(Path(__file__).resolve().parents[1] / "fixtures" / "hex_camera.toml"))
    ap.add_argument("--kind", choices=("pitch", "decenter"), default="decenter")
    ap.add_argument("--size", type=float, default=7.0, help="µm")
    ap.add_argument("--rays-per-pixel", type=float, default=200.0)
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args()
    cfg = load_config(args.config)
    em, truth = seeded(cfg, args.kind, args.size)
    path = Path(tempfile.gettempdir()) / (f"mlaqc_directions_{config_key(cfg)}_{args.kind}_{args.size:g}_"
                                          f"{args.rays_per_pixel:g}_{args.seed}_{SPACING + 1}x{SPACING}.tif")
    if not path.exists():
        write_simulation(path, simulate(cfg, None, em, rays_per_pixel=args.rays_per_pixel, seed=args.seed), cfg)
    result = inspect_image(load_frame(path, cfg), cfg)
    found = {(d.m, d.n): d for d in result.defects}
    types: dict[str, int] = {}
    errors: dict[float, list[float]] = {}
    for lens, direction in truth.items():
        d = found.get(lens)
        name = d.error_type if d is not None else "missed"
        types[name] = types.get(name, 0) + 1
        if d is not None and d.direction_deg is not None:
            errors.setdefault(direction % 180.0, []).append((d.direction_deg - direction + 180.0) % 360.0 - 180.0)
    false = sum((d.m, d.n) not in truth for d in result.defects)
    e = np.concatenate([np.asarray(v) for v in errors.values()]) if errors else np.array([np.nan])
    print(f"{args.kind} {args.size:g} µm on {len(truth)} lenses of {Path(args.config).name}, {args.rays_per_pixel:g} "
          f"rays/pixel, seed {args.seed}: read as {types}; {false} healthy lenses flagged")
    print(f"direction error: rms {np.sqrt(np.mean(e ** 2)):.2f}°, mean |err| {np.mean(np.abs(e)):.2f}°, "
          f"max {np.max(np.abs(e)):.1f}°")
    print("mean error per direction (mod 180°): " + ", ".join(f"{k:.0f}° {np.mean(v):+.1f}" for k, v in sorted(errors.items())))
    for parity, name in ((1, "odd"), (0, "even")):
        e = np.array([(found[k].direction_deg - d + 180.0) % 360.0 - 180.0 for k, d in truth.items()
                      if k[0] % 2 == parity and k in found and found[k].direction_deg is not None])
        if e.size:
            print(f"  rows m {name}: rms {np.sqrt(np.mean(e ** 2)):.2f}° over {e.size} lenses")
    return 0


if __name__ == "__main__":
    sys.exit(main())
