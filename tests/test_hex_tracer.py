"""The tracer on hexagonal arrays and circular apertures (issue #22), against facts computed without it:
the nearest lens centre by brute force, the perpendicular bisector of two vertices, the hexagonal lattice
and its reciprocal lattice, the area of a circle against that of a hexagonal cell; the compiled engine
against the NumPy reference ray by ray; the stratified sampler against plain Monte-Carlo.

Frame (MLA): x right, y down, z along the light, lengths in mm; lens k = row * cols + col (0-based).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from mlaqc.errors import InputError
from mlaqc.optics import raytrace_kernels
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.lattice import Lattice
from mlaqc.optics.raytrace import Camera, MicrolensArray, Rays
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
HEX = load_config(FIXTURES / "hex_small_camera.toml")  # 24 cols x 28 rows, pitch 100 µm, 496^2 px
SQUARE = load_config(FIXTURES / "small_camera.toml")
SAG = "sag-intersection"
needs_numba = pytest.mark.skipif(not raytrace_kernels.AVAILABLE, reason="numba is not installed")


def with_mla(cfg, **mla):
    return dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, **mla))


def with_trace(cfg, **trace):
    return dataclasses.replace(cfg, trace=dataclasses.replace(cfg.trace, **trace))


def normal_rays(x_mm: np.ndarray, y_mm: np.ndarray) -> Rays:
    """Rays along +z through (x, y), starting 0.1 mm in front of the MLA."""
    n = len(x_mm)
    return Rays(np.asarray(x_mm, float), np.asarray(y_mm, float), np.full(n, -0.1), np.zeros(n), np.zeros(n),
                np.ones(n), np.ones(n))


def brute_nearest(cx: np.ndarray, cy: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Flat index of the nearest of the centres (cx, cy) to each point, by computing every distance."""
    d2 = (x[:, None] - cx.ravel()[None, :]) ** 2 + (y[:, None] - cy.ravel()[None, :]) ** 2
    return np.argmin(d2, axis=1)


def hex_errors(seed: int, pitch_um: float = 4.0) -> ErrorMap:
    """Every lens of the small hex array with random pitch, decenter, radius, thickness and tilt errors."""
    rng = np.random.default_rng(seed)
    shape = (HEX.mla.count_h, HEX.mla.count_w)
    lens = {"pitch_um": rng.uniform(0, pitch_um, shape), "pitch_dir_deg": rng.uniform(0, 360, shape),
            "decenter_um": rng.uniform(0, 4, shape), "decenter_dir_deg": rng.uniform(0, 360, shape),
            "radius_front_rel": rng.uniform(-0.06, 0.06, shape), "radius_back_rel": rng.uniform(-0.06, 0.06, shape),
            "tilt_x_deg": rng.uniform(-0.4, 0.4, shape), "tilt_y_deg": rng.uniform(-0.4, 0.4, shape),
            "thickness_um": rng.uniform(-1.0, 1.0, shape)}
    return ErrorMap(shape, lens, packing="hex").with_globals(mla_rotation_deg=0.6, mla_tilt_x_deg=-0.2,
                                                              mla_shift_x_um=11)


# --- which lens a ray belongs to ----------------------------------------------------------------------


def test_centres_are_the_lattice_and_square_centres_are_unchanged():
    """Hex lens centres are Lattice.centres() (rows p sqrt(3)/2 apart, even rows m shifted p/2); the square
    tracer keeps its centres ((c + 1/2) p - cols p / 2) bit for bit."""
    mla = MicrolensArray(HEX)
    lat = Lattice.of(HEX)
    cx, cy = lat.centres()
    assert np.array_equal(mla.gx, cx.ravel()) and np.array_equal(mla.gy, cy.ravel())
    assert mla.gx[HEX.mla.count_w] - mla.gx[0] == pytest.approx(0.05)  # U(2,1) is half a pitch right of U(1,1)
    assert mla.gy[HEX.mla.count_w] - mla.gy[0] == pytest.approx(0.1 * math.sqrt(3) / 2)
    sq = MicrolensArray(SQUARE)
    cols = SQUARE.mla.count_w
    assert np.array_equal(sq.gx[:cols], (np.arange(cols) + 0.5) * 0.1 + (-0.5 * cols * 0.1))


def test_cell_lookup_is_the_nearest_lens_centre_and_edge_distance_the_bisector_distance():
    """At random points, the tracer's cell is the lens whose centre is nearest (brute force over every
    centre of a lattice one ring larger than the array), and the distance to the cell's edge is the
    smallest distance to a perpendicular bisector with another centre: (d_i^2 - d_k^2) / (2 |c_i - c_k|)."""
    mla = MicrolensArray(HEX)
    big = Lattice("hex", HEX.mla.count_h + 4, HEX.mla.count_w + 2, 0.1)
    bx, by = big.centres()  # U(1,1) of the array is U(3,2) of `big` (rows of the same parity)
    ox, oy = mla.gx[0] - bx[2, 1], mla.gy[0] - by[2, 1]
    bx, by = (bx + ox).ravel(), (by + oy).ravel()
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-1.25, 1.25, 20_000), rng.uniform(-1.25, 1.25, 20_000)
    k, on = mla.cell_of(x, y)
    best = brute_nearest(bx, by, x, y)
    brow, bcol = np.divmod(best, big.cols)
    on_ref = (brow >= 2) & (brow < HEX.mla.count_h + 2) & (bcol >= 1) & (bcol <= HEX.mla.count_w)
    assert np.array_equal(on, on_ref) and 0.3 < on.mean() < 0.99
    assert np.array_equal(k[on], ((brow - 2) * HEX.mla.count_w + bcol - 1)[on])
    d2 = (x[:, None] - bx[None, :]) ** 2 + (y[:, None] - by[None, :]) ** 2
    dk = d2[np.arange(len(x)), best]
    sep = np.hypot(bx[None, :] - bx[best][:, None], by[None, :] - by[best][:, None])
    with np.errstate(invalid="ignore", divide="ignore"):
        bis = np.where(sep > 0, (d2 - dk[:, None]) / (2 * sep), np.inf)
    assert np.allclose(mla.edge_distance(x, y)[on], bis.min(axis=1)[on], rtol=0, atol=1e-12)


@pytest.mark.parametrize("boundaries", ["grid", SAG])
def test_lens_of_assigns_normal_rays_to_the_hexagon_they_hit(boundaries):
    """On the design array (either boundary model) a ray along the axis enters and leaves the lens whose
    centre is nearest its crossing point (brute force), and rays beyond the outline are lost."""
    mla = MicrolensArray(with_mla(HEX, boundaries=boundaries))
    rng = np.random.default_rng(7)
    x, y = rng.uniform(-1.0, 1.0, 20_000), rng.uniform(-1.0, 1.0, 20_000)
    ch = mla.lens_of(normal_rays(x, y))
    expect = brute_nearest(mla.gx, mla.gy, x, y)
    live = ~ch.corner
    assert live.mean() > 0.9
    assert np.array_equal(ch.front[live], expect[live]) and np.array_equal(ch.rear[live], expect[live])
    # corners of a hexagon: its vertices are p / sqrt(3) = 57.7 µm out, inside Table 1's 68 µm crossing
    assert not ch.corner.any()


def test_grid_mode_keeps_the_design_hexagon_under_pitch_errors():
    """'grid': a pitch error moves a lens' surfaces, not its hexagonal aperture."""
    em = hex_errors(2, pitch_um=8.0)
    mla = MicrolensArray(with_mla(HEX, boundaries="grid"), em)
    rng = np.random.default_rng(8)
    x, y = rng.uniform(-1.0, 1.0, 20_000), rng.uniform(-1.0, 1.0, 20_000)
    ch = mla.lens_of(normal_rays(x, y))
    expect = brute_nearest(mla.gx, mla.gy, x, y)
    assert np.array_equal(ch.front[~ch.corner], expect[~ch.corner])


@pytest.mark.parametrize("direction_deg, step", [(0.0, (0, 1)), (60.0, (-1, 0)), (120.0, (-1, -1)),
                                                 (240.0, (1, -1))])
def test_sag_boundary_moves_by_half_a_shift_along_a_neighbour_direction(direction_deg, step):
    """U(13,12) (0-based row 12, even, unshifted) shifted by 3 µm towards one of its 6 neighbours: equal
    spheres meet on the perpendicular bisector of their vertices, so along the line joining the two
    centres the lens switches at (p + 3 µm) / 2 from the shifted lens' design centre."""
    r, c = 12, 12
    em = ErrorMap.zeros(HEX.mla.count_h, HEX.mla.count_w, "hex").with_lens(r + 1, c + 1, pitch_um=3.0,
                                                                          pitch_dir_deg=direction_deg)
    mla = MicrolensArray(with_mla(HEX, boundaries=SAG), em)
    k = r * HEX.mla.count_w + c
    kn = (r + step[0]) * HEX.mla.count_w + c + step[1]
    ax, ay, bx, by = mla.gx[k], mla.gy[k], mla.gx[kn], mla.gy[kn]
    assert math.hypot(bx - ax, by - ay) == pytest.approx(0.1)  # a nearest neighbour
    a = math.radians(direction_deg)
    assert (bx - ax, by - ay) == pytest.approx((0.1 * math.cos(a), -0.1 * math.sin(a)))
    s = np.arange(0.044, 0.056, 1e-5) + 5e-6  # mm along the line from k's design centre
    for side in (0.0, 0.02):  # on the line, and 20 µm beside it along the bisector
        px, py = -math.sin(a) * side, -math.cos(a) * side
        ch = mla.lens_of(normal_rays(ax + s * math.cos(a) + px, ay - s * math.sin(a) + py))
        change = np.flatnonzero(np.diff(ch.front))
        assert len(change) == 1 and (ch.front[change[0]], ch.front[change[0] + 1]) == (k, kn)
        assert 0.5 * (s[change[0]] + s[change[0] + 1]) == pytest.approx(0.0515, abs=1e-5)
        assert np.array_equal(ch.front, ch.rear)


def test_sag_fast_path_chooses_the_lens_brute_force_chooses():
    """Random errors on every lens, oblique rays: the front lens is the front sphere met first and the
    rear lens the rear sphere met last among every lens within 2.2 pitches (brute force), whatever the
    hexagonal margins let the fast path skip."""
    cfg = with_mla(HEX, boundaries=SAG)
    mla = MicrolensArray(cfg, hex_errors(4))
    assert 0 < mla.margin_front.max() < 0.5 * mla.p
    rng = np.random.default_rng(5)
    n = 30_000
    x, y = rng.uniform(-0.9, 0.9, n), rng.uniform(-0.9, 0.9, n)
    theta, phi = 0.25 * np.sqrt(rng.random(n)), 2 * np.pi * rng.random(n)
    L, M, N = np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)
    r = Rays(x - 0.05 * L / N, y - 0.05 * M / N, np.full(n, mla.z_front - 0.05), L, M, N, np.ones(n))
    ch = mla.lens_of(r)

    def brute(rays: Rays, rear: bool) -> np.ndarray:
        near = np.argsort((rays.x[:, None] - mla.gx[None, :]) ** 2 + (rays.y[:, None] - mla.gy[None, :]) ** 2,
                          axis=1)[:, :19]  # the cell, its 6 neighbours and the next 12: within 2 pitches
        best_k, best_t = np.full(len(rays), -1), np.full(len(rays), np.nan)
        for j in range(near.shape[1]):
            kc = near[:, j]
            _, _, _, t = mla._surface(kc, rays.x, rays.y, rays.z, rays.L, rays.M, rays.N, rear)
            with np.errstate(invalid="ignore"):
                better = (t > best_t) if rear else (t < best_t)
            take = np.isfinite(t) & (better | np.isnan(best_t))
            best_k, best_t = np.where(take, kc, best_k), np.where(take, t, best_t)
        return best_k

    at_front = Rays(*(a.copy() for a in (r.x, r.y, r.z, r.L, r.M, r.N, r.w)))
    at_front.advance((mla.z_front - at_front.z) / at_front.N)
    front = brute(at_front, rear=False)
    assert np.array_equal(ch.front, front)
    cell, _ = mla.cell_of(at_front.x, at_front.y)
    assert np.mean(front != cell) > 0.01
    live = ch.after_front.w > 0
    af = ch.after_front
    sub = Rays(*(a[live] for a in (af.x, af.y, af.z, af.L, af.M, af.N, af.w)))
    assert np.array_equal(ch.rear[live], brute(sub, rear=True))


@pytest.mark.parametrize("engine", ["numba", "numpy"])
def test_design_hex_array_renders_the_same_in_both_boundary_models(engine):
    """No errors: equal lenses meet on the hexagons' sides, so sag-intersection and grid agree."""
    if engine == "numba" and not raytrace_kernels.AVAILABLE:
        pytest.skip("numba is not installed")
    rays = 300_000 if engine == "numpy" else 3_000_000
    a = Renderer(with_mla(HEX, boundaries="grid"), engine=engine).render(WhiteScene(), rays=rays, seed=3).photons
    b = Renderer(with_mla(HEX, boundaries=SAG), engine=engine).render(WhiteScene(), rays=rays, seed=3).photons
    assert a.sum() > 0
    assert np.allclose(a, b, rtol=1e-12, atol=0)


def test_an_error_map_for_another_lattice_is_refused():
    with pytest.raises(InputError, match="square lattice but the camera's MLA is hex"):
        Camera(HEX, ErrorMap.zeros(HEX.mla.count_h, HEX.mla.count_w))
    with pytest.raises(InputError, match="hex lattice but the camera's MLA is square"):
        Renderer(SQUARE, ErrorMap.zeros(24, 24, "hex"), engine="numpy")


# --- circular apertures -------------------------------------------------------------------------------


@pytest.mark.parametrize("cfg", [HEX, SQUARE], ids=["hex", "square"])
def test_circle_aperture_takes_rays_inside_its_circle_and_gives_the_gap_the_rest(cfg):
    """A 90 µm circle round each front vertex, which moves with a 4 µm pitch error: a normal ray belongs to
    the lens whose (shifted) circle holds it, and the rest is gap; opaque gaps absorb, clear gaps pass the
    ray on undeviated."""
    shape = (cfg.mla.count_h, cfg.mla.count_w)
    em = ErrorMap.zeros(*shape, cfg.mla.packing).with_lens(12, 12, pitch_um=4.0, pitch_dir_deg=30.0)
    rng = np.random.default_rng(9)
    x, y = rng.uniform(-0.8, 0.8, 40_000), rng.uniform(-0.8, 0.8, 40_000)
    for gap in ("opaque", "clear"):
        mla = MicrolensArray(with_mla(cfg, aperture="circle", aperture_diameter_um=90.0, gap=gap), em)
        d2 = (x[:, None] - mla.fx[None, :]) ** 2 + (y[:, None] - mla.fy[None, :]) ** 2
        inside = d2.min(axis=1) <= 0.045 ** 2
        ch = mla.lens_of(normal_rays(x, y))
        assert np.array_equal(ch.gap, ~inside)
        assert np.array_equal(ch.front[inside], np.argmin(d2, axis=1)[inside])
        r = normal_rays(x, y)
        mla.trace(r)
        if gap == "opaque":
            assert np.all(r.w[~inside] == 0) and np.all(r.w[inside] > 0.9)
        else:
            assert np.allclose(r.x[~inside], x[~inside], rtol=0, atol=1e-15)
            assert np.all(r.L[~inside] == 0) and np.all(r.w[~inside] == 1.0)



@pytest.mark.parametrize("rear", [False, True])
def test_hex_pair_clearances_bound_where_each_neighbour_can_win(rear):
    """Hex cells, pair by pair: where Q = rho_i^2 - rho_k^2 (from the design centres) clears pair (k, i)'s
    bound, neighbour i's sphere is higher (front) / lower (rear) than lens k's at that point (heights from
    each sphere's centre, tilt included); the pairs clear more of the plane than the cell margins."""
    mla = MicrolensArray(with_mla(HEX, boundaries=SAG), hex_errors(4))
    q = mla.pair_clearance_mm2(rear)
    rng = np.random.default_rng(6)
    n = 100_000
    x, y = rng.uniform(-0.9, 0.9, n), rng.uniform(-0.9, 0.9, n)
    k, _ = mla.cell_of(x, y)

    def height(kc):
        if rear:
            local, radius = np.stack([mla.dx[kc], mla.dy[kc], mla.z_rear[kc] + 1 / mla.c2[kc]]), abs(1 / mla.c2[kc])
        else:
            local, radius = np.stack([0 * kc, 0 * kc, mla.z_front + 1 / mla.c1[kc]]), 1 / mla.c1[kc]
        centre = np.einsum("kij,jk->ik", mla.rot[kc], local)
        root = np.sqrt(radius ** 2 - (x - mla.fx[kc] - centre[0]) ** 2 - (y - mla.fy[kc] - centre[1]) ** 2)
        return centre[2] + root if rear else centre[2] - root

    h_k, rho2_k = height(k), (x - mla.gx[k]) ** 2 + (y - mla.gy[k]) ** 2
    all_clear, checked = np.ones(n, dtype=bool), 0
    for j, (kc, ok) in enumerate(mla.neighbours(x, y)):  # the cell, then its 6 neighbours
        clear = ok & (kc != k) & ((x - mla.gx[kc]) ** 2 + (y - mla.gy[kc]) ** 2 - rho2_k >= q[k, j])
        assert np.all((height(kc) < h_k) if rear else (height(kc) > h_k), where=clear)
        all_clear &= clear | ~ok | (kc == k)
        checked += clear.sum()
    assert checked > 3 * n
    margin = mla.margin_rear if rear else mla.margin_front
    far = mla.edge_distance(x, y) >= margin[k] + 1e-6
    assert np.all(all_clear[far]) and all_clear.mean() > far.mean() + 0.02


@pytest.mark.parametrize("cfg", [HEX, SQUARE], ids=["hex", "square"])
def test_circle_clearance_bounds_where_a_neighbours_circle_can_hold_a_hit(cfg):
    """Oblique rays (up to 0.3 rad) on 94 µm circles with pitch errors up to 6 µm and tilts: where a ray's
    hit on its cell's lens lies in that cell farther than the cell's clearance from its edge, no
    neighbour's front sphere takes the ray inside its circle (each intersection computed); nearer the
    edges some do, so the bound is not empty."""
    shape = (cfg.mla.count_h, cfg.mla.count_w)
    rng = np.random.default_rng(3)
    lens = dict(ErrorMap.zeros(*shape, cfg.mla.packing).lens)
    lens.update({"pitch_um": rng.uniform(0, 6, shape), "pitch_dir_deg": rng.uniform(0, 360, shape),
                 "tilt_x_deg": rng.uniform(-0.5, 0.5, shape), "tilt_y_deg": rng.uniform(-0.5, 0.5, shape)})
    mla = MicrolensArray(with_mla(cfg, aperture="circle", aperture_diameter_um=94.0), ErrorMap(shape, lens, packing=cfg.mla.packing))
    clearance = mla.circle_clearance_mm()
    assert np.mean(clearance > 0) > 0.5
    n = 60_000
    x, y = rng.uniform(-0.9, 0.9, n), rng.uniform(-0.9, 0.9, n)
    theta, phi = 0.3 * np.sqrt(rng.random(n)), 2 * np.pi * rng.random(n)
    L, M, N = np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)
    z = np.full(n, mla.z_front)
    k, _ = mla.cell_of(x, y)
    local, ldir, _, t = mla._surface(k, x, y, z, L, M, N, rear=False)
    gx, gy, _, _, _, _ = mla._from_lens(k, *local, *ldir)
    k2, on = mla.cell_of(gx, gy)
    far = on & (k2 == k) & (mla.edge_distance(gx, gy) > clearance[k]) & np.isfinite(t)
    taken = np.zeros(n, dtype=bool)
    for kc, ok in mla.neighbours(gx, gy):
        lc, _, _, tc = mla._surface(kc, x, y, z, L, M, N, rear=False)
        taken |= ok & (kc != k) & np.isfinite(tc) & (lc[0] ** 2 + lc[1] ** 2 <= mla.r_circle ** 2)
    assert 0.3 < far.mean() < 0.95
    assert not np.any(taken & far)
    assert np.any(taken & ~far)

@needs_numba
def test_circle_flux_is_proportional_to_its_area():
    """White scene, opaque gaps, no Fresnel: the light through the array is the irradiance times the clear
    area, so the flux ratio of circles of diameter D to full hexagonal cells is (pi D^2 / 4) / (p^2
    sqrt(3) / 2): 0.3265 at 60 µm and 0.7346 at 90 µm (no corners: both radii lie within the 68 µm
    where the surfaces cross)."""
    base = with_trace(HEX, fresnel=False)
    full = Renderer(base, engine="numba").render(WhiteScene(), rays=3_000_000, seed=2).photons.sum()
    for d_um in (60.0, 90.0):
        cfg = with_mla(base, aperture="circle", aperture_diameter_um=d_um, gap="opaque")
        got = Renderer(cfg, engine="numba").render(WhiteScene(), rays=3_000_000, seed=2).photons.sum()
        expect = (math.pi * d_um ** 2 / 4) / (100.0 ** 2 * math.sqrt(3) / 2)
        assert got / full == pytest.approx(expect, rel=0.01)


# --- the compiled engine against the reference --------------------------------------------------------


@needs_numba
@pytest.mark.parametrize("cfg_name, boundaries, extra", [
    ("hex", "grid", {}), ("hex", SAG, {}), ("hex", "grid", {"black_matrix_um": 5.0, "corners": "clear"}),
    ("hex", "grid", {"aperture": "circle", "aperture_diameter_um": 90.0, "gap": "opaque"}),
    ("hex", "grid", {"aperture": "circle", "aperture_diameter_um": 96.0, "gap": "clear"}),
    ("square", "grid", {"aperture": "circle", "aperture_diameter_um": 92.0, "gap": "clear"})])
def test_engines_agree_ray_by_ray(cfg_name, boundaries, extra):
    """Same draws through both engines: the same pixels, weights to rounding, with errors on every lens
    (the sag-intersection neighbour pass, the circles' neighbour scan) and global errors."""
    base = HEX if cfg_name == "hex" else SQUARE
    cfg = with_mla(base, boundaries=boundaries, **extra)
    em = hex_errors(6) if cfg_name == "hex" else ErrorMap.zeros(24, 24).with_globals(mla_rotation_deg=0.6)
    if cfg_name == "square":
        rng = np.random.default_rng(1)
        for m, n in rng.integers(2, 23, size=(30, 2)):
            em = em.with_lens(int(m), int(n), pitch_um=float(rng.uniform(0, 5)), pitch_dir_deg=float(rng.uniform(0, 360)),
                              tilt_x_deg=float(rng.uniform(-0.5, 0.5)))
    a = Renderer(cfg, em, engine="numpy")
    b = Renderer(cfg, em, engine="numba")
    i1, w1 = a.trace_batch(WhiteScene(), 7, 60_000, tile=(-1.2, 1.2, -1.2, 1.2))
    i2, w2 = b.trace_batch(WhiteScene(), 7, 60_000, tile=(-1.2, 1.2, -1.2, 1.2))
    assert len(i1) > 20_000
    assert np.array_equal(i1, i2)
    assert np.allclose(w1, w2, rtol=1e-13, atol=0)


@needs_numba
def test_engines_render_the_same_hex_image():
    """The stratified hex sampler (rhombus folded into the hexagon) in both engines: the same image."""
    cfg = with_mla(HEX, boundaries=SAG)
    em = hex_errors(6)
    a = Renderer(cfg, em, engine="numpy").render(WhiteScene(), rays=400_000, seed=4, threads=2)
    b = Renderer(cfg, em, engine="numba").render(WhiteScene(), rays=400_000, seed=4, threads=2)
    assert a.rays_landed == b.rays_landed
    assert np.allclose(a.photons, b.photons, rtol=1e-11, atol=0)


# --- rendering: where the sub-images lie, and an unbiased stratified sampler --------------------------


def _white(cfg, sampler: str, rays: int, seed: int = 1) -> np.ndarray:
    engine = "numba" if raytrace_kernels.AVAILABLE else "numpy"
    return Renderer(cfg, engine=engine, sampler=sampler).render(WhiteScene(), rays=rays, seed=seed).photons


def _subimage_centres_px(cfg) -> tuple[np.ndarray, np.ndarray]:
    """Where the lattice says each sub-image is: the lens centre times (b + gap) / b (the sub-image pitch
    over the lens pitch) from the sensor's centre, in pixel coordinates (pixel centres at integers)."""
    lat = Lattice.of(cfg, unit_um=1.0)
    cx, cy = lat.centres()
    scale = cfg.layout.subimage_pitch_px / cfg.mla.pitch_um
    return (0.5 * cfg.sensor.width_px - 0.5 + cx * scale, 0.5 * cfg.sensor.height_px - 0.5 + cy * scale)


@pytest.fixture(scope="module")
def hex_white() -> np.ndarray:
    return _white(HEX, "sobol", 6_000_000)


def test_hex_subimages_lie_at_the_magnified_lattice(hex_white):
    """Centroid of each inner sub-image (a disc of 0.45 sub-image pitches round where the lattice puts it)
    against the lattice position times the magnification (b + gap) / b."""
    img = hex_white
    ex, ey = _subimage_centres_px(HEX)
    pitch = HEX.layout.subimage_pitch_px
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    err = []
    for r in range(3, HEX.mla.count_h - 3):
        for c in range(3, HEX.mla.count_w - 3):
            x0, y0 = ex[r, c], ey[r, c]
            win = (slice(int(y0 - pitch), int(y0 + pitch) + 1), slice(int(x0 - pitch), int(x0 + pitch) + 1))
            sel = np.hypot(xx[win] - x0, yy[win] - y0) <= 0.45 * pitch
            w = img[win][sel]
            err.append(((xx[win][sel] * w).sum() / w.sum() - x0, (yy[win][sel] * w).sum() / w.sum() - y0))
    err = np.array(err)
    assert np.abs(err.mean(axis=0)).max() < 0.03  # px, over 22 x 18 lenses
    assert np.abs(err).max() < 0.25


def test_hex_white_spectrum_peaks_on_the_reciprocal_lattice(hex_white):
    """The image's spectrum has its peaks at the hexagonal reciprocal lattice of the sub-image lattice
    (vectors (1/P, -1/(sqrt(3) P)), (0, 2/(sqrt(3) P)), P the sub-image pitch), not at a square lattice's
    (1/P, 0), (0, 1/P)."""
    img = hex_white[40:456, 40:456]
    hann = np.hanning(img.shape[0])
    spec = np.abs(np.fft.fft2((img - img.mean()) * np.outer(hann, hann)))  # windowed: little leakage
    n = img.shape[0]
    big = HEX.layout.subimage_pitch_px

    def at(fx: float, fy: float) -> float:  # the spectrum's largest value within one bin of (fx, fy)
        i, j = int(round(fy * n)) % n, int(round(fx * n)) % n
        return spec[np.ix_([(i - 1) % n, i, (i + 1) % n], [(j - 1) % n, j, (j + 1) % n])].max()

    hexp = [at(1 / big, -1 / (math.sqrt(3) * big)), at(0, 2 / (math.sqrt(3) * big)),
            at(1 / big, 1 / (math.sqrt(3) * big))]
    square = [at(1 / big, 0), at(0, 1 / big)]
    floor = np.median(spec)
    assert min(hexp) > 50 * max(square) and min(hexp) > 50 * floor  # the square points are at the noise floor


def test_stratified_hex_sampler_is_unbiased():
    """Sobol cells (hexagons sampled through a folded rhombus) against plain Monte-Carlo on the same
    camera: the total and each inner lens' flux (its sub-image's Voronoi cell on the sensor) agree within
    the Monte-Carlo noise."""
    a = _white(HEX, "sobol", 3_000_000, seed=5)
    b = _white(HEX, "random", 3_000_000, seed=6)
    assert a.sum() / b.sum() == pytest.approx(1.0, abs=0.004)
    ex, ey = _subimage_centres_px(HEX)
    pitch = HEX.layout.subimage_pitch_px
    yy, xx = np.mgrid[0:a.shape[0], 0:a.shape[1]]
    u = (xx - ex[0, 0]) / pitch
    v = (yy - ey[0, 0]) / pitch
    from mlaqc.optics.raytrace import hex_cell
    row, col, _, _ = hex_cell(u, v)
    inner = (row >= 2) & (row < HEX.mla.count_h - 2) & (col >= 2) & (col < HEX.mla.count_w - 2)
    lens = np.where(inner, row * HEX.mla.count_w + col, -1).astype(int).ravel()
    k = lens >= 0
    fa = np.bincount(lens[k], weights=a.ravel()[k], minlength=HEX.mla.count_h * HEX.mla.count_w)
    fb = np.bincount(lens[k], weights=b.ravel()[k], minlength=HEX.mla.count_h * HEX.mla.count_w)
    used = fb > 0
    ratio = fa[used] / fb[used]
    rays_per_lens = 3_000_000 * 0.8 / (HEX.mla.count_h * HEX.mla.count_w)
    sigma = 1.0 / math.sqrt(rays_per_lens)  # the plain Monte-Carlo flux's relative noise, roughly
    assert abs(ratio.mean() - 1.0) < 4 * sigma / math.sqrt(ratio.size)
    assert ratio.std() < 2.0 * sigma
