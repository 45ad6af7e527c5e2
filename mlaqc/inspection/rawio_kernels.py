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
from mlaqc.compiled import kernel

_jit = kernel(cache=True, nogil=True, error_model="numpy")


@_jit
def _mirror(i, n):
    """Mirror index i into 0..n-1 ('mirror' mode: -1 -> 1, n -> n - 2); n >= 2."""
    if i < 0:
        return -i
    if i >= n:
        return 2 * (n - 1) - i
    return i


@_jit.aot("f4[:, ::1], i8, i8, i8, i8, f4[:, ::1]")
def ring_residual_sample(x, r0, c0, step, every, sample):
    """sample[a, b] = float32(x - ring mean) at plane pixel (every*a, every*b), in the old filters' float32
    arithmetic (a 1-in-every² sample for the plane's robust noise)."""
    height, width = x.shape
    ph = (height - r0 + step - 1) // step
    pw = (width - c0 + step - 1) // step
    for a in range(sample.shape[0]):
        pi = every * a
        above = x[r0 + step * _mirror(pi - 1, ph)]
        row = x[r0 + step * pi]
        below = x[r0 + step * _mirror(pi + 1, ph)]
        for b in range(sample.shape[1]):
            pj = every * b
            xm = c0 + step * _mirror(pj - 1, pw)
            x0 = c0 + step * pj
            xp = c0 + step * _mirror(pj + 1, pw)
            s1 = (np.float64(above[xm]) + np.float64(above[x0]) + np.float64(above[xp]) + np.float64(row[xm])
                  + np.float64(row[xp]) + np.float64(below[xm]) + np.float64(below[x0]) + np.float64(below[xp]))
            sample[a, b] = row[x0] - np.float32(s1) / np.float32(8.0)


@_jit.aot("f4[:, ::1], i8, i8, i8, f8, f8, i8, i8, b1[:, ::1], f4[:, ::1], i8[::1]")
def hot_pixel_rows(x, r0, c0, step, noise, nsigma, row_start, row_stop, mask, med, row_bad):
    """Outliers of plane rows [row_start, row_stop): mask[y, x] = True and med[y, x] = the 3 x 3
    same-channel median (centre included) where a pixel stands more than nsigma * max(noise, structure)
    above the brightest or below the darkest of its 8 neighbours; structure = rms residual of the ring
    about its least-squares plane (5 dof). row_bad[pi] counts the plane row's outliers.

    A first branch-free sweep over the row keeps only pixels outside their neighbours' range by more than
    nsigma * noise (no pixel inside it can be an outlier, since structure >= 0); the full test runs on those."""
    height, width = x.shape
    ph = (height - r0 + step - 1) // step
    pw = (width - c0 + step - 1) // step
    ring = np.empty(8)
    nine = np.empty(9)
    cand = np.empty(pw, np.bool_)
    t = nsigma * noise
    for pi in range(row_start, row_stop):
        ym = r0 + step * _mirror(pi - 1, ph)
        y0 = r0 + step * pi
        yp = r0 + step * _mirror(pi + 1, ph)
        above = x[ym]
        row = x[y0]
        below = x[yp]
        for pj in range(1, pw - 1):
            xm = c0 + step * (pj - 1)
            x0 = xm + step
            xp = x0 + step
            hi = max(max(max(above[xm], above[x0]), max(above[xp], row[xm])),
                     max(max(row[xp], below[xm]), max(below[x0], below[xp])))
            lo = min(min(min(above[xm], above[x0]), min(above[xp], row[xm])),
                     min(min(row[xp], below[xm]), min(below[x0], below[xp])))
            centre = row[x0]
            cand[pj] = (centre - hi > t) | (lo - centre > t)
        cand[0] = True
        cand[pw - 1] = True  # the mirrored edge columns go through the full test
        nbad = 0
        for pj in range(pw):
            if not cand[pj]:
                continue
            xm = c0 + step * _mirror(pj - 1, pw)
            x0 = c0 + step * pj
            xp = c0 + step * _mirror(pj + 1, pw)
            ring[0] = above[xm]
            ring[1] = above[x0]
            ring[2] = above[xp]
            ring[3] = row[xm]
            ring[4] = row[xp]
            ring[5] = below[xm]
            ring[6] = below[x0]
            ring[7] = below[xp]
            centre = np.float64(row[x0])
            s1 = 0.0
            lo = np.inf
            hi = -np.inf
            for q in range(8):
                s1 += ring[q]
                lo = min(lo, ring[q])
                hi = max(hi, ring[q])
            if centre - hi <= t and lo - centre <= t:
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
