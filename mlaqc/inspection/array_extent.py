"""A frame inspected with count_w = count_h = "auto" that holds the whole array: its lenses counted from
the frame, so that the array is inspected as a whole (its corner U(1,1), its edge lenses judged as edges).

Why: "auto" lays a lattice over the whole sensor with a lens to spare on every side. When the array is
smaller than the frame, the lattice places beyond its edges are dark, and its edge lenses, which lack a
neighbour's light on one side, were judged against inner lenses' spread: a healthy 41 Mpx hand-held frame
failed with 130 edge lenses "unknown". Counted from the frame, the array's edges are the edge groups they are
with the counts given (0 flags on that frame).
"""

from __future__ import annotations

import numpy as np

WHOLE_FILL = 0.95  # the lit places fill the array's box to this share at least (a few missing lenses), else
# they are not one rectangular array (a round field stop darkens a fifth of its box)
MIN_LENSES = 3  # rows and columns at least (the smallest array the identification judges)


def whole_array_counts(grid) -> tuple[int, int] | None:
    """(rows, lenses per row) of the array an "auto" frame holds whole, from its grid (mlaqc.inspection.
    calibrate.Grid): the lit lenses' centres a pitch or more inside the frame on every side (the lattice
    place beyond each edge is in view, and dark) and filling their box; None when the array runs off the
    frame (the lenses the frame cuts are lit) or is not one whole rectangular array (a field stop)."""
    lit = ~np.asarray(grid.missing, bool)
    rows, cols = np.flatnonzero(lit.any(axis=1)), np.flatnonzero(lit.any(axis=0))
    if rows.size < MIN_LENSES or cols.size < MIN_LENSES:
        return None
    x, y = np.asarray(grid.grid_x_px)[lit], np.asarray(grid.grid_y_px)[lit]
    step_x = float(grid.pitch_px[0])
    step_y = float(grid.pitch_px[1]) * (np.sqrt(3.0) / 2.0 if grid.packing == "hex" else 1.0)
    h, w = grid.image_shape
    if x.min() < step_x or y.min() < step_y or x.max() > w - 1 - step_x or y.max() > h - 1 - step_y:
        return None
    count_h = int(rows[-1] - rows[0] + 1)
    count_w = int(lit[rows[0]:rows[-1] + 1].sum(axis=1).max())  # (hex: the rows' ends alternate between two columns)
    if count_w < MIN_LENSES or lit.sum() < WHOLE_FILL * count_h * count_w:
        return None
    return count_h, count_w


def whole_array_note(count_h: int, count_w: int) -> str:
    """What the report says of an "auto" frame that holds the whole array."""
    return (f"The frame holds the whole array (mla.count_w / count_h = \"auto\"): {count_w} x {count_h} lenses "
            "found, with dark margins on every side. U(1,1) is the array's top-left lens and its edge lenses are "
            "judged as edges, as with those counts given; to read the array's assembly, give "
            f"count_w = {count_w} and count_h = {count_h} in the config and run `mlaqc models` once.")


def with_counts(cfg, count_h: int, count_w: int):
    """`cfg` with the array's counts fixed: the config an "auto" frame holding the whole array is inspected
    with (and its through-focus frames read with)."""
    from dataclasses import replace

    return replace(cfg, mla=replace(cfg.mla, count_h=count_h, count_w=count_w, counts_auto=False))


def calibrate_whole(img: np.ndarray, cfg):
    """The grid of a white frame (mlaqc.inspection.calibrate.calibrate_for); with "auto" counts on a frame
    that holds the whole array, the grid of that array (its counts from the frame)."""
    from mlaqc.inspection.calibrate import calibrate_for

    grid = calibrate_for(img, cfg)
    counts = whole_array_counts(grid) if cfg.mla.counts_auto else None
    return grid if counts is None else calibrate_for(img, with_counts(cfg, *counts))
