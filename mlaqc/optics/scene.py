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
from mlaqc.optics.raytrace import Rays
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


def sample_plane(region: SourceRegion, u: np.ndarray, tile: tuple[float, float, float, float]) -> Rays:
    """Rays from points uniform in `tile` (x0, x1, y0, y1 in mm) on the object plane towards the pupil, weight cos^4."""
    x0, x1, y0, y1 = tile
    return _towards_pupil(region, u[2:], x0 + (x1 - x0) * u[0], y0 + (y1 - y0) * u[1], power=4)


def sample_points(region: SourceRegion, u: np.ndarray, x_mm: float, y_mm: float) -> Rays:
    """Rays from one isotropic point towards the pupil, weight cos^3."""
    n = u.shape[1]
    return _towards_pupil(region, u, np.full(n, x_mm), np.full(n, y_mm), power=3)


def _towards_pupil(region: SourceRegion, u: np.ndarray, ox: np.ndarray, oy: np.ndarray, power: int) -> Rays:
    """Rays from (ox, oy, z_object) to points uniform on the pupil disc at z = 0 (u: two rows of draws)."""
    n = len(ox)
    rad = region.pupil_radius_mm * np.sqrt(u[0])
    cph, sph = cos_sin_2pi(u[1])
    dx = rad * cph - ox
    dy = rad * sph - oy
    dz = -region.z_object_mm
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    cos_t = dz * inv
    w = cos_t * cos_t * cos_t
    if power == 4:
        w = w * cos_t
    return Rays(ox, oy, np.full(n, region.z_object_mm), dx * inv, dy * inv, cos_t, w)


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
