"""Tracer physics against independent facts: Snell, Fresnel, thick-lens formulas, Gaussian imaging, lookups."""

import math

import numpy as np
import pytest

from mlaqc.optics.config import default_config, load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.raytrace import (
    Camera,
    MainLens,
    MicrolensArray,
    Rays,
    fresnel_transmittance,
    intersect_sphere,
    refract,
)

N_MAIN, N_MLA = 1.5168, 1.56


def lensmaker(r1, r2, t, n):
    """Thick-lens EFL and rear principal-plane depth, written out here independently of mlaqc.optics.paraxial."""
    phi = (n - 1) * (1 / r1 - 1 / r2 + (n - 1) * t / (n * r1 * r2))
    f = 1 / phi
    return f, f * (n - 1) * t / (n * r1)


def rays(x, y, z, L, M, N):
    x, y, z, L, M, N = (np.atleast_1d(np.asarray(v, float)).copy() for v in (x, y, z, L, M, N))
    x, y, z, L, M, N = np.broadcast_arrays(x, y, z, L, M, N)
    return Rays(*(a.copy() for a in (x, y, z, L, M, N)), np.ones(x.shape))


# --- single surfaces -----------------------------------------------------------------------------


@pytest.mark.parametrize("theta_deg", [0.0, 10.0, 30.0, 60.0, 85.0])
def test_snell_law_and_plane_of_incidence(theta_deg):
    th = math.radians(theta_deg)
    d = np.array([math.sin(th) * math.cos(0.3), math.sin(th) * math.sin(0.3), math.cos(th)])
    L, M, N, ci, ct, ok = refract(*d, 0.0, 0.0, -1.0, 1.0 / N_MAIN)
    assert ok
    out = np.array([L, M, N])
    assert np.linalg.norm(out) == pytest.approx(1.0, abs=1e-15)
    sin_t = math.hypot(L, M)
    assert 1.0 * math.sin(th) == pytest.approx(N_MAIN * sin_t, abs=1e-14)  # n1 sin(i) = n2 sin(t)
    # refracted ray stays in the plane of incidence (spanned by d and the normal z)
    assert np.cross(d, [0, 0, 1]) @ out == pytest.approx(0.0, abs=1e-15)


def test_total_internal_reflection_flagged_beyond_critical_angle():
    crit = math.asin(1 / N_MLA)
    for th, expect in ((crit - 0.01, True), (crit + 0.01, False)):
        _, _, _, _, _, ok = refract(math.sin(th), 0.0, math.cos(th), 0.0, 0.0, -1.0, N_MLA)
        assert bool(ok) is expect


@pytest.mark.parametrize("theta_deg", [0.0, 20.0, 45.0, 70.0, 89.0])
def test_fresnel_energy_conservation(theta_deg):
    """T from mlaqc equals 1 - R from the amplitude coefficients (Hecht), and normal incidence matches."""
    n1, n2 = 1.0, N_MAIN
    ci = math.cos(math.radians(theta_deg))
    st = n1 / n2 * math.sin(math.radians(theta_deg))
    ct = math.sqrt(1 - st * st)
    rs = (n1 * ci - n2 * ct) / (n1 * ci + n2 * ct)
    rp = (n2 * ci - n1 * ct) / (n2 * ci + n1 * ct)
    assert fresnel_transmittance(ci, ct, n1, n2) == pytest.approx(1 - (rs * rs + rp * rp) / 2, abs=1e-14)
    assert fresnel_transmittance(ci, ct, n2, n1) == pytest.approx(fresnel_transmittance(ct, ci, n1, n2), abs=1e-15)
    if theta_deg == 0:
        assert fresnel_transmittance(1.0, 1.0, n1, n2) == pytest.approx(1 - ((n2 - n1) / (n2 + n1)) ** 2)


def test_sphere_intersection_on_surface_and_nearest_sheet():
    c = 1 / 106.0
    r = rays(np.linspace(-20, 20, 9), 3.0, -50.0, 0.0, 0.0, 1.0)
    t = intersect_sphere(r.x, r.y, r.z, r.L, r.M, r.N, 0.0, 0.0, 0.0, c)
    z = r.z + t
    rho2 = r.x ** 2 + r.y ** 2
    assert np.allclose(z, 106.0 - np.sqrt(106.0 ** 2 - rho2), atol=1e-12)  # sag of the vertex-side sheet
    miss = intersect_sphere(np.array([200.0]), np.array([0.0]), np.array([-5.0]), np.array([0.0]), np.array([0.0]),
                            np.array([1.0]), 0.0, 0.0, 0.0, c)
    assert np.isnan(miss[0])


# --- focal lengths ---------------------------------------------------------------------------------


def _crossing(r: Rays) -> tuple[np.ndarray, np.ndarray]:
    """z where each meridional ray (y = 0) crosses the axis, and its slope angle."""
    t = -r.x / r.L
    return r.z + t * r.N, r.L / r.N


def test_main_lens_focal_length_matches_thick_lens_formula():
    cfg = default_config()
    lens = MainLens(cfg)
    h = np.array([0.05, 0.1, 0.2])  # paraxial heights, mm
    r = rays(h, 0.0, -10.0, 0.0, 0.0, 1.0)
    lens.trace(r)
    z_cross, slope = _crossing(r)
    f_expect, hp = lensmaker(106.0, -106.0, 14.5, N_MAIN)
    efl = -h / slope
    assert efl == pytest.approx(np.full(3, f_expect), rel=2e-5)
    assert f_expect == pytest.approx(105.0, abs=0.01)  # the paper's Table 1
    assert z_cross - 14.5 == pytest.approx(np.full(3, f_expect - hp), rel=2e-5)  # back focal distance
    assert hp == pytest.approx(4.89, abs=0.01)  # DESIGN.md: principal planes 4.89 mm inside each vertex


def test_main_lens_has_the_expected_sign_of_spherical_aberration():
    """Marginal rays of a biconvex singlet focus short of paraxial focus (undercorrected)."""
    lens = MainLens(default_config())
    r = rays(np.array([0.1, 20.0]), 0.0, -10.0, 0.0, 0.0, 1.0)
    lens.trace(r)
    z, _ = _crossing(r)
    assert z[1] < z[0] - 1.0


def test_microlens_focal_length_matches_thick_lens_formula():
    cfg = default_config()
    mla = MicrolensArray(cfg, ErrorMap.zeros(102, 102))
    cx = 0.05  # centre of U(51, 52): x = (52 - 0.5) * 0.1 - 5.1 mm
    cy = -0.05  # centre of U(51, ...): y = (51 - 0.5) * 0.1 - 5.1
    h = np.array([0.0005, 0.001, 0.002])  # mm: paraxial (at 4 µm spherical aberration shows at 1e-4)
    r = rays(cx + h, cy, -0.1, 0.0, 0.0, 1.0)
    mla.trace(r)
    assert np.all(r.w > 0)
    slope = r.L / r.N
    f_expect, hp = lensmaker(0.469, -0.469, 0.010, N_MLA)
    assert -h / slope == pytest.approx(np.full(3, f_expect), rel=1e-4)
    assert f_expect * 1e3 == pytest.approx(420.4, abs=0.05)  # DESIGN.md: 420.4 µm effective
    z_cross = r.z - (r.x - cx) / r.L * r.N
    assert (z_cross - 0.005) * 1e3 == pytest.approx(np.full(3, 417.1), abs=0.1)  # BFD from the rear vertex


def test_default_geometry_images_the_object_onto_the_mla():
    """Paraxial rays from the axial object point meet at the MLA mid-plane (Gaussian imaging)."""
    cfg = default_config()
    lay = cfg.layout
    cam = Camera(cfg)
    f, hp = lensmaker(106.0, -106.0, 14.5, N_MAIN)
    a = lay.object_distance_mm + hp
    b = 1 / (1 / f - 1 / a)
    assert b == pytest.approx(42.0 * lay.micro.efl / 0.1, rel=1e-9)  # f-number matched: D/b = p/f
    assert a == pytest.approx(259.0, abs=0.2)  # DESIGN.md: object ~259 mm before the front principal plane
    u = np.array([0.01, 0.02, 0.03]) / a  # paraxial slopes
    r = rays(0.0, 0.0, lay.z_object_mm, 0.0, 0.0, 1.0)
    r = rays(np.zeros(3), 0.0, lay.z_object_mm, np.sin(u), 0.0, np.cos(u))
    cam.main.trace(r)
    z, _ = _crossing(r)
    assert z == pytest.approx(np.full(3, 14.5 - hp + b), abs=5e-4)
    assert z == pytest.approx(np.full(3, lay.z_mla_mm), abs=5e-4)


# --- lenslet lookup --------------------------------------------------------------------------------


def test_rays_at_cell_edges_refract_towards_their_own_lens():
    """Parallel rays just either side of the boundary between U(51,51) and U(51,52) (x = 0) bend towards
    their own lens' axis: the lookup puts each in the right lens."""
    mla = MicrolensArray(default_config(), ErrorMap.zeros(102, 102))
    eps = 1e-7  # mm
    r = rays(np.array([-eps, eps]), -0.05, -0.1, 0.0, 0.0, 1.0)
    mla.trace(r)
    assert np.all(r.w > 0)
    assert r.L[0] < 0 < r.L[1]  # left ray bends left (towards x=-0.05), right ray right (towards +0.05)
    assert r.L[0] == pytest.approx(-r.L[1], rel=1e-9)


def test_oblique_ray_crossing_a_cell_edge_uses_the_lens_it_hits():
    """A ray crossing the vertex plane in one cell but meeting the surface in the next is traced by the
    lens whose surface it meets: compare with tracing both candidate lenses' surfaces by hand."""
    cfg = default_config()
    mla = MicrolensArray(cfg, ErrorMap.zeros(102, 102))
    slope = 0.3  # steep, so the ~5 µm of sag near the edge moves it ~1.5 µm sideways
    x0 = -0.0005  # 0.5 µm left of the x = 0 cell boundary on the vertex plane
    z_front = -0.005
    r = rays(x0, -0.05, z_front, slope / math.hypot(1, slope), 0.0, 1 / math.hypot(1, slope))
    mla.trace(r)
    # by hand: intersect the right-hand lens' front sphere (vertex at x = +0.05)
    c = 1 / 0.469
    x, z = np.array([x0]), np.array([z_front])
    L, N = np.array([slope / math.hypot(1, slope)]), np.array([1 / math.hypot(1, slope)])
    t = intersect_sphere(x, np.array([-0.05]), z, L, np.zeros(1), N, 0.05, -0.05, z_front, c)
    assert x0 + t[0] * L[0] > 0  # the hit is in the right-hand cell
    r2 = rays(x0 + t[0] * L[0] - 1e-9 * L[0], -0.05, z_front + t[0] * N[0] - 1e-9 * N[0], L[0], 0.0, N[0])
    # a ray starting just before that hit point and inside the right cell sees only the right lens
    mla.trace(r2)
    assert r.w[0] > 0
    assert r.L[0] == pytest.approx(r2.L[0], abs=1e-9) and r.x[0] == pytest.approx(r2.x[0], abs=1e-9)


def test_array_border_rays_outside_are_blocked_inside_pass():
    mla = MicrolensArray(default_config(), ErrorMap.zeros(102, 102))
    edge = 5.1
    r = rays(np.array([edge - 0.01, edge + 0.01, -edge + 0.01, -edge - 0.01]), 0.0, -0.1, 0.0, 0.0, 1.0)
    mla.trace(r)
    assert list(r.w > 0) == [True, False, True, False]


def test_corners_opaque_or_clear():
    """Where the two sags exceed the vertex thickness (r > 68.3 µm) there is no lens: opaque blocks,
    clear passes the ray undeviated; inside the rim the lens refracts."""
    rim = math.sqrt(0.469 ** 2 - (0.469 - 0.005) ** 2)
    assert rim * 1e3 == pytest.approx(68.3, abs=0.05)
    cx, cy = 0.05, -0.05
    d_in, d_out = 0.045, 0.0495  # diagonal offsets: radius 63.6 µm (lens) and 70.0 µm (corner)
    for corners, expect_w in (("opaque", [True, False]), ("clear", [True, True])):
        cfg = load_config(None)
        cfg = type(cfg)(cfg.main_lens, type(cfg.mla)(**{**cfg.mla.__dict__, "corners": corners}), cfg.sensor, cfg.geometry, cfg.trace)
        mla = MicrolensArray(cfg, ErrorMap.zeros(102, 102))
        r = rays(np.array([cx + d_in, cx + d_out]), np.array([cy + d_in, cy + d_out]), -0.1, 0.0, 0.0, 1.0)
        mla.trace(r)
        assert list(r.w > 0) == expect_w
        assert r.L[0] < -0.05  # refracted towards the lens axis
        if corners == "clear":
            assert r.L[1] == 0.0 and r.M[1] == 0.0 and r.N[1] == 1.0
