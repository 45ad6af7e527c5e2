"""Exact, vectorized sequential ray tracing through the main lens and a per-lens-perturbed MLA.

Frame: x to the right of the raw image (towards larger n), y down (towards larger m), z along the light;
z = 0 at the main lens' front vertex, lengths in mm. Rays are structure-of-arrays (x, y, z, L, M, N, w);
a ray that misses, is vignetted or totally reflected gets weight 0 (masked, never removed mid-trace).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mlaqc.errors import InputError
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.errormap import ErrorMap

# INV_ROW_PAIR_HEX, hex_cell: the NumPy reference's hex cell rule (the compiled engine has its own copy, hex_locate)
from mlaqc.optics.lattice import (  # noqa: F401
    INV_ROW_PAIR_HEX,
    Lattice,
    hex_cell,
    hex_edge,
    neighbour_offsets,
)


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
    """The thick main lens: two spheres, the rim (diameter) as aperture stop on both surfaces. An ideal
    main lens (datasheet numbers) is two unbounded planes of air at its exit pupil: image-side rays pass
    unchanged (weight 1 to rounding; the exit pupil disc where they start is its stop)."""

    def __init__(self, cfg: CameraConfig) -> None:
        ml = cfg.main_lens
        self.fresnel = cfg.trace.fresnel
        if ml.ideal:
            self.n, self.mu_in, self.mu_out = 1.0, 1.0, 1.0
            self.c1 = self.c2 = self.z2 = 0.0
            self.rim2 = math.inf
            return
        self.n = ml.refractive_index
        self.mu_in, self.mu_out = 1.0 / self.n, self.n
        self.c1 = 1.0 / ml.radius_front_mm
        self.c2 = 1.0 / ml.radius_back_mm
        self.z2 = ml.thickness_mm
        self.rim2 = (0.5 * ml.diameter_mm) ** 2

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


@dataclass(frozen=True)
class LensChoice:
    """Which lens each ray went through (flat indices row * cols + col), from `MicrolensArray.lens_of`."""

    front: np.ndarray  # lens whose front surface the ray entered
    rear: np.ndarray  # lens whose rear surface it left (meaningless where corner)
    corner: np.ndarray  # True where the front hit is outside every lens' material (`mla.corners`)
    after_front: Rays  # the rays just after the front surface (MLA frame), for checks of the rear choice
    gap: np.ndarray | None = None  # True where the front hit is outside every lens' circle (`mla.gap`)


class MicrolensArray:
    """The MLA with every lens' own errors, traced lens by lens in one vectorized pass.

    Each lens is looked up from the ray's crossing point (its design cell: the square floor((coord -
    origin) / p), or on a hex array (`mla.packing`) the hexagon of the nearest lattice point, `hex_cell`;
    centres from mlaqc.optics.lattice), its parameters gathered from flat per-lens tables, and both its
    surfaces intersected in its own frame. Where the two surfaces of a lens cross (its corners) there is no
    lens (`mla.corners`).

    Lens boundaries (`mla.boundaries`):

    - 'grid': a ray belongs to the lens of the design-grid cell its surface hit lies in; rays whose hit
      lands in another cell than the one first guessed are re-traced once with that cell's lens. A pitch
      error moves a lens' surfaces, not its square aperture.
    - 'sag-intersection': a 100 %-fill array replicated from a master, whose lenses end where their sags
      meet. The material is the union of the lenses' solids, so its front surface is the lower envelope
      z = min_k front_k(x, y) of the front spheres (curvature c1 > 0, material behind) and its rear
      surface the upper envelope max_k rear_k(x, y) of the rear spheres (c2 < 0, material in front). A ray
      (travelling +z, far steeper than the surfaces) crosses each envelope once: it enters the front
      sphere it meets first (argmin of the distance t over the candidates) and leaves by the rear sphere
      it meets last (argmax of t); refraction uses the winning sphere's normal. Two equal lenses meet on
      the perpendicular bisector of their vertices (a lens shifted by Δ moves its boundaries by Δ/2, a
      rear-surface decenter δ moves only the rear boundaries by δ/2); unequal radii or vertex heights
      (radius, thickness, tilt errors) move the boundary to where the two sags are equal. Candidates are
      the 3 x 3 lenses around the cell of the hit (hex: the cell and its 6 neighbours); only rays whose hit
      lies within a per-cell margin of
      their cell's edge (or in another cell) need them (`boundary_margins_mm`), the others keep the lens
      of their cell. Corners: the front hit lies outside the union of the lenses' rear regions (no lens
      has material there); on the design array that is the grid mode's corner.

    Circle apertures (`mla.aperture = "circle"`, either packing; `boundaries` does not apply: circles do
    not meet): a ray belongs to the lens whose circle (diameter `mla.aperture_diameter_um`, about its
    front vertex, in its frame: it moves with the lens) holds its hit on that lens' front sphere, and
    leaves by the same lens' rear. A hit in no circle meets the flat substrate between them (`mla.gap`):
    'opaque' absorbs it, 'clear' lets it go on undeviated and without Fresnel loss, as a clear corner does
    (a thin flat plate's lateral shift and its ~2 x 4.8 % reflection are left out).

    `mla.black_matrix_um` (all modes): an opaque mask of that width centred on the design cell edges (grid
    lines or hexagon sides) in the front vertex plane; a ray crossing that plane within half the width of
    an edge is absorbed.
    """

    def __init__(self, cfg: CameraConfig, errors: ErrorMap | None = None) -> None:
        mla = cfg.mla
        rows, cols = mla.count_h, mla.count_w
        errors = errors if errors is not None else ErrorMap.zeros(rows, cols, mla.packing)
        if errors.shape != (rows, cols):
            raise ValueError(f"error map shape {errors.shape} does not match the MLA {rows}x{cols}")
        if errors.packing != mla.packing:
            raise InputError(f"the error map is for a {errors.packing} lattice but the camera's MLA is "
                             f"{mla.packing} (mla.packing)")
        e = errors.lens
        self.rows, self.cols = rows, cols
        self.lattice = Lattice.of(cfg)
        self.hex = self.lattice.hex
        self.p = mla.pitch_um * 1e-3
        self.inv_p = 1.0 / self.p
        if self.hex:  # (x0, y0): U(1,1)'s centre; (x - x0) / p, (y - y0) / p are lattice units (hex_cell)
            u0, v0 = self.lattice.centre_uv()
            self.x0, self.y0 = -u0 * self.p, -v0 * self.p
            cx, cy = self.lattice.centres()
        else:  # (x0, y0): the first cell's corner (the formulas of the square-only tracer, bit for bit)
            self.x0 = -0.5 * cols * self.p
            self.y0 = -0.5 * rows * self.p
            cy, cx = np.meshgrid((np.arange(rows) + 0.5) * self.p + self.y0, (np.arange(cols) + 0.5) * self.p + self.x0,
                                 indexing="ij")
        self.n = mla.refractive_index
        self.mu_in = 1.0 / self.n
        self.clear_corners = mla.corners == "clear"
        self.fresnel = cfg.trace.fresnel
        t = mla.thickness_um * 1e-3
        self.z_front = -0.5 * t
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
        self.circle = mla.aperture == "circle"
        self.clear_gap = mla.gap == "clear"
        self.r_circle = 0.5 * (mla.aperture_diameter_um or 0.0) * 1e-3
        self.sag = mla.boundaries == "sag-intersection" and not self.circle
        self.half_black_mm = 0.5 * mla.black_matrix_um * 1e-3
        self.gx, self.gy = cx.ravel(), cy.ravel()  # design centres
        self.c1_design = 1.0 / (mla.radius_front_um * 1e-3)
        self.c2_design = 1.0 / (mla.radius_back_um * 1e-3)
        self.z_rear_design = self.z_front + t
        zero = np.zeros(rows * cols)
        self._side_margins: dict[bool, tuple[np.ndarray, np.ndarray]] = {}  # side_margins_mm, once per side
        self.margin_front, self.margin_rear = self.boundary_margins_mm() if self.sag else (zero, zero)
        self.circle_reach = self.circle_reach_mm() if self.circle else np.zeros(rows * cols)

    def sphere_offsets_mm(self, rear: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per lens, how its front or rear sphere departs from the design one, in the MLA frame: the
        lateral offset |u| of the sphere's centre from the design centre (pitch, decenter and tilt: a lens
        tilted by a about its centre moves its centre of curvature sideways by about |R| a), the offset w
        of its vertex height (thickness error; tilt), and its radius R (signed, as c)."""
        if rear:
            vx, vy, vz, radius, vz0 = self.dx, self.dy, self.z_rear, 1.0 / self.c2, self.z_rear_design
        else:
            zero = np.zeros_like(self.fx)
            vx, vy, vz, radius, vz0 = zero, zero, np.full_like(self.fx, self.z_front), 1.0 / self.c1, self.z_front
        cx, cy, cz = vx, vy, vz + radius  # centre of curvature in the lens frame
        if self.tilted:
            cx, cy, cz = _rotate_batch(self.rot, cx, cy, cz)
        u = np.hypot(self.fx + cx - self.gx, self.fy + cy - self.gy)
        w = (cz - radius) - vz0
        return u, w, radius

    def boundary_margins_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Per cell, how far (mm) inside its edges a neighbour's region can reach, front and rear surface.

        A point x of cell k at distance >= margin from its edges belongs to lens k whatever the errors:
        the sag-intersection fast path keeps lens k there. Bound (front; the rear is the same with |R|):
        write every lens' surface height as the design sphere H(rho) = z_v + R0 - sqrt(R0^2 - rho^2) of its
        design centre, raised by its vertex height offset w (signed), plus a shape error
        |h_i(x) - H(rho_i) - w_i| <= A_i(rho_i) with (mean-value theorem, exact)
            A(rho) = |sag_R(rho + |u|) - sag_R0(rho + |u|)| + |u| sag'_R0(rho + |u|),
        sag_R(r) = R - sqrt(R^2 - r^2), sag'(r) = r / sqrt(R0^2 - r^2) (u, w, R: `sphere_offsets_mm`).
        With Q = rho_i^2 - rho_k^2 the design heights differ by
            H(rho_i) - H(rho_k) = Q / (sqrt(R0^2 - rho_k^2) + sqrt(R0^2 - rho_i^2)) >= Q / 2R0,
        so lens k is strictly lowest at x if Q / 2R0 > (w_k - w_i) + A_i(rho_i) + A_k(rho_k) (the rear,
        highest wins: w_i - w_k; `_lead`). A lens standing towards winning by its vertex height alone keeps
        its whole cell against that neighbour, which gets the margin on its side. In a square cell k
        rho_k <= p/sqrt(2) and rho_i^2 <= p^2/2 + Q; at distance >= d from the cell's edges Q >= 2 p d (edge
        neighbours; >= 4 p d diagonally). In a hexagonal cell rho_k <= p/sqrt(3) (its vertices) and
        rho_i^2 <= p^2/3 + Q, and Q >= 2 p d holds for all 6 neighbours (each is one pitch away across a
        side: Q = 2 p times the distance to that side). Per pair (k, i) the smallest d* >= 0 with
        g(d) = 2 p d / 2R0 - lead - A_i - A_k > 0 is
        found by fixed-point iteration (to first order the boundary moves by (|u_i| + |u_k|)/sqrt(2) at a
        cell corner, |u|/2 mid-edge, and by R0 |w_i - w_k| / p for a vertex height difference, into the cell
        of the lens standing lower (front) / higher (rear): a 1 µm thickness error moves the rear boundaries
        ~4.7 µm); g is then checked on a grid up to d = p, and
        a cell whose bound fails there gets margin p (every ray brute-forced). Margin = max over the 8
        (hex: 6) neighbours of d* (+ 1 nm). Cells whose whole neighbourhood is error-free get 0: equal lenses meet
        exactly on the grid lines. Lenses two cells away are assumed never to win (errors well below p).
        """
        return self.side_margins_mm(False)[0].max(axis=1), self.side_margins_mm(True)[0].max(axis=1)

    def side_margins_mm(self, rear: bool) -> tuple[np.ndarray, np.ndarray]:
        """Per cell k and candidate i (`neighbours` order, axis 1): the pair's margin d* (mm, see
        boundary_margins_mm; 0 where neither lens is flawed, p where the bound fails), and whether i is a
        neighbour on the array (False for the cell itself and candidates off the array, whose d* is 0).
        Computed once per side (the cell margins and the compiled engine's pair clearances both read it;
        read-only arrays)."""
        if rear not in self._side_margins:
            d, on = self._pair_margins(rear)
            d.setflags(write=False)
            on.setflags(write=False)
            self._side_margins[rear] = d, on
        return self._side_margins[rear]

    def _pair_margins(self, rear: bool) -> tuple[np.ndarray, np.ndarray]:
        """side_margins_mm, computed: each flawed pair's _pair_margin, candidate direction by direction."""
        cands = self.neighbours(self.gx, self.gy)
        k_all = np.arange(self.rows * self.cols)
        on = np.stack([ok & (nb != k_all) for nb, ok in cands], axis=1)
        if (self.c2_design if rear else self.c1_design) == 0.0:  # a flat side (plano-convex): one plane, no
            return np.zeros(on.shape), on  # boundaries between lenses: each point is its own cell's
        u, w, radius = self.sphere_offsets_mm(rear)
        r0 = abs(1.0 / (self.c2_design if rear else self.c1_design))
        ra = np.abs(radius)
        flawed = (u > 1e-9) | (np.abs(w) > 1e-9) | (np.abs(ra - r0) > 1e-12 * r0)  # mm; rounding is not an error
        d = np.zeros(on.shape)
        for j, (nb, ok) in enumerate(cands):
            k = k_all[on[:, j]]
            i = nb[k]
            pair = flawed[k] | flawed[i]
            k, i = k[pair], i[pair]
            if k.size:
                d[k, j] = _pair_margin(self.p, r0, u[i], ra[i], u[k], ra[k], _lead(w, k, i, rear), self.hex)
        return d, on

    def pair_clearance_mm2(self, rear: bool) -> np.ndarray:
        """Per cell k and candidate i (`neighbours` order, axis 1), the Q = rho_i^2 - rho_k^2 (mm^2, distances
        from the design centres) beyond which lens i cannot reach point x of cell k (see boundary_margins_mm:
        the bound holds pair by pair, Q = 2 p d with d the pair's margin), + 2 p x 1 nm; -inf for the cell
        itself and candidates off the array, +inf where the pair's bound fails. The compiled engine's
        re-trace keeps / takes the cell's lens without scanning the candidates where every Q clears it."""
        d, on = self.side_margins_mm(rear)
        return np.where(on, np.where(d >= 0.5 * self.p, np.inf, 2.0 * self.p * (d + 1e-6)), -np.inf)

    def circle_clearance_mm(self) -> np.ndarray:
        """Per cell, the largest distance (mm) from its nearest edge at which a front hit can lie in a
        neighbour's circle: a point e from cell k's edges is >= p/2 + e from every neighbour's design centre,
        and lens i's circle holds only hits within r_circle + its own reach (front vertex move and tilt
        swing, `circle_reach_mm`'s terms) of its design centre. Negative (no hit of the cell can be a
        neighbour's) on a design array whose circles leave gaps; the compiled engine's gap test."""
        move = np.hypot(self.fx - self.gx, self.fy - self.gy)
        own = self._circle_own_reach_mm(move)
        nb = self.lattice.neighbours(diagonal=True)
        near = np.max(np.where(nb >= 0, own[np.maximum(nb, 0)], -np.inf), axis=1, initial=-np.inf)
        return self.r_circle + near - 0.5 * self.p

    def _circle_own_reach_mm(self, move: np.ndarray) -> np.ndarray:
        """Per lens, how far beyond r_circle from its design centre a front hit in its circle can lie (see
        circle_reach_mm), + 1 nm."""
        rim = self.r_circle + float(move.max(initial=0.0))
        sag = float(_sag_abs(np.abs(1.0 / self.c1), min(rim, 0.999 * np.abs(1.0 / self.c1).min())).max())
        if self.tilted:
            cos_tilt = np.clip(self.rot[:, 2, 2], -1.0, 1.0)
            move = move + (abs(self.z_front) + sag) * np.sqrt(1.0 - cos_tilt ** 2) + rim * (1.0 - cos_tilt)
        return move + sag + 1e-6

    def circle_reach_mm(self) -> np.ndarray:
        """Per cell, how far (mm) beyond the circles' radius from the cell's design centre a front hit can
        still lie in some lens' circle: the largest lateral move of a front vertex (pitch error; a tilt's
        swing) among the cell's lens and its neighbours, plus how far apart two spheres' hits of one ray can
        lie (their height difference, at most the rim sag, times the ray's slope, taken <= 1), + 1 nm. Hits
        farther out are in the gap (`_hit_circle`): a point of a cell is nearest that cell's design centre."""
        move = np.hypot(self.fx - self.gx, self.fy - self.gy)
        rim = self.r_circle + float(move.max(initial=0.0))
        sag = float(_sag_abs(np.abs(1.0 / self.c1), min(rim, 0.999 * np.abs(1.0 / self.c1).min())).max())
        if self.tilted:
            cos_tilt = np.clip(self.rot[:, 2, 2], -1.0, 1.0)
            move = move + (abs(self.z_front) + sag) * np.sqrt(1.0 - cos_tilt ** 2) + rim * (1.0 - cos_tilt)
        nb = self.lattice.neighbours(diagonal=True)
        near = np.max(np.where(nb >= 0, move[np.maximum(nb, 0)], 0.0), axis=1, initial=0.0)
        return np.maximum(move, near) + sag + 1e-6

    def _hit_circle(self, k, r: Rays):
        """'circle' apertures: the lens whose circle (radius r_circle about its front vertex, in its frame)
        holds the ray's hit on that lens' front sphere: lens k (the front-plane crossing's cell) first,
        then the candidates around the cell of k's hit (`neighbours` order). Only hits within
        r_circle + circle_reach of their cell's design centre can lie in another lens' circle; the others
        outside k's circle are in the gap. Returns k, local hit, direction, normal, hit, gap."""
        local, ldir, nrm, t = self._surface(k, r.x, r.y, r.z, r.L, r.M, r.N, rear=False)
        r2 = self.r_circle * self.r_circle
        with np.errstate(invalid="ignore"):
            gap = ~(local[0] * local[0] + local[1] * local[1] <= r2)
            gx, gy, _, _, _, _ = self._from_lens(k, *local, *ldir)
            k2, on = self.cell_of(gx, gy)  # off the array: every candidate round the clipped cell is tried
            near = ~on | ((gx - self.gx[k2]) ** 2 + (gy - self.gy[k2]) ** 2 <= (self.r_circle + self.circle_reach[k2]) ** 2)
        todo = np.flatnonzero(gap & near & np.isfinite(t))
        if todo.size:
            sub = [a[todo] for a in (r.x, r.y, r.z, r.L, r.M, r.N)]
            kb = k[todo].copy()
            found = np.zeros(todo.size, dtype=bool)
            for kc, ok in self.neighbours(gx[todo], gy[todo]):
                lc, _, _, tc = self._surface(kc, *sub, rear=False)
                with np.errstate(invalid="ignore"):
                    take = ok & ~found & (lc[0] * lc[0] + lc[1] * lc[1] <= r2) & np.isfinite(tc)
                kb = np.where(take, kc, kb)
                found |= take
            sel, kb = todo[found], kb[found]
            if sel.size:
                k = k.copy()
                k[sel] = kb
                l2, d2, n2, t2 = self._surface(kb, *(a[sel] for a in (r.x, r.y, r.z, r.L, r.M, r.N)), rear=False)
                local, ldir, nrm = (tuple(_put(a, sel, b) for a, b in zip(g1, g2)) for g1, g2 in ((local, l2), (ldir, d2), (nrm, n2)))
                t = _put(t, sel, t2)
                gap = gap.copy()
                gap[sel] = False
        return k, local, ldir, nrm, np.isfinite(t), gap

    def cell_of(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat lens index of each point's design cell (square or hexagon; clipped into range) and whether
        it lies on the array."""
        if self.hex:
            row, col, _, _ = hex_cell((x - self.x0) * self.inv_p, (y - self.y0) * self.inv_p)
        else:
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
        self._trace(r, record=False)

    def lens_of(self, r: Rays) -> LensChoice:
        """Which lenses the rays (MLA frame; left unchanged) go through: for tests and diagnostics."""
        r = Rays(*(np.array(a, dtype=float, copy=True) for a in (r.x, r.y, r.z, r.L, r.M, r.N, r.w)))
        return self._trace(r, record=True)

    def _trace(self, r: Rays, record: bool) -> LensChoice | None:
        t = (self.z_front - r.z) / r.N
        r.advance(t)
        k, on_array = self.cell_of(r.x, r.y)
        if self.half_black_mm > 0.0:
            on_array = on_array & ~self.black_matrix(r.x, r.y)
        gap = False
        if self.circle:
            k, local, ldir, nrm, hit, gap = self._hit_circle(k, r)
            corner = ~self._inside_lens(k, *local) & ~gap  # the gap is flat substrate: no corner there
        elif self.sag:
            k, local, ldir, nrm, hit = self._hit_sag(k, r, rear=False)
            corner = self._corner_sag(k, *local)
        else:
            k, local, ldir, nrm, hit = self._hit(k, r, rear=False)
            corner = ~self._inside_lens(k, *local)
        k_front = k
        L, M, N, ci, ct, ok = refract(*ldir, *nrm, self.mu_in)
        absorbed = (corner & (not self.clear_corners)) | (gap & (not self.clear_gap))
        straight = corner | gap  # no lens: a clear corner or gap passes undeviated, without Fresnel loss
        if self.clear_corners or (self.circle and self.clear_gap):
            L, M, N = (np.where(straight, a, b) for a, b in zip(ldir, (L, M, N)))
        keep = on_array & hit & ~absorbed
        w = r.w * (np.where(straight, 1.0, fresnel_transmittance(ci, ct, 1.0, self.n)) if self.fresnel else 1.0)
        r.x, r.y, r.z, r.L, r.M, r.N = self._from_lens(k, *local, L, M, N)
        front_state = (r.x, r.y, r.z, r.L, r.M, r.N)
        after_front = Rays(*front_state, np.where(keep & ok, w, 0.0)) if record else None
        if self.circle:  # the circle's lens, front and rear
            local, ldir, nrm, t2 = self._surface(k, r.x, r.y, r.z, r.L, r.M, r.N, rear=True)
            hit2 = np.isfinite(t2)
        else:
            k, local, ldir, nrm, hit2 = (self._hit_sag if self.sag else self._hit)(k, r, rear=True)
        L, M, N, ci, ct, ok2 = refract(*ldir, *nrm, self.n)
        if self.fresnel:
            w = w * np.where(straight, 1.0, fresnel_transmittance(ci, ct, self.n, 1.0))
        out = self._from_lens(k, *local, L, M, N)
        if self.clear_corners or (self.circle and self.clear_gap):  # no lens there: straight on from the front
            out = tuple(np.where(straight, a, b) for a, b in zip(front_state, out))
            hit2, ok2 = hit2 | straight, ok2 | straight
        r.x, r.y, r.z, r.L, r.M, r.N = out
        with np.errstate(invalid="ignore"):
            r.w = np.where(keep & ok & hit2 & ok2, w, 0.0)
        return LensChoice(k_front, k, corner, after_front, gap & np.ones_like(corner)) if record else None

    def black_matrix(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """True where a point of the front vertex plane (MLA frame) lies under the black matrix: within
        half its width of a design cell edge (grid line or hexagon side)."""
        if self.hex:
            return self.edge_distance(x, y) < self.half_black_mm
        u = (x - self.x0) * self.inv_p
        v = (y - self.y0) * self.inv_p
        fu, fv = u - np.floor(u), v - np.floor(v)
        return (self.p * np.minimum(fu, 1.0 - fu) < self.half_black_mm) | (self.p * np.minimum(fv, 1.0 - fv) < self.half_black_mm)

    def edge_distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Distance (mm) of MLA-plane points from the nearest edge of the design cell they lie in."""
        u = (x - self.x0) * self.inv_p
        v = (y - self.y0) * self.inv_p
        if self.hex:
            _, _, du, dv = hex_cell(u, v)
            return self.p * hex_edge(du, dv)
        fu, fv = u - np.floor(u), v - np.floor(v)
        return self.p * np.minimum(np.minimum(fu, 1.0 - fu), np.minimum(fv, 1.0 - fv))

    def neighbours(self, x: np.ndarray, y: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """The candidate lenses around the design cell of each point (clipped onto the array): square the
        3 x 3 cells row-major, hex the cell then its 6 neighbours (lattice.neighbour_offsets order); a list
        of (flat index, exists) pairs; the order is the tie-break (first wins)."""
        if self.hex:
            r, c, _, _ = hex_cell((x - self.x0) * self.inv_p, (y - self.y0) * self.inv_p)
            row, col = np.clip(r, 0, self.rows - 1), np.clip(c, 0, self.cols - 1)
            odd = (row % 2).astype(bool)
            steps = [(0, 0, 0)] + [(dr, dc0, dc1) for (dr, dc0), (_, dc1) in
                                   zip(neighbour_offsets("hex", 0), neighbour_offsets("hex", 1))]
            pairs = [(row + dr, col + np.where(odd, dc1, dc0)) for dr, dc0, dc1 in steps]
        else:
            col = np.clip(np.floor((x - self.x0) * self.inv_p), 0, self.cols - 1)
            row = np.clip(np.floor((y - self.y0) * self.inv_p), 0, self.rows - 1)
            pairs = [(row + dr, col + dc) for dr in (-1.0, 0.0, 1.0) for dc in (-1.0, 0.0, 1.0)]
        out = []
        for rr, cc in pairs:
            ok = (rr >= 0) & (rr < self.rows) & (cc >= 0) & (cc < self.cols)
            out.append((np.where(ok, rr * self.cols + cc, 0).astype(np.int64), ok))
        return out

    def _hit_sag(self, k, r: Rays, rear: bool):
        """'sag-intersection' lookup: lens k's surface first; rays whose hit is near their cell's edge
        (within the cell's margin) or in another cell take the first-met front / last-met rear sphere of
        the 3 x 3 lenses around the hit's cell (hex: the cell and its 6 neighbours)."""
        local, ldir, nrm, t = self._surface(k, r.x, r.y, r.z, r.L, r.M, r.N, rear)
        gx, gy, _, _, _, _ = self._from_lens(k, *local, *ldir)
        k2, inside = self.cell_of(gx, gy)
        margin = self.margin_rear if rear else self.margin_front
        with np.errstate(invalid="ignore"):
            near = (k2 != k) | ~inside | (self.edge_distance(gx, gy) < margin[k])
        todo = np.flatnonzero(near & np.isfinite(t))
        if todo.size:
            sub = [a[todo] for a in (r.x, r.y, r.z, r.L, r.M, r.N)]
            kb = self.extreme_lens(k[todo], t[todo], gx[todo], gy[todo], *sub, rear)
            k = k.copy()
            k[todo] = kb
            l2, d2, n2, t2 = self._surface(kb, *sub, rear)
            local, ldir, nrm = (tuple(_put(a, todo, b) for a, b in zip(g1, g2)) for g1, g2 in ((local, l2), (ldir, d2), (nrm, n2)))
            t = _put(t, todo, t2)
        return k, local, ldir, nrm, np.isfinite(t)

    def extreme_lens(self, k, t_k, gx, gy, x, y, z, L, M, N, rear: bool) -> np.ndarray:
        """Brute force over the candidate lenses around the cell of (gx, gy) (`neighbours`): the front sphere met first
        (smallest t) or the rear sphere met last (largest t), starting from lens k met at t_k (it keeps
        a tie; among the others the first in row-major order wins); misses are skipped."""
        best_k = np.array(k, dtype=np.int64, copy=True)
        best_t = np.array(t_k, dtype=float, copy=True)
        for kc, ok in self.neighbours(gx, gy):
            _, _, _, t = self._surface(kc, x, y, z, L, M, N, rear)
            with np.errstate(invalid="ignore"):
                better = (t < best_t) if not rear else (t > best_t)
            take = ok & (kc != best_k) & np.isfinite(t) & (better | np.isnan(best_t))
            best_k = np.where(take, kc, best_k)
            best_t = np.where(take, t, best_t)
        return best_k

    def _corner_sag(self, k, hx, hy, hz) -> np.ndarray:
        """'sag-intersection' corners: the front hit (lens k's frame) lies outside the union of the lenses'
        rear regions. Far from its cell's edge (rear margin) only lens k's rear can hold it; inside lens k's
        own rear region it is in the union (no scan of the neighbours)."""
        corner = ~self._inside_lens(k, hx, hy, hz)
        gx, gy, gz, _, _, _ = self._from_lens(k, hx, hy, hz, 0.0, 0.0, 0.0)  # a point: no direction
        k2, inside = self.cell_of(gx, gy)
        with np.errstate(invalid="ignore"):
            near = (k2 != k) | ~inside | (self.edge_distance(gx, gy) < self.margin_rear[k])
        todo = np.flatnonzero(near & np.isfinite(hz) & corner)  # inside lens k's own rear region: no corner
        if todo.size:
            px, py, pz = gx[todo], gy[todo], gz[todo]
            any_in = np.zeros(todo.size, dtype=bool)
            for kc, ok in self.neighbours(px, py):
                lx, ly, lz, _, _, _ = self._to_lens(kc, px, py, pz, 0.0, 0.0, 0.0)
                any_in |= ok & self._inside_lens(kc, lx, ly, lz)
            corner = corner.copy()
            corner[todo] = ~any_in
        return corner

    def _inside_lens(self, k, hx, hy, hz):
        """True where the lens has positive thickness under a front-surface point (not a corner)."""
        rx, ry = hx - self.dx[k], hy - self.dy[k]
        c2 = self.c2[k]
        rho2 = rx * rx + ry * ry
        arg = 1.0 - c2 * c2 * rho2
        with np.errstate(invalid="ignore"):
            z_back = self.z_rear[k] + c2 * rho2 / (1.0 + np.sqrt(arg))
        return (arg >= 0.0) & (z_back > hz)


def _sag_abs(radius, rho):
    """Sag magnitude of a sphere of radius |radius| at height rho (NaN beyond the sphere)."""
    return radius - np.sqrt(radius * radius - rho * rho)


def _shape_error(rho, u, radius, r0):
    """Bound A(rho) on a surface's height error against the design sphere moved to its vertex height
    (radius and lateral offset; see boundary_margins_mm)."""
    r = rho + u
    return np.abs(_sag_abs(radius, r) - _sag_abs(r0, r)) + u * r / np.sqrt(r0 * r0 - r * r)


def _lead(w: np.ndarray, k: np.ndarray, i: np.ndarray, rear: bool) -> np.ndarray:
    """How far (mm, signed) lens k's vertex height stands towards losing to lens i's: the front surface met
    first is the lowest, so w_k - w_i there; the rear met last is the highest, so w_i - w_k."""
    return w[i] - w[k] if rear else w[k] - w[i]


def _pair_margin(p: float, r0: float, u_i, r_i, u_k, r_k, lead, hexagonal: bool = False) -> np.ndarray:
    """Smallest d >= 0 (mm) beyond which neighbour i cannot reach into cell k (see boundary_margins_mm); p
    where the bound fails anywhere up to d = p. A cell's farthest point from its centre: the square's
    corner p/sqrt(2), the hexagon's vertex p/sqrt(3). `lead` (`_lead`) is signed: a lens whose vertex
    stands towards winning keeps its whole cell against a neighbour that differs from it in height alone."""
    rho_max = p / math.sqrt(3.0) if hexagonal else p / math.sqrt(2.0)
    rho2_max = p * p / 3.0 if hexagonal else 0.5 * p * p
    e_k = _shape_error(np.full_like(u_k, rho_max), u_k, r_k, r0) + lead

    def rhs_d(d):  # the d at which the design height gap 2 p d / 2R0 equals lead + A_i + A_k
        with np.errstate(invalid="ignore"):
            return (_shape_error(np.sqrt(rho2_max + 2.0 * p * d), u_i, r_i, r0) + e_k) * r0 / p

    d = np.zeros_like(u_k)
    for _ in range(60):  # increasing from 0 to the smallest root; contraction ratio ~ |u|/R0 + |eps|
        d = np.clip(rhs_d(d), 0.0, p)
    d = np.where(np.isfinite(d), d + 1e-6, p)  # + 1 nm: strictly beyond the root
    grid = d[:, None] + (p - d[:, None]) * np.linspace(0.0, 1.0, 65)[None, :]
    with np.errstate(invalid="ignore"):
        holds = np.all(grid > rhs_d(grid.T).T, axis=1)  # NaN (a sphere too small for the cell) fails
    return np.where(holds & (d < 0.5 * p), d, p)


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
        self.errors = errors if errors is not None else ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w, cfg.mla.packing)
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
        self.pixel = cfg.pixel_at_mla_um * 1e-3  # a relay's sensor, seen in the MLA's focal plane
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
