"""The lot views of the results database: yield per lot and wafer, the defect types that cost it (a
Pareto), how often each lens is flagged across arrays (the stacked defect map), and the defects that
repeat at one lens in many arrays — a defect of the master (mold or stamp) that every replica carries.

Each array counts once, by its latest inspection (an array inspected again replaces its earlier reading
in these views; the history stays in the database). An inspection without an array identity counts as
an array of its own raw.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from dataclasses import dataclass

from mlaqc.resultsdb.store import ResultsDB

DIRECTIONAL = ("pitch", "decenter", "position", "tilt", "scratch", "obscuration")  # types whose reading has a direction
# a lens repeats when chance (every flag equally likely on every lens of every array, the lot's own rate)
# explains its count with a probability under this, counted over all lenses of the array (Bonferroni)
REPEAT_P = 1e-3
REPEAT_MIN_ARRAYS = 3
TYPE_SHARE = 0.75  # ... and one type holds at least this share of its flags
DIRECTION_R = 0.7  # ... and, directional, their directions agree (mean resultant length at least this)


def latest_selection(lot: str | None, wafer: str | None) -> tuple[str, tuple]:
    """SQL condition and parameters of the latest inspection of every array of the selection."""
    cond, params = [], []
    if lot is not None:
        cond.append("lot = ?")
        params.append(lot)
    if wafer is not None:
        cond.append("wafer = ?")
        params.append(wafer)
    where = f"WHERE {' AND '.join(cond)}" if cond else ""
    latest = (f"SELECT MAX(id) FROM inspections {where} "
              "GROUP BY lot, wafer, COALESCE(array_id, position, source)")
    return latest, tuple(params)


def yield_table(db: ResultsDB, lot: str | None = None, wafer: str | None = None) -> list[dict]:
    """Per lot and wafer: arrays inspected, passed, failed, and the yield."""
    latest, params = latest_selection(lot, wafer)
    rows = db.query(f"SELECT lot, wafer, COUNT(*), SUM(CASE WHEN verdict = 'PASS' THEN 1 ELSE 0 END) "
                    f"FROM inspections WHERE id IN ({latest}) GROUP BY lot, wafer ORDER BY lot, wafer", params)
    return [{"lot": r[0], "wafer": r[1], "arrays": int(r[2]), "passed": int(r[3] or 0),
             "failed": int(r[2]) - int(r[3] or 0), "yield": (int(r[3] or 0) / int(r[2])) if r[2] else math.nan}
            for r in rows]


def pareto(db: ResultsDB, lot: str | None = None, wafer: str | None = None) -> list[dict]:
    """Per defect type, most costly first: the arrays it failed (a flag out of tolerance), the lenses it
    flagged out of tolerance, and its share of all such lenses."""
    latest, params = latest_selection(lot, wafer)
    rows = db.query(f"SELECT error_type, COUNT(DISTINCT inspection_id), COUNT(*) FROM flagged_lenses "
                    f"WHERE within_tolerance = 0 AND inspection_id IN ({latest}) GROUP BY error_type", params)
    total = sum(int(r[2]) for r in rows)
    out = [{"error_type": r[0], "arrays_failed": int(r[1]), "lenses": int(r[2]),
            "share": int(r[2]) / total if total else math.nan} for r in rows]
    return sorted(out, key=lambda d: (-d["arrays_failed"], -d["lenses"], d["error_type"]))


def stacked_map(db: ResultsDB, lot: str | None = None, wafer: str | None = None) -> tuple[dict, int, tuple]:
    """({(m, n): arrays in which U(m,n) was flagged}, arrays in the selection, (rows, cols) of the largest)."""
    latest, params = latest_selection(lot, wafer)
    arrays, shape = _extent(db, latest, params)
    rows = db.query(f"SELECT m, n, COUNT(DISTINCT inspection_id) FROM flagged_lenses "
                    f"WHERE inspection_id IN ({latest}) GROUP BY m, n", params)
    return {(int(m), int(n)): int(k) for m, n, k in rows}, arrays, shape


def _extent(db: ResultsDB, latest: str, params: tuple) -> tuple[int, tuple[int, int]]:
    """(arrays in the selection, (rows, cols) of the largest)."""
    arrays, rows, cols = db.query(f"SELECT COUNT(*), MAX(lens_rows), MAX(lens_cols) FROM inspections "
                                  f"WHERE id IN ({latest})", params)[0]
    return int(arrays or 0), (int(rows or 0), int(cols or 0))


ARRAY_COLUMNS = ("wafer", "array", "verdict", "flagged", "out_of_tolerance", "inspected_utc", "station", "report_dir")


def arrays(db: ResultsDB, lot: str | None = None, wafer: str | None = None) -> list[tuple]:
    """Every array of the selection by its latest inspection, in wafer and inspection order: tuples of
    ARRAY_COLUMNS (the array named by its serial, else its position label, else its raw)."""
    latest, params = latest_selection(lot, wafer)
    return db.query("SELECT wafer, COALESCE(array_id, position, source), verdict, flagged, out_of_tolerance, "
                    f"inspected_utc, station, report_dir FROM inspections WHERE id IN ({latest}) "
                    "ORDER BY wafer, inspected_utc, id", params)


@dataclass(frozen=True)
class RepeatingDefect:
    """A lens flagged in many arrays with one type (and direction): the master's, not chance's."""

    m: int
    n: int
    arrays: int  # in which it is flagged
    of_arrays: int  # in the selection
    error_type: str
    type_share: float  # of its flags
    direction_deg: float | None  # the mean direction of its directional flags
    direction_r: float | None  # their agreement, 0 (none) .. 1 (all alike)
    median_magnitude: float | None
    unit: str
    p_chance: float  # that the lot's random flags put this many on one lens (over all lenses)

    @property
    def share(self) -> float:
        return self.arrays / self.of_arrays

    def sentence(self) -> str:
        d = f" at {self.direction_deg:.0f}°" if self.direction_deg is not None else ""
        mag = f", median {self.median_magnitude:.3g} {self.unit}".rstrip() if self.median_magnitude is not None else ""
        return (f"U({self.m},{self.n}) repeats: {self.error_type}{d} in {self.arrays} of {self.of_arrays} arrays "
                f"({self.share:.0%}{mag}); chance would put so many on one lens with probability {self.p_chance:.1e}: "
                "a defect of the master (mold or stamp), in every replica it made")


def repeating_defects(db: ResultsDB, lot: str | None = None, wafer: str | None = None) -> list[RepeatingDefect]:
    """The lenses flagged in more arrays than chance explains, with one consistent type (and direction)."""
    from scipy.stats import binom

    latest, params = latest_selection(lot, wafer)
    arrays, (rows, cols) = _extent(db, latest, params)
    lenses = rows * cols
    if arrays < REPEAT_MIN_ARRAYS or not lenses:
        return []
    flags = db.query(f"SELECT m, n, inspection_id, error_type, direction_deg, magnitude, unit FROM flagged_lenses "
                     f"WHERE inspection_id IN ({latest})", params)
    per_lens: dict[tuple[int, int], list] = defaultdict(list)
    for m, n, ident, kind, direction, magnitude, unit in flags:
        per_lens[(int(m), int(n))].append((ident, kind, direction, magnitude, unit))
    total = sum(len({f[0] for f in v}) for v in per_lens.values())  # lens-arrays flagged
    out = []
    for (m, n), lens_flags in per_lens.items():
        k = len({f[0] for f in lens_flags})
        if k < REPEAT_MIN_ARRAYS:
            continue
        rate = max(total - k, 1) / max(arrays * lenses - arrays, 1)  # the lot's rate elsewhere
        p = min(1.0, lenses * float(binom.sf(k - 1, arrays, rate)))
        kind, count = Counter(f[1] for f in lens_flags).most_common(1)[0]
        share = count / len(lens_flags)
        if p >= REPEAT_P or share < TYPE_SHARE:
            continue
        mean_dir, r = _mean_direction([f[2] for f in lens_flags if f[1] == kind], kind)
        if r is not None and r < DIRECTION_R:
            continue
        mags = sorted(f[3] for f in lens_flags if f[1] == kind and f[3] is not None)
        unit = next((f[4] for f in lens_flags if f[1] == kind), "") or ""
        out.append(RepeatingDefect(m, n, k, arrays, kind, share, mean_dir, r,
                                   mags[len(mags) // 2] if mags else None, unit, p))
    return sorted(out, key=lambda d: (d.p_chance, -d.arrays, d.m, d.n))


def _mean_direction(directions: list, kind: str) -> tuple[float | None, float | None]:
    """(mean direction in degrees, mean resultant length) of a directional type's readings; a scratch's
    axis is taken modulo 180°. (None, None) for a type without direction."""
    values = [float(d) for d in directions if d is not None]
    if kind not in DIRECTIONAL or not values:
        return None, None
    fold = 2.0 if kind == "scratch" else 1.0
    c = sum(math.cos(math.radians(v * fold)) for v in values) / len(values)
    s = sum(math.sin(math.radians(v * fold)) for v in values) / len(values)
    return (math.degrees(math.atan2(s, c)) / fold) % (360.0 / fold), math.hypot(c, s)


HISTORY_COLUMNS = ("recorded_utc", "inspected_utc", "lot", "wafer", "array_id", "position", "source", "verdict",
                   "flagged", "out_of_tolerance", "station", "operator", "software_version", "config_hash",
                   "report_dir")


def history(db: ResultsDB, array: str, lot: str | None = None, wafer: str | None = None) -> list[dict]:
    """Every inspection of one array (by its serial, else its position label), oldest first."""
    cond, params = ["(array_id = ? OR (array_id IS NULL AND position = ?))"], [array, array]
    for col, value in (("lot", lot), ("wafer", wafer)):
        if value is not None:
            cond.append(f"{col} = ?")
            params.append(value)
    rows = db.query(f"SELECT {', '.join(HISTORY_COLUMNS)} FROM inspections WHERE {' AND '.join(cond)} "
                    "ORDER BY recorded_utc, id", tuple(params))
    return [{("array" if c == "array_id" else c): v for c, v in zip(HISTORY_COLUMNS, r)} for r in rows]
