"""The microlens lattice: where lens U(m,n) sits, which lenses are its neighbours, and what its cell and
aperture are, for square and hexagonal packing. Every stage asks this module instead of doing grid
arithmetic of its own.

Index convention (both packings): U(m, n) is row m from the top, column n from the left, 1-based; per-lens
tables have shape (rows, cols) and [m-1, n-1] is U(m, n) ("offset coordinates" for hex).

- square: centres at (n-1, m-1) * pitch.
- hex: rows are pitch * sqrt(3)/2 apart; even rows (m = 2, 4, ...) are shifted +pitch/2 in x. A lens has
  6 neighbours at one pitch: two in its row, two in the row above and two below. Its cell (the region
  nearer its centre than any other's) is a hexagon with flat sides facing its row neighbours: pitch wide,
  2 pitch / sqrt(3) tall, area pitch^2 sqrt(3)/2.

Positions in "lattice units" (u, v) are in pitches from U(1,1)'s centre, u along x (right), v along y
(down). `centres` gives positions in any length unit relative to the array's centre (the centre of the
bounding box of the lens centres; the MLA frame of the tracer).

A third packing would add its name to PACKINGS and its rules in `_row_step`, `_row_offset`,
`neighbour_offsets`, `cell_vertices` and `nearest`; besides this module, the compiled tracer's cell lookup,
the calibration's Fourier peaks and the signature patch's shape know the packing (docs/architecture.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mlaqc.errors import InputError

PACKINGS = ("square", "hex")
SQRT3_2 = math.sqrt(3.0) / 2.0
INV_ROW_PAIR_HEX = 0.5 / SQRT3_2  # pairs of hex rows (even and odd) per unit of v (pitches)

CONVENTIONS = {
    "square": "U(m,n): row m from the top, column n from the left, 1-based; centres (n-1, m-1) pitches "
              "from U(1,1)'s, x right, y down",
    "hex": "U(m,n): row m from the top, column n from the left, 1-based; rows pitch*sqrt(3)/2 apart, even "
           "rows (m = 2, 4, ...) shifted +pitch/2 in x; centres (n-1 + 0.5*[m even], (m-1)*sqrt(3)/2) "
           "pitches from U(1,1)'s, x right, y down",
}


def _row_step(packing: str) -> float:
    """Distance between rows in pitches."""
    return SQRT3_2 if packing == "hex" else 1.0


def _row_offset(packing: str, r: Any) -> Any:
    """x offset (pitches) of 0-based row r: +1/2 on hex rows r = 1, 3, ... (m even)."""
    if packing == "hex":
        return 0.5 * (np.asarray(r) % 2)
    return np.zeros(np.shape(r)) if np.ndim(r) else 0.0


def neighbour_offsets(packing: str, r_parity: int, diagonal: bool = True) -> list[tuple[int, int]]:
    """(dr, dc) index steps to a lens' nearest neighbours, for a lens on a row of parity r_parity
    (0-based row % 2): square 4 (edge) + 4 (diagonal, when `diagonal`), hex 6 (row, then the rows above
    and below). The order is fixed: it is the tie-break wherever the first of equals wins."""
    if packing == "hex":
        lo = -1 if r_parity == 0 else 0  # the unshifted rows' neighbours above/below sit half a pitch left
        return [(0, -1), (0, 1), (-1, lo), (-1, lo + 1), (1, lo), (1, lo + 1)]
    edge = [(0, -1), (0, 1), (-1, 0), (1, 0)]
    return edge + ([(-1, -1), (-1, 1), (1, -1), (1, 1)] if diagonal else [])


def cell_vertices(packing: str) -> np.ndarray:
    """(k, 2) vertices (u, v) of the cell round a lens centre, in pitches, counterclockwise as displayed."""
    if packing == "hex":
        a = np.radians(np.arange(6) * 60.0 + 30.0)  # pointy top: vertices at 30, 90, ... degrees
        radius = 1.0 / math.sqrt(3.0)
        return np.stack([radius * np.cos(a), -radius * np.sin(a)], axis=1)
    return np.array([[0.5, 0.5], [0.5, -0.5], [-0.5, -0.5], [-0.5, 0.5]])


@dataclass(frozen=True)
class Lattice:
    """A rows x cols array of lenses `pitch` apart (any length unit; 1 = lattice units) in `packing`."""

    packing: str
    rows: int
    cols: int
    pitch: float = 1.0

    def __post_init__(self) -> None:
        if self.packing not in PACKINGS:
            raise ValueError(f"packing must be one of {PACKINGS}, got {self.packing!r}")

    @classmethod
    def of(cls, cfg: Any, unit_um: float = 1000.0) -> Lattice:
        """The lattice of a CameraConfig's MLA, lengths in units of `unit_um` µm (default mm)."""
        mla = cfg.mla
        return cls(mla.packing, mla.count_h, mla.count_w, mla.pitch_um / unit_um)

    @property
    def hex(self) -> bool:
        return self.packing == "hex"

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def row_step(self) -> float:
        """Distance between rows (pitch units of this lattice)."""
        return self.pitch * _row_step(self.packing)

    @property
    def cell_area(self) -> float:
        """Area of one lens' cell."""
        return self.pitch * self.row_step

    @property
    def span_uv(self) -> tuple[float, float]:
        """Extent (u, v) of the lens centres in pitches (max - min)."""
        shifted = 0.5 if self.hex and self.rows > 1 else 0.0
        return (self.cols - 1 + shifted, (self.rows - 1) * _row_step(self.packing))

    @property
    def extent(self) -> tuple[float, float]:
        """Width and height of the array's outline (the union of its cells), in this lattice's unit."""
        su, sv = self.span_uv
        cell_h = 2.0 / math.sqrt(3.0) if self.hex else 1.0
        return ((su + 1.0) * self.pitch, (sv + cell_h) * self.pitch)

    def uv(self, r: Any, c: Any) -> tuple[np.ndarray, np.ndarray]:
        """Lattice units (u, v) of 0-based (row, col) indices (arrays broadcast; may lie off the array)."""
        r = np.asarray(r, dtype=np.float64)
        c = np.asarray(c, dtype=np.float64)
        return c + _row_offset(self.packing, r.astype(np.int64)), r * _row_step(self.packing)

    def centre_uv(self) -> tuple[float, float]:
        """Lattice units of the array's centre (the middle of the lens centres' bounding box)."""
        su, sv = self.span_uv
        return 0.5 * su, 0.5 * sv

    def position(self, r: Any, c: Any) -> tuple[np.ndarray, np.ndarray]:
        """Centre (x, y) of 0-based lens (r, c) relative to the array's centre, in this lattice's unit."""
        u, v = self.uv(r, c)
        u0, v0 = self.centre_uv()
        return (u - u0) * self.pitch, (v - v0) * self.pitch

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) arrays of every lens' centre (x, y) relative to the array's centre."""
        r, c = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        return self.position(r, c)

    def nearest(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """0-based (row, col) of the lattice point nearest each point (x, y) (array-centred frame), and
        whether it is a lens of the array: the cell (square or hexagon) the point lies in."""
        u0, v0 = self.centre_uv()
        u = np.asarray(x, dtype=np.float64) / self.pitch + u0
        v = np.asarray(y, dtype=np.float64) / self.pitch + v0
        if not self.hex:
            r, c = np.floor(v + 0.5), np.floor(u + 0.5)
        else:
            r, c, _, _ = hex_cell(u, v)
        inside = (r >= 0) & (r < self.rows) & (c >= 0) & (c < self.cols)
        return r.astype(np.int64), c.astype(np.int64), inside

    def nearest_on_grid(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        """`nearest` for every point of the grid of columns x (w,) and rows y (h,): (h, w) flat indices
        (row * cols + col; any value off the array) and whether each is a lens of the array. The same cells
        as `nearest`, each rule worked per grid row or column where it depends on one of them alone (a
        report's hex panel is ~10^6 points)."""
        u0, v0 = self.centre_uv()
        u = np.asarray(x, dtype=np.float64)[None, :] / self.pitch + u0
        v = np.asarray(y, dtype=np.float64)[:, None] / self.pitch + v0
        if not self.hex:
            return self._flat(np.floor(v + 0.5), np.floor(u + 0.5))
        (ra, ca, dua, dva), (rb, cb, dub, dvb) = _hex_candidates(u, v)
        take = dub * dub + dvb * dvb < dua * dua + dva * dva
        (flat_a, in_a), (flat_b, in_b) = self._flat(ra, ca), self._flat(rb, cb)
        return np.where(take, flat_b, flat_a), np.where(take, in_b, in_a)

    def _flat(self, r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices of rows r (h, 1) and columns c (1, w) (floats), and whether each is on the array."""
        inside = ((r >= 0) & (r < self.rows)) & ((c >= 0) & (c < self.cols))
        return r.astype(np.int64) * self.cols + c.astype(np.int64), inside

    def neighbours(self, diagonal: bool = True) -> np.ndarray:
        """(rows * cols, k) flat indices of every lens' nearest neighbours (`neighbour_offsets` order), -1
        where the neighbour lies off the array."""
        r, c = np.divmod(np.arange(self.rows * self.cols), self.cols)
        out = []
        n_off = len(neighbour_offsets(self.packing, 0, diagonal))
        for j in range(n_off):
            dr = np.array([neighbour_offsets(self.packing, p, diagonal)[j][0] for p in (0, 1)])[r % 2]
            dc = np.array([neighbour_offsets(self.packing, p, diagonal)[j][1] for p in (0, 1)])[r % 2]
            rr, cc = r + dr, c + dc
            ok = (rr >= 0) & (rr < self.rows) & (cc >= 0) & (cc < self.cols)
            out.append(np.where(ok, rr * self.cols + cc, -1))
        return np.stack(out, axis=1)

    def neighbour_steps(self, diagonal: bool = True) -> np.ndarray:
        """(2, k, 2) (dr, dc) steps to the neighbours for rows of parity 0 and 1."""
        return np.array([neighbour_offsets(self.packing, p, diagonal) for p in (0, 1)])

    def to_json_dict(self) -> dict[str, Any]:
        """The lattice as report.json and grid.json state it."""
        return {"packing": self.packing, "rows": self.rows, "cols": self.cols,
                "row_step_pitch": _row_step(self.packing), "convention": CONVENTIONS[self.packing]}


def hex_cell(u, v):
    """The hexagonal cell (Voronoi) of points (u, v) in lattice units from U(1,1)'s centre: row, column
    (floats; may lie off the array) and the offset (du, dv) from that lens' centre, in pitches. The lattice
    is two rectangular ones (1 by sqrt(3)): the even 0-based rows, and the odd rows shifted by (1/2,
    sqrt(3)/2); the nearer of their nearest points (each by rounding) wins, the even row's on a tie
    (Lattice.nearest is this). Plain arithmetic and selects: the compiled tracer
    (mlaqc.optics.kernel_geometry.hex_locate) does the same operations."""
    (ra, ca, dua, dva), (rb, cb, dub, dvb) = _hex_candidates(u, v)
    take = dub * dub + dvb * dvb < dua * dua + dva * dva
    return np.where(take, rb, ra), np.where(take, cb, ca), np.where(take, dub, dua), np.where(take, dvb, dva)


def _hex_candidates(u, v):
    """`hex_cell`'s two candidates: (row, column, du, dv) of the nearest even-row lattice point, then of
    the nearest odd-row one. Row and dv follow v alone, column and du u alone."""
    ja = np.floor(v * INV_ROW_PAIR_HEX + 0.5)  # nearest even row: 2 ja
    jb = np.floor(v * INV_ROW_PAIR_HEX)  # nearest odd row: 2 jb + 1
    ca, cb = np.floor(u + 0.5), np.floor(u)  # their nearest columns (odd rows' centres at cb + 1/2)
    ra, rb = 2.0 * ja, 2.0 * jb + 1.0
    return (ra, ca, u - ca, v - ra * SQRT3_2), (rb, cb, u - (cb + 0.5), v - rb * SQRT3_2)


def hex_edge(du, dv):
    """Distance (pitches) from a point at offset (du, dv) from its hexagon's centre to the hexagon's
    nearest side: the sides face the 6 neighbours, half a pitch out along (1, 0) and (1/2, ±sqrt(3)/2)."""
    a = np.abs(du)
    b = np.abs(0.5 * du + SQRT3_2 * dv)
    c = np.abs(0.5 * du - SQRT3_2 * dv)
    return 0.5 - np.maximum(a, np.maximum(b, c))


def packing_of(data: Any, source: str) -> str:
    """The packing named by a JSON dict's "packing" key; files written before hex support have none and
    are square. InputError for anything else."""
    value = data.get("packing", "square") if isinstance(data, dict) else "square"
    if value not in PACKINGS:
        raise InputError(f"{source}: \"packing\" must be one of {list(PACKINGS)}, got {value!r}")
    return value
