"""The iris control's value-to-f-number mapping (IrisMap) and the iris limits; why: drivers.camera.v4l2's docstring."""

from __future__ import annotations

import itertools
import math
import numbers
import operator
from dataclasses import dataclass

from mlaqc.errors import InputError

UVC_IRIS_UNIT = 0.01  # f-number per unit of UVC's CT_IRIS_ABSOLUTE_CONTROL ("fstop * 100")
IRIS_TOLERANCE_REL = 0.01  # a setting further than this from the f-number asked for is refused
IRIS_TIMEOUT_S = 2.0  # default wait for the iris to read back what was written
IRIS_POLL_S = 0.02
IRIS_HOME_EXTRA_STEPS = 2  # opening steps beyond the table's largest count when finding the open stop


@dataclass(frozen=True)
class IrisMap:
    """How an iris control's value maps to the main lens' f-number N (module docstring: why UVC is the default).

    `unit`: N = value x unit. `table`: measured (value, N) points, N strictly monotonic in the value,
    interpolated linearly in stops (log N) between them; nothing outside the table is mapped. For a
    relative iris control the value counts the steps closed from fully open. InputError if malformed."""

    unit: float = UVC_IRIS_UNIT
    table: tuple[tuple[int, float], ...] = ()

    def __post_init__(self) -> None:
        if isinstance(self.unit, bool) or not isinstance(self.unit, numbers.Real) or not math.isfinite(self.unit) \
                or self.unit <= 0:
            raise InputError(f"iris_unit must be a positive number (f-number per control unit), got {self.unit!r}")
        if not self.table:
            return
        try:
            points = tuple(sorted((operator.index(v), float(n)) for v, n in self.table))
        except (TypeError, ValueError):
            points = ()
        values = [v for v, _ in points]
        stops = [n for _, n in points]
        steps = [b - a for a, b in itertools.pairwise(stops)]
        if (len(points) < 2 or len(set(values)) != len(values) or not all(math.isfinite(n) and n > 0 for n in stops)
                or not (all(d > 0 for d in steps) or all(d < 0 for d in steps))):
            raise InputError(f"iris_table must be at least two value:f-number points with distinct whole values and "
                             f"positive f-numbers that all rise or all fall with the value, got {self.table!r}")
        object.__setattr__(self, "table", points)

    def f_number(self, value: float) -> float:
        """The f-number at a control value; NaN outside the table."""
        if not self.table:
            return float(value) * self.unit
        for (v0, n0), (v1, n1) in itertools.pairwise(self.table):
            if v0 <= value <= v1:
                return n0 * (n1 / n0) ** ((value - v0) / (v1 - v0))
        return math.nan

    def value(self, f_number: float) -> float | None:
        """The (fractional) control value giving f/N; None outside the table."""
        if not self.table:
            return f_number / self.unit
        for (v0, n0), (v1, n1) in itertools.pairwise(self.table):
            if min(n0, n1) <= f_number <= max(n0, n1):
                return v0 + (v1 - v0) * math.log(f_number / n0) / math.log(n1 / n0)
        return None

    def f_range(self, lo: int, hi: int) -> tuple[float, float] | None:
        """The smallest and largest f-number among control values lo..hi (within the table); None if none."""
        if self.table:
            lo, hi = max(lo, self.table[0][0]), min(hi, self.table[-1][0])
        if lo > hi:
            return None
        ends = (self.f_number(lo), self.f_number(hi))
        return min(ends), max(ends)

    def describe(self) -> str:
        if self.table:
            return "iris_table " + ",".join(f"{v}:{n:g}" for v, n in self.table)
        if self.unit == UVC_IRIS_UNIT:
            return "f-number x 100, UVC's unit"
        return f"f-number = value x {self.unit:g}, iris_unit"
