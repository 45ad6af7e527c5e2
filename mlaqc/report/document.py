"""report.json and lenses.csv: building them from an InspectionResult, and reading a report.json back.

Conventions shared by every file (DESIGN.md §2):
- lens U(m,n) is row m (1 = top), column n (1 = left); array element [m-1, n-1]; on a hex array even rows
  (m = 2, 4, ...) sit half a pitch right and rows are pitch*sqrt(3)/2 apart (mlaqc.optics.lattice.CONVENTIONS;
  report.json's conventions.lattice, and lenses.csv's design_* columns give every lens' design centre);
- pixel coordinates: (0, 0) is the centre of the top-left pixel, x to the right, y down;
- directions are degrees counterclockwise from the image's +x axis towards its top;
- JSON has no NaN (null instead); the CSV writes NaN as an empty field.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc import __version__
from mlaqc.errors import InputError
from mlaqc.inspection.measure import MEASUREMENTS
from mlaqc.inspection.throughfocus_results import TF_MEASUREMENTS
from mlaqc.inspection.results import METRICS, InspectionResult
from mlaqc.optics.lattice import CONVENTIONS
from mlaqc.report.maps import _type_order
from mlaqc.report.numtext import format_column, format_rows, format_rows_utf8
from mlaqc.report.view import View

REPORT_FORMAT = "mlaqc-report"
REPORT_FORMAT_VERSION = 1


#: Key -> file name of every file `write_report` writes.
REPORT_FILES: dict[str, str] = {
    "json": "report.json",
    "csv": "lenses.csv",
    "defect_map": "defect_map.png",
    "defect_map_small": "defect_map_small.png",
    "lens_maps": "lens_maps.png",
    "html": "report.html",
}

GALLERY_MAX = 200
CSV_COLUMNS: tuple[str, ...] = (
    "row", "col", "x_px", "y_px", "grid_x_px", "grid_y_px", "flagged", "error_type", *METRICS, *MEASUREMENTS,
    *TF_MEASUREMENTS)
#: Columns a hex array's lenses.csv adds after CSV_COLUMNS: the lens' design centre in pitches from U(1,1)'s
#: (u right, v down: the offset convention spelled out) and in µm from the array's centre (the MLA frame;
#: empty when the report is written without the config's pitch).
HEX_CSV_COLUMNS: tuple[str, ...] = ("design_u", "design_v", "design_x_um", "design_y_um")


def build_report_dict(result: InspectionResult, *, config_dict: dict | None = None,
                      _view: View | None = None) -> dict[str, Any]:
    """The content of report.json (plain JSON types, no NaN)."""
    v = _view or View(result)
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
        "not_inspected": int(getattr(result, "not_inspected", 0)),
        "below_reportable": int(getattr(result, "below_reportable", 0)),
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
            "lens": (CONVENTIONS["hex"] if v.hex else "U(m,n): row m from 1 at the top, column n from 1 at the left"),
            # the lattice U(m,n) indexes (mlaqc.optics.lattice): packing, shape, row step and its convention
            "lattice": v.lattice.to_json_dict(),
            "pixel": "(0, 0) is the centre of the top-left pixel; x right, y down",
            "direction_deg": "counterclockwise from the image's +x axis towards its top",
        },
        "image_size_px": {"width": int(v.image.shape[1]), "height": int(v.image.shape[0])},
        "summary": summary,
        "grid_summary": grid_summary,
        "grid": grid_json,
        "tolerances": dict(result.tolerances),
        # the lens-boundary model the frame was inspected with (mla.boundaries): 'sag-intersection' (physical,
        # types pitch and decenter apart) or 'grid' (idealised: both reported as 'position'); null if not known
        "lens_boundaries": getattr(result, "lens_boundaries", "") or None,
        # what a PASS means: per error type the smallest magnitude this frame flags (inner lenses, at the
        # configured detect_sigma and minimum reportable size); null where nothing rendered is detectable
        "detection_limit": dict(getattr(result, "detection_limit", {}) or {}),
        "timings_s": dict(result.timings_s),
        "notes": list(result.notes),
        "metrics": {k: {"unit": u, "meaning": m} for k, (u, m) in METRICS.items()},
        "files": dict(REPORT_FILES),
        "config": config_dict,
        "defects": [d.to_json_dict() for d in result.defects],
        # every lens' optical-centre displacement and focal-length error with 1-sigma (mlaqc.inspection.measure)
        "measurements": _measurements_json(v),
        # the through-focus pinhole pairs' per-lens readings (mlaqc.inspection.throughfocus), null without them
        "through_focus": _through_focus_json(v),
        # the array's placement in the camera: the error map's global fields, each {value, sigma}
        # (mlaqc.inspection.assembly), with what they assume; null when not read
        "assembly": result.assembly.to_json_dict() if getattr(result, "assembly", None) is not None else None,
    }
    return _jsonable(report)


def _float_attr(obj: Any, name: str, default: float | None) -> float | None:
    val = getattr(obj, name, None)
    try:
        return float(val) if val is not None else default
    except (TypeError, ValueError):
        return default


class _NumberRows(list):
    """Rows (lists) of numbers and nulls that carry their own JSON text, each row "[a, b, ...]" as `_dumps`
    writes it (a measurement map: formatted once, by the compiled formatter, not walked and encoded again)."""

    def __init__(self, rows: list, rows_json: list[str]):
        super().__init__(rows)
        self.rows_json = rows_json


class _Records(list):
    """Records (dicts with the same keys) of plain JSON values, with those values column by column
    (`_record_columns`: found once, by `_jsonable`, used again by `_dumps`)."""

    def __init__(self, records: list, columns: tuple[tuple[str, ...], list[list]], decimals: int | None = None):
        super().__init__(records)
        self.columns = columns
        self.record_decimals = decimals  # every float is round(v, decimals), if given


_PLAIN = frozenset({str, int, bool, type(None)})
_INF, _NINF = math.inf, -math.inf


def _jsonable(obj: Any) -> Any:
    """Plain JSON types: numpy scalars and arrays converted, NaN/inf -> None, paths -> str."""
    t = type(obj)  # exact-type fast paths first: a grid brings ~10^5 values
    if t in _PLAIN:
        return obj
    if t is float:
        return obj if math.isfinite(obj) else None
    # (a finite float is kept inline too: a grid's lenses and the measurement maps are ~10^5 of them)
    if t is dict:
        return {k if type(k) is str else str(k): v if (tv := type(v)) in _PLAIN or (tv is float and _INF > v > _NINF)
                else _jsonable(v) for k, v in obj.items()}
    if t is not list and isinstance(obj, list) and hasattr(obj, "record_columns"):
        # records that carry their columns (a grid's lenses)
        return _Records(obj, obj.record_columns, getattr(obj, "record_decimals", None))
    if t is list:
        columns = _record_columns(obj, finite=True)
        if columns is not None:  # records of plain JSON values already (a grid's lenses): nothing to convert
            return _Records(obj, columns)
        return [v if (tv := type(v)) in _PLAIN or (tv is float and _INF > v > _NINF) else _jsonable(v) for v in obj]
    if t is _NumberRows or t is _Records:
        return obj  # JSON values already, with their text
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
    parts: list[str] = []
    _dump_parts(obj, level, parts)
    return "".join(parts)


def dumps_utf8(obj: Any) -> bytes:
    """`_dumps(obj)` as UTF-8 bytes, its pieces encoded apart: a 2048² frame's record lines stay ASCII and
    are copied once, never widened into a string holding the few non-ASCII units (µm) nor concatenated level
    by level (a 40 Mpx frame's 74 MB report: 1.2-2.0 s of copies on this host, 0.5 s now)."""
    parts: list[str] = []
    _dump_parts(obj, 0, parts)
    return b"".join(p.encode("utf-8") for p in parts)


def _dump_parts(obj: Any, level: int, out: list[str]) -> None:
    """Append `_dumps(obj, level)`'s text to `out` in pieces, each large list's lines joined once."""
    if isinstance(obj, dict):
        if not obj:
            out.append("{}")
            return
        pad, sep = "  " * (level + 1), "{\n"
        for k, v in obj.items():
            out.append(f"{sep}{pad}{json.dumps(k, ensure_ascii=False)}: ")
            _dump_parts(v, level + 1, out)
            sep = ",\n"
        out.append("\n" + "  " * level + "}" + ("\n" if level == 0 else ""))
        return
    if type(obj) is _NumberRows:
        out.append(_lines(obj.rows_json, level))
        return
    if not isinstance(obj, list):
        out.append(_ENCODER.encode(obj))
        return
    types = set(map(type, obj))  # (a type at a time: the measurement maps hold ~10^5 values)
    if not any(issubclass(t, (dict, list)) for t in types):
        out.append(_ENCODER.encode(obj))
        return
    if types == {list} and all(set(map(type, x)) <= _SCALAR_TYPES for x in obj):
        # rows of numbers (a measurement map): one row per line, the whole map encoded at once and cut
        # between its rows (no number's encoding holds a bracket)
        out.append(_lines(["[" + r + "]" for r in _ENCODER.encode(obj)[2:-2].split("], [")], level))
        return
    one_line = _flat_records(obj)  # e.g. the grid's lenses
    if one_line is None and all(isinstance(x, dict) and all(not isinstance(y, (dict, list)) for y in x.values())
                                for x in obj):
        one_line = [_ENCODER.encode(x) for x in obj]
    if one_line is not None and max(map(len, one_line)) <= 400:
        out.append(_lines(one_line, level))
        return
    pad, sep = "  " * (level + 1), "[\n"
    for x in obj:
        out.append(sep + pad)
        _dump_parts(x, level + 1, out)
        sep = ",\n"
    out.append("\n" + "  " * level + "]")


def _lines(lines: list[str], level: int) -> str:
    """A JSON list written one item (already encoded) per line at `level`'s indent."""
    pad = "  " * (level + 1)
    return "[\n" + (pad + (",\n" + pad).join(lines) if lines else "") + "\n" + "  " * level + "]"


_SCALAR_TYPES = frozenset({int, float, bool, type(None)})


def _record_columns(obj: list, finite: bool = False) -> tuple[tuple[str, ...], list[list]] | None:
    """(keys, one list of values per key) of a list of dicts that share their string keys (in order) and
    hold numbers, booleans and nulls only (and with `finite`, no NaN or infinity); None otherwise."""
    if not obj or type(obj[0]) is not dict:
        return None
    keys = tuple(obj[0])
    if not keys or not all(type(k) is str for k in keys) or not all(
            type(x) is dict and len(x) == len(keys) and tuple(x) == keys for x in obj):
        return None
    columns = []
    for k in keys:
        column = [x[k] for x in obj]
        types = set(map(type, column))
        if not types <= _SCALAR_TYPES:
            return None
        if finite and float in types and not all(map(math.isfinite, (v for v in column if type(v) is float))):
            return None
        columns.append(column)
    return keys, columns


def _flat_records(obj: list) -> list[str] | None:
    """`_ENCODER.encode(x)` of every record of a list of dicts that share their keys (in order) and hold
    numbers, booleans and nulls only, one field at a time (a record at a time cost 0.1 s for a grid's
    10,404 lenses); None for any other list (and the records are then encoded one by one)."""
    found = obj.columns if type(obj) is _Records else _record_columns(obj)
    if found is None:
        return None
    keys, columns = found
    head = ["{" + json.dumps(keys[0], ensure_ascii=False) + ": "]
    head += [", " + json.dumps(k, ensure_ascii=False) + ": " for k in keys[1:]]
    decimals = getattr(obj, "record_decimals", None)
    if decimals is not None and len(obj) > 100:
        compiled = _rounded_records(head, columns, decimals)
        if compiled is not None:
            return compiled
    # a list's encoding is its values' encodings joined by ", " (no scalar's encoding holds one)
    tokens = [_ENCODER.encode(column)[1:-1].split(", ") for column in columns]
    template = "".join(h.replace("%", "%%") + "%s" for h in head) + "}\0"
    flat = [t for row in zip(*tokens) for t in row]
    return (template * len(obj) % tuple(flat)).split("\0")[:-1]


def _rounded_records(head: list[str], columns: list[list], decimals: int) -> list[str] | None:
    """The records' JSON lines by the compiled formatter, for records whose floats are round(v, decimals)
    (a grid's lenses: JSON writes repr of each, "%.{decimals}r"), ints and booleans; None for other columns.
    The keys' text goes in as constant text cells between the values."""
    table = [*head, "}", "false", "true"]
    cells, formats = [], []
    for k, column in enumerate(columns):
        kinds = set(map(type, column))
        if kinds <= {bool}:
            values, fmt = np.array(column, dtype=np.float64) + (len(head) + 1), "%s"
        elif kinds <= {int}:
            values, fmt = np.array(column, dtype=np.float64), "%d"
            if np.abs(values).max(initial=0) >= 2 ** 53:
                return None
        elif kinds <= {float, type(None)}:
            values, fmt = np.array(column, dtype=np.float64), f"%.{decimals}r"
        else:
            return None
        cells += [np.full(len(column), float(k)), values]
        formats += ["%s", fmt]
    cells.append(np.full(len(columns[0]), float(len(head))))
    formats.append("%s")
    text = format_rows(np.column_stack(cells), formats, table, col_sep="", row_sep="\0", parallel=False)
    return text.split("\0")[:-1]


def lenses_csv(view: View | InspectionResult, pitch_um: float | None = None) -> str:
    """lenses.csv: one row per lens, U(1,1), U(1,2), ... U(rows,cols); NaN written as empty. Every number is
    written as Python's %-format writes it (mlaqc.report.numtext, compiled: 10,404 lenses in ~15 ms). A hex
    array's file adds HEX_CSV_COLUMNS (design centres; in µm with `pitch_um`, the config's mla.pitch_um)."""
    return lenses_csv_utf8(view, pitch_um).decode("utf-8")


def lenses_csv_utf8(view: View | InspectionResult, pitch_um: float | None = None) -> bytes:
    """lenses.csv's bytes (`lenses_csv`), as the compiled formatter writes them: no copy through a string."""
    v = view if isinstance(view, View) else View(view)
    return _csv_bytes(v, _design_columns(v, pitch_um) if v.hex else None)


_DESIGN_FORMATS = ("%.6g", "%.6g", "%.4f", "%.4f")  # HEX_CSV_COLUMNS'


def _csv_bytes(v: View, design: np.ndarray | None = None) -> bytes:
    """lenses.csv's common columns (CSV_COLUMNS) for every lens, then the `design` columns (HEX_CSV_COLUMNS,
    (lenses, 4): `_design_columns`) if given, written in the same pass."""
    m, n = np.meshgrid(np.arange(1, v.rows + 1), np.arange(1, v.cols + 1), indexing="ij")
    flagged = v.flagged.ravel()
    types = np.where(flagged, v.error_type.ravel(), "")
    table, type_index = np.unique(types, return_inverse=True)
    table = table.tolist()
    if "" in table:  # unflagged lenses: an empty field (the empty string sorts first)
        type_index = type_index - 1
        table = table[1:]
    if any(c in t for t in table for c in ',"\r\n') or any(c in name for name in CSV_COLUMNS for c in ',"\r\n'):
        text = _quoted_csv(v)
        return (text if design is None else _with_design_columns(text, design)).encode("utf-8")
    columns = [m.ravel(), n.ravel(), *(np.ravel(a) for a in (v.mx, v.my, v.gx, v.gy)), flagged, type_index,
               *(np.ravel(np.asarray(v.result.metrics[k], dtype=float)) for k in METRICS),
               *(np.ravel(_measured(v, k)) for k in (*MEASUREMENTS, *TF_MEASUREMENTS))]
    formats = ["%d", "%d", *["%.3f"] * 4, "%d", "%s", *["%.6g"] * len(METRICS),
               *["%.5g"] * (len(MEASUREMENTS) + len(TF_MEASUREMENTS))]
    names = CSV_COLUMNS
    if design is not None:
        columns, formats, names = columns + list(design.T), formats + list(_DESIGN_FORMATS), names + HEX_CSV_COLUMNS
    table_text = format_rows_utf8(np.column_stack(columns).astype(np.float64), formats, table, parallel=False)
    return b"".join([(",".join(names) + "\n").encode("utf-8"), table_text])  # (here: the pool deflates the PNGs)


def _design_columns(v: View, pitch_um: float | None) -> np.ndarray:
    """Every lens' HEX_CSV_COLUMNS values (lenses, 4): its design centre in pitches from U(1,1)'s, and in µm
    from the array's centre with `pitch_um` (NaN without)."""
    r, c = np.divmod(np.arange(v.rows * v.cols), v.cols)
    u, w = v.lattice.uv(r, c)
    known = pitch_um is not None and math.isfinite(pitch_um) and pitch_um > 0
    x, y = v.lattice.position(r, c) if known else (np.full(u.shape, np.nan),) * 2
    scale = float(pitch_um) if known else 1.0
    return np.column_stack([u, w, x * scale, y * scale])


def _with_design_columns(text: str, design: np.ndarray) -> str:
    """`text` (a quoted lenses.csv, fields may hold newlines) with HEX_CSV_COLUMNS appended to its header
    and every lens' row, through the csv module."""
    extra = format_rows(design, list(_DESIGN_FORMATS), parallel=False).split("\n")[:-1]
    head, *rows = list(csv.reader(io.StringIO(text)))
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(
        [head + list(HEX_CSV_COLUMNS)] + [row + e.split(",") for row, e in zip(rows, extra)])
    return buf.getvalue()


def _quoted_csv(v: View) -> str:
    """lenses.csv through the csv module, for the rare table whose text needs quoting."""
    m, n = np.meshgrid(np.arange(1, v.rows + 1), np.arange(1, v.cols + 1), indexing="ij")
    columns: list[list[str]] = [
        [str(i) for i in m.ravel().tolist()],
        [str(i) for i in n.ravel().tolist()],
        *(_fmt_column(a, "%.3f") for a in (v.mx, v.my, v.gx, v.gy)),
        ["1" if f else "0" for f in v.flagged.ravel().tolist()],
        [t if f else "" for t, f in zip(v.error_type.ravel().tolist(), v.flagged.ravel().tolist())],
        *(_fmt_column(np.asarray(v.result.metrics[k], dtype=float), "%.6g") for k in METRICS),
        *(_fmt_column(_measured(v, k), "%.5g") for k in (*MEASUREMENTS, *TF_MEASUREMENTS)),
    ]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    writer.writerows(zip(*columns))
    return buf.getvalue()


def _measured(v: View, name: str) -> np.ndarray:
    """A per-lens measurement map (white frame, or `tf_` through-focus), NaN everywhere when the result
    carries none."""
    if name in TF_MEASUREMENTS:
        tf = getattr(v.result, "through_focus", None)
        return (np.asarray(getattr(tf, TF_MEASUREMENTS[name][0]), dtype=float) if tf is not None
                else np.full((v.rows, v.cols), np.nan))
    m = getattr(v.result, "measurements", None)
    return np.asarray(m[name], dtype=float) if m is not None else np.full((v.rows, v.cols), np.nan)


def _through_focus_json(v: View) -> dict[str, Any] | None:
    """report.json's through-focus readings: meanings, the pairs' summary, and each map as rows."""
    tf = getattr(v.result, "through_focus", None)
    if tf is None:
        return None
    from mlaqc.inspection.combine import SOURCE_KEY

    return {"meaning": {k: {"unit": u, "meaning": t} for k, (_, u, t) in TF_MEASUREMENTS.items()},
            "summary": tf.summary() | {"flags_read_by_pairs": sum(1 for d in v.result.defects if SOURCE_KEY in d.indexes)},
            "lenses": {k: _rows_5g(_measured(v, k)) for k in TF_MEASUREMENTS}}


def _measurements_json(v: View) -> dict[str, Any] | None:
    """report.json's per-lens measurements: units and meanings, array-wide summary, and each map as
    rows of values (5 significant digits; null where not measured)."""
    m = getattr(v.result, "measurements", None)
    if m is None:
        return None
    maps = {k: _rows_5g(np.asarray(m[k], float)) for k in MEASUREMENTS}
    return {"meaning": {k: {"unit": u, "meaning": t} for k, (u, t) in MEASUREMENTS.items()},
            "summary": m.summary(), "lenses": maps}


def _rows_5g(a: np.ndarray) -> list:
    """`a` as nested lists (rows) of its values at 5 significant digits, float(f"{x:.5g}"), None where not
    finite; a 2-D map as `_NumberRows`, written once by the compiled formatter as JSON and read back."""
    if a.ndim != 2 or a.size == 0:
        return [[float(f"{x:.5g}") if math.isfinite(x) else None for x in row] for row in np.atleast_2d(a).tolist()]
    lines = format_rows(a, ["%.5j"] * a.shape[1], row_sep="\n", parallel=False).split("\n")[:-1]
    rows = json.loads("[[" + "],[".join(lines) + "]]")
    return _NumberRows(rows, ["[" + line.replace(",", ", ") + "]" for line in lines])


def _fmt_column(arr: np.ndarray, fmt: str) -> list[str]:
    """Each value in printf format `fmt` (e.g. "%.6g"), non-finite ones empty (compiled, mlaqc.report.numtext)."""
    return format_column(arr, fmt)


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
