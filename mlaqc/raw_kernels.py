"""Compiled (Numba) kernels of raw-frame preparation: hot-pixel detection and replacement.

Why: the filter formulation (six 3 x 3 ndimage filters per CFA plane, then a gather for the median)
spends 0.2 s on a 2048 x 2048 frame; one pass that reads each pixel's 8 same-channel neighbours once
does the same work in a few milliseconds. A plane is addressed inside the full frame as rows r0::step,
columns c0::step, with mirrored borders (ndimage 'mirror': the pixel is never its own neighbour).
Kernels release the GIL and take a row range, so callers split planes over a thread pool.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_jit = njit(cache=True, nogil=True, error_model="numpy")


@_jit
def _mirror(i, n):
    """Mirror index i into 0..n-1 ('mirror' mode: -1 -> 1, n -> n - 2); n >= 2."""
    if i < 0:
        return -i
    if i >= n:
        return 2 * (n - 1) - i
    return i


@_jit
def ring_residual_sample(x, r0, c0, step, sample):
    """sample[a, b] = float32(x - ring mean) at plane pixel (3a, 3b), in the old filters' float32
    arithmetic (a 1-in-9 sample for the plane's robust noise); returns the plane's (min, max)."""
    height, width = x.shape
    ph = (height - r0 + step - 1) // step
    pw = (width - c0 + step - 1) // step
    for a in range(sample.shape[0]):
        pi = 3 * a
        for b in range(sample.shape[1]):
            pj = 3 * b
            s1 = 0.0
            for di in range(-1, 2):
                yi = r0 + step * _mirror(pi + di, ph)
                for dj in range(-1, 2):
                    if di != 0 or dj != 0:
                        s1 += np.float64(x[yi, c0 + step * _mirror(pj + dj, pw)])
            sample[a, b] = x[r0 + step * pi, c0 + step * pj] - np.float32(s1) / np.float32(8.0)
    lo = np.inf
    hi = -np.inf
    for pi in range(ph):
        for pj in range(pw):
            val = np.float64(x[r0 + step * pi, c0 + step * pj])
            lo = min(lo, val)
            hi = max(hi, val)
    return lo, hi


@_jit
def hot_pixel_rows(x, r0, c0, step, noise, nsigma, row_start, row_stop, mask, med, row_bad):
    """Outliers of plane rows [row_start, row_stop): mask[y, x] = True and med[y, x] = the 3 x 3
    same-channel median (centre included) where a pixel stands more than nsigma * max(noise, structure)
    above the brightest or below the darkest of its 8 neighbours; structure = rms residual of the ring
    about its least-squares plane (5 dof). row_bad[pi] counts the plane row's outliers."""
    height, width = x.shape
    ph = (height - r0 + step - 1) // step
    pw = (width - c0 + step - 1) // step
    ring = np.empty(8)
    nine = np.empty(9)
    for pi in range(row_start, row_stop):
        ym = r0 + step * _mirror(pi - 1, ph)
        y0 = r0 + step * pi
        yp = r0 + step * _mirror(pi + 1, ph)
        nbad = 0
        for pj in range(pw):
            xm = c0 + step * _mirror(pj - 1, pw)
            x0 = c0 + step * pj
            xp = c0 + step * _mirror(pj + 1, pw)
            ring[0] = x[ym, xm]
            ring[1] = x[ym, x0]
            ring[2] = x[ym, xp]
            ring[3] = x[y0, xm]
            ring[4] = x[y0, xp]
            ring[5] = x[yp, xm]
            ring[6] = x[yp, x0]
            ring[7] = x[yp, xp]
            centre = np.float64(x[y0, x0])
            s1 = 0.0
            lo = np.inf
            hi = -np.inf
            for q in range(8):
                s1 += ring[q]
                lo = min(lo, ring[q])
                hi = max(hi, ring[q])
            # cheap exit: inside the neighbours' range by more than nsigma * noise is never an outlier
            if centre - hi <= nsigma * noise and lo - centre <= nsigma * noise:
                continue
            mean = s1 / 8.0
            ss = 0.0
            for q in range(8):
                ss += (ring[q] - mean) * (ring[q] - mean)
            gx = (ring[2] + ring[4] + ring[7] - ring[0] - ring[3] - ring[5]) / 6.0
            gy = (ring[5] + ring[6] + ring[7] - ring[0] - ring[1] - ring[2]) / 6.0
            rss = ss - 6.0 * (gx * gx + gy * gy)
            structure = math.sqrt(max(rss, 0.0) / 5.0)
            limit = nsigma * max(noise, structure)
            if centre - hi > limit or lo - centre > limit:
                for q in range(4):
                    nine[q] = ring[q]
                nine[4] = centre
                for q in range(4, 8):
                    nine[q + 1] = ring[q]
                nine.sort()
                mask[y0, x0] = True
                med[y0, x0] = nine[4]
                nbad += 1
        row_bad[pi] = nbad
