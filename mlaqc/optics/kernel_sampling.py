"""The compiled tracer's stage 1: draws, the low-discrepancy sampler, and rays through the main lens.

Each block of rays is drawn (counter-based uniforms or scrambled Sobol' points, as mlaqc.optics.unitcircle
and lowdisc), started on the aperture or in its MLA cell, and traced through the main lens to the MLA's
side, the texture's radiance applied; the same operations and draws as mlaqc.optics.scene's NumPy path.
"""

from __future__ import annotations

import math

import numpy as np

from mlaqc.optics import lowdisc
from mlaqc.optics.kernel_geometry import hex_locate, main_surface, refract, sphere_t
from mlaqc.optics.kernel_jit import jit, jit_inline
from mlaqc.optics.kernel_layout import (
    BLOCK, G_COL, G_HX, G_HY, G_HZ, G_LL, G_LM, G_LN, G_ROW, IMAGE_SIDE, POINT, S_AX0, S_AY0, S_C1, S_C2, S_CB,
    S_CBW, S_CC0, S_CR0, S_INVKR, S_J0, S_N, S_P, S_PCOLS, S_PX, S_PY, S_R00, S_R01, S_R10, S_R11,
    S_RIM2, S_RPUPIL, S_SHIFTX, S_SHIFTY, S_SQUARE, S_SQW, S_T, S_TEXHX, S_TEXHY, S_TEXTURE, S_X0, S_X1, S_Y0,
    S_Y1, S_ZEXIT, S_ZOBJ, S_ZSTART)
from mlaqc.optics.lattice import SQRT3_2
from mlaqc.optics.scene import FOUR_OVER_PI
from mlaqc.optics.scene import aperture_point as _aperture_point
from mlaqc.optics.unitcircle import GAMMA, HALF_PI, MIX1, MIX2, TO_UNIT
from mlaqc.optics.unitcircle import poly_cos as _poly_cos
from mlaqc.optics.unitcircle import poly_sin as _poly_sin

poly_sin = jit_inline(_poly_sin)
poly_cos = jit_inline(_poly_cos)
sobol32 = jit_inline(lowdisc.sobol32)
reverse32 = jit_inline(lowdisc.reverse32)
lk_hash = jit_inline(lowdisc.lk_hash)
hash32 = jit_inline(lowdisc.hash32)
SOBOL_DIRECTIONS = lowdisc.DIRECTIONS
aperture_point = jit_inline(_aperture_point)


@jit_inline
def texel(texture, ox, oy, hx, hy):
    th, tw = texture.shape
    uu = (ox + hx) / (2.0 * hx)
    vv = (oy + hy) / (2.0 * hy)
    if not (uu >= 0.0 and uu < 1.0 and vv >= 0.0 and vv < 1.0):
        return 0.0
    return texture[min(int(vv * th), th - 1), min(int(uu * tw), tw - 1)]


@jit_inline
def draw(key, i, d):
    """Scalar twin of unitcircle.counter_uniforms: draw d of ray i."""
    z = key + (np.uint64(4) * np.uint64(i) + np.uint64(d + 1)) * GAMMA
    z = (z ^ (z >> np.uint64(30))) * MIX1
    z = (z ^ (z >> np.uint64(27))) * MIX2
    z = (z ^ (z >> np.uint64(31))) >> np.uint64(11)
    # float64(z) exactly, from two halves that fit an int32: AVX2 converts those four at a time, not 64-bit ones
    hi = np.float64(np.int32(z >> np.uint64(26)))
    lo = np.float64(np.int32(z & np.uint64(0x3FFFFFF)))
    return (hi * 67108864.0 + lo) * TO_UNIT


@jit_inline
def owen32(x, seed):
    """Compiled twin of lowdisc.owen32."""
    return reverse32(lk_hash(reverse32(x), seed))


@jit_inline
def sobol_draws(start, m, s, seeds, shifts, jtab, g, ia, icf):
    """Draws of rays start..start+m-1 into g rows G_HX..G_LL (dims 0-3) and their cell into G_ROW, G_COL.

    Ray i of the job is point j0 + i // cb of cell i % cb of the job's block (point scenes: cb = 1, one
    shift). The block's few distinct points are scrambled once into `jtab`; each ray then only XORs its
    cell's shift (as lowdisc.cell_uniforms)."""
    cb, cbw, j0 = np.int64(s[S_CB]), np.int64(s[S_CBW]), np.int64(s[S_J0])
    q0 = start // cb
    nq = (start + m - 1) // cb - q0 + 1
    for a in range(nq):
        j = np.uint64(j0 + q0 + a)
        for d in range(4):
            jtab[a, d] = owen32(sobol32(j, d, SOBOL_DIRECTIONS), seeds[d])
    r0, c0 = s[S_CR0], s[S_CC0]
    # point, cell and the cell's row and column counted up ray by ray (integer division per ray is slow)
    a = np.int64(0)
    cf = start - q0 * cb
    rr = cf // cbw
    cc = cf - rr * cbw
    for j in range(m):
        ia[j], icf[j] = a, cf
        g[G_ROW, j] = r0 + rr
        g[G_COL, j] = c0 + cc
        cf += 1
        cc += 1
        if cc == cbw:
            cc = 0
            rr += 1
        if cf == cb:
            cf, rr, cc = 0, 0, 0
            a += 1
    for j in range(m):  # 32-bit values: converted through int64, one instruction (uint64 takes several)
        a, cf = ia[j], icf[j]
        g[G_HX, j] = (np.float64(np.int64(jtab[a, 0] ^ shifts[cf, 0])) + 0.5) * lowdisc.TO_UNIT32
        g[G_HY, j] = (np.float64(np.int64(jtab[a, 1] ^ shifts[cf, 1])) + 0.5) * lowdisc.TO_UNIT32
        g[G_HZ, j] = (np.float64(np.int64(jtab[a, 2] ^ shifts[cf, 2])) + 0.5) * lowdisc.TO_UNIT32
        g[G_LL, j] = (np.float64(np.int64(jtab[a, 3] ^ shifts[cf, 3])) + 0.5) * lowdisc.TO_UNIT32


@jit
def sobol_tables(s, key):
    """Scramble seeds, one digital shift per cell of the job's block (by its padded-grid id), and room
    for a block's scrambled points (see lowdisc)."""
    k = np.uint64(key)
    ks = k ^ lowdisc.OWEN_SALT
    seeds = np.empty(4, np.uint64)
    for d in range(4):
        seeds[d] = hash32(ks, np.uint64(0), d)
    cb, cbw = np.int64(s[S_CB]), np.int64(s[S_CBW])
    r0, c0, pcols = np.int64(s[S_CR0]), np.int64(s[S_CC0]), np.int64(s[S_PCOLS])
    shifts = np.empty((cb, 4), np.uint64)
    for cf in range(cb):
        rr = cf // cbw
        cid = np.uint64((r0 + rr + 1) * pcols + (c0 + cf - rr * cbw + 1)) if pcols > 0 else np.uint64(0)
        for d in range(4):
            shifts[cf, d] = hash32(k, cid, d)
    return seeds, shifts, np.empty((BLOCK + 2, 4), np.uint64)


@jit_inline
def cos_sin_2pi(u):
    """Scalar twin of unitcircle.cos_sin_2pi (same operations, so both engines draw the same angles)."""
    v = 4.0 * u
    q = math.floor(v + 0.5)
    a = (v - q) * HALF_PI
    a2 = a * a
    c, sn = poly_cos(a2), poly_sin(a, a2)
    iq = q - 4.0 if q >= 4.0 else q  # q mod 4 (q is 0..4), kept a float so that the loop vectorizes
    swap = (iq == 1.0) | (iq == 3.0)
    cc = sn if swap else c
    ss = c if swap else sn
    cc = -cc if ((iq == 1.0) | (iq == 2.0)) else cc
    ss = -ss if iq >= 2.0 else ss
    return cc, ss


@jit_inline
def stage1_image_side(start, m, s, key, buf, fres, texture, textured, g, sobol, shift_coef, lat):
    """Rays from the rear aperture to the MLA, traced back through the main lens for their weight.

    Branch-free loops (sampling, rear surface, front surface) that vectorize; split because one loop
    holding the whole chain of square roots and divisions was bound by its latency. `g` is scratch and,
    for the low-discrepancy sampler, holds the draws and cells already (sobol_draws). The object point a
    texture is looked up at is found only for a textured scene (`textured`)."""
    if sobol and s[S_PCOLS] > 0.0:  # a block of cells
        cell_starts(m, s, buf, g, shift_coef, lat)
        m = compact(m, buf)
    else:  # a tile of the MLA's bounding box
        if not sobol:
            for j in range(m):
                i = start + j
                g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j] = draw(key, i, 0), draw(key, i, 1), draw(key, i, 2), draw(key, i, 3)
        polar_starts(m, s, buf, g)
    if textured:
        image_side_surfaces(m, s, buf, fres, texture, g)
    else:
        image_side_surfaces(m, s, buf, fres, None, g)
    return m


@jit_inline
def compact(m, buf):
    """Move the rays of weight > 0 to the front of the block, in order; how many there are. The
    stratified sampler's points off the aperture disc (about a quarter) are so never traced."""
    k = 0
    for j in range(m):
        if buf[6, j] > 0.0:
            if k != j:
                for r in range(7):
                    buf[r, k] = buf[r, j]
            k += 1
    return k


@jit_inline
def cell_starts(m, s, buf, g, shift_coef, lat):
    """Rays of the stratified sampler: start in their MLA cell (hex, `lat` not None: the rhombus folded
    into the hexagon), aperture point a' on the square moved by Phi(h, a'), weight times the Jacobian (as
    scene.sample_image_cells)."""
    p, ax0, ay0 = s[S_P], s[S_AX0], s[S_AY0]
    r00, r01, r10, r11, shx, shy = s[S_R00], s[S_R01], s[S_R10], s[S_R11], s[S_SHIFTX], s[S_SHIFTY]
    rp, zs, dz = s[S_RPUPIL], s[S_ZSTART], s[S_ZSTART] - s[S_ZEXIT]
    inv_rm, sq, sqw = s[S_INVKR], s[S_SQUARE], s[S_SQW]
    inv_ra = 1.0 / rp
    rp2 = rp * rp
    if lat is not None:
        hex_fold(m, g)
    for j in range(m):
        u2, u3 = g[G_HZ, j], g[G_LL, j]
        mx = ax0 + (g[G_COL, j] + u2) * p
        my = ay0 + (g[G_ROW, j] + u3) * p
        x = r00 * mx + r01 * my + shx
        y = r10 * mx + r11 * my + shy
        hx, hy = (u2 - 0.5) * p, (u3 - 0.5) * p
        hcx, hcy = r00 * hx + r01 * hy, r10 * hx + r11 * hy
        bx, by = sq * (2.0 * g[G_HX, j] - 1.0), sq * (2.0 * g[G_HY, j] - 1.0)
        ax, ay, jac = aperture_point(shift_coef, inv_rm, inv_ra, hcx, hcy, bx, by)
        dx = x - ax
        dy = y - ay
        inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
        L, M, N = dx * inv, dy * inv, dz * inv
        w = (N * N) * (N * N) * sqw * jac
        buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j] = x, y, zs, L, M, N
        buf[6, j] = w if ax * ax + ay * ay <= rp2 else 0.0


@jit_inline
def hex_fold(m, g):
    """Hex cells (as scene.hex_cell_draws): each ray's cell draws (u2, u3) and cell (row, col) rewritten so
    that the square cell's formulas (x0 + (col + u2) p, offset (u2 - 1/2) p) give the point of its
    hexagon, (x0, y0) being U(1,1)'s centre."""
    for j in range(m):
        bb = g[G_LL, j] - 0.5
        _, _, du, dv = hex_locate((g[G_HZ, j] - 0.5) + 0.5 * bb, SQRT3_2 * bb)
        row = g[G_ROW, j]
        g[G_HZ, j], g[G_LL, j] = du + 0.5, dv + 0.5
        g[G_COL, j] = g[G_COL, j] + 0.5 * (row - 2.0 * np.floor(0.5 * row)) - 0.5
        g[G_ROW, j] = row * SQRT3_2 - 0.5


@jit_inline
def polar_starts(m, s, buf, g):
    """Rays of the plain Monte-Carlo sampler: uniform in the tile, uniform on the aperture disc."""
    x0, dx_span, y0, dy_span = s[S_X0], s[S_X1] - s[S_X0], s[S_Y0], s[S_Y1] - s[S_Y0]
    rp, zs, dz = s[S_RPUPIL], s[S_ZSTART], s[S_ZSTART] - s[S_ZEXIT]
    for j in range(m):
        x = x0 + dx_span * g[G_HX, j]
        y = y0 + dy_span * g[G_HY, j]
        rad = rp * math.sqrt(g[G_HZ, j])
        cph, sph = cos_sin_2pi(g[G_LL, j])
        dx = x - rad * cph
        dy = y - rad * sph
        inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
        L, M, N = dx * inv, dy * inv, dz * inv
        buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j], buf[6, j] = x, y, zs, L, M, N, (N * N) * (N * N)


@jit_inline
def image_side_surfaces(m, s, buf, fres, texture, g):
    """Back through the main lens' rear and front surfaces: vignetting, Fresnel, the object point."""
    zs = s[S_ZSTART]
    t_main, c1, c2, n, rim2, zobj = s[S_T], s[S_C1], s[S_C2], s[S_N], s[S_RIM2], s[S_ZOBJ]
    mu_in, mu_out = 1.0 / n, n
    # rear surface (the ray travels -z): hit, then refraction, in two loops
    for j in range(m):
        x, y, L, M, N = buf[0, j], buf[1, j], -buf[3, j], -buf[4, j], -buf[5, j]
        t = sphere_t(x, y, zs - t_main, L, M, N, c2)
        g[G_HX, j], g[G_HY, j], g[G_HZ, j] = x + t * L, y + t * M, zs + t * N
    for j in range(m):
        x, y, z = g[G_HX, j], g[G_HY, j], g[G_HZ, j]
        L, M, N, tr = refract(-buf[3, j], -buf[4, j], -buf[5, j], c2 * x, c2 * y, c2 * (z - t_main) - 1.0, mu_in, fres, 1.0, n)
        buf[6, j] *= tr if (x * x + y * y <= rim2 and tr >= 0.0) else 0.0
        g[G_LL, j], g[G_LM, j], g[G_LN, j] = L, M, N
    # front surface
    for j in range(m):
        x, y, z, L, M, N = g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j]
        t = sphere_t(x, y, z - 0.0, L, M, N, c1)
        g[G_HX, j], g[G_HY, j], g[G_HZ, j] = x + t * L, y + t * M, z + t * N
    for j in range(m):
        bx, by, bz = g[G_HX, j], g[G_HY, j], g[G_HZ, j]
        bL, bM, bN, tr = refract(g[G_LL, j], g[G_LM, j], g[G_LN, j], c1 * bx, c1 * by, c1 * (bz - 0.0) - 1.0, mu_out, fres, n, 1.0)
        buf[6, j] *= tr if (bx * bx + by * by <= rim2 and tr >= 0.0) else 0.0
        if texture is not None:  # pruned at compile time where the caller passes None (no texture)
            t = (zobj - bz) / bN
            buf[7, j], buf[8, j] = bx + t * bL, by + t * bM


@jit_inline
def stage1_forward(start, m, mode, s, key, buf, fres, texture, g, sobol):
    """Rays from object points (a point source, or points of the object plane) through the main lens.

    A sampling loop, then one loop per surface (see stage1_image_side). With the low-discrepancy sampler
    the draws are in g already (sobol_draws): dims 0, 1 a point on the square around the pupil (weight 0
    off the disc, 4/pi on it), dims 2, 3 the object point in the tile."""
    x0, dx_span, y0, dy_span = s[S_X0], s[S_X1] - s[S_X0], s[S_Y0], s[S_Y1] - s[S_Y0]
    rp, zs = s[S_RPUPIL], s[S_ZSTART]
    t_main, c1, c2, n, rim2 = s[S_T], s[S_C1], s[S_C2], s[S_N], s[S_RIM2]
    mu_in, mu_out = 1.0 / n, n
    point = mode == POINT
    rp2 = rp * rp
    for j in range(m):
        i = start + j
        if sobol:
            ox = s[S_PX] if point else x0 + dx_span * g[G_HZ, j]
            oy = s[S_PY] if point else y0 + dy_span * g[G_LL, j]
            ax = rp * (2.0 * g[G_HX, j] - 1.0)
            ay = rp * (2.0 * g[G_HY, j] - 1.0)
            keep = FOUR_OVER_PI if ax * ax + ay * ay <= rp2 else 0.0
        else:
            if point:
                ox, oy, ur, up = s[S_PX], s[S_PY], draw(key, i, 0), draw(key, i, 1)
            else:
                ox, oy = x0 + dx_span * draw(key, i, 0), y0 + dy_span * draw(key, i, 1)
                ur, up = draw(key, i, 2), draw(key, i, 3)
            rad = rp * math.sqrt(ur)
            cph, sph = cos_sin_2pi(up)
            ax, ay, keep = rad * cph, rad * sph, 1.0
        dx = ax - ox
        dy = ay - oy
        dz = -zs
        inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
        L, M, N = dx * inv, dy * inv, dz * inv
        w = N * N * N
        if not point:
            w *= N
        buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j], buf[6, j] = ox, oy, zs, L, M, N, w * keep
        buf[7, j], buf[8, j] = ox, oy
    for j in range(m):
        x, y, z, L, M, N, tr = main_surface(buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j], 0.0, c1,
                                            1.0, n, mu_in, rim2, fres)
        buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j] = x, y, z, L, M, N
        buf[6, j] *= tr
    for j in range(m):
        x, y, z, L, M, N, tr = main_surface(buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j], t_main,
                                            c2, n, 1.0, mu_out, rim2, fres)
        buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j] = x, y, z, L, M, N
        buf[6, j] *= tr



@jit_inline
def stage1_block(start, m, mode, s, key, buf, fres, texture, g, sobol, shift_coef, seeds, shifts, jtab, ia, icf,
                 lat):
    """Stage 1 for one block, shared by both kernels: draws, rays to the MLA's side of the main lens, the
    texture's radiance; returns the block's ray count (the image-side sampler compacts it)."""
    if sobol:
        sobol_draws(start, m, s, seeds, shifts, jtab, g, ia, icf)
    textured = s[S_TEXTURE] != 0.0
    if mode == IMAGE_SIDE:
        m = stage1_image_side(start, m, s, key, buf, fres, texture, textured, g, sobol, shift_coef, lat)
    else:
        stage1_forward(start, m, mode, s, key, buf, fres, texture, g, sobol)
    if textured:
        for j in range(m):
            buf[6, j] *= texel(texture, buf[7, j], buf[8, j], s[S_TEXHX], s[S_TEXHY])
    return m
