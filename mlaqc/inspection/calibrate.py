"""Microlens calibration from a white image: find every microlens' sub-image, index it U(m,n), fit a
global grid and keep every lens' own measurement (centre, residual, flux, size) as the QC signal.

Pipeline (DESIGN.md §6), vectorized over all lenses at once (no per-lens Python loop):

1. Lattice from the Fourier transform of the (Hann-windowed, for big frames binned) white image: pitch,
   rotation and offset from its fundamental peaks, square or hex, a spectrum plainly of the other packing
   than the config's refused by name (mlaqc.inspection.fourier_lattice, which says how).
2. Every sub-image is measured by a joint least-squares fit of the frame by a sum of discs, one per lens
   (mlaqc.inspection.disc_fit, which says why and how). The model has no background term: where the cell
   corners, well clear of the fitted rims, hold over 15 % of the sub-images' light (clear gaps between
   circular lenses, a low black level), a smooth surface through them is taken off and every lens
   measured again (`_without_background`).
3. Indexing: lattice rows/columns; with an expected MLA shape the window of N_H x N_W lattice lines with
   the most light (then the fewest lines seen dark, then nearest the frame centre) is U(1,1)..U(N_H,N_W).
   Hex (mlaqc.optics.lattice's offset convention: rows 2, 4, ... shifted +p/2): the window's columns
   zig-zag along a2 and a2 - a1, and which lattice row is U(1,n) decides which rows are the shifted ones,
   so rows and columns are anchored together (`_anchor_hex`).
4. Global model: a projective map of the lattice (pitch x/y, rotation, shear, offset, keystone from an
   MLA tilt) plus a radial term about the frame centre, fitted robustly (defective lenses are outliers)
   by Gauss-Newton with the analytic Jacobian. Its lattice coordinates are the design's, in pitches from
   U(1,1) (`Lattice.uv`: square (n-1, m-1), hex (n-1 + [m even]/2, (m-1) sqrt(3)/2)), so pitch, rotation
   and shear mean the same for both packings (a perfect hex array has shear 0).
   Lenses predicted by the model but dark or dim are reported in `missing`, never an error.
5. Edge lenses: each outer line's common offset from the model (the outer ring by side: a lens there sees
   its neighbours' rims on one side only, which biases the disc fit alike along the side) is taken
   off its line's measured centres and kept in `Grid.edge_offsets` (`_edge_offsets_removed`); the model
   and the offsets are fitted in turn until the offsets settle.
   The grid, its model map and its file grid.json: mlaqc.inspection.grid.

Measured on the Table 1 camera (50 rays/pixel, noise on): per-lens centres 0.029 px RMS (0.021 px per
axis, Monte-Carlo-noise limited) and grid centres 0.003 px RMS from the ray-traced sub-image centres.

Conventions: pixel (0, 0) is the centre of the top-left pixel, x to the right, y down. Lens U(m,n) is row m
from the top, column n from the left (1-based), arrays index [m-1, n-1]. Rotation is counterclockwise as
the image is displayed (as `ErrorMap`'s mla_rotation_deg).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from mlaqc.errors import InputError
from mlaqc.inspection import calibrate_kernels as kernels
from mlaqc.inspection.disc_fit import MIN_LENSES, MIN_VALID_FRACTION, _colours, _Discs, _measure
from mlaqc.inspection.fourier_lattice import MIN_PITCH_PX, _CORNERS, _bilinear, _fft_lattice, _Lattice
from mlaqc.inspection.grid import FORMAT, VERSION, Grid, _model_xy, load_grid
from mlaqc.optics.lattice import PACKINGS, SQRT3_2, Lattice

log = logging.getLogger(__name__)

# Thresholds (relative units unless stated).
MISSING_RELATIVE_FLUX = 0.3  # a lens under 30 % of its neighbourhood's amplitude is 'missing/dim'
MIN_FOUND_SHARE = 0.5  # with the counts given, at least this share of the array must be found (else: wrong config)
# light at the cell corners above this fraction of the sub-images' is a background: less pulls the centres by
# under 0.01 px even with strong vignetting, and blurred or Airy rims alone reach 5 - 12 % there (measured)
EDGE_GROUP_MIN = 5  # wholly seen lenses an edge group needs for its common offset to be read (a median)
EDGE_RINGS = (0,)  # the rings whose lines get an offset of their own: the outer one, which misses neighbours
# (freeing the second ring's too left a 7 x 7 array's model resting on its 3 x 3 middle: 0.029 px, not 0.008)
EDGE_ROUNDS = 40  # model fits at most, each followed by the outer lines' offsets read against it (7 x 7: 15)
EDGE_SETTLED_PX = 1e-4  # ... until no offset changes by more than this
BACKGROUND_MIN = 0.15
BACKGROUND_DEGREE = 4  # of the polynomial surface fitted to it


# --------------------------------------------------------------------------------------------- checks


def _as_image(img: Any) -> np.ndarray:
    """A float32 2-D view of the input; InputError for anything a white image cannot be."""
    if not isinstance(img, np.ndarray):
        raise InputError(f"the white image must be a 2-D array, not {type(img).__name__}")
    if img.ndim != 2:
        raise InputError(f"the white image must be a 2-D array, not of shape {img.shape}")
    if img.dtype.kind not in "fiu":
        raise InputError(f"the white image must hold numbers, not {img.dtype}")
    if min(img.shape) < 16:
        raise InputError(f"the white image ({img.shape[0]}x{img.shape[1]} px) is too small to hold a microlens grid")
    out = np.ascontiguousarray(img, dtype=np.float32)
    if not np.all(np.isfinite(out)):
        raise InputError("the white image contains NaN or infinite values")
    return out


def _check_levels(img: np.ndarray) -> None:
    """InputError if the (normalized, black-subtracted) frame is black or saturated."""
    step = max(1, int(math.sqrt(img.size / 250_000)))  # a quarter million pixels are plenty
    sample = img[::step, ::step]
    lo, hi = (float(v) for v in np.percentile(sample, [0.5, 99.5]))  # one partition for both
    saturated = float(np.count_nonzero(sample >= 0.999)) / sample.size
    if saturated > 0.05:
        raise InputError(f"the white image is saturated ({saturated:.0%} of pixels at full scale); reduce the exposure")

    def noise() -> float:  # only needed for a faint frame
        diff = img[::step, 1:][:, ::step] - img[::step, :-1][:, ::step]
        return 1.4826 * float(np.median(np.abs(diff))) / math.sqrt(2.0)

    if hi <= 0.005 or (hi <= 0.05 and hi <= 6.0 * noise()) or hi - lo <= 0.005:
        raise InputError("the white image is black (nothing rises above the black level); check the light and exposure")


# ------------------------------------------------------------------------------------------ calibrate


def calibrate(img: np.ndarray, *, expected_pitch_px: float | None = None,
              expected_shape: tuple[int, int] | None = None, packing: str = "square",
              min_found_share: float = MIN_FOUND_SHARE) -> Grid:
    """Find, measure and index every microlens of a white image; fit the global grid.

    `img`: float, black-subtracted, normalized (1 = full scale) white image. `expected_pitch_px`: the
    config's sub-image pitch (the found pitch must lie within 10 %). `expected_shape`: (N_H, N_W) of the
    MLA; the grid then has exactly that many rows and columns, U(1,1) being the array's top-left lens even
    if border lenses are dim or cut by the frame. `packing`: the MLA's ("square" or "hex", the config's
    mla.packing; mlaqc.optics.lattice's U(m,n) convention). `min_found_share`: the share of the expected
    lenses that must be found (0 for "auto" counts, an upper bound: the array may be smaller than the frame).
    Raises InputError for an image that cannot be calibrated, or whose lattice is not of `packing`.
    """
    if packing not in PACKINGS:
        raise InputError(f"packing must be one of {list(PACKINGS)}, got {packing!r}")
    img = _as_image(img)
    if expected_pitch_px is not None and not (np.isfinite(expected_pitch_px) and expected_pitch_px >= MIN_PITCH_PX):
        raise InputError(f"expected pitch must be a number of at least {MIN_PITCH_PX} px, got {expected_pitch_px!r}")
    if expected_shape is not None:
        if (len(expected_shape) != 2 or any(not isinstance(v, (int, np.integer)) or v < 1 for v in expected_shape)):
            raise InputError(f"expected shape must be two positive integers (N_H, N_W), got {expected_shape!r}")
        expected_shape = (int(expected_shape[0]), int(expected_shape[1]))
    _check_levels(img)
    lattice = _fft_lattice(img, expected_pitch_px, packing)
    lat_j, lat_i, px, py = _candidates(img.shape, lattice)
    order = np.argsort(_colours(lat_j, lat_i, packing), kind="stable")  # sweep colours, each contiguous
    lat_j, lat_i, px, py = lat_j[order], lat_i[order], px[order], py[order]
    pitch = float(np.sqrt(abs(np.linalg.det(lattice.basis))))
    radius0 = _radius_guess(img, pitch)
    discs, active = _measure(img, px, py, lat_j, lat_i, lattice.basis, radius0, packing)
    clean = _without_background(img, lattice, discs, active)
    if clean is not img:  # a background the discs do not explain: measured again without it
        discs, active = _measure(clean, px, py, lat_j, lat_i, lattice.basis, radius0, packing)
    return _assemble(img.shape, lattice, lat_j, lat_i, discs, active, expected_shape, min_found_share)


# the corners must lie this far outside the fitted rims to measure a background there: 1.5 px and two edge
# widths (a background widens the fitted edge, so no more); discs that reach them (radius > ~0.53 p in hex)
# light them themselves
BACKGROUND_CLEAR_PX = 1.5


def _without_background(img: np.ndarray, lattice: _Lattice, discs: _Discs, active: np.ndarray) -> np.ndarray:
    """The frame less a smooth background, if the cell corners (the places farthest from every sub-image)
    hold over BACKGROUND_MIN of the sub-images' light while the fitted rims lie well clear of them:
    unfocused light through clear gaps between circular lenses, or a black level set too low. The disc
    model has no background term, and a sloped one (vignetting) pulls the centres. The background is a
    robust polynomial surface through the corners' levels. Otherwise (dark corners, or corners the rims
    reach, where the light is the discs') the frame itself is returned."""
    h, w = img.shape
    lit = np.flatnonzero(active)
    corners = lattice.basis @ np.array(_CORNERS[lattice.packing], dtype=float).T  # (2, k) px from a centre
    clear = float(np.min(np.hypot(corners[0], corners[1]))) - float(np.median(discs.radius[lit]))
    if lit.size == 0 or clear < max(BACKGROUND_CLEAR_PX, 2.0 * discs.edge):
        return img

    def corner_levels(lenses: np.ndarray):
        """(x, y, level) of the corners of `lenses` inside the frame."""
        x = (discs.cx[lenses][:, None] + corners[0][None, :]).ravel()
        y = (discs.cy[lenses][:, None] + corners[1][None, :]).ravel()
        keep = (x >= 0) & (x <= w - 2) & (y >= 0) & (y <= h - 2)
        return x[keep], y[keep], _bilinear(img, x[keep], y[keep])

    # the question on a sample of a few thousand lenses (a millisecond), the surface from all of them
    sample = lit[:: max(1, lit.size // 2000)]
    inner = (discs.cx[sample] >= 0) & (discs.cx[sample] <= w - 2) & (discs.cy[sample] >= 0) & (discs.cy[sample] <= h - 2)
    _, _, level = corner_levels(sample)
    if level.size < 4 * (BACKGROUND_DEGREE + 1) ** 2 or not inner.any():
        return img
    plateau = float(np.median(_bilinear(img, discs.cx[sample][inner], discs.cy[sample][inner])))
    if not float(np.median(level)) > BACKGROUND_MIN * plateau:
        return img
    cx, cy, level = corner_levels(lit)
    sx, sy = 2.0 / w, 2.0 / h  # coordinates in [-1, 1]
    terms = [(a, b) for a in range(BACKGROUND_DEGREE + 1) for b in range(BACKGROUND_DEGREE + 1 - a)]
    xn, yn = cx * sx - 1.0, cy * sy - 1.0
    design = np.stack([xn ** a * yn ** b for a, b in terms], axis=1)
    used = np.ones(level.size, bool)
    for _ in range(3):  # corners next to defects are outliers
        coef = np.linalg.lstsq(design[used], level[used], rcond=None)[0]
        resid = level - design @ coef
        spread = 1.4826 * float(np.median(np.abs(resid[used]))) + 1e-12
        used = np.abs(resid) <= 3.0 * spread
    xs_row = (np.arange(w) * sx - 1.0)[None, :]
    ys_col = (np.arange(h) * sy - 1.0)[:, None]
    surface = np.zeros((h, w), np.float32)
    for b in range(BACKGROUND_DEGREE + 1):
        row = sum(c * xs_row ** a for (a, bb), c in zip(terms, coef) if bb == b)
        surface += (ys_col ** b * row).astype(np.float32)
    return img - surface


def calibrate_for(img: np.ndarray, cfg: Any) -> Grid:
    """The grid of a white frame of a CameraConfig's camera: its sub-image pitch, lens count and packing."""
    return calibrate(img, expected_pitch_px=cfg.layout.subimage_pitch_px,
                     expected_shape=(cfg.mla.count_h, cfg.mla.count_w), packing=cfg.mla.packing,
                     min_found_share=0.0 if getattr(cfg.mla, "counts_auto", False) else MIN_FOUND_SHARE)


def _candidates(shape: tuple[int, int], lattice: _Lattice):
    """Every lattice point whose sub-image centre lies within half a pitch of the frame."""
    h, w = shape
    inv = np.linalg.inv(lattice.basis)
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float) - lattice.origin
    lc = inv @ corners.T
    j = np.arange(math.floor(lc[0].min()) - 1, math.ceil(lc[0].max()) + 2)
    i = np.arange(math.floor(lc[1].min()) - 1, math.ceil(lc[1].max()) + 2)
    jj, ii = np.meshgrid(j, i)
    jj, ii = jj.ravel(), ii.ravel()
    pts = lattice.origin[:, None] + lattice.basis @ np.stack([jj, ii]).astype(float)
    margin = 0.5 * float(np.sqrt(abs(np.linalg.det(lattice.basis))))
    keep = (pts[0] >= -margin) & (pts[0] <= w - 1 + margin) & (pts[1] >= -margin) & (pts[1] <= h - 1 + margin)
    return jj[keep], ii[keep], pts[0][keep], pts[1][keep]


def _radius_guess(img: np.ndarray, pitch: float) -> float:
    """Sub-image radius from the lit area fraction of the frame's central part (the lenses cover it)."""
    h, w = img.shape
    core = img[h // 4: 3 * h // 4: 2, w // 4: 3 * w // 4: 2]
    level = float(np.percentile(core, 90))
    frac = float(np.count_nonzero(core > 0.5 * level)) / max(1, core.size)
    return float(np.clip(pitch * math.sqrt(frac / math.pi), 0.2 * pitch, 0.75 * pitch))


def _neighbourhood_median(values: np.ndarray, size: int = 5) -> np.ndarray:
    """NaN-ignoring median over a size x size window of a 2-D array (NaN where the window is empty)."""
    pad = size // 2
    padded = np.pad(values.astype(np.float64), pad, constant_values=np.nan)
    win = np.sort(np.lib.stride_tricks.sliding_window_view(padded, (size, size)).reshape(*values.shape, -1), axis=-1)
    count = np.count_nonzero(~np.isnan(win), axis=-1)  # NaNs sort last
    lo = np.take_along_axis(win, np.maximum(count - 1, 0)[..., None] // 2, axis=-1)[..., 0]
    hi = np.take_along_axis(win, (count // 2)[..., None], axis=-1)[..., 0]
    return np.where(count > 0, 0.5 * (lo + hi), np.nan)


def _assemble(shape, lattice, lat_j, lat_i, discs: _Discs, active, expected_shape,
              min_found_share: float = MIN_FOUND_SHARE) -> Grid:
    h, w = shape
    pitch = float(np.sqrt(abs(np.linalg.det(lattice.basis))))
    j0, i0 = int(lat_j.min()), int(lat_i.min())
    nj, ni = int(lat_j.max()) - j0 + 1, int(lat_i.max()) - i0 + 1
    table = lambda v, fill: _scatter(v, lat_i - i0, lat_j - j0, (ni, nj), fill)  # noqa: E731
    amp = table(np.where(active, discs.amp, np.nan), np.nan)
    local = _neighbourhood_median(amp)
    t_act = table(active, False)
    predicted = lattice.origin[:, None] + lattice.basis @ np.stack([lat_j, lat_i]).astype(float)
    off_lattice = np.hypot(discs.cx - predicted[0], discs.cy - predicted[1])
    rmed = float(np.median(discs.radius[active]))
    sane = (np.abs(discs.radius - rmed) < 0.3 * rmed) & (off_lattice < 0.4 * pitch)
    found = t_act & table(sane, False) & (amp >= MISSING_RELATIVE_FLUX * local)
    if np.count_nonzero(found) < MIN_LENSES:
        raise InputError(f"only {int(np.count_nonzero(found))} microlens sub-images could be measured in the white "
                         f"image (at least {MIN_LENSES} are needed)")
    weight = np.where(t_act, amp, 0.0)  # light of every lit lens (dim ones included)
    seen = table(discs.valid_fraction >= MIN_VALID_FRACTION, False)
    dark_seen = seen & ~t_act  # looked at, and nothing there: beyond the MLA
    axis_centre = np.linalg.inv(lattice.basis) @ (np.array([0.5 * (w - 1), 0.5 * (h - 1)]) - lattice.origin)
    hexagonal = lattice.packing == "hex"
    if expected_shape is None:
        rows_used = np.flatnonzero(found.any(axis=1))
        r0 = int(rows_used[0])
        rows = int(rows_used[-1]) - r0 + 1
        # hex: columns counted along the rows' zig-zag from the top row (offset coordinates)
        cols_used = np.flatnonzero((_sheared(found, r0 % 2) if hexagonal else found).any(axis=0))
        c0, cols = int(cols_used[0]), int(cols_used[-1]) - int(cols_used[0]) + 1
        if hexagonal:
            c0 = c0 - (r0 - r0 % 2) // 2 - 1
    elif hexagonal:
        rows, cols = expected_shape
        r0, c0 = _anchor_hex(weight, dark_seen, t_act, rows, cols, (axis_centre[0] - j0, axis_centre[1] - i0))
    else:
        rows, cols = expected_shape
        r0 = _anchor(weight.sum(axis=1), dark_seen.any(axis=1) & ~t_act.any(axis=1), rows, axis_centre[1] - i0)
        c0 = _anchor(weight.sum(axis=0), dark_seen.any(axis=0) & ~t_act.any(axis=0), cols, axis_centre[0] - j0)
    if rows < 3 or cols < 3:
        raise InputError(f"the microlens sub-images found span only {rows}x{cols} lenses; at least 3x3 are needed")
    # lens U(r+1, c+1) is table entry [ti, tj]: square (r0 + r, c0 + c); hex (r0 + r, c0 + c - floor(r / 2)),
    # the axial column of offset column c on window row r (a2 leans +p/2 per row)
    rr, cc = np.mgrid[0:rows, 0:cols]
    ti, tj = r0 + rr, c0 + cc - (rr // 2 if hexagonal else 0)
    inside_table = (ti >= 0) & (ti < ni) & (tj >= 0) & (tj < nj)

    def window(table_2d, fill):
        """(rows, cols) view of a lattice table, padded where the window leaves the candidate range."""
        out = np.full((rows, cols), fill, dtype=np.asarray(table_2d).dtype)
        out[inside_table] = table_2d[ti[inside_table], tj[inside_table]]
        return out

    found_w = window(found, False)
    n_found = int(np.count_nonzero(found_w))
    if n_found < MIN_LENSES:
        raise InputError(f"only {n_found} microlens sub-images lie inside the expected {rows}x{cols} array "
                         f"(at least {MIN_LENSES} are needed)")
    if expected_shape is not None and n_found < min_found_share * rows * cols:
        raise InputError(f"only {n_found} of the expected {rows}x{cols} microlenses were found in the "
                         f"{h}x{w} px image; check the camera config (MLA shape) and the image")
    mx = np.where(found_w, window(table(discs.cx, np.nan), np.nan), np.nan)
    my = np.where(found_w, window(table(discs.cy, np.nan), np.nan), np.nan)
    vfrac = window(table(discs.valid_fraction, 0.0), 0.0)
    flux = np.where(found_w, window(table(discs.amp * np.pi * discs.radius ** 2, np.nan), np.nan), np.nan)
    radius = np.where(found_w, window(table(discs.radius, np.nan), np.nan), np.nan)
    design = Lattice(lattice.packing, rows, cols)
    if hexagonal:
        uu, vv = design.uv(rr, cc)  # the design's lattice units (pitches): the model's (u, v)
    else:
        vv, uu = np.mgrid[0:rows, 0:cols].astype(float)
    span = design.span_uv
    centre = (0.5 * (w - 1), 0.5 * (h - 1))
    # lenses whose predicted window leaves the frame entirely were never candidates: clipped + missing
    clipped = (vfrac < 1.0) | ~np.isfinite(vfrac)
    # the model and the outer lines' offsets (least squares together): the model fitted to the centres less
    # the offsets, the offsets read against the model, in turn until they settle (on a 12 x 12 array the
    # model's terms otherwise took up part of the offsets); should they not, the centres as the fit read them
    raw_x, raw_y, seen = mx, my, found_w & ~clipped
    before, first = None, None
    for _ in range(EDGE_ROUNDS):
        fit = _fit_model(uu[found_w], vv[found_w], mx[found_w], my[found_w], centre, lattice, (r0 + i0, c0 + j0),
                         (rows, cols), span)
        gx, gy = _model_xy(fit[0], fit[1], centre, fit[2], uu, vv)
        mx, my, edge_offsets = _edge_offsets_removed(raw_x, raw_y, gx, gy, seen, lattice.packing)
        first = first or (fit, gx, gy)
        now = np.array([dx + dy for _, _, dx, dy in edge_offsets])
        if not edge_offsets or (before is not None and np.max(np.abs(now - before)) < EDGE_SETTLED_PX):
            break
        before = now
    else:
        log.warning("the outer lenses' offsets did not settle in %d rounds: their centres are kept as fitted", EDGE_ROUNDS)
        (fit, gx, gy), (mx, my, edge_offsets) = first, (raw_x, raw_y, ())
    hom, k, scale, _, rms = fit
    jac = _local_jacobian(hom, k, centre, scale, 0.5 * span[0], 0.5 * span[1])
    pitch_x, pitch_y = float(np.hypot(*jac[:, 0])), float(np.hypot(*jac[:, 1]))
    rotation = math.degrees(math.atan2(-jac[1, 0], jac[0, 0]))
    angle = math.degrees(math.acos(float(np.clip(jac[:, 0] @ jac[:, 1] / (pitch_x * pitch_y), -1, 1))))
    ox, oy = _model_xy(hom, k, centre, scale, 0.0, 0.0)
    return Grid(
        rows=rows, cols=cols, pitch_px=(pitch_x, pitch_y), rotation_deg=rotation, shear_deg=angle - 90.0,
        origin_px=(float(ox), float(oy)), homography=hom, radial_k=float(k), radial_centre_px=centre,
        radial_scale_px=float(scale), edge_width_px=float(discs.edge), image_shape=(h, w),
        measured_x_px=mx, measured_y_px=my, grid_x_px=gx, grid_y_px=gy,
        residual_px=np.hypot(mx - gx, my - gy), flux=flux, radius_px=radius,
        missing=~found_w, clipped=clipped, rms_residual_px=float(rms), packing=lattice.packing,
        edge_offsets=edge_offsets,
    )


def _edge_offsets_removed(mx, my, gx, gy, seen, packing):
    """The measured centres less each edge group's common offset from the lattice, along the normal to its
    side (`edge_lines` of the EDGE_RINGS: the outer ring by side, hex row ends apart), taken off its whole
    line (a corner lens lies on two), and the offsets removed: (name, lenses, dx, dy) per group of at least
    EDGE_GROUP_MIN wholly seen lenses. A lens at the array's edge sees its neighbours' rims on one side
    only, and the disc fit's rim is not the optics' (an Airy rim's tail): every lens of the microscope
    fixture's outer ring read 0.106 px inward, alike to 0.001 px, while the robust lattice fit (which
    rejects them) stayed true. A lens' own error stays: the median is the group's, not the lens'."""
    from mlaqc.inspection.lens_classes import edge_lines

    shift = np.zeros((2,) + mx.shape)
    removed = []
    for e in edge_lines(mx.shape, packing):
        use = e.group & seen & np.isfinite(mx) & np.isfinite(my)
        n = int(np.count_nonzero(use))
        if e.ring not in EDGE_RINGS or n < EDGE_GROUP_MIN:
            continue
        offset = round(float(np.median((mx - gx, my - gy)[e.axis][use])), 6)  # as grid.json keeps it
        shift[e.axis][e.line] += offset
        removed.append((e.name, n, offset if e.axis == 0 else 0.0, offset if e.axis == 1 else 0.0))
    return mx - shift[0], my - shift[1], tuple(removed)


def _scatter(values, rows, cols, shape, fill):
    values = np.asarray(values)
    out = np.full(shape, fill, dtype=values.dtype if values.dtype != bool else bool)
    out[rows, cols] = values
    return out


def _anchor(line_weight: np.ndarray, line_dark: np.ndarray, count: int, axis_pos: float) -> int:
    """Start of the `count`-long window of lattice lines (rows or columns) holding the MLA: the most light;
    among equals, the fewest lines seen dark inside the frame (beyond the array's edge), then the window
    centred nearest the frame centre (the optical axis). Windows may reach beyond the frame, where lines
    cut off by a cropped frame are unobserved, not dark."""
    pad = np.zeros(count)
    light = np.convolve(np.concatenate([pad, line_weight, pad]), np.ones(count), mode="valid")
    dark = np.convolve(np.concatenate([pad, line_dark.astype(float), pad]), np.ones(count), mode="valid")
    starts = np.arange(light.size) - count
    best = light >= light.max() * (1 - 1e-9) - 1e-12
    best &= dark <= dark[best].min()
    cand = starts[best]
    return int(cand[np.argmin(np.abs(cand + 0.5 * (count - 1) - axis_pos))])


def _sheared(table: np.ndarray, parity: int) -> np.ndarray:
    """An axial hex table (rows i, columns j) with each row moved floor((i - parity) / 2) + 1 columns right:
    its columns are then the offset columns of a window whose top row has that parity (a lens of window
    row r, offset column c sits in sheared column c + const)."""
    ni, nj = table.shape
    shift = (np.arange(ni) - parity) // 2 + 1
    out = np.zeros((ni, nj + int(shift.max()) + 1), dtype=table.dtype)
    out[np.arange(ni)[:, None], np.arange(nj)[None, :] + shift[:, None]] = table
    return out


def _box_sums(a: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Sums of `a` over every rows x cols window, windows reaching up to the whole size beyond each side:
    [s, t] is the window starting at (s - rows, t - cols)."""
    pad = np.pad(np.asarray(a, dtype=np.float64), ((rows, rows), (cols, cols)))
    cs = np.zeros((pad.shape[0] + 1, pad.shape[1] + 1))
    cs[1:, 1:] = pad.cumsum(axis=0).cumsum(axis=1)
    return cs[rows:, cols:] - cs[:-rows, cols:] - cs[rows:, :-cols] + cs[:-rows, :-cols]


def _anchor_hex(weight: np.ndarray, dark_seen: np.ndarray, lit: np.ndarray, rows: int, cols: int,
                axis_ji: tuple[float, float]) -> tuple[int, int]:
    """Top row r0 and axial column c0 (table indices) of U(1,1) for a hex array of rows x cols lenses: as
    `_anchor` but over both at once (the window's columns zig-zag, and the top row's parity decides which
    way): the most light; among equals, the fewest lattice lines (rows, zig-zag columns) seen dark; then
    the window centred nearest the frame centre. Windows may reach beyond the frame."""
    row_dark = (dark_seen.any(axis=1) & ~lit.any(axis=1)).astype(float)
    pad = np.zeros(rows)
    rdark = np.convolve(np.concatenate([pad, row_dark, pad]), np.ones(rows), mode="valid")  # [s]: start s - rows
    aj, ai = axis_ji
    per_parity = []
    for parity in (0, 1):
        first = (parity + rows) % 2  # box-sum rows s start at table row s - rows: those of this parity
        light = _box_sums(_sheared(weight, parity), rows, cols)[first::2]
        per_parity.append((parity, first, light))
    top = max(float(light.max()) for _, _, light in per_parity)
    cands = []
    for parity, first, light in per_parity:
        s, t = np.nonzero(light >= top * (1 - 1e-9) - 1e-12)  # the windows with the most light
        s = first + 2 * s
        col_dark = (_sheared(dark_seen, parity).any(axis=0) & ~_sheared(lit, parity).any(axis=0)).astype(float)
        cdark = np.convolve(np.concatenate([np.zeros(cols), col_dark, np.zeros(cols)]), np.ones(cols), mode="valid")
        r0 = s - rows
        c0 = (t - cols) - (r0 - parity) // 2 - 1  # axial column of U(1,1)
        u_mid = c0 + 0.5 * r0 + 0.5 * (cols - 1 + (0.5 if rows > 1 else 0.0))
        v_mid = r0 + 0.5 * (rows - 1)
        dist = (u_mid - (aj + 0.5 * ai)) ** 2 + ((v_mid - ai) * SQRT3_2) ** 2
        cands.append(np.stack([rdark[s] + cdark[t], dist, r0, c0]).astype(np.float64))
    dark, dist, r0, c0 = np.concatenate(cands, axis=1)
    best = dark <= dark.min()
    pick = np.flatnonzero(best)[np.argmin(dist[best])]
    return int(r0[pick]), int(c0[pick])


def _local_jacobian(hom, k, centre, scale, u, v) -> np.ndarray:
    d = 1e-3
    x1, y1 = _model_xy(hom, k, centre, scale, u + d, v)
    x0, y0 = _model_xy(hom, k, centre, scale, u - d, v)
    x3, y3 = _model_xy(hom, k, centre, scale, u, v + d)
    x2, y2 = _model_xy(hom, k, centre, scale, u, v - d)
    return np.array([[x1 - x0, x3 - x2], [y1 - y0, y3 - y2]]) / (2 * d)


def _fit_model(u, v, x, y, centre, lattice: _Lattice, start, shape, span=None):
    """Robust least-squares fit of the global model to the measured centres at design coordinates (u, v)
    (pitches from U(1,1); `span`: their extent, default the square's (cols - 1, rows - 1)).

    Returns (homography for the design coordinates `Lattice.uv` (square: (n-1, m-1)), radial k, radial scale, used mask, rms residual)."""

    rows, cols = shape
    su, sv = (cols - 1, rows - 1) if span is None else span
    full = u.size >= 100 and rows >= 8 and cols >= 8
    uc, vc = 0.5 * su, 0.5 * sv
    us, vs = max(uc, 1.0), max(vc, 1.0)
    un, vn = (u - uc) / us, (v - vc) / vs
    corners_u = np.array([0, su, 0, su], float)
    corners_v = np.array([0, 0, sv, sv], float)
    # initial affine from the Fourier lattice
    design = np.stack([np.ones_like(un), un, vn], 1)
    used = np.ones(u.size, bool)
    px = np.linalg.lstsq(design, x, rcond=None)[0]
    py = np.linalg.lstsq(design, y, rcond=None)[0]
    ext = np.array([centre[0], centre[1]])
    hn = np.array([[px[1], px[2], px[0]], [py[1], py[2], py[0]], [0.0, 0.0, 1.0]])
    cx_, cy_ = _model_xy(hn, 0.0, centre, 1.0, (corners_u - uc) / us, (corners_v - vc) / vs)
    scale = float(np.max(np.hypot(cx_ - ext[0], cy_ - ext[1]))) or 1.0

    def unpack(p):
        hm = np.array([[p[0], p[1], p[2]], [p[3], p[4], p[5]], [p[6], p[7], 1.0]])
        return hm, (p[8] if full else 0.0)

    def resid(p, sel):
        hm, kk = unpack(p)
        mx_, my_ = _model_xy(hm, kk, centre, scale, un[sel], vn[sel])
        return np.concatenate([mx_ - x[sel], my_ - y[sel]])

    def normal_equations(p, sel):
        """Gauss-Newton normal equations J^T J, J^T r and the cost r^T r of `resid` (analytic Jacobian,
        compiled; the radial parameter only in the full model)."""
        hm, kk = unpack(p)
        return kernels.grid_normal_equations(un[sel], vn[sel], x[sel], y[sel], hm, float(kk), float(centre[0]),
                                             float(centre[1]), float(scale), 9 if full else 8)

    def gauss_newton(p, sel):
        """Least squares from the affine start (the model is nearly linear: a few steps), column-scaled,
        with step halving should a step not lower the cost."""
        npar = 9 if full else 8
        p = p.copy()
        jtj, jtr, cost = normal_equations(p, sel)
        for _ in range(20):
            d = np.sqrt(np.diag(jtj)[:npar]) + 1e-300
            a = jtj[:npar, :npar] / np.outer(d, d) + 1e-12 * np.eye(npar)
            step = np.zeros(9)
            step[:npar] = -np.linalg.solve(a, jtr[:npar] / d) / d
            if -float(step @ jtr) <= 1e-12 * cost:  # the predicted decrease: nothing left to gain
                break
            for _ in range(10):
                new = p + step
                jtj_n, jtr_n, cost_n = normal_equations(new, sel)
                if cost_n <= cost:
                    break
                step *= 0.5
            else:
                break
            p, jtj, jtr, cost = new, jtj_n, jtr_n, cost_n
        return p

    p = np.array([hn[0, 0], hn[0, 1], hn[0, 2], hn[1, 0], hn[1, 1], hn[1, 2], 0.0, 0.0, 0.0])
    for _ in range(4):
        if full:
            p = gauss_newton(p, used)
        else:
            d = np.stack([np.ones(used.sum()), un[used], vn[used]], 1)
            ax = np.linalg.lstsq(d, x[used], rcond=None)[0]
            ay = np.linalg.lstsq(d, y[used], rcond=None)[0]
            p = np.array([ax[1], ax[2], ax[0], ay[1], ay[2], ay[0], 0.0, 0.0, 0.0])
        r = resid(p, np.ones(u.size, bool))
        dist = np.hypot(r[: u.size], r[u.size:])
        sigma = 1.4826 * float(np.median(dist[used])) / 1.1774  # median of a 2-D Rayleigh ~ 1.1774 sigma
        new_used = dist <= max(5.0 * sigma, 0.05)
        if np.array_equal(new_used, used):
            break
        used = new_used
        if used.sum() < max(4, u.size // 4):
            raise InputError("the microlens centres do not follow a regular grid; the white image is not usable")
    hm, kk = unpack(p)
    norm = np.array([[1.0 / us, 0.0, -uc / us], [0.0, 1.0 / vs, -vc / vs], [0.0, 0.0, 1.0]])
    hom = hm @ norm
    hom = hom / hom[2, 2]
    r = resid(p, used)
    rms = float(np.sqrt(np.mean(r[: used.sum()] ** 2 + r[used.sum():] ** 2))) if used.any() else float("nan")
    del lattice, start
    return hom, float(kk), scale, used, rms


# the grid and its file are mlaqc.inspection.grid's, importable from here as before
__all__ = ["calibrate", "calibrate_for", "Grid", "load_grid", "FORMAT", "VERSION"]
