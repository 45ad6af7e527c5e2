"""Rendering on a Dask cluster, bit-identical to a local render.

The render is planned here exactly as `Renderer.render` plans it (jobs, keys, chunks: `RenderPlan`);
each chunk is one task that a worker traces and sums in job order, and the client adds the chunks'
partial images into the frame in chunk order, whatever order they finish in. So the frame does not
depend on how many workers there are, or on a worker lost mid-render (its chunks run again elsewhere:
tasks are pure). The camera, errors and scene go to the cluster once (`mlaqc.cluster.share`); each
worker builds the camera's Renderer once and keeps it (keyed by a hash of the camera) for later chunks and renders.
"""

from __future__ import annotations

import hashlib
import pickle
import time
from dataclasses import dataclass

import numpy as np

from mlaqc.cluster import TASK_RETRIES, follow, share
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Progress, Renderer, RenderResult, add_chunk
from mlaqc.optics.scene import Scene


@dataclass(frozen=True)
class RenderSpec:
    """What a worker needs to rebuild the client's Renderer and trace its jobs."""

    cfg: CameraConfig
    errors: ErrorMap
    sampling: str
    engine: str
    sampler: str
    scene: Scene
    keys: np.ndarray
    token: str  # the camera's content hash: the worker's cache key, the same for every render of it


_RENDERERS: dict[str, Renderer] = {}  # in each worker process: the renderers of the last two cameras


def _renderer_for(spec: RenderSpec) -> Renderer:
    hit = _RENDERERS.get(spec.token)
    if hit is None:
        while len(_RENDERERS) >= 2:
            _RENDERERS.pop(next(iter(_RENDERERS)))
        hit = _RENDERERS[spec.token] = Renderer(spec.cfg, spec.errors, spec.sampling, spec.engine, spec.sampler)
    return hit


def _trace_chunk(spec: RenderSpec, jobs: list) -> tuple[int, int, np.ndarray, int]:
    """The task: one chunk, traced on one worker thread."""
    return _renderer_for(spec).trace_chunk(spec.scene, jobs, spec.keys)


def _camera_token(renderer: Renderer) -> str:
    """A hash of what builds the Renderer, so that a worker keeps it from one render of a camera to the
    next (building one for Table 1 costs a few tenths of a second)."""
    parts = (renderer.cfg, renderer.sampling, renderer.engine, renderer.sampler)
    h = hashlib.sha256(pickle.dumps(parts))
    h.update(pickle.dumps(renderer.camera.errors))
    return h.hexdigest()


def render_on_cluster(client, renderer: Renderer, scene: Scene, *, rays: int | None = None,
                      rays_per_pixel: float | None = None, seed: int = 0,
                      progress: Progress | None = None) -> RenderResult:
    """`renderer.render(scene, ...)` with the chunks traced on `client`'s workers; the same image."""
    start = time.perf_counter()
    plan = renderer.plan(scene, rays, rays_per_pixel, seed)
    spec = RenderSpec(renderer.cfg, renderer.camera.errors, renderer.sampling, renderer.engine, renderer.sampler,
                      scene, plan.keys, _camera_token(renderer))
    shared = share(client, spec, "render-spec")
    chunks = plan.chunks()
    futures = {client.submit(_trace_chunk, shared, chunk, pure=False, retries=TASK_RETRIES): i
               for i, chunk in enumerate(chunks)}
    image = np.zeros((renderer.cfg.sensor.height_px, renderer.cfg.sensor.width_px))
    waiting: dict[int, tuple] = {}
    landed = done = following = 0
    for i, part in follow(futures, "rendering", progress=False):
        waiting[i] = part
        done += sum(j.n for j in chunks[i])
        while following in waiting:  # add in chunk order: the sum's rounding is then the local one
            landed += add_chunk(image, waiting.pop(following))
            following += 1
        if progress is not None:
            progress(done, plan.total)
    image *= renderer.photons_per_weight(scene, plan.total)
    return RenderResult(image, plan.total, landed, time.perf_counter() - start, seed)
