"""Compiled fast path: the whole chain (sampling -> main lens -> MLA -> sensor pixel) fused per ray in Numba.

It follows `mlaqc.raytrace` and `mlaqc.scene` operation for operation and consumes the same uniform draws,
so tests compare the two ray by ray. It releases the GIL, so the renderer's thread pool keeps every core
busy. The NumPy path stays the reference; this module is used when Numba is importable.
"""

from __future__ import annotations

import math

import numpy as np

from mlaqc.unitcircle import GAMMA, HALF_PI, MIX1, MIX2, TO_UNIT
from mlaqc.unitcircle import poly_cos as _poly_cos
from mlaqc.unitcircle import poly_sin as _poly_sin

try:
    from numba import njit
except ImportError:  # pragma: no cover - exercised only where numba is missing
    njit = None

AVAILABLE = njit is not None


def _identity(fn):
    return fn


_jit = njit(cache=True, nogil=True, error_model="numpy") if AVAILABLE else _identity
_jit_inline = njit(cache=True, nogil=True, error_model="numpy", inline="always") if AVAILABLE else _identity
poly_sin = _jit_inline(_poly_sin)
poly_cos = _jit_inline(_poly_cos)

# Modes of the kernel.
IMAGE_SIDE, POINT, OBJECT_SIDE = 0, 1, 2
# Slots of the scalar parameter vector.
(S_MODE, S_X0, S_X1, S_Y0, S_Y1, S_ZSTART, S_ZEXIT, S_RPUPIL, S_PX, S_PY,
 S_C1, S_C2, S_T, S_N, S_RIM2, S_FRES, S_ZOBJ, S_TEXHX, S_TEXHY,
 S_P, S_AX0, S_AY0, S_ROWS, S_COLS, S_ZFRONT, S_NMLA, S_CLEAR, S_SHIFTX,
 S_ZMLA, S_SHIFTY, S_ZSENS, S_PIX, S_SX0, S_SY0, S_W, S_H, S_INVP, S_INVPIX, S_COUNT) = range(39)


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
def cell(x, y, s):
    col = math.floor((x - s[S_AX0]) * s[S_INVP])
    row = math.floor((y - s[S_AY0]) * s[S_INVP])
    if col >= 0 and col < s[S_COLS] and row >= 0 and row < s[S_ROWS]:
        return int(row * s[S_COLS] + col)
    return -1


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
    """Hit of lens k's front/rear sphere: local hit, local dir, normal, ok."""
    px, py, pz, lL, lM, lN = to_lens(k, x, y, z, L, M, N, tab, rot)
    if rear:
        vx, vy, vz, c = tab[2, k], tab[3, k], tab[6, k], tab[5, k]
    else:
        vx, vy, vz, c = 0.0, 0.0, zfront, tab[4, k]
    t = sphere_t(px - vx, py - vy, pz - vz, lL, lM, lN, c)
    hx, hy, hz = px + t * lL, py + t * lM, pz + t * lN
    return hx, hy, hz, lL, lM, lN, c * (hx - vx), c * (hy - vy), c * (hz - vz) - 1.0, t == t


@_jit_inline
def lens_hit(k, x, y, z, L, M, N, rear, tab, rot, s):
    """Intersect the right lens' surface, re-tracing once with the neighbour if the hit left the cell."""
    out = lens_surface(k, x, y, z, L, M, N, rear, tab, rot, s[S_ZFRONT])
    if out[9]:
        gx, gy, _, _, _, _ = from_lens(k, out[0], out[1], out[2], out[3], out[4], out[5], tab, rot)
        k2 = cell(gx, gy, s)
        if k2 >= 0 and k2 != k:
            k = k2
            out = lens_surface(k, x, y, z, L, M, N, rear, tab, rot, s[S_ZFRONT])
    return k, out


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
    z = z ^ (z >> np.uint64(31))
    return np.float64(z >> np.uint64(11)) * TO_UNIT


@_jit_inline
def cos_sin_2pi(u):
    """Scalar twin of unitcircle.cos_sin_2pi (same operations, so both engines draw the same angles)."""
    v = 4.0 * u
    q = math.floor(v + 0.5)
    a = (v - q) * HALF_PI
    a2 = a * a
    c, sn = poly_cos(a2), poly_sin(a, a2)
    iq = int(q) & 3
    swap = (iq & 1) == 1
    cc = sn if swap else c
    ss = c if swap else sn
    cc = -cc if (iq == 1 or iq == 2) else cc
    ss = -ss if iq >= 2 else ss
    return cc, ss


@_jit_inline
def stage1_image_side(start, m, s, key, buf, fres, texture):
    """Rays from the rear aperture to the MLA, traced back through the main lens for their weight.

    Branch-free with loop-invariant scalars, so the loop vectorizes."""
    x0, dx_span, y0, dy_span = s[S_X0], s[S_X1] - s[S_X0], s[S_Y0], s[S_Y1] - s[S_Y0]
    rp, zs, dz = s[S_RPUPIL], s[S_ZSTART], s[S_ZSTART] - s[S_ZEXIT]
    t_main, c1, c2, n, rim2, zobj = s[S_T], s[S_C1], s[S_C2], s[S_N], s[S_RIM2], s[S_ZOBJ]
    mu_in, mu_out = 1.0 / n, n
    for j in range(m):
        i = start + j
        x = x0 + dx_span * draw(key, i, 0)
        y = y0 + dy_span * draw(key, i, 1)
        rad = rp * math.sqrt(draw(key, i, 2))
        cph, sph = cos_sin_2pi(draw(key, i, 3))
        dx = x - rad * cph
        dy = y - rad * sph
        inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
        L, M, N = dx * inv, dy * inv, dz * inv
        w = (N * N) * (N * N)
        bx, by, bz, bL, bM, bN, tr = main_surface(x, y, zs, -L, -M, -N, t_main, c2, 1.0, n, mu_in, rim2, fres)
        w *= tr
        bx, by, bz, bL, bM, bN, tr = main_surface(bx, by, bz, bL, bM, bN, 0.0, c1, n, 1.0, mu_out, rim2, fres)
        w *= tr
        buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j], buf[6, j] = x, y, zs, L, M, N, w
        if texture is not None:  # pruned at compile time when there is no texture
            t = (zobj - bz) / bN
            buf[7, j], buf[8, j] = bx + t * bL, by + t * bM


@_jit_inline
def stage1_forward(start, m, mode, s, key, buf, fres, texture):
    """Rays from object points (a point source, or points of the object plane) through the main lens."""
    x0, dx_span, y0, dy_span = s[S_X0], s[S_X1] - s[S_X0], s[S_Y0], s[S_Y1] - s[S_Y0]
    rp, zs = s[S_RPUPIL], s[S_ZSTART]
    t_main, c1, c2, n, rim2 = s[S_T], s[S_C1], s[S_C2], s[S_N], s[S_RIM2]
    mu_in, mu_out = 1.0 / n, n
    point = mode == POINT
    for j in range(m):
        i = start + j
        if point:
            ox, oy, ur, up = s[S_PX], s[S_PY], draw(key, i, 0), draw(key, i, 1)
        else:
            ox, oy = x0 + dx_span * draw(key, i, 0), y0 + dy_span * draw(key, i, 1)
            ur, up = draw(key, i, 2), draw(key, i, 3)
        rad = rp * math.sqrt(ur)
        cph, sph = cos_sin_2pi(up)
        dx = rad * cph - ox
        dy = rad * sph - oy
        dz = -zs
        inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
        L, M, N = dx * inv, dy * inv, dz * inv
        w = N * N * N
        if not point:
            w *= N
        x, y, z, L, M, N, tr = main_surface(ox, oy, zs, L, M, N, 0.0, c1, 1.0, n, mu_in, rim2, fres)
        w *= tr
        x, y, z, L, M, N, tr = main_surface(x, y, z, L, M, N, t_main, c2, n, 1.0, mu_out, rim2, fres)
        w *= tr
        buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j], buf[6, j] = x, y, z, L, M, N, w
        buf[7, j], buf[8, j] = ox, oy


@_jit_inline
def trace_mla_to_sensor(i, x, y, z, L, M, N, w, s, tab, rot, grot, clear, fres, n_mla, mu_mla_in, out_idx, out_w):
    """Stage 2: one ray from behind the main lens through its microlens onto a pixel (writes slot i)."""
    # --- into the MLA frame ---
    x = x - s[S_SHIFTX]
    y = y - s[S_SHIFTY]
    z = z - s[S_ZMLA]
    if grot is not None:
        x, y, z = (grot[0, 0] * x + grot[1, 0] * y + grot[2, 0] * z, grot[0, 1] * x + grot[1, 1] * y + grot[2, 1] * z,
                   grot[0, 2] * x + grot[1, 2] * y + grot[2, 2] * z)
        L, M, N = (grot[0, 0] * L + grot[1, 0] * M + grot[2, 0] * N, grot[0, 1] * L + grot[1, 1] * M + grot[2, 1] * N,
                   grot[0, 2] * L + grot[1, 2] * M + grot[2, 2] * N)
    t = (s[S_ZFRONT] - z) / N
    x += t * L
    y += t * M
    z += t * N
    k = cell(x, y, s)
    if k < 0:
        return
    # --- front surface ---
    k, f = lens_hit(k, x, y, z, L, M, N, False, tab, rot, s)
    if not f[9]:
        return
    hx, hy, hz = f[0], f[1], f[2]
    rx, ry = hx - tab[2, k], hy - tab[3, k]
    c2 = tab[5, k]
    rho2 = rx * rx + ry * ry
    arg = 1.0 - c2 * c2 * rho2
    corner = True
    if arg >= 0.0:
        corner = not (tab[6, k] + c2 * rho2 / (1.0 + math.sqrt(arg)) > hz)
    if corner and not clear:
        return
    if corner:
        nL, nM, nN = f[3], f[4], f[5]
    else:
        nL, nM, nN, tr = refract(f[3], f[4], f[5], f[6], f[7], f[8], mu_mla_in, fres, 1.0, n_mla)
        if tr < 0.0:
            return
        w *= tr
    x, y, z, L, M, N = from_lens(k, hx, hy, hz, nL, nM, nN, tab, rot)
    # --- rear surface ---
    if not corner:
        k, b = lens_hit(k, x, y, z, L, M, N, True, tab, rot, s)
        if not b[9]:
            return
        nL, nM, nN, tr = refract(b[3], b[4], b[5], b[6], b[7], b[8], n_mla, fres, n_mla, 1.0)
        if tr < 0.0:
            return
        w *= tr
        x, y, z, L, M, N = from_lens(k, b[0], b[1], b[2], nL, nM, nN, tab, rot)
    # --- back to the camera frame, onto the sensor ---
    if grot is not None:
        x, y, z = (grot[0, 0] * x + grot[0, 1] * y + grot[0, 2] * z, grot[1, 0] * x + grot[1, 1] * y + grot[1, 2] * z,
                   grot[2, 0] * x + grot[2, 1] * y + grot[2, 2] * z)
        L, M, N = (grot[0, 0] * L + grot[0, 1] * M + grot[0, 2] * N, grot[1, 0] * L + grot[1, 1] * M + grot[1, 2] * N,
                   grot[2, 0] * L + grot[2, 1] * M + grot[2, 2] * N)
    x = x + s[S_SHIFTX]
    y = y + s[S_SHIFTY]
    z = z + s[S_ZMLA]
    t = (s[S_ZSENS] - z) / N
    x += t * L
    y += t * M
    col = math.floor((x - s[S_SX0]) * s[S_INVPIX])
    row = math.floor((y - s[S_SY0]) * s[S_INVPIX])
    if w > 0.0 and col >= 0 and col < s[S_W] and row >= 0 and row < s[S_H]:
        out_idx[i] = int(row * s[S_W] + col)
        out_w[i] = w


BLOCK = 256  # rays per block: stage 1 runs vectorized over a block held in L1, stage 2 ray by ray


@_jit
def kernel(s, key, count, tab, rot, grot, texture, out_idx, out_w):
    """Trace `count` rays drawn with `key`; out_idx = flat pixel (-1 if lost), out_w = weight."""
    mode = int(s[S_MODE])
    fres = s[S_FRES] != 0.0
    clear = s[S_CLEAR] != 0.0
    n_mla = s[S_NMLA]
    mu_mla_in = 1.0 / n_mla
    tex_hx, tex_hy = s[S_TEXHX], s[S_TEXHY]
    buf = np.empty((9, BLOCK))
    for start in range(0, count, BLOCK):
        m = min(BLOCK, count - start)
        if mode == IMAGE_SIDE:
            stage1_image_side(start, m, s, key, buf, fres, texture)
        else:
            stage1_forward(start, m, mode, s, key, buf, fres, texture)
        if texture is not None:
            for j in range(m):
                buf[6, j] *= texel(texture, buf[7, j], buf[8, j], tex_hx, tex_hy)
        for j in range(m):
            i = start + j
            out_idx[i] = -1
            out_w[i] = 0.0
            w = buf[6, j]
            if not w > 0.0:  # also catches NaN
                continue
            trace_mla_to_sensor(i, buf[0, j], buf[1, j], buf[2, j], buf[3, j], buf[4, j], buf[5, j], w,
                                s, tab, rot, grot, clear, fres, n_mla, mu_mla_in, out_idx, out_w)


class FastCamera:
    """Packs a `raytrace.Camera` into the flat tables the kernel reads; one per Renderer."""

    def __init__(self, camera, image_region, source_region, texture_half_mm) -> None:
        mla, main, cfg = camera.mla, camera.main, camera.cfg
        self.tab = np.ascontiguousarray(np.stack([mla.fx, mla.fy, mla.dx, mla.dy, mla.c1, mla.c2, mla.z_rear]))
        # None (not an identity) where unused: Numba then compiles a kernel without those branches.
        self.rot = np.ascontiguousarray(mla.rot) if mla.tilted else None
        self.grot = np.ascontiguousarray(camera.rot) if camera.rotated else None
        s = np.zeros(S_COUNT)
        s[S_C1], s[S_C2], s[S_T], s[S_N], s[S_RIM2] = main.c1, main.c2, main.z2, main.n, main.rim2
        s[S_FRES] = float(cfg.trace.fresnel)
        s[S_ZOBJ] = camera.layout.z_object_mm
        s[S_TEXHX], s[S_TEXHY] = texture_half_mm
        s[S_P], s[S_AX0], s[S_AY0], s[S_ROWS], s[S_COLS] = mla.p, mla.x0, mla.y0, mla.rows, mla.cols
        s[S_ZFRONT], s[S_NMLA], s[S_CLEAR] = mla.z_front, mla.n, float(mla.clear_corners)
        s[S_ZMLA], s[S_ZSENS] = camera.z_mla, camera.z_sensor
        s[S_SHIFTX], s[S_SHIFTY] = camera.shift_x, camera.shift_y
        s[S_PIX], s[S_SX0], s[S_SY0], s[S_W], s[S_H] = camera.pixel, camera.sx0, camera.sy0, camera.width, camera.height
        s[S_INVP], s[S_INVPIX] = 1.0 / mla.p, 1.0 / camera.pixel
        self.base = s
        self.image_region = image_region
        self.source_region = source_region

    def trace(self, mode: int, key: int, n: int, tile=None, point=None, texture=None):
        """Trace one batch; returns (flat pixel index, weight) of the rays that reached the sensor."""
        s = self.base.copy()
        s[S_MODE] = mode
        if mode == IMAGE_SIDE:
            s[S_ZSTART], s[S_ZEXIT], s[S_RPUPIL] = self.image_region.z_mla_mm, self.image_region.z_exit_mm, self.image_region.exit_radius_mm
        else:
            s[S_ZSTART], s[S_RPUPIL] = self.source_region.z_object_mm, self.source_region.pupil_radius_mm
        if tile is not None:
            s[S_X0], s[S_X1], s[S_Y0], s[S_Y1] = tile
        if point is not None:
            s[S_PX], s[S_PY] = point
        tex = None if texture is None else np.ascontiguousarray(texture, dtype=np.float64)
        idx = np.empty(n, np.int64)
        w = np.empty(n)
        if not AVAILABLE:
            raise RuntimeError("numba is not installed; use the NumPy engine")
        kernel(s, np.uint64(key), n, self.tab, self.rot, self.grot, tex, idx, w)
        good = idx >= 0
        return idx[good], w[good]
