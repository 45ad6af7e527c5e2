"""Small exact maximum filters over per-lens maps, in NumPy (scipy.ndimage's import alone cost 0.13 s of
every `mlaqc inspect`; these maps are ~10^4 values). A maximum is exact whatever the order, so these give
scipy.ndimage.maximum_filter's result bit for bit (tests/test_filters.py) on maps without NaN (the callers'
boolean maps and finite scores; np.maximum spreads a NaN, scipy does not)."""

from __future__ import annotations

import functools

import numpy as np


def max_filter_nearest(a: np.ndarray, size: int) -> np.ndarray:
    """maximum_filter(a, size=size, mode="nearest") of a 2-D map (odd sizes; even ones go to scipy)."""
    if size % 2 == 0 or a.ndim != 2 or a.size == 0:
        from scipy.ndimage import maximum_filter

        return maximum_filter(a, size=size, mode="nearest")
    half = size // 2
    out = a
    for axis in (0, 1):
        padded = np.pad(out, [(half, half) if ax == axis else (0, 0) for ax in (0, 1)], mode="edge")
        n = out.shape[axis]
        acc = np.take(padded, np.arange(0, n), axis=axis)
        for k in range(1, size):
            acc = np.maximum(acc, np.take(padded, np.arange(k, k + n), axis=axis))
        out = acc
    return out.astype(a.dtype, copy=False)


def max_of_neighbours(a: np.ndarray) -> np.ndarray:
    """maximum_filter(a, footprint=3x3 ring without its centre, mode="constant") (cval 0) of a 2-D map."""
    rows, cols = a.shape
    padded = np.zeros((rows + 2, cols + 2), dtype=a.dtype)
    padded[1:-1, 1:-1] = a
    windows = [padded[di:di + rows, dj:dj + cols] for di in (0, 1, 2) for dj in (0, 1, 2) if (di, dj) != (1, 1)]
    return np.maximum.reduce(windows)



def lattice_max_of_neighbours(a: np.ndarray, packing: str = "square") -> np.ndarray:
    """Per lens the largest value of `a` over its lattice neighbours (square 8: `max_of_neighbours`; hex 6,
    `Lattice.neighbours`), 0 off the array."""
    if packing == "square":
        return max_of_neighbours(a)
    from mlaqc.optics.lattice import neighbour_offsets

    # each row parity's neighbours as shifted views of the map padded with 0 (off the array): the lenses
    # `Lattice.neighbours` lists (a maximum is exact whatever the order), without gathering them
    rows, cols = a.shape
    padded = np.zeros((rows + 2, cols + 2), dtype=a.dtype)
    padded[1:-1, 1:-1] = a
    out = np.empty_like(a)
    for parity in (0, 1):
        n = len(range(parity, rows, 2))
        if n:
            out[parity::2] = np.maximum.reduce([padded[1 + parity + dr::2][:n, 1 + dc:1 + dc + cols]
                                                for dr, dc in neighbour_offsets(packing, parity, True)])
    return out


def with_neighbours(mask: np.ndarray, packing: str = "square") -> np.ndarray:
    """`mask` grown by every lens' lattice neighbours: the lenses whose windows a flagged lens' light reaches."""
    return mask | lattice_max_of_neighbours(mask, packing)


@functools.lru_cache(maxsize=8)
def lattice_neighbours(packing: str, rows: int, cols: int) -> np.ndarray:
    """`Lattice(packing, rows, cols).neighbours(diagonal=True)`, read-only and cached per shape (1.3 ms a
    call on a 102 x 116 hex array)."""
    from mlaqc.optics.lattice import Lattice

    out = Lattice(packing, rows, cols).neighbours(diagonal=True)
    out.flags.writeable = False
    return out
