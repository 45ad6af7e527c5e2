"""`mlaqc errormap`: write a seeded random error map, or check one against a camera config."""

from __future__ import annotations

import argparse
import sys

from mlaqc.errors import InputError
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ERROR_TYPES, load_error_map, physical_types, random_defects


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `errormap` subcommand."""
    p = sub.add_parser("errormap", help="create or check a per-lens error map (JSON keyed by U(m,n))",
                       description="Create a seeded random error map, or check an error map against a camera.")
    p.add_argument("--config", "-c", help="camera config TOML (default: the paper's Table 1 camera)")
    act = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    r = act.add_parser("random", help="write a map with N random separated defects")
    r.add_argument("count", type=int, help="number of defective lenses")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--types", default="pitch,decenter,radius", help=f"comma-separated, from {','.join(ERROR_TYPES)}")
    r.add_argument("--out", "-o", required=True, help="output JSON")
    c = act.add_parser("check", help="validate a map and list its defective lenses")
    c.add_argument("map", help="error map JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Create or check; 0 on success."""
    cfg = load_config(args.config)
    shape = (cfg.mla.count_h, cfg.mla.count_w)
    if args.action == "random":
        if args.count < 0:
            raise InputError("the defect count must not be negative")
        types = tuple(t.strip() for t in args.types.split(",") if t.strip())
        emap = random_defects(*shape, args.count, args.seed, types=physical_types(types, cfg.mla),
                              packing=cfg.mla.packing)
        emap.save(args.out)
        print(f"wrote {args.out}: {args.count} defects on a {shape[0]}x{shape[1]} {cfg.mla.packing} MLA (seed {args.seed})", file=sys.stderr)
        return 0
    emap = load_error_map(args.map, shape, cfg.mla.packing)
    kinds = emap.lens_type()
    for m, n in zip(*emap.defective().nonzero()):
        print(f"U({m + 1},{n + 1})\t{kinds[m, n]}")
    print(f"{args.map}: valid, {int(emap.defective().sum())} defective lenses", file=sys.stderr)
    return 0
