"""`mlaqc models`: render the reference model and signature tables of a camera, and the through-focus
model of the shipped protocol (mlaqc.inspection.throughfocus), before they are needed.

`mlaqc inspect` renders them itself the first time it meets new optics (a minute or more), and keeps
them in the cache ($MLAQC_CACHE or ~/.cache/mlaqc), keyed by the optics. A lab that changes its camera,
or a QC line that wants the first inspection to be quick, builds them here — on a Dask cluster with
--scheduler — and sees where they are stored.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time

from mlaqc.cluster import add_scheduler_option, check_address, connect, scheduler_address
from mlaqc.optics.config import load_config
from mlaqc.progress import ProgressBar


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `models` subcommand."""
    p = sub.add_parser("models", help="build (or rebuild) a camera's reference model, signature tables, "
                                      "through-focus model and assembly calibration",
                       description="Render the reference sub-image model and the signature tables that inspection "
                                   "compares every lens with, the shipped through-focus protocol's model, and the "
                                   "assembly readings' calibration (rendered frames of the array's placement), for the "
                                   "camera's optics, and store them in the cache "
                                   "($MLAQC_CACHE or ~/.cache/mlaqc). Tables already stored are kept unless --rebuild.")
    p.add_argument("--config", "-c", help="camera config TOML (default: the paper's Table 1 camera)")
    p.add_argument("--rebuild", action="store_true", help="render them again even if stored")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar or summary")
    add_scheduler_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Build what is missing (or everything with --rebuild); 0 on success."""
    from mlaqc.models.assembly_model import assembly_model
    from mlaqc.models.reference import config_key, reference_model
    from mlaqc.user_cache import cache_dir
    from mlaqc.models.signatures import signature_key, signature_table

    cfg = load_config(args.config)
    address = scheduler_address(args.scheduler)
    if not args.quiet:
        print_derived_numbers(cfg, args.config)
    t0 = time.perf_counter()
    bar = ProgressBar("signature renders", enabled=False if args.quiet else None)
    with contextlib.ExitStack() as stack:
        client = stack.enter_context(connect(check_address(address), quiet=args.quiet)) if address else None
        try:
            reference_model(cfg, client=client, rebuild=args.rebuild)
            signature_table(cfg, client=client, rebuild=args.rebuild, progress=bar)
        finally:
            bar.close()
    ideal = cfg.main_lens.ideal  # no object side to put pinholes on
    tf_key = "(none: an ideal main lens has no object side)" if ideal else _through_focus_model(cfg, args.rebuild)
    asm_bar = ProgressBar("assembly renders", enabled=False if args.quiet else None)
    try:
        asm_key = assembly_model(cfg, rebuild=args.rebuild, progress=asm_bar).key
    finally:
        asm_bar.close()
    if not args.quiet:
        print(f"reference model {config_key(cfg)}, signature tables {signature_key(cfg)}, through-focus model "
              f"{tf_key} and assembly model {asm_key} ready ({time.perf_counter() - t0:.1f} s); cache: {cache_dir()}", file=sys.stderr)
    return 0


def print_derived_numbers(cfg, source: str | None) -> None:
    """The numbers derived from the config, to check against the instrument before trusting a verdict."""
    from mlaqc.optics.datasheet import derived_numbers

    rows = derived_numbers(cfg)
    width = max(len(label) for label, _ in rows)
    print(f"camera {source or '(built-in: the paper Table 1)'}:", file=sys.stderr)
    for label, value in rows:
        print(f"  {label:<{width}}  {value}", file=sys.stderr)


def _through_focus_model(cfg, rebuild: bool) -> str:
    """Build (if missing, or again with `rebuild`) the shipped through-focus protocol's model; its key."""
    from mlaqc.inspection.throughfocus_model import model_curves
    from mlaqc.optics.throughfocus import F_NUMBER, FOCUS_OFFSET_MM, SPACING_LENSES, ThroughFocus, pair_radius_lenses

    r_in = pair_radius_lenses(cfg, ThroughFocus(FOCUS_OFFSET_MM, F_NUMBER, SPACING_LENSES))
    return model_curves(cfg, FOCUS_OFFSET_MM, F_NUMBER, r_in, rebuild=rebuild).key
