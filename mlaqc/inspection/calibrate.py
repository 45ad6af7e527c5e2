"""Microlens calibration from a white image: find every microlens' sub-image, index it U(m,n), fit a
global grid and keep every lens' own measurement (centre, residual, flux, size) as the QC signal.

Pipeline (DESIGN.md §6), vectorized over all lenses at once (no per-lens Python loop):

1. Lattice from the Fourier transform of the (Hann-windowed, for big frames 2x2- or 4x4-binned) white
   image: the two fundamental peaks give pitch and rotation (refined to ~0.01 bin with a local DTFT),
   their phases the lattice offset (the remaining half-period ambiguity is settled by where the cell
   corners are dark). Square: the peaks at |k| = 1/p, 90 degrees apart. Hex: two of the six at
   |k| = 2/(sqrt(3) p), 60 degrees apart; the real basis is then a1 along the rows (~x) and a2 at +60
   degrees (down-right as displayed), both a pitch long ("axial" lattice coordinates (j, i)); the basis
   is refined on the second shell (|k| = 2/p) where that is the stronger, or where the first shell's
   three peaks do not close (b1 + b2 off the third: sub-images growing through its zero across the
   field pull them all the same way); the cell offset is the half-period shift about which the frame
   is six-fold symmetric. A spectrum plainly of
   the other packing than the config's (shells of equal peaks 60 rather than 90 degrees apart, or the
   reverse) is refused by name.
2. Every sub-image is measured by a joint least-squares fit of the frame by a sum of discs, one per lens:
   lens k adds (a_k + slope . (x - c_k)) * e((R_k - |x - c_k|) / s) to the model, e a logistic edge.
   Gauss-Newton on (a_k, c_k, R_k) of all lenses at once: one compiled pass per lens
   (mlaqc.inspection.calibrate_kernels) builds its normal equations straight from the frame, evaluating its own
   disc and its lattice neighbours' where they reach its pixels (no frame-sized model, no scatter; hex: the
   neighbours' discs in long vectorized runs, `HALVES_ORDER`), blocks of lenses on a thread pool.
   Why not a thresholded centre of gravity: in the f-number-matched camera the sub-images touch and even
   overlap (radius 10.2 px at a 20.05 px pitch), so a cell-window centroid is governed by where the window
   is put, not by the lens (it even moves the wrong way). The position information sits in each disc's
   rim; the joint model separates a lens' rim from its neighbours' in the overlap zones, so a shifted
   lens reads its full shift and its neighbours read ~2 % of it. Details that matter:
   - each lens is fitted on an annulus round its rim, tapered and centred on its current estimate (a
     window fixed to the pixel grid would pull a not-yet-right model off centre); its amplitude on its
     plateau too (the pixels well inside, clear of its neighbours' light): on the rim alone amplitude and
     radius trade off, and a photon-starved frame (~1 photon per pixel) sent them oscillating until
     healthy lenses read as missing;
   - red-black sweeps (hex: three colours, (j + 2 i) mod 3): side neighbours (whose discs overlap) never
     step together;
   - noise weights ~ 1 / signal (Monte-Carlo and photon noise), except round lenses far off the lattice;
   - intensity slopes across each sub-image (illumination falloff, vignetting) come from the smooth
     field of the lens amplitudes (a plane through the 5 x 5 lenses round each: a neighbour pair's
     difference put its amplitudes' noise into every centre, 2 % of their spread at 15 % noise) and are
     held fixed (fitting them per lens costs precision);
   - the edge width and typical radius come from a central block first; lenses the sharp edge cannot
     pull in (more than ~1.5 px off the lattice) are captured with a wide edge of their own, then they
     and their neighbours are fitted again with the sharp one;
   - pixels outside the frame are simply left out, so lenses cut by the frame are measured unbiased;
   - the first weighted sweep is not damped as an oscillation (it answers a new objective), so three
     sweeps settle nearly every lens;
   - the model has no background term: where the cell corners, well clear of the fitted rims, hold over
     15 % of the sub-images' light (clear gaps between circular lenses, a low black level), a smooth
     surface through them is taken off and every lens measured again (`_without_background`).
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

Measured on the Table 1 camera (50 rays/pixel, noise on): per-lens centres 0.029 px RMS (0.021 px per
axis, Monte-Carlo-noise limited) and grid centres 0.003 px RMS from the ray-traced sub-image centres.

Conventions: pixel (0, 0) is the centre of the top-left pixel, x to the right, y down. Lens U(m,n) is row m
from the top, column n from the left (1-based), arrays index [m-1, n-1]. Rotation is counterclockwise as
the image is displayed (as `ErrorMap`'s mla_rotation_deg).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc.atomic import write_json_atomic
from mlaqc.errors import InputError
from mlaqc.inspection.fft import rfft2
from mlaqc.inspection import calibrate_kernels as kernels
from mlaqc.optics.lattice import CONVENTIONS, PACKINGS, SQRT3_2, Lattice, packing_of
from mlaqc.parallel import thread_map

FORMAT = "mlaqc-grid"
VERSION = 1

# Thresholds (relative units unless stated).
MISSING_RELATIVE_FLUX = 0.3  # a lens under 30 % of its neighbourhood's amplitude is 'missing/dim'
MIN_VALID_FRACTION = 0.35  # lenses with less of their rim than this inside the frame are not measured
PITCH_TOLERANCE = 0.10  # the found pitch may differ from the expected one by 10 %
MIN_LENSES = 9
MIN_PITCH_PX = 4.0
# light at the cell corners above this fraction of the sub-images' is a background: less pulls the centres by
# under 0.01 px even with strong vignetting, and blurred or Airy rims alone reach 5 - 12 % there (measured)
BACKGROUND_MIN = 0.15
BACKGROUND_DEGREE = 4  # of the polynomial surface fitted to it

# The disc fit (see _measure). Lengths in pixels.
BLOCK_SWEEPS = 5  # sweeps on the central block that sets the edge width and typical radius
SUBSET = 16  # that block is SUBSET x SUBSET lenses
N_SWEEPS = 3  # sweeps over every lens (the first unweighted)
MAX_EXTRA = 10  # more sweeps, for the lenses not yet settled and their neighbours only
SETTLED_PX = 0.02  # a lens has settled when its step is under this
BAND = 1.5  # each lens is fitted on |r - R| <= BAND (+ a 0.5 px taper) round its rim
SLOPE_REACH = 2  # a lens' intensity slope: the plane through the amplitudes of the 5 x 5 lenses round it
PLATEAU_EDGES = 3.0  # its amplitude on its plateau too: the pixels this many edge widths inside the band
WEIGHT_FLOOR = 0.05  # noise weights ~ 1 / signal, the signal floored at this fraction of the plateau
COUPLED_PX = 0.3  # lenses this far off the lattice, and their neighbours, are fitted unweighted
WIDE_EDGE = 1.0  # lenses the sharp edge cannot capture get an edge at least this wide for a while
N_LENS_PARAMS = 4  # amplitude, centre x, centre y, radius
BLOCK_LENSES = 512  # lenses per work block of the thread pool
# the disc kernel's pixel order (calibrate_kernels.disc_normals' `halves`): the neighbours' discs on the vector
# units, summed in another order. Hex: its six side neighbours' discs are most of the work (the kernel 40 %
# faster). Square keeps its span order and so its results to the last bit (`halves` would make its
# calibration 26 % faster, its centres moving by < 1e-4 px)
HALVES_ORDER = {"square": False, "hex": True}


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
                   packing=packing)

    def save(self, path: str | Path) -> None:
        """Write grid.json atomically (a reader never sees half a file)."""
        write_json_atomic(path, self.to_json_dict())


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


# -------------------------------------------------------------------------------------------- lattice


@dataclass(frozen=True)
class _Lattice:
    """The image's sub-image lattice: point (j, i) (lattice coordinates) lies at origin + basis @ (j, i).
    Square: a1 along n (~x), a2 along m (~y). Hex: a1 along the rows (~x), a2 at 60 degrees from it
    (down and to the right as displayed), both one pitch long ("axial" coordinates)."""

    basis: np.ndarray  # (2, 2): columns a1 and a2, px
    origin: np.ndarray  # (2,) a lattice point (sub-image centre) near the frame centre, px
    packing: str = "square"


def _hann(n: int) -> np.ndarray:
    return (0.5 - 0.5 * np.cos(2.0 * np.pi * (np.arange(n) + 0.5) / n)).astype(np.float32)


def _dtft(a: np.ndarray, kxs: np.ndarray, kys: np.ndarray) -> np.ndarray:
    """DTFT of `a` (coordinates about the frame centre) on the grid kys x kxs (cycles/px), real matmuls."""
    h, w = a.shape
    x = (np.arange(w) - 0.5 * (w - 1)).astype(np.float64)
    y = (np.arange(h) - 0.5 * (h - 1)).astype(np.float64)
    px = 2.0 * np.pi * np.outer(kxs, x)
    t = kernels.row_dots(a, np.concatenate([np.cos(px), -np.sin(px)]).astype(np.float32))  # (h, 2 nx)
    row = (t[:, : len(kxs)] + 1j * t[:, len(kxs):]).astype(np.complex128)
    ey = np.exp(-2j * np.pi * np.outer(kys, y))
    return ey @ row


def _refine_peak(a: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, complex]:
    """Sub-bin peak of |DTFT|^2 near k: quadratic fits of log power on shrinking 5x5 grids."""
    h, w = a.shape
    k = np.array(k, dtype=np.float64)
    off = np.arange(-2, 3, dtype=np.float64)
    gy, gx = np.meshgrid(off, off, indexing="ij")
    design = np.stack([np.ones(25), gx.ravel(), gy.ravel(), gx.ravel() ** 2, (gx * gy).ravel(), gy.ravel() ** 2], 1)
    for step in (0.3, 0.08, 0.02):
        f = _dtft(a, k[0] + off * step / w, k[1] + off * step / h)
        lp = np.log(np.abs(f) ** 2 + 1e-300).ravel()
        c = np.linalg.lstsq(design, lp, rcond=None)[0]
        hess = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
        try:
            d = np.linalg.solve(hess, -c[1:3])
        except np.linalg.LinAlgError:
            d = np.zeros(2)
        if not (hess[0, 0] < 0 and np.linalg.det(hess) > 0):
            d = np.array(np.unravel_index(np.argmax(lp), (5, 5))[::-1], float) - 2.0
        d = np.clip(d, -2.0, 2.0)
        k = k + d * step / np.array([w, h])
    return k, complex(_dtft(a, k[:1], k[1:])[0, 0])


def _fft_lattice(img: np.ndarray, expected_pitch_px: float | None, packing: str = "square") -> _Lattice:
    """Pitch, rotation and offset of the sub-image lattice of `packing` from the image's Fourier transform."""
    full_h, full_w = img.shape
    # large frames of coarse lattices: b x b binning keeps the fundamental periods (>= 5 binned px) and the
    # frame centre, and costs 1 / b^2 of the transform and of the peak refinement
    b = 1
    if expected_pitch_px is not None:
        while b < 4 and expected_pitch_px >= 10.0 * b and min(full_h, full_w) >= 1024 * b:
            b *= 2
    binned = b > 1
    if binned:
        src = img[: full_h // b * b, : full_w // b * b]
        acc = src[0::b, 0::b].copy()
        for i in range(b):
            for j in range(b):
                if i or j:
                    acc += src[i::b, j::b]  # strided adds: far faster than a reshaped mean
        src = acc * np.float32(1.0 / (b * b))
        expected_pitch_px = expected_pitch_px / b
    else:
        src = img
    h, w = src.shape
    a = (src - np.float32(src.mean())) * _hann(h)[:, None] * _hann(w)[None, :]
    spec = rfft2(a, workers=_workers() if a.size > 1 << 20 else 1)  # small: threads cost more
    power = spec.real ** 2 + spec.imag ** 2
    ky = np.fft.fftfreq(h).astype(np.float32)
    kx = np.fft.rfftfreq(w).astype(np.float32)
    kr = np.hypot(ky[:, None], kx[None, :])
    band = (kr >= 6.0 / min(h, w)) & (kr <= 1.0 / MIN_PITCH_PX)
    pb = np.where(band, power, 0.0)
    if not pb.any():
        raise InputError("the white image shows no periodic microlens structure")
    iy, ix = np.nonzero(pb >= 0.03 * pb.max())
    if iy.size > 20000:  # a noise-like spectrum: no clear peaks
        raise InputError("the white image shows no periodic microlens structure")
    pv = pb[iy, ix]
    nb = np.stack([pb[(iy + dy) % h, np.clip(ix + dx, 0, pb.shape[1] - 1)]
                   for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])
    is_peak = pv >= nb.max(axis=0)
    iy, ix, pv = iy[is_peak], ix[is_peak], pv[is_peak]
    floor = float(np.median(power[::4, ::4][band[::4, ::4]]))
    if pv.size == 0 or pv.max() <= 200.0 * max(floor, 1e-30):
        raise InputError("the white image shows no periodic microlens structure")
    strong = pv >= 0.03 * pv.max()
    iy, ix, pv = iy[strong], ix[strong], pv[strong]
    kvec = np.stack([kx[ix], ky[iy]], 1).astype(np.float64)
    kmag = np.hypot(kvec[:, 0], kvec[:, 1])
    order = np.argsort(kmag)
    kvec, kmag, pv = kvec[order], kmag[order], pv[order]
    if packing == "hex":
        return _hex_lattice(img, a, kvec, kmag, pv, b, expected_pitch_px)
    first = kvec[0]
    if expected_pitch_px is not None:
        near = np.abs(kmag * expected_pitch_px - 1.0) <= PITCH_TOLERANCE
        if not near.any():
            _refuse_mismatch(kvec, pv, "square")
            unit = float(b)
            raise InputError(f"the microlens pitch in the image ({unit / kmag[0]:.2f} px) is far from the expected "
                             f"{unit * expected_pitch_px:.2f} px; check the camera config and the image")
        first = kvec[np.argmax(near)]
    # its partner: the strongest peak roughly perpendicular with a similar length
    cosang = np.abs(kvec @ first) / (np.hypot(kvec[:, 0], kvec[:, 1]) * np.hypot(*first))
    ratio = np.hypot(kvec[:, 0], kvec[:, 1]) / np.hypot(*first)
    partner = (cosang < math.sin(math.radians(10))) & (np.abs(ratio - 1) < 0.1)
    if not partner.any():
        _refuse_mismatch(kvec, pv, "square")
        raise InputError("the white image shows no square microlens lattice (only one periodic direction found)")
    second = kvec[np.argmax(np.where(partner, pv, -1))]
    k1, f1 = _refine_peak(a, first)
    k2, f2 = _refine_peak(a, second)
    # order: k1 along x (n), k2 along y (m); signs so that the real-space axes point +x and +y
    if abs(k1[0]) < abs(k2[0]):
        k1, k2, f1, f2 = k2, k1, f2, f1
    kmat = np.array([k1, k2])  # rows: reciprocal vectors; basis = inverse
    basis = np.linalg.inv(kmat)  # columns a1, a2 with k_i . a_j = delta_ij
    phase = -np.angle([f1, f2]) / (2.0 * np.pi)
    if basis[0, 0] < 0:
        basis[:, 0] *= -1
        phase[0] *= -1
    if basis[1, 1] < 0:
        basis[:, 1] *= -1
        phase[1] *= -1
    if binned:  # back to frame pixels: x = b x_binned + (b - 1) / 2, the same centre for frame sizes of b n
        basis *= b
        expected_pitch_px *= b
        h, w = full_h // b * b, full_w // b * b
    pitch = np.hypot(basis[0], basis[1])
    if pitch.min() < MIN_PITCH_PX:
        raise InputError(f"the periodic structure in the image ({pitch.min():.2f} px) is too fine for microlenses")
    if expected_pitch_px is not None and np.any(np.abs(pitch / expected_pitch_px - 1) > PITCH_TOLERANCE):
        _refuse_mismatch(kvec, pv, "square")
        raise InputError(f"the microlens pitch in the image ({pitch[0]:.2f} x {pitch[1]:.2f} px) is far from the expected "
                         f"{expected_pitch_px:.2f} px; check the camera config and the image")
    centre = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    base = centre + basis @ phase
    origin = _resolve_half_period(img, basis, base)
    return _Lattice(basis, origin)


PACKING_WORDS = {"square": "square", "hex": "hexagonal"}


def _spectrum_packing(kvec: np.ndarray, pv: np.ndarray) -> str | None:
    """The packing the spectrum's peaks show, or None if unclear: a hexagonal lattice's shells of equal
    peaks lie 60 degrees apart, a square one's 90 degrees. Looked at round the lowest and the strongest
    peak (peaks of one shell have lengths within 3 %; directions are lines, k and -k alike)."""
    if kvec.shape[0] < 2:
        return None
    mag = np.hypot(kvec[:, 0], kvec[:, 1])
    votes = set()
    for ref in {0, int(np.argmax(pv))}:
        same = np.abs(mag / mag[ref] - 1.0) < 0.03
        same[ref] = False
        cos = np.abs(kvec[same] @ kvec[ref]) / (mag[same] * mag[ref])
        if np.any(cos < math.sin(math.radians(5.0))):
            votes.add("square")
        if np.any(np.abs(cos - 0.5) < 0.075):  # 60 or 120 degrees, within ~5
            votes.add("hex")
    return votes.pop() if len(votes) == 1 else None


def _refuse_mismatch(kvec: np.ndarray, pv: np.ndarray, packing: str) -> None:
    """InputError if the spectrum plainly shows the other packing than the config's."""
    seen = _spectrum_packing(kvec, pv)
    if seen is not None and seen != packing:
        raise InputError(f"the white image shows a {PACKING_WORDS[seen]} microlens lattice but the config says "
                         f"mla.packing = {packing!r}")


def _hex_lattice(img: np.ndarray, a: np.ndarray, kvec: np.ndarray, kmag: np.ndarray, pv: np.ndarray, b: int,
                 expected_pitch_px: float | None) -> _Lattice:
    """The hexagonal lattice from the (binned by b, windowed) frame `a`'s spectral peaks (sorted by |k|):
    two of the six fundamental peaks (|k| = 2 / (sqrt(3) p), 60 degrees apart) give the lattice and its
    offset; the basis is then a1 along the rows (the lattice vector nearest +x), a2 at +60 degrees."""
    full_h, full_w = img.shape
    _refuse_mismatch(kvec, pv, "hex")
    first, shell = kvec[0], 1
    if expected_pitch_px is not None:  # binned px here
        near = np.abs(kmag * expected_pitch_px * SQRT3_2 - 1.0) <= PITCH_TOLERANCE
        # discs whose transform has a zero at the first shell (a defocused array's) leave only the second
        # shell (|k| = 2 / p) among the strong peaks
        near2 = np.abs(kmag * expected_pitch_px * 0.5 - 1.0) <= PITCH_TOLERANCE
        if not near.any() and not near2.any():
            raise InputError(f"the microlens pitch in the image ({b / (kmag[0] * SQRT3_2):.2f} px) is far from the "
                             f"expected {b * expected_pitch_px:.2f} px; check the camera config and the image")
        first, shell = (kvec[np.argmax(near)], 1) if near.any() else (kvec[np.argmax(near2)], 2)
    mag = np.hypot(kvec[:, 0], kvec[:, 1])
    cosang = np.abs(kvec @ first) / (mag * np.hypot(*first))
    partner = (np.abs(cosang - 0.5) < 0.15) & (np.abs(mag / np.hypot(*first) - 1) < 0.1)
    if not partner.any():
        raise InputError("the white image shows no hexagonal microlens lattice (only one periodic direction found)")
    second = kvec[np.argmax(np.where(partner, pv, -1))]
    if shell == 1:
        k1, f1 = _refine_peak(a, first)
        k2, f2 = _refine_peak(a, second)
    else:  # second-shell peaks q1, q2 60 degrees apart: first-shell (2 q1 - q2) / 3 and (q1 + q2) / 3
        q1, _ = _refine_peak(a, first)
        q2, _ = _refine_peak(a, second)
        k1, k2 = (2.0 * q1 - q2) / 3.0, (q1 + q2) / 3.0
        f1, f2 = (complex(_dtft(a, k[:1], k[1:])[0, 0]) for k in (k1, k2))
    prime = np.linalg.inv(np.array([k1, k2])) * b  # columns: a lattice basis (k_i . a_j = delta_ij), frame px
    phase = -np.angle([f1, f2]) / (2.0 * np.pi)
    h, w = (full_h // b * b, full_w // b * b) if b > 1 else (full_h, full_w)
    centre = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    base = centre + prime @ phase
    basis = _second_shell_basis(a, _hex_basis(prime) / b, min(abs(f1), abs(f2))) * b
    pitch = np.hypot(basis[0], basis[1])
    if pitch.min() < MIN_PITCH_PX:
        raise InputError(f"the periodic structure in the image ({pitch.min():.2f} px) is too fine for microlenses")
    if expected_pitch_px is not None and np.any(np.abs(pitch / (b * expected_pitch_px) - 1) > PITCH_TOLERANCE):
        raise InputError(f"the microlens pitch in the image ({pitch[0]:.2f} x {pitch[1]:.2f} px) is far from the expected "
                         f"{b * expected_pitch_px:.2f} px; check the camera config and the image")
    candidates = [base + basis @ np.array([sx, sy]) for sx in (0.0, 0.5) for sy in (0.0, 0.5)]
    candidates += _second_shell_origins(a, basis / b, centre, b)
    origin = _six_fold_origin(img, basis, candidates)
    return _Lattice(basis, origin, "hex")


def _second_shell_origins(a: np.ndarray, basis: np.ndarray, centre: np.ndarray, b: int) -> list[np.ndarray]:
    """Lattice origins (frame px) the second shell's phases allow (`basis`: binned px). Where the
    sub-image radius crosses the first shell's zero within the frame (a tilted, defocused array: its
    sub-images grow across the field) the first-shell phases mix both signs and say nothing; the second
    shell's, P1 = 2 f1 + f2 and P2 = f1 + 2 f2 (f: the origin in lattice units), fix f up to thirds of a
    period and the transform's common sign: 9 candidates, sorted out by their six-fold symmetry."""
    k1, k2 = np.linalg.inv(basis)
    phases = [-np.angle(_dtft(a, q[:1], q[1:])[0, 0]) / (2.0 * np.pi) for q in (2.0 * k1 + k2, k1 + 2.0 * k2)]
    out = []
    for sign in (0.0, 0.5):
        for n1 in range(3):
            p1, p2 = phases[0] + sign + n1, phases[1] + sign
            f = np.array([(2.0 * p1 - p2) / 3.0, (2.0 * p2 - p1) / 3.0])
            out.append(centre + (basis * b) @ f)
    return out


# the second shell's peaks are looked for this far (FFT bins) round where the first shell
# puts them: a first shell pulled by a bin puts them up to three bins off (2 b1 + b2 carries its pull thrice)
SHELL_SEARCH_BINS = 4
# a shell's third peak lies at the sum (first shell) or difference (second) of the other two, to noise (~1e-4
# of |k|); a shell pulled off by a zero of the discs' transform crossing the field misses it by the pull
CLOSURE_TOLERANCE = 2e-3


def _second_shell_basis(a: np.ndarray, basis: np.ndarray, first_level: float) -> np.ndarray:
    """The hex basis (binned px) refined on the second shell of peaks (|k| = 2 / p: 2 b1 + b2 and b1 + 2 b2,
    b_i the reciprocal basis) where that shell is the better: the stronger (`first_level`: the weaker
    first-shell peak's |DTFT|), or the only one of the two whose three peaks close (`_shell_closure`).
    Discs of about half the pitch, as an f-number-matched camera makes, have their first-shell peaks next
    to a zero of the disc's transform (2 pi |k| R ~ 3.7 against 3.83): weak, good to a few 1e-4 of the pitch
    only; the second shell is then about twice as strong and twice as far out (discs of ~0.3 p have it at
    the zero instead). A tilted, defocused array whose sub-images grow through that zero across the frame
    has the first shell's peaks, sums over the field of both signs, all pulled off by the same few 1e-3
    cycles/px (1.4 % of |k| on the Table 1 hex array with the sensor 15 µm back and a 0.3 degree tilt):
    not a lattice (b1 + b2 misses the third peak by the pull), so its second-shell guesses are looked for
    SHELL_SEARCH_BINS round. Kept if both refined peaks lie within 10 % of where the first shell puts them
    (no other peak of the spectrum is that close)."""
    b1, b2 = np.linalg.inv(basis)
    guess = (2.0 * b1 + b2, b1 + 2.0 * b2)
    (q1, g1), (q2, g2) = (_refine_peak(a, _coarse_peak(a, q)) for q in guess)
    if max(float(np.hypot(*(q - g)) / np.hypot(*g)) for q, g in zip((q1, q2), guess)) > 0.1:
        return basis
    second = np.linalg.inv(np.array([(2.0 * q1 - q2) / 3.0, (2.0 * q2 - q1) / 3.0]))
    if min(abs(g1), abs(g2)) > first_level:
        return second
    if _shell_closure(a, b1, b2, 1.0) > CLOSURE_TOLERANCE >= _shell_closure(a, q1, q2, -1.0):
        return second
    return basis


def _coarse_peak(a: np.ndarray, k: np.ndarray) -> np.ndarray:
    """The largest |DTFT| of `a` within SHELL_SEARCH_BINS bins of k, on the bin grid (within half a bin of
    the peak, where `_refine_peak`, which reaches 0.8 bin, can start; a finer grid makes the products wide
    enough for multi-threaded BLAS, which stalls for 0.1 s at a time on a busy machine)."""
    h, w = a.shape
    off = np.arange(-SHELL_SEARCH_BINS, SHELL_SEARCH_BINS + 0.5, 1.0)
    f = np.abs(_dtft(a, k[0] + off / w, k[1] + off / h))
    iy, ix = np.unravel_index(int(np.argmax(f)), f.shape)
    return np.array([k[0] + off[ix] / w, k[1] + off[iy] / h])


def _shell_closure(a: np.ndarray, k1: np.ndarray, k2: np.ndarray, sign: float) -> float:
    """How far (in |k1|) the three peaks of a shell refined near k1, k2 and k1 + sign k2 miss closing
    (k3 = k1 + sign k2): ~1e-4 on a lattice, the pull where the shell is pulled off."""
    q1, q2, q3 = (_refine_peak(a, _coarse_peak(a, k))[0] for k in (k1, k2, k1 + sign * k2))
    return float(np.hypot(*(q1 + sign * q2 - q3)) / np.hypot(*k1))


def _hex_basis(prime: np.ndarray) -> np.ndarray:
    """The canonical basis of the hexagonal lattice spanned by `prime`'s columns: a1 the shortest lattice
    vector nearest +x, a2 the one nearest a1 turned 60 degrees towards +y (down as displayed)."""
    p1, p2 = prime[:, 0], prime[:, 1]
    vecs = np.array([p1, p2, p1 + p2, p1 - p2, -p1, -p2, -p1 - p2, p2 - p1])
    length = np.hypot(vecs[:, 0], vecs[:, 1])
    short = vecs[np.argsort(length, kind="stable")[:6]]
    a1 = short[np.argmax(short[:, 0] / np.hypot(short[:, 0], short[:, 1]))]
    c, s = 0.5, SQRT3_2
    turned = np.array([c * a1[0] - s * a1[1], s * a1[0] + c * a1[1]])
    a2 = short[np.argmax(short @ turned)]
    return np.stack([a1, a2], axis=1)


# cell corners in lattice coordinates: the square's 4, the hexagon's 6 (centroids of the lattice triangles)
_CORNERS = {"square": [(cx, cy) for cx in (-0.5, 0.5) for cy in (-0.5, 0.5)],
            "hex": [(1 / 3, 1 / 3), (-1 / 3, 2 / 3), (-2 / 3, 1 / 3), (-1 / 3, -1 / 3), (1 / 3, -2 / 3), (2 / 3, -1 / 3)]}


def _resolve_half_period(img: np.ndarray, basis: np.ndarray, base: np.ndarray, packing: str = "square") -> np.ndarray:
    """The Fourier phase fixes the lattice up to half a period per axis (the sign of the sub-image's
    transform); pick the shift whose points are bright with dark cell corners around them (hex: the
    shift about whose points the frame has the lattice's six-fold symmetry, `_six_fold_origin`)."""
    if packing == "hex":
        return _six_fold_origin(img, basis, [base + basis @ np.array([sx, sy]) for sx in (0.0, 0.5) for sy in (0.0, 0.5)])
    h, w = img.shape
    jj, ii = np.meshgrid(np.arange(-6, 7), np.arange(-6, 7))
    best, score_best = base, -np.inf
    for sx in (0.0, 0.5):
        for sy in (0.0, 0.5):
            o = base + basis @ np.array([sx, sy])
            pts = o[:, None] + basis @ np.stack([jj.ravel(), ii.ravel()])
            corners = [pts + basis @ np.array([cx, cy])[:, None] for cx, cy in _CORNERS[packing]]
            inside = lambda p: (p[0] > 1) & (p[0] < w - 2) & (p[1] > 1) & (p[1] < h - 2)  # noqa: E731
            ok = inside(pts) & np.all([inside(c) for c in corners], axis=0)
            if not ok.any():
                continue
            sample = lambda p: _bilinear(img, p[0][ok], p[1][ok])  # noqa: E731
            score = float(np.mean(sample(pts)) - np.mean([sample(c) for c in corners]))
            if score > score_best:
                best, score_best = o, score
    return best


def _six_fold_origin(img: np.ndarray, basis: np.ndarray, candidates: list[np.ndarray]) -> np.ndarray:
    """Of the candidate origins of a hex lattice (the four half-period shifts, and the second shell's
    `_second_shell_origins`), the one whose points are centres of six-fold symmetry: on rings round a sub-image centre the frame repeats every 60 degrees, round the other three
    (midpoints between two neighbours) only every 180. Brightness tests fail here: discs larger than half
    the pitch light their overlaps twice and, beyond ~0.56 p, the cell corners too. Measured on the
    analytic model for radii 0.15 - 0.65 p, noise-free and at 15 % noise. Rings at 0.2, 0.3 and 0.4 p,
    12 samples each, round 21 x 21 lattice points near the frame centre."""
    h, w = img.shape
    jj, ii = np.meshgrid(np.arange(-10, 11), np.arange(-10, 11))
    pitch = float(np.hypot(*basis[:, 0]))
    angle = math.atan2(basis[1, 0], basis[0, 0]) + np.radians(np.arange(12) * 30.0)
    best, score_best = candidates[0], np.inf
    for o in candidates:
        pts = o[:, None] + basis @ np.stack([jj.ravel(), ii.ravel()])
        score = 0.0
        for rho in (0.2 * pitch, 0.3 * pitch, 0.4 * pitch):
            rx = pts[0][:, None] + rho * np.cos(angle)[None, :]
            ry = pts[1][:, None] + rho * np.sin(angle)[None, :]
            ok = np.all((rx > 1) & (rx < w - 2) & (ry > 1) & (ry < h - 2), axis=1)
            if not ok.any():
                continue
            f = _bilinear(img, rx[ok], ry[ok])
            score += float(np.mean(np.abs(f - np.roll(f, -2, axis=1))) / (np.mean(np.abs(f)) + 1e-12))
        if score < score_best:
            best, score_best = o, score
    return best


# --------------------------------------------------------------------------------------- disc fitting


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """img interpolated bilinearly at points (x, y) inside the frame (map_coordinates' order=1, in NumPy)."""
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    fx, fy = x - x0, y - y0
    top = img[y0, x0] * (1.0 - fx) + img[y0, x0 + 1] * fx
    bottom = img[y0 + 1, x0] * (1.0 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1.0 - fy) + bottom * fy


def _workers() -> int:
    return max(1, min(4, os.cpu_count() or 1))


@dataclass
class _Discs:
    """What the disc fit found, per candidate lattice position."""

    cx: np.ndarray
    cy: np.ndarray
    amp: np.ndarray
    radius: np.ndarray
    edge: float
    valid_fraction: np.ndarray


def _disc_offsets(reach: float, inner: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    hw = int(math.ceil(reach))
    dy, dx = np.mgrid[-hw:hw + 1, -hw:hw + 1]
    r = np.hypot(dx, dy)
    keep = (r <= reach) & (r >= inner)
    return dy[keep].astype(np.int32), dx[keep].astype(np.int32)


class _DiscFit:
    """Joint fit of the frame by one logistic-edged disc per lens (see the module docstring).

    Each lens is fitted on the pixels of an annulus about its current rim (the plateau inside carries no
    position information). The model on those pixels is the lens' own disc plus the discs of its lattice
    neighbours that reach them, evaluated afresh from the current parameters in one compiled pass per
    lens (mlaqc.inspection.calibrate_kernels), so overlapping neighbours are accounted for without a frame-sized
    model. Blocks of lenses run on a thread pool (the kernel releases the GIL).
    """

    def __init__(self, img: np.ndarray, cx: np.ndarray, cy: np.ndarray, radius0: float,
                 neighbours: np.ndarray, colour: np.ndarray | None = None, halves: bool = False,
                 spacing_px: float = math.inf) -> None:
        self.img = img
        self.spacing_px = spacing_px  # between nearest lattice neighbours: bounds the plateau clear of their light
        self.halves = halves  # the kernel's pixel order for vectorized neighbour discs (hex; see disc_normals)
        self.h, self.w = img.shape
        self.cx, self.cy = cx.astype(np.float64).copy(), cy.astype(np.float64).copy()
        self.n = cx.size
        self.radius = np.full(self.n, radius0)
        self.edge = 0.8
        self.amp = np.zeros(self.n)
        self.slope_x = np.zeros(self.n)  # plateau level change per radius, x and y
        self.slope_y = np.zeros(self.n)
        self.r_norm = float(radius0)
        self.band = BAND
        self.neighbours = np.ascontiguousarray(neighbours, dtype=np.int64)
        self.prev_step = np.zeros((self.n, N_LENS_PARAMS))
        self.last_step = np.zeros(self.n)
        self.rss = np.zeros(self.n)
        self.npix = np.zeros(self.n, np.int64)
        self.valid_fraction = np.ones(self.n)
        self.colour = np.zeros(self.n, np.int8) if colour is None else colour.astype(np.int8)
        if np.any(np.diff(self.colour) < 0):
            raise ValueError("lenses must be sorted by colour")
        self.n_red = int(np.count_nonzero(self.colour == 0))
        self.n_colours = max(2, int(self.colour.max()) + 1) if self.n else 2
        self.coupled = np.zeros(self.n, bool)  # lenses next to (or being) a lens far off the lattice
        self.wide = None  # lenses fitted with a wide edge (capture of far-off lenses)
        self.wide_edge = 1.0
        self.workers = min(_workers(), -(-self.n // 16))

    def _map(self, fn, lenses: np.ndarray) -> None:
        """fn(block) over blocks of `lenses` (an index array), on the process' pool: a multiple of the
        worker count of equal blocks (small sets are split too), so the workers finish together."""
        n_blocks = self.workers * -(-lenses.size // (self.workers * BLOCK_LENSES))
        size = max(16, -(-lenses.size // max(n_blocks, 1)))
        blocks = [slice(b, min(b + size, lenses.size)) for b in range(0, lenses.size, size)]
        if self.workers > 1:
            thread_map(fn, blocks)
        else:
            for b in blocks:
                fn(b)

    def set_band(self, band: float) -> None:
        """Fit each lens on |r - R| <= band (+ a 0.5 px taper); note how much of each rim is in the frame."""
        self.band = band
        self.valid_fraction = self.rim_in_frame()

    def rim_in_frame(self) -> np.ndarray:
        """Fraction of each sub-image's rim (|r - R| <= 1 px about its rounded centre) inside the frame."""
        out = np.ones(self.n)
        r0 = float(np.median(self.radius))
        dy, dx = _disc_offsets(r0 + 1.0, max(0.0, r0 - 1.0))
        gx, gy = np.rint(self.cx).astype(np.int64), np.rint(self.cy).astype(np.int64)
        hw = math.ceil(r0 + 1.0)
        edge = np.flatnonzero((gx - hw < 0) | (gx + hw >= self.w) | (gy - hw < 0) | (gy + hw >= self.h))
        if edge.size:
            iy, ix = gy[edge, None] + dy[None, :], gx[edge, None] + dx[None, :]
            out[edge] = ((iy >= 0) & (iy < self.h) & (ix >= 0) & (ix < self.w)).mean(axis=1)
        return out

    def init_amplitude(self, radius: float) -> None:
        """Amplitude guess: the mean level of the pixels well inside each lens' disc (0 off the frame)."""
        self.amp = kernels.plateau_mean(self.img, self.cx, self.cy, max(1, int(0.4 * radius)))

    def set_slopes(self, lat_j: np.ndarray, lat_i: np.ndarray, basis: np.ndarray, active: np.ndarray) -> None:
        """Intensity slope across each sub-image from the smooth field of lens amplitudes (non-uniform
        illumination, vignetting): the gradient of a plane fitted to the amplitudes of the lenses within
        SLOPE_REACH lattice steps, turned into x/y slopes per disc radius. Held fixed in the fit (fitting
        them per lens would cost precision)."""
        j0, i0 = lat_j.min(), lat_i.min()
        shape = (lat_i.max() - i0 + 1, lat_j.max() - j0 + 1)
        amp, on = np.zeros(shape), np.zeros(shape)
        amp[lat_i - i0, lat_j - j0] = np.where(active, self.amp, 0.0)
        on[lat_i - i0, lat_j - j0] = active
        dj, di = _plane_gradient(amp, on, SLOPE_REACH)
        dj, di = dj[lat_i - i0, lat_j - j0], di[lat_i - i0, lat_j - j0]
        grad = np.linalg.solve(basis.T, np.stack([dj, di]))  # d amp / d(x, y) per px
        self.slope_x = np.where(active, grad[0] * self.r_norm, 0.0)
        self.slope_y = np.where(active, grad[1] * self.r_norm, 0.0)

    def _plateau_inset(self, edge: float) -> float:
        """How far inside its rim a lens' plateau ends: clear of the fitted annulus and of the rim's tail
        (PLATEAU_EDGES edge widths), and of its neighbours' light."""
        tail = PLATEAU_EDGES * edge
        return max(self.band + 0.5 + tail, 2.0 * self.r_norm + tail + 0.5 - self.spacing_px)

    def _normals(self, idx: np.ndarray, edge: float, weighted: bool, fit_edge: bool):
        """Normal equations (n, 5, 5), right-hand sides (n, 5) of lenses `idx` against the frame residual;
        notes each lens' residual sum of squares and pixel count (a fit-quality figure).

        Parameters per lens: amplitude, centre x and y, radius (+ the global edge width in slot 4)."""
        inv_edge = np.full(self.n, 1.0 / edge)
        wide = np.zeros(self.n, bool) if self.wide is None else self.wide
        if self.wide is not None:
            inv_edge[wide] = 1.0 / self.wide_edge
        k = 1.0 / self.r_norm
        sx, sy = self.slope_x * k, self.slope_y * k
        normal = np.empty((idx.size, kernels.N_NORMAL, kernels.N_NORMAL))
        rhs = np.empty((idx.size, kernels.N_NORMAL))
        rss = np.empty(idx.size)
        npix = np.empty(idx.size, np.int64)

        inset = self._plateau_inset(edge if self.wide is None else max(edge, self.wide_edge))

        def block(b: slice) -> None:
            kernels.disc_normals(self.img, idx[b], self.cx, self.cy, self.amp, self.radius, inv_edge, sx, sy,
                                 self.neighbours, self.coupled, wide, self.band + 0.5, weighted, fit_edge,
                                 WEIGHT_FLOOR, self.halves, normal[b], rhs[b], rss[b], npix[b])
            kernels.add_plateau(self.img, idx[b], self.cx, self.cy, self.amp, self.radius, sx, sy, inset,
                                normal[b], rhs[b])

        self._map(block, idx)
        self.rss[idx], self.npix[idx] = rss, npix
        return normal, rhs

    def sweep(self, edge: float | None, active: np.ndarray, weighted: bool, lenses: np.ndarray | None = None) -> None:
        """One Gauss-Newton step for every lens (or `lenses`), by colour (square red-black, hex three): lenses
        of one lattice colour step together, then the next colour steps against their new positions (side
        neighbours, whose discs overlap, never step at the same time, so overlapping pairs cannot run away)."""
        # each lens once: `iterate` updates its lenses by fancy index, which must not repeat a lens
        idx = np.arange(self.n) if lenses is None else np.unique(np.asarray(lenses))
        for colour in range(self.n_colours):
            part = idx[self.colour[idx] == colour]
            if part.size:
                self.iterate(edge, active, weighted, part)

    def iterate(self, edge: float | None, active: np.ndarray, weighted: bool, idx: np.ndarray) -> None:
        """One Gauss-Newton step for lenses `idx` (inactive ones: amplitude only), the others held; with
        `edge` None the global edge width steps too (eliminated exactly through each lens' block)."""
        if edge is not None:
            self.edge = edge
            normal, rhs = self._normals(idx, edge, weighted, False)
            kernels.apply_steps(idx, normal, rhs, active, self.amp, self.cx, self.cy, self.radius, self.prev_step,
                                self.last_step, self.r_norm - 1.0, self.r_norm + 1.0)
            return
        s = self.edge
        normal, rhs = self._normals(idx, s, weighted, True)
        act = active[idx]
        npar = N_LENS_PARAMS
        diag = np.arange(npar)
        normal[:, diag, diag] += 1e-6 * (1.0 + normal[:, diag, diag])
        frozen = np.flatnonzero(~act)
        if frozen.size:
            normal[frozen, 1:, :] = 0.0
            normal[frozen, :, 1:] = 0.0
            normal[np.ix_(frozen, np.arange(1, normal.shape[1]), np.arange(1, normal.shape[1]))] = \
                np.eye(normal.shape[1] - 1)
            rhs[frozen, 1:] = 0.0
        cross = normal[:, :npar, npar]
        sol = np.linalg.solve(normal[:, :npar, :npar], np.stack([rhs[:, :npar], cross], axis=2))
        num = float(np.sum(rhs[act, npar]) - np.sum(np.einsum("li,li->l", cross, sol[:, :, 0])[act]))
        den = float(np.sum(normal[act, npar, npar]) - np.sum(np.einsum("li,li->l", cross, sol[:, :, 1])[act]))
        ds = float(np.clip(num / den, -0.5 * s, 0.5 * s)) if den > 0 else 0.0
        step = sol[:, :, 0] - sol[:, :, 1] * np.where(act, ds, 0.0)[:, None]
        self.edge = float(np.clip(s + ds, 0.05, 5.0))
        step[:, 1:] = np.clip(step[:, 1:], -1.0, 1.0)
        # damp lenses that oscillate (the step reverses the last one); as kernels.apply_steps
        flip = np.einsum("li,li->l", step[:, 1:3], self.prev_step[idx, 1:3]) < 0
        step[flip, 1:] *= 0.5
        # idx holds each lens once (`sweep` makes it unique, one colour class): a per-lens update, not an
        # accumulation of hits, written as one
        self.amp[idx] = self.amp[idx] + step[:, 0]
        self.cx[idx] = self.cx[idx] + step[:, 1]
        self.cy[idx] = self.cy[idx] + step[:, 2]
        # a lens' sub-image radius may differ from the typical one by a pixel (size defects), no more:
        # two strongly overlapping discs could otherwise trade radius against amplitude without end
        self.radius[idx] = np.clip(self.radius[idx] + step[:, 3], self.r_norm - 1.0, self.r_norm + 1.0)
        self.prev_step[idx] = step
        self.last_step[idx] = np.hypot(step[:, 1], step[:, 2])


def _plane_gradient(field: np.ndarray, on: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray]:
    """Gradient (d/dcolumn, d/drow) at every cell of a 2-D field of the least-squares plane through the
    cells marked `on` within `reach` steps; 0 where fewer than three, or only collinear ones, are there.
    A full window is point-symmetric, so a quadratic field's gradient comes out unbiased; 5 x 5 has 1/25
    of a two-cell central difference's noise variance."""
    rows, cols = field.shape
    pf, po = np.pad(field, reach), np.pad(on, reach)
    n, sj, si, sjj, sji, sii, sa, saj, sai = np.zeros((9, rows, cols))
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            o = po[reach + di: reach + di + rows, reach + dj: reach + dj + cols]
            a = pf[reach + di: reach + di + rows, reach + dj: reach + dj + cols]
            n += o
            sj += dj * o
            si += di * o
            sjj += dj * dj * o
            sji += dj * di * o
            sii += di * di * o
            sa += a
            saj += dj * a
            sai += di * a
    with np.errstate(divide="ignore", invalid="ignore"):
        mj, mi = sj / n, si / n
        cjj, cji, cii = sjj - n * mj * mj, sji - n * mj * mi, sii - n * mi * mi
        bj, bi = saj - sa * mj, sai - sa * mi
        det = cjj * cii - cji * cji
        ok = (n >= 3) & (det > 1e-9 * np.maximum(n, 1) ** 2)
        gj = np.where(ok, (bj * cii - bi * cji) / det, 0.0)
        gi = np.where(ok, (bi * cjj - bj * cji) / det, 0.0)
    return gj, gi


# ------------------------------------------------------------------------------------------ calibrate


def calibrate(img: np.ndarray, *, expected_pitch_px: float | None = None,
              expected_shape: tuple[int, int] | None = None, packing: str = "square") -> Grid:
    """Find, measure and index every microlens of a white image; fit the global grid.

    `img`: float, black-subtracted, normalized (1 = full scale) white image. `expected_pitch_px`: the
    config's sub-image pitch (the found pitch must lie within 10 %). `expected_shape`: (N_H, N_W) of the
    MLA; the grid then has exactly that many rows and columns, U(1,1) being the array's top-left lens even
    if border lenses are dim or cut by the frame. `packing`: the MLA's ("square" or "hex", the config's
    mla.packing; mlaqc.optics.lattice's U(m,n) convention). Raises InputError for an image that cannot be
    calibrated, or whose lattice is not of `packing`.
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
    return _assemble(img.shape, lattice, lat_j, lat_i, discs, active, expected_shape)


def _colours(lat_j: np.ndarray, lat_i: np.ndarray, packing: str) -> np.ndarray:
    """Sweep colour of each lattice point such that side neighbours (whose discs overlap) differ: square
    red-black, hex (j + 2 i) mod 3 (its six neighbours step j, i or i - j by one)."""
    if packing == "hex":
        return (lat_j + 2 * lat_i) % 3
    return (lat_i + lat_j) % 2


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
                     expected_shape=(cfg.mla.count_h, cfg.mla.count_w), packing=cfg.mla.packing)


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


def _measure(img: np.ndarray, px: np.ndarray, py: np.ndarray, lat_j: np.ndarray, lat_i: np.ndarray,
             basis: np.ndarray, radius0: float, packing: str = "square") -> tuple[_Discs, np.ndarray]:
    """Joint disc fit of every lens (see the module docstring), in two stages:

    1. a central block of lenses, from a wide edge down: the edge width, the typical radius and a lattice
       good to a few hundredths of a pixel everywhere (the Fourier one is good to ~0.1 px at the corners);
    2. every lens, from there: N_SWEEPS sweeps, the capture of lenses far off the lattice, then more
       sweeps for the lenses that still move and their neighbours only.
    """
    pitch = float(np.sqrt(abs(np.linalg.det(basis))))
    band = BAND * max(1.0, pitch / 20.0)
    # lattice neighbours whose discs can overlap a lens' fitting annulus: the first ring, and the second
    # too for discs large against the pitch
    spacing = float(np.min(np.hypot(basis[0], basis[1])))
    second = (math.sqrt(3.0) if packing == "hex" else 2.0) * spacing  # distance to the second ring
    ring = 1 if second > 2.0 * radius0 + band + 0.5 + 4.0 else 2
    # stage 1: a block of about SUBSET x SUBSET lenses round the brightest part of the centre
    cj, ci = np.median(lat_j), np.median(lat_i)
    half = SUBSET // 2
    # its lenses are fitted with one ring of lenses round them held on the lattice (amplitude only); hex:
    # two rings, as the first ring's amplitude, fitted with its outer neighbours (not in the block) left
    # out, is inflated by their overlaps and would push the block's edge lenses inwards (0.05 px measured)
    pad = 2 if packing == "hex" else 1
    block = (np.abs(lat_j - cj) <= half + pad) & (np.abs(lat_i - ci) <= half + pad)
    inner = (np.abs(lat_j - cj) <= half) & (np.abs(lat_i - ci) <= half)
    colour = _colours(lat_j, lat_i, packing)
    px, py = px.copy(), py.copy()
    lattice_x, lattice_y = px, py
    halves = HALVES_ORDER[packing]
    sub = _DiscFit(img, px[block], py[block], radius0, _lattice_neighbours(lat_j[block], lat_i[block], ring, packing),
                   colour[block], halves, spacing)
    sub.init_amplitude(radius0)
    sub.set_band(band)
    ref = float(np.percentile(sub.amp, 90)) if sub.amp.size else 0.0
    act = inner[block] & (sub.amp > 0.2 * ref) & (sub.valid_fraction >= MIN_VALID_FRACTION)
    if np.count_nonzero(act) >= MIN_LENSES:
        sub.sweep(max(0.8, 0.05 * pitch), act, weighted=False)
        sub.edge = max(0.4, 0.025 * pitch)
        for it in range(BLOCK_SWEEPS):
            sub.sweep(None, act, weighted=it >= 1)
        radius0 = float(np.median(sub.radius[act]))
        edge0 = sub.edge
        # a better lattice from the block's centres (the Fourier pitch is good to ~1e-4): every lens
        # then starts within a few hundredths of a pixel; the block's lenses start where they were found
        design = np.stack([np.ones(act.sum()), lat_j[block][act], lat_i[block][act]], 1)
        coef = np.linalg.lstsq(design, np.stack([sub.cx[act], sub.cy[act]], 1), rcond=None)[0]
        if np.count_nonzero(act) >= 25:
            px = coef[0, 0] + coef[1, 0] * lat_j + coef[2, 0] * lat_i
            py = coef[0, 1] + coef[1, 1] * lat_j + coef[2, 1] * lat_i
        lattice_x, lattice_y = px.copy(), py.copy()
        done = np.flatnonzero(block)[act]
        px[done], py[done] = sub.cx[act], sub.cy[act]
    else:
        edge0 = max(0.4, 0.025 * pitch)
    # stage 2: every lens
    neighbours = _lattice_neighbours(lat_j, lat_i, ring, packing)
    fit = _DiscFit(img, px, py, radius0, neighbours, colour, halves, spacing)
    fit.edge = edge0
    fit.init_amplitude(radius0)
    ref = float(np.percentile(fit.amp, 90)) if fit.amp.size else 0.0
    fit.set_band(band)
    active = (fit.amp > 0.2 * ref) & (fit.valid_fraction >= MIN_VALID_FRACTION)
    if np.count_nonzero(active) < MIN_LENSES:
        raise InputError(f"only {int(np.count_nonzero(active))} microlens sub-images found in the white image "
                         f"(at least {MIN_LENSES} are needed)")
    side = neighbours[:, :_FIRST_RING[packing]]  # the first ring: who is coupled to whom
    for it in range(N_SWEEPS):
        if it == 1:
            fit.set_slopes(lat_j, lat_i, basis, active)
            off = active & (np.hypot(fit.cx - lattice_x, fit.cy - lattice_y) > COUPLED_PX)
            fit.coupled[_with_neighbours(np.flatnonzero(off), side)] = True
            # a new objective (weights, slopes): its first step is no oscillation to damp
            fit.prev_step[:] = 0.0
        fit.sweep(fit.edge, active, weighted=it >= 1)  # the edge width is known from the block
    # lenses the sharp edge cannot pull in (beyond ~1 px off the lattice: big defects) fit badly; they
    # are captured with a wide edge of their own, then refined; only they and their neighbours step
    per_px = fit.rss / np.maximum(fit.npix, 1)
    typical = float(np.median(per_px[active]))
    far = active & ((per_px > 3.0 * typical) | (fit.last_step > 0.3))
    if far.any():
        fit.wide, fit.wide_edge = far, max(WIDE_EDGE, 4.0 * fit.edge)
        group = _with_neighbours(np.flatnonzero(far), side)
        fit.coupled[group] = True
        for _ in range(3):
            fit.sweep(fit.edge, active, weighted=True, lenses=group)
        fit.wide = None
        # where the wide edges left the group is no fit of the sharp one: it steps again below
        fit.last_step[group] = np.inf
    for _ in range(MAX_EXTRA):  # until every lens has settled
        moving = np.flatnonzero(active & (fit.last_step > SETTLED_PX))
        if not moving.size:
            break
        fit.sweep(fit.edge, active, weighted=True, lenses=_with_neighbours(moving, side))
    fit.valid_fraction = fit.rim_in_frame()
    discs = _Discs(fit.cx, fit.cy, fit.amp, fit.radius, fit.edge, fit.valid_fraction)
    return discs, active


_FIRST_RING = {"square": 8, "hex": 6}  # neighbours in the first ring (square: edges and diagonals)


def _lattice_neighbours(lat_j: np.ndarray, lat_i: np.ndarray, ring: int = 1, packing: str = "square") -> np.ndarray:
    """(n, k) indices of each candidate's lattice neighbours within `ring` steps (-1 where there is none),
    nearest ring first: square (2 ring + 1)^2 - 1 (the first 8 the first ring), hex 3 ring (ring + 1)
    (the first 6 the first ring; axial steps (dj, di) with max(|dj|, |di|, |dj + di|) <= ring)."""
    j0, i0 = lat_j.min(), lat_i.min()
    table = np.full((lat_i.max() - i0 + 1 + 2 * ring, lat_j.max() - j0 + 1 + 2 * ring), -1)
    table[lat_i - i0 + ring, lat_j - j0 + ring] = np.arange(lat_j.size)
    if packing == "hex":
        steps = lambda o: max(abs(o[0]), abs(o[1]), abs(o[0] + o[1]))  # noqa: E731 (hex distance)
    else:
        steps = lambda o: max(abs(o[0]), abs(o[1]))  # noqa: E731
    offsets = sorted(((di, dj) for di in range(-ring, ring + 1) for dj in range(-ring, ring + 1)
                      if (di or dj) and steps((di, dj)) <= ring), key=steps)
    return np.stack([table[lat_i - i0 + ring + di, lat_j - j0 + ring + dj] for di, dj in offsets], axis=1)


def _with_neighbours(lenses: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    out = np.concatenate([lenses, neighbours[lenses].ravel()])
    return np.unique(out[out >= 0])


def _neighbourhood_median(values: np.ndarray, size: int = 5) -> np.ndarray:
    """NaN-ignoring median over a size x size window of a 2-D array (NaN where the window is empty)."""
    pad = size // 2
    padded = np.pad(values.astype(np.float64), pad, constant_values=np.nan)
    win = np.sort(np.lib.stride_tricks.sliding_window_view(padded, (size, size)).reshape(*values.shape, -1), axis=-1)
    count = np.count_nonzero(~np.isnan(win), axis=-1)  # NaNs sort last
    lo = np.take_along_axis(win, np.maximum(count - 1, 0)[..., None] // 2, axis=-1)[..., 0]
    hi = np.take_along_axis(win, (count // 2)[..., None], axis=-1)[..., 0]
    return np.where(count > 0, 0.5 * (lo + hi), np.nan)


def _assemble(shape, lattice, lat_j, lat_i, discs: _Discs, active, expected_shape) -> Grid:
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
    if expected_shape is not None and n_found < 0.5 * rows * cols:
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
    hom, k, scale, used, rms = _fit_model(uu[found_w], vv[found_w], mx[found_w], my[found_w], centre,
                                          lattice, (r0 + i0, c0 + j0), (rows, cols), span)
    gx, gy = _model_xy(hom, k, centre, scale, uu, vv)
    # lenses whose predicted window leaves the frame entirely were never candidates: clipped + missing
    clipped = (vfrac < 1.0) | ~np.isfinite(vfrac)
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
    )


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
