"""Local obscuration: dust, residue or a dig on a lens darkens part of its sub-image, the rest unchanged.
No error of the lens' shape does that: a shift or decenter moves the rim, a radius or thickness error
changes the whole disc symmetrically, a transmission loss scales it all. So a flagged lens is read here,
after it was typed, against the typical sub-image of this very frame (healthy lenses averaged about their
measured centres on a grid OVERSAMPLE times finer, then sampled at the flagged lens' own centre): their
ratio over the disc's interior (the rim left out, where a shift or a defocus shows) is smoothed over
3 x 3 pixels and scaled by its unobscured level (its 80th percentile: a dim lens is then flat). A dark region holding 3 to 70 % of an
interior of at least MIN_INTERIOR_PX pixels (a sub-image about 7 px in radius or more), at least SPOT_DEPTH
deep, not a ring round the centre, with no brightened region beside it (over the whole disc: light moved
to the rim is a shift's or a decenter's) and the rest of the disc keeping its light, is an obscuration:
its area fraction, its depth (the loss of its darkest tenth) and its position (the angle of its centroid
from the sub-image's centre) replace the reading of the lens' shape, which stays as the alternative.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from mlaqc.inspection.lens_classes import edge_classes
from mlaqc.inspection.results import Defect
from mlaqc.inspection.scratches import is_line, line_shape

INTERIOR = 0.9  # pixels where the typical sub-image exceeds this share of its peak: the disc inside its rim
MIN_AREA, MAX_AREA = 0.03, 0.7  # a region smaller is noise or a rim effect; larger is the lens' whole light
NOISE_SIGMAS = 5.0  # the darkening threshold, in the smoothed ratio's noise over healthy lenses
MIN_DEPTH = 0.03  # and never below this loss
SPOT_DEPTH = 0.06  # a spot's loss (its 90th percentile) must reach this: a rim blurred x2 darkens by 4 %
BRIGHT_SHARE = 0.3  # a brightened region this large against the dark one: light moved (a shift, a skew), not lost
RING_REACH = 0.6  # dark pixels all round the centre this far out are a rim's, not a spot's
MIN_INTERIOR_PX = 100  # fewer interior pixels cannot tell a spot's shape from a skew or a smaller disc
LEVEL_PERCENTILE = 80  # the interior's unobscured light: a spot may cover up to 70 % of it
OVERSAMPLE = 4
TEMPLATE_LENSES = 400  # healthy lenses averaged into the frame's typical sub-image
UNIT = "area"


@dataclasses.dataclass(frozen=True)
class SpotReading:
    """One lens' dark region: its share of the disc, its loss, where it sits (the angle of its centroid
    and the centroid's offset from the sub-image's centre, px, y down), its shape (`scratches.line_shape`)
    and the radius of the interior it was read in (px)."""

    area: float
    depth: float
    direction_deg: float
    dx_px: float
    dy_px: float
    elongation: float
    axis_deg: float
    length_px: float
    width_px: float
    interior_px: float


def obscuration_readings(sub, cx, cy, flagged, candidates) -> dict[tuple[int, int], SpotReading]:
    """{(row, col): SpotReading} of the `candidates` lenses (bool map) two or more lenses in from the array's
    edge whose sub-image is locally obscured (see the module note); `sub` (rows, cols, h, w) windows and
    (cx, cy) the lenses' measured centres in window pixels, `flagged` the lenses left out of the template
    and the noise."""
    if not candidates.any():
        return {}
    inner = edge_classes(flagged.shape) == 2  # lenses with a full neighbourhood: the border's differ
    healthy = inner & ~flagged & np.isfinite(cx) & np.isfinite(cy) & np.isfinite(sub).all(axis=(-2, -1))
    keys = np.argwhere(healthy)
    if len(keys) < 9:
        return {}
    template = _typical(sub, cx, cy, keys[:: max(1, len(keys) // TEMPLATE_LENSES)])
    noise = _ratios(sub, cx, cy, template, keys[:: max(1, len(keys) // 100)])[0]
    seen = np.isfinite(noise).any(axis=(1, 2))  # a lens whose window holds no ratio (its centre off) has no spread
    spread = float(np.median(np.nanstd(noise[seen], axis=(1, 2)))) if seen.any() else float("nan")
    if not np.isfinite(spread):
        return {}
    threshold = max(MIN_DEPTH, NOISE_SIGMAS * spread)
    keys = np.argwhere(candidates & inner)  # a border lens' sub-image is not the inner lenses' typical one
    if not len(keys):
        return {}
    ratio, dy, dx, whole = _ratios(sub, cx, cy, template, keys)
    inside = np.isfinite(ratio)
    dark = inside & (ratio < -threshold)
    n_dark = dark.sum(axis=(1, 2))
    share = n_dark / np.maximum(inside.sum(axis=(1, 2)), 1)  # of the interior: what decides
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a lens with no dark pixel: an all-NaN slice
        rest = np.nanmedian(np.where(inside & ~dark, ratio, np.nan).reshape(len(keys), -1), axis=1)
        depth = -np.nanpercentile(np.where(dark, ratio, np.nan).reshape(len(keys), -1), 10, axis=1)
        sx, sy = np.where(dark, dx, 0.0).sum(axis=(1, 2)) / n_dark, np.where(dark, dy, 0.0).sum(axis=(1, 2)) / n_dark
        area = _spot_area(whole, dy, dx, depth, sx, sy, n_dark)
        n_disc = np.maximum(np.isfinite(whole).sum(axis=(1, 2)), 1)
        lit = (whole > np.maximum(threshold, depth)[:, None, None]).sum(axis=(1, 2)) / n_disc
    bright = (inside & (ratio > threshold)).sum(axis=(1, 2)) / np.maximum(inside.sum(axis=(1, 2)), 1)
    resolved = inside.sum(axis=(1, 2)) >= MIN_INTERIOR_PX
    spot = (resolved & (share >= MIN_AREA) & (share <= MAX_AREA) & (area >= MIN_AREA) & (depth >= SPOT_DEPTH)
            & (np.abs(rest) < 0.5 * threshold) & (bright < BRIGHT_SHARE * share) & (lit < BRIGHT_SHARE * area)
            & ~_ring(dark, inside, dy, dx))
    direction = np.degrees(np.arctan2(-sy, sx)) % 360.0
    shape = line_shape(dark, dx, dy, sx, sy)
    interior = np.sqrt(inside.sum(axis=(1, 2)) / np.pi)
    return {(int(m), int(n)): SpotReading(float(area[i]), float(depth[i]), float(direction[i]), float(sx[i]),
                                          float(sy[i]), *(float(v[i]) for v in shape), float(interior[i]))
            for i, (m, n) in enumerate(keys) if spot[i]}


def _spot_area(whole, dy, dx, depth, sx, sy, n_dark) -> np.ndarray:
    """The spot's share of the whole disc (to its rim's half height): the disc's pixels darker than half the
    spot's depth within twice the radius of the interior's dark region from its centroid (a spot near the
    rim reaches past the interior; the rim's own noise elsewhere is not counted)."""
    reach = 2.0 * np.sqrt(n_dark / np.pi) + 1.0
    near = np.hypot(dy - sy[:, None, None], dx - sx[:, None, None]) <= reach[:, None, None]
    dark = near & (whole < -0.5 * depth[:, None, None])
    return dark.sum(axis=(1, 2)) / np.maximum(np.isfinite(whole).sum(axis=(1, 2)), 1)


def _ring(dark, inside, dy, dx) -> np.ndarray:
    """Per lens whether its dark pixels surround the centre near the rim (a smaller or defocused disc, not a
    spot): in at least 7 of 8 sectors, at a mean distance beyond RING_REACH of the interior's radius."""
    r = np.hypot(dy, dx)
    reach = np.where(inside, r, 0.0).max(axis=(1, 2))
    sector = (np.floor(np.arctan2(dy, dx) / (np.pi / 4)).astype(np.int64) % 8)[..., None] == np.arange(8)
    sectors = (dark[..., None] & sector).any(axis=(1, 2)).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_r = np.where(dark, r, 0.0).sum(axis=(1, 2)) / dark.sum(axis=(1, 2))
    return (sectors >= 7) & (mean_r > RING_REACH * reach)


def _typical(sub, cx, cy, keys):
    """The mean sub-image of lenses `keys` about their centres, each scaled to unit mean, on a grid
    OVERSAMPLE times finer whose centre (index OVERSAMPLE * half) is the lens' centre."""
    h, w = sub.shape[-2:]
    half = max(h, w) // 2 + 1
    size = 2 * half * OVERSAMPLE + 1
    m, n = keys[:, 0], keys[:, 1]
    win = np.asarray(sub[m, n], dtype=np.float64)
    win = win / np.maximum(win.mean(axis=(1, 2), keepdims=True), 1e-12)
    yy, xx = np.mgrid[0:h, 0:w]
    gy = np.rint((yy[None] - cy[m, n][:, None, None]) * OVERSAMPLE).astype(np.int64) + half * OVERSAMPLE
    gx = np.rint((xx[None] - cx[m, n][:, None, None]) * OVERSAMPLE).astype(np.int64) + half * OVERSAMPLE
    ok = (gy >= 0) & (gy < size) & (gx >= 0) & (gx < size)
    idx = gy[ok] * size + gx[ok]
    acc = np.bincount(idx, weights=win[ok], minlength=size * size)
    cnt = np.bincount(idx, minlength=size * size)
    return np.where(cnt > 0, acc / np.maximum(cnt, 1), 0.0).reshape(size, size)


def _ratios(sub, cx, cy, template, keys):
    """Per lens of `keys` (K, 2): its sub-image over the typical one sampled at its centre, smoothed over
    3 x 3 pixels, scaled to its unobscured level (LEVEL_PERCENTILE) of 1, minus 1, NaN outside the disc's
    interior; the pixels' offsets (dy, dx) from the lens' centre; and the same ratio over the whole disc
    (to its rim's half height), (K, h, w) each."""
    h, w = sub.shape[-2:]
    m, n = keys[:, 0], keys[:, 1]
    win = np.asarray(sub[m, n], dtype=np.float64)
    yy, xx = np.mgrid[0:h, 0:w]
    dy, dx = yy[None] - cy[m, n][:, None, None], xx[None] - cx[m, n][:, None, None]
    centre = (template.shape[0] - 1) / 2
    ref = _bilinear(template, dy * OVERSAMPLE + centre, dx * OVERSAMPLE + centre)
    peak = ref.max(axis=(1, 2), keepdims=True)
    # the sub-image to its rim's half height, and no farther out than half the window (about half a pitch):
    # the template holds the neighbours' discs too, and a neighbour's spot is not this lens'
    own = np.hypot(dy, dx) <= 0.5 * (min(h, w) - 1)
    disc = (ref > 0.5 * peak) & np.isfinite(win) & own
    inside = disc & (ref > INTERIOR * peak)
    raw = np.where(disc, win / np.where(disc, ref, 1.0), 0.0)
    ratio, whole = (_smoothed(raw, zone) for zone in (inside, disc))  # each smoothed within its own zone
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        # the unobscured level: a high quantile, so that a spot over most of the interior is still the dark part
        level = np.nanpercentile(ratio.reshape(len(keys), -1), LEVEL_PERCENTILE, axis=1)[:, None, None]
    with np.errstate(invalid="ignore", divide="ignore"):  # a lens without light: no level, NaN ratios
        return ratio / level - 1.0, dy, dx, whole / level - 1.0


def _smoothed(raw, zone):
    """The 3 x 3 mean of `raw` over the pixels of `zone` (per lens), NaN outside it."""
    num, den = _box3(np.where(zone, raw, 0.0)), _box3(zone.astype(np.float64))
    return np.where(zone, num / np.maximum(den, 1e-9), np.nan)


def _box3(a):
    """3 x 3 sums over the last two axes, zero beyond the edges (plain NumPy: an inspection loads no
    scipy.ndimage, tests/test_compiled.py)."""
    p = np.pad(a, ((0, 0), (1, 1), (1, 1)))
    h, w = a.shape[-2:]
    return sum(p[:, i:i + h, j:j + w] for i in range(3) for j in range(3))


def _bilinear(image, y, x):
    """`image` interpolated bilinearly at (y, x) (index units), 0 beyond it."""
    y0, x0 = np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)
    fy, fx = y - y0, x - x0
    h, w = image.shape
    out = np.zeros(np.shape(y))
    for dy, wy in ((0, 1.0 - fy), (1, fy)):
        for dx, wx in ((0, 1.0 - fx), (1, fx)):
            yy, xx = y0 + dy, x0 + dx
            ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
            out += np.where(ok, image[np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)], 0.0) * wy * wx
    return out


def retype(found, readings, qc, metrics, centres, candidates=None):
    """`found` (an Identification) with the obscured lenses typed 'obscuration' (magnitude: the area fraction;
    direction: where the spot sits) or, where the dark region is a line, 'scratch' (magnitude: the area
    fraction; direction: the line's axis, 0-180°), judged against `qc.obscuration_area` / `qc.scratch_area`;
    depth and the spot's centroid on the sensor (`centres`: every lens' centre in frame pixels, x and y)
    in the indexes. A flagged lens' shape reading stays as the alternative, and a lens whose deviation was
    significant but read as an error below the reportable size (`found.unreported`), or taken for a
    neighbour's echo (`candidates`: those over the detection threshold), is flagged now: a line through
    three lenses darkens each, and the middle one was taken for its neighbours' echo."""
    if not readings:
        return found
    defects, error_type, flagged = [], found.error_type.copy(), found.flagged.copy()
    unreported = found.unreported.copy() if found.unreported is not None else np.zeros(flagged.shape, bool)
    typed = {(d.m - 1, d.n - 1): d for d in found.defects}
    extra = unreported | (candidates if candidates is not None else False)
    for (m, n), r in readings.items():
        d = typed.get((m, n))
        if d is None and not extra[m, n] or d is not None and d.error_type == "missing":
            continue
        spot = _typed_spot(r, qc)
        if d is None:
            d = Defect(m + 1, n + 1, score=float(found.score[m, n]), indexes=metrics.at(m + 1, n + 1), **spot)
            unreported[m, n], flagged[m, n] = False, True
        else:
            was = (d.error_type, d.magnitude, d.unit, d.direction_deg)
            d = dataclasses.replace(d, alternatives=(was,) if was[0] != "unknown" else (), **spot)
        where = {"spot_area": r.area, "spot_depth": r.depth, "spot_x_px": float(centres[0][m, n]) + r.dx_px,
                 "spot_y_px": float(centres[1][m, n]) + r.dy_px}
        if spot["error_type"] == "scratch":
            where |= {"scratch_length_px": r.length_px, "scratch_width_px": r.width_px}
        typed[(m, n)] = dataclasses.replace(d, indexes={**d.indexes, **where})
        error_type[m, n] = spot["error_type"]
    defects = tuple(typed[k] for k in sorted(typed))
    return dataclasses.replace(found, defects=defects, error_type=error_type, flagged=flagged,
                               unreported=unreported, below_reportable=int(unreported.sum()))


def _typed_spot(r: SpotReading, qc) -> dict:
    """The Defect fields of a dark region: a line is a scratch (direction: its axis), else an obscuration."""
    if is_line(r):
        return {"error_type": "scratch", "magnitude": r.area, "unit": UNIT, "direction_deg": r.axis_deg,
                "within_tolerance": r.area <= qc.scratch_area}
    return {"error_type": "obscuration", "magnitude": r.area, "unit": UNIT, "direction_deg": r.direction_deg,
            "within_tolerance": r.area <= qc.obscuration_area}
