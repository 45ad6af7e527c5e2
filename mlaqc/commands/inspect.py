"""`mlaqc inspect`: find, classify and size defective microlenses in a raw image; write the report set."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mlaqc.config import load_config
from mlaqc.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `inspect` subcommand."""
    p = sub.add_parser("inspect", help="inspect a raw image: defective lenses, type, size, PASS/FAIL",
                       description="Calibrate the microlens grid, compute every lens' indexes, flag and classify "
                                   "defective lenses, and write report.json, lenses.csv, defect_map.png and "
                                   "report.html. Exit status 0 = PASS, 1 = FAIL, 2 = input error.")
    p.add_argument("raw", help="raw image (DNG, vendor raw, TIFF, PNG, NPY)")
    p.add_argument("--white", "-w", help="white image to calibrate the grid on (default: the raw itself)")
    p.add_argument("--config", "-c", help="camera config TOML (default: the paper's Table 1 camera)")
    p.add_argument("--out", "-o", required=True, help="output folder for the report set")
    p.add_argument("--quiet", "-q", action="store_true", help="no summary on stderr")
    p.set_defaults(func=run)


def check_out_dir(out: str) -> Path:
    """The report folder: created if its parent exists; refused if it is a file."""
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise InputError(f"output {out!r} exists and is not a folder")
    if not path.parent.is_dir():
        raise InputError(f"the folder containing {out!r} does not exist")
    return path


def summary(result) -> str:
    """A few lines an operator reads at the bench."""
    g = result.grid
    kinds: dict[str, int] = {}
    for d in result.defects:
        kinds[d.error_type] = kinds.get(d.error_type, 0) + 1
    out_tol = sum(1 for d in result.defects if not d.within_tolerance)
    lines = [f"{result.verdict}: {len(result.defects)} flagged lenses ({out_tol} out of tolerance) of {g.rows}x{g.cols}",
             f"  grid: pitch {g.pitch_px[0]:.3f} x {g.pitch_px[1]:.3f} px, rotation {g.rotation_deg:+.3f} deg, "
             f"RMS residual {g.rms_residual_px:.3f} px",
             "  by type: " + (", ".join(f"{k} {v}" for k, v in sorted(kinds.items())) or "none"),
             "  time: " + ", ".join(f"{k} {v:.2f} s" for k, v in result.timings_s.items())]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Inspect and report; 0 PASS, 1 FAIL."""
    from mlaqc.inspect import inspect_file
    from mlaqc.report import write_report

    out = check_out_dir(args.out)
    cfg = load_config(args.config)
    result = inspect_file(args.raw, cfg, white=args.white)
    write_report(result, out, config_dict=cfg.to_dict())
    if not args.quiet:
        print(summary(result), file=sys.stderr)
        print(f"  report: {out / 'report.html'}", file=sys.stderr)
    return 1 if result.failed else 0
