"""Compiled (Numba) kernels of the through-focus analysis: every spot's first guess, and its windowed
centroid, second moment and the moment's variance (mlaqc.inspection.throughfocus_spots.moments).

Why: the NumPy formulation (separable weights, batched matrix products) made a dozen (L, n) temporaries per
pass and five passes per frame: 0.12 s of the 0.25 s a 32-frame series took on one core. Here each lens
is read start to finish while its window sits in L1 cache, and only the pixels the window weighs are
visited. The sums are the per-pixel definitions (weight = row weight x column weight), accumulated in
float64 in row-major order; they differ from the matrix products in the last bits only. Kernels release
the GIL: the analysis runs its +u / -u pairs on a thread per core.
"""

from __future__ import annotations

import math

import numpy as np
from mlaqc.compiled import kernel

_jit = kernel(cache=True, nogil=True, error_model="numpy")

# columns of the (L, 6) array `moments_kernel` fills
MX, MY, M2, M2_VAR, FLUX, WIDTH = range(6)


@_jit
def _weights(centre, w, half, out):
    """out[k] = the share of pixel [k - half - 1/2, k - half + 1/2] inside [centre - w, centre + w];
    returns the first and one past the last pixel with a share above zero."""
    lo, hi = out.shape[0], 0
    for k in range(out.shape[0]):
        v = min(max(w + 0.5 - abs((k - half) - centre), 0.0), 1.0)
        out[k] = v
        if v > 0.0:
            lo = min(lo, k)
            hi = k + 1
    return lo, hi


@_jit.aot("f8[:, :, ::1], f8[::1], f8[::1], f8[::1], f8[::1], i8, f8, f8, i8, b1, f8[:, ::1]")
def moments_kernel(cells, background, cx0, cy0, w0, refine, e_per_unit, bg_sigma, ring_px, variance, out):
    """For every window of `cells` (L, n, n), background-subtracted, with its `background` (L,): the
    centroid (window coordinates), the second moment x + y (px^2), its variance (NaN unless `variance`),
    the flux and the window half-width used, in a square window of half-width w around (cx, cy) that
    follows the centroid `refine` times and shrinks to stay inside the ring (as throughfocus_spots.moments
    documents). out: (L, 6), columns MX, MY, M2, M2_VAR, FLUX, WIDTH."""
    n = cells.shape[1]
    half = n // 2
    limit = half - ring_px - 0.5
    ring = n * n - (n - 2 * ring_px) ** 2
    noise2 = bg_sigma * bg_sigma
    wx = np.empty(n)
    wy = np.empty(n)
    for m in range(cells.shape[0]):
        c = cells[m]
        cx, cy = cx0[m], cy0[m]
        w = min(max(w0[m], 0.5), limit)
        flux = mx = my = np.nan
        x0 = x1 = y0 = y1 = 0
        for it in range(refine + 1):
            x0, x1 = _weights(cx, w, half, wx)
            y0, y1 = _weights(cy, w, half, wy)
            flux = sx = sy = 0.0
            for i in range(y0, y1):
                for j in range(x0, x1):
                    v = c[i, j] * wy[i] * wx[j]
                    flux += v
                    sx += v * (j - half)
                    sy += v * (i - half)
            mx, my = sx / flux, sy / flux
            if it < refine:
                cx = min(max(mx if math.isfinite(mx) else cx, -half + 1.0), half - 1.0)
                cy = min(max(my if math.isfinite(my) else cy, -half + 1.0), half - 1.0)
                w = min(max(min(w, limit - max(abs(cx), abs(cy)) + ring_px), 0.5), limit)
        s2 = 0.0
        for i in range(y0, y1):
            dy2 = (i - half - my) ** 2
            for j in range(x0, x1):
                s2 += c[i, j] * wy[i] * wx[j] * ((j - half - mx) ** 2 + dy2)
        m2 = s2 / flux
        m2_var = np.nan
        if variance:
            # delta method: d m2 / d v_ij = w_ij (r2_ij - m2) / flux (the centroid's own derivative is zero)
            acc = lever_sum = 0.0
            for i in range(y0, y1):
                dy2 = (i - half - my) ** 2
                for j in range(x0, x1):
                    lever = wy[i] * wx[j] * ((j - half - mx) ** 2 + dy2 - m2)
                    var_pix = max(c[i, j] + background[m], 0.0) / e_per_unit + noise2
                    acc += lever * lever * var_pix
                    lever_sum += lever
            m2_var = acc / flux ** 2 + (np.pi / 2) * noise2 / ring * (lever_sum / flux) ** 2  # the ring median
        out[m, MX], out[m, MY], out[m, M2], out[m, M2_VAR], out[m, FLUX], out[m, WIDTH] = mx, my, m2, m2_var, flux, w


@_jit.aot("f8[:, :, ::1], i8, f8[:, ::1]")
def first_guess_kernel(cells, ring_px, out):
    """out[m] = (x, y), window coordinates, of the brightest 3 x 3 sum of window m whose centre is inside
    the ring (the first of equals in row-major order)."""
    n = cells.shape[1]
    half = n // 2
    col = np.empty(n)
    for m in range(cells.shape[0]):
        c = cells[m]
        best, bx, by = -np.inf, ring_px, ring_px
        for y in range(ring_px, n - ring_px):
            for x in range(ring_px - 1, n + 1 - ring_px):
                col[x] = c[y - 1, x] + c[y, x] + c[y + 1, x]
            for x in range(ring_px, n - ring_px):
                s = col[x - 1] + col[x] + col[x + 1]
                if s > best:
                    best, bx, by = s, x, y
        out[m, 0], out[m, 1] = bx - half, by - half


@_jit
def _select(a, k):
    """Reorder `a` in place so that a[k] is its k-th smallest, none before it larger, none after it smaller
    (quickselect, median-of-three pivots); returns a[k]."""
    lo, hi = 0, a.shape[0] - 1
    while hi > lo:
        mid = (lo + hi) // 2
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
        pivot = a[mid]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


@_jit.aot("u1[:, ::1], i8[::1], i8[::1], f8, f8, i8, f8, f8[:, :, ::1], f4[::1], b1[::1]",
          "u2[:, ::1], i8[::1], i8[::1], f8, f8, i8, f8, f8[:, :, ::1], f4[::1], b1[::1]",
          "f4[:, ::1], i8[::1], i8[::1], f8, f8, i8, f8, f8[:, :, ::1], f4[::1], b1[::1]",
          "f8[:, ::1], i8[::1], i8[::1], f8, f8, i8, f8, f8[:, :, ::1], f4[::1], b1[::1]")
def spot_windows_kernel(data, iy0, ix0, black, span, ring_px, saturated_level, cells, background, saturated):
    """Window m of `cells` (L, n, n) = the frame's pixels from (iy0[m], ix0[m]) normalized in float32,
    (data - black) / span as `raw_levels.normalized` computes it, less the window's background: the median of
    its outer ring (ring_px wide, float32 as NumPy's median of it); saturated[m]: a normalized pixel at or
    above `saturated_level`. The windows lie inside the frame (the caller checks)."""
    n = cells.shape[1]
    b, s, top = np.float32(black), np.float32(span), np.float32(saturated_level)
    count = n * n - (n - 2 * ring_px) ** 2
    k0 = (count - 1) // 2
    win = np.empty((n, n), np.float32)
    ring = np.empty(count, np.float32)
    for m in range(cells.shape[0]):
        y0, x0 = iy0[m], ix0[m]
        sat = False
        for i in range(n):
            for j in range(n):
                v = (np.float32(data[y0 + i, x0 + j]) - b) / s
                win[i, j] = v
                sat |= v >= top
        r = 0
        for i in range(n):
            if ring_px <= i < n - ring_px:
                for j in range(ring_px):
                    ring[r] = win[i, j]
                    ring[r + 1] = win[i, n - 1 - j]
                    r += 2
            else:
                for j in range(n):
                    ring[r] = win[i, j]
                    r += 1
        bg = _select(ring, k0)
        if count % 2 == 0:  # the next value up: the smallest of those after k0
            bg = (bg + ring[k0 + 1:].min()) / np.float32(2.0)
        for i in range(n):
            for j in range(n):
                cells[m, i, j] = win[i, j] - bg
        background[m] = bg
        saturated[m] = sat


@_jit.aot("f8[:, ::1], f8[::1], f8[::1], i8, f8[::1], f8[::1]")
def likelihood_kernel(cv, x, noise, substeps, m1_out, var_out):
    """Per row of cv (L, K): the likelihood exp(-(c - x)^2 / 2 noise^2) of the piecewise-linear curve
    through the K nodes, at `substeps` points per interval (the last node included); its mean and
    variance over the point index (0 .. (K-1) substeps) into m1_out, var_out. NaN where it is nowhere
    finite (a NaN reading or noise). The sums run in point order."""
    L, K = cv.shape
    n = (K - 1) * substeps + 1
    chi = np.empty(n)
    for m in range(L):
        inv = 1.0 / noise[m]
        low = np.inf
        for i in range(n):
            k, t = divmod(i, substeps)
            c = cv[m, k] if k == K - 1 else cv[m, k] + (cv[m, k + 1] - cv[m, k]) * (t / substeps)
            v = (c - x[m]) * inv
            v = v * v
            if not math.isfinite(v):
                v = np.inf
            chi[i] = v
            low = min(low, v)
        w = s1 = s2 = 0.0
        for i in range(n):
            p = math.exp(-0.5 * (chi[i] - low))
            w += p
            s1 += p * i
            s2 += p * i * i
        mean = s1 / w
        m1_out[m] = mean
        var_out[m] = s2 / w - mean * mean


@_jit.aot("f8[::1], i8[:, :, ::1], f8[:, :, ::1], i8[:, ::1], i8, f8[:, ::1]")
def lens_model_kernel(flat, idx, wts, nodes, stride, out):
    """out[l, k] = the model D of lens l at eps node nodes[l, k]: sum over c of wts[l, f, c] *
    flat[idx[l, f, c] + nodes[l, k] * stride] for the +u frame (f = 0) less the same for the -u frame."""
    L, F, C = idx.shape
    for m in range(L):
        for k in range(nodes.shape[1]):
            shift = nodes[m, k] * stride
            plus = minus = 0.0
            for c in range(C):
                plus += flat[idx[m, 0, c] + shift] * wts[m, 0, c]
                minus += flat[idx[m, 1, c] + shift] * wts[m, 1, c]
            out[m, k] = plus - minus
