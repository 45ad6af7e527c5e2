"""Write the inspection report set: report.json, lenses.csv, defect_map(.png, _small.png), report.html.

`write_report(result, out_dir)` renders every file in memory first and only then writes them, each
through a temporary file renamed over the final name (mlaqc.atomic). If anything fails — a bad result,
an encoder error, a full disk — every temporary file is removed and files from an earlier report are
left as they were. report.json is renamed last, so a reader that finds a new report.json finds the
new set beside it.

Conventions shared by every file (DESIGN.md §2):
- lens U(m,n) is row m (1 = top), column n (1 = left); array element [m-1, n-1];
- pixel coordinates: (0, 0) is the centre of the top-left pixel, x to the right, y down;
- directions are degrees counterclockwise from the image's +x axis towards its top;
- JSON has no NaN (null instead); the CSV writes NaN as an empty field.

`ERROR_COLOURS` is the palette of the defect map (RGB, the Okabe–Ito colour-blind-safe set); the GUI
reuses it so that a colour means the same error type everywhere. `load_report` reads a report.json
back and checks it.
"""

from __future__ import annotations

import base64
import contextlib
import csv
import html
import io
import json
import math
import os
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mlaqc import __version__
from mlaqc.atomic import atomic_path
from mlaqc.errors import InputError
from mlaqc.results import METRICS, Defect, InspectionResult

REPORT_FORMAT = "mlaqc-report"
REPORT_FORMAT_VERSION = 1

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
    "missing": (213, 94, 0),  # vermillion, drawn as a ring with a cross
    "unknown": (0, 114, 178),  # blue
}
#: Verdict colours, RGB (banner of the HTML report and the map's corner label).
VERDICT_COLOURS: dict[str, tuple[int, int, int]] = {"PASS": (26, 127, 55), "FAIL": (207, 34, 46)}

#: Key -> file name of every file `write_report` writes.
REPORT_FILES: dict[str, str] = {
    "json": "report.json",
    "csv": "lenses.csv",
    "defect_map": "defect_map.png",
    "defect_map_small": "defect_map_small.png",
    "html": "report.html",
}

SMALL_MAP_MAX_PX = 1024
GALLERY_MAX = 200
CSV_COLUMNS: tuple[str, ...] = (
    "row", "col", "x_px", "y_px", "grid_x_px", "grid_y_px", "flagged", "error_type", *METRICS)

_OUTLINE = (0, 0, 0)  # dark halo under every ring so that it reads on bright and dark sub-images
_PNG_LEVEL = 1  # zlib level of the full map: level 3 is ~15 % smaller but 1.5x slower on a 2048² frame


def error_colour(error_type: str) -> tuple[int, int, int]:
    """The palette colour of an error type; unknown names get the 'unknown' colour."""
    return ERROR_COLOURS.get(error_type, ERROR_COLOURS["unknown"])


# --------------------------------------------------------------------------------------- writing


def write_report(result: InspectionResult, out_dir: str | os.PathLike[str], *,
                 config_dict: dict | None = None) -> dict[str, Path]:
    """Write the report set for `result` into `out_dir` (created if its parent exists).

    Returns {key: path} for the keys of REPORT_FILES. Raises InputError (one sentence) if the result
    is inconsistent or the folder cannot be written; no partial file is ever left behind.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"cannot write the report: {out} exists and is not a folder.")
    if not out.parent.is_dir():
        raise InputError(f"cannot write the report: folder {out.parent} does not exist.")
    view = _View(result)
    contents = _render_all(view, config_dict)  # everything in memory before the first byte is written

    created = False
    try:
        try:
            out.mkdir()
            created = True
        except FileExistsError:
            pass
        with contextlib.ExitStack() as stack:
            # Entered first = renamed last: report.json marks the set as complete.
            for key in ("json", "html", "csv", "defect_map_small", "defect_map"):
                tmp = stack.enter_context(atomic_path(out / REPORT_FILES[key]))
                _write_bytes(tmp, contents[key])
    except BaseException as exc:
        if created:
            with contextlib.suppress(OSError):
                out.rmdir()  # only if still empty
        if isinstance(exc, OSError):
            reason = (exc.strerror or str(exc)).rstrip(".")
            raise InputError(f"cannot write the report to {out}: {reason}.") from exc
        raise
    return {key: out / name for key, name in REPORT_FILES.items()}


def _write_bytes(path: Path, data: bytes) -> None:
    """Write one temporary file (a seam for tests that simulate a full disk)."""
    path.write_bytes(data)


def _render_all(view: _View, config_dict: dict | None) -> dict[str, bytes]:
    """Every file's bytes, keyed like REPORT_FILES."""
    base = view.tone_mapped()
    full = render_defect_map(view, base=base)
    small = render_defect_map(view, base=base, max_side=SMALL_MAP_MAX_PX)
    # OpenCV releases the GIL: encode the big map while the text files are built.
    with ThreadPoolExecutor(max_workers=1) as pool:
        full_job = pool.submit(_encode_png, full)
        try:
            small_png = _encode_png(small, level=3) if small.shape != full.shape else None
            report = build_report_dict(view.result, config_dict=config_dict, _view=view)
            text = {"json": _dumps(report), "csv": lenses_csv(view)}
        finally:
            full_png = full_job.result()  # waits; re-raises an encoder error
        small_png = full_png if small_png is None else small_png
        text["html"] = _html(view, report, small_png)
    return {**{k: t.encode("utf-8") for k, t in text.items()},
            "defect_map": full_png, "defect_map_small": small_png}


# --------------------------------------------------------------------------------- result access


class _View:
    """Checked, convenient access to an InspectionResult and its grid."""

    def __init__(self, result: InspectionResult) -> None:
        self.result = result
        grid = result.grid
        try:
            self.rows, self.cols = int(grid.rows), int(grid.cols)
        except (AttributeError, TypeError, ValueError) as exc:
            raise InputError("cannot write the report: the inspection result has no usable lens grid.") from exc
        shape = (self.rows, self.cols)
        self.mx = self._grid_array("measured_x_px")
        self.my = self._grid_array("measured_y_px")
        self.gx = self._grid_array("grid_x_px")
        self.gy = self._grid_array("grid_y_px")
        self.residual = self._grid_array("residual_px")
        self.missing = self._grid_array("missing").astype(bool)
        self.flagged = np.asarray(result.flagged).astype(bool)
        self.error_type = np.asarray(result.error_type).astype(str)
        for name, arr in (("flagged", self.flagged), ("error_type", self.error_type)):
            _check(arr.shape == shape, f"its {name} array is {arr.shape}, the grid {shape}")
        for name in METRICS:
            _check(name in result.metrics.values, f"metric '{name}' is missing")
            _check(np.shape(result.metrics[name]) == shape,
                   f"metric '{name}' is {np.shape(result.metrics[name])}, the grid {shape}")
        self.image = np.asarray(result.image)
        _check(self.image.ndim == 2 and self.image.size > 0, f"its image is {self.image.shape}, not (H, W)")
        self.subimages = np.asarray(result.subimages)
        _check(self.subimages.ndim == 4 and self.subimages.shape[:2] == shape,
               f"its sub-images are {self.subimages.shape}, not {shape} + (h, w)")
        self.reference = np.asarray(result.reference)
        _check(self.reference.ndim == 2 or (self.reference.ndim == 4 and self.reference.shape[:2] == shape),
               f"its reference is {self.reference.shape}, not (h, w) or {shape} + (h, w)")
        _check(result.verdict in ("PASS", "FAIL"), f"its verdict is {result.verdict!r}")
        seen = set()
        for d in result.defects:
            _check(1 <= d.m <= self.rows and 1 <= d.n <= self.cols,
                   f"defect U({d.m},{d.n}) is outside the {self.rows} x {self.cols} grid")
            _check((d.m, d.n) not in seen, f"lens U({d.m},{d.n}) has two defects")
            _check(bool(self.flagged[d.m - 1, d.n - 1]), f"defect U({d.m},{d.n}) is not flagged")
            seen.add((d.m, d.n))
        _check(len(seen) == int(self.flagged.sum()),
               f"{int(self.flagged.sum())} lenses are flagged but {len(seen)} defects listed")
        self.pitch_x, self.pitch_y = _grid_pitch(grid)

    def _grid_array(self, name: str) -> np.ndarray:
        arr = np.asarray(getattr(self.result.grid, name, None))
        _check(arr.shape == (self.rows, self.cols), f"grid.{name} is {arr.shape}, not {(self.rows, self.cols)}")
        return arr if arr.dtype == bool else arr.astype(float)

    @property
    def pitch(self) -> float:
        return 0.5 * (self.pitch_x + self.pitch_y)

    def centre(self, m: int, n: int) -> tuple[float, float]:
        """Measured centre of U(m,n), or the grid's prediction where it was not found."""
        x, y = self.mx[m - 1, n - 1], self.my[m - 1, n - 1]
        if not (np.isfinite(x) and np.isfinite(y)):
            x, y = self.gx[m - 1, n - 1], self.gy[m - 1, n - 1]
        return float(x), float(y)

    def reference_of(self, m: int, n: int) -> np.ndarray:
        return self.reference if self.reference.ndim == 2 else self.reference[m - 1, n - 1]

    def tone_mapped(self) -> np.ndarray:
        """The image as uint8 grey, 0.5 and 99.5 percentiles stretched to 0 and 255; NaN black."""
        img = self.image.astype(np.float32, copy=False)
        step = max(1, int(math.sqrt(img.size / 250_000)))  # percentiles from a ~250k-pixel sample
        sample = img[::step, ::step]
        sample = sample[np.isfinite(sample)]
        lo, hi = (np.percentile(sample, [0.5, 99.5]) if sample.size else (0.0, 1.0))
        if not hi > lo:
            hi = lo + 1.0
        out = (img - np.float32(lo)) * np.float32(255.0 / (hi - lo))
        out = np.nan_to_num(out, nan=0.0, posinf=255.0, neginf=0.0)
        return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def _check(ok: bool, what: str) -> None:
    if not ok:
        raise InputError(f"cannot write the report: the inspection result is inconsistent ({what}).")


def _grid_pitch(grid: Any) -> tuple[float, float]:
    """(pitch_x_px, pitch_y_px) from a Grid that has either both or one `pitch_px`."""
    px, py = getattr(grid, "pitch_x_px", None), getattr(grid, "pitch_y_px", None)
    if px is None or py is None:
        p = getattr(grid, "pitch_px", None)
        if p is None:
            raise InputError("cannot write the report: the inspection result's grid has no pitch.")
        p_arr = np.ravel(np.asarray(p, dtype=float))
        px, py = (p_arr[0], p_arr[-1]) if p_arr.size else (math.nan, math.nan)
    return float(px), float(py)


# ----------------------------------------------------------------------------------------- JSON


def build_report_dict(result: InspectionResult, *, config_dict: dict | None = None,
                      _view: _View | None = None) -> dict[str, Any]:
    """The content of report.json (plain JSON types, no NaN)."""
    v = _view or _View(result)
    grid = result.grid
    found = ~v.missing
    res = v.residual[found & np.isfinite(v.residual)]
    by_type = Counter(d.error_type for d in result.defects)
    summary = {
        "rows": v.rows, "cols": v.cols, "lens_count": v.rows * v.cols,
        "found": int(found.sum()), "missing": int(v.missing.sum()),
        "flagged": len(result.defects),
        "out_of_tolerance": sum(not d.within_tolerance for d in result.defects),
        "by_error_type": {t: by_type[t] for t in _type_order(by_type)},
    }
    origin = getattr(grid, "origin_px", None)
    if origin is None or np.size(origin) != 2:
        origin = (v.gx[0, 0], v.gy[0, 0])
    grid_summary = {
        "rows": v.rows, "cols": v.cols,
        "pitch_px": v.pitch, "pitch_x_px": v.pitch_x, "pitch_y_px": v.pitch_y,
        "rotation_deg": float(getattr(grid, "rotation_deg", math.nan)),
        # origin: the grid's predicted centre of U(1,1)
        "origin_x_px": float(origin[0]), "origin_y_px": float(origin[1]),
        # the grid's own figure (over the lenses used in its fit) if it has one, else over all found lenses
        "rms_residual_px": _float_attr(grid, "rms_residual_px",
                                       float(np.sqrt(np.mean(res ** 2))) if res.size else None),
        "max_residual_px": float(res.max()) if res.size else None,
    }
    grid_json = grid.to_json_dict() if hasattr(grid, "to_json_dict") else None
    report = {
        "format": REPORT_FORMAT,
        "format_version": REPORT_FORMAT_VERSION,
        "mlaqc_version": __version__,
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "source": str(result.source),
        "verdict": result.verdict,
        "conventions": {
            "lens": "U(m,n): row m from 1 at the top, column n from 1 at the left",
            "pixel": "(0, 0) is the centre of the top-left pixel; x right, y down",
            "direction_deg": "counterclockwise from the image's +x axis towards its top",
        },
        "image_size_px": {"width": int(v.image.shape[1]), "height": int(v.image.shape[0])},
        "summary": summary,
        "grid_summary": grid_summary,
        "grid": grid_json,
        "tolerances": dict(result.tolerances),
        "timings_s": dict(result.timings_s),
        "notes": list(result.notes),
        "metrics": {k: {"unit": u, "meaning": m} for k, (u, m) in METRICS.items()},
        "files": dict(REPORT_FILES),
        "config": config_dict,
        "defects": [d.to_json_dict() for d in result.defects],
    }
    return _jsonable(report)


def _float_attr(obj: Any, name: str, default: float | None) -> float | None:
    val = getattr(obj, name, None)
    try:
        return float(val) if val is not None else default
    except (TypeError, ValueError):
        return default


def _type_order(types: Any) -> list[str]:
    """Error types in palette order, any others after them alphabetically."""
    known = [t for t in ERROR_COLOURS if t in types]
    return known + sorted(t for t in types if t not in ERROR_COLOURS)


_PLAIN = frozenset({str, int, bool, type(None)})


def _jsonable(obj: Any) -> Any:
    """Plain JSON types: numpy scalars and arrays converted, NaN/inf -> None, paths -> str."""
    t = type(obj)  # exact-type fast paths first: a grid brings ~10^5 values
    if t in _PLAIN:
        return obj
    if t is float:
        return obj if math.isfinite(obj) else None
    if t is dict:
        return {k if type(k) is str else str(k): v if type(v) in _PLAIN else _jsonable(v) for k, v in obj.items()}
    if t is list:
        return [v if type(v) in _PLAIN else _jsonable(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f":  # fast path for the grid's (rows, cols) arrays
            out = obj.astype(object)
            out[~np.isfinite(obj)] = None
            return out.tolist()
        if obj.dtype.kind in "biu":
            return obj.tolist()
        return _jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if hasattr(obj, "to_json_dict"):
        return _jsonable(obj.to_json_dict())
    return str(obj)


_ENCODER = json.JSONEncoder(allow_nan=False, ensure_ascii=False)


def _dumps(obj: Any, level: int = 0) -> str:
    """Indented JSON, but a list of scalars on one line and a list of flat records one record per line."""
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        pad = "  " * (level + 1)
        items = ",\n".join(f"{pad}{json.dumps(k, ensure_ascii=False)}: {_dumps(v, level + 1)}"
                           for k, v in obj.items())
        return "{\n" + items + "\n" + "  " * level + "}" + ("\n" if level == 0 else "")
    if isinstance(obj, list):
        if all(not isinstance(x, (dict, list)) for x in obj):
            return _ENCODER.encode(obj)
        if all(isinstance(x, dict) and all(not isinstance(y, (dict, list)) for y in x.values()) for x in obj):
            one_line = [_ENCODER.encode(x) for x in obj]  # e.g. the grid's lenses
            if max(map(len, one_line)) <= 400:
                pad = "  " * (level + 1)
                return "[\n" + ",\n".join(pad + x for x in one_line) + "\n" + "  " * level + "]"
        pad = "  " * (level + 1)
        return "[\n" + ",\n".join(pad + _dumps(x, level + 1) for x in obj) + "\n" + "  " * level + "]"
    return _ENCODER.encode(obj)


# ------------------------------------------------------------------------------------------ CSV


def lenses_csv(view: _View | InspectionResult) -> str:
    """lenses.csv: one row per lens, U(1,1), U(1,2), ... U(rows,cols); NaN written as empty."""
    v = view if isinstance(view, _View) else _View(view)
    m, n = np.meshgrid(np.arange(1, v.rows + 1), np.arange(1, v.cols + 1), indexing="ij")
    columns: list[list[str]] = [
        [str(i) for i in m.ravel().tolist()],
        [str(i) for i in n.ravel().tolist()],
        *(_fmt_column(a, "{:.3f}") for a in (v.mx, v.my, v.gx, v.gy)),
        ["1" if f else "0" for f in v.flagged.ravel().tolist()],
        [t if f else "" for t, f in zip(v.error_type.ravel().tolist(), v.flagged.ravel().tolist())],
        *(_fmt_column(np.asarray(v.result.metrics[k], dtype=float), "{:.6g}") for k in METRICS),
    ]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    writer.writerows(zip(*columns))
    return buf.getvalue()


def _fmt_column(arr: np.ndarray, fmt: str) -> list[str]:
    f = fmt.format
    return [f(x) if math.isfinite(x) else "" for x in np.asarray(arr, dtype=float).ravel().tolist()]


# ---------------------------------------------------------------------------------- defect map


def render_defect_map(result: InspectionResult | _View, *, base: np.ndarray | None = None,
                      max_side: int | None = None) -> np.ndarray:
    """The defect map as an RGB uint8 array: the tone-mapped image, a ring per flagged lens, a legend.

    Full image size, or scaled down so that its longer side is at most `max_side`. Rings are centred on
    the measured centre (grid centre if the lens was not found), diameter about one pitch, coloured by
    ERROR_COLOURS over a dark halo; out-of-tolerance rings are thicker; a directional defect gets a
    tick from the centre towards its direction; missing lenses get a cross as well.
    """
    v = result if isinstance(result, _View) else _View(result)
    grey = v.tone_mapped() if base is None else base
    h, w = grey.shape
    scale = 1.0
    if max_side is not None and max(h, w) > max_side:
        scale = max_side / max(h, w)
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    bgr = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    pitch = v.pitch * scale if math.isfinite(v.pitch) and v.pitch > 0 else 20.0 * scale
    radius = max(3, round(0.5 * pitch))
    thin = max(2, round(0.08 * pitch))  # under 2 px the dark halo swamps the colour
    thick = max(thin + 1, round(0.2 * pitch))

    marks = [(d, d.error_type) for d in v.result.defects]
    flagged_pos = {(d.m, d.n) for d in v.result.defects}
    marks += [(None, (m + 1, n + 1)) for m, n in zip(*np.nonzero(v.missing)) if (m + 1, n + 1) not in flagged_pos]
    # in-tolerance first so that out-of-tolerance rings end up on top
    marks.sort(key=lambda t: (t[0] is not None and not t[0].within_tolerance))
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
        for col, extra in ((_OUTLINE, 2), (colour, 0)):  # halo, then colour
            cv2.circle(bgr, c, radius, col, t + extra, cv2.LINE_8)
            if is_missing:
                cv2.line(bgr, (c[0] - arm, c[1] - arm), (c[0] + arm, c[1] + arm), col, thin + extra, cv2.LINE_8)
                cv2.line(bgr, (c[0] - arm, c[1] + arm), (c[0] + arm, c[1] - arm), col, thin + extra, cv2.LINE_8)
            if tick is not None:
                cv2.line(bgr, c, tick, col, thin + extra, cv2.LINE_8)
    _draw_legend(bgr, v, thin, thick)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _bgr(rgb: tuple[int, int, int]) -> tuple[int, int, int]:
    return (rgb[2], rgb[1], rgb[0])


def legend_corner(result: InspectionResult | _View) -> str:
    """The image corner ('tl', 'tr', 'bl', 'br') where the legend goes: the one with fewest defects."""
    v = result if isinstance(result, _View) else _View(result)
    h, w = v.image.shape
    counts = dict.fromkeys(("tl", "tr", "bl", "br"), 0)
    for d in v.result.defects:
        x, y = v.centre(d.m, d.n)
        if math.isfinite(x) and math.isfinite(y):
            counts[("t" if y < h / 2 else "b") + ("l" if x < w / 2 else "r")] += 1
    return min(counts, key=lambda k: counts[k])  # ties: top-left first


def _draw_legend(bgr: np.ndarray, v: _View, thin: int, thick: int) -> None:
    """Verdict, defect counts per type (colour swatch) and the ring key, in a dark box in a corner."""
    h, w = bgr.shape[:2]
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
    big = fs * 1.6
    (vw, vh), _ = cv2.getTextSize(verdict, font, big, lw + 1)
    text_w = max([vw] + [cv2.getTextSize(s, font, fs, lw)[0][0] + (sw + pad if c else 0) for s, c in lines])
    box_w = min(w, text_w + 2 * pad)
    box_h = min(h, vh + pad * 2 + line_h * len(lines) + pad // 2)
    corner = legend_corner(v)
    x0 = 0 if corner[1] == "l" else w - box_w
    y0 = 0 if corner[0] == "t" else h - box_h
    bgr[y0:y0 + box_h, x0:x0 + box_w] = (bgr[y0:y0 + box_h, x0:x0 + box_w] // 8 + 16)  # dark, still grey
    cv2.putText(bgr, verdict, (x0 + pad, y0 + pad + vh), font, big, _bgr(VERDICT_COLOURS[verdict]), lw + 1,
                cv2.LINE_AA)
    y = y0 + pad + vh + pad // 2
    for text, colour in lines:
        y += line_h
        x = x0 + pad
        if colour is not None:
            cv2.rectangle(bgr, (x, y - sw), (x + sw, y), _bgr(colour), -1)
            x += sw + pad
        cv2.putText(bgr, text, (x, y), font, fs, (235, 235, 235), lw, cv2.LINE_AA)


def _encode_png(rgb: np.ndarray, level: int = _PNG_LEVEL) -> bytes:
    """PNG bytes of an RGB (H, W, 3) or grey (H, W) uint8 image; `level` is zlib's 0-9."""
    img = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb.ndim == 3 else rgb
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, level])
    if not ok:
        raise RuntimeError("OpenCV could not encode a PNG image")
    return buf.tobytes()


# ----------------------------------------------------------------------------------------- HTML

_CSS = """
body{font:14px/1.4 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;color:#1f2328;background:#f6f8fa}
main{max-width:1200px;margin:0 auto;padding:0 16px 32px}
.banner{color:#fff;padding:14px 20px;font-size:22px;font-weight:600}
.banner.PASS{background:#1a7f37}.banner.FAIL{background:#cf222e}
.banner small{font-weight:400;font-size:14px;opacity:.9;display:block;word-break:break-all}
h2{margin:24px 0 8px;font-size:18px}
.cards{display:flex;flex-wrap:wrap;gap:8px}
.card{background:#fff;border:1px solid #d0d7de;border-radius:6px;padding:8px 12px;min-width:90px}
.card b{display:block;font-size:20px}
.sw{display:inline-block;width:12px;height:12px;border-radius:2px;margin-right:4px;vertical-align:-1px;
border:1px solid #0003}
table{border-collapse:collapse;background:#fff}
th,td{border:1px solid #d0d7de;padding:3px 8px;text-align:left}
td.num{text-align:right;font-variant-numeric:tabular-nums}
table.sortable th{cursor:pointer;user-select:none;background:#eaeef2;position:sticky;top:0}
table.sortable th::after{content:" \\2195";color:#8c959f}
table.sortable th[aria-sort=ascending]::after{content:" \\25B2";color:#1f2328}
table.sortable th[aria-sort=descending]::after{content:" \\25BC";color:#1f2328}
tr.out td:last-child{color:#cf222e;font-weight:600}
.map img{max-width:100%;height:auto;border:1px solid #d0d7de}
.gallery{display:flex;flex-wrap:wrap;gap:12px}
.lens{background:#fff;border:1px solid #d0d7de;border-radius:6px;padding:8px;width:300px}
.lens h3{margin:0 0 6px;font-size:15px}
.pair{display:flex;gap:8px}
.pair figure{margin:0;text-align:center;font-size:12px;color:#57606a}
.pair img{image-rendering:pixelated;display:block;border:1px solid #d0d7de}
.lens table{font-size:12px;margin-top:6px;width:100%}
.lens td{padding:1px 4px}
.lens th{font-weight:600;background:#eaeef2;padding:1px 4px}
.note{color:#57606a}
pre{background:#fff;border:1px solid #d0d7de;padding:8px;overflow:auto;max-height:400px}
"""

_JS = """
(function () {
  function key(row, i) {
    var c = row.cells[i];
    return c.hasAttribute('data-sort') ? c.getAttribute('data-sort') : c.textContent.trim();
  }
  function sortBy(table, th, i) {
    var asc = th.getAttribute('aria-sort') !== 'ascending';
    var num = th.getAttribute('data-type') === 'num';
    var heads = table.tHead.rows[0].cells;
    for (var h = 0; h < heads.length; h++) heads[h].removeAttribute('aria-sort');
    th.setAttribute('aria-sort', asc ? 'ascending' : 'descending');
    var body = table.tBodies[0];
    var rows = Array.prototype.slice.call(body.rows);
    rows.sort(function (a, b) {
      var x = key(a, i), y = key(b, i), r;
      if (num) {
        x = x === '' ? NaN : parseFloat(x); y = y === '' ? NaN : parseFloat(y);
        if (isNaN(x) || isNaN(y)) return isNaN(x) - isNaN(y);  /* blanks last either way */
        r = x - y;
      } else {
        r = x.localeCompare(y);
      }
      return asc ? r : -r;
    });
    for (var k = 0; k < rows.length; k++) body.appendChild(rows[k]);
  }
  var tables = document.querySelectorAll('table.sortable');
  for (var t = 0; t < tables.length; t++) {
    (function (table) {
      var heads = table.tHead.rows[0].cells;
      for (var i = 0; i < heads.length; i++) {
        (function (th, i) {
          th.addEventListener('click', function () { sortBy(table, th, i); });
          th.addEventListener('keydown', function (e) {
            if (e.key === 'Enter' || e.key === ' ') { e.preventDefault(); sortBy(table, th, i); }
          });
        })(heads[i], i);
      }
    })(tables[t]);
  }
})();
"""

_E = html.escape


def _num(x: float | None, digits: int = 4) -> str:
    """A number for people: `digits` significant digits, '∞' for infinity, '' for None/NaN."""
    if x is None or math.isnan(x):
        return ""
    if math.isinf(x):
        return "∞" if x > 0 else "-∞"
    return f"{x:.{digits}g}"


def _sort_key(x: float | None) -> str:
    """A number for the table's data-sort (JavaScript parseFloat); '' sorts last."""
    if x is None or math.isnan(x):
        return ""
    if math.isinf(x):
        return "Infinity" if x > 0 else "-Infinity"
    return repr(float(x))


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _severity(d: Defect) -> tuple:
    score = d.score if math.isfinite(d.score) else -math.inf
    return (d.within_tolerance, -score, d.m, d.n)


def _html(v: _View, report: dict[str, Any], small_png: bytes) -> str:
    r = v.result
    s, g = report["summary"], report["grid_summary"]
    defects = sorted(r.defects, key=_severity)
    out: list[str] = []
    w = out.append
    w("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n")
    w("<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n")
    w(f"<title>{_E(r.verdict)} — MLA inspection of {_E(Path(str(r.source)).name)}</title>\n")
    w(f"<style>{_CSS}</style>\n</head>\n<body>\n")
    w(f"<div class=\"banner {_E(r.verdict)}\" id=\"verdict\">{_E(r.verdict)}"
      f"<small>source: {_E(str(r.source))} · {_E(report['created_utc'])} · mlaqc {_E(__version__)}</small></div>\n")
    w("<main>\n<h2>Summary</h2>\n<div class=\"cards\">\n")
    cards = [("lenses", f"{s['lens_count']}", f"{s['rows']} × {s['cols']}"), ("found", f"{s['found']}", ""),
             ("missing", f"{s['missing']}", ""), ("flagged", f"{s['flagged']}", ""),
             ("out of tolerance", f"{s['out_of_tolerance']}", ""),
             ("pitch", f"{_num(g['pitch_px'], 5)} px", ""), ("rotation", f"{_num(g['rotation_deg'], 3)}°", ""),
             ("RMS residual", f"{_num(g['rms_residual_px'], 3)} px", "")]
    for label, value, extra in cards:
        w(f"<div class=\"card\"><b>{_E(value)}</b>{_E(label)}"
          + (f" <span class=\"note\">{_E(extra)}</span>" if extra else "") + "</div>\n")
    w("</div>\n")
    if s["by_error_type"]:
        w("<p>")
        w(" &nbsp; ".join(f"{_swatch(t)}{_E(t)}: {n}" for t, n in s["by_error_type"].items()))
        w("</p>\n")
    for note in r.notes:
        w(f"<p class=\"note\">{_E(str(note))}</p>\n")

    w("<h2>Defect map</h2>\n<div class=\"map\">")
    w(f"<a href=\"{_E(REPORT_FILES['defect_map'])}\"><img id=\"defect-map\" alt=\"defect map\" "
      f"src=\"{_data_uri(small_png)}\"></a></div>\n")
    w(f"<p class=\"note\">Ring colour = error type, thick ring = out of tolerance, cross = missing lens, "
      f"tick = direction. Full resolution: <a href=\"{_E(REPORT_FILES['defect_map'])}\">"
      f"{_E(REPORT_FILES['defect_map'])}</a>; every lens: <a href=\"{_E(REPORT_FILES['csv'])}\">"
      f"{_E(REPORT_FILES['csv'])}</a>.</p>\n")

    w(f"<h2>Flagged lenses ({len(defects)})</h2>\n")
    if defects:
        w("<p class=\"note\">Click a column heading to sort. U(m,n): row m from the top, column n from the "
          "left. Direction: degrees counterclockwise from the image's +x axis.</p>\n")
        w("<table class=\"sortable\" id=\"defects\">\n<thead><tr>")
        for name, kind in (("U(m,n)", "num"), ("type", "str"), ("magnitude", "num"), ("direction °", "num"),
                           ("score", "num"), ("tolerance", "str")):
            w(f"<th tabindex=\"0\" data-type=\"{kind}\" scope=\"col\">{_E(name)}</th>")
        w("</tr></thead>\n<tbody>\n")
        for d in defects:
            row_cls = ' class="out"' if not d.within_tolerance else ""
            w(f"<tr{row_cls}>"
              f"<td data-sort=\"{d.m * 100000 + d.n}\"><a href=\"#U{d.m}-{d.n}\">U({d.m},{d.n})</a></td>"
              f"<td>{_swatch(d.error_type)}{_E(d.error_type)}</td>"
              f"<td class=\"num\" data-sort=\"{_sort_key(d.magnitude)}\">{_E(_num(d.magnitude))} {_E(d.unit)}</td>"
              f"<td class=\"num\" data-sort=\"{_sort_key(d.direction_deg)}\">{_E(_num(d.direction_deg, 3))}</td>"
              f"<td class=\"num\" data-sort=\"{_sort_key(d.score)}\">{_E(_num(d.score, 3))}</td>"
              f"<td>{'within' if d.within_tolerance else 'OUT'}</td></tr>\n")
        w("</tbody>\n</table>\n")
    else:
        w("<p>No lens was flagged.</p>\n")

    if defects:
        shown = defects[:GALLERY_MAX]
        w("<h2>Sub-images of flagged lenses</h2>\n")
        if len(defects) > len(shown):
            w(f"<p class=\"note\" id=\"gallery-cap\">Showing the {len(shown)} most severe of {len(defects)} "
              f"flagged lenses; every lens is in {_E(REPORT_FILES['csv'])}.</p>\n")
        w("<p class=\"note\">Each lens' sub-image beside its reference, enlarged without smoothing, both on "
          "the same grey scale; its indexes beside the median over all lenses.</p>\n<div class=\"gallery\">\n")
        medians = _metric_medians(v)
        for d in shown:
            w(_lens_card(v, d, medians))
        w("</div>\n")

    w("<h2>Grid, tolerances, timings</h2>\n<table>\n")
    rows = [(f"grid {k}", _num(val, 6) if isinstance(val, float) else str(val)) for k, val in g.items()]
    rows += [(f"tolerance {k}", _num(val, 6) if isinstance(val, float) else str(val))
             for k, val in report["tolerances"].items()]
    rows += [(f"time {k}", f"{_num(val, 3)} s" if isinstance(val, (int, float)) else str(val))
             for k, val in report["timings_s"].items()]
    for k, val in rows:
        w(f"<tr><td>{_E(k)}</td><td class=\"num\">{_E(val)}</td></tr>\n")
    w("</table>\n")
    if report.get("config") is not None:
        w("<details><summary>Configuration</summary><pre>")
        w(_E(json.dumps(report["config"], indent=2, ensure_ascii=False)))
        w("</pre></details>\n")
    w(f"</main>\n<script>{_JS}</script>\n</body>\n</html>\n")
    return "".join(out)


def _swatch(error_type: str) -> str:
    r, g, b = error_colour(error_type)
    return f"<span class=\"sw\" style=\"background:#{r:02x}{g:02x}{b:02x}\"></span>"


def _metric_medians(v: _View) -> dict[str, float]:
    """Median of every index over the lenses where it is defined (NaN if nowhere)."""
    out = {}
    for name in METRICS:
        a = np.asarray(v.result.metrics[name], dtype=float)
        a = a[np.isfinite(a)]
        out[name] = float(np.median(a)) if a.size else math.nan
    return out


def _lens_card(v: _View, d: Defect, medians: dict[str, float]) -> str:
    sub = np.asarray(v.subimages[d.m - 1, d.n - 1], dtype=np.float32)
    ref = np.asarray(v.reference_of(d.m, d.n), dtype=np.float32)
    both = np.concatenate([sub[np.isfinite(sub)], ref[np.isfinite(ref)]])
    lo, hi = (float(both.min()), float(both.max())) if both.size else (0.0, 1.0)
    if not hi > lo:
        hi = lo + 1.0
    side = max(sub.shape + ref.shape)
    k = max(1, min(12, math.ceil(128 / max(1, side))))
    imgs = [_data_uri(_encode_png(_grey_tile(a, lo, hi, k))) for a in (sub, ref)]
    values = v.result.metrics.at(d.m, d.n)
    parts = [f"<div class=\"lens\" id=\"U{d.m}-{d.n}\"><h3>{_swatch(d.error_type)}U({d.m},{d.n}) · "
             f"{_E(d.error_type)} · {_E(_num(d.magnitude))} {_E(d.unit)}"
             + (f" @ {_E(_num(d.direction_deg, 3))}°" if d.direction_deg is not None else "")
             + f" · {'within tolerance' if d.within_tolerance else 'OUT of tolerance'}</h3>\n<div class=\"pair\">"]
    for label, uri, a in (("lens", imgs[0], sub), ("reference", imgs[1], ref)):
        parts.append(f"<figure><img alt=\"{label} U({d.m},{d.n})\" width=\"{a.shape[1] * k}\" "
                     f"height=\"{a.shape[0] * k}\" src=\"{uri}\"><figcaption>{label}</figcaption></figure>")
    parts.append(f"</div><div class=\"note\">grey scale {_E(_num(lo, 3))} … {_E(_num(hi, 3))} · "
                 f"score {_E(_num(d.score, 3))}</div>\n")
    alts = [a for a in getattr(d, "alternatives", ()) or () if len(a) == 4]
    if alts:
        readings = "; ".join(f"{t} {_num(mag)} {u}" + (f" @ {_num(a, 3)}°" if a is not None else "")
                             for t, mag, u, a in alts)
        parts.append(f"<div class=\"note\">also fits: {_E(readings)}</div>\n")
    parts.append("<table><tr><th>index</th><th>lens</th><th>median</th><th>unit</th></tr>")
    for name, (unit, meaning) in METRICS.items():
        val = d.indexes.get(name, values.get(name, math.nan))
        parts.append(f"<tr title=\"{_E(meaning)}\"><td>{_E(name)}</td><td class=\"num\">{_E(_num(val))}</td>"
                     f"<td class=\"num\">{_E(_num(medians[name]))}</td><td>{_E(unit)}</td></tr>")
    for name in (k for k in d.indexes if k not in METRICS):
        parts.append(f"<tr><td>{_E(str(name))}</td><td class=\"num\">{_E(_num(d.indexes[name]))}</td>"
                     "<td></td><td></td></tr>")
    parts.append("</table></div>\n")
    return "".join(parts)


def _grey_tile(a: np.ndarray, lo: float, hi: float, k: int) -> np.ndarray:
    """uint8 tile of `a` on the scale lo..hi, enlarged k times by pixel repetition (NaN black)."""
    t = np.nan_to_num((a - lo) * (255.0 / (hi - lo)), nan=0.0, posinf=255.0, neginf=0.0)
    t = np.clip(t + 0.5, 0, 255).astype(np.uint8)
    return np.repeat(np.repeat(t, k, axis=0), k, axis=1)


# ----------------------------------------------------------------------------------------- reading


def load_report(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read and check a report.json (or the folder holding one); InputError in one sentence otherwise."""
    p = Path(path)
    if p.is_dir():
        p = p / REPORT_FILES["json"]
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"report {p} does not exist.") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read report {p}: {getattr(exc, 'strerror', None) or exc}.") from exc

    def _no_nan(const: str) -> Any:
        raise ValueError(f"{const} is not valid JSON")

    try:
        data = json.loads(text, parse_constant=_no_nan)
    except ValueError as exc:
        raise InputError(f"report {p} is not valid JSON ({exc}).") from exc

    def bad(what: str) -> InputError:
        return InputError(f"report {p} is not an mlaqc report: {what}.")

    if not isinstance(data, dict):
        raise bad("it is not a JSON object")
    if data.get("format") != REPORT_FORMAT:
        raise bad(f"its format is {data.get('format')!r}, not {REPORT_FORMAT!r}")
    ver = data.get("format_version")
    if not isinstance(ver, int) or isinstance(ver, bool) or not 1 <= ver <= REPORT_FORMAT_VERSION:
        raise bad(f"format_version {ver!r} is not one this mlaqc ({__version__}) reads")
    if data.get("verdict") not in ("PASS", "FAIL"):
        raise bad(f"verdict {data.get('verdict')!r} is not PASS or FAIL")
    if not isinstance(data.get("source"), str):
        raise bad("'source' is missing")
    summary = data.get("summary")
    if not isinstance(summary, dict):
        raise bad("'summary' is missing")
    rows, cols = summary.get("rows"), summary.get("cols")
    if not (_is_int(rows) and _is_int(cols) and rows > 0 and cols > 0):
        raise bad("summary rows/cols are not positive integers")
    for key in ("grid_summary", "tolerances", "timings_s"):
        if not isinstance(data.get(key), dict):
            raise bad(f"'{key}' is missing")
    defects = data.get("defects")
    if not isinstance(defects, list):
        raise bad("'defects' is not a list")
    for i, d in enumerate(defects):
        if not isinstance(d, dict):
            raise bad(f"defect {i} is not an object")
        m, n = d.get("row"), d.get("col")
        if not (_is_int(m) and _is_int(n) and 1 <= m <= rows and 1 <= n <= cols):
            raise bad(f"defect {i} has lens ({m!r}, {n!r}) outside the {rows} x {cols} grid")
        if not isinstance(d.get("error_type"), str) or not isinstance(d.get("unit"), str):
            raise bad(f"defect U({m},{n}) has no error_type or unit")
        for key in ("magnitude", "score", "direction_deg"):
            val = d.get(key)
            if val is not None and not (isinstance(val, (int, float)) and not isinstance(val, bool)):
                raise bad(f"defect U({m},{n}) has a non-numeric {key}")
        if not isinstance(d.get("within_tolerance"), bool):
            raise bad(f"defect U({m},{n}) has no within_tolerance flag")
        if not isinstance(d.get("indexes", {}), dict):
            raise bad(f"defect U({m},{n}) has indexes that are not an object")
    if summary.get("flagged", len(defects)) != len(defects):
        raise bad(f"its summary counts {summary.get('flagged')} flagged lenses but lists {len(defects)}")
    return data


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)
