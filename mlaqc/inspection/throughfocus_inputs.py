"""The through-focus frames checked: the series against the grid and config, grouped into +u / -u pairs, and each frame's exposure."""

from __future__ import annotations

import math

import numpy as np

from mlaqc.errors import InputError
from mlaqc.inspection.calibrate import Grid
from mlaqc.inspection.raw_levels import check_exposure
from mlaqc.inspection.rawio import RawFrame
from mlaqc.inspection.throughfocus_spots import SpotFrame, Spots
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.throughfocus import ThroughFocus
from mlaqc.parallel import thread_map

def _check_inputs(frames, grid: Grid, cfg: CameraConfig):
    """Validate, and group the frames into +u / -u pairs by (|u|, offset): [(u, offset, plus, minus)]."""
    if not isinstance(grid, Grid):
        raise InputError("the through-focus analysis needs the white frame's calibrated Grid")
    if (grid.rows, grid.cols) != (cfg.mla.count_h, cfg.mla.count_w):
        raise InputError(f"the grid has {grid.rows} x {grid.cols} lenses but the camera's MLA has "
                         f"{cfg.mla.count_h} x {cfg.mla.count_w}")
    grid_packing = getattr(grid, "packing", "square")
    if grid_packing != cfg.mla.packing:
        raise InputError(f"the white frame's grid is a {grid_packing} lattice but the camera config's MLA is "
                         f"{cfg.mla.packing} (mla.packing): read the frames with the config of the array they show")
    frames = list(frames)
    if len(frames) < 2:
        raise InputError("a through-focus reading needs at least one +u / -u pair of frames")
    shape = tuple(grid.image_shape)

    def extremes(item) -> tuple[float, float] | None:  # (max, min): NaN propagates through both, +-inf shows
        img = SpotFrame.of(item[1][0]).data if isinstance(item[1], tuple) and len(item[1]) == 2 else None
        if img is None or img.shape != shape or img.dtype.kind not in "fiu":
            return None
        return float(img.max()), float(img.min())

    # a prepared integer frame is normalized by construction and holds no NaN: only other frames are
    # checked whole (their one full pass, a thread per core)
    whole = [k for k, item in enumerate(frames)
             if not (isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], SpotFrame)
                     and item[0].counts)]
    span = dict(zip(whole, thread_map(extremes, [(k, frames[k]) for k in whole])))
    checked = []
    for k, item in enumerate(frames):
        try:
            img, rec = item
        except (TypeError, ValueError):
            raise InputError(f"through-focus frame {k + 1} must be an (image, ThroughFocus) pair") from None
        if not isinstance(rec, ThroughFocus):
            raise InputError(f"through-focus frame {k + 1} has no ThroughFocus record")
        img = SpotFrame.of(img)
        if img.data.ndim != 2 or img.data.dtype.kind not in "fiu":
            raise InputError(f"through-focus frame {k + 1} must be a 2-D numeric image")
        if img.shape != shape:
            raise InputError(f"through-focus frame {k + 1} is {img.shape[1]}x{img.shape[0]} px but the white "
                             f"frame's grid is {shape[1]}x{shape[0]} px")
        if k in span:
            top, bottom = span[k] if span[k] is not None else (float(img.data.max()), float(img.data.min()))
            if not (math.isfinite(top) and math.isfinite(bottom)):
                raise InputError(f"through-focus frame {k + 1} holds NaN or infinite pixels")
            top = (top - img.black) / img.span
            if top > 2.0:
                raise InputError(f"through-focus frame {k + 1} reaches {top:g}, not a normalized frame "
                                 "(white level 1): prepare it with prepare_spots")
        checked.append((img, rec))
    first = checked[0][1]
    for k, (_, rec) in enumerate(checked):
        if rec.f_number != first.f_number or rec.spacing_lenses != first.spacing_lenses:
            raise InputError(f"through-focus frame {k + 1} was taken at f/{rec.f_number:g} with pinholes "
                             f"{rec.spacing_lenses} lenses apart, frame 1 at f/{first.f_number:g} and "
                             f"{first.spacing_lenses}: all frames of a series must share both")
    groups: dict[tuple[float, tuple[int, int]], dict[int, tuple]] = {}
    for k, (img, rec) in enumerate(checked):
        key = (abs(rec.focus_offset_mm), tuple(int(v) for v in rec.offset_lenses))
        sign = 1 if rec.focus_offset_mm > 0 else -1
        slot = groups.setdefault(key, {})
        if sign in slot:
            raise InputError(f"through-focus frames {slot[sign][2] + 1} and {k + 1} are both u = "
                             f"{rec.focus_offset_mm:+g} mm at offset {key[1]}: give each frame once")
        slot[sign] = (img, rec, k)
    pairs = []
    for (u, off), slot in sorted(groups.items()):
        if len(slot) != 2:
            have = next(iter(slot.values()))
            raise InputError(f"through-focus frame {have[2] + 1} (u = {have[1].focus_offset_mm:+g} mm, offset "
                             f"{off}) has no partner of the other sign at the same offset")
        pairs.append((u, off, slot[1], slot[-1]))
    return pairs


EXPOSURE_WINDOWS = 64  # the exposure check looks at about this many of a frame's lit windows, spread over it


def _check_exposure(frame: SpotFrame, sp: Spots, name: str) -> None:
    """The raw_levels black/saturation checks, on the sub-image windows that should be lit (a pinhole frame
    lights a few per cent of the sensor: the whole frame's percentiles would call it black); every k-th
    window, about EXPOSURE_WINDOWS of them (the statistics of a frame-wide check need no more; each
    spot's own saturation is checked on all of them). A frame of integer counts is checked on its counts
    against its own black and white levels (raw_levels' histogram statistics), as a white frame is."""
    pick = slice(None, None, max(1, len(sp.cells) // EXPOSURE_WINDOWS))
    n = sp.cells.shape[-1]
    if frame.counts:
        half = n // 2
        cells = np.lib.stride_tricks.sliding_window_view(frame.data, (n, n))[sp.iy[pick] - half, sp.ix[pick] - half]
        black, white = int(round(frame.black)), int(round(frame.black + frame.span))
        bits = min(16, max(8, white.bit_length()))
        check_exposure(RawFrame(np.ascontiguousarray(cells.reshape(-1, n)), bits, None, black, white, source=name))
        return
    flat = np.ascontiguousarray((sp.cells + sp.background[:, None, None])[pick].reshape(-1, n), dtype=np.float32)
    check_exposure(RawFrame(flat, 16, None, 0, 1, source=name, levels_from="normalized"))
