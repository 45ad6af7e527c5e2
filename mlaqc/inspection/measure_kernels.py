"""Compiled (Numba) kernels of the per-lens focal reading (mlaqc.inspection.measure): every lens' focus
indexes against the radius-error curve, coarse then dense, one pass per lens range (the array version
took 11 ms a frame in temporaries). Kernels release the GIL; callers split lens ranges over the pool."""

from __future__ import annotations

import math

import numpy as np

from mlaqc.compiled import kernel

_jit = kernel(cache=True, nogil=True)


@_jit.aot("f8[:, ::1], f8[:, ::1], i8, f8[:, ::1]")
def coarse_chi2(uv, ug, coarse, out):  # pragma: no cover - compiled
    """out[q, j] = the chi-square of lens q's focus indexes against the curve's coarse point j."""
    for q in range(out.shape[0]):
        for j in range(out.shape[1]):
            out[q, j] = _dense_chi2(uv, ug, q, j * coarse)


@_jit
def _dense_chi2(uv, ug, q, d):  # pragma: no cover - compiled
    """The chi-square of lens q's focus indexes against the curve's dense point d."""
    s = 0.0
    for f in range(uv.shape[1]):
        r = uv[q, f] - ug[d, f]
        s += r * r
    return s


@_jit.aot("f8[:, ::1], f8[::1], f8[:, ::1], f8[:, ::1], i8, f8, f8, f8, f8[::1], f8[::1], f8[::1], b1[::1]")
def focal_scan(chi2, dense_m, ug, uv, coarse, inv_s2, limit, apart, value, sigma, alt,
                resolved):  # pragma: no cover - compiled
    """`_focal`'s scan: two passes over the coarse curve per lens, then the dense refinement (the
    array version took 11 ms a frame in temporaries)."""
    n, g = chi2.shape
    gd = len(dense_m)
    cands = np.empty(g, np.int64)
    for q in range(n):
        c = chi2[q]
        lo, best_pos, best_neg = np.inf, np.inf, np.inf
        for j in range(g):
            m = dense_m[j * coarse]
            lo = min(lo, c[j])
            if m > 0:
                best_pos = min(best_pos, c[j])
            elif m < 0:
                best_neg = min(best_neg, c[j])
        bar = lo + limit / inv_s2
        k = 0
        for j in range(g):  # the local minima within the bar
            if c[j] <= bar and (j == 0 or c[j] <= c[j - 1]) and (j == g - 1 or c[j] <= c[j + 1]):
                cands[k] = j
                k += 1
        pick = cands[0]
        for t in range(1, k):
            if abs(dense_m[cands[t] * coarse]) < abs(dense_m[pick * coarse]):
                pick = cands[t]
        far, alt_j = -1.0, pick
        for t in range(k):
            d = abs(dense_m[cands[t] * coarse] - dense_m[pick * coarse])
            if d > far:
                far, alt_j = d, cands[t]
        alt[q] = dense_m[alt_j * coarse] if far > apart else np.nan
        # refine on the dense curve within one coarse point either side
        d0, d1 = max((pick - 1) * coarse, 0), min((pick + 1) * coarse, gd - 1)
        best_d, best_c = d0, np.inf
        for d in range(d0, d1 + 1):
            cd = _dense_chi2(uv, ug, q, d)
            if cd < best_c:
                best_d, best_c = d, cd
        i = min(max(best_d, 1), gd - 2)
        h = 0.5 * (dense_m[i + 1] - dense_m[i - 1])
        c0 = _dense_chi2(uv, ug, q, i - 1) * inv_s2
        c1 = _dense_chi2(uv, ug, q, i) * inv_s2
        c2 = _dense_chi2(uv, ug, q, i + 1) * inv_s2
        curv = (c0 - 2.0 * c1 + c2) / max(h * h, 1e-30)  # d2 chi2 / dm2
        if curv > 0:
            value[q] = dense_m[i] + min(max(-0.5 * (c2 - c0) / (curv * h), -1.0), 1.0) * h
            sigma[q] = math.sqrt(2.0 / curv)
        else:
            value[q], sigma[q] = dense_m[i], abs(h)
        other = best_neg if value[q] > 0 else best_pos  # the best reading of the other sign
        opposite_alt = far > apart and (dense_m[alt_j * coarse] > 0) != (value[q] > 0)
        resolved[q] = (other - c[pick]) * inv_s2 >= limit and not opposite_alt
