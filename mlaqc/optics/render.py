"""Monte-Carlo and quasi-Monte-Carlo rendering of raw images: batched, threaded, seeded, memory-bounded.

Two samplers (config `trace.sampler`). 'sobol' (default) stratifies plane scenes per microlens: every
cell of the MLA (one ring of padding cells included) gets the same number of rays, whose start in the cell
and point on the rear aperture are a scrambled Sobol sequence shifted per cell (`mlaqc.optics.lowdisc`);
a job is a block of cells and a range of point indices, so a cell's points are the same whatever the
batching. 'random' is plain Monte-Carlo (the test oracle): tiles of the MLA's bounding box with uniform
draws per batch.

Plane scenes are sampled from the image side (see `mlaqc.optics.scene`), and so is every scene of an
ideal main lens (datasheet numbers), given by its image (a point's rays drawn through its image). The
MLA area is cut into tiles, one batch of rays per tile (stratified sampling: each batch lands on a compact patch of the sensor, so it is
summed per pixel over that patch only: `np.bincount` in the NumPy engine, the same sums in ray order in
compiled code in the Numba engine). Batches run on a thread pool (NumPy and the compiled kernel release
the GIL) and are added into the image in batch order, so a seed gives a bit-identical image whatever the
thread count. Memory is bounded by the batch size times the number of batches in flight (2 per thread),
plus one patch per batch in flight; there is no per-thread copy of the frame.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from mlaqc.optics.config import CameraConfig, require_thick_main_lens
from mlaqc.optics.errormap import ErrorMap
from mlaqc.errors import InputError
from mlaqc.optics import kernel_layout, lowdisc
from mlaqc.optics.raytrace import Camera, Rays
from mlaqc.optics.unitcircle import counter_uniforms
from mlaqc.optics.scene import (CellGrid, ImageRegion, PointScene, Scene, SourceRegion, TextureScene, WhiteScene,
                                hex_cell_offsets, sample_image_cells, sample_image_side, sample_plane, sample_points, texture_weight)

Progress = Callable[[int, int], None]
MAX_RAYS = 10 ** 11


def _fast_camera():
    """The compiled tracer's camera class (imports the kernels, as `_kernels`)."""
    from mlaqc.optics.fast_camera import FastCamera

    return FastCamera


def _kernels():
    """The tracer's compiled kernels, imported on the first render (`import numba` costs a few tenths of a
    second that inspecting alone need not pay)."""
    from mlaqc.optics import raytrace_kernels

    return raytrace_kernels


@dataclass(frozen=True)
class RenderResult:
    """Expected photons per pixel (a Monte-Carlo estimate) and what it cost."""

    photons: np.ndarray  # (H, W) float64
    rays_traced: int
    rays_landed: int
    seconds: float
    seed: int


# A chunk (jobs summed into one partial image before it is added to the frame, and one task on a Dask
# worker) ends after CHUNK_JOBS jobs or CHUNK_RAYS rays: about 0.5 s of one core, a few MiB of patches.
CHUNK_JOBS = 64
CHUNK_RAYS = 1 << 24


@dataclass(frozen=True)
class _Job:
    index: int
    n: int
    tile: tuple[float, float, float, float] | None  # plane scenes, random sampler
    point: tuple[float, float] | None  # point scenes
    cells: tuple[int, int, int, int, int] | None = None  # plane scenes, sobol: row0, col0, rows, cols, first point


def _mla_half_extent(camera: Camera) -> tuple[float, float]:
    """Half-width and half-height (mm) of the MLA's bounding box, its rotation about the axis included."""
    cfg = camera.cfg
    if camera.mla.hex:
        hx, hy = (0.5 * e for e in camera.mla.lattice.extent)
    else:
        hx = 0.5 * cfg.mla.count_w * cfg.mla.pitch_um * 1e-3
        hy = 0.5 * cfg.mla.count_h * cfg.mla.pitch_um * 1e-3
    angle = math.radians(abs(camera.errors.globals["mla_rotation_deg"]))
    return hx * math.cos(angle) + hy * math.sin(angle), hy * math.cos(angle) + hx * math.sin(angle)


_SHIFTS: dict[str, tuple[tuple[float, ...], float, float]] = {}  # aperture_shift per optics (0.1 s to fit)


def cell_grid(camera: Camera, region: ImageRegion) -> CellGrid:
    """The MLA's cells in its own frame, the map of that frame onto the start plane, and the aperture
    shift that keeps a pixel's preimage a box (see CellGrid)."""
    mla, rot = camera.mla, camera.rot
    d = camera.cfg.to_dict()
    key = json.dumps([d["main_lens"], d["mla"], d["geometry"], d["sensor"], d["trace"]["fresnel"], repr(region)],
                     sort_keys=True)
    if key not in _SHIFTS:
        _SHIFTS[key] = aperture_shift(camera.cfg, region)
    coef, r_max, reach = _SHIFTS[key]
    return CellGrid(mla.x0, mla.y0, mla.p, mla.rows, mla.cols, float(rot[0, 0]), float(rot[0, 1]),
                    float(rot[1, 0]), float(rot[1, 1]), camera.shift_x, camera.shift_y,
                    coef, r_max, region.exit_radius_mm + 1.01 * reach, camera.cfg.mla.packing)


def aperture_shift(cfg: CameraConfig, region: ImageRegion, n: int = 40_000,
                   seed: int = 5) -> tuple[tuple[float, ...], float, float]:
    """Coefficients c of the aperture shift Phi(h, a') (see CellGrid and `shift_terms`) for the design lens
    nearest the axis: a ray that starts h (mm) from its cell centre towards a' + Phi lands where the ray
    from a' through the centre does. Fitted by least squares to shifts found by tracing the design camera
    (no errors; Newton steps on the landing point) at random h in the cell and a' on the aperture; rays
    that leave the lens' own sub-image (through a corner or into a neighbour) are left out robustly.
    Paraxially Phi = h; the microlens' spherical aberration and coma (c0..c3 and c4..c5) matter to tenths
    of a pixel. Returns c, the cell's corner radius r_max and the largest |Phi| over cell and aperture."""
    cam = Camera(cfg)
    mla = cam.mla
    if mla.hex:  # the hit's own lens; Phi is fitted on the square round it (a superset of the hexagon)
        k = (mla.rows // 2) * mla.cols + mla.cols // 2
        cx, cy = float(mla.gx[k]), float(mla.gy[k])
    else:
        cx = mla.x0 + (mla.cols // 2 + 0.5) * mla.p
        cy = mla.y0 + (mla.rows // 2 + 0.5) * mla.p
    r_max, ra = 0.5 * math.sqrt(2.0) * mla.p, region.exit_radius_mm
    dz = region.z_mla_mm - region.z_exit_mm

    def land(h: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        mx, my = cx + h[0], cy + h[1]
        dx, dy = mx - a[0], my - a[1]
        inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        r = Rays(mx, my, np.full(len(mx), region.z_mla_mm), dx * inv, dy * inv, dz * inv, np.ones(len(mx)))
        cam.trace_behind_main(r)
        return np.stack([r.x, r.y]), r.w

    rng = np.random.default_rng(seed)
    h = (rng.random((2, n)) - 0.5) * mla.p
    if mla.hex:  # h uniform in the hexagonal cell
        h = np.stack(hex_cell_offsets(h[0] / mla.p + 0.5, h[1] / mla.p + 0.5)) * mla.p
    a = (2.0 * rng.random((2, n)) - 1.0) * ra
    a = a[:, np.hypot(a[0], a[1]) < 0.98 * ra]
    h = h[:, :a.shape[1]]
    step = 1e-3 * ra
    gain = (land(np.zeros((2, 1)), np.array([[step], [0.0]]))[0][0, 0]
            - land(np.zeros((2, 1)), np.array([[-step], [0.0]]))[0][0, 0]) / (2.0 * step)
    target, w0 = land(np.zeros_like(h), a)
    phi = h.copy()
    with np.errstate(invalid="ignore", over="ignore"):
        for _ in range(4):
            got, w = land(h, a + phi)
            phi += (target - got) / gain
        basis = shift_terms(h, a, r_max, ra)
        design = np.concatenate([basis[:, 0], basis[:, 1]], axis=1).T
        y = np.concatenate([phi[0], phi[1]])
        good = np.tile((w > 0) & (w0 > 0) & np.isfinite(phi).all(axis=0), 2)
        coef = np.zeros(design.shape[1])
        for _ in range(5):  # drop rays that landed in another sub-image (huge shifts), refit
            coef = np.linalg.lstsq(design[good], y[good], rcond=None)[0]
            res = np.abs(y - design @ coef)
            good &= res < 5.0 * np.median(res[good]) + 1e-9
    if not np.all(np.isfinite(coef)) or good.mean() < 0.5:
        coef = np.zeros(design.shape[1])
        coef[0] = 1.0
    # the largest shift, for a' out to a little beyond the disc (where the square's preimage reaches)
    reach = float(np.max(np.abs(np.einsum("k,kdn->dn", coef, shift_terms(h, 1.1 * a, r_max, ra)))))
    return tuple(float(c) for c in coef), r_max, reach


def shift_terms(h: np.ndarray, a: np.ndarray, r_max: float, ra: float) -> np.ndarray:
    """(8, 2, n) vector terms of Phi: h times 1, s1, s1^2, s1^3, s2, s3 and a' times s1, s2, with u = h / r_max,
    v = a' / ra, s1 = |u|^2, s2 = u.v, s3 = |v|^2 (spherical aberration, coma, field curvature and their
    mixtures, the terms a rotationally symmetric lens allows to this order)."""
    u, v = h / r_max, a / ra
    s1, s2, s3 = (u * u).sum(0), (u * v).sum(0), (v * v).sum(0)
    return np.stack([h, h * s1, h * s1 ** 2, h * s1 ** 3, h * s2, h * s3, a * s1, a * s2])


def image_region(camera: Camera) -> ImageRegion:
    """The MLA's bounding box plus one pitch (image-side sampling) and the rear aperture disc."""
    hx, hy = _mla_half_extent(camera)
    pad = camera.cfg.mla.pitch_um * 1e-3
    lay = camera.layout
    return ImageRegion(camera.z_mla, hx + pad, hy + pad, lay.z_exit_mm, lay.exit_radius_mm,
                       camera.shift_x, camera.shift_y)


def source_region(camera: Camera) -> SourceRegion:
    """The object rectangle whose image covers the MLA plus the main lens' blur, and the pupil disc.

    The blur margin is measured by tracing a pupil fan from the field's centre and corner, so that the
    border lenses get all the light they would get from an infinite plane.
    """
    cfg, lay = camera.cfg, camera.layout
    require_thick_main_lens(cfg, "a scene other than a white frame")
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


MIN_JOB_CELLS = 64
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


def _cell_jobs(cells: CellGrid, total: int, batch: int, pixels_per_cell: float) -> tuple[list[_Job], int]:
    """Blocks of padded cells with a range of point indices each, about `batch` rays a job; every cell gets
    the same k = round(total / cells) rays. Returns the jobs and k."""
    n_cells = cells.padded_rows * cells.padded_cols
    k = max(1, round(total / n_cells))
    # at least MIN_JOB_CELLS cells a job, so that a point's scramble is shared by that many rays
    per_job = max(MIN_JOB_CELLS, min(batch // k, int(PATCH_PIXELS / pixels_per_cell)))
    bw = max(1, min(cells.padded_cols, round(math.sqrt(per_job))))
    bh = max(1, min(cells.padded_rows, per_job // bw))
    span = max(1, min(k, batch // (bw * bh)))
    jobs = []
    for r0 in range(-1, cells.rows + 1, bh):
        for c0 in range(-1, cells.cols + 1, bw):
            h, w = min(bh, cells.rows + 1 - r0), min(bw, cells.cols + 1 - c0)
            for j0 in range(0, k, span):
                jobs.append(_Job(len(jobs), h * w * min(span, k - j0), None, None, (r0, c0, h, w, j0)))
    return jobs, k


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
                 engine: str | None = None, sampler: str | None = None) -> None:
        if sampling not in ("image", "object"):
            raise ValueError(f"sampling must be 'image' or 'object', got {sampling!r}")
        self.sampler = sampler or cfg.trace.sampler
        if self.sampler not in ("sobol", "random"):
            raise ValueError(f"sampler must be 'sobol' or 'random', got {self.sampler!r}")
        engine = engine or cfg.trace.engine
        if engine == "auto":
            engine = "numba" if _kernels().AVAILABLE else "numpy"
        if engine == "numba" and not _kernels().AVAILABLE:
            raise InputError("the numba engine was asked for but numba is not installed")
        self.engine = engine
        self.cfg = cfg
        self.camera = Camera(cfg, errors)
        self.sampling = sampling
        if cfg.main_lens.ideal:  # no object side: every scene is traced from the exit pupil, given by its image
            if sampling == "object":
                require_thick_main_lens(cfg, "object-side sampling")
            self.region = None
            hx, hy = _mla_half_extent(self.camera)
            lay = cfg.layout
            cone = (lay.z_scene_mm - lay.z_exit_mm) / (lay.z_mla_mm - lay.z_exit_mm)
            self.texture_half_mm = (hx * cone, hy * cone)  # a texture spans the MLA seen from the pupil's centre
        else:
            self.region = source_region(self.camera)
            hx, hy = _mla_half_extent(self.camera)
            mag = self.region.magnification
            self.texture_half_mm = (hx / mag, hy / mag)  # a texture spans the object-side conjugate of the MLA
        self.image_region = image_region(self.camera)
        self.cells = cell_grid(self.camera, self.image_region)
        self.fast = (_fast_camera()(self.camera, self.image_region, self.region, self.texture_half_mm,
                                    self.cells if self.sampler == "sobol" else None)
                     if engine == "numba" else None)
        if engine == "numba":  # the variants the install left out compile in the background, once
            from mlaqc.optics.tracer_background import start_if_needed

            start_if_needed()

    def render(self, scene: Scene, *, rays: int | None = None, rays_per_pixel: float | None = None,
               seed: int = 0, threads: int | None = None, progress: Progress | None = None) -> RenderResult:
        """Trace `rays` rays of `scene` and return expected photons per pixel."""
        start = time.perf_counter()
        plan = self.plan(scene, rays, rays_per_pixel, seed)
        image = np.zeros((self.cfg.sensor.height_px, self.cfg.sensor.width_px))
        landed = done = 0
        n_threads = threads or self.cfg.trace.threads or os.cpu_count() or 1

        def work(job: _Job):
            return self._trace_job(scene, job, int(plan.keys[job.index]))

        with ThreadPoolExecutor(max_workers=n_threads) as pool:
            pending: deque = deque()
            it = iter(plan.jobs)
            for job in it:
                pending.append((job, pool.submit(work, job)))
                if len(pending) >= 2 * n_threads:
                    break
            chunk: list = []
            ends = set(plan.chunk_ends)
            while pending:
                job, fut = pending.popleft()
                chunk.append(fut.result())
                if job.index in ends:
                    landed += add_chunk(image, sum_patches(chunk))
                    chunk = []
                done += job.n
                nxt = next(it, None)
                if nxt is not None:
                    pending.append((nxt, pool.submit(work, nxt)))
                if progress is not None:
                    progress(done, plan.total)
        image *= self.photons_per_weight(scene, plan.total)
        return RenderResult(image, plan.total, landed, time.perf_counter() - start, seed)

    def plan(self, scene: Scene, rays: int | None, rays_per_pixel: float | None, seed: int) -> RenderPlan:
        """The jobs, their keys and their chunks for a render; the same wherever the jobs then run."""
        jobs = self.jobs(scene, ray_count(self.cfg, rays, rays_per_pixel))
        keys = np.random.SeedSequence(seed).generate_state(len(jobs), np.uint64)
        if jobs and jobs[0].cells is not None:  # one key: a cell's shift must not depend on how it was batched
            keys[:] = keys[0]
        ends, rays_in, first = [], 0, 0
        for job in jobs:
            rays_in += job.n
            if rays_in >= CHUNK_RAYS or job.index - first + 1 >= CHUNK_JOBS or job is jobs[-1]:
                ends.append(job.index)
                rays_in, first = 0, job.index + 1
        return RenderPlan(jobs, keys, sum(j.n for j in jobs), tuple(ends))

    def trace_chunk(self, scene: Scene, jobs: list[_Job], keys: np.ndarray) -> tuple[int, int, np.ndarray, int]:
        """Trace a chunk's jobs one after the other and sum them as `render` does (a Dask worker's task)."""
        return sum_patches([self._trace_job(scene, job, int(keys[job.index])) for job in jobs])

    def jobs(self, scene: Scene, total: int) -> list[_Job]:
        """The batches `total` rays of `scene` are traced in (their order fixes the sum's order)."""
        batch = self.cfg.trace.batch_rays
        if isinstance(scene, PointScene):
            if not scene.points_mm:
                raise InputError("a point scene needs at least one point")
            return _point_jobs(scene, total, batch)
        if self.sampler == "sobol" and self.sampling == "image":
            return _cell_jobs(self.cells, total, batch, self.cfg.layout.subimage_pitch_px ** 2)[0]
        return _plane_jobs(self.image_region if self.sampling == "image" else self.region, total, batch,
                           self.cfg.sensor.width_px * self.cfg.sensor.height_px)

    def _trace_job(self, scene: Scene, job: _Job, key: int):
        """Sample, trace and bin one batch; returns the patch of the sensor it touched."""
        if self.fast is not None:  # traced and binned in compiled code, no (index, weight) arrays in Python
            texture = scene.radiance if isinstance(scene, TextureScene) else None
            return self.fast.trace_binned(self._fast_mode(job.point), key, job.n, job.tile, job.point, texture,
                                          job.cells)
        idx, wts = self.trace_batch(scene, key, job.n, job.tile, job.point, job.cells)
        return _bin_patch(idx, wts, self.cfg.sensor.width_px)

    def trace_batch(self, scene: Scene, key: int, n: int, tile=None, point=None, cells=None):
        """Trace n rays drawn with `key`; (flat pixel index, weight) of those that reached the sensor.
        `cells` (sobol, image side): the job's block of cells and first point, instead of a tile."""
        texture = scene.radiance if isinstance(scene, TextureScene) else None
        if self.fast is not None:
            return self.fast.trace(self._fast_mode(point), key, n, tile, point, texture, cells)
        sobol = self.sampler == "sobol"
        if cells is not None:
            r = self._sample_cells(key, n, cells)
        else:  # a point through a thick lens draws its pupil point only
            dims = 2 if point is not None and self.region is not None else 4
            u = (lowdisc.batch_uniforms if sobol else counter_uniforms)(key, n, dims)
        if point is not None and self.region is None:  # an ideal main lens: every ray through the point's image
            r = sample_image_side(self.scene_region, u, (point[0], point[0], point[1], point[1]))
            self.camera.trace_behind_main(r)
        elif point is not None:
            r = sample_points(self.region, u, *point, square=sobol)
            self.camera.trace(r)
        elif self.sampling == "image":
            if cells is None:
                r = sample_image_side(self.image_region, u, tile)
            self._weigh_by_main_lens(scene, r)
            self.camera.trace_behind_main(r)
        else:
            r = sample_plane(self.region, u, tile, square=sobol)
            if texture is not None:
                r.w *= texture_weight(scene, *self.texture_half_mm, r.x, r.y)
            self.camera.trace(r)
        return self.camera.pixel_index(r)

    def _sample_cells(self, key: int, n: int, cells: tuple[int, int, int, int, int]) -> Rays:
        """Rays i < n of a cell job: point j0 + i // (rows*cols) of cell i % (rows*cols) of the block."""
        r0, c0, bh, bw, j0 = cells
        i = np.arange(n)
        q, cf = np.divmod(i, bh * bw)
        row, col = r0 + cf // bw, c0 + cf % bw
        u = lowdisc.cell_uniforms(key, j0 + q, self.cells.cell_id(row, col))
        return sample_image_cells(self.image_region, self.cells, u, row.astype(np.float64), col.astype(np.float64))

    @property
    def scene_region(self) -> ImageRegion:
        """The image-side region with its start plane moved to the scene's image (an ideal main lens' points)."""
        return dataclasses.replace(self.image_region, z_mla_mm=self.cfg.layout.z_scene_mm)

    def _fast_mode(self, point) -> int:
        """The kernel's mode: an ideal main lens traces every scene from the image side (a point's rays
        through its image)."""
        return (kernel_layout.POINT if point is not None and self.region is not None else
                kernel_layout.IMAGE_SIDE if self.sampling == "image" else kernel_layout.OBJECT_SIDE)

    def _weigh_by_main_lens(self, scene: Scene, r: Rays) -> None:
        """Trace image-side rays back through the main lens: vignetting, Fresnel, and the object radiance."""
        back = Rays(r.x.copy(), r.y.copy(), r.z.copy(), -r.L, -r.M, -r.N, r.w)
        self.camera.main.trace_back(back)
        r.w = back.w
        if isinstance(scene, TextureScene):
            t = (self.camera.layout.z_scene_mm - back.z) / back.N
            r.w = r.w * texture_weight(scene, *self.texture_half_mm, back.x + t * back.L, back.y + t * back.M)

    def photons_per_weight(self, scene: Scene, total: int) -> float:
        """Photons one unit of ray weight stands for, so that pixels read physical photon counts."""
        if isinstance(scene, PointScene):
            return scene.photons * len(scene.points_mm) / total
        if self.sampling == "image" and self.sampler == "sobol":
            image_area = self.cells.area_mm2
        elif self.sampling == "image":
            image_area = 4 * self.image_region.half_x_mm * self.image_region.half_y_mm
        else:  # same radiometric unit: object area seen through the front disc instead of the MLA through the rear
            reg, lay = self.region, self.camera.layout
            ratio = (lay.z_mla_mm - self.cfg.main_lens.thickness_mm) / -lay.z_object_mm
            image_area = 4 * reg.half_x_mm * reg.half_y_mm * ratio * ratio
        pixel_area = (self.cfg.pixel_at_mla_um * 1e-3) ** 2
        return self.cfg.sensor.exposure_photons * (image_area / pixel_area) / total


@dataclass(frozen=True)
class RenderPlan:
    """A render cut into jobs (batches with their keys) and chunks of consecutive jobs: each chunk's
    patches are summed in job order into one partial image, and the partial images are added to the frame
    in chunk order. That order depends on the jobs alone, so a local render and one spread over any
    number of Dask workers give the same image, bit for bit."""

    jobs: list[_Job]
    keys: np.ndarray
    total: int
    chunk_ends: tuple[int, ...]  # index of each chunk's last job

    def chunks(self) -> list[list[_Job]]:
        out, first = [], 0
        for end in self.chunk_ends:
            out.append(self.jobs[first:end + 1])
            first = end + 1
        return out


def sum_patches(parts: list[tuple[int, int, np.ndarray, int]]) -> tuple[int, int, np.ndarray, int]:
    """Patches (row0, col0, patch, hits) added in order over their common bounding box."""
    parts = [p for p in parts if p[2].size]
    hits = sum(p[3] for p in parts)
    if not parts:
        return 0, 0, np.zeros((0, 0)), hits
    r0 = min(p[0] for p in parts)
    c0 = min(p[1] for p in parts)
    r1 = max(p[0] + p[2].shape[0] for p in parts)
    c1 = max(p[1] + p[2].shape[1] for p in parts)
    out = np.zeros((r1 - r0, c1 - c0))
    for r, c, patch, _ in parts:
        out[r - r0:r - r0 + patch.shape[0], c - c0:c - c0 + patch.shape[1]] += patch
    return r0, c0, out, hits


def add_chunk(image: np.ndarray, part: tuple[int, int, np.ndarray, int]) -> int:
    """Add a chunk's partial image into the frame; returns its hits."""
    r0, c0, patch, hits = part
    image[r0:r0 + patch.shape[0], c0:c0 + patch.shape[1]] += patch
    return hits


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
