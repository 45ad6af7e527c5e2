"""`mlaqc lot`: what the results database says about many arrays — yield per lot and wafer, the defect types
that cost it, how often each lens is flagged, the defects that repeat at one lens across arrays (the
master's), and one array's history. Reads only; exit status 4 when the database cannot be read."""

from __future__ import annotations

import argparse
import json
import math

from mlaqc.resultsdb.control import CHARTS, CUSUM_H
from mlaqc.resultsdb.store import default_target

VIEWS = ("yield", "pareto", "map", "repeats", "chart", "history", "report")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `lot` subcommand."""
    p = sub.add_parser("lot", help="lot views of the results database: yield, Pareto, defect map, repeating defects",
                       description="Views of the inspections recorded in the results database (each array counts "
                                   "once, by its latest inspection): `yield` per lot and wafer; `pareto`: the defect "
                                   "types that failed arrays, most costly first; `map`: how many arrays flagged each "
                                   "lens; `repeats`: lenses flagged in more arrays than chance explains, with one type "
                                   "and direction (a defect of the master, in every replica); `chart`: a control "
                                   "chart of an array-level reading (--reading; a self-starting CUSUM, or with --chart "
                                   "imr an individuals chart with the Western Electric run rules), the arrays out of "
                                   "control named; `history`: every inspection of one "
                                   "array (--array), with its config and station; `report`: all of them on one "
                                   "HTML page with its plots (--out).")
    p.add_argument("view", choices=VIEWS, help="what to show")
    p.add_argument("--db", metavar="TARGET", help=f"the results database (default: $MLAQC_DB, else {default_target()})")
    p.add_argument("--lot", help="only this lot")
    p.add_argument("--wafer", help="only this wafer")
    p.add_argument("--array", help="history: the array (its serial or position)")
    p.add_argument("--reading", default="pitch_x_px",
                   help="chart: the reading (pitch_x_px, pitch_y_px, rotation_deg, distance_um, mla_rotation_deg, "
                        "tilt_x_deg, tilt_y_deg, flagged, out_of_tolerance; default pitch_x_px)")
    p.add_argument("--chart", choices=CHARTS, default="cusum",
                   help="chart and report: 'cusum' (default), a self-starting CUSUM: each array against all before "
                        "it, in-control false calls ~1 in 1,200 arrays; 'imr': an individuals / moving-range chart "
                        "with limits from the baseline and the Western Electric run rules (--rules)")
    p.add_argument("--baseline", type=int, default=20, metavar="N",
                   help="chart: the first N arrays are the process known good, not judged (imr: its limits come "
                        "from them; default 20)")
    p.add_argument("--cusum-h", type=float, metavar="H",
                   help=f"chart cusum: the decision interval in sigmas (default {CUSUM_H:g}; 5: a false call in ~460 "
                        "arrays, drifts called about one array sooner)")
    p.add_argument("--rules", help="chart imr: the run rules judged (default all: 1,2,3,4,5)")
    p.add_argument("--out", "-o", metavar="FILE.html", help="report: the page to write")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from mlaqc.errors import InputError
    from mlaqc.resultsdb import lot as views
    from mlaqc.resultsdb.store import open_database

    if args.view == "history" and not args.array:
        raise InputError("`mlaqc lot history` needs --array (the array's serial or position)")
    if args.view == "report" and not args.out:
        raise InputError("`mlaqc lot report` needs --out FILE.html")
    rules, h = _chart_options(args) if args.view in ("chart", "report") else (None, None)
    with open_database(args.db, create=False) as db:
        if args.view == "yield":
            data = views.yield_table(db, args.lot, args.wafer)
            lines = _table(data, ("lot", "wafer", "arrays", "passed", "failed", "yield"))
        elif args.view == "pareto":
            data = views.pareto(db, args.lot, args.wafer)
            lines = _table(data, ("error_type", "arrays_failed", "lenses", "share"))
        elif args.view == "map":
            counts, arrays, shape = views.stacked_map(db, args.lot, args.wafer)
            data = {"arrays": arrays, "rows": shape[0], "cols": shape[1],
                    "flagged": [{"m": m, "n": n, "arrays": k} for (m, n), k in sorted(counts.items())]}
            top = sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))[:20]
            lines = [f"{arrays} arrays; {len(counts)} lenses flagged in at least one; most often:",
                     *(f"  U({m},{n}): {k} of {arrays}" for (m, n), k in top)]
        elif args.view == "repeats":
            found = views.repeating_defects(db, args.lot, args.wafer)
            data = [{**d.__dict__, "share": d.share} for d in found]
            lines = [d.sentence() for d in found] or ["no lens is flagged in more arrays than chance explains"]
        elif args.view == "chart":
            from mlaqc.inspection.results import finite_or_none
            from mlaqc.resultsdb.control import lot_chart

            chart = lot_chart(db, args.reading, args.lot, args.wafer, args.baseline, rules, args.chart, h)
            data = {"reading": args.reading, "chart": chart.kind, "centre": finite_or_none(chart.centre),
                    "sigma": finite_or_none(chart.sigma),
                    "baseline": chart.baseline, "arrays": chart.labels, "values": chart.values.tolist(),
                    "out_of_control": {chart.labels[i]: r for i, r in chart.signals.items()},
                    "not_charted": chart.not_charted, "not_read": chart.not_read}
            if chart.kind == "cusum":
                data["h"] = chart.h
            lines = [chart.summary(args.reading), *chart.sentences()]
        elif args.view == "report":
            from pathlib import Path

            from mlaqc.atomic import write_bytes_atomic
            from mlaqc.resultsdb.lot_report import lot_report_html

            out = Path(args.out)
            if not out.parent.is_dir():
                raise InputError(f"cannot write the lot report: folder {out.parent} does not exist")
            page = lot_report_html(db, args.lot, args.wafer, baseline=args.baseline, kind=args.chart,
                                   rules=rules, h=h).encode()
            try:
                write_bytes_atomic(out, page)
            except OSError as exc:
                raise InputError(f"cannot write the lot report {out}: {(exc.strerror or str(exc)).rstrip('.')}") from exc
            print(f"lot report: {out}")
            return 0
        else:
            data = views.history(db, args.array, args.lot, args.wafer)
            lines = _table(data, ("recorded_utc", "lot", "wafer", "array", "verdict", "flagged", "station",
                                  "operator", "software_version", "config_hash", "report_dir"))
    print(json.dumps(data, indent=1, default=str) if args.json else "\n".join(lines))
    return 0


def _chart_options(args: argparse.Namespace) -> tuple[tuple[int, ...], float]:
    """The run rules and the CUSUM's h the chart and report views use; InputError for an option of the
    other chart or a value out of range."""
    from mlaqc.errors import InputError

    if args.rules is not None and args.chart != "imr":
        raise InputError("--rules chooses the run rules of `--chart imr`; the CUSUM chart has none")
    if args.cusum_h is not None and args.chart != "cusum":
        raise InputError("--cusum-h is the CUSUM chart's decision interval; `--chart imr` has none")
    if args.baseline < 2:
        raise InputError(f"--baseline must be at least 2 arrays, got {args.baseline}")
    h = CUSUM_H if args.cusum_h is None else args.cusum_h
    if not (math.isfinite(h) and h > 0):
        raise InputError(f"--cusum-h must be a positive number of sigmas, got {args.cusum_h}")
    return _rules(args.rules if args.rules is not None else "1,2,3,4,5"), h


def _rules(text: str) -> tuple[int, ...]:
    from mlaqc.errors import InputError
    from mlaqc.resultsdb.control import RULES

    try:
        rules = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        rules = ()
    if not rules or any(r not in RULES for r in rules):
        raise InputError(f"--rules must list run rules among {', '.join(map(str, RULES))} (e.g. 1,5), got {text!r}")
    return rules


def _cell(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3f}" if math.isfinite(v) else "-"
    return str(v)


def _table(rows: list[dict], columns: tuple[str, ...]) -> list[str]:
    """Rows as aligned text columns (the header first)."""
    if not rows:
        return ["nothing recorded for this selection"]
    cells = [list(columns)] + [[_cell(r.get(c)) for c in columns] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    return ["  ".join(v.ljust(w) for v, w in zip(row, widths)).rstrip() for row in cells]
