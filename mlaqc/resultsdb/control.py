"""Control charts of the array-level readings: is a process drifting (the array's pitch scale, rotation,
MLA–sensor distance, defect count), array after array?

Two charts, each naming the arrays out of control:

- `cusum_chart` (the default): a self-starting CUSUM (Hawkins 1987). Each array is standardised against the
  mean and standard deviation of every array before it (Student's t with their degrees of freedom, turned
  into a normal score), so that an in-control process gives exactly independent N(0, 1) scores however
  short its history: the chart's false-call rate is its design's, not the luck of a short baseline. The
  scores are summed both ways, S = max(0, S + U - k), k = 0.5 (tuned to a shift of one sigma); an array is
  out of control while either sum is beyond h = 6 (a sustained rise or fall), or when its own score is
  beyond 4 (a jump; a lone one stays out of the sums, Lucas and Crosier's robust CUSUM, so one misread
  array does not call the ones after it). In-control, the first false call comes after a mean of about 1,200 arrays (4 % of
  series call one within 49 arrays); a drift of a quarter sigma per array is called after a median of 9
  arrays, one of a sigma per array after 4 (tests/test_control_charts.py measures all three). After the
  first call the estimates stop learning: the arrays after it are judged against the process as it was.
- `individuals_chart` (`--chart imr`): an individuals and moving-range (I-MR) chart, the shop-floor classic.
  Its centre line is the mean of a baseline (the first `baseline` arrays), sigma the baseline's mean moving
  range over d2 = 1.128, and every array after is judged by the Western Electric run rules:

  1. one point beyond 3 sigma;
  2. two of three in a row beyond 2 sigma on one side;
  3. four of five in a row beyond 1 sigma on one side;
  4. eight in a row on one side of the centre line;
  plus the trend rule: six in a row steadily rising or falling (a creeping drift shows here first).

  Their price is false calls: with limits from 20 in-control arrays, the first comes after a median of 34
  arrays with every rule, 92 with rules 1 and 5 alone (`rules`), while a drift of a quarter sigma per array
  is called after a median of 6 arrays (every rule) or 8 (rules 1 and 5). The baseline mean's own error,
  ±sigma/√20, looks like a shift to every rule that integrates.

In both, the first `baseline` arrays are taken as the process known good and are not judged. A reading that
did not vary over them (a fixed value, a noise-free simulation) has no sigma: any change of it is out of
control. A reading's own measured sigma (the assembly's) is not used: a chart's sigma is the arrays' spread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

D2 = 1.128  # the mean moving range of two normal values, in sigmas
CUSUM_K = 0.5  # the CUSUM's reference value, in sigmas: tuned to a shift of one sigma
CUSUM_H = 6.0  # its decision interval: a two-sided in-control run of ~1,200 arrays on average
JUMP_Z = 4.0  # one array's score beyond this is out of control at once (a false call in ~16,000 arrays)
CHARTS = ("cusum", "imr")
NAMED_UNREAD = 10  # a chart's summary names this many arrays without a reading (the JSON names them all)
CUSUM_SIGNALS = {
    "rise": "a sustained rise (the upper CUSUM beyond h)",
    "fall": "a sustained fall (the lower CUSUM beyond h)",
    "jump": f"beyond {JUMP_Z:g} sigma of the arrays before it",
}
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
    """A chart: the values in order, its centre and sigma, and the points out of control. A CUSUM chart
    also holds what each array was judged against (`centre_at`, `sigma_at`: NaN for the baseline) and its
    two sums (`cusum`: (2, n), upper and lower, in sigmas)."""

    values: np.ndarray
    labels: list[str]
    centre: float
    sigma: float
    baseline: int
    signals: dict[int, list] = field(default_factory=dict)  # index -> the rules it breaks
    kind: str = "imr"
    centre_at: np.ndarray | None = None
    sigma_at: np.ndarray | None = None
    cusum: np.ndarray | None = None
    h: float = CUSUM_H
    known: np.ndarray | None = None  # CUSUM: how many arrays each was judged against
    jump: float = JUMP_Z
    not_charted: list[str] = field(default_factory=list)  # arrays whose reading is stored not finite (inf, NaN)
    not_read: list[str] = field(default_factory=list)  # arrays with no reading stored (not read, not determined)

    def jump_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """CUSUM: the values beyond which each array is a jump (its score beyond ±`jump`): the mean of the
        arrays before it ± their deviation × sqrt((n + 1) / n) × Student's t at the normal's tail of `jump`
        (n - 1 degrees of freedom; far wider than `jump` sigmas while n is small); NaN where not judged."""
        from scipy.special import ndtr, stdtrit

        n = self.known.astype(float)
        with np.errstate(all="ignore"):
            half = self.sigma_at * np.sqrt((n + 1) / n) * stdtrit(np.maximum(n - 1, 1), ndtr(self.jump))
        return self.centre_at - half, self.centre_at + half

    @property
    def first_signal(self) -> int | None:
        return min(self.signals) if self.signals else None

    def summary(self, reading: str) -> str:
        """One line: what the chart is, its centre and sigma, how many arrays are out of control."""
        n, base = len(self.values), self.baseline
        if n <= base:
            how = f"{n} arrays: none judged after the first {base}"
        elif not self.sigma > 0:
            how = f"no spread over the first {base}: any change is out of control"
        elif self.kind == "cusum":
            how = (f"self-starting CUSUM (k {CUSUM_K:g}, h {self.h:g} sigma), the first {base} not judged"
                   + ("; centre and sigma of the arrays before the first call" if self.signals else ""))
        else:
            how = f"I-MR, limits from the first {base}"
        left = (f"; {len(self.not_charted)} not charted, their reading not finite: {', '.join(self.not_charted)}"
                if self.not_charted else "") + (f"; {self.unread_words()}" if self.not_read else "")
        centre = f"{self.centre:.6g}" if math.isfinite(self.centre) else "–"
        return (f"{reading}: {n} arrays, centre {centre}, sigma {self.sigma:.3g} ({how}); "
                f"{len(self.signals)} out of control{left}")

    def unread_words(self, most: int = NAMED_UNREAD) -> str:
        """How many arrays have no reading (the frame did not read it, or could not determine it), the
        first `most` named: a lot of cropped frames has no assembly reading at all."""
        more = len(self.not_read) - most
        names = ", ".join(self.not_read[:most]) + (f" and {more} more" if more > 0 else "")
        return f"{len(self.not_read)} without this reading (not read or not determined): {names}"

    def sentences(self) -> list[str]:
        words = CUSUM_SIGNALS if self.kind == "cusum" else RULES
        return [f"{self.labels[i]} out of control: value {self.values[i]:.6g} (" + self._offset(i) + "; "
                + "; ".join(words[r] for r in rules) for i, rules in sorted(self.signals.items())]

    def _offset(self, i: int) -> str:
        if not self.sigma > 0:
            return f"the baseline's was {self.centre:.6g} without spread)"
        if self.kind == "cusum":
            z = (self.values[i] - self.centre_at[i]) / self.sigma_at[i]
            return f"{z:+.1f} sigma from the arrays before it; CUSUM {max(self.cusum[:, i]):.1f}, h {self.h:g})"
        return f"{(self.values[i] - self.centre) / self.sigma:+.1f} sigma)"


def make_chart(values, labels=None, baseline: int = 20, kind: str = "cusum", rules=tuple(RULES),
               h: float = CUSUM_H) -> Chart:
    """The chart of `kind` ('cusum' or 'imr', CHARTS) of `values` in production order."""
    if kind not in CHARTS:
        raise ValueError(f"chart kind must be one of {CHARTS}, not {kind!r}")
    if kind == "cusum":
        return cusum_chart(values, labels, baseline, h=h)
    return individuals_chart(values, labels, baseline, rules)


def cusum_chart(values, labels=None, baseline: int = 20, k: float = CUSUM_K, h: float = CUSUM_H,
                jump: float = JUMP_Z) -> Chart:
    """The self-starting CUSUM chart of `values` (in production order; see the module note): the first
    `baseline` of them not judged, every later one against all before it until the first call, and against
    the arrays before that call after it. A score beyond ±`jump` is a jump; it enters the sums (clipped to
    ±`jump`) only when the one before it went beyond on the same side too (Lucas and Crosier's robust
    CUSUM): one wild array (a misread, a broken part) is not a sustained rise for the arrays after it."""
    x = _finite(values)
    labels = list(labels) if labels is not None else [f"#{i + 1}" for i in range(x.size)]
    nb = max(2, min(baseline, x.size))
    if x.size < 3 or not np.ptp(x[:nb]) > 0:
        return _without_spread(x, labels, nb)
    ref = float(np.median(x[:nb]))  # centred first: pitches of 20 px vary by 1e-5
    u, centre_at, sigma_at = _scores(x - ref, np.arange(x.size))
    sums, signals = _cusum(u, nb, k, h, jump)
    if signals and min(signals) + 1 < x.size:  # the process moved: judge what follows against what it was
        first = min(signals)
        known = np.minimum(np.arange(x.size), first)  # the arrays each is judged against: those before `first`
        u, centre_at, sigma_at = _scores(x - ref, known)
        sums, signals = _cusum(u, nb, k, h, jump)
    else:
        known = np.arange(x.size)
    before = x[: min(signals)] if signals else x
    return Chart(x, labels, float(np.mean(before)), float(np.std(before, ddof=1)), nb, signals, "cusum",
                 centre_at + ref, sigma_at, sums, h, known, jump)


def _finite(values) -> np.ndarray:
    """`values` as floats; ValueError naming the first that is not a finite number (the charts' sums and
    means would carry it to every array after it)."""
    x = np.asarray(values, float)
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        raise ValueError(f"value #{bad[0] + 1} ({x[bad[0]]}) is not a finite number: a chart cannot judge it")
    return x


def _scores(d: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each value's normal score against the first known[i] values (their mean and standard deviation,
    Student's t with known[i] - 1 degrees of freedom), with that mean and deviation; NaN where known[i] < 2.
    `d`: the values less a typical one (the sums of squares keep their precision)."""
    from scipy.special import ndtri, stdtr

    s1 = np.concatenate([[0.0], np.cumsum(d)])[known]
    s2 = np.concatenate([[0.0], np.cumsum(d * d)])[known]
    n = known.astype(float)
    with np.errstate(all="ignore"):
        mean = s1 / n
        sd = np.sqrt(np.maximum(s2 - s1 * mean, 0.0) / (n - 1))
        t = (d - mean) / sd * np.sqrt(n / (n + 1))
        ok = (known >= 2) & (sd > 0) & np.isfinite(t)
        tail = stdtr(np.where(ok, n - 1, 1.0), -np.abs(np.where(ok, t, 0.0)))  # the far tail: exact in both
        tail = np.maximum(tail, np.finfo(float).tiny)  # beyond it (~38 sigma) the score stays finite
        u = np.where(ok, -np.sign(t) * ndtri(tail), np.nan)
    return u, np.where(ok, mean, np.nan), np.where(ok, sd, np.nan)


def _cusum(u: np.ndarray, start: int, k: float, h: float, jump: float) -> tuple[np.ndarray, dict[int, list]]:
    """The upper and lower CUSUMs of the scores from `start` on ((2, n), 0 before), and the arrays beyond
    h or beyond `jump` on their own."""
    his, los = [0.0] * u.size, [0.0] * u.size
    signals: dict[int, list] = {}
    hi = lo = 0.0
    scores = u.tolist()  # (Python floats: the recursion is sequential, 10^5 arrays in a tenth of a second)
    beyond = 0  # the side the previous score went beyond `jump` on (0: it did not)
    for i in range(start, u.size):
        ui = scores[i]
        side = (ui > jump) - (ui < -jump)
        if side == 0 or side == beyond:  # a lone wild score stays out of the sums; a second in a row is a shift
            clipped = min(max(ui, -jump), jump)
            hi, lo = max(0.0, hi + clipped - k), max(0.0, lo - clipped - k)
        beyond = side
        his[i], los[i] = hi, lo
        if hi > h or lo > h or abs(ui) > jump:
            signals[i] = [name for name, out in (("rise", hi > h), ("fall", lo > h), ("jump", abs(ui) > jump)) if out]
    return np.array([his, los]), signals


def _without_spread(x: np.ndarray, labels: list[str], nb: int, kind: str = "cusum") -> Chart:
    """A baseline without spread (a fixed value, a noise-free simulation): no sigma, so any change at all
    is out of control ('jump' / rule 1)."""
    centre = float(x[0]) if x.size else math.nan
    chart = Chart(x, labels, centre, 0.0, min(nb, x.size), kind=kind)
    for i in range(chart.baseline, x.size):
        if not math.isclose(x[i], centre, rel_tol=1e-12, abs_tol=1e-300):
            chart.signals[i] = ["jump" if kind == "cusum" else 1]
    return chart


def individuals_chart(values, labels=None, baseline: int = 20, rules=tuple(RULES)) -> Chart:
    """The I-MR chart of `values` (in production order), its limits from the first `baseline` of them,
    judged by `rules` (keys of RULES)."""
    x = _finite(values)
    labels = list(labels) if labels is not None else [f"#{i + 1}" for i in range(x.size)]
    base = x[: max(2, min(baseline, x.size))]
    centre = float(np.mean(base)) if base.size else math.nan
    mr = np.abs(np.diff(base))
    sigma = float(np.mean(mr)) / D2 if mr.size else math.nan
    if not (math.isfinite(sigma) and sigma > 0):  # no run rule can be judged; any change is out of control
        chart = _without_spread(x, labels, base.size, "imr")
        if 1 not in rules:
            chart.signals.clear()
        return chart
    chart = Chart(x, labels, centre, sigma, base.size)
    broken = _rules((x - centre) / sigma)  # (5, n): rule r broken at point i, reading points up to i
    use = np.array([r in rules for r in RULES])
    for i in np.flatnonzero(broken[use].any(axis=0)):
        if i >= base.size:
            chart.signals[int(i)] = [r for r, hit in zip(RULES, broken[:, i]) if hit and r in rules]
    return chart


def _rules(z: np.ndarray) -> np.ndarray:
    """(5, n) bool: the run rules (RULES' order) each point breaks, read on the points up to it (a window
    that would reach before the first point breaks nothing), all points at once."""
    n = z.size
    out = np.zeros((5, n), bool)
    out[0] = np.abs(z) > 3

    def windows(size):  # (n, size): the `size` points ending at each point, NaN-padded before the first
        padded = np.concatenate([np.full(size - 1, np.nan), z])
        return np.lib.stride_tricks.sliding_window_view(padded, size)

    for row, (size, k, level) in ((1, (3, 2, 2.0)), (2, (5, 4, 1.0))):
        w = windows(size)
        full = ~np.isnan(w).any(axis=1)
        for sign in (1, -1):
            out[row] |= full & (np.count_nonzero(sign * w > level, axis=1) >= k) & (sign * z > level)
    w = windows(8)
    out[3] = ~np.isnan(w).any(axis=1) & (np.all(w > 0, axis=1) | np.all(w < 0, axis=1))
    d = np.diff(windows(6), axis=1)
    out[4] = ~np.isnan(d).any(axis=1) & (np.all(d > 0, axis=1) | np.all(d < 0, axis=1))
    return out


def lot_chart(db, reading: str, lot: str | None = None, wafer: str | None = None, baseline: int = 20,
              rules=tuple(RULES), kind: str = "cusum", h: float = CUSUM_H) -> Chart:
    """The chart of one array-level reading over the selection's arrays, in the order they were inspected
    (each array by its latest inspection)."""
    from mlaqc.resultsdb.lot import latest_selection

    if reading not in READINGS:
        from mlaqc.errors import InputError

        raise InputError(f"no chart of {reading!r}: the readings are {', '.join(READINGS)}")
    latest, params = latest_selection(lot, wafer)
    rows = db.query(f"SELECT {reading}, lot, wafer, COALESCE(array_id, position, source) FROM inspections "
                    f"WHERE id IN ({latest}) ORDER BY inspected_utc, recorded_utc, id", params)
    values, labels, left, unread = [], [], [], []
    for value, *who in rows:
        label = f"{who[0] or '-'}/{who[1] or '-'}/{who[2]}"
        if value is None:  # not read (a crop, too few lenses whole) or not determined: named, not charted
            unread.append(label)
        elif math.isfinite(float(value)):
            values.append(float(value))
            labels.append(label)
        else:  # a reading stored as inf or NaN: not charted, named
            left.append(label)
    chart = make_chart(values, labels, baseline, kind, rules, h)
    chart.not_charted, chart.not_read = left, unread
    return chart
