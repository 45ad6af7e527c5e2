"""Object-space scenes and their ray sources, importance-sampled towards the main lens' entrance pupil.

Every ray starts on the object plane and aims at a point drawn uniformly on the disc that the front
vertex plane cuts out of the lens rim, so (almost) every traced ray can reach the sensor. Weights make the
estimator unbiased: cos^4 for a Lambertian plane (radiance L: dPhi = L cos_o cos_p dA dA' / d^2), cos^3
for an isotropic point source. Object-space x, y follow the camera frame (x right, y down as seen from
the camera); like any camera, the main lens forms an inverted image on the MLA.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mlaqc.errors import InputError
from mlaqc.raytrace import Rays


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


def sample_plane(region: SourceRegion, rng: np.random.Generator, n: int,
                 tile: tuple[float, float, float, float]) -> Rays:
    """n rays from points uniform in `tile` (x0, x1, y0, y1 in mm) towards the pupil, weight cos^4."""
    x0, x1, y0, y1 = tile
    ox = rng.uniform(x0, x1, n)
    oy = rng.uniform(y0, y1, n)
    return _towards_pupil(region, rng, ox, oy, power=4)


def sample_points(region: SourceRegion, rng: np.random.Generator, n: int, x_mm: float, y_mm: float) -> Rays:
    """n rays from one isotropic point towards the pupil, weight cos^3."""
    return _towards_pupil(region, rng, np.full(n, x_mm), np.full(n, y_mm), power=3)


def _towards_pupil(region: SourceRegion, rng: np.random.Generator, ox: np.ndarray, oy: np.ndarray, power: int) -> Rays:
    """Rays from (ox, oy, z_object) to points uniform on the pupil disc at z = 0."""
    n = len(ox)
    rad = region.pupil_radius_mm * np.sqrt(rng.random(n))
    phi = (2.0 * math.pi) * rng.random(n)
    dx = rad * np.cos(phi) - ox
    dy = rad * np.sin(phi) - oy
    dz = -region.z_object_mm
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    cos_t = dz * inv
    return Rays(ox, oy, np.full(n, region.z_object_mm), dx * inv, dy * inv, np.full(n, 0.0) + cos_t, cos_t ** power)


def texture_weight(scene: TextureScene, region: SourceRegion, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
    """Radiance of the texture at object points (nearest texel); the image spans the sampled region."""
    h, w = scene.radiance.shape
    col = np.clip(((ox + region.half_x_mm) / (2 * region.half_x_mm) * w).astype(np.int64), 0, w - 1)
    row = np.clip(((oy + region.half_y_mm) / (2 * region.half_y_mm) * h).astype(np.int64), 0, h - 1)
    return scene.radiance[row, col]
