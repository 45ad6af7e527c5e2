"""Checked, convenient access to an InspectionResult and its grid, shared by every report file."""

from __future__ import annotations

import math
from functools import cached_property
from typing import Any

import numpy as np

from mlaqc.errors import InputError
from mlaqc.inspection.results import METRICS, InspectionResult, LazyReferences
from mlaqc.optics.lattice import PACKINGS, Lattice
from mlaqc.parallel import cores, thread_map


class View:
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
        ref = result.reference  # LazyReferences: kept lazy, the report reads the gallery's lenses only
        self.reference = ref if isinstance(ref, LazyReferences) else np.asarray(ref)
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
        packing = getattr(grid, "packing", "square") or "square"
        _check(packing in PACKINGS, f"its grid's packing is {packing!r}, not one of {list(PACKINGS)}")
        self.lattice = Lattice(packing, self.rows, self.cols)

    @property
    def packing(self) -> str:
        return self.lattice.packing

    @property
    def hex(self) -> bool:
        return self.lattice.hex

    @cached_property
    def affine(self) -> np.ndarray | None:
        """(2, 3) affine map from lattice units to pixels fitted to the grid's predicted centres (None when
        fewer than three non-collinear lenses are predicted)."""
        return lattice_affine(self.lattice, self.gx, self.gy)

    def _grid_array(self, name: str) -> np.ndarray:
        arr = np.asarray(getattr(self.result.grid, name, None))
        _check(arr.shape == (self.rows, self.cols), f"grid.{name} is {arr.shape}, not {(self.rows, self.cols)}")
        return arr if arr.dtype == bool else arr.astype(float)

    @property
    def pitch(self) -> float:
        """Lens pitch in pixels: the mean of the grid's x and y pitch; on a hex grid the spacing of a row's
        lenses, read from the grid's centres (its rows are only sqrt(3)/2 of it apart)."""
        if self.hex and self.affine is not None:
            return float(np.hypot(*self.affine[:, 0]))
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
        out = np.empty(img.shape, np.uint8)

        def band(rows: slice) -> None:  # element by element: bands on the pool's threads give the same bytes
            x = img[rows] - np.float32(lo)
            x *= np.float32(255.0 / (hi - lo))
            x += np.float32(0.5)
            # fmax/fmin clip as np.clip does and send NaN to 0 (the NaN-ignoring pair): NaN black, ±inf clipped
            np.fmax(x, np.float32(0), out=x)
            np.fmin(x, np.float32(255), out=x)
            out[rows] = x

        edges = np.linspace(0, img.shape[0], 2 * cores() + 1).astype(int) if img.ndim == 2 else [0, len(img)]
        thread_map(band, [slice(a, b) for a, b in zip(edges[:-1], edges[1:])])
        return out


def lattice_affine(lattice: Lattice, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray | None:
    """(2, 3) least-squares affine map [x, y] = A @ [u, v, 1] from lattice units (pitches from U(1,1)'s centre,
    `Lattice.uv`) to the pixel centres (rows, cols) given (NaN ignored); None when fewer than three
    non-collinear centres are finite. Its first column is a row's pitch vector in pixels: the report and
    the app draw cells and find the lens under the cursor with it."""
    x, y = np.asarray(x_px, float).ravel(), np.asarray(y_px, float).ravel()
    r, c = np.divmod(np.arange(lattice.rows * lattice.cols), lattice.cols)
    u, v = lattice.uv(r, c)
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3:
        return None
    design = np.column_stack([u[ok], v[ok], np.ones(int(ok.sum()))])
    coef, _, rank, _ = np.linalg.lstsq(design, np.column_stack([x[ok], y[ok]]), rcond=None)
    return coef.T.copy() if rank == 3 else None


def cell_outline_px(packing: str, affine: np.ndarray) -> np.ndarray:
    """(k, 2) pixel offsets of a lens' cell corners from its centre (`cell_vertices` through the affine map)."""
    from mlaqc.optics.lattice import cell_vertices

    return cell_vertices(packing) @ affine[:, :2].T


def lens_at_px(lattice: Lattice, affine: np.ndarray, grid_x_px: np.ndarray, grid_y_px: np.ndarray,
               x: Any, y: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """0-based (row, col) of the lens whose cell holds pixel (x, y) and whether it is a lens of the array:
    `Lattice.nearest` (the square or hexagon round each lattice point) in the lattice units of the grid's
    affine fit, then again in a frame anchored on that lens' own predicted centre, so that a grid's smooth
    distortion (radial, keystone) does not move the cell boundaries."""
    unit = Lattice(lattice.packing, lattice.rows, lattice.cols)
    u0, v0 = unit.centre_uv()
    inv = np.linalg.inv(affine[:, :2])
    px, py = np.asarray(x, float), np.asarray(y, float)
    u, v = _apply(inv, px - affine[0, 2], py - affine[1, 2])
    r, c, inside = unit.nearest(u - u0, v - v0)
    rr, cc = np.clip(r, 0, lattice.rows - 1), np.clip(c, 0, lattice.cols - 1)
    gx, gy = np.asarray(grid_x_px, float)[rr, cc], np.asarray(grid_y_px, float)[rr, cc]
    anchored = inside & np.isfinite(gx) & np.isfinite(gy)
    uc, vc = unit.uv(rr, cc)
    lu, lv = _apply(inv, np.where(anchored, px - gx, 0.0), np.where(anchored, py - gy, 0.0))
    r2, c2, in2 = unit.nearest(uc + lu - u0, vc + lv - v0)
    return np.where(anchored, r2, r), np.where(anchored, c2, c), np.where(anchored, in2, inside)


def _apply(m: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 2x2 matrix `m` applied to points (x, y) (arrays broadcast)."""
    return m[0, 0] * x + m[0, 1] * y, m[1, 0] * x + m[1, 1] * y


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
