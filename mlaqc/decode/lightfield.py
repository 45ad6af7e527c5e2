"""The 4D light field of a plenoptic frame: decoding (`decode`), devignetting by a white frame
(`devignetted`), a hex array's views on a rectangular grid (`rectangular`) and shift-and-add refocusing
(`refocus`); lenses without a usable light field are refilled by `mlaqc.decode.fill`, and a scene frame
is decoded against its white by `mlaqc.decode.scene`.

Axes of `LightField.values`: (v, u, t, s[, channel]): (v, u) the view, i.e. the pupil point, as a pixel
offset (v down, u right) from each lens' sub-image centre, view_offsets_px[j], view_offsets_px[i]; (t, s)
the lens, row and column (U(m, n) = [m-1, n-1] before a hex array is resampled). values[j, i] is one
sub-aperture view: the scene as seen through one point of the main lens' pupil. `weights` has the same
axes but the channel: each sample's confidence, 0 where the frame holds no light field (outside the pupil's
image, outside the frame, a lens without light).

Every sample is read by exact bilinear interpolation (numpy gathers, vectorized over all samples).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np

from mlaqc.decode.sampling import LensSampling
from mlaqc.errors import InputError
from mlaqc.optics.lattice import SQRT3_2

WHITE_FLOOR = 0.1  # a sample whose white is under this fraction of its view's typical white carries no signal


@dataclass(frozen=True, eq=False)
class LightField:
    """Decoded samples (see the module note) and how they were taken."""

    values: np.ndarray  # (nv, nu, rows, cols[, channels]) float32
    weights: np.ndarray  # (nv, nu, rows, cols) float32 in [0, 1]
    view_offsets_px: np.ndarray  # (n,) pixel offsets of the views from a sub-image centre (both axes)
    packing: str  # the (t, s) grid: 'square', 'hex' (U(m,n) order) or 'rect' (a hex array resampled)
    devignetted: bool = False
    foreign: np.ndarray | None = None  # (nv, nu, rows, cols) samples dropped as mostly another lens' light

    @property
    def spatial_shape(self) -> tuple[int, int]:
        return tuple(self.values.shape[2:4])  # type: ignore[return-value]


def view_offsets(radius_px: float, views: int | None = None) -> np.ndarray:
    """The views' pixel offsets: `views` (odd) whole-pixel steps centred on the sub-image centre, by
    default every whole pixel whose circle fits inside the pupil's image (radius less one pixel)."""
    if views is None:
        half = max(0, int(np.floor(radius_px - 1.0)))
    else:
        if views < 1 or views % 2 == 0:
            raise InputError(f"--views must be an odd number of views a side (1, 3, 5, ...), got {views}")
        half = views // 2
        if half > radius_px:
            raise InputError(f"{views} views a side reach {half} px from a sub-image centre, beyond its radius "
                             f"({radius_px:.1f} px): the outer views would see the next lens' light")
    return np.arange(-half, half + 1, dtype=np.float64)


def decode(img: np.ndarray, sampling: LensSampling, offsets_px: np.ndarray) -> LightField:
    """Sample every lens' sub-image at every view offset (scaled by the lens' `scale`) from `img`
    ((H, W) or (H, W, C) float); views outside the pupil's image and samples outside the frame weigh 0."""
    if img.shape[:2] != tuple(sampling.image_shape):
        h, w = img.shape[:2]
        raise InputError(f"the frame is {w}x{h} px but its grid is for {sampling.image_shape[1]}x"
                         f"{sampling.image_shape[0]} px: it is of another camera or crop")
    o = np.asarray(offsets_px, dtype=np.float64)
    sx = sampling.x_px[None, None] + sampling.scale[None, None] * o[None, :, None, None]
    sy = sampling.y_px[None, None] + sampling.scale[None, None] * o[:, None, None, None]
    sx, sy = np.broadcast_arrays(sx, sy)
    values, inside = bilinear(img, sx, sy)
    disc = np.hypot(o[:, None], o[None, :]) <= sampling.radius_px - 0.5
    weights = (inside & disc[:, :, None, None]) * sampling.weight[None, None]
    return LightField(values, weights.astype(np.float32), o, sampling.packing)


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`img` (H, W[, C]) at float pixel positions (x, y) (any equal shapes), exact bilinear weights; 0 and
    inside=False where the 2x2 neighbourhood leaves the frame or a position is not finite."""
    h, w = img.shape[:2]
    ok = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    xs, ys = np.where(ok, x, 0.0), np.where(ok, y, 0.0)
    x0 = np.minimum(np.floor(xs).astype(np.intp), max(w - 2, 0))
    y0 = np.minimum(np.floor(ys).astype(np.intp), max(h - 2, 0))
    fx, fy = (xs - x0).astype(np.float32), (ys - y0).astype(np.float32)
    flat = img.reshape(h * w, -1)
    i00 = y0 * w + x0
    x1 = np.minimum(1, w - 1)
    y1 = w if h > 1 else 0
    if img.ndim == 3:
        fx, fy = fx[..., None], fy[..., None]
    top = _take(flat, i00, img) * (1 - fx) + _take(flat, i00 + x1, img) * fx
    bottom = _take(flat, i00 + y1, img) * (1 - fx) + _take(flat, i00 + y1 + x1, img) * fx
    out = top * (1 - fy) + bottom * fy
    mask = ok[..., None] if img.ndim == 3 else ok
    return np.where(mask, out, 0.0).astype(np.float32), ok


def _take(flat: np.ndarray, idx: np.ndarray, img: np.ndarray) -> np.ndarray:
    """flat[idx] shaped as idx (plus the channel axis for a colour image)."""
    got = flat[idx.ravel()]
    return got.reshape(idx.shape + ((img.shape[2],) if img.ndim == 3 else ())).astype(np.float32)


def devignetted(lf: LightField, white: LightField) -> LightField:
    """`lf` divided by the white frame's light field decoded at the same samples: each pupil point's
    transmission through each lens (vignetting, a dim lens, a dust shadow) divided out. The weight becomes
    the white's share of its view's typical white (capped at 1): a sample that received little light is
    a noisy one; under WHITE_FLOOR it is dropped."""
    wv = white.values if white.values.ndim == 4 else white.values.mean(axis=-1)
    used = (white.weights > 0) & (wv > 0)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a view no lens sees: its typical white is NaN -> 0
        typical = np.nan_to_num(np.nanmedian(np.where(used, wv, np.nan), axis=(2, 3)))
    share = np.where(typical[:, :, None, None] > 0, wv / np.maximum(typical[:, :, None, None], 1e-30), 0.0)
    keep = used & (share >= WHITE_FLOOR)
    denom = white.values if white.values.ndim == lf.values.ndim else wv[..., None]
    if lf.values.ndim == 5 and denom.ndim == 4:
        denom = denom[..., None]
    ratio = np.where(_expand(keep, lf.values), lf.values / np.where(denom > 0, denom, 1.0), 0.0)
    weights = lf.weights * np.where(keep, np.minimum(share, 1.0), 0.0)
    return replace(lf, values=ratio.astype(np.float32), weights=weights.astype(np.float32), devignetted=True)


def _expand(mask: np.ndarray, like: np.ndarray) -> np.ndarray:
    """A (nv, nu, rows, cols) mask broadcastable against `like` (which may carry a channel axis)."""
    return mask[..., None] if like.ndim == mask.ndim + 1 else mask


def rectangular(lf: LightField) -> LightField:
    """A hex array's light field on a rectangular (s, t) grid one lens pitch apart in both directions:
    the rows' half-pitch shift and their sqrt(3)/2 spacing interpolated out (linear, weight-aware: a sample
    with no weight contributes nothing). A square array's comes back unchanged."""
    if lf.packing != "hex":
        return lf
    vals, w = lf.values.astype(np.float64), lf.weights.astype(np.float64)
    rows, cols = w.shape[2], w.shape[3]
    # design lattice units: u = col + 0.5 [row odd (0-based, i.e. m even)], v = row sqrt(3)/2
    shift = (np.arange(rows) % 2 == 1)
    u_out = np.arange(cols, dtype=np.float64)  # integer u, from 0
    # along each row: value at integer u from the row's own lenses (shifted rows: between c-1 and c)
    c0 = np.where(shift[:, None], u_out[None, :] - 1.0, u_out[None, :])
    frac = np.where(shift[:, None], 0.5, 0.0) * np.ones((1, cols))
    wv, ww = _lerp_columns(vals * _expand(w, vals), w, c0, frac)
    t_count = int(np.floor((rows - 1) * SQRT3_2)) + 1
    v_out = np.arange(t_count, dtype=np.float64) / SQRT3_2  # the output rows in input row units
    r0 = np.minimum(np.floor(v_out), rows - 2 if rows > 1 else 0)
    fr = v_out - r0
    wv, ww = _lerp_rows(wv, ww, r0.astype(int), fr)
    values = np.where(_expand(ww > 0, wv), wv / np.where(_expand(ww, wv) > 0, _expand(ww, wv), 1.0), 0.0)
    return replace(lf, values=values.astype(np.float32), weights=ww.astype(np.float32), packing="rect",
                   foreign=None)


def _lerp_columns(wv: np.ndarray, w: np.ndarray, c0: np.ndarray, frac: np.ndarray):
    """Per row r, columns c0[r] + frac[r] of weight-premultiplied values and weights (c0 = -1 reads 0)."""
    rows, cols = w.shape[2], w.shape[3]
    r_idx = np.arange(rows)[:, None]
    lo = c0.astype(int)
    hi = lo + 1
    out_v = np.zeros(wv.shape[:3] + (cols,) + wv.shape[4:])
    out_w = np.zeros(w.shape[:3] + (cols,))
    for idx, f in ((lo, 1.0 - frac), (hi, frac)):
        ok = (idx >= 0) & (idx < cols) & (f > 0)
        safe = np.clip(idx, 0, cols - 1)
        fw = np.where(ok, f, 0.0)
        out_w += w[:, :, r_idx, safe] * fw
        out_v += wv[:, :, r_idx, safe] * (fw[..., None] if wv.ndim == 5 else fw)
    return out_v, out_w


def _lerp_rows(wv: np.ndarray, w: np.ndarray, r0: np.ndarray, fr: np.ndarray):
    """Rows r0 + fr (linear) of weight-premultiplied values and weights."""
    rows = w.shape[2]
    r1 = np.minimum(r0 + 1, rows - 1)
    f = fr[:, None]
    fv = f[..., None] if wv.ndim == 5 else f
    out_w = w[:, :, r0] * (1 - f) + w[:, :, r1] * f
    out_v = wv[:, :, r0] * (1 - fv) + wv[:, :, r1] * fv
    return out_v, out_w


def refocus(lf: LightField, slope: float) -> tuple[np.ndarray, np.ndarray]:
    """Shift-and-add: the image focused where a point moves `slope` lenses (s, t) per pixel of view offset,
    E(s, t) = sum w L(u, v, s + slope u, t + slope v) / sum w; 0 the plane the MLA sees in focus. Returns
    (image, summed weight). A view's weight w is its typical weight over the lenses (a view near the pupil's
    rim is noisier) on every sample that has a light field (weight > 0): a per-lens weight would pull each
    interpolated point towards the better lenses, a bias that costs more than a doubted lens' reading
    (measured, bench/decode.py; refill doubted lenses with `fill.filled`)."""
    nv, nu, rows, cols = lf.weights.shape
    o = lf.view_offsets_px
    s_grid, t_grid = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    num = np.zeros(lf.values.shape[2:], np.float64)
    den = np.zeros((rows, cols), np.float64)
    for j in range(nv):  # one pass per view (a few hundred at most), each vectorized over every lens
        for i in range(nu):
            seen = lf.weights[j, i] > 0
            if not seen.any():
                continue
            weight = np.where(seen, np.float32(np.median(lf.weights[j, i][seen])), np.float32(0.0))
            xs, ys = s_grid + slope * o[i], t_grid + slope * o[j]
            wv = lf.values[j, i] * _expand(weight, lf.values[j, i])
            v, _ = bilinear(wv, xs, ys)
            w, _ = bilinear(weight, xs, ys)
            num += v
            den += w
    image = np.where(_expand(den > 0, num), num / np.where(_expand(den, num) > 0, _expand(den, num), 1.0), 0.0)
    return image.astype(np.float32), den.astype(np.float32)
