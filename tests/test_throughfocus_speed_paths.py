"""The through-focus analysis' fast paths (mlaqc.inspection.throughfocus) against their plain definitions:
the compiled moments and first guess against the per-pixel sums, the lattice's nearest pinhole
against the argmin over every pinhole, the compiled window cut against the normalized frame, the per-frame
constants eliminated before the field polynomial against one least squares with a column per frame, the
pairs on threads against a plain loop, the likelihood reading against the Gaussian's closed form, and
the model's disk cache (read back as traced; a damaged file traced again). No wall-clock assertions.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from analytic_frames import AnalyticModel
from mlaqc.inspection import throughfocus as tf
from mlaqc.inspection import throughfocus_fits as tf_fits
from mlaqc.inspection import throughfocus_geometry as tf_geometry
from mlaqc.inspection import throughfocus_model as tf_model
from mlaqc.inspection import throughfocus_reading as tf_reading
from mlaqc.inspection import throughfocus_spots as tf_spots
from mlaqc.inspection.calibrate import calibrate
from mlaqc.optics.config import default_config, load_config
from mlaqc.optics.throughfocus import ThroughFocus, pair_radius_lenses, pinhole_lenses

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
SMALL = load_config(FIXTURES / "small_camera.toml")


def _share(centre, w, coords):
    """(L, n): the share of each pixel [k - 1/2, k + 1/2] inside [centre - w, centre + w]."""
    return np.clip(w[:, None] + 0.5 - np.abs(coords[None, :] - centre[:, None]), 0.0, 1.0)


def _plain_moments(sp: tf_spots.Spots, cx, cy, w, e_per_unit: float, refine: int = 2):
    """The moments written out pixel by pixel (the weights' full (L, n, n) product)."""
    n = sp.cells.shape[1]
    half = n // 2
    k = np.arange(n) - half
    limit = half - tf_spots.RING_PX - 0.5
    w = np.clip(w, 0.5, limit)
    for it in range(refine + 1):
        wx, wy = _share(cx, w, k), _share(cy, w, k)
        wgt = wy[:, :, None] * wx[:, None, :]
        flux = np.sum(sp.cells * wgt, axis=(1, 2))
        mx = np.sum(sp.cells * wgt * k[None, None, :], axis=(1, 2)) / flux
        my = np.sum(sp.cells * wgt * k[None, :, None], axis=(1, 2)) / flux
        if it < refine:
            cx = np.clip(np.where(np.isfinite(mx), mx, cx), -half + 1, half - 1)
            cy = np.clip(np.where(np.isfinite(my), my, cy), -half + 1, half - 1)
            w = np.clip(np.minimum(w, limit - np.maximum(np.abs(cx), np.abs(cy)) + tf_spots.RING_PX), 0.5, limit)
    r2 = (k[None, None, :] - mx[:, None, None]) ** 2 + (k[None, :, None] - my[:, None, None]) ** 2
    m2 = np.sum(sp.cells * wgt * r2, axis=(1, 2)) / flux
    var_pix = np.maximum(sp.cells + sp.background[:, None, None], 0.0) / e_per_unit + sp.bg_sigma ** 2
    lever = wgt * (r2 - m2[:, None, None])
    m2_var = np.sum(lever ** 2 * var_pix, axis=(1, 2)) / flux ** 2
    ring = n * n - (n - 2 * tf_spots.RING_PX) ** 2
    m2_var += (np.pi / 2) * sp.bg_sigma ** 2 / ring * (lever.sum(axis=(1, 2)) / flux) ** 2
    return mx, my, m2, m2_var, flux, w


def _random_spots(n_lens: int = 300, seed: int = 1) -> tf_spots.Spots:
    """Gaussian spots of 0.5-2 px rms anywhere within 3 px of the window's centre, with noise."""
    rng = np.random.default_rng(seed)
    k = np.arange(21) - 10
    cx, cy = rng.uniform(-3, 3, (2, n_lens))
    s = rng.uniform(0.5, 2.0, n_lens)
    cells = np.exp(-((k[None, None, :] - cx[:, None, None]) ** 2 + (k[None, :, None] - cy[:, None, None]) ** 2)
                   / (2 * s[:, None, None] ** 2)) * 0.3 + rng.normal(0, 1e-3, (n_lens, 21, 21))
    return tf_spots.Spots(cells, np.zeros(n_lens, np.int64), np.zeros(n_lens, np.int64), np.full(n_lens, 0.01), 1e-3,
                          np.zeros(n_lens, bool))


def _plain_first_guess(sp: tf_spots.Spots):
    """The brightest 3 x 3 box sum centred inside the ring, by ndimage (first of equals, row-major)."""
    from scipy import ndimage

    n, r = sp.cells.shape[1], tf_spots.RING_PX
    box = ndimage.uniform_filter(sp.cells, size=(1, 3, 3), mode="constant") * 9
    inner = box[:, r:n - r, r:n - r].reshape(len(box), -1)
    iy, ix = np.divmod(inner.argmax(axis=1), n - 2 * r)
    return ix + r - n // 2, iy + r - n // 2


@pytest.mark.parametrize("refine", [0, 1, 2])
def test_compiled_moments_equal_the_pixel_sums(refine):
    sp = _random_spots()
    cx, cy, w = tf_spots._spot_window(sp, 2e4)
    fast = tf_spots.moments(sp, cx, cy, w, 2e4, refine=refine)
    plain = _plain_moments(sp, cx, cy, w, 2e4, refine=refine)
    for a, b in zip(fast, plain):
        assert np.allclose(a, b, rtol=1e-10, atol=1e-13)
    m = tf_spots.moments(sp, cx, cy, w, 2e4, refine=refine, variance=False)
    assert m[3] is None and np.array_equal(m[2], fast[2])


def test_a_window_without_light_reads_nan_and_keeps_its_place():
    """A dark window: flux 0, no centroid (NaN), the window not moved; its neighbours unaffected."""
    sp = _random_spots(4)
    cells = sp.cells.copy()
    cells[1] = 0.0
    sp = replace(sp, cells=cells)
    mx, my, m2, var, flux, w = tf_spots.moments(sp, np.zeros(4), np.zeros(4), np.full(4, 3.0), 2e4)
    assert flux[1] == 0.0 and np.isnan(mx[1]) and np.isnan(m2[1]) and w[1] == 3.0
    assert np.isfinite(m2[[0, 2, 3]]).all()


def test_first_guess_is_the_brightest_box_inside_the_ring():
    sp = _random_spots(200, seed=4)
    gx, gy = tf_spots._first_guess(sp)
    px, py = _plain_first_guess(sp)
    assert np.array_equal(gx, px) and np.array_equal(gy, py)


@pytest.mark.parametrize("cfg", [default_config(), SMALL], ids=["table1", "small"])
@pytest.mark.parametrize("u, f, s, off", [(5, 11, 4, (0, 0)), (5, 11, 4, (3, 1)), (10, 8, 9, (0, 0)),
                                          (10, 8, 9, (4, 7)), (5, 8, 9, (2, 2)), (3, 4, 2, (1, 0))])
def test_the_lattices_nearest_pinhole_is_the_argmin_over_all(cfg, u, f, s, off):
    rec = ThroughFocus(u, f, s, off)
    lit, near, dxy = tf_geometry.coverage(cfg, rec)
    pins = pinhole_lenses(cfg, rec)
    m, n = np.meshgrid(np.arange(cfg.mla.count_h), np.arange(cfg.mla.count_w), indexing="ij")
    d2 = (m[..., None] - pins[:, 0]) ** 2 + (n[..., None] - pins[:, 1]) ** 2
    want = np.argmin(d2, axis=-1)
    assert np.array_equal(near, want)
    assert np.array_equal(dxy, np.stack([n - pins[want, 1], m - pins[want, 0]], axis=-1))
    r_in = pair_radius_lenses(cfg, rec)
    assert np.array_equal(lit, np.min(d2, axis=-1) <= r_in * r_in)


@pytest.mark.parametrize("stored", ["uint16", "float32", "float64"])
def test_spot_windows_are_the_normalized_frame_less_the_ring_median(stored):
    """The compiled cut equals its definition: the frame normalized as raw_levels.normalized does (float32),
    each window less the NumPy median of its outer ring, saturation where a pixel reaches SATURATED."""
    from mlaqc.inspection.raw_levels import normalized
    from mlaqc.inspection.rawio import RawFrame

    rng = np.random.default_rng(3)
    counts = rng.integers(60, 4095, (120, 150)).astype(np.uint16)
    counts[40, 50] = 4095  # a saturated pixel in one window
    raw = RawFrame(counts, 12, None, 64, 4095)
    norm = normalized(raw)
    frame = tf_spots.prepare_spots(raw) if stored == "uint16" else tf_spots.SpotFrame(norm.astype(stored))
    x, y = rng.uniform(12, 137, 40), rng.uniform(12, 107, 40)
    x[0], y[0] = 50.3, 39.6
    sp = tf_spots.spots(frame, x, y, 10)
    ix, iy = np.rint(x).astype(int), np.rint(y).astype(int)
    ring = np.ones((21, 21), bool)
    ring[tf_spots.RING_PX:21 - tf_spots.RING_PX, tf_spots.RING_PX:21 - tf_spots.RING_PX] = False
    for m in range(len(x)):
        win = norm[iy[m] - 10:iy[m] + 11, ix[m] - 10:ix[m] + 11]
        bg = np.median(win[ring])
        assert sp.background[m] == bg
        assert np.array_equal(sp.cells[m], (win - bg).astype(np.float64))
        assert sp.saturated[m] == (win >= tf_spots.SATURATED).any()
    assert sp.saturated[0] and sp.saturated.sum() >= 1
    assert np.array_equal(frame.image(), norm)


def test_frame_constants_eliminated_first_give_the_joint_least_squares():
    rng = np.random.default_rng(2)
    n, frames = 4000, 12
    frame = rng.integers(0, frames, n)
    xy = rng.uniform(-7, 7, (n, 2))
    v = 0.3 * frame + 0.01 * xy[:, 0] ** 2 - 0.002 * xy[:, 0] * xy[:, 1] ** 2 + rng.normal(0, 0.05, n)
    v[rng.random(n) < 0.02] += 3.0  # outliers the robust passes drop
    v[:3] = np.nan
    got = tf_fits._field_removed(v, xy, frame)
    # the plain form: one least squares with a column per frame, the same robust passes
    x, y = xy[:, 0], xy[:, 1]
    a = np.stack([(frame == f).astype(float) for f in range(frames)]
                 + [x, y, x * x, x * y, y * y, x ** 3, x * x * y, x * y * y, y ** 3], axis=1)
    ok = np.isfinite(v)
    keep = ok.copy()
    for _ in range(3):
        beta, *_ = np.linalg.lstsq(a[keep], v[keep], rcond=None)
        want = v - a @ beta
        keep = ok & (np.abs(want) <= 4.0 * max(tf_fits._robust_sigma(want[keep]), 1e-12))
    assert np.allclose(got[ok], want[ok], atol=1e-10) and np.isnan(got[~ok]).all()


def test_the_likelihood_reading_of_a_straight_curve_is_its_crossing_and_noise_over_slope():
    """exp(-(c(e) - x)^2 / 2 s^2) on a straight c = a + b e is a Gaussian in e: mean (x - a) / b, sd
    s / |b|; on a flat one it is the span's uniform mean and sd."""
    e = np.tile(np.linspace(-0.03, 0.03, 13), (2, 1))
    b = np.array([-25.0, 0.0])
    cv = 0.2 + b[:, None] * e
    x = np.array([0.2 + 25.0 * 0.004, 0.2])
    noise = np.array([0.02, 0.02])
    mean, sd = tf_reading._likelihood_mean(cv, e, x, noise)
    assert mean[0] == pytest.approx(-0.004, abs=2e-5) and sd[0] == pytest.approx(0.02 / 25.0, rel=0.02)
    assert mean[1] == pytest.approx(0.0, abs=1e-12) and sd[1] == pytest.approx(0.06 / math.sqrt(12), rel=0.02)


def _plain_likelihood_mean(cv, e, x, noise):
    """The likelihood reading written with whole-array NumPy: every row's curve at SUBSTEPS points per
    interval, its chi-square, the weights and their moments."""
    L, K = cv.shape
    t = np.arange(tf_reading.SUBSTEPS) / tf_reading.SUBSTEPS
    c = np.concatenate([(cv[:, :-1, None] + (cv[:, 1:] - cv[:, :-1])[:, :, None] * t).reshape(L, -1), cv[:, -1:]], axis=1)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        chi = ((c - x[:, None]) / noise[:, None]) ** 2
        chi[~np.isfinite(chi)] = np.inf
        w = np.exp(-0.5 * (chi - chi.min(axis=1, keepdims=True)))
        pos = np.arange(c.shape[1])
        m1 = (w * pos).sum(axis=1) / w.sum(axis=1)
        m2 = (w * pos ** 2).sum(axis=1) / w.sum(axis=1)
    step = (e[:, 1] - e[:, 0]) / tf_reading.SUBSTEPS
    return e[:, 0] + m1 * step, np.maximum(np.sqrt(np.maximum(m2 - m1 * m1, 0.0)) * step, step / math.sqrt(12.0))


def test_compiled_likelihood_reading_equals_the_array_formula():
    """Random curves (some flat, some steep, one NaN reading, one zero noise): the compiled reading is the
    whole-array formula's, NaN where it is."""
    rng = np.random.default_rng(8)
    L, K = 400, 13
    e = np.tile(np.linspace(-0.03, 0.03, K), (L, 1)) + rng.uniform(-0.1, 0.1, (L, 1))
    cv = rng.normal(0, 0.05, (L, 1)) + rng.uniform(-40, 40, (L, 1)) * e + rng.normal(0, 0.01, (L, K))
    x = rng.normal(0, 0.3, L)
    noise = rng.uniform(0.005, 0.05, L)
    x[3], noise[5] = np.nan, 0.0
    got, want = tf_reading._likelihood_mean(cv, e, x, noise), _plain_likelihood_mean(cv, e, x, noise)
    for a, b in zip(got, want):
        assert np.array_equal(np.isnan(a), np.isnan(b))
        assert np.allclose(a, b, rtol=1e-9, atol=1e-12, equal_nan=True)
    assert np.isnan(got[0][3])


def test_compiled_lens_model_equals_the_gather():
    """The compiled model read is the fancy-index gather and weighted sum it replaced."""
    rng = np.random.default_rng(9)
    flat, stride = rng.normal(size=5000), 64
    idx = rng.integers(0, 64, (300, 2, 8))
    wts = rng.uniform(0, 1, (300, 2, 8))
    nodes = rng.integers(0, 70, (300, 5))
    at = flat[idx[:, :, :, None] + (nodes * stride)[:, None, None, :]]
    m = np.einsum("lfck,lfc->lfk", at, wts)
    assert np.allclose(tf_reading._lens_model(flat, idx, wts, nodes, stride), m[:, 0] - m[:, 1], rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="outside"):
        tf_reading._lens_model(flat, idx, wts, nodes + 20, stride)


def test_pairs_on_threads_equal_a_plain_loop(monkeypatch):
    """Two +u / -u pairs of spot frames (Gaussian spots at the lit lenses of the analytic white frame's
    grid): the threaded pair measurement is the loop's, pair for pair."""
    white = AnalyticModel(shape=(496, 496), lenses=(24, 24))
    grid = calibrate((0.8 * white.render()).astype(np.float32), expected_pitch_px=SMALL.layout.subimage_pitch_px,
                     expected_shape=(24, 24))
    yy, xx = np.mgrid[:496, :496]
    frames = []
    rng = np.random.default_rng(3)
    for off in ((0, 0), (3, 3)):
        for u in (10.0, -10.0):
            rec = ThroughFocus(focus_offset_mm=u, offset_lenses=off)
            lit = tf_geometry.coverage(SMALL, rec)[0]
            img = np.zeros((496, 496))
            for m, n in zip(*np.nonzero(lit)):
                x0, y0 = grid.grid_x_px[m, n] + rng.normal(0, 0.3), grid.grid_y_px[m, n] + rng.normal(0, 0.3)
                s = 0.7 if u > 0 else 1.0
                img += 0.5 * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * s * s))
            frames.append((img.astype(np.float32), rec))
    threaded = tf.pair_spots(frames, grid, SMALL)

    monkeypatch.setattr(tf, "thread_map", lambda fn, items: [fn(item) for item in items])
    plain = tf.pair_spots(frames, grid, SMALL)
    assert len(threaded) == len(plain) == 2
    for a, b in zip(threaded, plain):
        assert a.keys() == b.keys()
        for key in a:
            assert np.array_equal(np.asarray(a[key]), np.asarray(b[key])), key


def test_the_model_is_cached_on_disk_and_read_back_as_traced(tmp_path, monkeypatch):
    """`model_curves` traces a model once, writes it to the cache and reads it back (the same arrays a
    trace gives); a damaged cache file is traced again."""
    from mlaqc.models import store

    monkeypatch.setattr(store, "PACKAGE_DATA", tmp_path / "package")
    monkeypatch.setenv("MLAQC_CACHE", str(tmp_path / "cache"))
    rng = np.random.default_rng(0)
    calls = []

    def fake_trace(cfg, u, f, r_in):
        calls.append((u, f, r_in))
        return tf_model.ModelCurves(np.array(tf_model.MODEL_EPS), np.array([0]),
                                    rng.normal(size=(1, len(tf_model.MODEL_EPS))), 1.09, np.array([0.0, 5.0]),
                                    np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, 2), np.int64),
                                    rng.normal(size=(1, 2, 2, len(tf_model.MODEL_EPS), 8, 8)),
                                    tf_model.model_key(cfg, u, f, r_in))

    monkeypatch.setattr(tf_model, "trace_model", fake_trace)
    cfg = replace(SMALL, mla=replace(SMALL.mla, count_w=23))  # a config no other test caches
    tf_model._model_curves.cache_clear()
    try:
        first = tf_model.model_curves(cfg, 5.0, 11.0, 0.3)
        files = list((tmp_path / "cache").glob("throughfocus_*.npz"))
        assert len(calls) == 1 and len(files) == 1 and files[0].name == f"throughfocus_{first.key}.npz"
        tf_model._model_curves.cache_clear()
        again = tf_model.model_curves(cfg, 5.0, 11.0, 0.3)
        assert len(calls) == 1
        for name in tf_model._MODEL_ARRAYS:
            assert np.array_equal(getattr(first, name), getattr(again, name)), name
        assert first.gain == again.gain and again.spot_m2.dtype == np.float64
        files[0].write_bytes(b"not a model")
        tf_model._model_curves.cache_clear()
        tf_model.model_curves(cfg, 5.0, 11.0, 0.3)
        assert len(calls) == 2
        assert tf_model.model_key(cfg, 5.0, 11.0, 0.3) != tf_model.model_key(cfg, 5.0, 8.0, 0.3)
        assert tf_model.model_key(cfg, 5.0, 11.0, 0.3) != tf_model.model_key(replace(cfg, formation=replace(
            cfg.formation, crosstalk=0.0)), 5.0, 11.0, 0.3)
    finally:
        tf_model._model_curves.cache_clear()


def test_a_spot_window_past_the_frame_edge_is_refused():
    """The compiled cut reads without bounds checks: a window reaching past the edge is refused first."""
    frame = tf_spots.SpotFrame(np.zeros((60, 80), np.uint16), 0.0, 4095.0)
    assert tf_spots.spots(frame, np.array([10.0, 69.4]), np.array([10.0, 49.4]), 10).cells.shape == (2, 21, 21)
    for x, y in ((9.4, 30.0), (70.0, 30.0), (40.0, 9.0), (40.0, 50.0)):
        with pytest.raises(ValueError, match="edge"):
            tf_spots.spots(frame, np.array([x]), np.array([y]), 10)


def test_a_spot_window_without_an_inside_is_refused():
    """The compiled cut fills the ring from the window's edge: a window no wider than twice the ring has
    no inside, and would overrun the ring's buffer; it is refused."""
    frame = tf_spots.SpotFrame(np.zeros((60, 80), np.uint16), 0.0, 4095.0)
    for half in (0, 1, tf_spots.RING_PX):
        with pytest.raises(ValueError, match="ring"):
            tf_spots.spots(frame, np.array([30.0]), np.array([30.0]), half)
    assert tf_spots.spots(frame, np.array([30.0]), np.array([30.0]), tf_spots.RING_PX + 1).cells.shape == (1, 7, 7)
