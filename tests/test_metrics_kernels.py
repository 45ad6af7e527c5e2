"""The compiled inspection kernels against straightforward NumPy/scipy formulations of the same indexes.

`_numpy_metrics` is the vectorized NumPy implementation the kernels replaced (one temporary per index over
the whole (rows, cols, h, w) stack), kept here as the oracle, computed in float64.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from mlaqc.inspection.identify import _scipy_baseline, local_deviation, local_deviations
from mlaqc.inspection.metrics import compute_metrics, reference_images, reference_windows
from mlaqc.inspection.metrics_kernels import INDEX_NAMES, MEDIAN25_PAIRS, N_RING, RING_EDGES
from mlaqc.models.reference import reference_model
from mlaqc.optics.config import default_config

ENTROPY_BINS = 32


# ------------------------------------------------------------------------------------ NumPy oracle


def _sum(a: np.ndarray) -> np.ndarray:
    return a.sum(axis=(-1, -2))


def _register(img, valid, model, cx, cy, steps=2):
    h, w = img.shape[-2:]
    dx, dy = np.zeros(cx.shape), np.zeros(cy.shape)
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
        dx = qx - cx - (syy * bx - sxy * by) / safe / ax
        dy = qy - cy - (sxx * by - sxy * bx) / safe / ax
    tables, qx, qy = reference_windows(model, cx + dx, cy + dy, h, w)
    return dx, dy, [t.astype(np.float64) for t in tables], (qx, qy)


def _numpy_metrics(img, cx, cy, model, um_per_px):
    """Every index of every lens, NumPy over the whole stack (flux raw)."""
    valid = np.isfinite(img)
    x32 = np.where(valid, img, 0.0).astype(np.float32)
    x = x32.astype(np.float64)
    vf = valid.astype(np.float64)
    h, w = x.shape[-2:]
    dx, dy, (r, gx, gy, lap), (qx, qy) = _register(x, vf, model, cx, cy)
    r, lap = r * vf, lap * vf
    a = _sum(x * r) / np.maximum(_sum(r * r), 1e-30)
    an = np.where(a != 0, a, np.nan)
    resid = x - a[..., None, None] * r
    yy = np.arange(h)[:, None] - qy[..., None, None]
    xx = np.arange(w)[None, :] - qx[..., None, None]
    out = {}
    flux = _sum(x)
    out["flux"] = flux
    out["mean_gray"] = flux / np.maximum(_sum(vf), 1)
    disc = ((xx * xx + yy * yy) <= (0.35 * h) ** 2) * vf
    nd = np.maximum(_sum(disc), 1)
    mean = _sum(x * disc) / nd
    var = _sum(np.square(x - mean[..., None, None]) * disc) / nd
    out["uniformity"] = 1.0 - np.sqrt(var) / np.where(mean > 0, mean, np.nan)
    # entropy: 32 bins from 0 to the maximum, binned in float32 as the kernel documents
    top32 = x32.max(axis=(-1, -2))
    b = np.clip((x32 / np.where(top32 > 0, top32, np.float32(1))[..., None, None] * np.float32(ENTROPY_BINS))
                .astype(np.int64), 0, ENTROPY_BINS - 1)
    counts = np.stack([_sum((b == k) & valid) for k in range(ENTROPY_BINS)], axis=-1).astype(np.float64)
    p = counts / np.maximum(counts.sum(axis=-1, keepdims=True), 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        out["entropy"] = -np.sum(np.where(p > 0, p * np.log2(p), 0.0), axis=-1)
    ge = _sum(np.square(np.gradient(x, axis=-1)) + np.square(np.gradient(x, axis=-2)))
    out["sharpness"] = ge / np.maximum(_sum(gx * gx + gy * gy) * a * a, 1e-30)
    out["offset_x_px"], out["offset_y_px"] = dx, dy
    out["offset_um"] = np.hypot(dx, dy) * um_per_px
    top = x.max(axis=(-1, -2), keepdims=True)
    wgt = np.clip(x - 0.5 * top, 0, None)
    s = np.maximum(_sum(wgt), 1e-30)
    mx, my = _sum(wgt * xx) / s, _sum(wgt * yy) / s
    ux, uy = xx - mx[..., None, None], yy - my[..., None, None]
    cxx, cyy, cxy = _sum(wgt * ux * ux) / s, _sum(wgt * uy * uy) / s, _sum(wgt * ux * uy) / s
    tr, det = cxx + cyy, cxx * cyy - cxy * cxy
    root = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    l1, l2 = tr / 2 + root, np.maximum(tr / 2 - root, 0)
    out["size_px"] = np.sqrt(tr)
    out["ellipticity"] = 1.0 - np.sqrt(l2 / np.where(l1 > 0, l1, np.nan))
    out["blur"] = _sum(resid * lap) / np.maximum(_sum(lap * lap), 1e-30) / an
    bx, by = r * xx / (0.5 * h), r * yy / (0.5 * h)
    sxx, sxy, syy = _sum(bx * bx), _sum(bx * by), _sum(by * by)
    px, py = _sum(bx * resid), _sum(by * resid)
    tdet = np.where(np.abs(sxx * syy - sxy * sxy) > 1e-30, sxx * syy - sxy * sxy, np.inf)
    out["asym_x"], out["asym_y"] = (syy * px - sxy * py) / tdet / an, (sxx * py - sxy * px) / tdet / an
    n = np.maximum(_sum(vf), 1)
    xs = x / an[..., None, None]
    mse = _sum(np.square(xs - r) * vf) / n
    peak = r.max(axis=(-1, -2))
    mxs, mr = _sum(xs * vf) / n, _sum(r * vf) / n
    dxm, drm = (xs - mxs[..., None, None]) * vf, (r - mr[..., None, None]) * vf
    vx, vr, cov = _sum(dxm * dxm) / n, _sum(drm * drm) / n, _sum(dxm * drm) / n
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    out["ssim"] = ((2 * mxs * mr + c1) * (2 * cov + c2)) / ((mxs * mxs + mr * mr + c1) * (vx + vr + c2))
    with np.errstate(divide="ignore", invalid="ignore"):
        out["psnr_db"] = 10 * np.log10(peak * peak / mse)
        out["ncc"] = cov / np.sqrt(vx * vr)
    # soft rings: a pixel at distance d counts in ring k by the overlap of [d - 1/2, d + 1/2] with the ring
    d = np.hypot(xx, yy)
    edges = np.concatenate([[-np.inf], RING_EDGES * 0.5 * h, [np.inf]])
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(N_RING):
            weight = np.clip(np.minimum(d + 0.5, edges[k + 1]) - np.maximum(d - 0.5, edges[k]), 0.0, 1.0)
            out[f"ring{k}"] = _sum(resid * weight) / (a * _sum(r))
    lost = ~(flux > 0) | (_sum(vf) < 0.5 * h * w)
    for v in out.values():
        v[lost] = np.nan
    return out


# ------------------------------------------------------------------------------------ test stacks


@pytest.fixture(scope="module")
def model():
    return reference_model(default_config())


def _stack(model, rows=6, cols=7, seed=3):
    """Simulated sub-images: the ideal lens at random sub-pixel shifts and fluxes, some blurred or tilted,
    noise; a row of windows cut by the frame edge (NaN), one window off the frame, one black lens."""
    rng = np.random.default_rng(seed)
    h = w = 21
    cx = 10 + rng.uniform(-0.5, 0.5, (rows, cols))
    cy = 10 + rng.uniform(-0.5, 0.5, (rows, cols))
    shift_x, shift_y = rng.normal(0, 0.3, (rows, cols)), rng.normal(0, 0.3, (rows, cols))
    ref = reference_windows(model, cx + shift_x, cy + shift_y, h, w)[0][0].astype(np.float64)
    img = ref * rng.uniform(0.5, 1.5, (rows, cols))[..., None, None]
    img[1, 2] = gaussian_filter(img[1, 2], 1.2)
    img[2, 3] *= 1 + 0.3 * (np.arange(w) - 10) / 10
    img += rng.normal(0, 0.01, img.shape)
    img[0, :, :, :4] = np.nan  # frame edge
    img[3, 0] = np.nan  # off the frame
    img[4, 4] = 0.0  # black lens: lost
    img[5, 6, :12] = np.nan  # more than half outside: lost
    return img.astype(np.float32), cx, cy


def test_lens_indexes_match_the_numpy_formulation(model):
    img, cx, cy = _stack(model)
    got = compute_metrics(img, cx, cy, model, um_per_px_at_mla=1.7, threads=1)
    want = _numpy_metrics(img, cx, cy, model, 1.7)
    want["flux"] = want["flux"] / np.nanmedian(np.where(want["flux"] > 0, want["flux"], np.nan))  # (not 102 x 102)
    assert set(got.values) == set(INDEX_NAMES) == set(want)
    lost = ~np.isfinite(want["flux"])
    assert lost.sum() == 3 and lost[3, 0] and lost[4, 4] and lost[5, 6]
    for name in INDEX_NAMES:
        assert np.array_equal(np.isfinite(got[name]), np.isfinite(want[name])), name
        np.testing.assert_allclose(got[name], want[name], rtol=1e-9, atol=1e-12, err_msg=name)
    # the blurred, tilted and shifted lenses really moved their indexes (the stack exercises them)
    assert got["blur"][1, 2] > 5 * np.nanstd(np.delete(got["blur"].ravel(), [9]))
    assert abs(got["asym_x"][2, 3]) > 0.1


def test_threads_and_chunks_do_not_change_results(model):
    img, cx, cy = _stack(model, rows=24, cols=23, seed=5)
    one = compute_metrics(img, cx, cy, model, um_per_px_at_mla=1.7, threads=1)
    two = compute_metrics(img, cx, cy, model, um_per_px_at_mla=1.7, threads=2)
    for name in INDEX_NAMES:
        assert np.array_equal(one[name], two[name], equal_nan=True), name


def test_reference_images_are_the_template_gather(model):
    rng = np.random.default_rng(0)
    cx, cy = rng.uniform(8, 12, (4, 5)), rng.uniform(8, 12, (4, 5))
    assert np.array_equal(reference_images(model, cx, cy, 21, 19), reference_windows(model, cx, cy, 21, 19)[0][0])


# ------------------------------------------------------------------------------------ median baselines


def test_median_network_selects_the_median_of_every_0_1_input():
    """0-1 principle: a comparator network that selects the median of all 2^25 binary inputs selects it
    for every input. Bit-parallel: wire k of input i is bit k of i, packed 8 inputs per byte."""
    n = 1 << 25
    idx = np.arange(n >> 3, dtype=np.uint32)[:, None] * 8 + np.arange(8, dtype=np.uint32)  # (n/8, 8)
    wires = [np.packbits(((idx >> k) & 1).astype(bool), axis=1, bitorder="little").ravel() for k in range(25)]
    for a, b in MEDIAN25_PAIRS:
        wires[a], wires[b] = wires[a] & wires[b], wires[a] | wires[b]
    ones = np.zeros(idx.shape, np.uint8)
    for k in range(25):
        ones += ((idx >> k) & 1).astype(np.uint8)
    want = np.packbits(ones >= 13, axis=1, bitorder="little").ravel()
    assert np.array_equal(wires[12], want)


@pytest.mark.parametrize("size", [5, 3, 7])
@pytest.mark.parametrize("axis", ["", "x"])
def test_median_baselines_match_scipy(size, axis):
    rng = np.random.default_rng(size)
    for values in (rng.normal(size=(17, 23)), rng.integers(0, 4, (12, 9)).astype(float),  # ties
                   rng.normal(size=(4, 30)), rng.normal(size=(1, 6))):  # smaller than the window
        got = local_deviation(values, size=size, axis=axis)
        assert np.array_equal(got, values - _scipy_baseline(values, size, axis))


def test_local_deviations_fill_nan_with_the_median():
    rng = np.random.default_rng(1)
    values = rng.normal(size=(20, 20))
    values[3, 4] = values[0, 0] = np.nan
    fill = np.where(np.isfinite(values), values, np.nanmedian(values))
    a, b = local_deviations([values, values.T.copy()], ["x", ""])
    assert np.isnan(a[3, 4]) and np.isnan(a[0, 0])
    assert np.array_equal(a, values - _scipy_baseline(fill, 5, "x"), equal_nan=True)
    assert np.array_equal(b, values.T - _scipy_baseline(fill.T.copy(), 5, ""), equal_nan=True)


def test_phase_table_gather_equals_the_clipped_template_gather(model):
    """The contiguous phase-table copy and its element-wise fallback (windows far off the template) give
    exactly the clipped gather of `reference_windows`, for every phase and shifts up to +-40 px."""
    from mlaqc.inspection.metrics import _PHASE_PAD, _phase_tables, _template_stack
    from mlaqc.inspection.metrics_kernels import _gather_tables

    stack, size, c = _template_stack(model)
    phases = _phase_tables(model)
    os_ = int(model.oversample)
    rng = np.random.default_rng(8)
    h, w = 21, 19
    q = np.concatenate([np.arange(80, 96), rng.integers(-240, 400, 40)])  # every phase near centre, then wild
    dst = np.empty((4, h * w), np.float32)
    for qx, qy in zip(q, rng.permutation(q)):
        _gather_tables(stack, size, c, os_, phases, _PHASE_PAD, int(qx), int(qy), h, w, 4, dst)
        want = reference_windows(model, np.array([[qx / os_]]), np.array([[qy / os_]]), h, w)[0][:, 0, 0]
        assert np.array_equal(dst.reshape(4, h, w), want), (qx, qy)
