"""The mock wafer's production story (issue #39): a lot of wafers of replicated arrays, scanned and inspected
as a station would (`mlaqc scan --inspect --db`, the mock camera rendering each array with the ray tracer),
then the lot's questions answered from the results database and checked against the story's truth:

- a defect of the master (U(5,7), pitch 1.5 µm at 30°) in a seeded 80 % of the arrays: named as repeating,
  with its lens, type, direction and share (bar: the share within 5 % of the seeded one);
- 2 random defects of random types on every array: none called repeating (bar: 0);
- from one array on (production index `--drift-from`), the MLA–sensor distance 0.5 µm larger with every
  array: the control chart of the assembly's distance reading calls it (bar: within 5 arrays of its onset,
  no call on the arrays before it), by the default self-starting CUSUM and by the I-MR chart with every run
  rule and with rules 1 and 5 alone.

    python bench/production.py                    # 5 wafers x 25 arrays of the small camera (~10 min)
    python bench/production.py --wafers 2 --side 3 --drift-from 12
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from mlaqc.cli import main as mlaqc  # noqa: E402
from mlaqc.resultsdb import lot as views  # noqa: E402
from mlaqc.resultsdb.control import lot_chart  # noqa: E402
from mlaqc.resultsdb.store import open_database  # noqa: E402

MASTER = (5, 7)


def raster_plan(side: int, pitch_mm: float) -> str:
    """A scan plan visiting a side x side wafer's arrays row by row (their production order)."""
    lines = ["[scan]", "settle_s = 0.0"]
    for m in range(1, side + 1):
        for n in range(1, side + 1):
            lines += ["[[positions]]", f"x_mm = {10.0 + (n - 1) * pitch_mm}", f"y_mm = {10.0 + (m - 1) * pitch_mm}",
                      f'label = "W({m},{n})"']
    return "\n".join(lines) + "\n"


def camera_url(wafer: int, side: int, pitch_mm: float, args) -> str:
    return (f"mock://?wafer={side}x{side}&pitch_mm={pitch_mm}&defects=2&defect_types=pitch,decenter,radius"
            f"&seed={wafer}&rpp={args.rpp}&master={MASTER[0]},{MASTER[1]}&master_type=pitch&master_size=1.5"
            f"&master_dir=30&master_share={args.share}&drift_from={args.drift_from}&drift_um={args.drift_um}"
            f"&first_index={(wafer - 1) * side * side + 1}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--wafers", type=int, default=5)
    ap.add_argument("--side", type=int, default=5, help="arrays per wafer side")
    ap.add_argument("--share", type=float, default=0.8, help="the master's share of the arrays")
    ap.add_argument("--drift-from", type=int, default=70, help="production index of the first drifted array")
    ap.add_argument("--drift-um", type=float, default=0.5)
    ap.add_argument("--rpp", type=float, default=40)
    ap.add_argument("--keep", help="keep the scans and the database in this folder")
    args = ap.parse_args()
    root = Path(args.keep or tempfile.mkdtemp(prefix="mlaqc-production-"))
    root.mkdir(parents=True, exist_ok=True)
    db = str(root / "lot.sqlite")
    pitch_mm = 5.0
    (root / "plan.toml").write_text(raster_plan(args.side, pitch_mm))
    truth = []
    t0 = time.perf_counter()
    for w in range(1, args.wafers + 1):
        out = root / f"wafer{w:02d}"
        status = mlaqc(["scan", "--camera", camera_url(w, args.side, pitch_mm, args), "--stage", "mock://",
                        "--plan", str(root / "plan.toml"), "--out", str(out), "--inspect", "--db", db,
                        "--lot", "LOT1", "--wafer", f"W{w:02d}", "--quiet"])
        header = json.loads((out / "manifest.jsonl").read_text().splitlines()[0])
        truth += [{**a, "wafer": f"W{w:02d}"} for a in header["truth"]["arrays"]]
        print(f"wafer {w}: scanned and inspected (exit {status}), {time.perf_counter() - t0:.0f} s", flush=True)
    n_arrays = len(truth)
    seeded_share = sum(a["master"] for a in truth) / n_arrays
    with open_database(db, create=False) as store:
        repeats = views.repeating_defects(store, "LOT1")
        charts = {"self-starting CUSUM (the default)": lot_chart(store, "distance_um", "LOT1"),
                  **{f"I-MR, rules {','.join(map(str, rules))}": lot_chart(store, "distance_um", "LOT1", rules=rules, kind="imr")
                     for rules in ((1, 2, 3, 4, 5), (1, 5))}}
        yields = views.yield_table(store, "LOT1")
    print(f"{n_arrays} arrays scanned, {sum(y['arrays'] for y in yields)} inspected and recorded; yield "
          + ", ".join(f"{y['wafer']} {y['passed']}/{y['arrays']}" for y in yields))
    master = [d for d in repeats if (d.m, d.n) == MASTER]
    others = [d for d in repeats if (d.m, d.n) != MASTER]
    for d in repeats:
        print("  " + d.sentence())
    if master:
        d = master[0]
        print(f"master: found, share {d.share:.3f} vs seeded {seeded_share:.3f} (bar: within 0.05), type {d.error_type}, "
              f"direction {d.direction_deg:.1f}° (seeded 30)")
    else:
        print("master: NOT found")
    print(f"random defects called repeating: {len(others)} (bar: 0)")
    # the chart's arrays are in inspection order = production order: index i is production index i + 1
    onset = args.drift_from - 1
    for name, chart in charts.items():
        calls = sorted(chart.signals)
        before = [f"{chart.labels[i]} ({','.join(map(str, chart.signals[i]))})" for i in calls if i < onset]
        after = [i for i in calls if i >= onset]
        print(f"distance chart, {name}: centre {chart.centre:.2f} µm, sigma {chart.sigma:.2f} µm "
              f"(the first {chart.baseline} arrays not judged); calls on the {onset - chart.baseline} arrays before the drift: {len(before)} "
              f"{before[:4]} (bar: 0); the drift called "
              + (f"at array {after[0] - onset + 1} of it (bar: within 5)" if after else "never"))
    print(f"scans, database and reports in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
