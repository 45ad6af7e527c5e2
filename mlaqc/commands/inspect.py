"""`mlaqc inspect`: find, classify and size defective microlenses in raw images; write the report sets.

One raw writes its report set into --out. Several raws (a production batch) share one calibration —
from --white, from a saved --grid, or else each frame calibrates itself — and each writes its report set
into --out/<raw name>/, plus --out/batch.csv with one line per frame. A bad frame in a batch is reported
and skipped; the others are still inspected.
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
import time
from pathlib import Path

from mlaqc.atomic import write_bytes_atomic
from mlaqc.commands.levels import add_level_options, stated_levels
from mlaqc.errors import InputError
from mlaqc.inspection.rawio import Levels
from mlaqc.inspection.results import detection_limit_text
from mlaqc.optics.config import CameraConfig, load_config

BATCH_COLUMNS = ("raw", "verdict", "flagged", "out_of_tolerance", "missing", "seconds", "report", "error")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `inspect` subcommand."""
    p = sub.add_parser("inspect", help="inspect raw images: defective lenses, type, size, PASS/FAIL",
                       description="Calibrate the microlens grid, compute every lens' indexes, flag and classify "
                                   "defective lenses, and write report.json, lenses.csv, defect_map.png and "
                                   "report.html. Several raws share one calibration (--white or --grid) and get "
                                   "one report folder each under --out, plus batch.csv. Exit status 0 = every "
                                   "frame PASS, 1 = some frame FAIL, 2 = input error (in a batch: some frame "
                                   "could not be inspected; the others still are).")
    p.add_argument("raw", nargs="+", help="raw image(s) (DNG, vendor raw, TIFF, PNG, NPY)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--white", "-w", help="white image to calibrate the grid on (default: each raw itself)")
    src.add_argument("--grid", "-g", help="grid.json from `mlaqc calibrate`, reused without recalibrating")
    p.add_argument("--config", "-c", help="camera config TOML (default: the paper's Table 1 camera)")
    p.add_argument("--out", "-o", required=True, help="output folder for the report set(s)")
    p.add_argument("--quiet", "-q", action="store_true", help="no summary on stderr")
    add_level_options(p)
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
             f"  this frame {detection_limit_text(result.detection_limit)}",
             "  time: " + ", ".join(f"{k} {v:.2f} s" for k, v in result.timings_s.items())]
    return "\n".join(lines)


def shared_grid(args: argparse.Namespace, cfg: CameraConfig):
    """The calibration every raw reuses: loaded from --grid, fitted on --white, or None (self-calibrate)."""
    from mlaqc.inspection.calibrate import calibrate, load_grid
    from mlaqc.inspection.pipeline import load_frame

    if args.grid:
        grid = load_grid(args.grid)
        want = (cfg.sensor.height_px, cfg.sensor.width_px)
        if (grid.rows, grid.cols) != (cfg.mla.count_h, cfg.mla.count_w) or tuple(grid.image_shape) != want:
            raise InputError(f"grid file {args.grid!r} is for {grid.cols}x{grid.rows} lenses on a "
                             f"{grid.image_shape[1]}x{grid.image_shape[0]} px frame, but the camera has "
                             f"{cfg.mla.count_w}x{cfg.mla.count_h} lenses on {want[1]}x{want[0]} px")
        return grid
    if args.white:
        return calibrate(load_frame(args.white, cfg, stated_levels(args)), expected_pitch_px=cfg.layout.subimage_pitch_px,
                         expected_shape=(cfg.mla.count_h, cfg.mla.count_w))
    return None


def report_folders(out: Path, raws: list[str]) -> list[Path]:
    """--out itself for one raw; --out/<name> for several, names made unique where stems collide."""
    if len(raws) == 1:
        return [out]
    seen: dict[str, int] = {}
    folders = []
    for raw in raws:
        stem = Path(raw).stem or "raw"
        seen[stem] = seen.get(stem, 0) + 1
        folders.append(out / (stem if seen[stem] == 1 else f"{stem}-{seen[stem]}"))
    return folders


def inspect_one(raw: str, cfg: CameraConfig, grid, folder: Path, levels: Levels | None = None) -> dict:
    """Load, inspect and report one raw; a row of batch.csv (InputError propagates)."""
    from mlaqc.inspection.pipeline import inspect_image, load_frame
    from mlaqc.report import write_report

    t0 = time.perf_counter()
    notes: list[str] = []
    img = load_frame(raw, cfg, levels, notes)
    load_s = time.perf_counter() - t0
    result = inspect_image(img, cfg, grid=grid, source=str(raw), notes=tuple(notes))
    result.timings_s["load"] = round(load_s, 4)  # the dict is mutable; the result is frozen
    write_report(result, folder, config_dict=cfg.to_dict())
    return {"result": result, "verdict": result.verdict, "flagged": len(result.defects),
            "out_of_tolerance": sum(1 for d in result.defects if not d.within_tolerance),
            "missing": sum(1 for d in result.defects if d.error_type == "missing"),
            "seconds": round(time.perf_counter() - t0, 3), "report": str(folder), "error": ""}


def write_batch_csv(path: Path, rows: list[dict]) -> None:
    """One line per frame, written atomically."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=BATCH_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    write_bytes_atomic(path, buf.getvalue().encode())


def run(args: argparse.Namespace) -> int:
    """Inspect and report; 0 all PASS, 1 some FAIL, 2 some frame was bad input (batch) or bad input."""
    out = check_out_dir(args.out)
    cfg = load_config(args.config)
    grid = shared_grid(args, cfg)
    if len(args.raw) == 1:
        row = inspect_one(args.raw[0], cfg, grid, out, stated_levels(args))
        if not args.quiet:
            print(summary(row["result"]), file=sys.stderr)
            print(f"  report: {out / 'report.html'}", file=sys.stderr)
        return 1 if row["result"].failed else 0
    out.mkdir(exist_ok=True)
    rows, t0 = [], time.perf_counter()
    for i, (raw, folder) in enumerate(zip(args.raw, report_folders(out, args.raw)), 1):
        try:
            row = inspect_one(raw, cfg, grid, folder, stated_levels(args))
            line = f"{row['verdict']}, {row['flagged']} flagged ({row['seconds']:.2f} s)"
        except InputError as exc:
            row = {"raw": raw, "verdict": "ERROR", "error": str(exc), "report": ""}
            line = f"ERROR: {exc}"
        rows.append({**row, "raw": raw})
        if not args.quiet:
            print(f"[{i}/{len(args.raw)}] {raw}: {line}", file=sys.stderr)
    write_batch_csv(out / "batch.csv", rows)
    verdicts = [r["verdict"] for r in rows]
    if not args.quiet:
        dt = time.perf_counter() - t0
        print(f"{verdicts.count('PASS')} PASS, {verdicts.count('FAIL')} FAIL, {verdicts.count('ERROR')} ERROR "
              f"in {dt:.1f} s ({dt / len(rows):.2f} s/frame); {out / 'batch.csv'}", file=sys.stderr)
    return 2 if "ERROR" in verdicts else (1 if "FAIL" in verdicts else 0)
