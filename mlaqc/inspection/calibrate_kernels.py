"""Compiled kernels of the calibration's joint disc fit (mlaqc.inspection.calibrate._DiscFit).

One fused pass per lens builds its Gauss-Newton normal equations straight from the frame: for each pixel
of the lens' rim annulus it evaluates the lens' own logistic-edged disc and those of its lattice
neighbours that reach the pixel (the overlapping sub-images), the residual, the noise weight and the
Jacobian, and accumulates them. No frame-sized model, no gathered pixel sets, no scatter: a lens' work
stays in registers and cache. The kernels release the GIL; the caller spreads blocks of lenses over its
thread pool (no Numba threading layer, so concurrent callers are safe and compilation stays short).
"""

from __future__ import annotations

import math

import numpy as np
from mlaqc.compiled import kernel

_jit = kernel(cache=True, nogil=True, error_model="numpy")
_jit_fast = kernel(cache=True, nogil=True, error_model="numpy", fastmath=True)
_inline_fast = kernel(cache=True, nogil=True, error_model="numpy", inline="always", fastmath=True)

N_NORMAL = 5  # amplitude, centre x, centre y, radius, (global edge width)
TAIL = 10.0  # a neighbour's disc is left out beyond this many edge widths outside its rim (< 5e-5 of its level)


# float32 constants: the disc profiles are evaluated in single precision (8 lanes per AVX2 instruction;
# the model needs ~1e-6, the data are noisy at ~1e-2); sums and the normal equations stay in double
_F = np.float32
_ZERO, _ONE, _HALF, _TINY = _F(0.0), _F(1.0), _F(0.5), _F(1e-4)
_LO, _HI, _S = _F(-20.0), _F(20.0), _F(1.0 / 32.0)
_C3, _C4, _C5, _C6, _C7, _C8 = _F(1 / 6), _F(1 / 24), _F(1 / 120), _F(1 / 720), _F(1 / 5040), _F(1 / 40320)


@_inline_fast
def _logistic(t):
    """1 / (1 + exp(t)) in float32, t clipped to +-20 (off by < 3e-9 there): exp(t) = exp(t / 32)^32, the
    inner one a Taylor polynomial (|t / 32| <= 0.625), so loops of it vectorize (no libm call);
    relative error ~1e-6."""
    x = min(max(t, _LO), _HI) * _S
    p = _ONE + x * (_ONE + x * (_HALF + x * (_C3 + x * (_C4 + x * (_C5 + x * (_C6 + x * (_C7 + x * _C8)))))))
    p = p * p
    p = p * p
    p = p * p
    p = p * p
    p = p * p
    return _ONE / (_ONE + p)


@_inline_fast
def _disc(u, v, amp, radius, inv, sx, sy):
    """One lens' model (float32) at offset (u, v) from its centre: plateau (amplitude + slope) times the rim."""
    r = math.sqrt(u * u + v * v) + _TINY
    return (amp + sx * u + sy * v) * _logistic((r - radius) * inv)


@_inline_fast
def _row_span(ck_x, v, inner, outer, w):
    """Columns of the annulus inner..outer about (ck_x, 0) on the row at offset v, inside 0..w-1: the span
    xa..xl left of the hole and xr..xb right of it (a row clear of the hole: xl = xb, xr = xb + 1; no
    pixel: xa > xb)."""
    span2 = outer * outer - v * v
    if span2 < 0.0:
        return 1, 0, 1, 0
    span = math.sqrt(span2)
    xa = max(math.ceil(ck_x - span), 0)
    xb = min(math.floor(ck_x + span), w - 1)
    hole2 = inner * inner - v * v
    if hole2 > 0.0:
        hole = math.sqrt(hole2)
        return xa, min(math.floor(ck_x - hole), xb), max(math.ceil(ck_x + hole), xa), xb
    return xa, xb, xb + 1, xb


@_inline_fast
def _add_span(img, y, v, lo, hi, ck_x, n, n_seg, uu, vv, val, seg, seg_u):
    """Append pixels lo..hi of row y (offset v) to the annulus' pixels and, if any, a span (segment)
    to seg / seg_u; returns the new pixel and span counts."""
    if hi < lo:
        return n, n_seg
    seg[n_seg, 0] = n
    for x in range(lo, hi + 1):
        uu[n], vv[n], val[n] = x - ck_x, v, img[y, x]
        n += 1
    seg[n_seg, 1] = n
    seg_u[n_seg, 0], seg_u[n_seg, 1], seg_u[n_seg, 2] = v, lo - ck_x, hi - ck_x
    return n, n_seg + 1


@_inline_fast
def _span_reached(seg_u, g, ox, oy, lim):
    """Whether a disc reaching sqrt(lim) about (-ox, -oy) reaches any pixel of span g."""
    vj = seg_u[g, 0] + oy
    u0, u1 = seg_u[g, 1] + ox, seg_u[g, 2] + ox
    near = _ZERO if u0 <= _ZERO <= u1 else min(abs(u0), abs(u1))
    return near * near + vj * vj < lim


@_inline_fast
def _gather_halves(img, ck_x, ck_y, inner, outer, y0, rows, uu, vv, val, starts):
    """The annulus' pixels of rows y0 .. y0 + rows - 1 (`disc_normals`' `halves`): first those at
    x <= floor(ck_x) row by row, then those right of it; starts[half, k] is the index of row y0 + k's first
    pixel in each half (starts[half, rows] the half's end). Returns the pixel count."""
    w = img.shape[1]
    mid = math.floor(ck_x)
    n = 0
    for half in range(2):
        for k in range(rows):
            starts[half, k] = n
            y = y0 + k
            v = y - ck_y
            xa, xl, xr, xb = _row_span(ck_x, v, inner, outer, w)
            lo, hi = (xa, min(xl, mid)) if half == 0 else (max(xa if xl >= xb else xr, mid + 1), xb)
            for x in range(lo, hi + 1):
                uu[n], vv[n], val[n] = x - ck_x, v, img[y, x]
                n += 1
        starts[half, rows] = n
    return n


@_inline_fast
def _add_disc(uu, vv, mod, ox, oy, lim, a_j, r_j, inv_j, sx_j, sy_j):
    """mod += a neighbour's disc (offset (ox, oy), reaching sqrt(lim)) at pixels (uu, vv): one loop from
    index 0 over views, so that it runs on the vector units."""
    for p in range(mod.size):
        uj = uu[p] + ox
        vj = vv[p] + oy
        c = _disc(uj, vj, a_j, r_j, inv_j, sx_j, sy_j)
        mod[p] += c if uj * uj + vj * vj < lim else _ZERO


@_jit_fast.aot("f4[:, ::1], i8[::1], f8[::1], f8[::1], f8[::1], f8[::1], f8[::1], f8[::1], f8[::1], "
               "i8[:, ::1], b1[::1], b1[::1], f8, b1, b1, f8, b1, f8[:, :, ::1], f8[:, ::1], f8[::1], i8[::1]")
def disc_normals(img, lenses, cx, cy, amp, radius, inv_edge, slope_x, slope_y, neighbours, coupled,
                 wide, half_band, weighted, fit_edge, floor, halves, normal, rhs, rss, npix):
    """Normal equations of lenses `lenses` against the frame `img` (float32, (h, w)).

    Per lens k, over the pixels with |r - radius_k| < half_band about its current centre (inside the
    frame), with the taper weight clip(half_band - |r - radius_k|, 0, 1):
    model = own disc + the discs of neighbours[k] (lattice neighbours, -1 = none) that reach the pixel;
    weights (if `weighted`) amp / max(model, floor * amp), or 1 for `coupled` lenses;
    Jacobian columns: amplitude, centre x, centre y, radius (+ the edge width if `fit_edge`, zero for
    `wide` lenses). Slopes are per pixel of offset (the caller's slope per radius / radius).
    Writes normal[t] (5, 5), rhs[t] (5,), and rss[t], npix[t]: the unweighted residual sum of squares over
    the npix pixels of the window (a fit-quality figure).
    Per lens: gather the annulus' pixels (row spans), evaluate its own disc, add the neighbours' on the
    spans they reach, then one pass accumulates residuals, weights and Jacobian products.
    `halves`: the pixels are gathered as the left half of the annulus (x <= the centre's column), row by
    row, then the right half, so that the pixels a neighbour's disc can reach (the rows within its reach,
    on its side or both) are one or two index ranges, each one loop on the vector units (a span alone is
    a few pixels, and its loop runs scalar): the same model, summed in another order (last bits differ,
    centres by ~1e-6 px), in 40 % less time on the Table 1 hex frame. Hex sets it: its six side
    neighbours make their discs most of the work; square keeps the span order (its results unchanged)."""
    h, w = img.shape
    n_nb = neighbours.shape[1]
    nb = np.empty(n_nb, np.int64)
    nb_reach2 = np.empty(n_nb)
    side = 2 * math.ceil(np.max(radius) + half_band) + 3
    cap = side * side
    uu, vv, val = np.empty(cap, np.float32), np.empty(cap, np.float32), np.empty(cap, np.float32)
    ee, mod = np.empty(cap, np.float32), np.empty(cap, np.float32)  # the lens' own rim profile, the model of all discs
    seg = np.empty((4 * side, 2), np.int64)  # pixel index ranges of the row spans
    seg_u = np.empty((4 * side, 3), np.float32)  # their v, first u, last u
    starts = np.empty((2, side + 1), np.int64)  # `halves`: index of each row's first pixel in each half
    for t in range(lenses.size):
        k = lenses[t]
        ck_x, ck_y, a_k, r_k, inv = cx[k], cy[k], amp[k], radius[k], inv_edge[k]
        sx, sy = slope_x[k], slope_y[k]
        outer = r_k + half_band
        inner = max(r_k - half_band, 0.0)
        # neighbours whose disc can reach this lens' annulus
        count = 0
        for q in range(n_nb):
            j = neighbours[k, q]
            if j < 0:
                continue
            reach = outer + radius[j] + TAIL / inv_edge[j]
            dxj, dyj = cx[j] - ck_x, cy[j] - ck_y
            if dxj * dxj + dyj * dyj < reach * reach:
                nb[count] = j
                nb_reach2[count] = (radius[j] + TAIL / inv_edge[j]) ** 2
                count += 1
        # the annulus' pixels inside the frame: per row, the spans left and right of the plateau
        # (`halves`: the rows' pixels left of the centre column, then those right of it)
        n = 0
        n_seg = 0
        y0 = max(math.ceil(ck_y - outer), 0)
        y1 = min(math.floor(ck_y + outer), h - 1)
        rows = max(y1 - y0 + 1, 0)
        if halves:
            n = _gather_halves(img, ck_x, ck_y, inner, outer, y0, rows, uu, vv, val, starts)
        else:
            for y in range(y0, y1 + 1):
                v = y - ck_y
                xa, xl, xr, xb = _row_span(ck_x, v, inner, outer, w)
                n, n_seg = _add_span(img, y, v, xa, xl, ck_x, n, n_seg, uu, vv, val, seg, seg_u)
                n, n_seg = _add_span(img, y, v, xr, xb, ck_x, n, n_seg, uu, vv, val, seg, seg_u)
        # own disc
        r32, inv32, a32, sx32, sy32 = _F(r_k), _F(inv), _F(a_k), _F(sx), _F(sy)
        for p in range(n):
            u = uu[p]
            v = vv[p]
            e = _logistic((math.sqrt(u * u + v * v) + _TINY - r32) * inv32)
            ee[p] = e
            mod[p] = (a32 + sx32 * u + sy32 * v) * e
        # neighbours' discs, on the spans they reach (`halves`: on the rows they reach, in their half or both)
        for q in range(count):
            j = nb[q]
            ox, oy, lim = _F(ck_x - cx[j]), _F(ck_y - cy[j]), _F(nb_reach2[q])
            a_j, r_j, inv_j, sx_j, sy_j = _F(amp[j]), _F(radius[j]), _F(inv_edge[j]), _F(slope_x[j]), _F(slope_y[j])
            if halves:
                # rows within its reach (a pixel to spare: the per-pixel test decides), clipped to the annulus'
                reach = math.sqrt(nb_reach2[q]) + 1.0
                k0 = min(max(math.floor(cy[j] - reach) - y0, 0), rows)
                k1 = min(max(math.ceil(cy[j] + reach) - y0 + 1, k0), rows)
                for half in range(2):
                    # the left half lies at x <= ck_x, the right one at x > ck_x
                    if (cx[j] - reach < ck_x) if half == 0 else (cx[j] + reach > ck_x):
                        p0, p1 = starts[half, k0], starts[half, k1]
                        _add_disc(uu[p0:p1], vv[p0:p1], mod[p0:p1], ox, oy, lim, a_j, r_j, inv_j, sx_j, sy_j)
                continue
            for g in range(n_seg):
                if not _span_reached(seg_u, g, ox, oy, lim):
                    continue
                vj = seg_u[g, 0] + oy
                for p in range(seg[g, 0], seg[g, 1]):
                    uj = uu[p] + ox
                    c = _disc(uj, vj, a_j, r_j, inv_j, sx_j, sy_j)
                    mod[p] += c if uj * uj + vj * vj < lim else _ZERO
        # residuals, weights, Jacobian
        a_w = max(a_k, 1e-6)
        floor_a = floor * a_w
        reweight = weighted and not coupled[k]
        edge_gain = inv * (0.0 if wide[k] or not fit_edge else 1.0)
        ss = 0.0
        cnt = 0.0
        n00 = n01 = n02 = n03 = n04 = n11 = n12 = n13 = n14 = 0.0
        n22 = n23 = n24 = n33 = n34 = n44 = 0.0
        b0 = b1 = b2 = b3 = b4 = 0.0
        for p in range(n):
            u = uu[p]
            v = vv[p]
            e = ee[p]
            mp = mod[p]
            r = math.sqrt(u * u + v * v) + 1e-4
            d = r - r_k
            wp = min(half_band - abs(d), 1.0)
            inside = 1.0 if wp > 0.0 else 0.0
            wp = max(wp, 0.0)
            rp = val[p] - mp
            ss += inside * rp * rp
            cnt += inside
            if reweight:
                wp *= a_w / max(mp, floor_a)
            ag = e * (1.0 - e) * (a_k + sx * u + sy * v) * inv
            ir = ag / r
            j1 = ir * u - e * sx
            j2 = ir * v - e * sy
            j4 = d * ag * edge_gain
            we, wx, wy, wr, wd = wp * e, wp * j1, wp * j2, wp * ag, wp * j4
            n00 += we * e
            n01 += we * j1
            n02 += we * j2
            n03 += we * ag
            n04 += we * j4
            n11 += wx * j1
            n12 += wx * j2
            n13 += wx * ag
            n14 += wx * j4
            n22 += wy * j2
            n23 += wy * ag
            n24 += wy * j4
            n33 += wr * ag
            n34 += wr * j4
            n44 += wd * j4
            b0 += we * rp
            b1 += wx * rp
            b2 += wy * rp
            b3 += wr * rp
            b4 += wd * rp
        m = normal[t]
        m[0, 0], m[0, 1], m[0, 2], m[0, 3], m[0, 4] = n00, n01, n02, n03, n04
        m[1, 1], m[1, 2], m[1, 3], m[1, 4] = n11, n12, n13, n14
        m[2, 2], m[2, 3], m[2, 4] = n22, n23, n24
        m[3, 3], m[3, 4] = n33, n34
        m[4, 4] = n44
        for i in range(N_NORMAL):
            for jj in range(i):
                m[i, jj] = m[jj, i]
        rhs[t, 0], rhs[t, 1], rhs[t, 2], rhs[t, 3], rhs[t, 4] = b0, b1, b2, b3, b4
        npix[t] = int(cnt)
        rss[t] = ss


@_jit_fast.aot("f4[:, ::1], i8[::1], f8[::1], f8[::1], f8[::1], f8[::1], f8[::1], f8[::1], f8, f8[:, :, ::1], f8[:, ::1]")
def add_plateau(img, lenses, cx, cy, amp, radius, slope_x, slope_y, inset, normal, rhs):
    """Adds to lens lenses[t]'s amplitude normal equation (normal[t, 0, 0], rhs[t, 0]) the pixels of its
    plateau, within radius - inset of its centre (inside the frame): model amp + slope . offset, Jacobian
    1, weight 1 (the plateau is the level a weighted fit weighs as one). They carry the amplitude only.
    Row by row: the span of a row inside the circle is one contiguous sum (a vector loop)."""
    h, w = img.shape
    for t in range(lenses.size):
        k = lenses[t]
        r_in = radius[k] - inset
        if r_in < 1.0:
            continue
        cnt = 0.0
        res = 0.0
        for y in range(max(math.ceil(cy[k] - r_in), 0), min(math.floor(cy[k] + r_in), h - 1) + 1):
            v = y - cy[k]
            half = math.sqrt(max(r_in * r_in - v * v, 0.0))
            xa, xb = max(math.ceil(cx[k] - half), 0), min(math.floor(cx[k] + half), w - 1)
            if xb < xa:
                continue
            s = 0.0
            for x in range(xa, xb + 1):
                s += img[y, x]
            n = xb - xa + 1
            # the model summed over the span: amp and the slopes at the span's mean offset
            res += s - n * (amp[k] + slope_x[k] * (0.5 * (xa + xb) - cx[k]) + slope_y[k] * v)
            cnt += n
        normal[t, 0, 0] += cnt
        rhs[t, 0] += res


@_jit.aot("f4[:, ::1], f8[::1], f8[::1], i8")
def plateau_mean(img, cx, cy, half):
    """Mean level of the pixels within `half` px of each rounded centre (0 where none is in the frame)."""
    h, w = img.shape
    out = np.zeros(cx.size)
    lim = half * half
    for k in range(cx.size):
        ix, iy = round(cx[k]), round(cy[k])
        s = 0.0
        c = 0
        for dy in range(-half, half + 1):
            y = iy + dy
            if y < 0 or y >= h:
                continue
            for dx in range(-half, half + 1):
                x = ix + dx
                if x < 0 or x >= w or dx * dx + dy * dy > lim:
                    continue
                s += img[y, x]
                c += 1
        out[k] = s / max(c, 1)
    return out


@_jit.aot("i8[::1], f8[:, :, ::1], f8[:, ::1], b1[::1], f8[::1], f8[::1], f8[::1], f8[::1], "
          "f8[:, ::1], f8[::1], f8, f8")
def apply_steps(idx, normal, rhs, active, amp, cx, cy, radius, prev_step, last_step, r_lo, r_hi):
    """One Gauss-Newton step per lens idx[t] from its normal equations (normal[t][:4, :4], rhs[t][:4]):
    a 1e-6 relative ridge, Cholesky solve (inactive lenses: amplitude only), centre and radius steps
    clipped to 1 px and halved where they reverse the lens' last step (oscillation), radius kept in
    [r_lo, r_hi]. Updates amp, cx, cy, radius, prev_step (n, 4) and last_step (|centre step|) in place."""
    m = np.empty((4, 4))
    b = np.empty(4)
    for t in range(idx.size):
        k = idx[t]
        npar = 4 if active[k] else 1
        for i in range(npar):
            for j in range(npar):
                m[i, j] = normal[t, i, j]
            m[i, i] += 1e-6 * (1.0 + normal[t, i, i])
            b[i] = rhs[t, i]
        ok = True
        for j in range(npar):  # Cholesky, lower triangle in place
            d = m[j, j]
            for q in range(j):
                d -= m[j, q] * m[j, q]
            if d <= 0.0:
                ok = False
                break
            d = math.sqrt(d)
            m[j, j] = d
            for i in range(j + 1, npar):
                s = m[i, j]
                for q in range(j):
                    s -= m[i, q] * m[j, q]
                m[i, j] = s / d
        step = np.zeros(4)
        if ok:
            for i in range(npar):  # forward
                s = b[i]
                for q in range(i):
                    s -= m[i, q] * step[q]
                step[i] = s / m[i, i]
            for i in range(npar - 1, -1, -1):  # backward
                s = step[i]
                for q in range(i + 1, npar):
                    s -= m[q, i] * step[q]
                step[i] = s / m[i, i]
        for i in range(1, 4):
            step[i] = min(max(step[i], -1.0), 1.0)
        if step[1] * prev_step[k, 1] + step[2] * prev_step[k, 2] < 0.0:
            for i in range(1, 4):
                step[i] *= 0.5
        amp[k] += step[0]
        cx[k] += step[1]
        cy[k] += step[2]
        radius[k] = min(max(radius[k] + step[3], r_lo), r_hi)
        for i in range(4):
            prev_step[k, i] = step[i]
        last_step[k] = math.hypot(step[1], step[2])


@_jit_fast.aot("f4[:, ::1], f4[:, ::1]")
def row_dots(a, m):
    """a (h, w) float32 times m.T, m (k, w) float32: (h, k) float64 (each row sum in float32). A narrow
    product that multi-threaded BLAS handles poorly on a busy machine; this stays on one core."""
    h, w = a.shape
    out = np.zeros((h, m.shape[0]))
    for y in range(h):
        for j in range(m.shape[0]):
            s = _ZERO
            for x in range(w):
                s += a[y, x] * m[j, x]
            out[y, j] = s
    return out


@_jit.aot("f8[::1], f8[::1], f8[::1], f8[::1], f8[:, ::1], f8, f8, f8, f8, i8")
def grid_normal_equations(u, v, x, y, hom, k, cx, cy, scale, n_par):
    """Gauss-Newton normal equations of the global grid model (mlaqc.inspection.calibrate._model_xy: projective map
    hom of the lattice (u, v), then the radial term k about (cx, cy) / scale) against centres (x, y).
    Parameters: hom[0, :], hom[1, :], hom[2, :2], k (the first n_par of them). Returns J^T J (9, 9),
    J^T r (9,) and r^T r, in one pass (no Jacobian array)."""
    jtj = np.zeros((9, 9))
    jtr = np.zeros(9)
    cost = 0.0
    jx = np.zeros(9)
    jy = np.zeros(9)
    s2 = 1.0 / (scale * scale)
    for i in range(u.size):
        inv_w = 1.0 / (hom[2, 0] * u[i] + hom[2, 1] * v[i] + 1.0)
        xp = (hom[0, 0] * u[i] + hom[0, 1] * v[i] + hom[0, 2]) * inv_w
        yp = (hom[1, 0] * u[i] + hom[1, 1] * v[i] + hom[1, 2]) * inv_w
        dx, dy = xp - cx, yp - cy
        rho2 = (dx * dx + dy * dy) * s2
        f = 1.0 + k * rho2
        g = 2.0 * k * s2
        xx, xy, yy = f + g * dx * dx, g * dx * dy, f + g * dy * dy  # d(X, Y) / d(x', y')
        rx, ry = cx + dx * f - x[i], cy + dy * f - y[i]
        h0, h1, h2 = u[i] * inv_w, v[i] * inv_w, inv_w  # d x' / d hom[0, :], d y' / d hom[1, :]
        ax, ay = -(xx * xp + xy * yp), -(xy * xp + yy * yp)  # times h0, h1: d / d hom[2, :2]
        jx[0], jx[1], jx[2], jx[3], jx[4], jx[5], jx[6], jx[7], jx[8] = (
            xx * h0, xx * h1, xx * h2, xy * h0, xy * h1, xy * h2, ax * h0, ax * h1, dx * rho2)
        jy[0], jy[1], jy[2], jy[3], jy[4], jy[5], jy[6], jy[7], jy[8] = (
            xy * h0, xy * h1, xy * h2, yy * h0, yy * h1, yy * h2, ay * h0, ay * h1, dy * rho2)
        for a in range(n_par):
            jtr[a] += jx[a] * rx + jy[a] * ry
            for b in range(a, n_par):
                jtj[a, b] += jx[a] * jx[b] + jy[a] * jy[b]
        cost += rx * rx + ry * ry
    for a in range(n_par):
        for b in range(a):
            jtj[a, b] = jtj[b, a]
    return jtj, jtr, cost
