"""The compiled inspection kernels against straightforward NumPy/scipy formulations of the same indexes.

`_numpy_metrics` is the vectorized NumPy implementation the kernels replaced (one temporary per index over
the whole (rows, cols, h, w) stack), kept here as the oracle, computed in float64.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from mlaqc.inspection.baselines import _scipy_baseline, local_deviation, local_deviations
from mlaqc.inspection.metrics import compute_metrics, reference_images, reference_windows
from mlaqc.inspection.metrics_kernels import INDEX_NAMES, MEDIAN25_PAIRS, N_RING, RING_EDGES, TAPER_PX, median_baselines
from mlaqc.models.reference import reference_model
from mlaqc.optics.config import default_config

ENTROPY_BINS = 32


# ------------------------------------------------------------------------------------ NumPy oracle


def _sum(a: np.ndarray) -> np.ndarray:
    return a.sum(axis=(-1, -2))


def _taper(u, half):
    """The kernel's pixel weight along one axis: 1 inside, down to 0 over the window's outermost TAPER_PX
    (raised cosine)."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip((half - np.abs(u)) / TAPER_PX, 0.0, 1.0))


def _weights(cx, cy, h, w, inset=0.0):
    """Per pixel taper weight (rows, cols, h, w) about the grid centre; `inset` px further in."""
    tx = _taper(np.arange(w) - cx[..., None], 0.5 * w - inset)
    ty = _taper(np.arange(h) - cy[..., None], 0.5 * h - inset)
    return ty[..., :, None] * tx[..., None, :]


def _register(img, wgt, model, cx, cy, steps=2):
    """Weighted Gauss-Newton registration on the reference interpolated at the current estimate; the last
    step's reference moved by that step to first order. Returns the shift, the final tables and centre."""
    h, w = img.shape[-2:]
    qx, qy = cx.astype(np.float64).copy(), cy.astype(np.float64).copy()
    lx, ly = np.zeros(cx.shape), np.zeros(cy.shape)
    for st in range(max(steps, 1)):
        tables = [t.astype(np.float64) for t in reference_windows(model, qx, qy, h, w)[0]]
        if steps == 0:
            break
        r, gx, gy, _lap = tables
        a = _sum(wgt * img * r) / np.maximum(_sum(wgt * r * r), 1e-30)
        d = img - a[..., None, None] * r
        sxx, sxy, syy = _sum(wgt * gx * gx), _sum(wgt * gx * gy), _sum(wgt * gy * gy)
        bx, by = _sum(wgt * gx * d), _sum(wgt * gy * d)
        det = sxx * syy - sxy * sxy
        safe = np.where(np.abs(det) > 1e-30, det, np.inf)
        ax = np.where(np.abs(a) > 1e-30, a, np.inf)
        lx = -(syy * bx - sxy * by) / safe / ax
        ly = -(sxx * by - sxy * bx) / safe / ax
        if st < steps - 1:
            qx, qy = qx + lx, qy + ly
    r, gx, gy, lap = tables
    ref = r - (lx[..., None, None] * gx + ly[..., None, None] * gy)
    qx, qy = qx + lx, qy + ly
    return qx - cx, qy - cy, (ref, gx, gy, lap), (qx, qy)


def _numpy_metrics(img, cx, cy, model, um_per_px):
    """Every index of every lens, NumPy over the whole stack (flux raw)."""
    valid = np.isfinite(img)
    x32 = np.where(valid, img, 0.0).astype(np.float32)
    x = x32.astype(np.float64)
    vf = valid.astype(np.float64)
    h, w = x.shape[-2:]
    wgt = _weights(cx, cy, h, w) * vf  # every index against the reference: tapered, valid pixels
    tg = _weights(cx, cy, h, w, inset=1.0)  # gradient energy: one pixel further in, validity not masked
    dx, dy, (r, gx, gy, lap), (qx, qy) = _register(x, wgt, model, cx, cy)
    a = _sum(wgt * x * r) / np.maximum(_sum(wgt * r * r), 1e-30)
    an = np.where(a != 0, a, np.nan)
    resid = x - a[..., None, None] * r
    yy = np.arange(h)[:, None] - qy[..., None, None]
    xx = np.arange(w)[None, :] - qx[..., None, None]
    out = {}
    flux = _sum(wgt * x)
    out["flux"] = flux
    with np.errstate(divide="ignore", invalid="ignore"):  # (a lens wholly off the frame: lost, NaN)
        out["mean_gray"] = flux / _sum(wgt)
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
    ge = _sum(tg * (np.square(np.gradient(x, axis=-1)) + np.square(np.gradient(x, axis=-2))))
    out["sharpness"] = ge / np.maximum(_sum(tg * (gx * gx + gy * gy)) * a * a, 1e-30)
    out["offset_x_px"], out["offset_y_px"] = dx, dy
    out["offset_um"] = np.hypot(dx, dy) * um_per_px
    top = x.max(axis=(-1, -2), keepdims=True)
    mw = wgt * np.clip(x - 0.5 * top, 0, None)
    s = np.maximum(_sum(mw), 1e-30)
    mx, my = _sum(mw * xx) / s, _sum(mw * yy) / s
    ux, uy = xx - mx[..., None, None], yy - my[..., None, None]
    cxx, cyy, cxy = _sum(mw * ux * ux) / s, _sum(mw * uy * uy) / s, _sum(mw * ux * uy) / s
    tr, det = cxx + cyy, cxx * cyy - cxy * cxy
    root = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    l1, l2 = tr / 2 + root, np.maximum(tr / 2 - root, 0)
    out["size_px"] = np.sqrt(tr)
    out["ellipticity"] = 1.0 - np.sqrt(l2 / np.where(l1 > 0, l1, np.nan))
    out["blur"] = _sum(wgt * resid * lap) / np.maximum(_sum(wgt * lap * lap), 1e-30) / an
    bx, by = r * xx / (0.5 * h), r * yy / (0.5 * h)
    sxx, sxy, syy = _sum(wgt * bx * bx), _sum(wgt * bx * by), _sum(wgt * by * by)
    px, py = _sum(wgt * bx * resid), _sum(wgt * by * resid)
    tdet = np.where(np.abs(sxx * syy - sxy * sxy) > 1e-30, sxx * syy - sxy * sxy, np.inf)
    out["asym_x"], out["asym_y"] = (syy * px - sxy * py) / tdet / an, (sxx * py - sxy * px) / tdet / an
    n = np.where(_sum(wgt) > 0, _sum(wgt), np.nan)
    xs = x / an[..., None, None]
    mse = _sum(wgt * np.square(xs - r)) / n
    peak = (r * vf).max(axis=(-1, -2))
    mxs, mr = _sum(wgt * xs) / n, _sum(wgt * r) / n
    dxm, drm = xs - mxs[..., None, None], r - mr[..., None, None]
    vx, vr, cov = _sum(wgt * dxm * dxm) / n, _sum(wgt * drm * drm) / n, _sum(wgt * dxm * drm) / n
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
            out[f"ring{k}"] = _sum(wgt * resid * weight) / (a * _sum(wgt * r))
    lost = ~(_sum(x) > 0) | (_sum(vf) < 0.5 * h * w)
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
    assert np.array_equal(reference_images(model, cx, cy, 21, 19),
                          reference_windows(model, cx, cy, 21, 19)[0][0].astype(np.float32))


# ------------------------------------------------------------------------------------ median baselines


def _packed_wire(k: int, n: int) -> np.ndarray:
    """Bit k of every input i < n, packed 8 inputs per byte (input 8j + b in bit b of byte j), as 64-bit words."""
    if k < 3:  # bit k of 8j + b is bit k of b: the same byte throughout
        byte = sum(1 << b for b in range(8) if (b >> k) & 1)
        return np.full(n >> 6, int.from_bytes(bytes([byte]) * 8, "little"), np.uint64)
    j = np.arange(n >> 3, dtype=np.uint32)  # bit k of 8j + b is bit k - 3 of j: the byte is all ones or none
    return (((j >> (k - 3)) & 1) * 0xFF).astype(np.uint8).view(np.uint64)


def test_median_network_selects_the_median_of_every_0_1_input():
    """0-1 principle: a comparator network that selects the median of all 2^25 binary inputs selects it
    for every input. Bit-parallel: wire k of input i is bit k of i, packed 8 inputs per byte."""
    n = 1 << 25
    i = np.arange(1 << 12, dtype=np.uint32)  # the packed wires, against bit k of i written out
    for k in range(25):
        direct = np.packbits(((i >> k) & 1).astype(bool), bitorder="little")
        assert np.array_equal(_packed_wire(k, n).view(np.uint8)[: direct.size], direct)
    wires = [_packed_wire(k, n) for k in range(25)]
    for a, b in MEDIAN25_PAIRS:
        wires[a], wires[b] = wires[a] & wires[b], wires[a] | wires[b]
    # the median of 25 bits is 1 where 13 or more are: popcount(i) = popcount(i >> 12) + popcount(i & 4095)
    ones_hi, ones_lo = (sum((np.arange(1 << bits) >> k) & 1 for k in range(bits)) for bits in (13, 12))
    want = np.packbits((np.add.outer(ones_hi, ones_lo) >= 13).ravel(), bitorder="little")
    assert np.array_equal(wires[12].view(np.uint8), want)


@pytest.mark.parametrize("size", [5, 3, 7])
@pytest.mark.parametrize("axis", ["", "x"])
def test_median_baselines_match_scipy(size, axis):
    """The compiled median pass is scipy's median filter (mode 'nearest'), edges along their own line."""
    rng = np.random.default_rng(size)
    for values in (rng.normal(size=(17, 23)), rng.integers(0, 4, (12, 9)).astype(float),  # ties
                   rng.normal(size=(4, 30)), rng.normal(size=(1, 6))):  # smaller than the window
        got = np.empty((1,) + values.shape)
        median_baselines(values[None].copy(), size, np.array([axis == "x"]), got)
        assert np.array_equal(got[0], _scipy_baseline(values, size, axis))


def _baseline_oracle(values: np.ndarray, size: int, axis: str) -> np.ndarray:
    """`local_deviation`'s baseline, lens by lens: the median over the scipy filter's window (clipped to
    the array: mode 'nearest', an edge lens along its edge line, a corner along the columns for an x
    index) of the lenses that belong in it: never a lens not measured (NaN), and not the array's
    outermost lenses for a lens two or more rows in, or one whose window they would fill half of."""
    rows, cols = values.shape
    half = size // 2
    edges = rows >= size and cols >= size
    plain = _scipy_baseline(np.where(np.isfinite(values), values, np.nanmedian(values)), size, axis)
    out = plain.copy()
    clip = lambda k, n: min(max(k, 0), n - 1)  # noqa: E731
    for m in range(rows):
        for n in range(cols):
            ring = min(m, n, rows - 1 - m, cols - 1 - n)
            if edges and ring == 0:
                on_col = n in (0, cols - 1) and (axis == "x" or m not in (0, rows - 1))
                line, k = (values[:, n], m) if on_col else (values[m, :], n)
                win = [line[clip(k + d, line.size)] for d in range(-half, half + 1)]
            else:
                cells = [(i, j) for i in (clip(m + d, rows) for d in range(-half, half + 1))
                         for j in (clip(n + d, cols) for d in range(-half, half + 1))]
                outer = [min(i, j, rows - 1 - i, cols - 1 - j) == 0 for i, j in cells]
                leave = edges and (ring >= 2 or np.mean(outer) >= 0.5)  # beside a corner they fill half of it
                win = [values[i, j] for (i, j), o in zip(cells, outer) if not (leave and o)]
            win = np.array(win)
            if np.isfinite(win).any():
                out[m, n] = np.median(win[np.isfinite(win)])
    return out


@pytest.mark.parametrize("axis", ["", "x"])
def test_local_deviations_leave_out_unmeasured_and_outermost_lenses(axis):
    """A lens not measured (NaN) counts in no neighbour's baseline; the outermost lenses, biased by the
    neighbours they miss, count only in their own edge line's."""
    rng = np.random.default_rng(1)
    values = rng.normal(size=(20, 22))
    values[0, :] += 5.0  # an outermost row far off the rest: it must not move the rows inside it
    values[3, 4] = values[0, 0] = values[7, 21] = values[8, 21] = values[12, 0] = np.nan
    values[15:18, 10:12] = np.nan
    got = local_deviation(values, axis=axis)
    want = values - _baseline_oracle(values, 5, axis)
    assert np.array_equal(np.isnan(got), np.isnan(values))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12, equal_nan=True)
    # the row two in from the shifted one is judged against its own population
    assert np.abs(np.nanmedian(got[2, 2:-2])) < 0.3
    # several maps at once: the same, each with its own NaN
    other = np.where(np.arange(22) == 9, np.nan, values[::-1] * 2.0)  # another map, its own NaN
    a, b = local_deviations([values, other], [axis, "x"])
    np.testing.assert_allclose(a, got, rtol=0, atol=0, equal_nan=True)
    np.testing.assert_allclose(b, other - _baseline_oracle(other, 5, "x"), rtol=0, atol=1e-12, equal_nan=True)


def test_local_deviations_of_a_small_array_leave_out_only_the_unmeasured():
    values = np.arange(12.0).reshape(3, 4)
    values[1, 1] = np.nan
    got = local_deviation(values)
    np.testing.assert_allclose(got, values - _baseline_oracle(values, 5, ""), rtol=0, atol=1e-12, equal_nan=True)


def test_reference_gather_is_the_bilinear_template_interpolation(model):
    """`_gather_at` (the phase-table blend and its element-wise fallback for windows far off the template)
    is the template interpolated bilinearly at the lens centre, indices clipped into the zero border, for
    centres on and between the 1/8-px samples and shifts up to +-40 px."""
    from mlaqc.inspection.metrics import _PHASE_PAD, _phase_tables, _template_stack
    from mlaqc.inspection.metrics_kernels import _gather_at

    stack, size, c = _template_stack(model)
    full = stack.reshape(4, size, size)
    phases = _phase_tables(model)
    os_ = int(model.oversample)
    rng = np.random.default_rng(8)
    h, w = 21, 19
    q = np.concatenate([np.arange(80, 96) + 0.0, 80 + 16 * rng.random(40), rng.uniform(-240, 400, 40)])
    dst = np.empty((4, h * w + 8))
    for fx, fy in zip(q, rng.permutation(q)):
        _gather_at(stack, size, c, os_, phases, _PHASE_PAD, fx, fy, h, w, 4, dst)
        x0, y0 = np.floor(fx), np.floor(fy)
        tx, ty = fx - x0, fy - y0
        wts = [(1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty]
        rows = [np.clip(c + np.arange(h) * os_ - int(y0) - k, 0, size - 1) for k in (0, 1)]
        cols = [np.clip(c + np.arange(w) * os_ - int(x0) - k, 0, size - 1) for k in (0, 1)]
        corner = lambda i, j: full[:, rows[i][:, None], cols[j][None, :]].astype(np.float64)  # noqa: E731
        want = (wts[0] * corner(0, 0) + wts[1] * corner(0, 1)) + (wts[2] * corner(1, 0) + wts[3] * corner(1, 1))
        np.testing.assert_allclose(dst[:, :h * w].reshape(4, h, w), want, rtol=1e-14, atol=1e-15, err_msg=str((fx, fy)))
        if fx == int(fx) and fy == int(fy):  # on a sample: exactly the template's samples
            assert np.array_equal(dst[:, :h * w].reshape(4, h, w), corner(0, 0)), (fx, fy)
