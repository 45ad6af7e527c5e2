"""The defect map: the tone-mapped frame with a ring per flagged lens, coloured by error type, and a legend.

`ERROR_COLOURS` is the palette (RGB, the Okabe–Ito colour-blind-safe set); the GUI reuses it so that a
colour means the same error type everywhere.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from mlaqc.inspection.results import InspectionResult
from mlaqc.report.png import encode_png
from mlaqc.report.view import View, cell_outline_px

#: Defect-map colour per error type, RGB. The seven Okabe & Ito "Color Universal Design" colours
#: (distinguishable with the common colour-vision deficiencies) plus magenta for the ambiguous
#: 'position' (pitch or decenter). None is grey, so every ring stands out on the grey image.
ERROR_COLOURS: dict[str, tuple[int, int, int]] = {
    "pitch": (230, 159, 0),  # orange
    "decenter": (86, 180, 233),  # sky blue
    "position": (255, 0, 255),  # magenta: pitch or decenter, the sub-image alone cannot tell
    "radius": (0, 158, 115),  # bluish green
    "tilt": (240, 228, 66),  # yellow
    "thickness": (204, 121, 167),  # reddish purple
    "dim": (255, 255, 255),  # white: a transmission loss, the sub-image's shape kept
    "obscuration": (170, 255, 0),  # lime: dust, residue or a dig darkening part of the sub-image
    "scratch": (255, 140, 200),  # pink: a dark line through the sub-image
    "missing": (213, 94, 0),  # vermillion, drawn as a ring with a cross
    "unknown": (0, 114, 178),  # blue
}
#: Verdict colours, RGB (banner of the HTML report and the map's corner label).
VERDICT_COLOURS: dict[str, tuple[int, int, int]] = {"PASS": (26, 127, 55), "FAIL": (207, 34, 46)}

_OUTLINE = (0, 0, 0)  # dark halo under every ring so that it reads on bright and dark sub-images
_PNG_LEVEL = 1  # zlib level of the full map: level 3 is ~15 % smaller but 1.5x slower on a 2048² frame


def error_colour(error_type: str) -> tuple[int, int, int]:
    """The palette colour of an error type; unknown names get the 'unknown' colour."""
    return ERROR_COLOURS.get(error_type, ERROR_COLOURS["unknown"])



def _type_order(types: Any) -> list[str]:
    """Error types in palette order, any others after them alphabetically."""
    known = [t for t in ERROR_COLOURS if t in types]
    return known + sorted(t for t in types if t not in ERROR_COLOURS)


def render_defect_map(result: InspectionResult | View, *, base: np.ndarray | None = None,
                      max_side: int | None = None) -> np.ndarray:
    """The defect map as an RGB uint8 array: the tone-mapped image, a ring per flagged lens, a legend.

    Full image size, or scaled down so that its longer side is at most `max_side`. Rings are centred on
    the measured centre (grid centre if the lens was not found), diameter about one pitch, coloured by
    ERROR_COLOURS over a dark halo; out-of-tolerance rings are thicker; a directional defect gets a
    tick from the centre towards its direction; missing lenses get a cross as well. On a hex array the
    ring is the lens' hexagonal cell (pointy top, as the grid's fitted lattice lays it on the image).
    The legend goes in the corner where it covers fewest rings, and the rings are drawn over it: a
    flagged lens is never hidden, even on a small array whose every corner holds one.
    """
    v = result if isinstance(result, View) else View(result)
    grey = v.tone_mapped() if base is None else base
    h, w = grey.shape
    scale = 1.0
    if max_side is not None and max(h, w) > max_side:
        scale = max_side / max(h, w)
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    bgr = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    radius, thin, thick = _ring_sizes(v, scale)
    hexagon = _hexagon(v, scale)

    marks = [(d, d.error_type) for d in v.result.defects]
    flagged_pos = {(d.m, d.n) for d in v.result.defects}
    marks += [(None, (m + 1, n + 1)) for m, n in zip(*np.nonzero(v.missing)) if (m + 1, n + 1) not in flagged_pos]
    # in-tolerance first so that out-of-tolerance rings end up on top
    marks.sort(key=lambda t: (t[0] is not None and not t[0].within_tolerance))
    legend = _legend_layout(v, h=bgr.shape[0], w=bgr.shape[1])
    _draw_legend(bgr, legend, legend_corner(v, legend.size, scale=scale))
    for d, info in marks:
        if d is None:  # missing but not flagged (e.g. excluded by the identification)
            mm, nn = info
            etype, t, direction = "missing", thin, None
        else:
            mm, nn, etype = d.m, d.n, d.error_type
            t = thin if d.within_tolerance else thick
            direction = d.direction_deg
        x, y = v.centre(mm, nn)
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        c = (round(x * scale), round(y * scale))
        colour = _bgr(error_colour(etype))
        is_missing = etype == "missing" or bool(v.missing[mm - 1, nn - 1])
        arm = max(2, round(0.35 * radius))
        tick = None
        if direction is not None and math.isfinite(direction) and not is_missing:
            a = math.radians(direction)
            tick = (round(c[0] + 0.8 * radius * math.cos(a)), round(c[1] - 0.8 * radius * math.sin(a)))
        outline = None if hexagon is None else np.round((np.array([x, y]) * scale + hexagon) * _SUB).astype(np.int32)
        for col, extra in ((_OUTLINE, 2), (colour, 0)):  # halo, then colour
            if outline is None:
                cv2.circle(bgr, c, radius, col, t + extra, cv2.LINE_8)
            else:
                cv2.polylines(bgr, [outline], True, col, t + extra, cv2.LINE_8, _SUB_BITS)
            if is_missing:
                cv2.line(bgr, (c[0] - arm, c[1] - arm), (c[0] + arm, c[1] + arm), col, thin + extra, cv2.LINE_8)
                cv2.line(bgr, (c[0] - arm, c[1] + arm), (c[0] + arm, c[1] - arm), col, thin + extra, cv2.LINE_8)
            if tick is not None:
                cv2.line(bgr, c, tick, col, thin + extra, cv2.LINE_8)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


_SUB_BITS = 4  # polygon corners to 1/16 px (cv2's fixed-point `shift`)
_SUB = 1 << _SUB_BITS


def _ring_sizes(v: View, scale: float) -> tuple[int, int, int]:
    """(ring radius, thin and thick line widths) of the map drawn at `scale`, px: about one pitch across."""
    pitch = v.pitch * scale if math.isfinite(v.pitch) and v.pitch > 0 else 20.0 * scale
    thin = max(2, round(0.08 * pitch))  # under 2 px the dark halo swamps the colour
    return max(3, round(0.5 * pitch)), thin, max(thin + 1, round(0.2 * pitch))


def _ring_reach(v: View, scale: float) -> float:
    """How far a ring (circle or hexagonal cell, thick line and halo) reaches from its lens' centre, px."""
    radius, _, thick = _ring_sizes(v, scale)
    hexagon = _hexagon(v, scale)
    return (radius if hexagon is None else float(np.hypot(*hexagon.T).max())) + thick + 2


def _hexagon(v: View, scale: float) -> np.ndarray | None:
    """(6, 2) offsets (map pixels) of a lens' hexagonal cell corners from its centre on a hex array; None on a
    square array (rings stay circles) or when the grid predicts too few lenses to lay the lattice."""
    if not v.hex or v.affine is None:
        return None
    return cell_outline_px(v.packing, v.affine) * scale


def _bgr(rgb: tuple[int, int, int]) -> tuple[int, int, int]:
    return (rgb[2], rgb[1], rgb[0])


def legend_corner(result: InspectionResult | View, box_wh: tuple[int, int] | None = None, *,
                  scale: float = 1.0) -> str:
    """The corner ('tl', 'tr', 'bl', 'br') of the map drawn at `scale` where the legend box (`box_wh` px;
    by default the one laid out for that map) covers fewest flagged lenses' rings (`_ring_reach`); ties
    go to the corner whose quadrant holds fewest flagged lenses, then top-left first."""
    v = result if isinstance(result, View) else View(result)
    h, w = (round(s * scale) for s in v.image.shape)
    bw, bh = _legend_layout(v, h, w).size if box_wh is None else box_wh
    reach_px = _ring_reach(v, scale)
    covered = dict.fromkeys(("tl", "tr", "bl", "br"), 0)
    quadrant = dict.fromkeys(covered, 0)
    for d in v.result.defects:
        x, y = v.centre(d.m, d.n)
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        x, y = x * scale, y * scale
        quadrant[("t" if y < h / 2 else "b") + ("l" if x < w / 2 else "r")] += 1
        for k in covered:
            x0, y0 = (0 if k[1] == "l" else w - bw), (0 if k[0] == "t" else h - bh)
            covered[k] += (x0 - reach_px <= x <= x0 + bw + reach_px) and (y0 - reach_px <= y <= y0 + bh + reach_px)
    return min(covered, key=lambda k: (covered[k], quadrant[k]))


@dataclass(frozen=True)
class _Legend:
    """The legend's text lines (with their swatch colours) and metrics, laid out for one map size."""

    verdict: str
    lines: list[tuple[str, tuple[int, int, int] | None]]
    fs: float  # font scale
    lw: int  # stroke width
    line_h: int
    pad: int
    sw: int  # swatch side
    vh: int  # the verdict's text height
    size: tuple[int, int]  # box (width, height), px


def _legend_layout(v: View, h: int, w: int) -> _Legend:
    """Verdict, defect counts per type and the ring key, measured for an h x w map."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    fs = max(0.35, min(h, w) / 2000)
    lw = max(1, round(fs * 1.6))
    line_h = round(30 * fs) + 4
    pad = round(10 * fs) + 2
    sw = round(18 * fs) + 2  # swatch size
    by_type = Counter(d.error_type for d in v.result.defects)
    n_out = sum(not d.within_tolerance for d in v.result.defects)
    verdict = v.result.verdict
    lines: list[tuple[str, tuple[int, int, int] | None]] = [(f"{len(v.result.defects)} flagged", None)]
    if by_type:
        lines.append((f"{n_out} out of tol.", None))
    lines += [(f"{t}: {by_type[t]}", error_colour(t)) for t in _type_order(by_type)]
    if by_type:
        lines.append(("thick = out of tol.", None))
        if v.hex:
            lines.append(("ring = hex lens cell", None))
    (vw, vh), _ = cv2.getTextSize(verdict, font, fs * 1.6, lw + 1)
    text_w = max([vw] + [cv2.getTextSize(s, font, fs, lw)[0][0] + (sw + pad if c else 0) for s, c in lines])
    size = (min(w, text_w + 2 * pad), min(h, vh + pad * 2 + line_h * len(lines) + pad // 2))
    return _Legend(verdict, lines, fs, lw, line_h, pad, sw, vh, size)


def _draw_legend(bgr: np.ndarray, lg: _Legend, corner: str) -> None:
    """The legend `lg` in a dark box in `corner`."""
    h, w = bgr.shape[:2]
    font = cv2.FONT_HERSHEY_SIMPLEX
    box_w, box_h = lg.size
    x0 = 0 if corner[1] == "l" else w - box_w
    y0 = 0 if corner[0] == "t" else h - box_h
    bgr[y0:y0 + box_h, x0:x0 + box_w] = (bgr[y0:y0 + box_h, x0:x0 + box_w] // 8 + 16)  # dark, still grey
    cv2.putText(bgr, lg.verdict, (x0 + lg.pad, y0 + lg.pad + lg.vh), font, lg.fs * 1.6,
                _bgr(VERDICT_COLOURS[lg.verdict]), lg.lw + 1, cv2.LINE_AA)
    y = y0 + lg.pad + lg.vh + lg.pad // 2
    for text, colour in lg.lines:
        y += lg.line_h
        x = x0 + lg.pad
        if colour is not None:
            cv2.rectangle(bgr, (x, y - lg.sw), (x + lg.sw, y), _bgr(colour), -1)
            x += lg.sw + lg.pad
        cv2.putText(bgr, text, (x, y), font, lg.fs, (235, 235, 235), lg.lw, cv2.LINE_AA)


def _encode_png(rgb: np.ndarray, level: int = _PNG_LEVEL) -> bytes:
    """PNG bytes of an RGB (H, W, 3) or grey (H, W) uint8 image; `level` is zlib's 0-9 (mlaqc.report.png:
    deflated on every core)."""
    return encode_png(rgb, level)
