"""The calibrated microlens grid: `Grid` (the global model and every lens' own measurement), the model's
map from lattice to pixels (`_model_xy`) and the grid's file, grid.json (`Grid.save`, `load_grid`).

What the calibration (mlaqc.inspection.calibrate) finds, kept apart from how it is found: the later stages
(sub-images, through-focus, assembly, the report) read a Grid, computed from a white frame or loaded from
its file, and its reading checks every field so a damaged or foreign file is refused by name.

The model: a projective map of the design's lattice coordinates, in pitches from U(1,1) (`Lattice.uv`:
square (n-1, m-1), hex (n-1 + [m even]/2, (m-1) sqrt(3)/2)), so pitch, rotation and shear mean the same
for both packings (a perfect hex array has shear 0), plus a radial term about the frame centre.

Conventions: pixel (0, 0) is the centre of the top-left pixel, x to the right, y down. Lens U(m,n) is row m
from the top, column n from the left (1-based), arrays index [m-1, n-1]. Rotation is counterclockwise as
the image is displayed (as `ErrorMap`'s mla_rotation_deg).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc.atomic import write_json_atomic
from mlaqc.errors import InputError
from mlaqc.optics.lattice import CONVENTIONS, Lattice, packing_of

FORMAT = "mlaqc-grid"
VERSION = 1


# ------------------------------------------------------------------------------------------------ Grid


@dataclass(frozen=True, eq=False)
class Grid:
    """The calibrated microlens grid: the global model and every lens' own measurement.

    Per-lens arrays have shape (rows, cols); [m-1, n-1] is lens U(m,n). `measured_*` and the per-lens
    measurements are NaN where `missing` (dark/dim, or mostly outside the frame). `grid_*` is the global
    model's prediction for every lens. The model maps design coordinates (u, v) (`Lattice.uv` of
    `packing`, in pitches from U(1,1): square (n-1, m-1), hex (n-1 + 0.5 [m even], (m-1) sqrt(3)/2)) to pixels:
    (x', y') = projective(homography, u, v), then a radial term about `radial_centre_px`:
    p = c + (p' - c) * (1 + radial_k * |p' - c|^2 / radial_scale_px^2).
    """

    rows: int
    cols: int
    pitch_px: tuple[float, float]  # (x, y) lattice spacing at the array centre
    rotation_deg: float  # lattice x axis, counterclockwise as displayed
    shear_deg: float  # deviation of the angle between the lattice axes from 90 degrees
    origin_px: tuple[float, float]  # predicted centre (x, y) of U(1,1)
    homography: np.ndarray  # (3, 3)
    radial_k: float
    radial_centre_px: tuple[float, float]
    radial_scale_px: float
    edge_width_px: float  # logistic scale of the sub-image rim (global)
    image_shape: tuple[int, int]  # (height, width) of the calibrated frame
    measured_x_px: np.ndarray
    measured_y_px: np.ndarray
    grid_x_px: np.ndarray
    grid_y_px: np.ndarray
    residual_px: np.ndarray  # |measured - grid|
    flux: np.ndarray  # fitted disc amplitude * area (normalized signal * px^2)
    radius_px: np.ndarray  # fitted sub-image radius (size)
    missing: np.ndarray  # bool: predicted by the grid, not found (dark, dim or out of frame)
    clipped: np.ndarray  # bool: part of the sub-image lies outside the frame
    rms_residual_px: float  # over the lenses used in the fit
    packing: str = "square"  # the lattice U(m,n) indexes (mlaqc.optics.lattice)
    # each edge group's common offset from the model, taken off its measured centres by the calibration:
    # (group name, lenses it was read on, dx px, dy px)
    edge_offsets: tuple[tuple[str, int, float, float], ...] = ()

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def residual_x_px(self) -> np.ndarray:
        """measured - grid, x (NaN where missing)."""
        return self.measured_x_px - self.grid_x_px

    @property
    def residual_y_px(self) -> np.ndarray:
        """measured - grid, y (NaN where missing)."""
        return self.measured_y_px - self.grid_y_px

    def uncorrected_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """The measured centres as the disc fit read them, before each edge line's common offset was taken
        off (`edge_offsets`): what the shipped assembly calibrations were built from."""
        from mlaqc.inspection.lens_classes import edge_lines

        x, y = np.array(self.measured_x_px, float), np.array(self.measured_y_px, float)
        lines = {e.name: e.line for e in edge_lines(self.shape, self.packing)}
        for name, _, dx, dy in self.edge_offsets:  # (names checked when the grid was built or read)
            x[lines[name]] += dx  # (the offset along the side is 0)
            y[lines[name]] += dy
        return x, y

    @property
    def lenses_found(self) -> int:
        return int(np.count_nonzero(~self.missing))

    @property
    def lenses_missing(self) -> int:
        return int(np.count_nonzero(self.missing))

    def predict(self, m, n) -> tuple[np.ndarray, np.ndarray]:
        """Model centre (x, y) in pixels of lens U(m,n) (1-based; arrays broadcast; may extrapolate; hex:
        integer m, whose parity shifts the row)."""
        if self.packing == "square":
            u = np.asarray(n, dtype=np.float64) - 1.0
            v = np.asarray(m, dtype=np.float64) - 1.0
        else:
            u, v = Lattice(self.packing, self.rows, self.cols).uv(np.asarray(m) - 1, np.asarray(n) - 1)
        return _model_xy(self.homography, self.radial_k, self.radial_centre_px, self.radial_scale_px, u, v)

    # ------------------------------------------------------------------ JSON

    def to_json_dict(self) -> dict[str, Any]:
        """The grid.json form: model terms and every lens' measured and predicted centre (null = NaN)."""
        # whole columns as Python values first (indexing numpy scalars lens by lens cost 0.1 s per grid)
        m_all, n_all = np.divmod(np.arange(self.rows * self.cols), self.cols)
        floats = [_rounded_column(getattr(self, key)) for key in _LENS_FLOATS]
        flags = [np.asarray(getattr(self, key), dtype=bool).ravel().tolist() for key in ("missing", "clipped")]
        columns = [(m_all + 1).tolist(), (n_all + 1).tolist(), *floats, *flags]
        lenses = _LensRecords([{"m": m, "n": n, "measured_x_px": mx, "measured_y_px": my, "grid_x_px": gx,
                                "grid_y_px": gy, "residual_px": res, "flux": flux, "radius_px": rad,
                                "missing": miss, "clipped": clip}
                               for m, n, mx, my, gx, gy, res, flux, rad, miss, clip in zip(*columns)])
        lenses.record_columns = (_LENS_KEYS, columns)
        return {
            "format": FORMAT,
            "version": VERSION,
            "conventions": "pixel (0,0) = centre of the top-left pixel, x right, y down; U(m,n): row m from "
                           "the top, column n from the left, 1-based; rotation counterclockwise as displayed"
                           + ("" if self.packing == "square" else f"; {CONVENTIONS[self.packing]}"),
            "packing": self.packing,
            "image": {"height_px": self.image_shape[0], "width_px": self.image_shape[1]},
            "shape": {"rows": self.rows, "cols": self.cols},
            "pitch_px": {"x": self.pitch_px[0], "y": self.pitch_px[1]},
            "rotation_deg": self.rotation_deg,
            "shear_deg": self.shear_deg,
            "origin_px": {"x": self.origin_px[0], "y": self.origin_px[1]},
            "model": {
                "type": "projective+radial",
                "lattice": _MODEL_LATTICE[self.packing],
                "homography": [[float(v) for v in row] for row in self.homography],
                "radial": "p = c + (p' - c) * (1 + k * |p' - c|^2 / scale^2)",
                "radial_k": self.radial_k,
                "radial_centre_px": {"x": self.radial_centre_px[0], "y": self.radial_centre_px[1]},
                "radial_scale_px": self.radial_scale_px,
                "edge_width_px": self.edge_width_px,
                "edge_offsets_px": [{"group": name, "lenses": n, "x": dx, "y": dy}
                                    for name, n, dx, dy in self.edge_offsets],
            },
            "summary": {"lenses_found": self.lenses_found, "lenses_missing": self.lenses_missing,
                        "lenses_clipped": int(np.count_nonzero(self.clipped)),
                        "rms_residual_px": self.rms_residual_px},
            "lenses": lenses,
        }

    @classmethod
    def from_json_dict(cls, data: Any, source: str = "grid") -> Grid:
        """Rebuild a Grid from its JSON dict; InputError naming the problem."""
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise InputError(f"{source}: not an mlaqc grid (missing \"format\": \"{FORMAT}\")")
        if data.get("version") != VERSION:
            raise InputError(f"{source}: grid version {data.get('version')!r} is not supported (expected {VERSION})")
        try:
            rows, cols = _pos_int(data["shape"]["rows"]), _pos_int(data["shape"]["cols"])
            height, width = _pos_int(data["image"]["height_px"]), _pos_int(data["image"]["width_px"])
            model = data["model"]
            hom = np.array(model["homography"], dtype=np.float64)
            if hom.shape != (3, 3):
                raise ValueError("homography is not 3x3")
            head = {
                "pitch_px": (_num(data["pitch_px"]["x"]), _num(data["pitch_px"]["y"])),
                "rotation_deg": _num(data["rotation_deg"]),
                "shear_deg": _num(data["shear_deg"]),
                "origin_px": (_num(data["origin_px"]["x"]), _num(data["origin_px"]["y"])),
                "radial_k": _num(model["radial_k"]),
                "radial_centre_px": (_num(model["radial_centre_px"]["x"]), _num(model["radial_centre_px"]["y"])),
                "radial_scale_px": _num(model["radial_scale_px"]),
                "edge_width_px": _num(model["edge_width_px"]),
                "rms_residual_px": _num(data["summary"]["rms_residual_px"], allow_none=True),
            }
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{source}: grid header is incomplete or malformed ({_describe(exc)})") from None
        packing = packing_of(data, source)
        if not np.all(np.isfinite(hom)) or head["radial_scale_px"] <= 0:
            raise InputError(f"{source}: grid model terms must be finite numbers with a positive radial scale")
        lenses = data.get("lenses")
        if not isinstance(lenses, list) or len(lenses) != rows * cols:
            raise InputError(f"{source}: \"lenses\" must list all {rows}x{cols} = {rows * cols} lenses")
        arrays = {k: np.full((rows, cols), np.nan) for k in _LENS_FLOATS}
        flags = {k: np.zeros((rows, cols), bool) for k in ("missing", "clipped")}
        seen = np.zeros((rows, cols), bool)
        # a well-formed file is read column by column; anything the checks below would refuse is left to
        # the lens-by-lens reading, which names the first problem
        if _read_lens_columns(lenses, rows, cols, arrays, flags):
            lenses = []
        else:
            arrays = {k: np.full((rows, cols), np.nan) for k in _LENS_FLOATS}
            flags = {k: np.zeros((rows, cols), bool) for k in ("missing", "clipped")}
        for i, entry in enumerate(lenses):
            if not isinstance(entry, dict):
                raise InputError(f"{source}: lenses[{i}] must be an object")
            m, n = entry.get("m"), entry.get("n")
            if not (isinstance(m, int) and isinstance(n, int) and 1 <= m <= rows and 1 <= n <= cols):
                raise InputError(f"{source}: lenses[{i}] needs integer m in 1..{rows} and n in 1..{cols}, got m={m!r}, n={n!r}")
            if seen[m - 1, n - 1]:
                raise InputError(f"{source}: lens U({m},{n}) is listed twice")
            seen[m - 1, n - 1] = True
            for key in _LENS_FLOATS:
                v = entry.get(key)
                if v is None:
                    continue
                if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)):
                    raise InputError(f"{source}: lens U({m},{n}) field {key!r} must be a number or null, got {v!r}")
                arrays[key][m - 1, n - 1] = float(v)
            for key in flags:
                v = entry.get(key, False)
                if not isinstance(v, bool):
                    raise InputError(f"{source}: lens U({m},{n}) field {key!r} must be true or false")
                flags[key][m - 1, n - 1] = v
        if np.isnan(arrays["grid_x_px"]).any() or np.isnan(arrays["grid_y_px"]).any():
            m, n = (int(v) + 1 for v in np.argwhere(np.isnan(arrays["grid_x_px"]) | np.isnan(arrays["grid_y_px"]))[0])
            raise InputError(f"{source}: lens U({m},{n}) has no grid (predicted) centre")
        lost = ~flags["missing"] & (np.isnan(arrays["measured_x_px"]) | np.isnan(arrays["measured_y_px"]))
        if lost.any():
            m, n = (int(v) + 1 for v in np.argwhere(lost)[0])
            raise InputError(f"{source}: lens U({m},{n}) is not marked missing but has no measured centre")
        return cls(rows=rows, cols=cols, homography=hom, image_shape=(height, width), **head, **arrays, **flags,
                   packing=packing,
                   edge_offsets=_edge_offsets(model.get("edge_offsets_px", []), source, (rows, cols), packing))

    def save(self, path: str | Path) -> None:
        """Write grid.json atomically (a reader never sees half a file)."""
        write_json_atomic(path, self.to_json_dict())


def _edge_offsets(entries: Any, source: str, shape: tuple[int, int], packing: str) -> tuple[tuple[str, int, float, float], ...]:
    """The model's "edge_offsets_px" (absent in grids written before them: none): each an edge group of this
    array's (`edge_lines`), once, measured on at most its lenses, its offset along the normal to its side only."""
    from mlaqc.inspection.lens_classes import edge_lines

    lines = {e.name: e for e in edge_lines(shape, packing) if e.name}
    try:
        out = tuple((e["group"], _pos_int(e["lenses"]), _num(e["x"]), _num(e["y"])) for e in entries)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{source}: model.edge_offsets_px must list objects with group, lenses, x and y "
                         f"({_describe(exc)})") from None
    seen = set()
    for name, lenses, dx, dy in out:
        if not isinstance(name, str) or name not in lines or name in seen:
            raise InputError(f"{source}: model.edge_offsets_px names {name!r}, which is not an edge group of a "
                             f"{shape[0]}x{shape[1]} {packing} array or is listed twice")
        size = int(lines[name].group.sum())
        if lenses > size:
            raise InputError(f"{source}: model.edge_offsets_px group {name!r} counts {lenses} lenses; it has "
                             f"{size} in a {shape[0]}x{shape[1]} {packing} array")
        if (dy if lines[name].axis == 0 else dx) != 0:
            raise InputError(f"{source}: model.edge_offsets_px group {name!r} has an offset along its side; "
                             "only the normal to the side is read")
        seen.add(name)
    return out


_MODEL_LATTICE = {  # the design coordinates (u, v) of U(m,n) the model maps (mlaqc.optics.lattice.Lattice.uv)
    "square": "u = n - 1, v = m - 1; [x', y', w] = homography @ [u, v, 1]; x' /= w, y' /= w",
    "hex": "u = n - 1 + 0.5 [m even], v = (m - 1) sqrt(3)/2 (pitches); [x', y', w] = homography @ [u, v, 1]; "
           "x' /= w, y' /= w",
}


_LENS_FLOATS = ("measured_x_px", "measured_y_px", "grid_x_px", "grid_y_px", "residual_px", "flux", "radius_px")


_LENS_KEYS = ("m", "n", *_LENS_FLOATS, "missing", "clipped")  # the order of to_json_dict's records


class _LensRecords(list):
    """grid.json's lens records, with the same values column by column (`record_columns`: keys, one list of
    plain JSON values per key), so a writer need not gather them back out of 10^4 dicts; every float in
    them is rounded to `record_decimals` (`_rounded_column`). Read-only: the columns do not follow an edit
    of a record (change a copy, `list(records)`)."""

    record_columns: tuple[tuple[str, ...], list[list]]
    record_decimals = 6


def _rounded_column(a: np.ndarray) -> list[float | None]:
    """Every value of `a` (C order) as round(v, 6), a Python float, None where not finite.

    Vectorized and exact: round(v, 6) is the double nearest to n / 10^6 with n the integer nearest to
    v * 10^6 (ties to even), and so is the IEEE quotient n / 1e6. The product v * 1e6 can round across
    a half-integer only when it lies within a few ulps of one; those values (and huge ones) are rounded
    by Python itself."""
    v = np.asarray(a, dtype=np.float64).ravel()
    with np.errstate(invalid="ignore", over="ignore"):
        y = v * 1e6
        n = np.rint(y)
        risky = ~(np.abs(np.abs(y - np.floor(y)) - 0.5) > 4 * np.abs(np.spacing(y))) | ~(np.abs(y) < 2.0 ** 51)
    out = (n / 1e6).tolist()
    values = v.tolist()
    for i in np.flatnonzero(risky).tolist():
        out[i] = round(values[i], 6) if math.isfinite(values[i]) else None
    return out


def _read_lens_columns(lenses: list, rows: int, cols: int, arrays: dict[str, np.ndarray],
                       flags: dict[str, np.ndarray]) -> bool:
    """Fill `arrays` and `flags` from grid.json's lens entries, a whole field at a time; False (and the
    maps possibly half filled) where any entry is not what the lens-by-lens check accepts."""
    try:
        if not all(type(e) is dict for e in lenses):
            return False
        idx = []
        for key, size in (("m", rows), ("n", cols)):
            vals = [e.get(key) for e in lenses]
            if set(map(type, vals)) != {int}:
                return False
            a = np.array(vals, dtype=np.int64)
            if a.min() < 1 or a.max() > size:
                return False
            idx.append(a - 1)
        flat = idx[0] * cols + idx[1]
        if np.bincount(flat, minlength=rows * cols).max() > 1:
            return False  # a lens listed twice
        for key in _LENS_FLOATS:
            vals = [e.get(key) for e in lenses]
            if not set(map(type, vals)) <= {int, float, type(None)}:
                return False
            a = np.array(vals, dtype=np.float64)  # None -> NaN
            if np.count_nonzero(~np.isfinite(a)) != vals.count(None):
                return False  # a number that is not finite
            arrays[key].ravel()[flat] = a
        for key in flags:
            vals = [e.get(key, False) for e in lenses]
            if not set(map(type, vals)) <= {bool}:
                return False
            flags[key].ravel()[flat] = np.array(vals, dtype=bool)
    except (OverflowError, ValueError, TypeError):
        return False
    return True


def _pos_int(v: Any) -> int:
    if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
        raise ValueError(f"{v!r} is not a positive integer")
    return v


def _num(v: Any, allow_none: bool = False) -> float:
    if v is None and allow_none:
        return float("nan")
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
        raise ValueError(f"{v!r} is not a finite number")
    return float(v)


def _describe(exc: BaseException) -> str:
    if isinstance(exc, KeyError):
        return f"missing key {exc.args[0]!r}"
    return str(exc)


def load_grid(path: str | Path) -> Grid:
    """Read and validate grid.json; InputError naming the file and the problem."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"grid file {str(p)!r} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"grid file {str(p)!r} is not readable JSON ({exc.__class__.__name__})") from None
    return Grid.from_json_dict(data, source=f"grid file {str(p)!r}")


# ------------------------------------------------------------------------------------------- the model


def _model_xy(hom: np.ndarray, k: float, centre: tuple[float, float], scale: float, u, v):
    """Lattice (u, v) -> pixel (x, y): projective map, then the radial term."""
    w = hom[2, 0] * u + hom[2, 1] * v + hom[2, 2]
    x = (hom[0, 0] * u + hom[0, 1] * v + hom[0, 2]) / w
    y = (hom[1, 0] * u + hom[1, 1] * v + hom[1, 2]) / w
    if k:
        dx, dy = x - centre[0], y - centre[1]
        f = 1.0 + k * (dx * dx + dy * dy) / (scale * scale)
        x, y = centre[0] + dx * f, centre[1] + dy * f
    return x, y
