"""Local baselines: each lens' index values less the median of its own neighbourhood, what identification
(mlaqc.inspection.identify) detects on.

Detection compares every lens with its own neighbourhood (5 x 5 local median, which cancels vignetting,
exposure and slow field variation; on a hex lattice the same 5 x 5 window of offset coordinates, see
`local_deviations`): one compiled median pass over all of a frame's index maps (`median_baselines`;
`_scipy_baseline` is the reference formulation). The few windows that hold lenses that do not belong in
them are recomputed without them (`_refine_baselines`): lenses not measured, and the array's outermost
lenses, which miss neighbours and carry their own bias. On hex the outer lenses, whose windows miss the
strip of the rows beyond, are left out of every other lens' baseline, and the row ends that stick out are
compared with each other (`_hex_edge_columns`). With circular apertures, and on hex, the windows stay
centred on their lens near the edges and beside lenses left out (`centred`), but for the end lenses of a
hex edge column's row parity, whose clipped window would be their own value (`_line_windows`).
"""

from __future__ import annotations

import os
from itertools import pairwise

import numpy as np

from mlaqc.inspection.filters import max_filter_nearest
from mlaqc.inspection.lens_classes import ring_distance
from mlaqc.inspection.metrics_kernels import median_baselines
from mlaqc.inspection.medians import last_axis_medians, middles
from mlaqc.parallel import thread_map


def local_deviation(values: np.ndarray, size: int = 5, axis: str = "", packing: str = "square") -> np.ndarray:
    """values minus a NaN-robust local baseline: the median over size x size lenses inside the array
    (leaving out lenses not measured, and the outermost ones for lenses two or more in: see
    `_refine_baselines`); along an edge the running median of that edge (its lenses miss the same
    neighbours). A corner lens misses neighbours on two sides: for an x index (axis='x') it is compared
    along its left/right edge, otherwise along its top/bottom edge, whose running median repeats its own
    value: its deviation is 0 (not judged: `lens_classes.corner_lenses`)."""
    return local_deviations([values], [axis], size, packing)[0]


def local_deviations(planes: list[np.ndarray], axes: list[str], size: int = 5,
                     packing: str = "square", centred: bool = False,
                     exclude: np.ndarray | None = None, only: np.ndarray | None = None) -> list[np.ndarray]:
    """`local_deviation` of several (rows, cols) index maps at once: one compiled median pass over all of
    them (scipy's median_filter cost 16 ms per map); even sizes or all-NaN maps take the scipy route.

    Hex (`packing`): the window is the same size x size block of offset coordinates (U(m,n) indexes). It
    is local (every lens in it lies within 2.6 pitches) but not point-symmetric: rows m +- 1 sit half a
    pitch to one side. Its median is still the lens' own value on a linear trend along x, y or the
    lattice directions, and off by at most 0.33 pitch times the trend's slope per pitch in between (a
    trend of 1 % per pitch reads 0.0033), far below any index' noise; the slow maps it removes
    (vignetting, exposure, distortion) change by much less per pitch. The left and right columns,
    whose lenses alternately stick out (missing 3 of 6 neighbours) and sit in (missing 1), take the
    running median of the lenses of their own row parity (`_hex_edge_columns`). `centred`: the windows
    that leave the outermost lenses out stay centred on their lens (`_refine_baselines`). `exclude`:
    lenses left out of every baseline (as a lens not measured is), each still compared with its own.
    `only`: the lenses whose deviations the caller reads (the others' edge rules are skipped: each lens'
    baseline is its own window's, so theirs come out as without it)."""
    measured = planes
    if exclude is not None and exclude.any():
        planes = [np.where(exclude, np.nan, v) for v in planes]
    fills = []
    for values in planes:
        finite = np.isfinite(values)
        fills.append(values if finite.all() else np.where(finite, values, np.nanmedian(values)))
    stack = np.array(fills, dtype=np.float64)
    if size % 2 == 1 and np.isfinite(stack).all():
        base = np.empty_like(stack)
        x_axis = np.array([a == "x" for a in axes])
        workers = min(len(stack) // 2, os.cpu_count() or 1)  # the kernel releases the GIL: planes in parallel
        if stack[0].size < _THREADED_FROM:  # (a strip's few lenses: the threads cost more than they save)
            workers = 1
        if workers > 1:
            cuts = np.linspace(0, len(stack), workers + 1).astype(int)
            thread_map(lambda ab: median_baselines(stack[ab[0]:ab[1]], int(size), x_axis[ab[0]:ab[1]],
                                                   base[ab[0]:ab[1]]), pairwise(cuts))
        else:
            median_baselines(stack, int(size), x_axis, base)
    else:
        base = np.stack([_scipy_baseline(f, size, a) for f, a in zip(stack, axes)])
    finite = np.isfinite(np.array(planes, dtype=np.float64))
    # hex: a window 2 px taller than the 0.87-pitch row step holds a strip of the rows above and below,
    # so the outer lenses, missing theirs, differ from the others far more than on a square lattice
    # (measured: SSIM 0.56 against 0.97): they are left out of every other lens' neighbourhood
    _refine_baselines(stack, finite, base, size, [a == "x" for a in axes], 1 if packing == "hex" else 2, centred, only)
    if packing == "hex":
        _hex_edge_columns(stack, finite, base, size, [a == "x" for a in axes], only)
    return [values - b for values, b in zip(measured, base)]


_THREADED_FROM = 4096  # lenses per map from which the compiled median pass runs its planes in threads


def _hex_edge_columns(stack: np.ndarray, finite: np.ndarray, base: np.ndarray, size: int,
                      x_axis: list[bool], only: np.ndarray | None = None) -> None:
    """Hex lattice: the baselines of the first and last columns, in place, as the running median (size
    lenses, centred and clipped; the end lenses' slid inward, `_line_windows`) of the finite lenses of the
    same column and row parity: a shifted row's end lens misses other neighbours than an unshifted row's,
    and the two carry different biases. Corners are left to the rows for planes not along x (as
    `median_baselines` leaves them), and out of the other lenses' medians: outermost along their row too,
    they are another population (measured: a corner's tilt 0.2 against 0.003 along the column), which the
    window's clipping at the column's end counts twice, so that one lens not measured beside it made it
    half the median). `only`: as `_refine_baselines` takes it (a column with none of those lenses is left
    as it is)."""
    _, rows, cols = stack.shape
    if rows < 2 * size or cols < size:
        return
    x_planes = np.asarray(x_axis, bool)
    for col in (0, cols - 1):
        if only is not None and not only[:, col].any():
            continue
        for parity in (0, 1):
            r = np.arange(parity, rows, 2)
            corner = (r == 0) | (r == rows - 1)
            idx, inside = _line_windows(len(r), size, corner)
            vals = stack[:, r, col][:, idx]
            # a corner lens (outermost along its row too) is no sample of the column's population
            use = finite[:, r, col][:, idx] & inside[None] & ~(corner[idx] & ~corner[:, None])[None]
            med, ok = last_axis_medians(np.where(use, vals, np.nan))
            write = ok & (~corner[None, :] | x_planes[:, None])
            base[:, r, col] = np.where(write, med, base[:, r, col])


def _line_windows(n: int, size: int, corner: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Running-median windows along a line of n lenses whose `corner` ones (at its ends) are no sample:
    (idx (n, size), inside (n, size) bool). Each window is centred on its lens and clipped to the line
    (mode 'nearest'), but the first and last lenses between the corners take the `size` lenses nearest
    them: clipped, their window repeats them, and without the corner its median is always their own
    value, so that they were never judged. Windows elsewhere stay centred: one slid off its lens reads
    the lenses beyond it, whose systematics near a corner are not its own (measured: 2 false flags on a
    102 x 116 hex frame of round lenses)."""
    off = np.arange(size) - size // 2
    j = np.arange(n)
    idx = np.clip(j[:, None] + off[None, :], 0, n - 1)
    inside = np.ones((n, size), bool)
    lo = 1 if n and corner[0] else 0
    hi = n - 2 if n and corner[-1] else n - 1
    for end in {lo, hi} if 0 <= lo <= hi else ():
        start = min(max(end - size // 2, lo), max(hi - size + 1, lo))
        idx[end] = np.minimum(start + np.arange(size), n - 1)
        inside[end] = start + np.arange(size) <= hi
    return idx, inside


def _outer_share(rows: int, cols: int, size: int) -> np.ndarray:
    """Per lens the share of its size x size window, clipped to the array (mode 'nearest': an edge row
    counted again for each row beyond it), that the array's outermost lenses fill."""
    off = np.arange(size) - size // 2
    inner_rows = np.clip(np.arange(rows)[:, None] + off, 0, rows - 1)
    inner_cols = np.clip(np.arange(cols)[:, None] + off, 0, cols - 1)
    r_in = ((inner_rows > 0) & (inner_rows < rows - 1)).sum(axis=1)
    c_in = ((inner_cols > 0) & (inner_cols < cols - 1)).sum(axis=1)
    return 1.0 - np.outer(r_in, c_in) / float(size * size)


def _refine_baselines(stack: np.ndarray, finite: np.ndarray, base: np.ndarray, size: int,
                      x_axis: list[bool], outer_from: int = 2, centred: bool = False,
                      only: np.ndarray | None = None) -> None:
    """Recompute, in place, the baselines of the few lenses whose neighbourhood (the compiled pass'
    window, clipped to the array as scipy's mode 'nearest') holds lenses that do not belong in it, as the
    median of the others (`stack`: the maps, read only where `finite`). A lens not measured (NaN: off
    the sensor, lost) is left out instead of counted as the whole map's median; the array's outermost
    lenses, which miss neighbours and carry their own bias, are left out of the neighbourhoods of the
    lenses two or more rows in (those next to the edge are their own class, judged against their own
    spread, and keep them, but beside a corner, where they would fill half the window and be its median:
    a microscope's 46 px sub-images read the outer lenses' 1.7 % flux deficit there at 28 sigma). Without
    this a lens beside the not-inspected part of an edge, or two lenses in from the edge, is judged against a
    baseline pulled towards another population. `outer_from`: the
    ring (distance to the edge) from which on the outermost lenses are left out (hex: 1, every lens).
    `centred`: the lenses opposite those left out (the window point-mirrored through the lens: beyond the
    outermost or a lens not measured) are left out too, two or more lenses in, so the window stays
    centred on its lens: one reaching a row further to one side reads a
    slow trend (vignetting: 0.24 % of flux per row near a Table 1 frame's top and bottom) as half a row's
    worth of deviation, which a frame whose flux noise floor is low (circular apertures: a lens' flux
    does not answer to its focal errors) flags along the whole second row. `only`: the lenses whose
    baselines are wanted (None: all); the others' windows are not recomputed."""
    n_f, rows, cols = stack.shape
    half = size // 2
    edges = rows >= size and cols >= size
    ring = ring_distance((rows, cols)) if edges else np.zeros((rows, cols), np.int64)
    outer = edges & (ring == 0)
    # left out of a window: NaN lenses; the outermost ones too for lenses two or more in
    near_nan = max_filter_nearest(~finite.all(axis=0), size)
    # left out also where they would be half a lens' window (clipped as the compiled pass clips it): beside a
    # corner, where the outer lenses' own bias (their light lacks the neighbours beyond them) is the median
    crowded = _outer_share(rows, cols, size) >= 0.5 if edges else np.zeros_like(outer)
    leave_out = (ring >= outer_from) | crowded
    near_outer = max_filter_nearest(outer, size) & leave_out if edges else np.zeros_like(outer)
    todo = (near_nan | near_outer) & ~outer
    m, n = np.nonzero(todo if only is None else todo & only)
    if m.size:
        off = np.arange(-half, half + 1)
        ii, jj = np.broadcast_arrays(m[:, None, None] + off[None, :, None], n[:, None, None] + off[None, None, :])
        ii, jj = np.clip(ii, 0, rows - 1).reshape(m.size, -1), np.clip(jj, 0, cols - 1).reshape(m.size, -1)
        same = (finite == finite[0]).all()  # (the usual case: every map measured at the same lenses)
        drop = ~(finite[:1] if same else finite)[:, ii, jj] | (outer[ii, jj] & leave_out[m, n][:, None])[None]
        if centred:  # two or more in, also those opposite them (mirrored through the lens): centred on it
            drop = drop | (drop[..., ::-1] & (ring[m, n] >= 2)[None, :, None])
        if same:
            med, ok = _kept_medians(stack.reshape(n_f, -1), ii * cols + jj, drop[0])
        else:
            med, ok = last_axis_medians(np.where(drop, np.nan, stack[:, ii, jj]))
        base[:, m, n] = np.where(ok, med, base[:, m, n])
    if not edges:
        return
    # the outermost lenses, along their edge line: only the lenses not measured are left out (all maps at
    # once; a corner keeps the value of the line the compiled pass wrote last: columns for an x index)
    if finite[:, outer].all():
        return
    x_planes = np.asarray(x_axis, bool)
    for sl, corner_wins in (((0, slice(None)), ~x_planes), ((-1, slice(None)), ~x_planes),
                            ((slice(None), 0), x_planes), ((slice(None), -1), x_planes)):
        line_ok = finite[(slice(None),) + sl]  # (F, L)
        if line_ok.all():
            continue
        q = np.flatnonzero(np.convolve(~line_ok.all(axis=0), np.ones(size), mode="same") > 0)
        idx = np.clip(q[:, None] + np.arange(-half, half + 1)[None, :], 0, line_ok.shape[1] - 1)
        med, ok = last_axis_medians(np.where(line_ok[:, idx], stack[(slice(None),) + sl][:, idx], np.nan))
        line = base[(slice(None),) + sl]  # (a view: written through)
        ends = (q == 0) | (q == line_ok.shape[1] - 1)  # the corners: only where this line wins them
        write = ok & (~ends[None, :] | corner_wins[:, None])
        line[:, q] = np.where(write, med, line[:, q])


def _kept_medians(flat: np.ndarray, idx: np.ndarray, drop: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`last_axis_medians` of flat[:, idx] (F, N, K) with the values where `drop` (N, K) left out, the same
    lenses in every map: per count of values kept, one gather of those alone and its two middle ranks
    (`middles`: no NaN to sort; the same order statistics, so the same medians bit for bit)."""
    k = (~drop).sum(axis=1)
    med = np.zeros((flat.shape[0], len(k)))
    if len(k):
        order = np.argsort(drop, axis=1, kind="stable")  # the kept values first, in window order
        kept = np.take_along_axis(idx, order, axis=1)
        for kk in np.unique(k[k > 0]):
            sel = np.flatnonzero(k == kk)
            med[:, sel] = middles(flat[:, kept[sel, :kk]], (kk - 1) // 2, kk // 2)
    return med, np.broadcast_to(k > 0, med.shape)


def _scipy_baseline(fill: np.ndarray, size: int, axis: str) -> np.ndarray:
    """The local median baseline of one NaN-filled map with scipy (the reference formulation)."""
    from scipy.ndimage import median_filter

    base = median_filter(fill, size=size, mode="nearest")
    rows, cols = fill.shape
    if rows >= size and cols >= size:
        horizontal = ((0, slice(None)), (-1, slice(None)))
        vertical = ((slice(None), 0), (slice(None), -1))
        order = horizontal + vertical if axis == "x" else vertical + horizontal  # the last one wins at corners
        for sl in order:
            base[sl] = median_filter(fill[sl], size=size, mode="nearest")
    return base
