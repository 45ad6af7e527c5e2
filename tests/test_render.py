"""Rendered images against independent facts: sub-image geometry, error signatures, energy, determinism.

Renders of the same seed share their random draws ray by ray (counter-based sampling), so an image with
one defective lens differs from the perfect one only in the light of that lens: differences isolate it.
Every test runs twice: with the low-discrepancy sampler (the default) and with plain Monte-Carlo, the
oracle it must agree with.
"""

import dataclasses
import math
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from mlaqc.optics.config import default_config, load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import PointScene, TextureScene, WhiteScene

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
BASE = load_config(FIXTURES / "small_camera.toml")
SMALL = BASE  # the small camera with the sampler under test (set by the `sampler` fixture)
LENS = (12, 12)  # a central lens of the 24 x 24 small camera


def with_sampler(cfg, sampler):
    return dataclasses.replace(cfg, trace=dataclasses.replace(cfg.trace, sampler=sampler))


@pytest.fixture(scope="module", params=["sobol", "random"], autouse=True)
def sampler(request):
    """Run the module once per sampler (pytest groups the tests by this module-scoped parameter)."""
    global SMALL
    SMALL = with_sampler(BASE, request.param)
    yield request.param
    SMALL = BASE


def centre_px(cfg, m, n):
    """Paraxial sub-image centre of U(m,n) in pixel coordinates: the chief ray through the lens centre."""
    lay, s = cfg.layout, cfg.sensor
    cy = (s.height_px - 1) / 2 + (m - (cfg.mla.count_h + 1) / 2) * lay.subimage_pitch_px
    cx = (s.width_px - 1) / 2 + (n - (cfg.mla.count_w + 1) / 2) * lay.subimage_pitch_px
    return cx, cy


def window(img, cx, cy, half):
    iy, ix = int(round(cy)), int(round(cx))
    y, x = np.mgrid[iy - half:iy + half + 1, ix - half:ix + half + 1]
    return img[iy - half:iy + half + 1, ix - half:ix + half + 1], x, y


@pytest.fixture(scope="module")
def small_base(sampler):
    return Renderer(SMALL).render(WhiteScene(), rays_per_pixel=40, seed=7).photons


def render_small(seed=7, rpp=40, **lens_errors):
    em = ErrorMap.zeros(24, 24).with_lens(*LENS, **lens_errors)
    return Renderer(SMALL, em).render(WhiteScene(), rays_per_pixel=rpp, seed=seed).photons


def lens_shift_px(img, base, cfg=SMALL, lens=LENS):
    """Centroid displacement of one lens' light, from the first moment of the difference image.

    Coordinates are taken about the lens' nominal centre, so a small change of its flux (its corners
    move too) only enters at second order."""
    cx, cy = centre_px(cfg, *lens)
    d, x, y = window(img - base, cx, cy, 16)
    flux, _, _ = window(base, cx, cy, 10)
    f = flux.sum()
    return (d * (x - cx)).sum() / f, (d * (y - cy)).sum() / f


# --- white image geometry ----------------------------------------------------------------------


def centroids(img, cfg, iters=8, sigma=4.0, half=9):
    """Iterative Gaussian-weighted centroids of every sub-image (vectorized over lenses)."""
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    cx0, cy0 = centre_px(cfg, np.arange(1, rows + 1)[:, None], np.arange(1, cols + 1)[None, :])
    cx, cy = np.broadcast_arrays(cx0, cy0)
    cx, cy = cx.astype(float), cy.astype(float)
    off = np.arange(-half, half + 1)
    for _ in range(iters):
        iy = np.rint(cy).astype(int)[..., None, None] + off[:, None]
        ix = np.rint(cx).astype(int)[..., None, None] + off[None, :]
        win = img[np.clip(iy, 0, img.shape[0] - 1), np.clip(ix, 0, img.shape[1] - 1)]
        g = win * np.exp(-((iy - cy[..., None, None]) ** 2 + (ix - cx[..., None, None]) ** 2) / (2 * sigma ** 2))
        cy, cx = (g * iy).sum((2, 3)) / g.sum((2, 3)), (g * ix).sum((2, 3)) / g.sum((2, 3))
    return cx, cy


@pytest.fixture(scope="module")
def full_white(sampler):
    cfg = with_sampler(default_config(), sampler)
    return cfg, Renderer(cfg).render(WhiteScene(), rays_per_pixel=5, seed=11).photons


def test_white_subimage_pitch_is_p_b_plus_f_over_b(full_white):
    """Sub-image centres are spaced p*(b+f)/b (20.048 px), not p/s = 20 px, to 0.02 px over the array."""
    cfg, img = full_white
    lay = cfg.layout
    b = lay.pupil_to_mla_mm
    f = lay.z_sensor_mm - lay.z_mla_mm
    expected = 100.0 * (b + f) / b / 5.0
    assert expected == pytest.approx(20.048, abs=0.001)
    cx, cy = centroids(img, cfg)
    n = np.arange(102)
    pitch_x = np.polyfit(n, cx.mean(axis=0), 1)[0]
    pitch_y = np.polyfit(n, cy.mean(axis=1), 1)[0]
    assert pitch_x == pytest.approx(expected, abs=0.02)
    assert pitch_y == pytest.approx(expected, abs=0.02)
    assert abs(pitch_x - 20.0) > 0.03  # and clearly not the naive 20 px


def test_white_image_is_symmetric_about_the_axis(full_white):
    cfg, img = full_white
    cx, cy = centroids(img, cfg)
    ex, ey = centre_px(cfg, np.arange(1, 103)[:, None], np.arange(1, 103)[None, :])
    dx, dy = cx - ex, cy - ey
    assert abs(dx.mean()) < 0.01 and abs(dy.mean()) < 0.01  # centred on the optical axis
    # point symmetry: U(m,n) mirrors U(103-m, 103-n) (averaged over the array; per lens it is MC noise)
    assert abs((dx + dx[::-1, ::-1]).mean()) < 0.01 and abs((dy + dy[::-1, ::-1]).mean()) < 0.01
    rows = img.sum(axis=1)
    assert rows[:1024].sum() == pytest.approx(rows[1024:].sum(), rel=2e-3)


def test_white_level_falls_off_towards_the_corners_as_cos4(full_white):
    """Natural vignetting: the corner patch is dimmer than the centre by cos^4 of its chief-ray angle
    (from the exit pupil, near the rear principal plane), a little more where the two rims clip."""
    cfg, img = full_white
    centre = img[924:1124, 924:1124].mean()
    corner = img[10:210, 10:210].mean()
    r_mm = math.hypot(1023.5 - 109.5, 1023.5 - 109.5) * 5e-3
    cos4 = math.cos(math.atan(r_mm / cfg.layout.pupil_to_mla_mm)) ** 4
    assert cos4 - 0.01 < corner / centre < cos4 + 0.002


# --- error signatures (small camera, same draws with and without the error) ---------------------


@pytest.mark.parametrize("alpha", [0.0, 90.0, 225.0])
def test_pitch_error_moves_its_subimage_by_dp_b_plus_f_over_b(alpha):
    """With grid lens boundaries, set explicitly: there the whole lens' optics move and its square aperture
    stays on the grid, so its light moves by Δp·(b+f)/b and no neighbour's light changes. With the default
    sag-intersection boundaries the aperture moves by about Δp/2 and the neighbours' light changes (see
    tests/test_boundaries.py)."""
    grid = dataclasses.replace(SMALL, mla=dataclasses.replace(SMALL.mla, boundaries="grid"))
    small_base = Renderer(grid).render(WhiteScene(), rays_per_pixel=40, seed=7).photons
    lay = SMALL.layout
    gain = (lay.pupil_to_mla_mm + lay.z_sensor_mm - lay.z_mla_mm) / lay.pupil_to_mla_mm
    dp_um = 2.0
    em = ErrorMap.zeros(24, 24).with_lens(*LENS, pitch_um=dp_um, pitch_dir_deg=alpha)
    img = Renderer(grid, em).render(WhiteScene(), rays_per_pixel=40, seed=7).photons
    dx, dy = lens_shift_px(img, small_base)
    expect = dp_um * gain / SMALL.sensor.pixel_um
    a = math.radians(alpha)
    assert math.hypot(dx, dy) == pytest.approx(expect, rel=0.10)
    # direction: counterclockwise from +x towards the image top (y down in pixels)
    assert math.degrees(math.atan2(-dy, dx)) % 360 == pytest.approx(alpha % 360, abs=5.0)
    # the neighbours' light is untouched
    cx, cy = centre_px(SMALL, *LENS)
    for dm, dn in ((0, 2), (2, 0), (-2, -2)):
        nx, ny = centre_px(SMALL, LENS[0] + dm, LENS[1] + dn)
        a_, _, _ = window(img, nx, ny, 6)
        b_, _, _ = window(small_base, nx, ny, 6)
        assert np.array_equal(a_, b_)
    _ = a


def test_decenter_moves_and_skews_its_subimage_and_direction_rotates_the_effect(small_base):
    shifts = {}
    for beta in (0.0, 90.0):
        img = render_small(decenter_um=8.0, decenter_dir_deg=beta)
        shifts[beta] = lens_shift_px(img, small_base)
        cx, cy = centre_px(SMALL, *LENS)
        w, x, y = window(img, cx, cy, 10)
        w0, _, _ = window(small_base, cx, cy, 10)

        def skew(v, ww):
            m = (ww * v).sum() / ww.sum()
            return (ww * (v - m) ** 3).sum() / ww.sum()

        along, across = (x, y) if beta == 0.0 else (y, x)
        assert abs(skew(along, w) - skew(along, w0)) > 3 * abs(skew(across, w) - skew(across, w0))
    (dx0, dy0), (dx9, dy9) = shifts[0.0], shifts[90.0]
    assert abs(dx0) > 0.3 and abs(dy0) < 0.1 * abs(dx0)  # beta = 0 moves it along x
    assert abs(dy9) > 0.3 and abs(dx9) < 0.1 * abs(dy9)  # beta = 90 moves it along y
    assert math.hypot(dx0, dy0) == pytest.approx(math.hypot(dx9, dy9), rel=0.1)  # same size, rotated


def test_radius_error_defocuses_the_subimage_about_the_aberrated_best_focus():
    """Sensor at the nominal (paraxial) focal plane: a shorter radius (shorter focal length) blurs the
    sub-image's edge more the larger |eps| is. The microlens' spherical aberration puts its best focus
    beyond the paraxial one, so a slightly longer radius first sharpens the edge (+5 %) before a large
    one blurs it (+20 %). (Plain Monte-Carlo noise at a few tens of rays per pixel adds its own gradient
    energy and hid the first half of this; hence 150 rays per pixel.)"""
    cx, cy = centre_px(SMALL, *LENS)

    def sharpness(eps):
        img = render_small(rpp=150, radius_front_rel=eps, radius_back_rel=eps)
        w, _, _ = window(img, cx, cy, 10)
        gy, gx = np.gradient(w)
        return (gx ** 2 + gy ** 2).sum() / w.sum() ** 2

    s = {eps: sharpness(eps) for eps in (-0.1, -0.05, 0.0, 0.05, 0.2)}
    assert s[0.0] > s[-0.05] > s[-0.1], s
    assert s[0.05] > s[0.0] > s[0.2], s


def test_global_sensor_distance_error_changes_every_subimage_alike():
    em = ErrorMap.zeros(24, 24).with_globals(mla_sensor_distance_um=30.0)
    base = Renderer(SMALL).render(WhiteScene(), rays_per_pixel=60, seed=3).photons
    img = Renderer(SMALL, em).render(WhiteScene(), rays_per_pixel=60, seed=3).photons
    _, cy = centroids(base, SMALL)
    _, cy2 = centroids(img, SMALL)
    # a farther sensor spreads the sub-image grid: pitch grows by (b + f + dz) / (b + f)
    lay = SMALL.layout
    f = lay.z_sensor_mm - lay.z_mla_mm
    ratio = (lay.pupil_to_mla_mm + f + 0.030) / (lay.pupil_to_mla_mm + f)
    p0 = np.polyfit(np.arange(24), cy.mean(axis=1), 1)[0]
    p1 = np.polyfit(np.arange(24), cy2.mean(axis=1), 1)[0]
    # paraxial ratio 1.000170; converged renders give 1.000132 (the defocused sub-image's centroid is not
    # quite its chief ray), and 60 rays per pixel add about 1e-5 of noise
    assert p1 / p0 == pytest.approx(ratio, abs=7e-5)


# --- engines, estimators, energy ---------------------------------------------------------------


def _all_errors():
    em = ErrorMap.zeros(24, 24)
    em = em.with_lens(5, 6, pitch_um=3, pitch_dir_deg=30).with_lens(8, 8, decenter_um=7, decenter_dir_deg=200)
    em = em.with_lens(10, 14, radius_front_rel=0.1, radius_back_rel=-0.05).with_lens(15, 4, tilt_x_deg=2, tilt_y_deg=-1)
    em = em.with_lens(18, 18, thickness_um=-3).with_lens(20, 3, pitch_um=1)
    return em.with_globals(mla_rotation_deg=0.7, mla_tilt_x_deg=0.2, mla_sensor_distance_um=4, mla_shift_x_um=15)


@pytest.mark.parametrize("scene", [WhiteScene(), TextureScene(np.linspace(0, 1, 35 * 20).reshape(20, 35)),
                                   PointScene(((0.2, -0.3), (-1.0, 0.5)), 1e5)])
@pytest.mark.parametrize("sampling", ["image", "object"])
def test_numba_engine_traces_exactly_the_numpy_reference_rays(scene, sampling):
    em = _all_errors()
    a = Renderer(SMALL, em, sampling=sampling, engine="numpy")
    b = Renderer(SMALL, em, sampling=sampling, engine="numba")
    kw = dict(point=(0.2, -0.3)) if isinstance(scene, PointScene) else dict(tile=(-1.3, 1.3, -1.2, 1.1))
    i1, w1 = a.trace_batch(scene, 99, 50_000, **kw)
    i2, w2 = b.trace_batch(scene, 99, 50_000, **kw)
    assert len(i1) > 10_000
    assert np.array_equal(i1, i2)
    assert np.allclose(w1, w2, rtol=1e-13, atol=0)


def test_image_side_and_object_side_sampling_agree():
    """Two independent estimators of the same irradiance (backward vs forward through the main lens)."""
    em = ErrorMap.zeros(24, 24).with_lens(12, 12, decenter_um=6, decenter_dir_deg=45)
    a = Renderer(SMALL, em, sampling="image").render(WhiteScene(), rays_per_pixel=30, seed=1).photons
    b = Renderer(SMALL, em, sampling="object").render(WhiteScene(), rays_per_pixel=60, seed=2).photons
    assert b.sum() == pytest.approx(a.sum(), rel=0.01)
    # per-lens flux of the 24 x 24 cells agrees to MC noise
    def cells(img):
        return img[8:488, 8:488].reshape(24, 20, 24, 20).sum(axis=(1, 3))
    ratio = cells(b) / cells(a)
    assert np.median(np.abs(ratio - 1)) < 0.02


def test_fresnel_losses_match_four_surfaces_of_transmission():
    cfg_off = dataclasses.replace(SMALL, trace=dataclasses.replace(SMALL.trace, fresnel=False))
    on = Renderer(SMALL).render(WhiteScene(), rays_per_pixel=10, seed=5).photons.sum()
    off = Renderer(cfg_off).render(WhiteScene(), rays_per_pixel=10, seed=5).photons.sum()
    t_main = 1 - ((1.5168 - 1) / (1.5168 + 1)) ** 2
    t_mla = 1 - ((1.56 - 1) / (1.56 + 1)) ** 2
    # near-normal incidence everywhere (f/2.5): within 1 % of the normal-incidence product
    assert on / off == pytest.approx(t_main ** 2 * t_mla ** 2, rel=0.01)
    assert on < off


def test_point_source_flux_is_conserved_to_the_lens_transmission():
    """The photons an axial point sends into the pupil reach the sensor, less four Fresnel losses and a
    few per cent more: opaque lens corners (0.25 %), the front rim clipping rays aimed at the edge of the
    vertex-plane pupil disc (~1.6 %), cos^3 and oblique Fresnel (full camera: the main lens' ~1.7 mm
    aberration blur fits on its MLA)."""
    scene = PointScene(((0.0, 0.0),), 1e6)
    img = Renderer(with_sampler(default_config(), SMALL.trace.sampler)).render(scene, rays=400_000, seed=3).photons
    fresnel = (1 - (0.5168 / 2.5168) ** 2) ** 2 * (1 - (0.56 / 2.56) ** 2) ** 2
    assert fresnel * 0.95 * 1e6 < img.sum() < fresnel * 1e6


# --- determinism and memory -------------------------------------------------------------------


def test_seeded_renders_are_bit_identical_across_runs_and_thread_counts():
    em = _all_errors()
    r = Renderer(SMALL, em)
    a = r.render(WhiteScene(), rays_per_pixel=4, seed=42, threads=1).photons
    b = r.render(WhiteScene(), rays_per_pixel=4, seed=42, threads=2).photons
    c = Renderer(SMALL, em).render(WhiteScene(), rays_per_pixel=4, seed=42, threads=3).photons
    d = r.render(WhiteScene(), rays_per_pixel=4, seed=43).photons
    assert np.array_equal(a, b) and np.array_equal(a, c)
    assert not np.array_equal(a, d)


def test_memory_is_bounded_by_batching_not_ray_count():
    cfg = dataclasses.replace(SMALL, trace=dataclasses.replace(SMALL.trace, batch_rays=1 << 15))
    r = Renderer(cfg)
    peaks = []
    for rays in (2_000_000, 8_000_000):
        tracemalloc.start()
        r.render(WhiteScene(), rays=rays, seed=1, threads=2)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    assert peaks[1] < 1.3 * peaks[0]
    assert peaks[1] < 64 * 2 ** 20


def test_progress_is_reported_to_completion():
    seen = []
    res = Renderer(SMALL).render(WhiteScene(), rays=3_000_000, seed=0, progress=lambda d, t: seen.append((d, t)))
    assert seen[-1][0] == seen[-1][1] == res.rays_traced
    # the stratified sampler gives every one of the 26 x 26 padded cells the same number of rays
    assert abs(res.rays_traced - 3_000_000) <= (26 * 26 if SMALL.trace.sampler == "sobol" else 0)
    assert all(a[0] <= b[0] for a, b in zip(seen, seen[1:]))
