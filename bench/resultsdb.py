"""The results database (issue #39, part 1): what recording costs an inspection, and how fast the lot views
answer on a large store.

1. Recording: the record of a real inspection (a 2048² analytic Table 1 frame, `tests/analytic_frames.py`,
   24 anomalies, whole-process `mlaqc inspect` in this process) written into a fresh SQLite store 50 times
   (each its own transaction, committed to disk), its median against the inspection's own time.
2. Lot queries: a store of N inspections (default 100,000: 400 lots of 250 arrays of 102 x 102 lenses, a
   master defect at one lens in 80 % of one lot's arrays, 8 random flags per array) built in bulk, then
   each view (`yield`, `pareto`, `map`, `repeats`, `history`, a `chart` of the grid pitch) timed for one
   lot, and `yield` and the charts for all.

    python bench/resultsdb.py               # 100,000 inspections (~2 min to build the store)
    python bench/resultsdb.py --store 10000 --quick
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parent / "tests")]

from mlaqc.resultsdb.control import Chart, lot_chart  # noqa: E402
from mlaqc.resultsdb import lot as views  # noqa: E402
from mlaqc.resultsdb.record import Identity, record_from_report  # noqa: E402
from mlaqc.resultsdb.store import open_database  # noqa: E402

TYPES = ("pitch", "radius", "dim", "tilt", "decenter", "missing")


def recording_cost(tmp: Path, repeats: int) -> tuple[float, float]:
    """(median seconds to record one real inspection, that inspection's whole-process seconds)."""
    import analytic_frames as am
    from mlaqc.cli import main

    rng = np.random.default_rng(5)
    model = am.AnalyticModel(rim="airy")
    model = model.with_anomalies(am.random_anomalies(model, 24, rng))
    counts = am.to_counts(am.expose(model.render(), 0.01, rng), 16)
    raw = am.write_container(tmp / "t1.tif", counts, 16, 0)
    main(["inspect", str(raw), "-o", str(tmp / "warm"), "--quiet", "--no-db"])  # models and kernels loaded
    t0 = time.perf_counter()
    main(["inspect", str(raw), "-o", str(tmp / "out"), "--quiet", "--no-db"])
    inspect_s = time.perf_counter() - t0
    import json

    rec = record_from_report(json.loads((tmp / "out" / "report.json").read_text()))
    times = []
    with open_database(str(tmp / "cost.sqlite")) as db:
        for i in range(repeats):
            t0 = time.perf_counter()
            db.record(rec, Identity(lot="L", array=f"A{i}"), str(tmp / "out"))
            times.append(time.perf_counter() - t0)
    return statistics.median(times), inspect_s


def build_store(path: str, n: int, per_lot: int = 250, seed: int = 1) -> None:
    """N synthetic inspections in bulk (one transaction per 5,000), as `ResultsDB.record` lays them out."""
    rng = np.random.default_rng(seed)
    with open_database(path) as db:
        cols = None
        batch_i, batch_f = [], []
        for i in range(n):
            lot, a = divmod(i, per_lot)
            defects = [(int(m), int(c), str(rng.choice(TYPES)), 1.0, "µm", float(rng.uniform(0, 360)), 9.0,
                        int(rng.random() < 0.7)) for m, c in rng.integers(1, 103, (8, 2))]
            if lot == 3 and rng.random() < 0.8:
                defects.append((51, 17, "pitch", 1.3, "µm", float(rng.normal(120, 4)), 12.0, 0))
            failed = any(not d[-1] for d in defects)
            fields = {"run_key": f"k{i}", "recorded_utc": f"2026-{1 + i * 12 // n:02d}-01T00:00:00", "lot": f"L{lot:04d}",
                      "wafer": f"W{a // 25:02d}", "array_id": f"A{a:03d}", "source": f"f{i}.tif",
                      "verdict": "FAIL" if failed else "PASS", "software_version": "0.1.0", "lens_rows": 102,
                      "lens_cols": 102, "flagged": len(defects), "pitch_x_px": 20.05 + rng.normal(0, 1e-4)}
            cols = cols or list(fields)
            batch_i.append(tuple(fields[c] for c in cols))
            batch_f.append(defects)
            if len(batch_i) == 5000 or i == n - 1:
                with db._transaction() as cur:
                    cur.execute("SELECT COALESCE(MAX(id), 0) FROM inspections")
                    first = cur.fetchone()[0] + 1
                    cur.executemany(f"INSERT INTO inspections ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})",
                                    batch_i)
                    cur.executemany("INSERT INTO flagged_lenses VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                                    [(first + k, *d) for k, ds in enumerate(batch_f) for d in ds])
                batch_i, batch_f = [], []


def time_views(path: str) -> list[tuple[str, float, str]]:
    out = []
    with open_database(path, create=False) as db:
        for name, fn in (("yield, all lots", lambda: views.yield_table(db)),
                         ("yield, one lot", lambda: views.yield_table(db, "L0003")),
                         ("pareto, one lot", lambda: views.pareto(db, "L0003")),
                         ("map, one lot", lambda: views.stacked_map(db, "L0003")),
                         ("repeats, one lot", lambda: views.repeating_defects(db, "L0003")),
                         ("history, one array", lambda: views.history(db, "A017", "L0003")),
                         ("chart (CUSUM), one lot", lambda: lot_chart(db, "pitch_x_px", "L0003")),
                         ("chart (CUSUM), all lots", lambda: lot_chart(db, "pitch_x_px")),
                         ("chart (I-MR), all lots", lambda: lot_chart(db, "pitch_x_px", kind="imr"))):
            fn()  # warm: the file in the page cache, scipy imported
            t0 = time.perf_counter()
            result = fn()
            dt = time.perf_counter() - t0
            what = (f"{len(result)} rows" if isinstance(result, list) else
                    f"{result.values.size} arrays, {len(result.signals)} out of control" if isinstance(result, Chart) else
                    f"{len(result[0])} lenses")
            if name.startswith("repeats"):
                what = "; ".join(f"U({d.m},{d.n}) {d.error_type} {d.arrays}/{d.of_arrays}" for d in result) or "none"
            out.append((name, dt, what))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", type=int, default=100_000, help="inspections in the query store")
    ap.add_argument("--quick", action="store_true", help="10 recordings instead of 50")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rec_s, insp_s = recording_cost(tmp, 10 if args.quick else 50)
        print(f"recording one inspection: {rec_s * 1e3:.1f} ms median = {rec_s / insp_s:.1%} of its whole-process "
              f"inspection ({insp_s:.2f} s)   [bar <= 5 %]")
        path = str(tmp / "store.sqlite")
        t0 = time.perf_counter()
        build_store(path, args.store)
        size = Path(path).stat().st_size / 2**20
        print(f"store of {args.store:,} inspections built in {time.perf_counter() - t0:.0f} s ({size:.0f} MiB)")
        for name, dt, what in time_views(path):
            print(f"  {name:<20} {dt * 1e3:8.1f} ms   {what}   [bar <= 1000 ms]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
