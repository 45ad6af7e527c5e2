"""The compiled tracer's geometry: spheres, refraction, the lattice's cells and each lens' frame, for one ray.

Scalar helpers the kernels (raytrace_kernels) inline into their vectorized passes, each the twin of a
NumPy operation of mlaqc.optics.raytrace. What differs between square and hex cells is chosen when Numba
types the call (overloads on `lat`), not by a branch inside a pass.
"""

from __future__ import annotations

import math

import numpy as np

from mlaqc.optics.kernel_jit import AVAILABLE, jit, jit_inline
from mlaqc.optics.kernel_layout import S_AX0, S_AY0, S_COLS, S_INVP, S_ROWS
from mlaqc.optics.lattice import SQRT3_2
from mlaqc.optics.raytrace import INV_ROW_PAIR_HEX


@jit_inline
def sphere_t(px, py, pz, L, M, N, c):
    """As raytrace.intersect_sphere, for one ray (position relative to the vertex); NaN on a miss."""
    b = c * (px * L + py * M + pz * N) - N
    cc = c * (px * px + py * py + pz * pz) - 2.0 * pz
    disc = b * b - c * cc
    t = -cc / (b + math.copysign(math.sqrt(max(disc, 0.0)), b))
    return t if disc >= 0.0 else math.nan  # a select, not a branch


@jit_inline
def refract(L, M, N, nx, ny, nz, mu, fresnel, n1, n2):
    """As raytrace.refract + fresnel_transmittance; transmission -1 flags total internal reflection."""
    cos_i = -(nx * L + ny * M + nz * N)
    flip = -1.0 if cos_i < 0.0 else 1.0
    cos_i = cos_i * flip
    k = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
    cos_t = math.sqrt(max(k, 0.0))
    g = (mu * cos_i - cos_t) * flip
    tr = 1.0
    if fresnel:
        a = n1 * cos_i + n2 * cos_t
        b = n1 * cos_t + n2 * cos_i
        a2, b2 = a * a, b * b
        tr = (2.0 * n1 * n2) * cos_i * cos_t * (a2 + b2) / (a2 * b2)
    return mu * L + g * nx, mu * M + g * ny, mu * N + g * nz, tr if k >= 0.0 else -1.0


@jit_inline
def main_surface(x, y, z, L, M, N, zv, c, n1, n2, mu, rim2, fresnel):
    """Branch-free main-lens surface: a miss, vignetting or total reflection gives transmission 0."""
    t = sphere_t(x, y, z - zv, L, M, N, c)
    x += t * L
    y += t * M
    z += t * N
    L, M, N, tr = refract(L, M, N, c * x, c * y, c * (z - zv) - 1.0, mu, fresnel, n1, n2)
    return x, y, z, L, M, N, tr if (x * x + y * y <= rim2 and tr >= 0.0) else 0.0


@jit_inline
def hex_locate(u, v):
    """As raytrace.hex_cell, for one point (lattice units from U(1,1)): row, column (floats) and the
    offset (du, dv) from that lens' centre, in pitches."""
    ja = np.floor(v * INV_ROW_PAIR_HEX + 0.5)
    jb = np.floor(v * INV_ROW_PAIR_HEX)
    ca, cb = np.floor(u + 0.5), np.floor(u)
    ra, rb = 2.0 * ja, 2.0 * jb + 1.0
    dua, dva = u - ca, v - ra * SQRT3_2
    dub, dvb = u - (cb + 0.5), v - rb * SQRT3_2
    take = dub * dub + dvb * dvb < dua * dua + dva * dva
    return (rb if take else ra), (cb if take else ca), (dub if take else dua), (dvb if take else dva)


@jit_inline
def hex_edge(du, dv):
    """As raytrace.hex_edge: distance (pitches) from an offset in a hexagonal cell to its nearest side."""
    a = abs(du)
    b = abs(0.5 * du + SQRT3_2 * dv)
    c = abs(0.5 * du - SQRT3_2 * dv)
    mx = a if a > b else b
    mx = mx if mx > c else c
    return 0.5 - mx


# Helpers that differ between square and hex cells, chosen when Numba types the call from `lat` (None:
# square): a branch on `lat` inside a pass' loop, even one that can never be taken, keeps LLVM from
# vectorizing that loop (measured: the hex sag-intersection passes ran scalar, 3x slower). Without Numba
# the stubs branch at run time.
def _cell_square(u, v, lat):
    return np.floor(v), np.floor(u)  # np.floor stays a float: math.floor's int64 does not vectorize on AVX2


def _cell_hex(u, v, lat):
    row, col, _, _ = hex_locate(u, v)
    return row, col


def lattice_cell(u, v, lat):
    """Row and column (floats) of the cell holding lattice point (u, v): u, v in pitches from the first
    cell's corner (square) or from U(1,1)'s centre (hex)."""
    return _cell_square(u, v, lat) if lat is None else _cell_hex(u, v, lat)


def _cell_edge_square(u, v, ncols, nrows, lat):
    col = np.floor(u)
    row = np.floor(v)
    fu = u - col
    fv = v - row
    eu = fu if fu < 1.0 - fu else 1.0 - fu  # selects: the builtin min's NaN handling does not vectorize
    ev = fv if fv < 1.0 - fv else 1.0 - fv
    on = (col >= 0.0) & (col < ncols) & (row >= 0.0) & (row < nrows)
    return (row * ncols + col if on else -1.0), (eu if eu < ev else ev)


def _cell_edge_hex(u, v, ncols, nrows, lat):
    row, col, du, dv = hex_locate(u, v)
    on = (col >= 0.0) & (col < ncols) & (row >= 0.0) & (row < nrows)
    return (row * ncols + col if on else -1.0), hex_edge(du, dv)


def _own_edge_square(x, y, cx, cy, ax0, ay0, invp, ncols, nrows, kf, lat):
    return cell_edge((x - ax0) * invp, (y - ay0) * invp, ncols, nrows, lat)


def _own_edge_hex(x, y, cx, cy, ax0, ay0, invp, ncols, nrows, kf, lat):
    e = hex_edge((x - cx) * invp, (y - cy) * invp)
    return (kf if e >= 0.0 else -1.0), e


def own_edge(x, y, cx, cy, ax0, ay0, invp, ncols, nrows, kf, lat):
    """As cell_edge for MLA point (x, y) (mm) of lens kf's ray: square cells by the lattice; hex cells from
    the offset to lens kf's design centre (cx, cy): kf where inside its hexagon, -1.0 outside (in another
    cell, or off the array), and the distance (pitches) from its nearest side, no cell lookup."""
    if lat is None:
        return _own_edge_square(x, y, cx, cy, ax0, ay0, invp, ncols, nrows, kf, lat)
    return _own_edge_hex(x, y, cx, cy, ax0, ay0, invp, ncols, nrows, kf, lat)


def cell_edge(u, v, ncols, nrows, lat):
    """Flat cell index (float, -1.0 off the array) of lattice point (u, v) and its distance (pitches) from
    the cell's nearest edge."""
    return _cell_edge_square(u, v, ncols, nrows, lat) if lat is None else _cell_edge_hex(u, v, ncols, nrows, lat)


def _centre_square(x, y, ax0, ay0, invp, p, lat):
    return 0.0, 0.0


def _centre_hex(x, y, ax0, ay0, invp, p, lat):
    _, _, du, dv = hex_locate((x - ax0) * invp, (y - ay0) * invp)
    return x - du * p, y - dv * p


def cell_centre(x, y, ax0, ay0, invp, p, lat):
    """Hex: the design centre (mm) of the cell holding MLA point (x, y), from the point's offset in it
    (the look-up cell_f makes, on the same operands, for LLVM to share); square: unused zeros."""
    return _centre_square(x, y, ax0, ay0, invp, p, lat) if lat is None else _centre_hex(x, y, ax0, ay0, invp, p, lat)


def _black_square(u, v, p, hw, lat):
    fu = u - np.floor(u)
    fv = v - np.floor(v)
    return (p * min(fu, 1.0 - fu) < hw) | (p * min(fv, 1.0 - fv) < hw)


def _black_hex(u, v, p, hw, lat):
    _, _, du, dv = hex_locate(u, v)
    return p * hex_edge(du, dv) < hw


def under_black_matrix(u, v, p, hw, lat):
    """Lattice point (u, v) lies within hw (mm) of its cell's edge (pitch p mm)."""
    return _black_square(u, v, p, hw, lat) if lat is None else _black_hex(u, v, p, hw, lat)


if AVAILABLE:
    from numba import types
    from numba.extending import overload

    _TYPED = dict(inline="always", jit_options=dict(error_model="numpy", fastmath={"contract"}))
    # the overloads only forward to inline-compiled helpers: selects written in an overload's own body
    # trip a Numba SSA check (NumbaIRAssumptionWarning) when it is inlined
    _cs, _ch, _es, _eh = (jit_inline(f) for f in (_cell_square, _cell_hex, _cell_edge_square, _cell_edge_hex))
    _bs, _bh = jit_inline(_black_square), jit_inline(_black_hex)
    _ctrs, _ctrh = jit_inline(_centre_square), jit_inline(_centre_hex)

    @overload(cell_centre, **_TYPED)
    def _cell_centre_typed(x, y, ax0, ay0, invp, p, lat):
        if isinstance(lat, types.NoneType):
            return lambda x, y, ax0, ay0, invp, p, lat: _ctrs(x, y, ax0, ay0, invp, p, lat)
        return lambda x, y, ax0, ay0, invp, p, lat: _ctrh(x, y, ax0, ay0, invp, p, lat)
    _os, _oh = jit_inline(_own_edge_square), jit_inline(_own_edge_hex)

    @overload(own_edge, **_TYPED)
    def _own_edge_typed(x, y, cx, cy, ax0, ay0, invp, ncols, nrows, kf, lat):
        if isinstance(lat, types.NoneType):
            return lambda x, y, cx, cy, ax0, ay0, invp, ncols, nrows, kf, lat: _os(x, y, cx, cy, ax0, ay0, invp, ncols, nrows, kf, lat)
        return lambda x, y, cx, cy, ax0, ay0, invp, ncols, nrows, kf, lat: _oh(x, y, cx, cy, ax0, ay0, invp, ncols, nrows, kf, lat)

    @overload(lattice_cell, **_TYPED)
    def _lattice_cell_typed(u, v, lat):
        if isinstance(lat, types.NoneType):
            return lambda u, v, lat: _cs(u, v, lat)
        return lambda u, v, lat: _ch(u, v, lat)

    @overload(cell_edge, **_TYPED)
    def _cell_edge_typed(u, v, ncols, nrows, lat):
        if isinstance(lat, types.NoneType):
            return lambda u, v, ncols, nrows, lat: _es(u, v, ncols, nrows, lat)
        return lambda u, v, ncols, nrows, lat: _eh(u, v, ncols, nrows, lat)

    @overload(under_black_matrix, **_TYPED)
    def _black_typed(u, v, p, hw, lat):
        if isinstance(lat, types.NoneType):
            return lambda u, v, p, hw, lat: _bs(u, v, p, hw, lat)
        return lambda u, v, p, hw, lat: _bh(u, v, p, hw, lat)


@jit_inline
def row_col(x, y, s, lat):
    """Row and column (ints) of the cell holding MLA-frame point (x, y), on the array or off it."""
    if lat is None:
        return math.floor((y - s[S_AY0]) * s[S_INVP]), math.floor((x - s[S_AX0]) * s[S_INVP])
    rf, cf, _, _ = hex_locate((x - s[S_AX0]) * s[S_INVP], (y - s[S_AY0]) * s[S_INVP])
    return int(rf), int(cf)


@jit_inline
def cell(x, y, s, lat):
    """Flat index of the lens whose cell holds MLA-frame point (x, y); -1 off the array."""
    row, col = row_col(x, y, s, lat)
    if col >= 0 and col < s[S_COLS] and row >= 0 and row < s[S_ROWS]:
        return int(row * s[S_COLS] + col)
    return -1


@jit_inline
def candidate(i, row0, col0, lat):
    """Candidate i of the lenses around cell (row0, col0), as raytrace.MicrolensArray.neighbours: square
    the 3 x 3 cells row-major (i < 9), hex the cell then its 6 neighbours (i < 7, lattice order)."""
    if lat is None:
        return row0 + i // 3 - 1, col0 + i % 3 - 1
    lo = -1 if row0 % 2 == 0 else 0
    if i == 0:
        return row0, col0
    if i <= 2:
        return row0, col0 + 2 * i - 3
    return row0 + (-1 if i <= 4 else 1), col0 + lo + (i - 3) % 2


@jit_inline
def to_lens(k, x, y, z, L, M, N, tab, rot):
    px, py, pz = x - tab[0, k], y - tab[1, k], z
    if rot is None:
        return px, py, pz, L, M, N
    r = rot[k]
    return (r[0, 0] * px + r[1, 0] * py + r[2, 0] * pz, r[0, 1] * px + r[1, 1] * py + r[2, 1] * pz,
            r[0, 2] * px + r[1, 2] * py + r[2, 2] * pz, r[0, 0] * L + r[1, 0] * M + r[2, 0] * N,
            r[0, 1] * L + r[1, 1] * M + r[2, 1] * N, r[0, 2] * L + r[1, 2] * M + r[2, 2] * N)


@jit_inline
def from_lens(k, px, py, pz, L, M, N, tab, rot):
    if rot is not None:
        r = rot[k]
        px, py, pz = (r[0, 0] * px + r[0, 1] * py + r[0, 2] * pz, r[1, 0] * px + r[1, 1] * py + r[1, 2] * pz,
                      r[2, 0] * px + r[2, 1] * py + r[2, 2] * pz)
        L, M, N = (r[0, 0] * L + r[0, 1] * M + r[0, 2] * N, r[1, 0] * L + r[1, 1] * M + r[1, 2] * N,
                   r[2, 0] * L + r[2, 1] * M + r[2, 2] * N)
    return px + tab[0, k], py + tab[1, k], pz, L, M, N


@jit_inline
def lens_surface(k, x, y, z, L, M, N, rear, tab, rot, zfront):
    """Hit of lens k's front/rear sphere: local hit, local direction, distance t (NaN on a miss)."""
    px, py, pz, lL, lM, lN = to_lens(k, x, y, z, L, M, N, tab, rot)
    if rear:
        vx, vy, vz, c = tab[2, k], tab[3, k], tab[6, k], tab[5, k]
    else:
        vx, vy, vz, c = 0.0, 0.0, zfront, tab[4, k]
    t = sphere_t(px - vx, py - vy, pz - vz, lL, lM, lN, c)
    hx, hy, hz = px + t * lL, py + t * lM, pz + t * lN
    return hx, hy, hz, lL, lM, lN, t



@jit_inline
def rot_of(rot, k):
    """The nine entries of lens k's rotation matrix, row by row."""
    return (rot[k, 0, 0], rot[k, 0, 1], rot[k, 0, 2], rot[k, 1, 0], rot[k, 1, 1], rot[k, 1, 2],
            rot[k, 2, 0], rot[k, 2, 1], rot[k, 2, 2])


@jit_inline
def rot_t(r00, r01, r02, r10, r11, r12, r20, r21, r22, x, y, z):
    """R^T v, as to_lens writes it (scalars only: helpers of the vectorized passes never take arrays)."""
    return r00 * x + r10 * y + r20 * z, r01 * x + r11 * y + r21 * z, r02 * x + r12 * y + r22 * z


@jit_inline
def rot_n(r00, r01, r02, r10, r11, r12, r20, r21, r22, x, y, z):
    """R v, as from_lens writes it."""
    return r00 * x + r01 * y + r02 * z, r10 * x + r11 * y + r12 * z, r20 * x + r21 * y + r22 * z


@jit_inline
def cell_f(x, y, ax0, ay0, invp, ncols, nrows, lat):
    """Flat lens index as a float, -1.0 off the array (NaN too): branch-free, unlike `cell`. Square cells,
    or hexagons where `lat` is not None ((ax0, ay0) is then U(1,1)'s centre)."""
    row, col = lattice_cell((x - ax0) * invp, (y - ay0) * invp, lat)
    on = (col >= 0.0) & (col < ncols) & (row >= 0.0) & (row < nrows)
    return row * ncols + col if on else -1.0


@jit_inline
def lens_hit(px, py, pz, L, M, N, ox, oy, oz, c, rot, k):
    """A ray given in lens k's frame (before its own rotation) meets the sphere with vertex (ox, oy, oz)
    and curvature c: hit point, direction and distance t in the rotated lens frame, and the hit's x, y
    back in the unrotated frame (gx, gy), where the cells are."""
    if rot is not None:
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rot_of(rot, k)
        px, py, pz = rot_t(r00, r01, r02, r10, r11, r12, r20, r21, r22, px, py, pz)
        L, M, N = rot_t(r00, r01, r02, r10, r11, r12, r20, r21, r22, L, M, N)
    t = sphere_t(px - ox, py - oy, pz - oz, L, M, N, c)
    hx, hy, hz = px + t * L, py + t * M, pz + t * N
    gx, gy = hx, hy
    if rot is not None:
        gx, gy, _ = rot_n(r00, r01, r02, r10, r11, r12, r20, r21, r22, hx, hy, hz)
    return hx, hy, hz, L, M, N, t, gx, gy


@jit
def surface_hit(px, py, pz, L, M, N, ox, oy, oz, c, fx, fy, rot, k, ax0, ay0, invp, ncols, nrows, lat):
    """A ray given in lens k's frame (before its own rotation) meets the lens surface with vertex at
    (ox, oy, oz) and curvature c: hit point and direction in the rotated lens frame, the distance t (NaN on
    a miss), and the MLA cell the hit lies in (to flag hits that belong to a neighbour)."""
    hx, hy, hz, L, M, N, t, gx, gy = lens_hit(px, py, pz, L, M, N, ox, oy, oz, c, rot, k)
    return hx, hy, hz, L, M, N, t, cell_f(gx + fx, gy + fy, ax0, ay0, invp, ncols, nrows, lat)



@jit_inline
def hit_xy(k, hx, hy, hz, tab, rot):
    """MLA-frame x, y of a point given in lens k's frame."""
    gx, gy, _, _, _, _ = from_lens(k, hx, hy, hz, 0.0, 0.0, 0.0, tab, rot)
    return gx, gy


@jit_inline
def surface_hit_edge(px, py, pz, L, M, N, ox, oy, oz, c, fx, fy, rot, k, ax0, ay0, invp, p, ncols, nrows, lat):
    """As surface_hit, plus the hit's distance (mm) from the nearest edge of the cell it lies in: the
    sag-intersection fast path doubts hits in another cell or within a margin of the edge."""
    hx, hy, hz, L, M, N, t, gx, gy = lens_hit(px, py, pz, L, M, N, ox, oy, oz, c, rot, k)
    gx, gy = gx + fx, gy + fy
    kf, edge = cell_edge((gx - ax0) * invp, (gy - ay0) * invp, ncols, nrows, lat)
    return hx, hy, hz, L, M, N, t, kf, p * edge


@jit_inline
def surface_hit_own(px, py, pz, L, M, N, ox, oy, oz, c, fx, fy, rot, k, cx, cy, ax0, ay0, invp, p, ncols, nrows, lat):
    """As surface_hit_edge, the cell test by own_edge (lens k's design centre cx, cy; sag-intersection)."""
    hx, hy, hz, L, M, N, t, gx, gy = lens_hit(px, py, pz, L, M, N, ox, oy, oz, c, rot, k)
    kf, edge = own_edge(gx + fx, gy + fy, cx, cy, ax0, ay0, invp, ncols, nrows, np.float64(k), lat)
    return hx, hy, hz, L, M, N, t, kf, p * edge


@jit_inline
def centre_cell(gx, gy, s, lat):
    """Row and column of the cell holding an MLA-frame point, clipped onto the array."""
    row, col = row_col(gx, gy, s, lat)
    return min(max(row, 0), int(s[S_ROWS]) - 1), min(max(col, 0), int(s[S_COLS]) - 1)
