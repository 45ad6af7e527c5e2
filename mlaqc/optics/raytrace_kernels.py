"""Compiled fast path: the whole chain (sampling -> main lens -> MLA -> sensor pixel -> per-pixel sums) in Numba.

It follows `mlaqc.optics.raytrace` and `mlaqc.optics.scene` operation for operation and consumes the same uniform draws,
so tests compare the two ray by ray (same pixels; weights to rounding, FMA contraction being on here).
Rays go in blocks of BLOCK through a sequence of short loops (a pass per surface or step), each
branch-free over the block so that LLVM vectorizes it (4 doubles per AVX2 instruction) and independent
rays overlap in the pipeline; a single loop carrying one ray's whole chain of square roots and divisions
was bound by their latency. The rare neighbour re-trace near cell edges is a scalar pass of its own, in
both lens boundary models ('grid': the lens of the hit's cell; 'sag-intersection': the first / last of
the 3 x 3 spheres met (hex: the cell and its 6 neighbours), for hits within a per-cell margin of the
edge), and for circle apertures (the circle holding the hit, for gap hits near a neighbour's circle).
Hex cells, circle apertures and per-lens tilts are kernel variants: `lat`, `circ` and `rot` are None on
square / cell / untilted arrays, and what differs is chosen when Numba compiles (overloads on `lat`), never
by a branch inside a pass. A textured scene and a global MLA rotation are not: the passes they change are
inlined for both sides and chosen per block of rays (S_TEXTURE, S_GROT), so one compiled kernel serves both.
Hits are appended in ray order and summed per pixel in compiled code, as np.bincount would. It releases
the GIL, so the renderer's thread pool keeps every core busy. The NumPy path stays the reference; this
module is used when Numba is importable.
"""

from __future__ import annotations

import math

import numpy as np

from mlaqc.optics.kernel_geometry import (
    candidate, cell, cell_centre, cell_f, centre_cell, from_lens, hit_xy, lens_surface, refract, rot_n, rot_of, rot_t,
    surface_hit, surface_hit_edge, surface_hit_own, to_lens, under_black_matrix)
from mlaqc.optics.kernel_jit import AVAILABLE, jit, jit_inline  # noqa: F401 - AVAILABLE: whether this module compiles
from mlaqc.optics.kernel_layout import (
    BLOCK, C_CLEAR, C_GX, C_GY, C_REACH2, G_C1, G_C2, G_COL, G_COUNT, G_CX, G_CY, G_DX, G_DY, G_FX, G_FY, G_HX,
    G_HY, G_HZ, G_LL, G_LM, G_LN, G_MF, G_MR, G_ROW, G_T, G_ZR, S_AX0, S_AY0, S_CLEAR, S_CLEARGAP, S_COLS, S_FRES,
    S_GROT, S_H, S_HALFBM, S_INVP, S_INVPIX, S_MODE, S_NMLA, S_P, S_PRUNE, S_RCIRC2, S_ROWS, S_SHIFTX, S_SHIFTY,
    S_SOBOL, S_SX0, S_SY0, S_W, S_ZFRONT, S_ZMLA, S_ZSENS, T_GX, T_GY, T_MARGIN_FRONT, T_MARGIN_REAR)
from mlaqc.optics.kernel_sampling import sobol_tables, stage1_block
from mlaqc.optics.lattice import SQRT3_2


@jit_inline
def gather(j, k, tab, g):
    """Copy lens k's parameters into column j of the scratch table."""
    for r in range(7):
        g[r, j] = tab[r, k]


@jit_inline
def retrace_neighbours(m, flag, kk, buf, g, tab, rot, s, rear, lat):
    """Rays whose hit left their cell (near a cell edge, a few per cent) are re-traced once with the
    lens of the cell they hit, as raytrace.MicrolensArray._hit does (scalar pass: it is rare)."""
    for j in range(m):
        if flag[j]:
            gx, gy, _, _, _, _ = from_lens(kk[j], g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j],
                                           g[G_LN, j], tab, rot)
            k = cell(gx, gy, s, lat)
            kk[j] = k
            gather(j, k, tab, g)
            f = lens_surface(k, buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j], rear, tab, rot,
                             s[S_ZFRONT])
            g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j], g[G_T, j] = f[:7]



# The candidates' design-centre offsets from their cell's, in pitches, in candidate order (`candidate`):
# square the 3 x 3 row-major, hex the cell, then left, right, upper left, upper right, lower left, lower
# right (y down; FastCamera checks them against the lattice's centres).
SQUARE_DIRS = np.array([[dc, dr] for dr in (-1.0, 0.0, 1.0) for dc in (-1.0, 0.0, 1.0)])
HEX_DIRS = np.array([[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [-0.5, -SQRT3_2], [0.5, -SQRT3_2], [-0.5, SQRT3_2],
                     [0.5, SQRT3_2]])


@jit_inline
def clears_neighbours(k, x, y, side, margins, lims, lat):
    """Lens k's sphere (front, side 0, lowest; rear, side 1, highest) wins at MLA point (x, y) of its cell
    against every candidate around it: the point's offset from k's design centre projected on each
    candidate's direction stays within that pair's limit (`lims`, FastCamera: +inf for the cell itself
    and candidates off the array), so the scan could only return k. Branch-free: a few multiply-adds."""
    a, b = x - margins[T_GX, k], y - margins[T_GY, k]
    dirs = SQUARE_DIRS if lat is None else HEX_DIRS
    ok = True
    for i in range(9 if lat is None else 7):
        ok &= a * dirs[i, 0] + b * dirs[i, 1] <= lims[side, k, i]
    return ok


@jit
def scan_candidates(j, k0, row0, col0, buf, tab, rot, s, rear, lat, best, bt, bx, by, bz, bL, bM, bN):
    """The first-met front / last-met rear sphere among the candidates around cell (row0, col0), starting
    from lens k0's hit (best, bt, b*): another replaces it only if strictly earlier / later, so the first
    in candidate order wins a tie (as raytrace.MicrolensArray.extreme_lens)."""
    rows, cols = int(s[S_ROWS]), int(s[S_COLS])
    for i in range(9 if lat is None else 7):
        rr, cc = candidate(i, row0, col0, lat)
        kc = rr * cols + cc
        if rr < 0 or rr >= rows or cc < 0 or cc >= cols or kc == k0:
            continue
        hx, hy, hz, lL, lM, lN, t = lens_surface(kc, buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j],
                                                 buf[5, j], rear, tab, rot, s[S_ZFRONT])
        if t == t and (t > bt if rear else t < bt):
            best, bt, bx, by, bz, bL, bM, bN = kc, t, hx, hy, hz, lL, lM, lN
    return best, bt, bx, by, bz, bL, bM, bN


@jit_inline
def retrace_sag(m, flag, kk, buf, g, tab, rot, s, rear, cflag, margins, lims, lat, corner_of):
    """Flagged rays (near a cell edge) take the front sphere they meet first / the rear sphere they meet
    last among the 3 x 3 lenses around their hit's cell: lens kk's hit (in g) unless another is strictly
    earlier / later, the first in row-major order winning a tie (as raytrace.MicrolensArray.extreme_lens;
    a scalar pass: it is rare). Front re-traces also flag the ray's corner test (cflag).

    Pruned (S_PRUNE): a hit in its own lens' cell that clears every neighbour pair's bound keeps that lens
    without a scan, and a hit in a neighbour's cell takes that lens after one intersection when the lens
    is strictly better and its own hit lies in its cell clear of its neighbours; the rest scan, so the
    outcome is the scan's, ray for ray."""
    side = 1 if rear else 0
    prune = s[S_PRUNE] != 0.0
    for j in range(m):
        if flag[j]:
            if not rear:
                cflag[j] = True
            k0 = kk[j]
            gx, gy = hit_xy(k0, g[G_HX, j], g[G_HY, j], g[G_HZ, j], tab, rot)
            best, bt = k0, g[G_T, j]
            bx, by, bz, bL, bM, bN = g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j]
            k2 = cell(gx, gy, s, lat) if prune else -1
            done = False
            if k2 >= 0 and k2 == k0:
                done = clears_neighbours(k0, gx, gy, side, margins, lims, lat)
            elif k2 >= 0:
                hx, hy, hz, lL, lM, lN, t = lens_surface(k2, buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j],
                                                         buf[5, j], rear, tab, rot, s[S_ZFRONT])
                if t == t and (t > bt if rear else t < bt):
                    x2, y2 = hit_xy(k2, hx, hy, hz, tab, rot)
                    if cell(x2, y2, s, lat) == k2 and clears_neighbours(k2, x2, y2, side, margins, lims, lat):
                        best, bt, bx, by, bz, bL, bM, bN = k2, t, hx, hy, hz, lL, lM, lN
                        done = True
            if not done:
                row0, col0 = centre_cell(gx, gy, s, lat)
                best, bt, bx, by, bz, bL, bM, bN = scan_candidates(j, k0, row0, col0, buf, tab, rot, s, rear, lat,
                                                                   best, bt, bx, by, bz, bL, bM, bN)
            if best != k0:
                kk[j] = best
                gather(j, best, tab, g)
                g[G_MR, j] = margins[T_MARGIN_REAR, best]
                g[G_CX, j], g[G_CY, j] = margins[T_GX, best], margins[T_GY, best]
                g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j], g[G_T, j] = bx, by, bz, bL, bM, bN, bt
                if not rear:
                    corner_of[j] = True  # lens k0's corner test is stale: corners_sag decides


@jit_inline
def inside_rear(k, px, py, pz, tab):
    """A point of lens k's frame lies in front of (in the material of) its rear sphere."""
    rx, ry = px - tab[2, k], py - tab[3, k]
    c2 = tab[5, k]
    rho2 = rx * rx + ry * ry
    arg = 1.0 - c2 * c2 * rho2
    return (arg >= 0.0) & (tab[6, k] + c2 * rho2 / (1.0 + math.sqrt(max(arg, 0.0))) > pz)


@jit
def in_rear_union(gx, gy, gz, tab, rot, s, lat):
    """An MLA-frame point lies in the rear region of one of the candidates around its cell (a call, not
    inlined: rare, and compiled once for all kernels that share its types)."""
    rows, cols = int(s[S_ROWS]), int(s[S_COLS])
    row0, col0 = centre_cell(gx, gy, s, lat)
    inside = False
    for i in range(9 if lat is None else 7):
        rr, cc = candidate(i, row0, col0, lat)
        if rr < 0 or rr >= rows or cc < 0 or cc >= cols:
            continue
        kc = rr * cols + cc
        px, py, pz, _, _, _ = to_lens(kc, gx, gy, gz, 0.0, 0.0, 0.0, tab, rot)
        inside = inside or inside_rear(kc, px, py, pz, tab)
    return inside


@jit_inline
def corners_sag(m, cflag, kk, g, tab, rot, s, corner_of, lat):
    """Sag-intersection corners of the flagged rays (front hit within the rear margin of its cell's edge,
    or re-traced) outside their own lens' rear region (inside it, a hit is in the union: the scan is
    skipped): the front hit lies in no rear region of the candidates around its cell (as
    raytrace.MicrolensArray._corner_sag; elsewhere lens kk's rear decides, in pass B). Scalar: rare."""
    for j in range(m):
        if cflag[j] and corner_of[j]:  # inside its own lens' rear region, a hit is in the union: no corner
            gx, gy, gz, _, _, _ = from_lens(kk[j], g[G_HX, j], g[G_HY, j], g[G_HZ, j], 0.0, 0.0, 0.0, tab, rot)
            corner_of[j] = not in_rear_union(gx, gy, gz, tab, rot, s, lat)


@jit_inline
def black_matrix(m, buf, s, lat):
    """Absorb rays crossing the front vertex plane (buf, MLA frame) within half the black matrix' width of
    a cell edge (as raytrace.MicrolensArray.black_matrix)."""
    ax0, ay0, invp, p, hw = s[S_AX0], s[S_AY0], s[S_INVP], s[S_P], s[S_HALFBM]
    for j in range(m):
        masked = under_black_matrix((buf[0, j] - ax0) * invp, (buf[1, j] - ay0) * invp, p, hw, lat)
        buf[6, j] = 0.0 if masked else buf[6, j]


@jit_inline
def front_sag(m, buf, s, tab, rot, g, kk, flag, cflag, corner_of, lat):
    """Pass B in sag-intersection mode (branch-free): lens kk's front hit; flag hits in another cell or
    within the front margin of the cell's edge (re-traced), and those within the rear margin (their
    corner test needs the neighbours' rear regions); the corner test with lens kk's rear for the rest."""
    zfront, ax0, ay0, invp, p, ncols, nrows = s[S_ZFRONT], s[S_AX0], s[S_AY0], s[S_INVP], s[S_P], s[S_COLS], s[S_ROWS]
    for j in range(m):
        fx, fy, c, k = g[G_FX, j], g[G_FY, j], g[G_C1, j], kk[j]
        px, py, pz, L, M, N = buf[0, j] - fx, buf[1, j] - fy, buf[2, j], buf[3, j], buf[4, j], buf[5, j]
        hx, hy, hz, L, M, N, t, k2, edge = surface_hit_own(px, py, pz, L, M, N, 0.0, 0.0, zfront, c, fx, fy, rot, k,
                                                           g[G_CX, j], g[G_CY, j], ax0, ay0, invp, p, ncols, nrows, lat)
        g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j], g[G_T, j] = hx, hy, hz, L, M, N, t
        live = (buf[6, j] > 0.0) & (t == t)
        moved = k2 != k
        flag[j] = live & (moved | (edge < g[G_MF, j]))
        cflag[j] = live & (moved | (edge < g[G_MR, j]))
        rx, ry = hx - g[G_DX, j], hy - g[G_DY, j]
        c2 = g[G_C2, j]
        rho2 = rx * rx + ry * ry
        arg = 1.0 - c2 * c2 * rho2
        corner_of[j] = not ((arg >= 0.0) & (g[G_ZR, j] + c2 * rho2 / (1.0 + math.sqrt(max(arg, 0.0))) > hz))


@jit_inline
def rear_sag(m, buf, s, tab, rot, g, kk, flag, corner_of, lat):
    """Pass C' in sag-intersection mode (branch-free): lens kk's rear hit; flag live non-corner rays whose
    hit is in another cell or within the rear margin of the cell's edge."""
    ax0, ay0, invp, p, ncols, nrows = s[S_AX0], s[S_AY0], s[S_INVP], s[S_P], s[S_COLS], s[S_ROWS]
    for j in range(m):
        x, y, z, L, M, N = buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j]
        fx, fy, vx, vy, c2, vz, k = g[G_FX, j], g[G_FY, j], g[G_DX, j], g[G_DY, j], g[G_C2, j], g[G_ZR, j], kk[j]
        hx, hy, hz, L, M, N, t, k2, edge = surface_hit_own(x - fx, y - fy, z, L, M, N, vx, vy, vz, c2, fx, fy, rot, k,
                                                           g[G_CX, j], g[G_CY, j], ax0, ay0, invp, p, ncols, nrows, lat)
        g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j], g[G_T, j] = hx, hy, hz, L, M, N, t
        live = (buf[6, j] > 0.0) & (not corner_of[j]) & (t == t)
        flag[j] = live & ((k2 != k) | (edge < g[G_MR, j]))


@jit_inline
def grot_entries(grot):
    """The MLA's global rotation, nine entries (zeros where there is none)."""
    g00 = g01 = g02 = g10 = g11 = g12 = g20 = g21 = g22 = 0.0
    if grot is not None:
        g00, g01, g02, g10, g11, g12, g20, g21, g22 = (grot[0, 0], grot[0, 1], grot[0, 2], grot[1, 0], grot[1, 1],
                                                       grot[1, 2], grot[2, 0], grot[2, 1], grot[2, 2])
    return g00, g01, g02, g10, g11, g12, g20, g21, g22


@jit_inline
def pass_enter(m, buf, s, tab, grot, g, kk, lat, centres):
    """Pass A: into the MLA frame, onto the front plane, which cell (`centres`, hex sag-intersection: and
    its design centre, for own_edge, computed rather than gathered); the black matrix; gather the lenses."""
    zfront, shx, shy, zmla, p = s[S_ZFRONT], s[S_SHIFTX], s[S_SHIFTY], s[S_ZMLA], s[S_P]
    ax0, ay0, invp, ncols, nrows = s[S_AX0], s[S_AY0], s[S_INVP], s[S_COLS], s[S_ROWS]
    g00, g01, g02, g10, g11, g12, g20, g21, g22 = grot_entries(grot)
    for j in range(m):
        x, y, z, L, M, N, w = buf[0, j] - shx, buf[1, j] - shy, buf[2, j] - zmla, buf[3, j], buf[4, j], buf[5, j], buf[6, j]
        if grot is not None:
            x, y, z = rot_t(g00, g01, g02, g10, g11, g12, g20, g21, g22, x, y, z)
            L, M, N = rot_t(g00, g01, g02, g10, g11, g12, g20, g21, g22, L, M, N)
        t = (zfront - z) / N
        x += t * L
        y += t * M
        z += t * N
        kf = cell_f(x, y, ax0, ay0, invp, ncols, nrows, lat)
        if centres:
            g[G_CX, j], g[G_CY, j] = cell_centre(x, y, ax0, ay0, invp, p, lat)
        alive = (w > 0.0) & (kf >= 0.0)  # w > 0 also rejects NaN
        kk[j] = np.int32(kf) if alive else np.int32(0)  # int32: converts four at a time on AVX2
        buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j] = x, y, z, L, M, N
        buf[6, j] = w if alive else 0.0
    if s[S_HALFBM] > 0.0:
        black_matrix(m, buf, s, lat)
    for j in range(m):
        gather(j, kk[j], tab, g)


@jit_inline
def pass_front_grid(m, buf, s, tab, rot, g, kk, flag, lat):
    """Pass B (grid): front surface of the cell's lens; re-trace hits that fall in another cell."""
    zfront, ax0, ay0, invp, ncols, nrows = s[S_ZFRONT], s[S_AX0], s[S_AY0], s[S_INVP], s[S_COLS], s[S_ROWS]
    for j in range(m):
        fx, fy, c = g[G_FX, j], g[G_FY, j], g[G_C1, j]
        px, py, pz, L, M, N = buf[0, j] - fx, buf[1, j] - fy, buf[2, j], buf[3, j], buf[4, j], buf[5, j]
        hx, hy, hz, L, M, N, t, k2 = surface_hit(px, py, pz, L, M, N, 0.0, 0.0, zfront, c, fx, fy, rot, kk[j],
                                                 ax0, ay0, invp, ncols, nrows, lat)
        g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j], g[G_T, j] = hx, hy, hz, L, M, N, t
        flag[j] = (buf[6, j] > 0.0) & (t == t) & (k2 >= 0.0) & (k2 != kk[j])
    retrace_neighbours(m, flag, kk, buf, g, tab, rot, s, False, lat)


@jit_inline
def pass_front_refract(m, buf, s, rot, clear, fres, n_mla, mu_in, g, kk, corner_of, sag):
    """Pass C: corner test (grid: lens kk's rear; sag: corner_of, from corners_sag), front refraction,
    back to the MLA frame."""
    zfront = s[S_ZFRONT]
    r00 = r01 = r02 = r10 = r11 = r12 = r20 = r21 = r22 = 0.0
    for j in range(m):
        w = buf[6, j]
        hx, hy, hz, lL, lM, lN, t = g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j], g[G_T, j]
        fx, fy, vx, vy, c1, c2, vz = g[G_FX, j], g[G_FY, j], g[G_DX, j], g[G_DY, j], g[G_C1, j], g[G_C2, j], g[G_ZR, j]
        rx, ry = hx - vx, hy - vy
        rho2 = rx * rx + ry * ry
        arg = 1.0 - c2 * c2 * rho2
        corner = not ((arg >= 0.0) & (vz + c2 * rho2 / (1.0 + math.sqrt(max(arg, 0.0))) > hz))
        corner = corner_of[j] if sag else corner
        nL, nM, nN, tr = refract(lL, lM, lN, c1 * hx, c1 * hy, c1 * (hz - zfront) - 1.0, mu_in, fres, 1.0, n_mla)
        alive = (w > 0.0) & (t == t) & (clear | (not corner)) & (corner | (tr >= 0.0))
        w = w if corner else w * tr
        nL = lL if corner else nL
        nM = lM if corner else nM
        nN = lN if corner else nN
        if rot is not None:
            k = kk[j]
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = rot_of(rot, k)
            hx, hy, hz = rot_n(r00, r01, r02, r10, r11, r12, r20, r21, r22, hx, hy, hz)
            nL, nM, nN = rot_n(r00, r01, r02, r10, r11, r12, r20, r21, r22, nL, nM, nN)
        x, y, z, L, M, N = hx + fx, hy + fy, hz, nL, nM, nN
        buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j] = x, y, z, L, M, N
        buf[6, j] = w if alive else 0.0
        corner_of[j] = corner


@jit_inline
def pass_rear_grid(m, buf, s, tab, rot, g, kk, flag, corner_of, lat, retrace):
    """Pass C' (grid): rear surface of the same lens; re-trace hits that fall in another cell (not for
    circle apertures, `retrace` False: the circle's lens, front and rear)."""
    ax0, ay0, invp, ncols, nrows = s[S_AX0], s[S_AY0], s[S_INVP], s[S_COLS], s[S_ROWS]
    for j in range(m):
        x, y, z, L, M, N = buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j]
        fx, fy, vx, vy, c2, vz = g[G_FX, j], g[G_FY, j], g[G_DX, j], g[G_DY, j], g[G_C2, j], g[G_ZR, j]
        px, py, pz = x - fx, y - fy, z
        hx, hy, hz, L, M, N, t, k2 = surface_hit(px, py, pz, L, M, N, vx, vy, vz, c2, fx, fy, rot, kk[j],
                                                 ax0, ay0, invp, ncols, nrows, lat)
        g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j], g[G_T, j] = hx, hy, hz, L, M, N, t
        flag[j] = retrace & (buf[6, j] > 0.0) & (not corner_of[j]) & (t == t) & (k2 >= 0.0) & (k2 != kk[j])
    if retrace:
        retrace_neighbours(m, flag, kk, buf, g, tab, rot, s, True, lat)


@jit_inline
def pass_leave(m, buf, s, rot, grot, fres, n_mla, g, kk, corner_of, rows, cols, wts, nout, box):
    """Passes D (rear refraction, corners go on straight), D' (back to the camera frame, onto the sensor,
    which pixel) and E (append the hits in ray order, grow the bounding box). Returns the hit count."""
    shx, shy, zmla, zsens = s[S_SHIFTX], s[S_SHIFTY], s[S_ZMLA], s[S_ZSENS]
    sx0, sy0, invpix, width, height = s[S_SX0], s[S_SY0], s[S_INVPIX], s[S_W], s[S_H]
    g00, g01, g02, g10, g11, g12, g20, g21, g22 = grot_entries(grot)
    r00 = r01 = r02 = r10 = r11 = r12 = r20 = r21 = r22 = 0.0
    # --- D: rear refraction (corners go on straight) ---
    for j in range(m):
        w, corner = buf[6, j], corner_of[j]
        hx, hy, hz, lL, lM, lN, t = g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j], g[G_T, j]
        fx, fy, vx, vy, c, vz = g[G_FX, j], g[G_FY, j], g[G_DX, j], g[G_DY, j], g[G_C2, j], g[G_ZR, j]
        nL, nM, nN, tr = refract(lL, lM, lN, c * (hx - vx), c * (hy - vy), c * (hz - vz) - 1.0, n_mla, fres, n_mla, 1.0)
        if rot is not None:
            k = kk[j]
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = rot_of(rot, k)
            hx, hy, hz = rot_n(r00, r01, r02, r10, r11, r12, r20, r21, r22, hx, hy, hz)
            nL, nM, nN = rot_n(r00, r01, r02, r10, r11, r12, r20, r21, r22, nL, nM, nN)
        bx, by, bz, bL, bM, bN = buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j]
        alive = (w > 0.0) & (corner | ((t == t) & (tr >= 0.0)))
        w = w if corner else w * tr
        x = bx if corner else hx + fx
        y = by if corner else hy + fy
        z = bz if corner else hz
        L = bL if corner else nL
        M = bM if corner else nM
        N = bN if corner else nN
        buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j] = x, y, z, L, M, N
        buf[6, j] = w if alive else 0.0
    # --- D': back to the camera frame, onto the sensor, which pixel ---
    for j in range(m):
        x, y, z, L, M, N, w = buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j], buf[6, j]
        if grot is not None:
            x, y, z = rot_n(g00, g01, g02, g10, g11, g12, g20, g21, g22, x, y, z)
            L, M, N = rot_n(g00, g01, g02, g10, g11, g12, g20, g21, g22, L, M, N)
        x = x + shx
        y = y + shy
        z = z + zmla
        t = (zsens - z) / N
        x += t * L
        y += t * M
        col = np.floor((x - sx0) * invpix)
        row = np.floor((y - sy0) * invpix)
        landed = (w > 0.0) & (col >= 0.0) & (col < width) & (row >= 0.0) & (row < height)
        g[G_ROW, j] = row if landed else -1.0
        g[G_COL, j] = col if landed else 0.0
    # --- E: append the hits (in ray order) and grow the bounding box; branch-free (7 % are lost at random) ---
    r0, r1, c0, c1 = box[0], box[1], box[2], box[3]
    for j in range(m):
        row = g[G_ROW, j]
        hit = row >= 0.0
        r, c = np.int32(row), np.int32(g[G_COL, j])
        rows[nout], cols[nout], wts[nout] = r, c, buf[6, j]  # overwritten by the next ray unless it landed
        nout += 1 if hit else 0
        r0 = min(r0, r) if hit else r0
        r1 = max(r1, r) if hit else r1
        c0 = min(c0, c) if hit else c0
        c1 = max(c1, c) if hit else c1
    box[0], box[1], box[2], box[3] = r0, r1, c0, c1
    return nout


@jit_inline
def front_circle(m, buf, s, tab, rot, g, kk, flag, corner_of, clear, lat, circ):
    """Pass B (circle apertures, branch-free): lens kk's front hit; gap (flag) where it lies outside kk's
    circle, doubted (scanned by retrace_circle) where it lies within radius + reach of its cell's design
    centre (`circ`: design centres, raytrace.MicrolensArray._hit_circle); the corner test with lens kk's
    rear (corner_of). Pruned (S_PRUNE), a live gap hit is doubted (g[G_MR] = 1) only off the array, in
    another cell than its lens', or within its cell's clearance (g[G_MF]: circ[C_CLEAR]) of the cell's
    edge: elsewhere no neighbour's circle can hold it, and lens kk's own circle does not."""
    zfront, ax0, ay0, invp, p, ncols, nrows = s[S_ZFRONT], s[S_AX0], s[S_AY0], s[S_INVP], s[S_P], s[S_COLS], s[S_ROWS]
    r2 = s[S_RCIRC2]
    exhaustive = s[S_PRUNE] == 0.0
    for j in range(m):
        fx, fy, c, k = g[G_FX, j], g[G_FY, j], g[G_C1, j], kk[j]
        px, py, pz, L, M, N = buf[0, j] - fx, buf[1, j] - fy, buf[2, j], buf[3, j], buf[4, j], buf[5, j]
        hx, hy, hz, L, M, N, t, k2, edge = surface_hit_edge(px, py, pz, L, M, N, 0.0, 0.0, zfront, c, fx, fy, rot, k,
                                                            ax0, ay0, invp, p, ncols, nrows, lat)
        g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j], g[G_T, j] = hx, hy, hz, L, M, N, t
        gap = not (hx * hx + hy * hy <= r2)
        flag[j] = gap
        doubt = gap & (buf[6, j] > 0.0) & (t == t) & (exhaustive | (k2 != k) | (edge <= g[G_MF, j]))
        g[G_MR, j] = 1.0 if doubt else 0.0
        g[G_ROW, j] = k2  # the hit's cell, for retrace_circle
        rx, ry = hx - g[G_DX, j], hy - g[G_DY, j]
        c2 = g[G_C2, j]
        rho2 = rx * rx + ry * ry
        arg = 1.0 - c2 * c2 * rho2
        corner_of[j] = not ((arg >= 0.0) & (g[G_ZR, j] + c2 * rho2 / (1.0 + math.sqrt(max(arg, 0.0))) > hz))


@jit_inline
def retrace_circle(m, flag, kk, buf, g, tab, rot, s, lat, circ, corner_of):
    """Doubted gap rays (g[G_MR], front_circle) near a circle's reach: the first candidate around the hit's
    cell whose circle holds the ray's hit on its own front sphere takes the ray (flag cleared); others stay
    in the gap. Scalar."""
    rows, cols, r2 = int(s[S_ROWS]), int(s[S_COLS]), s[S_RCIRC2]
    for j in range(m):
        if g[G_MR, j] != 0.0:
            gx, gy = hit_xy(kk[j], g[G_HX, j], g[G_HY, j], g[G_HZ, j], tab, rot)
            k2 = int(g[G_ROW, j])
            if k2 >= 0:
                ex, ey = gx - circ[C_GX, k2], gy - circ[C_GY, k2]
                if not (ex * ex + ey * ey <= circ[C_REACH2, k2]):
                    continue
            row0, col0 = centre_cell(gx, gy, s, lat)
            for i in range(9 if lat is None else 7):
                rr, cc = candidate(i, row0, col0, lat)
                if rr < 0 or rr >= rows or cc < 0 or cc >= cols:
                    continue
                kc = rr * cols + cc
                hx, hy, hz, lL, lM, lN, t = lens_surface(kc, buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j],
                                                         buf[5, j], False, tab, rot, s[S_ZFRONT])
                if t == t and hx * hx + hy * hy <= r2:
                    kk[j] = kc
                    gather(j, kc, tab, g)
                    g[G_HX, j], g[G_HY, j], g[G_HZ, j], g[G_LL, j], g[G_LM, j], g[G_LN, j], g[G_T, j] = hx, hy, hz, lL, lM, lN, t
                    rx, ry = hx - tab[2, kc], hy - tab[3, kc]
                    c2 = tab[5, kc]
                    rho2 = rx * rx + ry * ry
                    arg = 1.0 - c2 * c2 * rho2
                    corner_of[j] = not ((arg >= 0.0) & (tab[6, kc] + c2 * rho2 / (1.0 + math.sqrt(max(arg, 0.0))) > hz))
                    flag[j] = False
                    break


@jit_inline
def circle_fate(m, buf, s, clear, g, flag, corner_of):
    """Circle apertures: a corner or gap ray (flag) goes on undeviated (corner_of) where clear, and is
    absorbed where opaque (`mla.corners`, `mla.gap`)."""
    clear_gap = s[S_CLEARGAP] != 0.0
    for j in range(m):
        gap = flag[j]
        corner = corner_of[j] & (not gap)  # the gap is flat substrate: no corner there
        absorbed = (corner & (not clear)) | (gap & (not clear_gap))
        buf[6, j] = 0.0 if absorbed else buf[6, j]
        corner_of[j] = corner | gap


@jit_inline
def stage2_block(m, buf, s, tab, rot, grot, clear, fres, n_mla, mu_in, g, kk, flag, corner_of, rows, cols, wts,
                 nout, box, lat, circ):
    """Stage 2 for one block, grid boundaries: MLA (per-lens errors, neighbour re-trace) -> sensor pixel,
    appending hits.

    Done in passes over the block, each branch-free over rays so that it vectorizes (the ray-by-ray
    version was bound by the latency of its chain of divisions and square roots); the rare re-trace near
    cell edges is a scalar pass of its own. Operations are those of raytrace.MicrolensArray, in the same
    order, so both engines agree to rounding."""
    rotated = s[S_GROT] != 0.0
    if rotated:
        pass_enter(m, buf, s, tab, grot, g, kk, lat, False)
    else:
        pass_enter(m, buf, s, tab, None, g, kk, lat, False)
    if circ is None:
        pass_front_grid(m, buf, s, tab, rot, g, kk, flag, lat)
        pass_front_refract(m, buf, s, rot, clear, fres, n_mla, mu_in, g, kk, corner_of, False)
    else:  # circle apertures: the lens whose circle holds the hit; gaps and corners from front_circle
        for j in range(m):  # a loop of its own, as gather: an indexed load keeps a pass from vectorizing
            g[G_MF, j] = circ[C_CLEAR, kk[j]]
        front_circle(m, buf, s, tab, rot, g, kk, flag, corner_of, clear, lat, circ)
        retrace_circle(m, flag, kk, buf, g, tab, rot, s, lat, circ, corner_of)
        circle_fate(m, buf, s, clear, g, flag, corner_of)
        pass_front_refract(m, buf, s, rot, True, fres, n_mla, mu_in, g, kk, corner_of, True)
    pass_rear_grid(m, buf, s, tab, rot, g, kk, flag, corner_of, lat, circ is None)
    if rotated:
        return pass_leave(m, buf, s, rot, grot, fres, n_mla, g, kk, corner_of, rows, cols, wts, nout, box)
    return pass_leave(m, buf, s, rot, None, fres, n_mla, g, kk, corner_of, rows, cols, wts, nout, box)


@jit_inline
def stage2_block_sag(m, buf, s, tab, rot, grot, clear, fres, n_mla, mu_in, g, kk, flag, corner_of, rows, cols, wts,
                     nout, box, cflag, margins, lims, lat):
    """Stage 2 for one block, sag-intersection boundaries: as stage2_block, with passes B and C' that also
    flag hits within a per-cell margin of the edge (front_sag, rear_sag) for the 3 x 3 neighbour pass
    (retrace_sag), and corners from the union of the rear regions (corners_sag). A kernel of its own
    (kernel_sag), so that grid kernels compile none of it."""
    rotated = s[S_GROT] != 0.0
    if rotated:
        pass_enter(m, buf, s, tab, grot, g, kk, lat, lat is not None)  # hex: own_edge's design centres
    else:
        pass_enter(m, buf, s, tab, None, g, kk, lat, lat is not None)
    for j in range(m):  # in a loop of its own, as gather: an indexed load keeps a pass from vectorizing
        k = kk[j]
        g[G_MF, j], g[G_MR, j] = margins[T_MARGIN_FRONT, k], margins[T_MARGIN_REAR, k]
    front_sag(m, buf, s, tab, rot, g, kk, flag, cflag, corner_of, lat)
    retrace_sag(m, flag, kk, buf, g, tab, rot, s, False, cflag, margins, lims, lat, corner_of)
    corners_sag(m, cflag, kk, g, tab, rot, s, corner_of, lat)
    pass_front_refract(m, buf, s, rot, clear, fres, n_mla, mu_in, g, kk, corner_of, True)
    rear_sag(m, buf, s, tab, rot, g, kk, flag, corner_of, lat)
    retrace_sag(m, flag, kk, buf, g, tab, rot, s, True, cflag, margins, lims, lat, corner_of)
    if rotated:
        return pass_leave(m, buf, s, rot, grot, fres, n_mla, g, kk, corner_of, rows, cols, wts, nout, box)
    return pass_leave(m, buf, s, rot, None, fres, n_mla, g, kk, corner_of, rows, cols, wts, nout, box)




@jit_inline
def kernel_settings(s, key):
    """What both kernels read from the settings: mode, Fresnel, clear corners, the MLA's index, whether the
    low-discrepancy sampler is on, and its scramble seeds, cell shifts and room for direction tables
    (empty placeholders of the same types for the random sampler)."""
    sobol = s[S_SOBOL] != 0.0
    if sobol:
        seeds, shifts, jtab = sobol_tables(s, key)
    else:
        seeds, shifts, jtab = np.zeros(4, np.uint64), np.zeros((1, 4), np.uint64), np.zeros((1, 4), np.uint64)
    return int(s[S_MODE]), s[S_FRES] != 0.0, s[S_CLEAR] != 0.0, s[S_NMLA], sobol, seeds, shifts, jtab


@jit_inline
def block_scratch():
    """One block's scratch arrays: rays, per-ray table, lens index, re-trace and corner flags, sampler cells."""
    return (np.empty((9, BLOCK)), np.empty((G_COUNT, BLOCK)), np.empty(BLOCK, np.int32), np.empty(BLOCK, np.bool_),
            np.empty(BLOCK, np.bool_), np.empty(BLOCK, np.int64), np.empty(BLOCK, np.int64))


@jit
def kernel(s, key, count, tab, rot, grot, texture, shift_coef, rows, cols, wts, box, lat, circ):
    """Trace `count` rays drawn with `key` (grid boundaries, or circle apertures where `circ` (the design
    centres) is not None; hex cells where `lat` is not None); appends the (row, col, weight) of those that
    landed, in ray order, grows box = [row min, row max, col min, col max] and returns how many landed."""
    mode, fres, clear, n_mla, sobol, seeds, shifts, jtab = kernel_settings(s, key)
    buf, g, kk, flag, corner_of, ia, icf = block_scratch()
    nout = 0
    for start in range(0, count, BLOCK):
        m = stage1_block(start, min(BLOCK, count - start), mode, s, key, buf, fres, texture, g, sobol, shift_coef,
                         seeds, shifts, jtab, ia, icf, lat)
        nout = stage2_block(m, buf, s, tab, rot, grot, clear, fres, n_mla, 1.0 / n_mla, g, kk, flag, corner_of,
                            rows, cols, wts, nout, box, lat, circ)
    return nout


@jit
def kernel_sag(s, key, count, tab, rot, grot, texture, shift_coef, rows, cols, wts, box, margins, lims, lat):
    """As kernel (the same loop), with sag-intersection boundaries (`margins`: per-lens front and rear
    margins, mm, and design centres; `lims`: per-pair limits (pair_limits), [front / rear, lens, candidate])."""
    cflag = np.empty(BLOCK, np.bool_)
    mode, fres, clear, n_mla, sobol, seeds, shifts, jtab = kernel_settings(s, key)
    buf, g, kk, flag, corner_of, ia, icf = block_scratch()
    nout = 0
    for start in range(0, count, BLOCK):
        m = stage1_block(start, min(BLOCK, count - start), mode, s, key, buf, fres, texture, g, sobol, shift_coef,
                         seeds, shifts, jtab, ia, icf, lat)
        nout = stage2_block_sag(m, buf, s, tab, rot, grot, clear, fres, n_mla, 1.0 / n_mla, g, kk, flag, corner_of,
                                rows, cols, wts, nout, box, cflag, margins, lims, lat)
    return nout


@jit
def bin_hits(rows, cols, wts, n, box):
    """Sum the weights per pixel over the hits' bounding box, in hit order (as np.bincount would)."""
    if n == 0:
        return np.zeros((0, 0))
    r0, c0 = box[0], box[2]
    patch = np.zeros((box[1] - r0 + 1, box[3] - c0 + 1))
    for i in range(n):
        patch[rows[i] - r0, cols[i] - c0] += wts[i]
    return patch
