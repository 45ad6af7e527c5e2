"""Per-lens sub-image indexes for all lenses at once: one compiled pass per lens over its window
(mlaqc.inspection.metrics_kernels.lens_indexes), lenses split over a thread pool; no per-lens Python.

The reference sub-image of each lens is interpolated from the oversampled reference template at that
lens' exact (current) position, bilinear between its 1/8-px samples, so that it moves continuously with
the lens. Against it each sub-image is registered (Lucas-Kanade, Gauss-Newton steps from the grid
centre): the shift from its grid position is the QC position signal. The residual is projected on blur
(the template's Laplacian) and intensity tilt (asymmetry); the usual no-reference and full-reference
indexes (flux, uniformity, entropy, sharpness, moments, PSNR, SSIM, NCC) are computed alongside for the
report. Everything taken against the reference weights the window's outermost pixel fading to zero
(`metrics_kernels.TAPER_PX`), so a window cut one pixel further over changes nothing.

Why both: a sub-image whose profile differs from the reference's (another rim, no overlap light in the
gaps) is registered with a step gain below 1. With the reference snapped to a 1/8-px phase the result was
that phase plus a fraction of the rest, and it jumped by up to 0.05 px wherever the snapped phase
changed; and a window cut on the nearest pixel swapped a mismatched edge column from one side to the
other as the centre crossed half a pixel (jumps of 0.1-0.13 px, false `position` flags on an independent
generator's frames). Now every index is a continuous function of the lens' position.
"""

from __future__ import annotations

import os
from functools import partial
from itertools import pairwise

import numpy as np

from mlaqc.inspection.metrics_kernels import INDEX_NAMES, N_INDEX, gather_tables_at, lens_indexes
from mlaqc.parallel import run_parts
from mlaqc.inspection.results import LensMetrics
from mlaqc.models.reference import ReferenceModel


def reference_windows(model: ReferenceModel, cx: np.ndarray, cy: np.ndarray, h: int, w: int):
    """Reference sub-image, its gradients and Laplacian for windows whose lens centre is at (cx, cy)
    (window pixel units), as one (4, rows, cols, h, w) float64 gather, interpolated at exactly that
    centre (what `lens_indexes` registers against); also that centre (qx, qy) = (cx, cy)."""
    cx = np.asarray(cx, dtype=np.float64)
    cy = np.asarray(cy, dtype=np.float64)
    out = _gather(model, cx, cy, h, w, 4)
    return np.moveaxis(out.reshape(cx.shape + (4, h, w)), -3, 0), cx.copy(), cy.copy()


def _gather(model: ReferenceModel, cx: np.ndarray, cy: np.ndarray, h: int, w: int, ntab: int,
            dtype=np.float64) -> np.ndarray:
    """(N, ntab, h*w) `dtype`: the first `ntab` template tables at every centre (compiled, continuous),
    chunks of lenses on a thread pool (the kernel releases the GIL; 10,404 lenses take 23 ms on one core)."""
    stack, size, c = _template_stack(model)
    fx = np.ascontiguousarray(cx, dtype=np.float64).ravel()
    fy = np.ascontiguousarray(cy, dtype=np.float64).ravel()
    out = np.empty((fx.size, ntab, h * w), dtype=dtype)
    run = partial(gather_tables_at, stack, size, c, int(model.oversample), _phase_tables(model), _PHASE_PAD)
    workers = max(1, min(os.cpu_count() or 1, fx.size // 512))
    edges = np.linspace(0, fx.size, workers + 1).astype(int)
    parts = [(a, b) for a, b in pairwise(edges) if b > a]
    if len(parts) <= 1:
        run(fx, fy, h, w, ntab, out)
    else:
        run_parts(lambda ab: run(fx[ab[0]:ab[1]], fy[ab[0]:ab[1]], h, w, ntab, out[ab[0]:ab[1]]), parts, len(parts))
    return out


def _template_stack(model: ReferenceModel) -> tuple[np.ndarray, int, int]:
    """Template, d/dx, d/dy and Laplacian per coarse pixel, flattened, with a zero border so that
    clipped indices read zeros (cached on the model object)."""
    cached = getattr(model, "_stack", None)
    if cached is None:
        t = model.template
        os_ = model.oversample
        gy, gx = np.gradient(t)
        gx, gy = gx * os_, gy * os_
        lap = (np.gradient(gx, axis=1) + np.gradient(gy, axis=0)) * os_
        padded = np.pad(np.stack([t, gx, gy, lap]), ((0, 0), (1, 1), (1, 1)))
        size = padded.shape[1]
        cached = (padded.reshape(4, -1).astype(np.float32), size, int(model.centre) + 1)
        object.__setattr__(model, "_stack", cached)
    return cached


_PHASE_PAD = 8  # zero margin (coarse px) of the phase tables: windows shifted up to ~15 px stay on the fast path


def _phase_tables(model: ReferenceModel) -> np.ndarray:
    """The four template tables decimated per sub-pixel phase: [k, pr, pc] is table k's every
    oversample-th row from pr and column from pc, zero-padded by _PHASE_PAD, so that a lens' window is a
    contiguous block (cached on the model object)."""
    cached = getattr(model, "_phases", None)
    if cached is None:
        stack, size, _c = _template_stack(model)
        os_ = int(model.oversample)
        full = stack.reshape(4, size, size)
        n = -(-size // os_)
        cached = np.zeros((4, os_, os_, n + 2 * _PHASE_PAD, n + 2 * _PHASE_PAD), np.float32)
        for pr in range(os_):
            for pc in range(os_):
                blk = full[:, pr::os_, pc::os_]
                cached[:, pr, pc, _PHASE_PAD:_PHASE_PAD + blk.shape[1], _PHASE_PAD:_PHASE_PAD + blk.shape[2]] = blk
        object.__setattr__(model, "_phases", cached)
    return cached


def reference_images(model: ReferenceModel, cx: np.ndarray, cy: np.ndarray, h: int, w: int) -> np.ndarray:
    """Only the reference sub-image (float32, cx.shape + (h, w)) of `reference_windows`: the report needs
    it for every lens, and the gradient tables would be 4x the work."""
    return _gather(model, np.asarray(cx), np.asarray(cy), h, w, 1, np.float32).reshape(np.shape(cx) + (h, w))


def compute_metrics(img: np.ndarray, cx: np.ndarray, cy: np.ndarray, model: ReferenceModel, *,
                    um_per_px_at_mla: float, threads: int | None = None, steps: int = 2) -> LensMetrics:
    """All indexes for sub-images `img` (rows, cols, h, w; NaN outside the frame) whose grid-predicted
    centres are (cx, cy) in window pixel coordinates, at most half a pixel from the window's centre (as
    `subimages.divide` cuts them); `steps` Gauss-Newton registration steps.

    One compiled pass per lens (mlaqc.inspection.metrics_kernels.lens_indexes); chunks of lenses run on a thread pool
    (the kernel releases the GIL). Only the flux normalization needs all lenses and is done after."""
    stack, size, c = _template_stack(model)
    phases = _phase_tables(model)
    rows, cols, h, w = img.shape
    n = rows * cols
    data = np.ascontiguousarray(img, dtype=np.float32).reshape(n, h, w)
    fx = np.ascontiguousarray(cx, dtype=np.float64).ravel()
    fy = np.ascontiguousarray(cy, dtype=np.float64).ravel()
    out = np.empty((n, N_INDEX))
    run = partial(lens_indexes, data, fx, fy, stack, size, c, int(model.oversample), phases, _PHASE_PAD,
                  float(um_per_px_at_mla), steps)
    workers = max(1, min(threads or os.cpu_count() or 1, n // 256 or 1))
    # a few chunks per worker keep both cores busy when one is slowed by other work on the machine
    edges = np.linspace(0, n, 4 * workers + 1 if workers > 1 else 2).astype(int)
    chunks = [(int(a), int(b)) for a, b in pairwise(edges) if b > a]
    if workers == 1:
        for a, b in chunks:
            run(a, b, out)
    else:
        run_parts(lambda ab: run(ab[0], ab[1], out), chunks, workers)
    by_index = np.ascontiguousarray(out.T)  # each index map contiguous: identification reads every one often
    values = {name: by_index[q].reshape(rows, cols) for q, name in enumerate(INDEX_NAMES)}
    flux = values["flux"]
    rel = flux / model.flux if model.flux.shape == flux.shape else flux
    with np.errstate(invalid="ignore", divide="ignore"):
        values["flux"] = rel / np.nanmedian(np.where(flux > 0, rel, np.nan))
    return LensMetrics(values)
