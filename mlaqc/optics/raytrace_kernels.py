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

from mlaqc.optics import kernel_sources, lowdisc
from mlaqc.optics.lattice import SQRT3_2
from mlaqc.optics.raytrace import INV_ROW_PAIR_HEX
from mlaqc.optics.scene import FOUR_OVER_PI
from mlaqc.optics.scene import aperture_point as _aperture_point
from mlaqc.optics.unitcircle import GAMMA, HALF_PI, MIX1, MIX2, TO_UNIT
from mlaqc.optics.unitcircle import poly_cos as _poly_cos
from mlaqc.optics.unitcircle import poly_sin as _poly_sin

try:
    from numba import njit
except ImportError:  # pragma: no cover - exercised only where numba is missing
    njit = None

AVAILABLE = njit is not None
# the message of Numba's pedantic SSA warning that inlined selects trip (silenced below; tests check it matches)
SSA_SCOPE_WARNING = r".*variable '.*' is not in scope"


def _identity(fn):
    return fn


# fastmath is limited to FMA contraction (a * b + c in one rounding): about 5 % faster, results within an
# ulp or two of the uncontracted NumPy reference. The other fast-math flags would break the NaN (miss)
# and +-0 handling the kernel relies on.
_FLAGS = dict(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
if AVAILABLE:  # Numba's cache stamped by every source the kernels are compiled from, not this file alone
    kernel_sources.register(__file__, kernel_sources.TRACER_SOURCES)
_jit = njit(**_FLAGS) if AVAILABLE else _identity
_jit_inline = njit(inline="always", **_FLAGS) if AVAILABLE else _identity
poly_sin = _jit_inline(_poly_sin)
poly_cos = _jit_inline(_poly_cos)
sobol32 = _jit_inline(lowdisc.sobol32)
reverse32 = _jit_inline(lowdisc.reverse32)
lk_hash = _jit_inline(lowdisc.lk_hash)
hash32 = _jit_inline(lowdisc.hash32)
SOBOL_DIRECTIONS = lowdisc.DIRECTIONS
aperture_point = _jit_inline(_aperture_point)

# Modes of the kernel.
IMAGE_SIDE, POINT, OBJECT_SIDE = 0, 1, 2
# Slots of the scalar parameter vector.
(S_MODE, S_X0, S_X1, S_Y0, S_Y1, S_ZSTART, S_ZEXIT, S_RPUPIL, S_PX, S_PY,
 S_C1, S_C2, S_T, S_N, S_RIM2, S_FRES, S_ZOBJ, S_TEXHX, S_TEXHY,
 S_P, S_AX0, S_AY0, S_ROWS, S_COLS, S_ZFRONT, S_NMLA, S_CLEAR, S_SHIFTX,
 S_ZMLA, S_SHIFTY, S_ZSENS, S_PIX, S_SX0, S_SY0, S_W, S_H, S_INVP, S_INVPIX,
 # the low-discrepancy sampler: on/off, the job's block of cells (first row and column, width, cells) and
 # first point index, padded cells per row, and the MLA frame's 2 x 2 map to the start plane
 S_SOBOL, S_CR0, S_CC0, S_CBW, S_CB, S_J0, S_PCOLS, S_R00, S_R01, S_R10, S_R11,
 S_INVKR, S_SQUARE, S_SQW,
 # half the black matrix' width (mm; sag-intersection boundaries are a kernel of their own, kernel_sag)
 S_HALFBM,
 # circle apertures: radius^2, clear gaps (per-cell reach: the `circ` table)
 S_RCIRC2, S_CLEARGAP,
 # 1: re-traces skip candidates that provably cannot win (pair clearances); 0: every doubted ray scans
 # them all (the exhaustive path, which tests hold the pruned one to, image for image)
 S_PRUNE,
 # run-time switches (one kernel serves both sides: each pass they change is inlined once per side and chosen
 # per block of rays, which costs nothing measurable): a textured scene, a global MLA rotation
 S_TEXTURE, S_GROT, S_COUNT) = range(59)
# Rows of the per-block scratch table `g`: the gathered parameters of each ray's lens (tab rows 0..6), its
# current hit and direction in the lens frame, the distance t to it (NaN on a miss), and its pixel.
# Sag-intersection mode also gathers the lens' front and rear margins (G_MF, G_MR) and design centre (G_CX, G_CY).
G_FX, G_FY, G_DX, G_DY, G_C1, G_C2, G_ZR, G_HX, G_HY, G_HZ, G_LL, G_LM, G_LN, G_T, G_ROW, G_COL, G_MF, G_MR, G_CX, G_CY, G_COUNT = range(21)
# Rows of the per-lens `margins` table of sag-intersection mode (kernel_sag): front and rear margins (mm,
# raytrace.MicrolensArray.boundary_margins_mm), design centre x, y (mm).
T_MARGIN_FRONT, T_MARGIN_REAR, T_GX, T_GY = 0, 1, 2, 3
# Rows of the per-lens `circ` table of circle apertures: design centre x, y (mm), (radius + reach)^2 (mm^2),
# the edge distance (mm) within which a neighbour's circle can hold a hit (circle_clearance_mm).
C_GX, C_GY, C_REACH2, C_CLEAR = 0, 1, 2, 3


@_jit_inline
def sphere_t(px, py, pz, L, M, N, c):
    """As raytrace.intersect_sphere, for one ray (position relative to the vertex); NaN on a miss."""
    b = c * (px * L + py * M + pz * N) - N
    cc = c * (px * px + py * py + pz * pz) - 2.0 * pz
    disc = b * b - c * cc
    t = -cc / (b + math.copysign(math.sqrt(max(disc, 0.0)), b))
    return t if disc >= 0.0 else math.nan  # a select, not a branch


@_jit_inline
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


@_jit_inline
def main_surface(x, y, z, L, M, N, zv, c, n1, n2, mu, rim2, fresnel):
    """Branch-free main-lens surface: a miss, vignetting or total reflection gives transmission 0."""
    t = sphere_t(x, y, z - zv, L, M, N, c)
    x += t * L
    y += t * M
    z += t * N
    L, M, N, tr = refract(L, M, N, c * x, c * y, c * (z - zv) - 1.0, mu, fresnel, n1, n2)
    return x, y, z, L, M, N, tr if (x * x + y * y <= rim2 and tr >= 0.0) else 0.0


@_jit_inline
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


@_jit_inline
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
    import warnings

    from numba import types
    from numba.core.errors import NumbaIRAssumptionWarning
    from numba.extending import overload

    # Inlining cell_edge's selects into the sag-intersection passes trips a pedantic SSA check of Numba's
    # (the variables are in scope: the kernels agree with the NumPy reference ray by ray); it is not the
    # user's to see at compile time. Numba prefixes the message with a terminal colour code (the filter matches
    # from the message's start: without the leading .* the warnings reached the user on every first compile).
    warnings.filterwarnings("ignore", SSA_SCOPE_WARNING, NumbaIRAssumptionWarning)

    _TYPED = dict(inline="always", jit_options=dict(error_model="numpy", fastmath={"contract"}))
    # the overloads only forward to inline-compiled helpers: selects written in an overload's own body
    # trip a Numba SSA check (NumbaIRAssumptionWarning) when it is inlined
    _cs, _ch, _es, _eh = (_jit_inline(f) for f in (_cell_square, _cell_hex, _cell_edge_square, _cell_edge_hex))
    _bs, _bh = _jit_inline(_black_square), _jit_inline(_black_hex)
    _ctrs, _ctrh = _jit_inline(_centre_square), _jit_inline(_centre_hex)

    @overload(cell_centre, **_TYPED)
    def _cell_centre_typed(x, y, ax0, ay0, invp, p, lat):
        if isinstance(lat, types.NoneType):
            return lambda x, y, ax0, ay0, invp, p, lat: _ctrs(x, y, ax0, ay0, invp, p, lat)
        return lambda x, y, ax0, ay0, invp, p, lat: _ctrh(x, y, ax0, ay0, invp, p, lat)
    _os, _oh = _jit_inline(_own_edge_square), _jit_inline(_own_edge_hex)

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


@_jit_inline
def cell(x, y, s, lat):
    if lat is None:
        col = math.floor((x - s[S_AX0]) * s[S_INVP])
        row = math.floor((y - s[S_AY0]) * s[S_INVP])
    else:
        rf, cf, _, _ = hex_locate((x - s[S_AX0]) * s[S_INVP], (y - s[S_AY0]) * s[S_INVP])
        row, col = int(rf), int(cf)
    if col >= 0 and col < s[S_COLS] and row >= 0 and row < s[S_ROWS]:
        return int(row * s[S_COLS] + col)
    return -1


@_jit_inline
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


@_jit_inline
def to_lens(k, x, y, z, L, M, N, tab, rot):
    px, py, pz = x - tab[0, k], y - tab[1, k], z
    if rot is None:
        return px, py, pz, L, M, N
    r = rot[k]
    return (r[0, 0] * px + r[1, 0] * py + r[2, 0] * pz, r[0, 1] * px + r[1, 1] * py + r[2, 1] * pz,
            r[0, 2] * px + r[1, 2] * py + r[2, 2] * pz, r[0, 0] * L + r[1, 0] * M + r[2, 0] * N,
            r[0, 1] * L + r[1, 1] * M + r[2, 1] * N, r[0, 2] * L + r[1, 2] * M + r[2, 2] * N)


@_jit_inline
def from_lens(k, px, py, pz, L, M, N, tab, rot):
    if rot is not None:
        r = rot[k]
        px, py, pz = (r[0, 0] * px + r[0, 1] * py + r[0, 2] * pz, r[1, 0] * px + r[1, 1] * py + r[1, 2] * pz,
                      r[2, 0] * px + r[2, 1] * py + r[2, 2] * pz)
        L, M, N = (r[0, 0] * L + r[0, 1] * M + r[0, 2] * N, r[1, 0] * L + r[1, 1] * M + r[1, 2] * N,
                   r[2, 0] * L + r[2, 1] * M + r[2, 2] * N)
    return px + tab[0, k], py + tab[1, k], pz, L, M, N


@_jit_inline
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


@_jit_inline
def texel(texture, ox, oy, hx, hy):
    th, tw = texture.shape
    uu = (ox + hx) / (2.0 * hx)
    vv = (oy + hy) / (2.0 * hy)
    if not (uu >= 0.0 and uu < 1.0 and vv >= 0.0 and vv < 1.0):
        return 0.0
    return texture[min(int(vv * th), th - 1), min(int(uu * tw), tw - 1)]


@_jit_inline
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


@_jit_inline
def owen32(x, seed):
    """Compiled twin of lowdisc.owen32."""
    return reverse32(lk_hash(reverse32(x), seed))


@_jit_inline
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


@_jit
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
def rot_of(rot, k):
    """The nine entries of lens k's rotation matrix, row by row."""
    return (rot[k, 0, 0], rot[k, 0, 1], rot[k, 0, 2], rot[k, 1, 0], rot[k, 1, 1], rot[k, 1, 2],
            rot[k, 2, 0], rot[k, 2, 1], rot[k, 2, 2])


@_jit_inline
def rot_t(r00, r01, r02, r10, r11, r12, r20, r21, r22, x, y, z):
    """R^T v, as to_lens writes it (scalars only: helpers of the vectorized passes never take arrays)."""
    return r00 * x + r10 * y + r20 * z, r01 * x + r11 * y + r21 * z, r02 * x + r12 * y + r22 * z


@_jit_inline
def rot_n(r00, r01, r02, r10, r11, r12, r20, r21, r22, x, y, z):
    """R v, as from_lens writes it."""
    return r00 * x + r01 * y + r02 * z, r10 * x + r11 * y + r12 * z, r20 * x + r21 * y + r22 * z


@_jit_inline
def cell_f(x, y, ax0, ay0, invp, ncols, nrows, lat):
    """Flat lens index as a float, -1.0 off the array (NaN too): branch-free, unlike `cell`. Square cells,
    or hexagons where `lat` is not None ((ax0, ay0) is then U(1,1)'s centre)."""
    row, col = lattice_cell((x - ax0) * invp, (y - ay0) * invp, lat)
    on = (col >= 0.0) & (col < ncols) & (row >= 0.0) & (row < nrows)
    return row * ncols + col if on else -1.0


@_jit_inline
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


@_jit
def surface_hit(px, py, pz, L, M, N, ox, oy, oz, c, fx, fy, rot, k, ax0, ay0, invp, ncols, nrows, lat):
    """A ray given in lens k's frame (before its own rotation) meets the lens surface with vertex at
    (ox, oy, oz) and curvature c: hit point and direction in the rotated lens frame, the distance t (NaN on
    a miss), and the MLA cell the hit lies in (to flag hits that belong to a neighbour)."""
    hx, hy, hz, L, M, N, t, gx, gy = lens_hit(px, py, pz, L, M, N, ox, oy, oz, c, rot, k)
    return hx, hy, hz, L, M, N, t, cell_f(gx + fx, gy + fy, ax0, ay0, invp, ncols, nrows, lat)


@_jit_inline
def gather(j, k, tab, g):
    """Copy lens k's parameters into column j of the scratch table."""
    for r in range(7):
        g[r, j] = tab[r, k]


@_jit_inline
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


@_jit_inline
def hit_xy(k, hx, hy, hz, tab, rot):
    """MLA-frame x, y of a point given in lens k's frame."""
    gx, gy, _, _, _, _ = from_lens(k, hx, hy, hz, 0.0, 0.0, 0.0, tab, rot)
    return gx, gy


@_jit_inline
def surface_hit_edge(px, py, pz, L, M, N, ox, oy, oz, c, fx, fy, rot, k, ax0, ay0, invp, p, ncols, nrows, lat):
    """As surface_hit, plus the hit's distance (mm) from the nearest edge of the cell it lies in: the
    sag-intersection fast path doubts hits in another cell or within a margin of the edge."""
    hx, hy, hz, L, M, N, t, gx, gy = lens_hit(px, py, pz, L, M, N, ox, oy, oz, c, rot, k)
    gx, gy = gx + fx, gy + fy
    kf, edge = cell_edge((gx - ax0) * invp, (gy - ay0) * invp, ncols, nrows, lat)
    return hx, hy, hz, L, M, N, t, kf, p * edge


@_jit_inline
def surface_hit_own(px, py, pz, L, M, N, ox, oy, oz, c, fx, fy, rot, k, cx, cy, ax0, ay0, invp, p, ncols, nrows, lat):
    """As surface_hit_edge, the cell test by own_edge (lens k's design centre cx, cy; sag-intersection)."""
    hx, hy, hz, L, M, N, t, gx, gy = lens_hit(px, py, pz, L, M, N, ox, oy, oz, c, rot, k)
    kf, edge = own_edge(gx + fx, gy + fy, cx, cy, ax0, ay0, invp, ncols, nrows, np.float64(k), lat)
    return hx, hy, hz, L, M, N, t, kf, p * edge


@_jit_inline
def centre_cell(gx, gy, s, lat):
    """Row and column of the cell holding an MLA-frame point, clipped onto the array."""
    if lat is None:
        col = math.floor((gx - s[S_AX0]) * s[S_INVP])
        row = math.floor((gy - s[S_AY0]) * s[S_INVP])
    else:
        rf, cf, _, _ = hex_locate((gx - s[S_AX0]) * s[S_INVP], (gy - s[S_AY0]) * s[S_INVP])
        row, col = int(rf), int(cf)
    return min(max(row, 0), int(s[S_ROWS]) - 1), min(max(col, 0), int(s[S_COLS]) - 1)


# The candidates' design-centre offsets from their cell's, in pitches, in candidate order (`candidate`):
# square the 3 x 3 row-major, hex the cell, then left, right, upper left, upper right, lower left, lower
# right (y down; FastCamera checks them against the lattice's centres).
SQUARE_DIRS = np.array([[dc, dr] for dr in (-1.0, 0.0, 1.0) for dc in (-1.0, 0.0, 1.0)])
HEX_DIRS = np.array([[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [-0.5, -SQRT3_2], [0.5, -SQRT3_2], [-0.5, SQRT3_2],
                     [0.5, SQRT3_2]])


@_jit_inline
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


@_jit
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


@_jit_inline
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


@_jit_inline
def inside_rear(k, px, py, pz, tab):
    """A point of lens k's frame lies in front of (in the material of) its rear sphere."""
    rx, ry = px - tab[2, k], py - tab[3, k]
    c2 = tab[5, k]
    rho2 = rx * rx + ry * ry
    arg = 1.0 - c2 * c2 * rho2
    return (arg >= 0.0) & (tab[6, k] + c2 * rho2 / (1.0 + math.sqrt(max(arg, 0.0))) > pz)


@_jit
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


@_jit_inline
def corners_sag(m, cflag, kk, g, tab, rot, s, corner_of, lat):
    """Sag-intersection corners of the flagged rays (front hit within the rear margin of its cell's edge,
    or re-traced) outside their own lens' rear region (inside it, a hit is in the union: the scan is
    skipped): the front hit lies in no rear region of the candidates around its cell (as
    raytrace.MicrolensArray._corner_sag; elsewhere lens kk's rear decides, in pass B). Scalar: rare."""
    for j in range(m):
        if cflag[j] and corner_of[j]:  # inside its own lens' rear region, a hit is in the union: no corner
            gx, gy, gz, _, _, _ = from_lens(kk[j], g[G_HX, j], g[G_HY, j], g[G_HZ, j], 0.0, 0.0, 0.0, tab, rot)
            corner_of[j] = not in_rear_union(gx, gy, gz, tab, rot, s, lat)


@_jit_inline
def black_matrix(m, buf, s, lat):
    """Absorb rays crossing the front vertex plane (buf, MLA frame) within half the black matrix' width of
    a cell edge (as raytrace.MicrolensArray.black_matrix)."""
    ax0, ay0, invp, p, hw = s[S_AX0], s[S_AY0], s[S_INVP], s[S_P], s[S_HALFBM]
    for j in range(m):
        masked = under_black_matrix((buf[0, j] - ax0) * invp, (buf[1, j] - ay0) * invp, p, hw, lat)
        buf[6, j] = 0.0 if masked else buf[6, j]


@_jit_inline
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


@_jit_inline
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


@_jit_inline
def grot_entries(grot):
    """The MLA's global rotation, nine entries (zeros where there is none)."""
    g00 = g01 = g02 = g10 = g11 = g12 = g20 = g21 = g22 = 0.0
    if grot is not None:
        g00, g01, g02, g10, g11, g12, g20, g21, g22 = (grot[0, 0], grot[0, 1], grot[0, 2], grot[1, 0], grot[1, 1],
                                                       grot[1, 2], grot[2, 0], grot[2, 1], grot[2, 2])
    return g00, g01, g02, g10, g11, g12, g20, g21, g22


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


@_jit_inline
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


BLOCK = 256  # rays per block: every pass works on a block held in L1
NO_TEXTURE = np.ones((1, 1))  # the texture argument of a scene without one (S_TEXTURE 0: never read)


@_jit_inline
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


@_jit_inline
def block_scratch():
    """One block's scratch arrays: rays, per-ray table, lens index, re-trace and corner flags, sampler cells."""
    return (np.empty((9, BLOCK)), np.empty((G_COUNT, BLOCK)), np.empty(BLOCK, np.int32), np.empty(BLOCK, np.bool_),
            np.empty(BLOCK, np.bool_), np.empty(BLOCK, np.int64), np.empty(BLOCK, np.int64))


@_jit_inline
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


@_jit
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


@_jit
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


@_jit
def bin_hits(rows, cols, wts, n, box):
    """Sum the weights per pixel over the hits' bounding box, in hit order (as np.bincount would)."""
    if n == 0:
        return np.zeros((0, 0))
    r0, c0 = box[0], box[2]
    patch = np.zeros((box[1] - r0 + 1, box[3] - c0 + 1))
    for i in range(n):
        patch[rows[i] - r0, cols[i] - c0] += wts[i]
    return patch
