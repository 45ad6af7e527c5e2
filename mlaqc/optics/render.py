"""Monte-Carlo rendering of raw images: batched, threaded, seeded, memory-bounded.

Plane scenes are sampled from the image side (see `mlaqc.optics.scene`); the MLA area is cut into tiles, one
batch of rays per tile (stratified sampling: each batch lands on a compact patch of the sensor, so it is
summed per pixel over that patch only: `np.bincount` in the NumPy engine, the same sums in ray order in
compiled code in the Numba engine). Batches run on a thread pool (NumPy and the compiled kernel release
the GIL) and are added into the image in batch order, so a seed gives a bit-identical image whatever the
thread count. Memory is bounded by the batch size times the number of batches in flight (2 per thread),
plus one patch per batch in flight; there is no per-thread copy of the frame.
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from mlaqc.optics import raytrace_kernels
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.errormap import ErrorMap
from mlaqc.errors import InputError
from mlaqc.optics.raytrace import Camera, Rays
from mlaqc.optics.unitcircle import counter_uniforms
from mlaqc.optics.scene import (ImageRegion, PointScene, Scene, SourceRegion, TextureScene, WhiteScene, sample_image_side,
                         sample_plane, sample_points, texture_weight)

Progress = Callable[[int, int], None]
MAX_RAYS = 10 ** 11


@dataclass(frozen=True)
class RenderResult:
    """Expected photons per pixel (a Monte-Carlo estimate) and what it cost."""

    photons: np.ndarray  # (H, W) float64
    rays_traced: int
    rays_landed: int
    seconds: float
    seed: int


@dataclass(frozen=True)
class _Job:
    index: int
    n: int
    tile: tuple[float, float, float, float] | None  # plane scenes
    point: tuple[float, float] | None  # point scenes


def _mla_half_extent(camera: Camera) -> tuple[float, float]:
    """Half-width and half-height (mm) of the MLA's bounding box, its rotation about the axis included."""
    cfg = camera.cfg
    hx = 0.5 * cfg.mla.count_w * cfg.mla.pitch_um * 1e-3
    hy = 0.5 * cfg.mla.count_h * cfg.mla.pitch_um * 1e-3
    angle = math.radians(abs(camera.errors.globals["mla_rotation_deg"]))
    return hx * math.cos(angle) + hy * math.sin(angle), hy * math.cos(angle) + hx * math.sin(angle)


def image_region(camera: Camera) -> ImageRegion:
    """The MLA's bounding box plus one pitch (image-side sampling) and the rear aperture disc."""
    hx, hy = _mla_half_extent(camera)
    pad = camera.cfg.mla.pitch_um * 1e-3
    ml = camera.cfg.main_lens
    return ImageRegion(camera.z_mla, hx + pad, hy + pad, ml.thickness_mm, 0.5 * ml.diameter_mm,
                       camera.shift_x, camera.shift_y)


def source_region(camera: Camera) -> SourceRegion:
    """The object rectangle whose image covers the MLA plus the main lens' blur, and the pupil disc.

    The blur margin is measured by tracing a pupil fan from the field's centre and corner, so that the
    border lenses get all the light they would get from an infinite plane.
    """
    cfg, lay = camera.cfg, camera.layout
    mag = lay.pupil_to_mla_mm / (lay.object_distance_mm + lay.main.front_principal)
    hx, hy = _mla_half_extent(camera)
    pupil = 0.5 * cfg.main_lens.diameter_mm
    cx, cy = -camera.shift_x / mag, -camera.shift_y / mag  # the image is inverted
    region = SourceRegion(lay.z_object_mm, hx / mag, hy / mag, pupil, mag, cx, cy)
    margin = max(_blur_radius(camera, region, cx, cy), _blur_radius(camera, region, cx - hx / mag, cy - hy / mag))
    margin += cfg.mla.pitch_um * 1e-3
    return SourceRegion(lay.z_object_mm, (hx + margin) / mag, (hy + margin) / mag, pupil, mag, cx, cy)


def _blur_radius(camera: Camera, region: SourceRegion, x_mm: float, y_mm: float) -> float:
    """Largest distance (mm, at the MLA plane) of a point's pupil fan from its median landing point."""
    r = sample_points(region, counter_uniforms(12345, 4096, 2), x_mm, y_mm)
    camera.trace_to_mla(r)
    r.advance((camera.z_mla - r.z) / r.N)
    ok = r.w > 0
    if not ok.any():
        return 0.0
    x, y = r.x[ok], r.y[ok]
    return float(np.max(np.hypot(x - np.median(x), y - np.median(y))))


def ray_count(cfg: CameraConfig, rays: int | None, rays_per_pixel: float | None) -> int:
    """Total rays to trace: explicit, or rays per sensor pixel (config default if neither is given)."""
    if rays is not None and rays_per_pixel is not None:
        raise InputError("give either a ray count or rays per pixel, not both")
    if rays is None:
        rpp = cfg.trace.rays_per_pixel if rays_per_pixel is None else rays_per_pixel
        if not (rpp > 0 and math.isfinite(rpp)):
            raise InputError(f"rays per pixel must be a positive number, got {rpp!r}")
        rays = int(round(rpp * cfg.sensor.width_px * cfg.sensor.height_px))
    if not 1 <= rays <= MAX_RAYS:
        raise InputError(f"ray count must be between 1 and {MAX_RAYS:.0e}, got {rays}")
    return rays


PATCH_PIXELS = 1 << 22  # at most about this many sensor pixels per tile (a 32 MiB patch in flight)


def _plane_jobs(region: SourceRegion | ImageRegion, total: int, batch: int, sensor_pixels: int = 0) -> list[_Job]:
    """Tiles of the sampled rectangle, about `batch` rays each, rays shared out exactly.

    Few rays on a large sensor still get enough tiles that no batch's patch approaches the whole frame
    (no change below 2^22 sensor pixels, e.g. the 2048 x 2048 Table 1 sensor)."""
    n_batches = max(1, math.ceil(total / batch), math.ceil(sensor_pixels / PATCH_PIXELS))
    aspect = region.half_x_mm / region.half_y_mm
    nx = max(1, round(math.sqrt(n_batches * aspect)))
    ny = max(1, math.ceil(n_batches / nx))
    tiles = nx * ny
    xs = region.center_x_mm + np.linspace(-region.half_x_mm, region.half_x_mm, nx + 1)
    ys = region.center_y_mm + np.linspace(-region.half_y_mm, region.half_y_mm, ny + 1)
    base, extra = divmod(total, tiles)
    jobs = []
    for i in range(tiles):
        ty, tx = divmod(i, nx)
        n = base + (1 if i < extra else 0)
        if n:
            jobs.append(_Job(len(jobs), n, (xs[tx], xs[tx + 1], ys[ty], ys[ty + 1]), None))
    return jobs


def _point_jobs(scene: PointScene, total: int, batch: int) -> list[_Job]:
    """Batches of rays per point source, rays shared equally among points."""
    per_point = max(1, total // len(scene.points_mm))
    jobs = []
    for pt in scene.points_mm:
        left = per_point
        while left:
            n = min(batch, left)
            jobs.append(_Job(len(jobs), n, None, (float(pt[0]), float(pt[1]))))
            left -= n
    return jobs


class Renderer:
    """Renders one camera (config + error map) for any scene; reusable across frames."""

    def __init__(self, cfg: CameraConfig, errors: ErrorMap | None = None, sampling: str = "image",
                 engine: str | None = None) -> None:
        if sampling not in ("image", "object"):
            raise ValueError(f"sampling must be 'image' or 'object', got {sampling!r}")
        engine = engine or cfg.trace.engine
        if engine == "auto":
            engine = "numba" if raytrace_kernels.AVAILABLE else "numpy"
        if engine == "numba" and not raytrace_kernels.AVAILABLE:
            raise InputError("the numba engine was asked for but numba is not installed")
        self.engine = engine
        self.cfg = cfg
        self.camera = Camera(cfg, errors)
        self.sampling = sampling
        self.region = source_region(self.camera)
        self.image_region = image_region(self.camera)
        mag = self.region.magnification
        hx, hy = _mla_half_extent(self.camera)
        self.texture_half_mm = (hx / mag, hy / mag)  # a texture spans the object-side conjugate of the MLA
        self.fast = (raytrace_kernels.FastCamera(self.camera, self.image_region, self.region, self.texture_half_mm)
                     if engine == "numba" else None)

    def render(self, scene: Scene, *, rays: int | None = None, rays_per_pixel: float | None = None,
               seed: int = 0, threads: int | None = None, progress: Progress | None = None) -> RenderResult:
        """Trace `rays` rays of `scene` and return expected photons per pixel."""
        start = time.perf_counter()
        total = ray_count(self.cfg, rays, rays_per_pixel)
        batch = self.cfg.trace.batch_rays
        if isinstance(scene, PointScene):
            if not scene.points_mm:
                raise InputError("a point scene needs at least one point")
            jobs = _point_jobs(scene, total, batch)
        else:
            jobs = _plane_jobs(self.image_region if self.sampling == "image" else self.region, total, batch,
                               self.cfg.sensor.width_px * self.cfg.sensor.height_px)
        total = sum(j.n for j in jobs)
        keys = np.random.SeedSequence(seed).generate_state(len(jobs), np.uint64)
        h, w = self.cfg.sensor.height_px, self.cfg.sensor.width_px
        image = np.zeros((h, w))
        landed = done = 0
        n_threads = threads or self.cfg.trace.threads or os.cpu_count() or 1

        def work(job: _Job):
            return self._trace_job(scene, job, int(keys[job.index]))

        with ThreadPoolExecutor(max_workers=n_threads) as pool:
            pending: deque = deque()
            it = iter(jobs)
            for job in it:
                pending.append((job, pool.submit(work, job)))
                if len(pending) >= 2 * n_threads:
                    break
            while pending:
                job, fut = pending.popleft()
                r0, c0, patch, hits = fut.result()
                image[r0:r0 + patch.shape[0], c0:c0 + patch.shape[1]] += patch
                landed += hits
                done += job.n
                nxt = next(it, None)
                if nxt is not None:
                    pending.append((nxt, pool.submit(work, nxt)))
                if progress is not None:
                    progress(done, total)
        image *= self._photons_per_weight(scene, total)
        return RenderResult(image, total, landed, time.perf_counter() - start, seed)

    def _trace_job(self, scene: Scene, job: _Job, key: int):
        """Sample, trace and bin one batch; returns the patch of the sensor it touched."""
        if self.fast is not None:  # traced and binned in compiled code, no (index, weight) arrays in Python
            texture = scene.radiance if isinstance(scene, TextureScene) else None
            return self.fast.trace_binned(self._fast_mode(job.point), key, job.n, job.tile, job.point, texture)
        idx, wts = self.trace_batch(scene, key, job.n, job.tile, job.point)
        return _bin_patch(idx, wts, self.cfg.sensor.width_px)

    def trace_batch(self, scene: Scene, key: int, n: int, tile=None, point=None):
        """Trace n rays drawn with `key`; (flat pixel index, weight) of those that reached the sensor."""
        texture = scene.radiance if isinstance(scene, TextureScene) else None
        if self.fast is not None:
            return self.fast.trace(self._fast_mode(point), key, n, tile, point, texture)
        u = counter_uniforms(key, n, 2 if point is not None else 4)
        if point is not None:
            r = sample_points(self.region, u, *point)
            self.camera.trace(r)
        elif self.sampling == "image":
            r = sample_image_side(self.image_region, u, tile)
            self._weigh_by_main_lens(scene, r)
            self.camera.trace_behind_main(r)
        else:
            r = sample_plane(self.region, u, tile)
            if texture is not None:
                r.w *= texture_weight(scene, *self.texture_half_mm, r.x, r.y)
            self.camera.trace(r)
        return self.camera.pixel_index(r)

    def _fast_mode(self, point) -> int:
        return (raytrace_kernels.POINT if point is not None else
                raytrace_kernels.IMAGE_SIDE if self.sampling == "image" else raytrace_kernels.OBJECT_SIDE)

    def _weigh_by_main_lens(self, scene: Scene, r: Rays) -> None:
        """Trace image-side rays back through the main lens: vignetting, Fresnel, and the object radiance."""
        back = Rays(r.x.copy(), r.y.copy(), r.z.copy(), -r.L, -r.M, -r.N, r.w)
        self.camera.main.trace_back(back)
        r.w = back.w
        if isinstance(scene, TextureScene):
            t = (self.camera.layout.z_object_mm - back.z) / back.N
            r.w = r.w * texture_weight(scene, *self.texture_half_mm, back.x + t * back.L, back.y + t * back.M)

    def _photons_per_weight(self, scene: Scene, total: int) -> float:
        """Photons one unit of ray weight stands for, so that pixels read physical photon counts."""
        if isinstance(scene, PointScene):
            return scene.photons * len(scene.points_mm) / total
        if self.sampling == "image":
            image_area = 4 * self.image_region.half_x_mm * self.image_region.half_y_mm
        else:  # same radiometric unit: object area seen through the front disc instead of the MLA through the rear
            reg, lay = self.region, self.camera.layout
            ratio = (lay.z_mla_mm - self.cfg.main_lens.thickness_mm) / -lay.z_object_mm
            image_area = 4 * reg.half_x_mm * reg.half_y_mm * ratio * ratio
        pixel_area = (self.cfg.sensor.pixel_um * 1e-3) ** 2
        return self.cfg.sensor.exposure_photons * (image_area / pixel_area) / total


def _bin_patch(idx: np.ndarray, wts: np.ndarray, width: int):
    """Sum weights per pixel over the bounding box of the hits (np.bincount: duplicates add up)."""
    if idx.size == 0:
        return 0, 0, np.zeros((0, 0)), 0
    rows, cols = np.divmod(idx, width)
    r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()
    pw = c1 - c0 + 1
    local = (rows - r0) * pw + (cols - c0)
    patch = np.bincount(local, weights=wts, minlength=(r1 - r0 + 1) * pw).reshape(r1 - r0 + 1, pw)
    return int(r0), int(c0), patch, int(idx.size)


def render(cfg: CameraConfig, scene: Scene | None = None, errors: ErrorMap | None = None, **kwargs) -> RenderResult:
    """One-shot convenience: build a Renderer and render `scene` (default: the white image)."""
    return Renderer(cfg, errors).render(scene if scene is not None else WhiteScene(), **kwargs)
