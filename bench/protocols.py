"""Candidate measurement protocols for bench/type_separation.py: one extra frame (or a series) of the same
MLA in the same Table 1 camera, each a config change plus a scene.

All frames start from the f-number-matched layout FROZEN (object and MLA distances written into
cfg.geometry), so that stopping the main lens down or changing the wavelength does not move the MLA:
`cfg.layout` would otherwise re-derive the distances from the new diameter or index. `frozen`,
`stopped` (which freezes first), `object_for_image_offset` and `magnification` come from
mlaqc.optics.throughfocus, the through-focus protocol's home.

- white: the calibration image (Lambertian plane), full aperture f/2.5, 632.8 nm.
- stop f/N: the same with the main lens' rim diameter cut to f/N. In this tracer the rim is checked on
  both surfaces (`MainLens`), so the stop is where the clip happens first: on axis, the front surface
  (a converging beam is narrower at the rear one). `stop_check` measures how far that is from a single iris.
- lambda: the white image at another wavelength. Main lens N-BK7 (Schott Sellmeier), offset so that
  n(632.8 nm) = 1.5168 as in Table 1 (catalogue N-BK7: 1.51509; the offset, +0.0017, keeps the paper's
  focal length). MLA: a two-term Cauchy n = A + B/lambda^2 through n(632.8 nm) = 1.56 with Abbe number
  V_d = 45 (a generic UV-cured replication resin / epoxy: such materials have V_d ~ 40-55; the value is
  an assumption, `--mla-abbe`).
- points: isotropic point sources (pinholes) on the object plane whose main-lens images land on lens
  centres, edge midpoints or corners, main lens stopped to f/8 and the object placed so the main lens'
  smallest (least-rms) spot lies on the MLA (at f/2.5 its spherical aberration makes the spot ~0.8 mm rms).
- through-focus: one point on the axis, f/8, its paraxial image u mm behind (+) or in front of (-) the
  MLA, by moving the object (stage Z) with the MLA fixed: each microlens under the blur sees a nearly
  spherical wave and focuses it to a spot (a Shack-Hartmann sensor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from mlaqc.optics.config import CameraConfig
from mlaqc.optics.raytrace import (
    Camera,
    MainLens,
    intersect_sphere,
    refract,
    sphere_normal,
)
from mlaqc.optics.render import source_region
from mlaqc.optics.scene import PointScene, WhiteScene, sample_points
from mlaqc.optics.throughfocus import frozen, magnification, object_for_image_offset, stopped  # noqa: F401 (re-exported)
from mlaqc.optics.unitcircle import counter_uniforms

LAMBDA0_NM = 632.8
N_MAIN_632 = 1.5168
N_MLA_632 = 1.56
MLA_ABBE = 45.0
POINT_F_NUMBER = 8.0

# Schott N-BK7 Sellmeier (lambda in µm)
_BK7_B = (1.03961212, 0.231792344, 1.01046945)
_BK7_C = (0.00600069867, 0.0200179144, 103.560653)


def n_bk7_catalogue(wavelength_nm: float) -> float:
    l2 = (wavelength_nm * 1e-3) ** 2
    return math.sqrt(1.0 + sum(b * l2 / (l2 - c) for b, c in zip(_BK7_B, _BK7_C)))


def n_main(wavelength_nm: float) -> float:
    """Main lens: N-BK7 dispersion, offset to n = 1.5168 at 632.8 nm (Table 1)."""
    return n_bk7_catalogue(wavelength_nm) - n_bk7_catalogue(LAMBDA0_NM) + N_MAIN_632


def mla_cauchy(abbe: float = MLA_ABBE) -> tuple[float, float]:
    """(A, B) of n = A + B / lambda^2 (lambda in µm) with n(632.8 nm) = 1.56 and V_d = abbe."""
    inv2 = lambda nm: 1.0 / (nm * 1e-3) ** 2
    # V = (n_d - 1) / (n_F - n_C), n_d = 1.56 + B (1/d^2 - 1/0.6328^2), n_F - n_C = B (1/F^2 - 1/C^2)
    k_d = inv2(587.56) - inv2(LAMBDA0_NM)
    k_fc = inv2(486.13) - inv2(656.27)
    b = (N_MLA_632 - 1.0) / (abbe * k_fc - k_d)
    return N_MLA_632 - b * inv2(LAMBDA0_NM), b


def n_mla(wavelength_nm: float, abbe: float = MLA_ABBE) -> float:
    a, b = mla_cauchy(abbe)
    return a + b / (wavelength_nm * 1e-3) ** 2


def at_wavelength(cfg: CameraConfig, wavelength_nm: float, abbe: float = MLA_ABBE) -> CameraConfig:
    return replace(cfg, geometry=replace(cfg.geometry, wavelength_nm=wavelength_nm),
                   main_lens=replace(cfg.main_lens, refractive_index=n_main(wavelength_nm)),
                   mla=replace(cfg.mla, refractive_index=n_mla(wavelength_nm, abbe)))


def trace_fan(cfg: CameraConfig, x_obj_mm: float, y_obj_mm: float, n: int = 100_000, seed: int = 7):
    """Rays of an object point traced to the MLA plane: (x, y, L, M, w) there, camera frame, mm."""
    cam = Camera(cfg)
    r = sample_points(source_region(cam), counter_uniforms(seed, n, 2), x_obj_mm, y_obj_mm)
    cam.trace_to_mla(r)
    t = (cam.z_mla - r.z) / r.N
    ok = r.w > 0
    return r.x + t * r.L, r.y + t * r.M, r.L / r.N, r.M / r.N, np.where(ok, r.w, 0.0)


def spot_stats(cfg: CameraConfig, x_obj_mm: float = 0.0, dz_mm: float = 0.0) -> dict:
    """Centroid, rms, r50, r80 (µm) of a point's spot dz_mm behind the MLA plane."""
    x, y, tx, ty, w = trace_fan(cfg, x_obj_mm, 0.0)
    x, y = x + dz_mm * tx, y + dz_mm * ty
    cx, cy = np.average(x, weights=w), np.average(y, weights=w)
    rr = np.hypot(x - cx, y - cy)
    o = np.argsort(rr)
    ee = np.cumsum(w[o]) / w.sum()
    return {"cx_um": cx * 1e3, "cy_um": cy * 1e3, "rms_um": 1e3 * math.sqrt(np.average(rr ** 2, weights=w)),
            "r50_um": 1e3 * rr[o][np.searchsorted(ee, 0.5)], "r80_um": 1e3 * rr[o][np.searchsorted(ee, 0.8)]}


def best_focus_offset_mm(cfg: CameraConfig, span_mm: float) -> float:
    """Where (mm behind the MLA, + towards the sensor) a point's least-rms spot lies."""
    x, y, tx, ty, w = trace_fan(cfg, 0.0, 0.0)

    def rms(dz: float) -> float:
        xx, yy = x + dz * tx, y + dz * ty
        cx, cy = np.average(xx, weights=w), np.average(yy, weights=w)
        return float(np.average((xx - cx) ** 2 + (yy - cy) ** 2, weights=w))

    grid = np.linspace(-span_mm, span_mm, 161)
    k = int(np.argmin([rms(d) for d in grid]))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    for _ in range(40):  # golden-section refinement
        m1, m2 = lo + 0.382 * (hi - lo), lo + 0.618 * (hi - lo)
        lo, hi = (lo, m2) if rms(m1) < rms(m2) else (m1, hi)
    return 0.5 * (lo + hi)


@lru_cache(maxsize=4)
def point_focus(cfg: CameraConfig) -> tuple[CameraConfig, float]:
    """The f/8 camera with the object moved so the least-rms spot of an on-axis point lies on the MLA,
    and the paraxial image offset u (mm behind the MLA) that takes."""
    c = stopped(cfg, POINT_F_NUMBER)
    u = -best_focus_offset_mm(c, 3.0)
    for _ in range(2):  # the offset barely depends on the object distance: two passes settle it
        c2 = object_for_image_offset(c, u)
        u -= best_focus_offset_mm(c2, 0.3)
    return object_for_image_offset(c, u), u


def grid_points_mm(cfg: CameraConfig, kind: str, reach: int) -> tuple[tuple[float, float], ...]:
    """Object-plane positions (mm) whose main-lens images land on lens centres, edge midpoints or
    corners of the lenses within `reach` lenses of the axis (the image is inverted: x_obj = -x_img / m)."""
    p = cfg.mla.pitch_um * 1e-3
    m = magnification(cfg)
    k = np.arange(-reach, reach + 1)
    h = np.arange(-reach, reach) + 0.5
    if kind == "centres":
        img = [(i, j) for i in k for j in k]
    elif kind == "edges":
        img = [(i, j) for i in h for j in k] + [(i, j) for i in k for j in h]
    elif kind == "corners":
        img = [(i, j) for i in h for j in h]
    else:
        raise ValueError(kind)
    return tuple((-float(i) * p / m, -float(j) * p / m) for i, j in img)


def point_landing_error_um(cfg: CameraConfig, points: tuple[tuple[float, float], ...], targets_img_mm) -> float:
    """Largest distance (µm) between a traced spot's centroid at the MLA and where the point should land."""
    worst = 0.0
    for (xo, yo), (xi, yi) in zip(points, targets_img_mm):
        x, y, _, _, w = trace_fan(cfg, xo, yo, n=20_000)
        worst = max(worst, 1e3 * math.hypot(np.average(x, weights=w) - xi, np.average(y, weights=w) - yi))
    return worst


def stop_check(cfg: CameraConfig, f_number: float, image_mm: float) -> dict:
    """How far the rim stop is from one thin iris: the share of an object point's rays (drawn towards
    the front pupil disc) that pass the front rim but are cut at the rear one, for a point on the axis
    and for the one imaged `image_mm` off axis in x and y. 0 means the front rim alone is the stop (a
    thin iris at the front vertex, whose image through the rear surface is the exit pupil)."""
    c = stopped(cfg, f_number)
    m = magnification(c)
    ml = MainLens(c)
    out = {}
    for name, pos in (("axis", 0.0), ("corner", -image_mm / m)):
        r = sample_points(source_region(Camera(c)), counter_uniforms(7, 50_000, 2), pos, pos)
        passed = []
        for zv, cv, mu in ((0.0, ml.c1, ml.mu_in), (ml.z2, ml.c2, ml.mu_out)):
            t = intersect_sphere(r.x, r.y, r.z, r.L, r.M, r.N, 0.0, 0.0, zv, cv)
            r.advance(t)
            nx, ny, nz = sphere_normal(r.x, r.y, r.z, 0.0, 0.0, zv, cv)
            r.L, r.M, r.N, _, _, ok = refract(r.L, r.M, r.N, nx, ny, nz, mu)
            passed.append(ok & (r.x * r.x + r.y * r.y <= ml.rim2))
        out[name] = float(np.sum(passed[0] & ~passed[1]) / max(np.sum(passed[0]), 1))
    return out


@dataclass(frozen=True)
class Frame:
    """One frame of a protocol: its camera, scene and ray budget (per half of the truth render)."""

    key: str
    label: str
    cfg: CameraConfig
    scene: object
    rays: int
    note: str = ""


def white_frames(cfg: CameraConfig, rays: int, abbe: float) -> dict[str, Frame]:
    out = {"W": Frame("W", "white f/2.5", cfg, WhiteScene(), rays)}
    for n in (8.0, 16.0):
        out[f"S{n:g}"] = Frame(f"S{n:g}", f"white f/{n:g}", stopped(cfg, n), WhiteScene(), rays,
                               f"rim diameter {cfg.layout.main.efl / n:.2f} mm")
    for nm in (450.0, 850.0):
        c = at_wavelength(cfg, nm, abbe)
        f_rel = c.layout.micro.efl / cfg.layout.micro.efl - 1
        out[f"L{nm:g}"] = Frame(f"L{nm:g}", f"white {nm:g} nm", c, WhiteScene(), rays,
                                f"n_main {c.main_lens.refractive_index:.4f}, n_MLA {c.mla.refractive_index:.4f}: "
                                f"microlens f {100 * f_rel:+.2f} %, main lens f "
                                f"{c.layout.main.efl - cfg.layout.main.efl:+.2f} mm")
    return out


def point_frames(cfg: CameraConfig, rays_per_point: int, reach: int) -> dict[str, Frame]:
    c, u = point_focus(cfg)
    out = {}
    for kind, key in (("centres", "PC"), ("edges", "PE"), ("corners", "PK")):
        pts = grid_points_mm(c, kind, reach)
        out[key] = Frame(key, f"points on {kind} f/8", c, PointScene(points_mm=pts, photons=1e6),
                         rays_per_point * len(pts), f"{len(pts)} points, object {c.geometry.object_distance_mm:.2f} mm "
                         f"(paraxial image {u:+.2f} mm behind the MLA: least-rms spot on it)")
    return out


def through_focus_frames(cfg: CameraConfig, offsets_mm: tuple[float, ...], rays: int) -> dict[str, Frame]:
    c8 = stopped(cfg, POINT_F_NUMBER)
    out = {}
    for u in offsets_mm:
        c = object_for_image_offset(c8, u)
        dz = c.geometry.object_distance_mm - cfg.geometry.object_distance_mm
        out[f"T{u:+g}"] = Frame(f"T{u:+g}", f"through-focus u={u:+g} mm", c, PointScene(points_mm=((0.0, 0.0),), photons=1e6),
                                rays, f"object {c.geometry.object_distance_mm:.2f} mm (stage Z {dz:+.2f} mm), blur "
                                f"{abs(u) / POINT_F_NUMBER:.2f} mm")
    return out
