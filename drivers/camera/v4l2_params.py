"""A V4L2 camera's URL parameters (URL_PARAMS) and their parsers, and the checks of values given to the camera."""

from __future__ import annotations

import math
import numbers
import operator
from typing import Any

from drivers.camera.v4l2_iris import IrisMap
from mlaqc.errors import InputError

URL_PARAMS = ("format", "width", "height", "exposure_us", "gain", "roi", "buffers", "settle_frames", "exposure_unit_us",
              "f_number", "iris_unit", "iris_table", "iris_timeout_s")


def _check_number(name: str, value: float, positive: bool = False) -> float:
    """A finite number (positive if asked); InputError otherwise."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) \
            or (positive and value <= 0):
        raise InputError(f"{name} must be a {'positive ' if positive else ''}finite number, got {value!r}")
    return float(value)


def _check_roi(what: str, roi: tuple[Any, ...]) -> tuple[int, int, int, int]:
    """(x, y, w, h) with x, y >= 0 and w, h > 0, all integers; InputError otherwise."""
    try:
        values = tuple(operator.index(v) for v in roi)
    except TypeError:
        values = ()
    if len(values) != 4 or min(values[:2]) < 0 or min(values[2:]) <= 0:
        raise InputError(f"{what} must be four integers x, y >= 0 and width, height > 0, got {tuple(roi)!r}")
    return values  # type: ignore[return-value]


def _int_param(url: str, name: str, text: str | None, lo: int, hi: int | None = None) -> int | None:
    """An integer URL parameter within [lo, hi], or None if absent."""
    if text is None:
        return None
    try:
        value = int(text)
    except ValueError:
        raise InputError(f"parameter {name}={text!r} in camera URL {url!r} is not an integer") from None
    if value < lo or (hi is not None and value > hi):
        bound = f"between {lo} and {hi}" if hi is not None else f"at least {lo}"
        raise InputError(f"parameter {name}={value} in camera URL {url!r} must be {bound}")
    return value


def _float_param(url: str, name: str, text: str | None, positive: bool = False) -> float | None:
    """A finite (optionally positive) float URL parameter, or None if absent."""
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"parameter {name}={text!r} in camera URL {url!r} is not a number") from None
    if not math.isfinite(value) or (positive and value <= 0):
        kind = "a positive number" if positive else "a finite number"
        raise InputError(f"parameter {name}={text!r} in camera URL {url!r} must be {kind}")
    return value


def _iris_table_param(url: str, text: str | None) -> tuple[tuple[int, float], ...] | None:
    """The iris_table=V:N,V:N,... URL parameter (control value: f-number), or None if absent."""
    if text is None:
        return None
    try:
        points = tuple((int(v), float(n)) for v, n in (item.split(":") for item in text.split(",")))
        IrisMap(table=points)
    except (ValueError, InputError):
        raise InputError(f"parameter iris_table={text!r} in camera URL {url!r} must be value:f-number points, e.g. "
                         "280:2.8,400:4,560:5.6, at least two, with f-numbers that all rise or all fall with the "
                         "value") from None
    return points


def _roi_param(url: str, text: str | None) -> tuple[int, int, int, int] | None:
    """The roi=x,y,w,h URL parameter, or None if absent."""
    if text is None:
        return None
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"parameter roi={text!r} in camera URL {url!r} must be x,y,width,height") from None
    return _check_roi(f"parameter roi in camera URL {url!r}", values)
