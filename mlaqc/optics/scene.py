"""Object-space scenes and their ray sources, importance-sampled so (almost) every ray reaches the sensor.

Point sources are sampled forward: rays from the point to points drawn uniformly on the entrance-pupil
disc (the lens rim at the front vertex plane), weight cos^3 (isotropic emitter). Planes (white, texture)
are sampled from the image side: a point uniform on the MLA and a point uniform on the rear aperture disc,
weight cos^4 (dPhi = L cos cos' dA dA' / d^2); the ray is then traced backwards through the main lens,
which applies vignetting and Fresnel losses and finds the object point whose radiance it carries. Radiance
is conserved along a ray and refraction is reversible, so this is exact, and unlike forward sampling it
wastes no rays on the main lens' large spherical-aberration blur (about 1.7 mm at the MLA for Table 1). Object-space x, y follow the camera frame (x right, y down as seen from
the camera); like any camera, the main lens forms an inverted image on the MLA.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mlaqc.errors import InputError
from mlaqc.optics.lattice import SQRT3_2
from mlaqc.optics.raytrace import Rays, hex_cell
from mlaqc.optics.unitcircle import cos_sin_2pi


@dataclass(frozen=True)
class WhiteScene:
    """A uniform Lambertian plane filling the field: the calibration ('white') image."""

    kind: str = "white"


@dataclass(frozen=True)
class PointScene:
    """Isotropic point sources: (x_mm, y_mm) on the object plane and photons each sends into the pupil."""

    points_mm: tuple[tuple[float, float], ...] = ((0.0, 0.0),)
    photons: float = 1e6
    kind: str = "points"


@dataclass(frozen=True)
class TextureScene:
    """A Lambertian plane with radiance from a grey image, stretched over the imaged field."""

    radiance: np.ndarray = field(default_factory=lambda: np.ones((1, 1)))
    kind: str = "texture"

    @classmethod
    def from_file(cls, path: str | Path) -> TextureScene:
        """Load a PNG/TIFF/NPY as radiance in [0, 1] (colour images are averaged to grey)."""
        p = Path(path)
        if not p.is_file():
            raise InputError(f"texture image {str(p)!r} does not exist")
        if p.suffix.lower() == ".npy":
            try:
                img = np.load(p, allow_pickle=False)
            except Exception as exc:  # noqa: BLE001 - any decoder failure is an input error
                raise InputError(f"texture image {str(p)!r} is not a readable NPY file ({exc.__class__.__name__})") from None
        else:
            import cv2

            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise InputError(f"texture image {str(p)!r} is not a readable image file")
        img = np.asarray(img, dtype=np.float64)
        if img.ndim == 3:
            img = img.mean(axis=2)
        if img.ndim != 2 or img.size == 0 or not np.all(np.isfinite(img)):
            raise InputError(f"texture image {str(p)!r} must be a non-empty 2-D image of finite values")
        top = img.max()
        if top <= 0 or img.min() < 0:
            raise InputError(f"texture image {str(p)!r} must have non-negative values and not be all black")
        return cls(radiance=img / top)


Scene = WhiteScene | PointScene | TextureScene


@dataclass(frozen=True)
class SourceRegion:
    """Where object points are drawn: a rectangle on the object plane (mm) and the pupil disc."""

    z_object_mm: float
    half_x_mm: float
    half_y_mm: float
    pupil_radius_mm: float
    magnification: float  # |image size / object size| at the MLA (paraxial)
    center_x_mm: float = 0.0  # object-side conjugate of the MLA's centre
    center_y_mm: float = 0.0


@dataclass(frozen=True)
class ImageRegion:
    """Where image-side rays are drawn: a rectangle on the MLA mid-plane and the main lens' rear aperture."""

    z_mla_mm: float
    half_x_mm: float
    half_y_mm: float
    z_exit_mm: float  # the main lens' rear vertex plane
    exit_radius_mm: float
    center_x_mm: float = 0.0  # the MLA's lateral shift
    center_y_mm: float = 0.0


@dataclass(frozen=True)
class CellGrid:
    """The MLA's cells, one ring of padding cells included, as the stratified image-side sampler draws them.

    Cell (row, col), -1 <= row <= rows and -1 <= col <= cols, is on a square array the square [x0 + col*p,
    x0 + (col+1)*p) x [y0 + row*p, ...) of the MLA frame; on a hex array (`packing`) the hexagon round the
    lattice point (x0 + (col + [row odd]/2) p, y0 + row p sqrt(3)/2) ((x0, y0): U(1,1)'s centre), drawn
    as the rhombus spanned by the lattice vectors (p, 0) and (p/2, p sqrt(3)/2) round that point, folded
    into the hexagon by lattice translations (`hex_cell_offsets`: both tile the plane, so the fold is one to
    one and keeps area: uniform on the rhombus is uniform on the hexagon, and the cell's stratification is
    kept piece by piece). (x, y) of the MLA frame map to the start plane (camera frame, z of the MLA) by
    the MLA's rotation and shift, projected along the axis (area scale |det| of that 2 x 2 map).

    The aperture point is drawn as a' on a square of half-side `square_half_mm` and moved to
    a = a' + Phi(h, a') (`aperture_point`), h the start's offset from its cell centre: a ray then lands
    where the ray from a' through the cell centre would, to the accuracy of Phi's fit to the design
    microlens (render.aperture_shift). A pixel's preimage is so nearly a box in a' alone, which the Sobol
    points fill evenly, instead of a region whose edges move with the start point. For each start the map
    a' -> a is smooth and one-to-one and the weight carries its Jacobian, so the estimate stays unbiased
    whatever Phi is; the square is large enough that its image covers the aperture disc for every start.
    """

    x0_mm: float
    y0_mm: float
    pitch_mm: float
    rows: int
    cols: int
    r00: float = 1.0
    r01: float = 0.0
    r10: float = 0.0
    r11: float = 1.0
    shift_x_mm: float = 0.0
    shift_y_mm: float = 0.0
    shift_coef: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # Phi's coefficients (aperture_point)
    shift_r_mm: float = 1.0  # the cell corner radius Phi is scaled by
    square_half_mm: float = 0.0  # 0: the rear aperture's radius
    packing: str = "square"

    @property
    def padded_cols(self) -> int:
        return self.cols + 2

    @property
    def padded_rows(self) -> int:
        return self.rows + 2

    @property
    def area_mm2(self) -> float:
        """Start-plane area of all padded cells."""
        det = abs(self.r00 * self.r11 - self.r01 * self.r10)
        cell = self.pitch_mm ** 2 * (SQRT3_2 if self.packing == "hex" else 1.0)
        return self.padded_cols * self.padded_rows * cell * det

    def cell_id(self, row, col):
        """Flat index of padded cell (row, col) (row, col from -1)."""
        return (row + 1) * self.padded_cols + (col + 1)


FOUR_OVER_PI = 4.0 / np.pi  # square around a disc over the disc: the weight of a ray drawn on the square

# Samplers take their uniform draws `u` (shape (4, n) or (2, n), values in [0, 1)) from the caller, so the
# NumPy reference path and the compiled fast path trace exactly the same rays.

def sample_image_side(region: ImageRegion, u: np.ndarray, tile: tuple[float, float, float, float]) -> Rays:
    """Rays from points uniform on the rear aperture disc to points uniform in `tile` on the MLA plane.

    The rays start on the MLA plane travelling +z, weight cos^4 relative to the axis.
    """
    x0, x1, y0, y1 = tile
    px = x0 + (x1 - x0) * u[0]
    py = y0 + (y1 - y0) * u[1]
    rad = region.exit_radius_mm * np.sqrt(u[2])
    cph, sph = cos_sin_2pi(u[3])
    dx = px - rad * cph
    dy = py - rad * sph
    dz = region.z_mla_mm - region.z_exit_mm
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    cos_t = dz * inv
    return Rays(px, py, np.full(len(px), region.z_mla_mm), dx * inv, dy * inv, cos_t, (cos_t * cos_t) * (cos_t * cos_t))


def sample_image_cells(region: ImageRegion, cells: CellGrid, u: np.ndarray, row: np.ndarray, col: np.ndarray) -> Rays:
    """As `sample_image_side`, for the stratified sampler: u[2], u[3] place the ray's start in its MLA cell
    (row, col), u[0], u[1] a point a' uniform on a square around the rear aperture disc, moved as CellGrid
    says; points outside the disc get weight 0, those inside the square's area over the disc's, so that
    the mean over the square is the mean over the disc."""
    p = cells.pitch_mm
    u2, u3 = u[2], u[3]
    if cells.packing == "hex":
        u2, u3, row, col = hex_cell_draws(u2, u3, row, col)
    mx = cells.x0_mm + (col + u2) * p
    my = cells.y0_mm + (row + u3) * p
    hx, hy = (u2 - 0.5) * p, (u3 - 0.5) * p
    px = cells.r00 * mx + cells.r01 * my + cells.shift_x_mm
    py = cells.r10 * mx + cells.r11 * my + cells.shift_y_mm
    rp = region.exit_radius_mm
    sq = cells.square_half_mm or rp
    hcx, hcy = cells.r00 * hx + cells.r01 * hy, cells.r10 * hx + cells.r11 * hy
    bx, by = sq * (2.0 * u[0] - 1.0), sq * (2.0 * u[1] - 1.0)
    ax, ay, jac = aperture_point(cells.shift_coef, 1.0 / cells.shift_r_mm, 1.0 / rp, hcx, hcy, bx, by)
    dx = px - ax
    dy = py - ay
    dz = region.z_mla_mm - region.z_exit_mm
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    cos_t = dz * inv
    inside = ax * ax + ay * ay <= rp * rp
    w = np.where(inside, (cos_t * cos_t) * (cos_t * cos_t) * (FOUR_OVER_PI * (sq / rp) ** 2) * jac, 0.0)
    return Rays(px, py, np.full(len(px), region.z_mla_mm), dx * inv, dy * inv, cos_t, w)


def hex_cell_offsets(a, b):
    """Offset (pitches) from its lens' centre of a point uniform in a hexagonal cell, from two uniforms:
    the point (a - 1/2) (1, 0) + (b - 1/2) (1/2, sqrt(3)/2) of the rhombus round the centre, moved by the
    lattice vector that brings it into the centre's hexagon (CellGrid)."""
    bb = b - 0.5
    _, _, du, dv = hex_cell((a - 0.5) + 0.5 * bb, SQRT3_2 * bb)
    return du, dv


def hex_cell_draws(u2, u3, row, col):
    """Hex cells: the draws (u2, u3) and cell (row, col) rewritten so that the square cell's formulas
    (x0 + (col + u2) p, offset (u2 - 1/2) p, the same in y) give the point of the hexagon
    (`hex_cell_offsets`; (x0, y0) is U(1,1)'s centre). The compiled engine does the same (hex_fold)."""
    du, dv = hex_cell_offsets(u2, u3)
    return du + 0.5, dv + 0.5, row * SQRT3_2 - 0.5, col + 0.5 * (row - 2.0 * np.floor(0.5 * row)) - 0.5


def aperture_point(c, inv_rm, inv_ra, hx, hy, bx, by):
    """a = a' + Phi(h, a') (CellGrid) and the Jacobian det(da/da') that keeps the estimate unbiased: with
    u = h / r_max, v = a' / ra, Phi = h P + a' Q, P = c0 + s1 (c1 + s1 (c2 + s1 c3)) + c4 s2 + c5 s3,
    Q = c6 s1 + c7 s2. Plain arithmetic: the compiled engine runs the same code on scalars."""
    ux, uy, vx, vy = hx * inv_rm, hy * inv_rm, bx * inv_ra, by * inv_ra
    s1, s2, s3 = ux * ux + uy * uy, ux * vx + uy * vy, vx * vx + vy * vy
    p = c[0] + s1 * (c[1] + s1 * (c[2] + s1 * c[3])) + c[4] * s2 + c[5] * s3
    q = c[6] * s1 + c[7] * s2
    gx, gy = (c[4] * ux + 2.0 * c[5] * vx) * inv_ra, (c[4] * uy + 2.0 * c[5] * vy) * inv_ra  # dP/da'
    tx, ty = c[7] * ux * inv_ra, c[7] * uy * inv_ra  # dQ/da'
    j00, j01 = 1.0 + q + hx * gx + bx * tx, hx * gy + bx * ty
    j10, j11 = hy * gx + by * tx, 1.0 + q + hy * gy + by * ty
    return bx + p * hx + q * bx, by + p * hy + q * by, j00 * j11 - j01 * j10


def sample_plane(region: SourceRegion, u: np.ndarray, tile: tuple[float, float, float, float],
                 square: bool = False) -> Rays:
    """Rays from points uniform in `tile` (x0, x1, y0, y1 in mm) on the object plane towards the pupil, weight
    cos^4. `square`: the stratified sampler's layout (u[0], u[1] on the pupil's square, u[2], u[3] the point)."""
    x0, x1, y0, y1 = tile
    if square:
        return _towards_pupil(region, u[:2], x0 + (x1 - x0) * u[2], y0 + (y1 - y0) * u[3], power=4, square=True)
    return _towards_pupil(region, u[2:], x0 + (x1 - x0) * u[0], y0 + (y1 - y0) * u[1], power=4)


def sample_points(region: SourceRegion, u: np.ndarray, x_mm: float, y_mm: float, square: bool = False) -> Rays:
    """Rays from one isotropic point towards the pupil, weight cos^3."""
    n = u.shape[1]
    return _towards_pupil(region, u, np.full(n, x_mm), np.full(n, y_mm), power=3, square=square)


def _towards_pupil(region: SourceRegion, u: np.ndarray, ox: np.ndarray, oy: np.ndarray, power: int,
                   square: bool = False) -> Rays:
    """Rays from (ox, oy, z_object) to points uniform on the pupil disc at z = 0 (u: two rows of draws);
    `square`: points uniform on the square around the disc, weight 4/pi on the disc and 0 off it."""
    n = len(ox)
    rp = region.pupil_radius_mm
    if square:
        ax, ay = rp * (2.0 * u[0] - 1.0), rp * (2.0 * u[1] - 1.0)
        keep = np.where(ax * ax + ay * ay <= rp * rp, FOUR_OVER_PI, 0.0)
    else:
        rad = rp * np.sqrt(u[0])
        cph, sph = cos_sin_2pi(u[1])
        ax, ay, keep = rad * cph, rad * sph, 1.0
    dx = ax - ox
    dy = ay - oy
    dz = -region.z_object_mm
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    cos_t = dz * inv
    w = cos_t * cos_t * cos_t
    if power == 4:
        w = w * cos_t
    return Rays(ox, oy, np.full(n, region.z_object_mm), dx * inv, dy * inv, cos_t, w * keep)


def texture_weight(scene: TextureScene, half_x_mm: float, half_y_mm: float, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
    """Radiance at object points (nearest texel) of a texture spanning [-half_x, half_x] x [-half_y, half_y]; 0 outside."""
    h, w = scene.radiance.shape
    u = (ox + half_x_mm) / (2 * half_x_mm)
    v = (oy + half_y_mm) / (2 * half_y_mm)
    with np.errstate(invalid="ignore"):
        inside = (u >= 0) & (u < 1) & (v >= 0) & (v < 1)
    col = np.clip(np.nan_to_num(u * w), 0, w - 1).astype(np.int64)
    row = np.clip(np.nan_to_num(v * h), 0, h - 1).astype(np.int64)
    return np.where(inside, scene.radiance[row, col], 0.0)
