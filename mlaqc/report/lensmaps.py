"""Per-lens measurement maps: one coloured block per lens, so array-wide trends (a pitch drift, form
error growing along the diagonals) show at a glance. Three panels: optical-centre displacement along x
and along y (µm, MLA plane) and focal-length error (%), each on a diverging scale symmetric about 0.
A square array is drawn as square blocks; a hex array as its hexagonal cells, each pixel coloured by the
lens whose cell holds it (`Lattice.nearest`), so the cells tile the array's outline with no gap."""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np

from mlaqc.optics.lattice import Lattice

LENS_PX = 4  # block side per lens: 102 lenses -> 408 px
HEX_LENS_PX = 6  # a hex cell's width (one pitch): at 4 px a hexagon does not read as one
_BACKGROUND = 255
_NAN_GREY = 128
_PANELS = (("centre_dx_um", "centre shift x", "µm", 1.0, "centre_sigma_um"),
           ("centre_dy_um", "centre shift y (down)", "µm", 1.0, "centre_sigma_um"),
           ("focal_rel", "focal length error", "%", 100.0, "focal_sigma_rel"))
NOISE_SPAN = 5.0  # the colour scale spans at least this many per-lens sigmas: noise alone stays pale


def diverging(values: np.ndarray, limit: float) -> np.ndarray:
    """RGB uint8 of values on blue (−limit) - white (0) - red (+limit); NaN grey."""
    t = np.clip(np.nan_to_num(values / max(limit, 1e-30), nan=0.0), -1.0, 1.0)
    blue, red = np.array([33, 102, 172], float), np.array([178, 24, 43], float)
    white = np.array([247, 247, 247], float)
    a = np.abs(t)[..., None]
    rgb = np.where((t < 0)[..., None], white + a * (blue - white), white + a * (red - white))
    rgb[~np.isfinite(values)] = _NAN_GREY
    return rgb.astype(np.uint8)


def _limit(v: np.ndarray, sigma: np.ndarray) -> float:
    """Colour-scale half-range: the 99th percentile of |v| (a few strong defects do not wash out the
    trend), and at least NOISE_SPAN times the median per-lens sigma (so that noise alone looks pale)."""
    f = np.abs(v[np.isfinite(v)])
    s = sigma[np.isfinite(sigma)]
    lim = max(float(np.percentile(f, 99)) if f.size else 0.0, NOISE_SPAN * float(np.median(s)) if s.size else 0.0)
    return lim if lim > 0 else 1.0


def hex_cells(lattice: Lattice, px: int = HEX_LENS_PX) -> tuple[np.ndarray, np.ndarray]:
    """(labels, inside) images of a hex array drawn `px` pixels per pitch: each pixel's 0-based flat lens
    index (row * cols + col) and whether that lens is on the array (False: background round the ragged
    outline). Pixel (i, j)'s centre is ((j + 0.5) / px, (i + 0.5) / px) pitches from the top-left corner of
    the array's bounding box; U(1,1)'s centre lies half a pitch right of it and 1/sqrt(3) pitch down."""
    return _hex_cells(lattice.packing, lattice.rows, lattice.cols, px)[:2]


@lru_cache(maxsize=4)
def _hex_cells(packing: str, rows: int, cols: int, px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """hex_cells, and each pixel's colour index for `_body` (its lens, or rows * cols: the background),
    kept for the report's three panels (read-only arrays)."""
    unit = Lattice(packing, rows, cols)
    ext_w, ext_h = unit.extent
    w, h = max(1, math.ceil(ext_w * px)), max(1, math.ceil(ext_h * px))
    x = (np.arange(w) + 0.5) / px - 0.5 * ext_w
    y = (np.arange(h) + 0.5) / px - 0.5 * ext_h
    flat, inside = unit.nearest_on_grid(x, y)
    labels = np.where(inside, flat, 0)
    colour = np.where(inside, flat, rows * cols)
    for a in (labels, inside, colour):
        a.setflags(write=False)
    return labels, inside, colour


def _body(rgb: np.ndarray, packing: str) -> np.ndarray:
    """The per-lens colours (rows, cols, 3) as a picture: square blocks, or hexagonal cells on white (each
    pixel's colour gathered as one 4-byte word: the background's appended after the lenses')."""
    if packing != "hex":
        return np.repeat(np.repeat(rgb, LENS_PX, 0), LENS_PX, 1)
    colour = _hex_cells(packing, rgb.shape[0], rgb.shape[1], HEX_LENS_PX)[2]
    palette = np.zeros((rgb.shape[0] * rgb.shape[1] + 1, 4), np.uint8)
    palette[:-1, :3] = rgb.reshape(-1, 3)
    palette[-1, :3] = _BACKGROUND
    words = palette.view(np.uint32)[:, 0].take(colour)
    return words.view(np.uint8).reshape(*colour.shape, 4)[..., :3]


def _panel(values: np.ndarray, sigma: np.ndarray, title: str, unit: str, packing: str = "square") -> np.ndarray:
    """One map with its title above and a colour bar with the scale's ends below."""
    lim = _limit(values, sigma)
    body = _body(diverging(values, lim), packing)
    h, w = body.shape[:2]
    bar = diverging(np.linspace(-lim, lim, w)[None, :].repeat(10, 0), lim)
    out = np.full((h + 70, w, 3), 255, np.uint8)
    out[26:26 + h] = body
    out[h + 32:h + 42] = bar
    font, black = cv2.FONT_HERSHEY_SIMPLEX, (20, 20, 20)
    cv2.putText(out, title, (2, 18), font, 0.55, black, 1, cv2.LINE_AA)
    cv2.putText(out, f"-{lim:.3g} {unit}", (2, h + 62), font, 0.45, black, 1, cv2.LINE_AA)
    right = f"+{lim:.3g} {unit}"
    (tw, _), _ = cv2.getTextSize(right, font, 0.45, 1)
    cv2.putText(out, right, (w - tw - 2, h + 62), font, 0.45, black, 1, cv2.LINE_AA)
    cv2.putText(out, "0", (w // 2 - 4, h + 62), font, 0.45, black, 1, cv2.LINE_AA)
    return out


def render_lens_maps(measurements, shape: tuple[int, int], packing: str = "square") -> np.ndarray:
    """The three panels side by side as one RGB uint8 image; grey panels when nothing was measured.
    `packing`: the array's lattice ('square' blocks or 'hex' cells, mlaqc.optics.lattice)."""
    panels = []
    for name, title, unit, scale, sigma in _PANELS:
        v, s = ((np.asarray(measurements[k], float) * scale for k in (name, sigma)) if measurements is not None
                else (np.full(shape, np.nan),) * 2)
        panels.append(_panel(v, s, title, unit, packing))
    gap = np.full((panels[0].shape[0], 12, 3), 255, np.uint8)
    return np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1)


__all__ = ["render_lens_maps", "diverging", "hex_cells", "LENS_PX", "HEX_LENS_PX"]
