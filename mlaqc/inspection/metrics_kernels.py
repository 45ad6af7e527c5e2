"""Compiled (Numba) kernels of the inspection hot path: window cutting, all per-lens indexes in one pass
over the sub-image stack, and the local median baselines of identification.

Why: the NumPy formulation builds a dozen (N_H, N_W, h, w) temporaries per index (0.3 s for 10,404
lenses); here every lens is handled start to finish while its 21 x 21 window sits in L1 cache. Kernels
release the GIL and work on a [start, stop) range of lenses, so callers split the work over a thread
pool (no Numba threading layer: safe to call from several threads at once). Sums are accumulated in
float64, the reference is interpolated in float64; the entropy bins follow the NumPy code's float32 rules.
"""

from __future__ import annotations

import math

import numpy as np
from mlaqc.compiled import kernel

_jit = kernel(cache=True, nogil=True, error_model="numpy")
# reassociation lets LLVM vectorize the window sums (their order changes at the 1e-16 level); no
# finite-math assumptions: NaN marks pixels outside the frame and lost lenses
_jit_fast = kernel(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})

# Column order of the (N, N_INDEX) array `lens_indexes` fills (the order of results.METRICS).
# Rings of the residual profile: outer radii in units of half the window (a 21-px window: 6, 8, 9, 10, 11 and
# 12 px; the window's corners beyond are the neighbours' and are left out). A radius or thickness error
# defocuses the lens and moves light across the sub-image's rim; the rings just inside and outside it say
# where and how much (mlaqc.inspection.identify's focus test).
RING_EDGES = np.array([6.0, 8.0, 9.0, 10.0, 11.0, 12.0]) / 10.5
N_RING = len(RING_EDGES)
INDEX_NAMES = ("flux", "mean_gray", "uniformity", "entropy", "sharpness", "offset_x_px", "offset_y_px", "offset_um",
               "size_px", "ellipticity", "blur", "asym_x", "asym_y", "psnr_db", "ssim", "ncc",
               *(f"ring{k}" for k in range(N_RING)))
N_INDEX = len(INDEX_NAMES)
_RING0 = INDEX_NAMES.index("ring0")
ENTROPY_BINS = 32
# The outermost TAPER_PX of a window fade out of every index computed against the reference (`_taper`).
TAPER_PX = 1.0


@_jit.aot("f4[:, ::1], i8[::1], i8[::1], i8, i8, f4[:, :, ::1], b1[:, :, ::1]")
def cut_windows_kernel(img, ox, oy, h, w, data, valid):
    """data[k] = img[oy[k]:oy[k]+h, ox[k]:ox[k]+w] as float32, NaN (and valid False) outside the frame."""
    height, width = img.shape
    for k in range(ox.shape[0]):
        x0, y0 = ox[k], oy[k]
        for i in range(h):
            y = y0 + i
            inside_y = 0 <= y < height
            for j in range(w):
                x = x0 + j
                if inside_y and 0 <= x < width:
                    data[k, i, j] = np.float32(img[y, x])
                    valid[k, i, j] = True
                else:
                    data[k, i, j] = np.float32(np.nan)
                    valid[k, i, j] = False


# fast like its first caller, lens_indexes: Numba gives a helper the fastmath of the kernel whose compile
# first reaches it, so without this its code (and the references' last bits) hung on which kernel ran first
@_jit_fast
def _gather_at(stack, size, c, os_, phases, pad, fx, fy, h, w, ntab, dst):
    """dst[k, i*w + j] (float64; rows of dst at least h*w + 8 long for the fast blend) = template table k
    at the continuous template position (c + i*os_ - fy, c + j*os_ - fx), bilinear between its samples
    (1/os_ px apart): the reference of a lens centred at (fx, fy) / os_ in window pixels, a continuous
    function of that centre. Reads four phase-table blocks (the corners of the sample cell) at once;
    falls back to the full `stack`, element by element, where a wild shift leaves the phase tables
    (indices clipped into the zero border)."""
    fx0 = math.floor(fx)
    fy0 = math.floor(fy)
    tx = fx - fx0
    ty = fy - fy0
    qx0 = np.int64(fx0)
    qy0 = np.int64(fy0)
    # (the blend in float64: in float32 the compiled kernel and its standalone use could round a value
    # differently, depending on whether the compiler fuses the multiply-adds where it inlines this)
    w00 = (1.0 - tx) * (1.0 - ty)  # corner (qx0, qy0)
    w01 = tx * (1.0 - ty)  # (qx0 + 1, qy0)
    w10 = (1.0 - tx) * ty  # (qx0, qy0 + 1)
    w11 = tx * ty  # (qx0 + 1, qy0 + 1)
    ua = c - qy0
    ub = ua - 1
    va = c - qx0
    vb = va - 1
    pra = ua % os_
    prb = ub % os_
    pca = va % os_
    pcb = vb % os_
    ra = pad + (ua - pra) // os_
    rb = pad + (ub - prb) // os_
    ca = pad + (va - pca) // os_
    cb = pad + (vb - pcb) // os_
    n_r = phases.shape[3]
    n_c = phases.shape[4]
    # rows are blended in whole vectors, a row's tail included, when dst has room for the last row's
    # overrun (the next row overwrites the rest): no scalar remainder loop, a third faster at w = 21
    wv = (w + 7) // 8 * 8 if dst.shape[1] >= h * w + 8 else w
    if (0 <= min(ra, rb) and max(ra, rb) + h <= n_r and 0 <= min(ca, cb) and max(ca, cb) + wv <= n_c):
        # flat offsets, unsigned: Numba then drops its negative-index handling and the row loop vectorizes
        # (7x faster than signed offsets or a view per row)
        flat = phases.reshape(-1)
        un_c = np.uint64(n_c)
        uw = np.uint64(w)
        for k in range(ntab):
            base = k * os_ * os_
            o00 = np.uint64(((base + pra * os_ + pca) * n_r + ra) * n_c + ca)
            o01 = np.uint64(((base + pra * os_ + pcb) * n_r + ra) * n_c + cb)
            o10 = np.uint64(((base + prb * os_ + pca) * n_r + rb) * n_c + ca)
            o11 = np.uint64(((base + prb * os_ + pcb) * n_r + rb) * n_c + cb)
            row = dst[k]
            d0 = np.uint64(0)
            for _i in range(h):
                for jj in range(wv):
                    j = np.uint64(jj)
                    row[d0 + j] = ((w00 * flat[o00 + j] + w01 * flat[o01 + j])
                                   + (w10 * flat[o10 + j] + w11 * flat[o11 + j]))
                o00 += un_c
                o01 += un_c
                o10 += un_c
                o11 += un_c
                d0 += uw
    else:
        for k in range(ntab):
            for i in range(h):
                r0 = min(max(ua + i * os_, 0), size - 1) * size
                r1 = min(max(ub + i * os_, 0), size - 1) * size
                for j in range(w):
                    j0 = min(max(va + j * os_, 0), size - 1)
                    j1 = min(max(vb + j * os_, 0), size - 1)
                    dst[k, i * w + j] = ((w00 * stack[k, r0 + j0] + w01 * stack[k, r0 + j1])
                                         + (w10 * stack[k, r1 + j0] + w11 * stack[k, r1 + j1]))


@_jit.aot("f4[:, ::1], i8, i8, i8, f4[:, :, :, :, ::1], i8, f8[::1], f8[::1], i8, i8, i8, f4[:, :, ::1]",
          "f4[:, ::1], i8, i8, i8, f4[:, :, :, :, ::1], i8, f8[::1], f8[::1], i8, i8, i8, f8[:, :, ::1]")
def gather_tables_at(stack, size, c, os_, phases, pad, cx, cy, h, w, ntab, out):
    """out[k, t] (float64, (N, ntab, h*w)) = the first `ntab` template tables for a lens centred at
    (cx[k], cy[k]) window px, continuous in that centre (`_gather_at`): what `lens_indexes` registers
    against, for the report's reference images and the tests."""
    npx = h * w
    tab = np.empty((ntab, npx + 8))
    for k in range(cx.shape[0]):
        _gather_at(stack, size, c, os_, phases, pad, cx[k] * os_, cy[k] * os_, h, w, ntab, tab)
        out[k] = tab[:, :npx]


@kernel(cache=True, nogil=True, inline="always")
def _taper(u, half):
    """Weight of a window pixel at u px from the lens' grid centre along one axis, in a window reaching
    `half` px either side of that centre: 1 inside, falling to 0 over the outermost TAPER_PX as a raised
    cosine. A window is cut on the pixel nearest the grid centre, so when the centre crosses half a pixel
    one pixel column (row) leaves the window at |u| = half and another enters at the other side: with
    weight 0 there, no index jumps with the sub-pixel phase, and with a zero slope there none bends either
    (a linear ramp left a kink that the smooth phase model of identification cannot follow)."""
    t = (half - abs(u)) / TAPER_PX
    if t >= 1.0:
        return 1.0
    if t <= 0.0:
        return 0.0
    return 0.5 - 0.5 * math.cos(math.pi * t)


@_jit_fast.aot("f4[:, :, ::1], f8[::1], f8[::1], f4[:, ::1], i8, i8, i8, f4[:, :, :, :, ::1], i8, f8, i8, i8, i8, "
               "f8[:, ::1]")
def lens_indexes(data, cx, cy, stack, size, c, os_, phases, pad, um_per_px, steps, start, stop, out):
    """Every index of lenses [start, stop) of `data` (N, h, w) float32 (NaN = outside the frame) into
    out[k, :] (columns INDEX_NAMES; 'flux' raw, normalized over all lenses by the caller).

    Same definitions as the NumPy formulation in tests/test_metrics_kernels.py: Lucas-Kanade registration
    (`steps` Gauss-Newton steps from the grid centre) on the reference interpolated at the current
    estimate (`_gather_at`: continuous in it, so the fixed point the steps converge to is a continuous
    function of the lens' position, whatever the sub-image's profile), then flux, mean, disc uniformity,
    32-bin entropy, gradient-energy sharpness, offsets, half-max second moments, blur and tilt projections
    of the residual, PSNR/SSIM/NCC of the flux-scaled sub-image and the residual's ring profile. Every
    index but the disc uniformity and the entropy (discrete by nature, and only reported) weights the
    window's pixels by `_taper` about the grid centre, so pixels that enter or leave the window as the
    centre crosses half a pixel count for nothing: no index jumps with the sub-pixel phase. Centred
    sums are expanded into raw sums (float64: no precision lost at these sizes) so that a few short,
    branch-free loops over the window do everything, and they vectorize."""
    h, w = data.shape[1:]
    npx = h * w
    x32 = np.empty(npx, np.float32)
    x = np.empty(npx)
    v = np.empty(npx)
    om = np.empty(npx)  # validity x taper: the weight of a pixel in the sums against the reference
    tp = np.empty(npx)  # the gradient energy's weights: the taper one pixel further in, validity not masked
    tx_ = np.empty(w)
    ty_ = np.empty(h)
    gx_ = np.empty(w)
    gy_ = np.empty(h)
    tab = np.empty((4, npx + 8))  # (+8: room for `_gather_at`'s whole-vector rows)
    ref = np.empty(npx)  # the final reference (moved by the last registration step)
    counts = np.empty((4, ENTROPY_BINS + 1), np.int64)
    bins = np.empty(npx, np.int32)
    ring = np.empty(N_RING + 1)  # the last one collects the corners, unused
    ring_k = np.empty(npx, np.int64)  # per pixel: its ring, distance to the lens centre and residual
    ring_d = np.empty(npx)
    ring_res = np.empty(npx)
    edges = RING_EDGES * (0.5 * h)
    inv_half = 1.0 / (0.5 * h)
    rdisc2 = (0.35 * h) ** 2
    half_w = 0.5 * w
    half_h = 0.5 * h
    nan = np.nan
    for k in range(start, stop):
        for j in range(w):
            tx_[j] = _taper(j - cx[k], half_w)
            gx_[j] = _taper(j - cx[k], half_w - 1.0)  # (a gradient's stencil reaches one pixel further out)
        for i in range(h):
            ty_[i] = _taper(i - cy[k], half_h)
            gy_[i] = _taper(i - cy[k], half_h - 1.0)
        nv = 0.0
        flux = 0.0
        top = np.float32(-np.inf)
        for i in range(h):
            for j in range(w):
                val = data[k, i, j]
                p = i * w + j
                ok = math.isfinite(val)
                xv = val if ok else np.float32(0.0)
                x32[p] = xv
                x[p] = xv
                v[p] = 1.0 if ok else 0.0
                tp[p] = gy_[i] * gx_[j]
                om[p] = ty_[i] * tx_[j] if ok else 0.0
                nv += 1.0 if ok else 0.0
                flux += xv
        for p in range(npx):  # (apart, as the max would keep the loop above from vectorizing)
            top = x32[p] if x32[p] > top else top
        # --- registration: I ~ a R(x - d) ~ a R - a d.grad R, so d = -(G'WG)^-1 G'W(I - a R) / a, with the
        # reference R interpolated at the current estimate (qx, qy) and W the pixel weights. The last step's
        # gather also takes the Laplacian, and its reference is moved by that step to first order
        # (R - d.grad R) instead of gathered again: the indexes below are taken against it.
        qx = cx[k]
        qy = cy[k]
        lx = 0.0
        ly = 0.0
        for st in range(max(steps, 1)):
            _gather_at(stack, size, c, os_, phases, pad, qx * os_, qy * os_, h, w, 4 if st >= steps - 1 else 3, tab)
            if steps == 0:
                break
            sxr = srr = sxx = sxy = syy = sgxx = sgxr = sgyx = sgyr = 0.0
            for p in range(npx):
                wp = om[p]
                xp = x[p]
                rp = tab[0, p]
                gxp = tab[1, p]
                gyp = tab[2, p]
                wr = wp * rp
                wgx = wp * gxp
                wgy = wp * gyp
                sxr += xp * wr
                srr += rp * wr
                sxx += gxp * wgx
                sxy += gxp * wgy
                syy += gyp * wgy
                sgxx += wgx * xp
                sgxr += wgx * rp
                sgyx += wgy * xp
                sgyr += wgy * rp
            a = sxr / max(srr, 1e-30)
            bx = sgxx - a * sgxr
            by = sgyx - a * sgyr
            det = sxx * syy - sxy * sxy
            safe = det if abs(det) > 1e-30 else np.inf
            ax = a if abs(a) > 1e-30 else np.inf
            lx = -(syy * bx - sxy * by) / safe / ax
            ly = -(sxx * by - sxy * bx) / safe / ax
            if st < steps - 1:
                qx += lx
                qy += ly
        for p in range(npx):
            ref[p] = tab[0, p] - (lx * tab[1, p] + ly * tab[2, p])
        qx += lx  # the registered lens centre (window px): every index below is taken about it
        qy += ly
        dx = qx - cx[k]
        dy = qy - cy[k]
        # --- reference products, weighted (gradient energy by `tp`)
        sxr = srr = slap2 = sg2 = sxl = srl = srv = sx2 = sxw = nw = 0.0
        peak = -np.inf
        for p in range(npx):
            wp = om[p]
            xp = x[p]
            rp = ref[p]
            lp = tab[3, p]
            gxp = tab[1, p]
            gyp = tab[2, p]
            sxr += wp * xp * rp
            srr += wp * rp * rp
            slap2 += wp * lp * lp
            sg2 += tp[p] * (gxp * gxp + gyp * gyp)
            sxl += wp * xp * lp
            srl += wp * rp * lp
            srv += wp * rp
            sx2 += wp * xp * xp
            sxw += wp * xp
            nw += wp
        for p in range(npx):  # (apart: a max in the loop above would keep it from vectorizing)
            rp = ref[p] * v[p]
            peak = rp if rp > peak else peak
        # --- position-weighted sums: central disc, tilt basis and half-maximum moments (weighted)
        nd = sxd = sx2d = tsxx = tsxy = tsyy = tbxx = tbxr = tbyx = tbyr = 0.0
        sw = swx = swy = swxx = swyy = swxy = 0.0
        half_top = 0.5 * np.float64(top)
        for i in range(h):
            yy = i - qy
            for j in range(w):
                p = i * w + j
                xx = j - qx
                vp = v[p]
                wp = om[p]
                xp = x[p]
                rp = ref[p]
                d = vp if xx * xx + yy * yy <= rdisc2 else 0.0
                nd += d
                sxd += xp * d
                sx2d += xp * xp * d
                bxp = rp * xx * inv_half
                byp = rp * yy * inv_half
                tsxx += wp * bxp * bxp
                tsxy += wp * bxp * byp
                tsyy += wp * byp * byp
                tbxx += wp * bxp * xp
                tbxr += wp * bxp * rp
                tbyx += wp * byp * xp
                tbyr += wp * byp * rp
                wgt = wp * max(xp - half_top, 0.0)
                sw += wgt
                swx += wgt * xx
                swy += wgt * yy
                swxx += wgt * xx * xx
                swyy += wgt * yy * yy
                swxy += wgt * xx * yy
        # --- gradient energy (np.gradient, edge_order 1, both axes), each pixel's weighted by `tp`: zero
        # wherever the stencil could reach a pixel that leaves the window
        ge = 0.0
        if w > 1:
            for i in range(h):
                b0 = i * w
                e = x[b0 + 1] - x[b0]
                ge += tp[b0] * e * e
                e = x[b0 + w - 1] - x[b0 + w - 2]
                ge += tp[b0 + w - 1] * e * e
                xr = x[b0:b0 + w]
                tr_ = tp[b0:b0 + w]
                for j in range(1, w - 1):
                    e = 0.5 * (xr[j + 1] - xr[j - 1])
                    ge += tr_[j] * e * e
        if h > 1:
            for j in range(w):
                e = x[w + j] - x[j]
                ge += tp[j] * e * e
                e = x[(h - 1) * w + j] - x[(h - 2) * w + j]
                ge += tp[(h - 1) * w + j] * e * e
            for i in range(1, h - 1):
                up = x[(i - 1) * w:i * w]
                dn = x[(i + 1) * w:(i + 2) * w]
                tr_ = tp[i * w:(i + 1) * w]
                for j in range(w):
                    e = 0.5 * (dn[j] - up[j])
                    ge += tr_[j] * e * e
        # --- entropy: bins follow NumPy's float32 arithmetic, int(x / top * 32) clipped to 0..31
        # (four interleaved histograms: neighbouring pixels often share a bin, and one histogram would
        # serialize on its counter)
        # The bins are computed in a branch-free loop that vectorizes; pixels outside the frame go to an
        # extra bin that is not counted.
        counts[:] = 0
        top_s = top if top > 0 else np.float32(1.0)
        for p in range(npx):
            bi = np.int32((x32[p] / top_s) * np.float32(ENTROPY_BINS))
            bi = min(max(bi, 0), ENTROPY_BINS - 1)
            bins[p] = bi if v[p] > 0 else ENTROPY_BINS
        for p in range(npx):
            counts[p & 3, bins[p]] += 1
        # --- residual profile: weighted light of the flux-scaled residual x - a R per ring around the lens centre
        a_reg = sxr / max(srr, 1e-30)
        ring[:] = 0.0
        for i in range(h):
            yy = i - qy
            for j in range(w):
                xx = j - qx
                d = math.sqrt(xx * xx + yy * yy)
                kk = 0
                for e in range(N_RING):
                    kk += 1 if d >= edges[e] else 0
                p = i * w + j
                ring_k[p] = kk
                ring_d[p] = d
                ring_res[p] = om[p] * (x[p] - a_reg * ref[p])
        # (apart: the loop above vectorizes; each ring's sum below takes its pixels in the same order)
        for p in range(npx):
            kk = ring_k[p]
            d = ring_d[p]
            res = ring_res[p]
            # soft membership: within half a pixel of an edge a pixel is shared linearly between the two
            # rings, so a ring's light is continuous in the lens' sub-pixel position
            lo = 0.5 - (d - edges[kk - 1]) if kk > 0 else 0.0
            hi = 0.5 - (edges[kk] - d) if kk < N_RING else 0.0
            lo = min(max(lo, 0.0), 1.0)
            hi = min(max(hi, 0.0), 1.0)
            ring[kk] += res * (1.0 - lo - hi)
            if kk > 0:
                ring[kk - 1] += res * lo
            if kk < N_RING:
                ring[kk + 1] += res * hi
        o = out[k]
        if not (flux > 0) or nv < 0.5 * npx:
            for q in range(N_INDEX):
                o[q] = nan
            continue
        a = sxr / max(srr, 1e-30)
        an = a if a != 0 else nan
        inv_an = 1.0 / an
        o[0] = sxw  # the weighted light: a window cut one pixel over does not change it (at the array's
        o[1] = sxw / max(nw, 1e-30)  # edge the two outermost columns differ: one is lit, one is not)
        ndc = max(nd, 1.0)
        mean_d = sxd / ndc
        var_d = max((sx2d - 2.0 * mean_d * sxd + mean_d * mean_d * nd) / ndc, 0.0)
        o[2] = 1.0 - math.sqrt(var_d) / (mean_d if mean_d > 0 else nan)
        total = 0
        for b in range(ENTROPY_BINS):
            total += counts[0, b] + counts[1, b] + counts[2, b] + counts[3, b]
        total = max(total, 1)
        ent = 0.0
        for b in range(ENTROPY_BINS):
            cb = counts[0, b] + counts[1, b] + counts[2, b] + counts[3, b]
            if cb > 0:
                pb = cb / total
                ent -= pb * math.log2(pb)
        o[3] = ent
        o[4] = ge / max(sg2 * a * a, 1e-30)
        o[5] = dx
        o[6] = dy
        o[7] = math.hypot(dx, dy) * um_per_px
        s = max(sw, 1e-30)
        mx = swx / s
        my = swy / s
        cxx = (swxx - 2.0 * mx * swx + mx * mx * sw) / s
        cyy = (swyy - 2.0 * my * swy + my * my * sw) / s
        cxy = (swxy - mx * swy - my * swx + mx * my * sw) / s
        tr = cxx + cyy
        dt = cxx * cyy - cxy * cxy
        disc = math.sqrt(max(tr * tr / 4 - dt, 0.0))
        l1 = tr / 2 + disc
        l2 = max(tr / 2 - disc, 0.0)
        o[8] = math.sqrt(max(tr, 0.0))
        o[9] = 1.0 - math.sqrt(l2 / (l1 if l1 > 0 else nan))
        o[10] = (sxl - a * srl) / max(slap2, 1e-30) * inv_an
        tpx = tbxx - a * tbxr
        tpy = tbyx - a * tbyr
        tdet = tsxx * tsyy - tsxy * tsxy
        tdet = tdet if abs(tdet) > 1e-30 else np.inf
        o[11] = (tsyy * tpx - tsxy * tpy) / tdet * inv_an
        o[12] = (tsxx * tpy - tsxy * tpx) / tdet * inv_an
        # full reference against xs = x / a, weighted: means, mse, (co)variances from raw sums
        nwc = max(nw, 1e-30)
        mxs = sxw * inv_an / nwc
        mr = srv / nwc
        sxs2 = sx2 * inv_an * inv_an
        sxsr = sxr * inv_an
        mse = (sxs2 - 2.0 * sxsr + srr) / nwc
        vx = max((sxs2 - 2.0 * mxs * sxw * inv_an + mxs * mxs * nw) / nwc, 0.0)
        vr = max((srr - 2.0 * mr * srv + mr * mr * nw) / nwc, 0.0)
        cov = (sxsr - mr * sxw * inv_an - mxs * srv + mxs * mr * nw) / nwc
        c1 = (0.01 * peak) ** 2
        c2 = (0.03 * peak) ** 2
        o[13] = 10.0 * np.log10(peak * peak / max(mse, 0.0))
        o[14] = ((2 * mxs * mr + c1) * (2 * cov + c2)) / ((mxs * mxs + mr * mr + c1) * (vx + vr + c2))
        o[15] = cov / math.sqrt(vx * vr)
        ref_light = a * srv if a * srv != 0 else nan
        for q in range(N_RING):
            o[_RING0 + q] = ring[q] / ref_light


# Median-of-25 selection network (Paeth / Devillard opt_med25): after these 99 compare-exchanges wire 12
# holds the median. Checked exhaustively on all 2^25 0-1 inputs (0-1 principle, tests/test_metrics_kernels.py).
MEDIAN25_PAIRS = np.array([
    (0, 1), (3, 4), (2, 4), (2, 3), (6, 7), (5, 7), (5, 6), (9, 10), (8, 10), (8, 9), (12, 13), (11, 13), (11, 12),
    (15, 16), (14, 16), (14, 15), (18, 19), (17, 19), (17, 18), (21, 22), (20, 22), (20, 21), (23, 24), (2, 5),
    (3, 6), (0, 6), (0, 3), (4, 7), (1, 7), (1, 4), (11, 14), (8, 14), (8, 11), (12, 15), (9, 15), (9, 12), (13, 16),
    (10, 16), (10, 13), (20, 23), (17, 23), (17, 20), (21, 24), (18, 24), (18, 21), (19, 22), (8, 17), (9, 18),
    (0, 18), (0, 9), (10, 19), (1, 19), (1, 10), (11, 20), (2, 20), (2, 11), (12, 21), (3, 21), (3, 12), (13, 22),
    (4, 22), (4, 13), (14, 23), (5, 23), (5, 14), (15, 24), (6, 24), (6, 15), (7, 16), (7, 19), (13, 21), (15, 23),
    (7, 13), (7, 15), (1, 9), (3, 11), (5, 17), (11, 17), (9, 17), (4, 10), (6, 12), (7, 14), (4, 6), (4, 7),
    (12, 14), (10, 14), (6, 7), (10, 12), (6, 10), (6, 17), (12, 17), (7, 17), (7, 10), (12, 18), (7, 12), (10, 18),
    (12, 20), (10, 20), (10, 12),
], dtype=np.int64)


@_jit.aot("f8[:, :, ::1], i8, b1[::1], f8[:, :, ::1]")
def median_baselines(values, size, x_axis, out):
    """Local median baseline of each (rows, cols) plane of `values` (F, rows, cols, no NaN) into `out`:
    the size x size median (scipy median_filter, mode 'nearest'); along the array's edges the running
    median of that edge line instead (when the array is at least size x size). Corners take the edge
    written last: for planes with x_axis[f] the left/right columns, else the top/bottom rows. Size 5 runs
    the median-25 network on a whole row at once (branch-free, vectorizes); other odd sizes sort."""
    n_feat, rows, cols = values.shape
    half = size // 2
    buf = np.empty(size * size)
    wires = np.empty((25, cols))
    for f in range(n_feat):
        a = values[f]
        o = out[f]
        for i in range(rows):
            if size == 5:
                q = 0
                for di in range(-2, 3):
                    ii = min(max(i + di, 0), rows - 1)
                    for dj in range(-2, 3):
                        for j in range(cols):
                            wires[q, j] = a[ii, min(max(j + dj, 0), cols - 1)]
                        q += 1
                for e in range(MEDIAN25_PAIRS.shape[0]):
                    lo_w = wires[MEDIAN25_PAIRS[e, 0]]
                    hi_w = wires[MEDIAN25_PAIRS[e, 1]]
                    for j in range(cols):
                        u = lo_w[j]
                        t = hi_w[j]
                        lo_w[j] = u if u < t else t
                        hi_w[j] = t if u < t else u
                for j in range(cols):
                    o[i, j] = wires[12, j]
                continue
            for j in range(cols):
                m = 0
                for di in range(-half, half + 1):
                    ii = min(max(i + di, 0), rows - 1)
                    for dj in range(-half, half + 1):
                        jj = min(max(j + dj, 0), cols - 1)
                        _insert(buf, m, a[ii, jj])
                        m += 1
                o[i, j] = buf[m // 2]
        if rows >= size and cols >= size:
            if x_axis[f]:
                _edge_rows(a, o, size, buf)
                _edge_cols(a, o, size, buf)
            else:
                _edge_cols(a, o, size, buf)
                _edge_rows(a, o, size, buf)


@_jit
def _insert(buf, m, val):
    """Insert val into the sorted buf[:m] (insertion sort step)."""
    q = m
    while q > 0 and buf[q - 1] > val:
        buf[q] = buf[q - 1]
        q -= 1
    buf[q] = val


@_jit
def _edge_rows(a, o, size, buf):
    """Running 1-D median (mode 'nearest') along the first and the last row."""
    rows, cols = a.shape
    half = size // 2
    for i in (0, rows - 1):
        for j in range(cols):
            m = 0
            for dj in range(-half, half + 1):
                _insert(buf, m, a[i, min(max(j + dj, 0), cols - 1)])
                m += 1
            o[i, j] = buf[m // 2]


@_jit
def _edge_cols(a, o, size, buf):
    """Running 1-D median (mode 'nearest') along the first and the last column: the rows' on the transpose."""
    _edge_rows(a.T, o.T, size, buf)
