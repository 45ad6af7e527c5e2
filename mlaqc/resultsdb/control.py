"""Control charts of the array-level readings: is a process drifting (the array's pitch scale, rotation,
MLA–sensor distance, defect count), array after array?

An individuals and moving-range (I-MR) chart, the usual one for one measurement per unit: the centre line
is the mean of a baseline (the first `baseline` arrays, the process as it was known good), sigma the
baseline's mean moving range over d2 = 1.128 (robust to a slow drift, unlike the standard deviation), and
every array after is judged by the Western Electric run rules:

1. one point beyond 3 sigma;
2. two of three in a row beyond 2 sigma on one side;
3. four of five in a row beyond 1 sigma on one side;
4. eight in a row on one side of the centre line;
plus the trend rule: six in a row steadily rising or falling (a creeping drift shows here first).

A reading that did not vary over the baseline (a fixed value, a noise-free simulation) has no sigma: any
change of it is out of control, and the run rules are not judged. Their price is false calls: with limits from 20 in-control arrays, the first comes after a median of 34
arrays with every rule, 92 with rules 1 and 5 alone (`rules`), while a drift of a quarter sigma per array is
called after a median of 6 arrays (every rule) or 8 (rules 1 and 5) (tests/test_control_charts.py measures
both). A reading's own measured sigma (the assembly's) is not used: the chart's sigma is the arrays' spread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

D2 = 1.128  # the mean moving range of two normal values, in sigmas
RULES = {
    1: "beyond 3 sigma",
    2: "2 of 3 beyond 2 sigma on one side",
    3: "4 of 5 beyond 1 sigma on one side",
    4: "8 in a row on one side",
    5: "6 in a row steadily rising or falling",
}
# the readings a lot's charts can show: database column -> what it is
READINGS = {
    "pitch_x_px": "grid pitch along x (px)", "pitch_y_px": "grid pitch along y (px)",
    "rotation_deg": "grid rotation (deg)", "distance_um": "MLA-sensor distance (µm)",
    "mla_rotation_deg": "MLA rotation in the camera (deg)", "tilt_x_deg": "MLA tilt x (deg)",
    "tilt_y_deg": "MLA tilt y (deg)", "flagged": "flagged lenses", "out_of_tolerance": "lenses out of tolerance",
}


@dataclass
class Chart:
    """An I-MR chart: the values in order, its centre and sigma, and the points out of control."""

    values: np.ndarray
    labels: list[str]
    centre: float
    sigma: float
    baseline: int
    signals: dict[int, list[int]] = field(default_factory=dict)  # index -> the rules it breaks

    @property
    def first_signal(self) -> int | None:
        return min(self.signals) if self.signals else None

    def sentences(self) -> list[str]:
        return [f"{self.labels[i]} out of control: value {self.values[i]:.6g} ("
                + (f"{(self.values[i] - self.centre) / self.sigma:+.1f} sigma); " if self.sigma > 0
                   else f"the baseline's was {self.centre:.6g} without spread); ")
                + "; ".join(RULES[r] for r in rules) for i, rules in sorted(self.signals.items())]


def individuals_chart(values, labels=None, baseline: int = 20, rules=tuple(RULES)) -> Chart:
    """The I-MR chart of `values` (in production order), its limits from the first `baseline` of them,
    judged by `rules` (keys of RULES)."""
    x = np.asarray(values, float)
    labels = list(labels) if labels is not None else [f"#{i + 1}" for i in range(x.size)]
    base = x[: max(2, min(baseline, x.size))]
    centre = float(np.mean(base)) if base.size else math.nan
    mr = np.abs(np.diff(base))
    sigma = float(np.mean(mr)) / D2 if mr.size else math.nan
    if not (math.isfinite(sigma) and sigma > 0):
        # a baseline without spread (a fixed value, a noise-free simulation): no run rule can be judged;
        # any change at all is out of control (rule 1)
        centre = float(base[0]) if base.size else math.nan
        chart = Chart(x, labels, centre, 0.0, base.size)
        for i in range(base.size, x.size):
            if 1 in rules and not math.isclose(x[i], centre, rel_tol=1e-12, abs_tol=1e-300):
                chart.signals[i] = [1]
        return chart
    chart = Chart(x, labels, centre, sigma, base.size)
    z = (x - centre) / sigma
    for i in range(base.size, x.size):
        broken = [r for r in _rules(z, i) if r in rules]
        if broken:
            chart.signals[i] = broken
    return chart


def _rules(z: np.ndarray, i: int) -> list[int]:
    """The run rules point i breaks (only points up to i are read)."""
    out = []
    if abs(z[i]) > 3:
        out.append(1)
    for rule, (n, k, level) in ((2, (3, 2, 2.0)), (3, (5, 4, 1.0))):
        w = z[max(0, i - n + 1): i + 1]
        if w.size == n and any(np.count_nonzero(s * w > level) >= k and s * z[i] > level for s in (1, -1)):
            out.append(rule)
    w = z[max(0, i - 7): i + 1]
    if w.size == 8 and (np.all(w > 0) or np.all(w < 0)):
        out.append(4)
    w = z[max(0, i - 5): i + 1]
    if w.size == 6 and (np.all(np.diff(w) > 0) or np.all(np.diff(w) < 0)):
        out.append(5)
    return out


def lot_chart(db, reading: str, lot: str | None = None, wafer: str | None = None, baseline: int = 20,
              rules=tuple(RULES)) -> Chart:
    """The chart of one array-level reading over the selection's arrays, in the order they were inspected
    (each array by its latest inspection)."""
    from mlaqc.resultsdb.lot import latest_selection

    if reading not in READINGS:
        from mlaqc.errors import InputError

        raise InputError(f"no chart of {reading!r}: the readings are {', '.join(READINGS)}")
    latest, params = latest_selection(lot, wafer)
    rows = db.query(f"SELECT {reading}, lot, wafer, COALESCE(array_id, position, source) FROM inspections "
                    f"WHERE id IN ({latest}) AND {reading} IS NOT NULL ORDER BY inspected_utc, recorded_utc, id", params)
    return individuals_chart([float(r[0]) for r in rows], [f"{r[1] or '-'}/{r[2] or '-'}/{r[3]}" for r in rows],
                             baseline, rules)
