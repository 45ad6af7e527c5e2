"""Per-lens sub-image indexes, vectorized over all lenses at once.

The reference sub-image of each lens is gathered from the oversampled reference template at that lens'
sub-pixel phase (quantized to 1/8 px and compensated exactly). Against it each sub-image is registered
(Lucas-Kanade, two Gauss-Newton steps): the shift from its grid position is the QC position signal. The
residual is projected on blur (the template's Laplacian) and intensity tilt (asymmetry); the usual
no-reference and full-reference indexes (flux, uniformity, entropy, sharpness, moments, PSNR, SSIM,
NCC) are computed alongside for the report.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from mlaqc.reference import ReferenceModel
from mlaqc.results import LensMetrics

_ENTROPY_BINS = 32


def reference_windows(model: ReferenceModel, cx: np.ndarray, cy: np.ndarray, h: int, w: int):
    """Reference sub-image, its gradients and Laplacian for windows whose lens centre is at (cx, cy)
    (window pixel units), as one (4, rows, cols, h, w) float32 gather; also the exact position (qx, qy)
    the gathered reference is centred at (cx, cy quantized to 1/oversample px)."""
    os_ = model.oversample
    qx = np.rint(cx * os_).astype(np.int64)
    qy = np.rint(cy * os_).astype(np.int64)
    stack, size, c = _template_stack(model)
    ti = np.clip(c + np.arange(h)[None, None, :] * os_ - qy[..., None], 0, size - 1)  # (R, C, h)
    tj = np.clip(c + np.arange(w)[None, None, :] * os_ - qx[..., None], 0, size - 1)  # (R, C, w)
    flat = (ti[..., :, None] * size + tj[..., None, :]).astype(np.intp)
    return np.take(stack, flat, axis=1), qx / os_, qy / os_


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


def _sum(a: np.ndarray) -> np.ndarray:
    return a.sum(axis=(-1, -2))


def register(img: np.ndarray, valid: np.ndarray, model: ReferenceModel, cx: np.ndarray, cy: np.ndarray, steps: int = 2):
    """Sub-pixel shift of every sub-image against its reference; returns shift (dx, dy), flux scale a,
    and the reference tables at the final position."""
    h, w = img.shape[-2:]
    dx = np.zeros(cx.shape)
    dy = np.zeros(cy.shape)
    for _ in range(steps):
        (r, gx, gy, _lap), qx, qy = reference_windows(model, cx + dx, cy + dy, h, w)
        r, gx, gy = r * valid, gx * valid, gy * valid
        a = _sum(img * r) / np.maximum(_sum(r * r), 1e-30)
        d = img - a[..., None, None] * r
        sxx, sxy, syy = _sum(gx * gx), _sum(gx * gy), _sum(gy * gy)
        bx, by = _sum(gx * d), _sum(gy * d)
        det = sxx * syy - sxy * sxy
        safe = np.where(np.abs(det) > 1e-30, det, np.inf)
        ax = np.where(np.abs(a) > 1e-30, a, np.inf)
        # I ~ a R(x - d) ~ a R - a d.grad R, so d = -(G'G)^-1 G'(I - a R) / a
        step_x = -(syy * bx - sxy * by) / safe / ax
        step_y = -(sxx * by - sxy * bx) / safe / ax
        # the reference sat at (qx, qy), not at (cx + dx, cy + dy): the measured shift is from (qx, qy)
        dx = qx - cx + step_x
        dy = qy - cy + step_y
    tables, qx, qy = reference_windows(model, cx + dx, cy + dy, h, w)
    return dx, dy, tables, (qx, qy)


def compute_metrics(img: np.ndarray, cx: np.ndarray, cy: np.ndarray, model: ReferenceModel, *,
                    um_per_px_at_mla: float, threads: int | None = None) -> LensMetrics:
    """All indexes for sub-images `img` (rows, cols, h, w; NaN outside the frame) whose grid-predicted
    centres are (cx, cy) in window pixel coordinates. Blocks of lens rows run on a thread pool (NumPy
    releases the GIL); only the flux normalization needs all lenses and is done after."""
    _template_stack(model)  # build the shared tables once, before the threads read them
    rows = img.shape[0]
    n = max(1, min(threads or os.cpu_count() or 1, rows // 8 or 1))
    edges = np.linspace(0, rows, n + 1).astype(int)
    blocks = [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]

    def block(ab):
        a, b = ab
        return _block_metrics(img[a:b], cx[a:b], cy[a:b], model, um_per_px_at_mla)

    if len(blocks) == 1:
        parts = [block(blocks[0])]
    else:
        with ThreadPoolExecutor(len(blocks)) as pool:
            parts = list(pool.map(block, blocks))
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    flux = out["flux"]
    rel = flux / model.flux if model.flux.shape == flux.shape else flux
    out["flux"] = rel / np.nanmedian(np.where(flux > 0, rel, np.nan))
    return LensMetrics(out)


def _block_metrics(img, cx, cy, model: ReferenceModel, um_per_px_at_mla: float) -> dict[str, np.ndarray]:
    """Every index of a block of lens rows; 'flux' is left raw (normalized over all lenses later)."""
    valid = np.isfinite(img)
    x = np.where(valid, img, 0.0).astype(np.float32)
    vf = valid.astype(np.float32)
    h, w = x.shape[-2:]
    dx, dy, (r, gx, gy, lap), (qx, qy) = register(x, vf, model, cx, cy)
    r, lap = r * vf, lap * vf
    a = _sum(x * r) / np.maximum(_sum(r * r), 1e-30)
    resid = x - a[..., None, None] * r
    yy = np.arange(h)[:, None] - qy[..., None, None]
    xx = np.arange(w)[None, :] - qx[..., None, None]
    out: dict[str, np.ndarray] = {}
    flux = _sum(x)
    out["flux"] = flux.astype(np.float64)
    out["mean_gray"] = flux / np.maximum(_sum(vf), 1)
    out.update(_disc_stats(x, vf, xx, yy, h))
    out["entropy"] = _entropy(x, valid)
    ge = _sum(np.square(np.gradient(x, axis=-1)) + np.square(np.gradient(x, axis=-2)))
    ge_ref = _sum(np.square(gx) + np.square(gy)) * a * a
    out["sharpness"] = ge / np.maximum(ge_ref, 1e-30)
    out["offset_x_px"] = dx
    out["offset_y_px"] = dy
    out["offset_um"] = np.hypot(dx, dy) * um_per_px_at_mla
    out.update(_moments(x, xx, yy))
    out["blur"] = _sum(resid * lap) / np.maximum(_sum(lap * lap), 1e-30) / np.where(a != 0, a, np.nan)
    out.update(_tilt(resid, r, xx, yy, a, h))
    out.update(_full_reference(x, r, vf, a))
    lost = ~(flux > 0) | (_sum(vf) < 0.5 * h * w)
    for v in out.values():
        v[lost] = np.nan
    return out


def _disc_stats(x, vf, xx, yy, h):
    """Uniformity inside the central disc (radius 0.35 of the window)."""
    disc = ((xx * xx + yy * yy) <= (0.35 * h) ** 2) * vf
    n = np.maximum(_sum(disc), 1)
    mean = _sum(x * disc) / n
    var = _sum(np.square(x - mean[..., None, None]) * disc) / n
    return {"uniformity": 1.0 - np.sqrt(var) / np.where(mean > 0, mean, np.nan)}


def _entropy(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Shannon entropy (bits) of each sub-image's grey levels in 32 bins from 0 to its maximum."""
    rows, cols = x.shape[:2]
    top = x.max(axis=(-1, -2))
    scaled = x / np.where(top > 0, top, 1.0)[..., None, None]
    b = np.clip((scaled * _ENTROPY_BINS).astype(np.int64), 0, _ENTROPY_BINS - 1)
    lens = np.arange(rows * cols).reshape(rows, cols)[..., None, None]
    counts = np.bincount((lens * _ENTROPY_BINS + b)[valid], minlength=rows * cols * _ENTROPY_BINS)
    p = counts.reshape(rows, cols, _ENTROPY_BINS).astype(np.float64)
    p /= np.maximum(p.sum(axis=-1, keepdims=True), 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return -np.nansum(np.where(p > 0, p * np.log2(p), 0.0), axis=-1)


def _moments(x, xx, yy):
    """Second-moment size and ellipticity of the bright part (above half the sub-image's maximum)."""
    top = x.max(axis=(-1, -2), keepdims=True)
    wgt = np.clip(x - 0.5 * top, 0, None)
    s = np.maximum(_sum(wgt), 1e-30)
    mx, my = _sum(wgt * xx) / s, _sum(wgt * yy) / s
    ux, uy = xx - mx[..., None, None], yy - my[..., None, None]
    cxx, cyy, cxy = _sum(wgt * ux * ux) / s, _sum(wgt * uy * uy) / s, _sum(wgt * ux * uy) / s
    tr, det = cxx + cyy, cxx * cyy - cxy * cxy
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    l1, l2 = tr / 2 + disc, np.maximum(tr / 2 - disc, 0)
    return {"size_px": np.sqrt(tr), "ellipticity": 1.0 - np.sqrt(l2 / np.where(l1 > 0, l1, np.nan))}


def _tilt(resid, r, xx, yy, a, h):
    """Intensity tilt across the sub-image (relative brightness change from centre to window edge)."""
    half = 0.5 * h
    bx, by = r * xx / half, r * yy / half
    sxx, sxy, syy = _sum(bx * bx), _sum(bx * by), _sum(by * by)
    px, py = _sum(bx * resid), _sum(by * resid)
    det = np.where(np.abs(sxx * syy - sxy * sxy) > 1e-30, sxx * syy - sxy * sxy, np.inf)
    an = np.where(a != 0, a, np.nan)
    return {"asym_x": (syy * px - sxy * py) / det / an, "asym_y": (sxx * py - sxy * px) / det / an}


def _full_reference(x, r, vf, a):
    """PSNR, single-window SSIM and NCC of the flux-scaled sub-image against its reference."""
    n = np.maximum(_sum(vf), 1)
    xs = x / np.where(a != 0, a, np.nan)[..., None, None]
    mse = _sum(np.square(xs - r) * vf) / n
    peak = r.max(axis=(-1, -2))
    mx, mr = _sum(xs * vf) / n, _sum(r * vf) / n
    dxm, drm = (xs - mx[..., None, None]) * vf, (r - mr[..., None, None]) * vf
    vx, vr, cov = _sum(dxm * dxm) / n, _sum(drm * drm) / n, _sum(dxm * drm) / n
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    ssim = ((2 * mx * mr + c1) * (2 * cov + c2)) / ((mx * mx + mr * mr + c1) * (vx + vr + c2))
    with np.errstate(divide="ignore", invalid="ignore"):
        psnr = 10 * np.log10(peak * peak / mse)
        ncc = cov / np.sqrt(vx * vr)
    return {"psnr_db": psnr, "ssim": ssim, "ncc": ncc}
