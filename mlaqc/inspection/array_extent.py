"""A frame inspected with count_w = count_h = "auto" that holds the whole array: its lenses counted from
the frame, so that the array is inspected as a whole (its corner U(1,1), its edge lenses judged as edges);
one that shows some of the array's edges: the lattice cut there (`locate_array`).

Why: "auto" lays a lattice over the whole sensor with a lens to spare on every side. When the array is
smaller than the frame, the lattice places beyond its edges are dark, and its edge lenses, which lack a
neighbour's light on one side, were judged against inner lenses' spread: a healthy 41 Mpx hand-held frame
failed with 130 edge lenses "unknown". Counted from the frame, the array's edges are the edge groups they are
with the counts given (0 flags on that frame).
"""

from __future__ import annotations

import numpy as np

from mlaqc.errors import InputError

WHOLE_FILL = 0.95  # the lit places fill the array's box to this share at least (a few missing lenses), else
# they are not one rectangular array (a round field stop darkens a fifth of its box)
MIN_LENSES = 3  # rows and columns at least (the smallest array the identification judges)


SIDES = ("top", "bottom", "left", "right")


def seen_edges(grid) -> tuple[tuple[int, int], tuple[str, ...]] | None:
    """The lit lenses' box on an "auto" frame's grid, (rows, lenses per row), and the array's edges the frame
    shows: the sides where the lit lenses stop a pitch or more inside the frame (the lattice place beyond is
    in view, and dark); None when fewer than 3 x 3 lenses are lit."""
    lit = ~np.asarray(grid.missing, bool)
    rows, cols = np.flatnonzero(lit.any(axis=1)), np.flatnonzero(lit.any(axis=0))
    if rows.size < MIN_LENSES or cols.size < MIN_LENSES:
        return None
    x, y = np.asarray(grid.grid_x_px)[lit], np.asarray(grid.grid_y_px)[lit]
    step_x = float(grid.pitch_px[0])
    step_y = float(grid.pitch_px[1]) * (np.sqrt(3.0) / 2.0 if grid.packing == "hex" else 1.0)
    h, w = grid.image_shape
    inside = (y.min() >= step_y, y.max() <= h - 1 - step_y, x.min() >= step_x, x.max() <= w - 1 - step_x)
    count_h = int(rows[-1] - rows[0] + 1)
    count_w = int(lit[rows[0]:rows[-1] + 1].sum(axis=1).max())  # (hex: the rows' ends alternate between two columns)
    return (count_h, count_w), tuple(side for side, seen in zip(SIDES, inside) if seen)


def _filled_box(grid) -> tuple[tuple[int, int], tuple[str, ...]] | None:
    """`seen_edges`, when the lit lenses fill their box to WHOLE_FILL (one rectangular array, a few lenses
    missing at most; a round field stop does not); None otherwise."""
    found = seen_edges(grid)
    if found is None:
        return None
    (count_h, count_w), _ = found
    if count_w < MIN_LENSES or np.count_nonzero(~np.asarray(grid.missing, bool)) < WHOLE_FILL * count_h * count_w:
        return None
    return found


def whole_array_counts(grid) -> tuple[int, int] | None:
    """(rows, lenses per row) of the array an "auto" frame holds whole, from its grid (mlaqc.inspection.
    calibrate.Grid): its edges seen on every side (`seen_edges`) and its lit lenses filling their box; None
    when the array runs off the frame (the lenses the frame cuts are lit) or is not one whole rectangular
    array (a field stop)."""
    found = _filled_box(grid)
    return found[0] if found is not None and len(found[1]) == len(SIDES) else None


def whole_array_note(count_h: int, count_w: int, from_grid: bool = False) -> str:
    """What the report says of an "auto" frame that holds the whole array (`from_grid`: counted on the
    white frame whose grid it was given)."""
    how = ("the grid given holds the whole array" if from_grid else "the frame holds the whole array")
    return (f"Lenses counted: {how} (mla.count_w / count_h = \"auto\"), {count_w} x {count_h} lenses with dark "
            "margins on every side. U(1,1) is the array's top-left lens and its edge lenses are judged as edges, "
            "as with those counts given (a whole edge row or column missing would be counted out: give the "
            "counts for acceptance); to read the array's assembly, give count_w = "
            f"{count_w} and count_h = {count_h} in the config and run `mlaqc models` once.")


def with_counts(cfg, count_h: int, count_w: int, auto: bool = False):
    """`cfg` with the array's counts fixed: the config an "auto" frame holding the whole array is inspected
    with (and its through-focus frames read with); with `auto`, the counts of a lattice cut to the part of
    the array a frame shows, still "auto"."""
    from dataclasses import replace

    return replace(cfg, mla=replace(cfg.mla, count_h=count_h, count_w=count_w, counts_auto=auto))


def config_for_grid(cfg, grid):
    """`cfg`, or with "auto" counts and a grid that `calibrate_whole` fitted to the array it found, `cfg`
    with that grid's counts: fixed for a whole array, still "auto" for a part of one."""
    if not cfg.mla.counts_auto or grid.shape == (cfg.mla.count_h, cfg.mla.count_w):
        return cfg
    return with_counts(cfg, *grid.shape, auto=whole_array_counts(grid) != grid.shape)


def partial_array_note(seen: tuple[str, ...]) -> str:
    """What the report says of an "auto" frame that shows some of the array's edges."""
    corner = "top" in seen and "left" in seen
    anchor = ("U(1,1) is the array's top-left lens" if corner else
              "U(1,1) is the top-left lens the frame shows, not the array's corner")
    return (f"The frame shows the array's {', '.join(seen)} edge{'s' if len(seen) > 1 else ''} (mla.count_w / count_h "
            f"= \"auto\"): the lattice is cut there, the lenses along {'them' if len(seen) > 1 else 'it'} judged as "
            f"edge lenses and the dark places beyond not counted as lenses; {anchor}; the lenses the frame cuts are "
            "not inspected.")


def boxed_counts(grid) -> tuple[int, int] | None:
    """The counts (rows, lenses per row) to cut an "auto" grid down to, when it shows some of the array's
    edges but not all: the lit lenses' box, which they fill (`_filled_box`: a round field stop's frame is
    refused as before). None otherwise, and for a hex array running off the frame's top (its top row in
    view may be a shifted one, which a box of that width cannot hold)."""
    found = _filled_box(grid)
    if found is None or not 0 < len(found[1]) < len(SIDES) or (grid.packing == "hex" and "top" not in found[1]):
        return None
    return found[0]


def locate_array(img: np.ndarray, cfg):
    """An "auto" frame's grid, the config it was fitted with, and the counts (rows, lenses per row) of the
    array when the frame holds it whole (else None). When the frame shows some of the array's edges (dark
    lattice places beyond them, `boxed_counts`), the lattice is cut down to the lit lenses' box, so that those
    edges are the grid's (judged as edges, never a dark place flagged 'missing'); the config's counts are then
    the box's, still "auto". InputError when under half the lattice places are lit otherwise."""
    from mlaqc.inspection.calibrate import MIN_FOUND_SHARE, calibrate_for

    grid = calibrate_for(img, cfg)
    counts = whole_array_counts(grid)
    box = boxed_counts(grid) if counts is None else None
    if box is not None:
        boxed = with_counts(cfg, *box, auto=True)
        return calibrate_for(img, boxed), boxed, None
    if counts is None and grid.lenses_found < MIN_FOUND_SHARE * grid.rows * grid.cols:
        raise InputError(f"only {grid.lenses_found} of the {grid.cols}x{grid.rows} lens places that cover the "
                         "frame are lit (mla.count_w / count_h = \"auto\"), and they are not one whole array "
                         "with dark margins on every side: give the array's counts (mla.count_w, mla.count_h)")
    return grid, cfg, counts


def through_focus_config(cfg, grid):
    """The config to read through-focus frames on `grid` with (`config_for_grid`); InputError on a grid cut
    to part of the array, whose lenses' places on the MLA the frame does not tell."""
    out = config_for_grid(cfg, grid)
    if out is not cfg and out.mla.counts_auto:
        raise InputError("the through-focus frames need the array's place in the camera, which a frame showing "
                         "part of it does not give: set mla.count_w / count_h to the array's counts")
    return out


def calibrate_whole(img: np.ndarray, cfg):
    """The grid of a white frame (mlaqc.inspection.calibrate.calibrate_for); with "auto" counts on a frame
    that holds the whole array, the grid of that array (its counts from the frame)."""
    from mlaqc.inspection.calibrate import calibrate_for

    if not cfg.mla.counts_auto:
        return calibrate_for(img, cfg)
    grid, _, counts = locate_array(img, cfg)
    return grid if counts is None else calibrate_for(img, with_counts(cfg, *counts))
