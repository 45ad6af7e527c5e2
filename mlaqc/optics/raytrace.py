"""Exact, vectorized sequential ray tracing through the main lens and a per-lens-perturbed MLA.

Frame: x to the right of the raw image (towards larger n), y down (towards larger m), z along the light;
z = 0 at the main lens' front vertex, lengths in mm. Rays are structure-of-arrays (x, y, z, L, M, N, w);
a ray that misses, is vignetted or totally reflected gets weight 0 (masked, never removed mid-trace).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mlaqc.optics.config import CameraConfig
from mlaqc.optics.errormap import ErrorMap


@dataclass
class Rays:
    """A batch of rays: positions (mm), unit directions and weights, 1-D float64 arrays of equal length."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    L: np.ndarray
    M: np.ndarray
    N: np.ndarray
    w: np.ndarray

    def __len__(self) -> int:
        return len(self.x)

    def advance(self, t: np.ndarray) -> None:
        """Move every ray by distance t along its direction (in place)."""
        self.x += t * self.L
        self.y += t * self.M
        self.z += t * self.N


def intersect_sphere(x, y, z, L, M, N, xv, yv, zv, c):
    """Distance along each ray to the sphere of curvature c with vertex (xv, yv, zv); NaN if it misses.

    Solves c|P|^2 - 2 Pz = 0 (P relative to the vertex) with the cancellation-free root that reduces to
    the plane intersection as c -> 0 and picks the sheet through the vertex.
    """
    px, py, pz = x - xv, y - yv, z - zv
    b = c * (px * L + py * M + pz * N) - N
    cc = c * (px * px + py * py + pz * pz) - 2.0 * pz
    disc = b * b - c * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        root = np.sqrt(disc)
        return -cc / (b + np.copysign(root, b))


def sphere_normal(x, y, z, xv, yv, zv, c):
    """Unit normal (c*Px, c*Py, c*Pz - 1) of the sphere at a point on it; points towards -z at the vertex."""
    return c * (x - xv), c * (y - yv), c * (z - zv) - 1.0


def refract(L, M, N, nx, ny, nz, mu):
    """Vector Snell's law with relative index mu = n1/n2: returns (L', M', N', cos_i, cos_t, ok).

    The normal may point either way; ok is False where total internal reflection occurs.
    """
    cos_i = -(nx * L + ny * M + nz * N)
    flip = np.where(cos_i < 0.0, -1.0, 1.0)
    cos_i = cos_i * flip
    k = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
    ok = k >= 0.0
    cos_t = np.sqrt(np.maximum(k, 0.0))
    g = (mu * cos_i - cos_t) * flip
    return mu * L + g * nx, mu * M + g * ny, mu * N + g * nz, cos_i, cos_t, ok


def fresnel_transmittance(cos_i, cos_t, n1: float, n2: float):
    """Unpolarized Fresnel power transmittance (Ts + Tp)/2 with Ts = 4 n1 n2 ci ct / (n1 ci + n2 ct)^2,
    Tp = 4 n1 n2 ci ct / (n1 ct + n2 ci)^2 (Hecht, Optics §4.6), written with a single division."""
    a = n1 * cos_i + n2 * cos_t
    b = n1 * cos_t + n2 * cos_i
    a2, b2 = a * a, b * b
    return (2.0 * n1 * n2) * cos_i * cos_t * (a2 + b2) / (a2 * b2)


def _rotation(rx_deg: float, ry_deg: float, rz_deg: float) -> np.ndarray:
    """Body rotation Rz @ Ry @ Rx (angles in degrees, right-handed about the frame's axes)."""
    a, b, c = (math.radians(v) for v in (rx_deg, ry_deg, rz_deg))
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _rotate(r: np.ndarray, x, y, z):
    """Apply a 3x3 matrix to vectors given as three arrays."""
    return (r[0, 0] * x + r[0, 1] * y + r[0, 2] * z,
            r[1, 0] * x + r[1, 1] * y + r[1, 2] * z,
            r[2, 0] * x + r[2, 1] * y + r[2, 2] * z)


def direction_vector(angle_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vector in (x right, y down) for angles counterclockwise from +x towards the image top."""
    a = np.radians(angle_deg)
    return np.cos(a), -np.sin(a)


class MainLens:
    """The thick main lens: two spheres, the rim (diameter) as aperture stop on both surfaces."""

    def __init__(self, cfg: CameraConfig) -> None:
        ml = cfg.main_lens
        self.n = ml.refractive_index
        self.mu_in, self.mu_out = 1.0 / self.n, self.n
        self.c1 = 1.0 / ml.radius_front_mm
        self.c2 = 1.0 / ml.radius_back_mm
        self.z2 = ml.thickness_mm
        self.rim2 = (0.5 * ml.diameter_mm) ** 2
        self.fresnel = cfg.trace.fresnel

    def trace(self, r: Rays) -> None:
        """Refract object-side rays (travelling +z) through both surfaces in place; vignetted rays get weight 0."""
        self._surfaces(r, ((0.0, self.c1, 1.0, self.n, self.mu_in), (self.z2, self.c2, self.n, 1.0, self.mu_out)))

    def trace_back(self, r: Rays) -> None:
        """Refract image-side rays travelling -z back out through the front, in place (reversibility)."""
        self._surfaces(r, ((self.z2, self.c2, 1.0, self.n, self.mu_in), (0.0, self.c1, self.n, 1.0, self.mu_out)))

    def _surfaces(self, r: Rays, steps) -> None:
        for zv, c, n1, n2, mu in steps:
            t = intersect_sphere(r.x, r.y, r.z, r.L, r.M, r.N, 0.0, 0.0, zv, c)
            r.advance(t)
            nx, ny, nz = sphere_normal(r.x, r.y, r.z, 0.0, 0.0, zv, c)
            r.L, r.M, r.N, ci, ct, ok = refract(r.L, r.M, r.N, nx, ny, nz, mu)
            keep = ok & (r.x * r.x + r.y * r.y <= self.rim2)  # NaN (a miss) compares False
            r.w = np.where(keep, r.w * (fresnel_transmittance(ci, ct, n1, n2) if self.fresnel else 1.0), 0.0)


class MicrolensArray:
    """The MLA with every lens' own errors, traced lens by lens in one vectorized pass.

    Each lens is looked up from the ray's crossing point (cell = floor((coord - origin) / p)), its
    parameters gathered from flat per-lens tables, and both its surfaces intersected in its own frame.
    Rays that land in another cell than the one first guessed (near cell edges) are re-traced with the
    right lens. Where the two surfaces of a lens cross (its corners) there is no lens (`mla.corners`).
    """

    def __init__(self, cfg: CameraConfig, errors: ErrorMap | None = None) -> None:
        mla = cfg.mla
        rows, cols = mla.count_h, mla.count_w
        errors = errors if errors is not None else ErrorMap.zeros(rows, cols)
        if errors.shape != (rows, cols):
            raise ValueError(f"error map shape {errors.shape} does not match the MLA {rows}x{cols}")
        e = errors.lens
        self.rows, self.cols = rows, cols
        self.p = mla.pitch_um * 1e-3
        self.inv_p = 1.0 / self.p
        self.x0 = -0.5 * cols * self.p
        self.y0 = -0.5 * rows * self.p
        self.n = mla.refractive_index
        self.mu_in = 1.0 / self.n
        self.clear_corners = mla.corners == "clear"
        self.fresnel = cfg.trace.fresnel
        t = mla.thickness_um * 1e-3
        self.z_front = -0.5 * t
        cy, cx = np.meshgrid((np.arange(rows) + 0.5) * self.p + self.y0, (np.arange(cols) + 0.5) * self.p + self.x0, indexing="ij")
        ux, uy = direction_vector(e["pitch_dir_deg"])
        vx, vy = direction_vector(e["decenter_dir_deg"])
        self.fx = (cx + e["pitch_um"] * 1e-3 * ux).ravel()
        self.fy = (cy + e["pitch_um"] * 1e-3 * uy).ravel()
        self.dx = (e["decenter_um"] * 1e-3 * vx).ravel()  # rear vertex relative to the front one
        self.dy = (e["decenter_um"] * 1e-3 * vy).ravel()
        self.c1 = (1.0 / (mla.radius_front_um * 1e-3 * (1.0 + e["radius_front_rel"]))).ravel()
        self.c2 = (1.0 / (mla.radius_back_um * 1e-3 * (1.0 + e["radius_back_rel"]))).ravel()
        self.z_rear = (self.z_front + t + e["thickness_um"] * 1e-3).ravel()
        self.tilted = errors.has_tilt()
        if self.tilted:
            rots = [_rotation(ax, ay, 0.0) for ax, ay in zip(e["tilt_x_deg"].ravel(), e["tilt_y_deg"].ravel())]
            self.rot = np.stack(rots)  # (K, 3, 3), lens frame -> MLA frame

    def cell_of(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat lens index of each point (clipped into range) and whether it lies on the array."""
        col = np.floor((x - self.x0) * self.inv_p)
        row = np.floor((y - self.y0) * self.inv_p)
        inside = (col >= 0) & (col < self.cols) & (row >= 0) & (row < self.rows)
        k = np.where(inside, row * self.cols + col, 0).astype(np.int64)
        return k, inside

    def _to_lens(self, k, x, y, z, L, M, N):
        """Ray position relative to lens k's centre on the mid-plane, in the lens' (tilted) frame."""
        px, py, pz = x - self.fx[k], y - self.fy[k], z
        if not self.tilted:
            return px, py, pz, L, M, N
        rt = np.transpose(self.rot[k], (0, 2, 1))
        return (*_rotate_batch(rt, px, py, pz), *_rotate_batch(rt, L, M, N))

    def _from_lens(self, k, px, py, pz, L, M, N):
        """Inverse of `_to_lens`."""
        if self.tilted:
            r = self.rot[k]
            px, py, pz = _rotate_batch(r, px, py, pz)
            L, M, N = _rotate_batch(r, L, M, N)
        return px + self.fx[k], py + self.fy[k], pz, L, M, N

    def _surface(self, k, x, y, z, L, M, N, rear: bool):
        """Intersect lens k's front or rear sphere; returns hit (MLA frame), local hit and normal, t."""
        px, py, pz, lL, lM, lN = self._to_lens(k, x, y, z, L, M, N)
        if rear:
            vx, vy, vz, c = self.dx[k], self.dy[k], self.z_rear[k], self.c2[k]
        else:
            vx, vy, vz, c = 0.0, 0.0, self.z_front, self.c1[k]
        t = intersect_sphere(px, py, pz, lL, lM, lN, vx, vy, vz, c)
        hx, hy, hz = px + t * lL, py + t * lM, pz + t * lN
        nrm = sphere_normal(hx, hy, hz, vx, vy, vz, c)
        return (hx, hy, hz), (lL, lM, lN), nrm, t

    def _hit(self, k, r: Rays, rear: bool):
        """Intersect the right lens' surface, re-tracing rays whose hit falls in a neighbouring cell."""
        local, ldir, nrm, t = self._surface(k, r.x, r.y, r.z, r.L, r.M, r.N, rear)
        gx, gy, _, _, _, _ = self._from_lens(k, *local, *ldir)
        k2, inside = self.cell_of(gx, gy)
        moved = np.flatnonzero((k2 != k) & inside & np.isfinite(t))
        if moved.size:
            k = k.copy()
            k[moved] = k2[moved]
            sub = [a[moved] for a in (r.x, r.y, r.z, r.L, r.M, r.N)]
            l2, d2, n2, t2 = self._surface(k[moved], *sub, rear)
            local, ldir, nrm = (tuple(_put(a, moved, b) for a, b in zip(g1, g2)) for g1, g2 in ((local, l2), (ldir, d2), (nrm, n2)))
            t = _put(t, moved, t2)
        return k, local, ldir, nrm, np.isfinite(t)

    def trace(self, r: Rays) -> None:
        """Trace rays given in the MLA frame through their lenses, in place (MLA frame out)."""
        t = (self.z_front - r.z) / r.N
        r.advance(t)
        k, on_array = self.cell_of(r.x, r.y)
        k, local, ldir, nrm, hit = self._hit(k, r, rear=False)
        corner = ~self._inside_lens(k, *local)
        L, M, N, ci, ct, ok = refract(*ldir, *nrm, self.mu_in)
        if self.clear_corners:
            L, M, N = (np.where(corner, a, b) for a, b in zip(ldir, (L, M, N)))
            keep = on_array & hit
        else:
            keep = on_array & hit & ~corner
        w = r.w * (np.where(corner, 1.0, fresnel_transmittance(ci, ct, 1.0, self.n)) if self.fresnel else 1.0)
        r.x, r.y, r.z, r.L, r.M, r.N = self._from_lens(k, *local, L, M, N)
        front_state = (r.x, r.y, r.z, r.L, r.M, r.N)
        k, local, ldir, nrm, hit2 = self._hit(k, r, rear=True)
        L, M, N, ci, ct, ok2 = refract(*ldir, *nrm, self.n)
        if self.fresnel:
            w = w * np.where(corner, 1.0, fresnel_transmittance(ci, ct, self.n, 1.0))
        out = self._from_lens(k, *local, L, M, N)
        if self.clear_corners:  # no lens there: the ray goes on straight from the front plane
            out = tuple(np.where(corner, a, b) for a, b in zip(front_state, out))
            hit2, ok2 = hit2 | corner, ok2 | corner
        r.x, r.y, r.z, r.L, r.M, r.N = out
        with np.errstate(invalid="ignore"):
            r.w = np.where(keep & ok & hit2 & ok2, w, 0.0)

    def _inside_lens(self, k, hx, hy, hz):
        """True where the lens has positive thickness under a front-surface point (not a corner)."""
        rx, ry = hx - self.dx[k], hy - self.dy[k]
        c2 = self.c2[k]
        rho2 = rx * rx + ry * ry
        arg = 1.0 - c2 * c2 * rho2
        with np.errstate(invalid="ignore"):
            z_back = self.z_rear[k] + c2 * rho2 / (1.0 + np.sqrt(arg))
        return (arg >= 0.0) & (z_back > hz)


def _rotate_batch(r: np.ndarray, x, y, z):
    """Apply per-ray 3x3 matrices r (n, 3, 3) to vectors given as three arrays."""
    return (r[:, 0, 0] * x + r[:, 0, 1] * y + r[:, 0, 2] * z,
            r[:, 1, 0] * x + r[:, 1, 1] * y + r[:, 1, 2] * z,
            r[:, 2, 0] * x + r[:, 2, 1] * y + r[:, 2, 2] * z)


def _put(a: np.ndarray, idx: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Copy of a with a[idx] = b (a may be a scalar broadcast)."""
    out = np.array(np.broadcast_to(a, idx.shape if np.ndim(a) == 0 else np.shape(a)), dtype=float, copy=True)
    out[idx] = b
    return out


class Camera:
    """Main lens + MLA (with global assembly errors) + sensor plane: traces object-space rays to pixels."""

    def __init__(self, cfg: CameraConfig, errors: ErrorMap | None = None) -> None:
        self.cfg = cfg
        self.layout = cfg.layout
        self.errors = errors if errors is not None else ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w)
        self.main = MainLens(cfg)
        self.mla = MicrolensArray(cfg, self.errors)
        g = self.errors.globals
        self.rot = _rotation(g["mla_tilt_x_deg"], g["mla_tilt_y_deg"], -g["mla_rotation_deg"])
        self.rotated = not np.allclose(self.rot, np.eye(3), rtol=0, atol=0)
        self.z_mla = self.layout.z_mla_mm
        self.shift_x = g["mla_shift_x_um"] * 1e-3
        self.shift_y = g["mla_shift_y_um"] * 1e-3
        self.z_sensor = self.layout.z_sensor_mm + g["mla_sensor_distance_um"] * 1e-3
        s = cfg.sensor
        self.pixel = s.pixel_um * 1e-3
        self.inv_pixel = 1.0 / self.pixel
        self.width, self.height = s.width_px, s.height_px
        self.sx0 = -0.5 * s.width_px * self.pixel
        self.sy0 = -0.5 * s.height_px * self.pixel

    def to_mla(self, r: Rays) -> None:
        """Camera frame -> MLA frame (translate to the MLA's centre, undo its rotation/tilt)."""
        r.x = r.x - self.shift_x
        r.y = r.y - self.shift_y
        r.z = r.z - self.z_mla
        if self.rotated:
            rt = self.rot.T
            r.x, r.y, r.z = _rotate(rt, r.x, r.y, r.z)
            r.L, r.M, r.N = _rotate(rt, r.L, r.M, r.N)

    def from_mla(self, r: Rays) -> None:
        """MLA frame -> camera frame."""
        if self.rotated:
            r.x, r.y, r.z = _rotate(self.rot, r.x, r.y, r.z)
            r.L, r.M, r.N = _rotate(self.rot, r.L, r.M, r.N)
        r.x = r.x + self.shift_x
        r.y = r.y + self.shift_y
        r.z = r.z + self.z_mla

    def trace_to_mla(self, r: Rays) -> None:
        """Object space -> through the main lens, in place (camera frame)."""
        self.main.trace(r)

    def trace(self, r: Rays) -> None:
        """Object space -> sensor plane, in place; r.x, r.y are then sensor coordinates in mm."""
        self.main.trace(r)
        self.trace_behind_main(r)

    def trace_behind_main(self, r: Rays) -> None:
        """Rays already past the main lens (camera frame) -> through the MLA -> sensor plane, in place."""
        self.to_mla(r)
        self.mla.trace(r)
        self.from_mla(r)
        r.advance((self.z_sensor - r.z) / r.N)

    def pixel_index(self, r: Rays) -> tuple[np.ndarray, np.ndarray]:
        """Flat pixel index (row * W + col) and weight of rays that landed on the sensor with weight > 0."""
        with np.errstate(invalid="ignore"):
            col = np.floor((r.x - self.sx0) * self.inv_pixel)
            row = np.floor((r.y - self.sy0) * self.inv_pixel)
            good = (r.w > 0) & (col >= 0) & (col < self.width) & (row >= 0) & (row < self.height)
        idx = (row[good] * self.width + col[good]).astype(np.int64)
        return idx, r.w[good]
