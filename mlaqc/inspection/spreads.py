"""Per-lens noise spreads: what each lens' deviations are judged against (mlaqc.inspection.detection). A
lens' spread is its noise class' (`lens_classes.noise_classes`: inner, the outer rings, the corner zones),
never below the inner lenses', raised to its second ring's and its edge group's own where they have the
lenses to read one; tail-aware (`tail_sigma`) so that systematics do not cross the threshold, robust so that
a small array's few defects do not set it."""

from __future__ import annotations

import numpy as np

from mlaqc.inspection.lens_classes import (SECOND_RING_MIN, corner_lenses, edge_groups, hex_column_ends,
                                           noise_classes, second_ring)
from mlaqc.inspection.medians import column_medians, finite_median


def robust_sigma(dev: np.ndarray) -> float:
    """1.4826 x median absolute deviation (NaN ignored); a tiny floor keeps z finite."""
    d = dev[np.isfinite(dev)]
    if d.size == 0:
        return np.inf
    return max(1.4826 * finite_median(np.abs(d - finite_median(d))), 1e-9)


def class_sigmas(dev: np.ndarray, floor: float | np.ndarray = 0.0, exclude: np.ndarray | None = None,
                 packing: str = "square") -> np.ndarray:
    """Per lens the spread (`tail_sigma`) of its noise class (`noise_classes`), never below the inner
    lenses' nor `floor`: edge lenses are noisier than inner ones, and one spread for all would flag them.
    The second ring's lenses (`second_ring`) are judged against their own spread too where it is wider,
    and so is each group of edge lenses (`edge_groups`, by its robust spread, which one defect among
    them does not move) where it has EDGE_GROUP_MIN measured lenses (hex: HEX_EDGE_GROUP_MIN; and the
    two sides' row ends of each kind together, `hex_column_ends`), the corners, whose deviation is
    always 0, left out. `dev` (rows, cols) or a stack
    (rows, cols, J) of maps, each with its own floor; `exclude`: lenses left out of the inner,
    second-ring and edge-group spreads (`_quiet_inner`)."""
    stack = dev[..., None] if dev.ndim == 2 else dev
    floor = np.broadcast_to(np.asarray(floor, float), stack.shape[-1:])
    cls = noise_classes(stack.shape[:2])
    flat = stack.reshape(-1, stack.shape[-1])
    inner_rows = flat[_quiet_inner(cls == 2, exclude).ravel()]
    inner = _column_tail_sigmas(inner_rows if (np.isfinite(inner_rows).sum(axis=0) > 8).all() else flat, floor)
    inner = np.where(np.isfinite(inner), np.maximum(inner, floor), floor)
    out = np.broadcast_to(inner, stack.shape).copy()
    for c in (0, 1, 3):
        sel = cls == c
        rows = stack[sel]
        if rows.size:
            spread = _column_tail_sigmas(rows, floor)
            ok = np.isfinite(rows).sum(axis=0) > 8
            out[sel] = np.where(ok, np.maximum(inner, np.nan_to_num(spread, nan=0.0)), inner)
    second = second_ring(stack.shape[:2])
    quiet = second if exclude is None else second & ~exclude  # (its spread without the defects' light)
    _raise_to_own(out, second, stack[quiet], lambda v: _column_tail_sigmas(v, floor))
    corners = corner_lenses(stack.shape[:2])
    least = EDGE_GROUP_MIN if packing != "hex" else HEX_EDGE_GROUP_MIN
    groups = list(edge_groups(stack.shape[:2], packing))
    if packing == "hex":  # the row ends of each kind, both sides together: a side alone may hold too few
        groups += hex_column_ends(stack.shape[:2])
    for group in groups:
        quiet = (group if exclude is None else group & ~exclude) & ~corners
        _raise_to_own(out, group, stack[quiet], _column_robust_sigmas, least)
    return out[..., 0] if dev.ndim == 2 else out


def _raise_to_own(out: np.ndarray, group: np.ndarray, values: np.ndarray, spread_of,
                  least: int = SECOND_RING_MIN) -> None:
    """out[group] raised, map by map, to the group's own spread (`spread_of` its `values`, (n, J)) where
    that map has `least` finite values (lenses off the sensor read NaN: a clipped side is too few)."""
    enough = np.isfinite(values).sum(axis=0) >= least
    if enough.any():
        spread = spread_of(values)
        out[group] = np.maximum(out[group], np.where(enough & np.isfinite(spread), spread, 0.0))


def _column_robust_sigmas(a: np.ndarray) -> np.ndarray:
    """`robust_sigma` of every column of a (n, J) over its finite values (NaN for a column with none)."""
    return 1.4826 * column_medians(np.abs(a - column_medians(a)))


def _column_tail_sigmas(a: np.ndarray, floor: float | np.ndarray = 0.0) -> np.ndarray:
    """`tail_sigma` of every column of a (n, J) at once (one sort); the outliers left out of the tail are
    those beyond TAIL_OUTLIER times the larger of the robust sigma and `floor` (per column)."""
    k = np.isfinite(a).sum(axis=0)
    dev = np.abs(a - column_medians(a))
    s = np.sort(np.ascontiguousarray(np.where(np.isfinite(dev), dev, np.inf).T), axis=1).T
    cols = np.arange(a.shape[1])

    def quantile(q: float, k: np.ndarray) -> np.ndarray:  # numpy's 'linear' quantile of each column's k smallest
        pos = q * np.maximum(k - 1, 0)
        lo = np.floor(pos).astype(int)
        hi = np.minimum(lo + 1, np.maximum(k - 1, 0))
        frac = pos - lo
        return s[lo, cols] * (1 - frac) + s[hi, cols] * frac

    with np.errstate(invalid="ignore"):
        mad = quantile(0.5, k)
        # the tail without the outliers beyond TAIL_OUTLIER robust sigma (sorted: they are the last ones)
        cut = TAIL_OUTLIER * np.maximum(1.4826 * mad, np.broadcast_to(np.asarray(floor, float), mad.shape))
        kept = np.where(cut > 0, (s <= cut).sum(axis=0), k)
        p99 = quantile(0.99, np.minimum(kept, k))
        out = np.maximum(np.maximum(1.4826 * mad, 1e-9), np.where(k >= 20, p99 / 2.576, 0.0))
    return np.where(k > 0, out, np.inf)


# An edge group (one side's outer or second ring) is judged against its own robust spread from this many
# measured lenses: on a small array the four sides' systematics differ (the outer ring's intensity tilt
# follows the sub-pixel phase across a side, which no phase fit can take off ten lenses), and pooled in one
# class spread a quiet side's hid a busy one's (12 x 12 analytic frames at 1 % noise: 17 false flags in 3).
EDGE_GROUP_MIN = 8
# Hex: a side's edge column holds half its rows of each kind of row end (6 on a 12 x 14 array), and the
# sides' sub-pixel patterns differ: the right column's sharpness spread 6 times the left's on one such
# noise-free frame, which both sides pooled (`hex_column_ends`) hid. A hex edge group's own spread is read
# from this many of its lenses; it only ever raises a lens' spread (its class' or the pooled group's),
# so its scatter on few lenses costs sensitivity there, never a false flag.
HEX_EDGE_GROUP_MIN = 5
TAIL_OUTLIER = 10.0  # tail spreads leave out deviations beyond this many robust sigma: defects, not noise nor systematics


def tail_sigma(dev: np.ndarray, floor: float = 0.0) -> float:
    """A spread that also answers to heavy tails: the larger of 1.4826 MAD and the 99th percentile of
    |dev - median| over its Gaussian value (2.576 sigma). For Gaussian noise both agree; where
    systematic errors (a profile the reference does not share, an edge) leave more lenses far out than
    noise would, the spread follows them, so that they do not cross the threshold. A defect rate under
    1 % of a class does not move it, nor do lenses beyond TAIL_OUTLIER robust sigma (defects: in a small
    array a few are more than 1 % of a class, and 9 among a 24 x 24 array's 384 inner lenses made its
    spreads 10-20 times the noise and its detection limits 5 times the large array's). `floor`: the
    smallest spread the cut assumes (the noise a noise-free frame is judged by), so that how much is cut
    does not depend on whether the frame has noise."""
    d = np.asarray(dev, float).reshape(-1, 1)
    d = d[np.isfinite(d[:, 0])]
    return float(_column_tail_sigmas(d, floor)[0]) if d.size else np.inf


def _quiet_inner(inner: np.ndarray, exclude: np.ndarray | None, least: int = 20) -> np.ndarray:
    """The inner lenses less `exclude` (a defect and its neighbours, whose windows hold its light), when
    at least `least` are left (the tail spread's smallest sample); else all inner lenses."""
    if exclude is None:
        return inner
    quiet = inner & ~exclude
    return quiet if quiet.sum() >= least else inner
