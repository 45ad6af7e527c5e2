"""Lens classes by where a lens sits in the array: its ring (distance to the edge), its edge and noise
class, and the groups of lenses that share a systematic pattern.

A lens at the array's edge misses neighbours, so its indexes carry their own bias and spread:
identification (mlaqc.inspection.identify) judges each class against its own (`edge_classes`,
`noise_classes`, `second_ring`, `edge_groups`), and fits the sub-pixel phase pattern per group (`_groups`,
mlaqc.inspection.phase_pattern). On a hex lattice the row ends that stick out half a pitch past the rows
above and below are apart from those that sit in (`hex_row_ends`), and the second ring and the two kinds of
row end each have their own sub-pixel phase pattern. The maps depend on the array's shape alone: cached
per shape, read-only (`_frozen`) and shared by every frame.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np


@functools.lru_cache(maxsize=8)
def ring_distance(shape: tuple[int, int]) -> np.ndarray:
    """Per lens its distance to the array's edge in lenses (0 = the outer row or column): the ring it
    is on. The fewest lattice steps off the array on hex too (see `edge_classes`)."""
    rows, cols = shape
    m, n = np.ogrid[:rows, :cols]
    return _frozen(np.minimum(np.minimum(m, n), np.minimum(rows - 1 - m, cols - 1 - n)))


@functools.lru_cache(maxsize=8)
def edge_classes(shape: tuple[int, int]) -> np.ndarray:
    """Per lens its distance to the array's edge in lenses, clipped at 2 (0 = outer row/column, 1 = the
    next, 2 = inner): edge lenses miss neighbours, so their indexes have their own bias and spread.
    The same on a hex lattice: one step to a neighbour changes the row or the column index by at most
    one, and straight along a row or column reaches the edge, so the fewest steps from U(m,n) off the
    array are min(m, rows + 1 - m, n, cols + 1 - n) there too (each shifted row's end lens, missing one
    neighbour, is in the outer class with the unshifted rows' ends, which miss three; their baselines
    are kept apart, see `_hex_edge_columns`)."""
    return _frozen(ring_distance(shape).clip(max=2))


@functools.lru_cache(maxsize=8)
def corner_lenses(shape: tuple[int, int]) -> np.ndarray:
    """(rows, cols) bool: the array's four corner lenses. Their edge lines' running medians repeat their own
    value (a corner is the outermost lens of two lines), so their deviation is 0 whatever they hold: not
    judged, and said so, rather than passed unseen."""
    out = np.zeros(shape, bool)
    if shape[0] and shape[1]:
        out[[0, 0, -1, -1], [0, -1, 0, -1]] = True
    return _frozen(out)


@functools.lru_cache(maxsize=8)
def noise_classes(shape: tuple[int, int]) -> np.ndarray:
    """`edge_classes`, with the 4 x 4 lenses at each corner a class of their own (3): their
    neighbourhoods reach past the array on two sides, and their deviations are wider still."""
    rows, cols = shape
    m, n = np.ogrid[:rows, :cols]
    zone = (np.minimum(m, rows - 1 - m) <= 3) & (np.minimum(n, cols - 1 - n) <= 3)
    cls = edge_classes(shape)
    return _frozen(np.where(zone & (rows > 12) & (cols > 12), 3, cls))


@functools.lru_cache(maxsize=8)
def second_ring(shape: tuple[int, int]) -> np.ndarray:
    """The inner lenses (`noise_classes` 2) of the second ring in: their baseline windows leave the
    outermost lenses out (`_refine_baselines`: 3 or 4 rows of 5), so the frame's systematics read in
    them otherwise. Judged against their own spread where it is wider than the inner lenses' (which they
    stay part of) where the ring has SECOND_RING_MIN of them: behind circles the sub-pixel phase pattern
    a 3-row median leaves reached 6.6 sigma of the inner spread on a noise-free frame."""
    return _frozen((ring_distance(shape) == 2) & (noise_classes(shape) == 2))


@functools.lru_cache(maxsize=8)
def _groups(shape: tuple[int, int], packing: str = "square", centred: bool = False) -> tuple[np.ndarray, ...]:
    """Lens groups that share a systematic pattern: the inner lenses, and each edge class per side; on
    hex, and wherever the baselines are `centred`, also the second ring per side where it has the lenses
    to fit it (`SECOND_RING_MIN`); on hex the row ends that stick out apart from those that sit in
    (`hex_row_ends`: their windows hold other neighbours, and their indexes answer otherwise to the
    sub-pixel phase)."""
    inner = edge_classes(shape) == 2
    second = []
    if packing == "hex" or centred:
        side = _sides(shape)
        ring = ring_distance(shape)
        second = [g for g in ((ring == 2) & (side == s) for s in range(4)) if g.sum() >= SECOND_RING_MIN]
        for g in second:
            inner = inner & ~g
    return tuple(_frozen(g) for g in [inner] + second) + edge_groups(shape, packing)


def _sides(shape: tuple[int, int]) -> np.ndarray:
    """Per lens the array side it is nearest to: 0 top, 1 bottom, 2 left, 3 right."""
    rows, cols = shape
    m, n = np.ogrid[:rows, :cols]
    return np.argmin(np.stack(np.broadcast_arrays(m, rows - 1 - m, n, cols - 1 - n)), axis=0)


@functools.lru_cache(maxsize=8)
def edge_groups(shape: tuple[int, int], packing: str = "square") -> tuple[np.ndarray, ...]:
    """The outer two rings' lenses by ring and side (a corner lens goes with the side it is nearest to,
    the top or bottom on a tie); on hex the outer ring's row ends that stick out apart from those that
    sit in (`hex_row_ends`; a top or bottom row's end lens among them is a group of its own): lenses whose
    windows reach past the array alike."""
    cls, side = edge_classes(shape), _sides(shape)
    edges = [(cls == c) & (side == s) for c in (0, 1) for s in range(4)]
    if packing == "hex":
        ends = hex_row_ends(shape)
        edges = [part for g in edges for part in ((g & ends, g & ~ends) if (g & ends).any() else (g,))]
    return tuple(_frozen(g) for g in edges)


SIDE_NAMES = ("top", "bottom", "left", "right")  # `_sides`' numbers


class EdgeLine(NamedTuple):
    """One of `edge_groups`' groups and the line of lenses its side's offset applies to."""

    name: str  # "ring 0 left", "ring 0 left, row ends that stick out"; '' for a group the array is too small for
    ring: int
    axis: int  # the axis its side is normal to: 0 x (the left and right sides), 1 y
    group: np.ndarray  # (rows, cols) bool: the group's lenses (`edge_groups`)
    line: np.ndarray  # every lens at its ring from its side, corners included (hex: the row ends of its kind)


@functools.lru_cache(maxsize=8)
def edge_lines(shape: tuple[int, int], packing: str = "square") -> tuple[EdgeLine, ...]:
    """`edge_groups`' groups, in their order, each with its name, ring, axis and line: every lens at its
    ring from its side, the corner lenses `edge_groups` gives to the other side included (on hex, only the
    row ends of the group's kind; a top or bottom row's end that sticks out is a group of its own)."""
    rows, cols = shape
    m, n = np.ogrid[:rows, :cols]
    distance = np.broadcast_arrays(m, rows - 1 - m, n, cols - 1 - n)  # to the top, bottom, left, right side
    ends = hex_row_ends(shape) if packing == "hex" else np.zeros(shape, bool)
    ring, side = ring_distance(shape), _sides(shape)
    out = []
    for g in edge_groups(shape, packing):
        if not g.any():
            out.append(EdgeLine("", -1, 0, g, g))
            continue
        first = tuple(np.argwhere(g)[0])
        s, r = int(side[first]), int(ring[first])
        of_ends = packing == "hex" and bool(np.all(ends[g]))
        line = distance[s] == r
        if packing == "hex" and (s >= 2 or of_ends):
            line = line & (ends == of_ends)
        name = f"ring {r} {SIDE_NAMES[s]}" + (", row ends that stick out" if of_ends else "")
        out.append(EdgeLine(name, r, 0 if s >= 2 else 1, g, _frozen(line)))
    return tuple(out)


@functools.lru_cache(maxsize=8)
def hex_row_ends(shape: tuple[int, int]) -> np.ndarray:
    """On a hex lattice, the row ends that stick out half a pitch past the rows above and below (the
    unshifted rows' first lenses, the shifted rows' last): they miss 3 of their 6 neighbours, the other
    ends 1, and their sub-images differ the more (measured: flux 0.905 against 0.985)."""
    rows, cols = shape
    r = np.arange(rows)
    ends = np.zeros(shape, bool)
    ends[r % 2 == 0, 0] = True
    ends[r % 2 == 1, cols - 1] = True
    return _frozen(ends)


@functools.lru_cache(maxsize=8)
def hex_column_ends(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """On a hex lattice, the outer ring's row ends on the left and right sides pooled over both sides:
    (those that stick out, those that sit in; `hex_row_ends`). A side holds only half its rows of each
    kind (6 on a 12 x 14 array, under spreads.EDGE_GROUP_MIN): together they give a spread where a side alone
    gives none (a side's own, where it has one, may still be wider: `spreads.HEX_EDGE_GROUP_MIN`)."""
    ends, columns = hex_row_ends(shape), (edge_classes(shape) == 0) & (_sides(shape) >= 2)
    return _frozen(columns & ends), _frozen(columns & ~ends)


# Hex: the second ring's baselines leave the outermost lenses out (`_refine_baselines`), so their windows
# span 4 rows or columns, not 5, and take up another share of the sub-pixel phase pattern (which drifts
# 0.15 px per row on an array rotated 0.5°): measured on the analytic model, the second rows' x offset and
# tilt deviations kept 2.7 times the inner lenses' spread after the inner lenses' pattern was removed
# (false flags at z 6.3). Square windows kept centred (circular apertures) span 3 rows there: its
# intensity tilt along the edge kept 3.5 times the inner spread on an Airy-rimmed frame rotated 1.3°
# (14 false flags on that ring of 102 x 102). Each side's second ring is fitted on its own where it has
# this many lenses (the phase basis needs 40 for one harmonic), else with the inner lenses as before.
SECOND_RING_MIN = 40


def _frozen(a: np.ndarray) -> np.ndarray:
    """`a`, read-only: the class maps are cached per array shape and shared by every frame."""
    a.flags.writeable = False
    return a
