"""The low-discrepancy sampler: Sobol points against SciPy, the net property after scrambling, counter-based
draws, both engines on stratified jobs, agreement with plain Monte-Carlo (the oracle) within its error
bars on white, texture and point scenes, and lower pixel noise for the same rays."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import qmc

from mlaqc.optics import lowdisc
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Renderer, aperture_shift
from mlaqc.optics.scene import PointScene, TextureScene, WhiteScene

SMALL = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")


def with_sampler(cfg, sampler):
    return dataclasses.replace(cfg, trace=dataclasses.replace(cfg.trace, sampler=sampler))


def test_unscrambled_points_are_scipys_sobol_set():
    """Gray-code order visits the same first 2^m points as the natural order SciPy uses."""
    n = 1 << 10
    j = np.arange(n, dtype=np.uint64)
    ours = np.stack([lowdisc.sobol32(j, d, lowdisc.DIRECTIONS) for d in range(4)], axis=1) * 2.0 ** -32
    ref = qmc.Sobol(d=4, scramble=False).random(n)
    assert np.array_equal(np.array(sorted(map(tuple, ours))), np.array(sorted(map(tuple, ref))))


@pytest.mark.parametrize("key", [0, 7, 2 ** 63 + 12345])
def test_scrambled_and_shifted_points_keep_the_net_property(key):
    """Owen scrambling and a digital shift keep a (0, m, 2)-net a (0, m, 2)-net: every elementary box
    of area 2^-m of the first two dimensions holds exactly one of the first 2^m points, and each
    dimension alone has one point in each of its 2^m intervals."""
    m = 10
    u = lowdisc.cell_uniforms(key, np.arange(1 << m), np.full(1 << m, 37))
    assert u.min() > 0.0 and u.max() < 1.0
    for d in range(4):
        assert len(np.unique(np.floor(u[d] * (1 << m)))) == 1 << m
    for a in range(m + 1):
        box = np.floor(u[0] * (1 << a)) * (1 << (m - a)) + np.floor(u[1] * (1 << (m - a)))
        assert len(np.unique(box)) == 1 << m, a


def test_draws_are_counter_based():
    """A point's draws depend only on the key, its cell and its index, not on which other points are drawn."""
    j = np.arange(5000)
    cells = np.arange(5000) % 13
    full = lowdisc.cell_uniforms(99, j, cells)
    part = lowdisc.cell_uniforms(99, j[1234:2345], cells[1234:2345])
    assert np.array_equal(full[:, 1234:2345], part)
    other_cell = lowdisc.cell_uniforms(99, j, cells + 1)
    other_key = lowdisc.cell_uniforms(100, j, cells)
    assert not np.any(full == other_cell) and not np.any(full == other_key)
    assert np.array_equal(lowdisc.batch_uniforms(5, 300, 2, first=100), lowdisc.batch_uniforms(5, 400, 2)[:, 100:])


def _errors():
    em = ErrorMap.zeros(24, 24).with_lens(5, 6, pitch_um=3, pitch_dir_deg=30).with_lens(8, 8, decenter_um=7)
    em = em.with_lens(10, 14, radius_front_rel=0.1).with_lens(15, 4, tilt_x_deg=2, tilt_y_deg=-1)
    return em.with_globals(mla_rotation_deg=0.7, mla_tilt_x_deg=0.2, mla_sensor_distance_um=4, mla_shift_x_um=15)


@pytest.mark.parametrize("scene", [WhiteScene(), TextureScene(np.linspace(0, 1, 35 * 20).reshape(20, 35))])
def test_both_engines_trace_the_same_rays_on_stratified_jobs(scene):
    em = _errors()
    a = Renderer(SMALL, em, engine="numpy", sampler="sobol")
    b = Renderer(SMALL, em, engine="numba", sampler="sobol")
    jobs = a.jobs(scene, 3_000_000)
    assert all(j.cells is not None for j in jobs)
    for job in (jobs[0], jobs[len(jobs) // 2]):  # a border block (padding cells) and an inner one
        i1, w1 = a.trace_batch(scene, 99, job.n, cells=job.cells)
        i2, w2 = b.trace_batch(scene, 99, job.n, cells=job.cells)
        assert len(i1) > 0.2 * job.n
        assert np.array_equal(i1, i2)
        assert np.allclose(w1, w2, rtol=1e-13, atol=0)


def test_every_cell_gets_the_same_rays_whatever_the_batching():
    r = Renderer(SMALL, sampler="sobol")
    small = dataclasses.replace(SMALL, trace=dataclasses.replace(SMALL.trace, batch_rays=1 << 12, sampler="sobol"))
    for renderer in (r, Renderer(small)):
        jobs = renderer.jobs(WhiteScene(), 2_000_000)
        per_cell = {}
        for j in jobs:
            r0, c0, h, w, j0 = j.cells
            assert j.n % (h * w) == 0
            for rr in range(r0, r0 + h):
                for cc in range(c0, c0 + w):
                    per_cell[(rr, cc)] = per_cell.get((rr, cc), 0) + j.n // (h * w)
        assert len(per_cell) == 26 * 26 and len(set(per_cell.values())) == 1


def _cells(img):
    return img[8:488, 8:488].reshape(24, 20, 24, 20).sum(axis=(1, 3))


@pytest.mark.parametrize("scene", [WhiteScene(), TextureScene(np.add.outer(np.arange(9) % 2, np.arange(13) % 3) / 3.0)])
def test_sobol_agrees_with_monte_carlo_within_its_error_bars(scene):
    """Per-lens flux and the total of both estimators agree to the Monte-Carlo error, with per-lens and
    global errors (rotated, tilted, shifted MLA: the stratified cells must map to the same plane area)."""
    em = _errors()
    rpp = 40
    mc = [Renderer(SMALL, em, sampler="random").render(scene, rays_per_pixel=rpp, seed=s).photons for s in (1, 2)]
    qm = Renderer(SMALL, em, sampler="sobol").render(scene, rays_per_pixel=rpp, seed=3).photons
    lit = _cells(mc[0] + mc[1]) > 0.2 * _cells(mc[0] + mc[1]).max()
    sigma = np.abs(_cells(mc[0]) - _cells(mc[1]))[lit].std() / np.sqrt(2)  # one MC render's per-lens error
    dev = (_cells(qm) - 0.5 * (_cells(mc[0]) + _cells(mc[1])))[lit]
    assert np.abs(dev).max() < 5 * sigma * np.sqrt(1.5)  # qm error (smaller) + the mean of two MC renders
    assert abs(dev.mean()) < 4 * sigma * np.sqrt(1.5 / lit.sum())
    assert qm.sum() == pytest.approx(0.5 * (mc[0].sum() + mc[1].sum()), rel=2e-3)


def test_point_source_agrees_with_monte_carlo():
    scene = PointScene(((0.3, -0.2),), 1e6)
    mc = [Renderer(SMALL, sampler="random").render(scene, rays=300_000, seed=s).photons for s in (1, 2)]
    qm = Renderer(SMALL, sampler="sobol").render(scene, rays=300_000, seed=3).photons
    ys, xs = np.mgrid[0:496, 0:496]

    def centroid(img):
        return (img * xs).sum() / img.sum(), (img * ys).sum() / img.sum()

    (x1, y1), (x2, y2), (xq, yq) = centroid(mc[0]), centroid(mc[1]), centroid(qm)
    spread = max(abs(x1 - x2), abs(y1 - y2), 0.02)
    assert abs(xq - 0.5 * (x1 + x2)) < 4 * spread and abs(yq - 0.5 * (y1 + y2)) < 4 * spread
    assert qm.sum() == pytest.approx(0.5 * (mc[0].sum() + mc[1].sum()), rel=5e-3)


def test_stratified_sampler_lowers_pixel_noise_at_equal_rays():
    """Pixel noise over the lit pixels from two seeds: at 100 rays per pixel the Sobol sampler is
    measured at 3.5x below plain Monte-Carlo (bench/sampling.py prints the curve)."""
    noise = {}
    for sampler in ("random", "sobol"):
        r = Renderer(SMALL, sampler=sampler)
        a, b = (r.render(WhiteScene(), rays_per_pixel=100, seed=s).photons for s in (1, 2))
        m = 0.5 * (a + b)
        lit = m > 0.5 * np.percentile(m, 99)
        noise[sampler] = np.std((a - b)[lit]) / np.sqrt(2) / m[lit].mean()
    assert noise["random"] > 3.0 * noise["sobol"], noise


def test_aperture_shift_is_paraxially_the_start_offset():
    """Near a cell's centre a ray started h off and aimed h further over on the aperture lands where the
    central ray does (Phi = h: c0 = 1); the microlens' spherical aberration pulls the shift back towards the
    cell's rim (c1 < 0) and its coma makes it depend on where on the aperture the ray leaves (c4 != 0)."""
    r = Renderer(SMALL, engine="numpy")
    coef, r_max, reach = aperture_shift(SMALL, r.image_region)
    assert coef[0] == pytest.approx(1.0, abs=0.02)
    assert coef[1] < -5 and abs(coef[4]) > 1
    assert r_max == pytest.approx(0.05 * np.sqrt(2))
    assert r.cells.square_half_mm > r.image_region.exit_radius_mm + reach
