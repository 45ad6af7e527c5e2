"""Microlens calibration against ground truth computed without any image.

Rendered white images of the small camera (24 x 24 lenses, the Table 1 optics) are compared with the
ray-traced sub-image centres of `calib_images.true_centres`; synthetic disc frames (exact centres, any
rotation/offset) test the geometry and indexing. Renders are cached on disk (see calib_images).
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from calib_images import SMALL, layout_centres, normalize, render_cache, synthetic_white, true_centres  # noqa: F401
from mlaqc.inspection.calibrate import Grid, calibrate, load_grid
from mlaqc.cli import main
from mlaqc.optics.errormap import ErrorMap
from mlaqc.errors import InputError
from mlaqc.inspection.raw_write import write_raw
from mlaqc.optics.sensor import expose, white_level

PITCH = SMALL.layout.subimage_pitch_px
SHAPE = (SMALL.mla.count_h, SMALL.mla.count_w)
RPP = 50  # the default ray budget
PITCH_LENS = (12, 12)  # U(m,n) with a 2 µm pitch error in +x


def small_calibrate(img, **kw):
    kw.setdefault("expected_pitch_px", PITCH)
    kw.setdefault("expected_shape", SHAPE)
    return calibrate(img, **kw)


def rms(a):
    a = np.asarray(a, float)
    return float(np.sqrt(np.nanmean(a * a)))


def centre_errors(grid, tx, ty, dx=0.0, dy=0.0):
    """(measured error, grid error) magnitudes against truth shifted by (dx, dy) px."""
    meas = np.hypot(grid.measured_x_px - (tx - dx), grid.measured_y_px - (ty - dy))
    pred = np.hypot(grid.grid_x_px - (tx - dx), grid.grid_y_px - (ty - dy))
    return meas, pred


def truth_pitch(cfg, errors=None):
    """Mean spacing of the true centres along rows and columns (px)."""
    tx, ty = true_centres(cfg, errors)
    return float(np.mean(np.hypot(np.diff(tx, axis=1), np.diff(ty, axis=1)))), \
        float(np.mean(np.hypot(np.diff(tx, axis=0), np.diff(ty, axis=0))))


@pytest.fixture(scope="module")
def white(render_cache):
    return render_cache.white(SMALL, rpp=RPP, seed=1)


@pytest.fixture(scope="module")
def perfect(white):
    return small_calibrate(white.image)


@pytest.fixture(scope="module")
def truth():
    return true_centres(SMALL)


# ------------------------------------------------------------------------------------ accuracy


def test_perfect_white_centres_match_the_ray_traced_truth(perfect, truth):
    g = perfect
    assert (g.rows, g.cols) == SHAPE and g.lenses_missing == 0 and not g.clipped.any()
    meas, pred = centre_errors(g, *truth)
    # per-lens centres are Monte-Carlo-noise limited at 50 rays/pixel (about 0.02 px per axis)
    assert rms(meas) < 0.035, rms(meas)
    assert rms(pred) < 0.01 and np.max(pred) < 0.03, (rms(pred), np.max(pred))
    px, py = truth_pitch(SMALL)
    assert g.pitch_px[0] == pytest.approx(px, abs=0.002) and g.pitch_px[1] == pytest.approx(py, abs=0.002)
    assert abs(g.rotation_deg) < 0.005 and abs(g.shear_deg) < 0.01
    assert g.origin_px == pytest.approx((truth[0][0, 0], truth[1][0, 0]), abs=0.02)
    assert g.rms_residual_px == pytest.approx(rms(np.hypot(g.residual_x_px, g.residual_y_px)), rel=0.05)


@pytest.mark.skipif(not os.environ.get("MLAQC_SLOW_TESTS"), reason="renders the full camera (~30 s); set MLAQC_SLOW_TESTS=1")
def test_full_camera_at_the_default_ray_budget(render_cache):
    """The Table 1 camera at 50 rays/pixel, noise on (bench/calibrate.py prints the same figures)."""
    from mlaqc.optics.config import default_config

    cfg = default_config()
    g = calibrate(render_cache.white(cfg, rpp=RPP, seed=1).image, expected_pitch_px=cfg.layout.subimage_pitch_px,
                  expected_shape=(cfg.mla.count_h, cfg.mla.count_w))
    meas, pred = centre_errors(g, *true_centres(cfg))
    assert g.lenses_missing == 0
    assert rms(meas) < 0.031 and rms(pred) < 0.005, (rms(meas), rms(pred))
    assert abs(g.rotation_deg) < 0.001


def test_truth_agrees_with_the_first_order_layout_on_the_small_camera(truth):
    """Independent cross-check of the yardstick: within 0.03 px of p(b+f)/b spacing about the axis."""
    lx, ly = layout_centres(SMALL)
    assert np.max(np.hypot(truth[0] - lx, truth[1] - ly)) < 0.03


def test_noise_free_frame_is_as_accurate(white, truth):
    raw = expose(white.photons.astype(np.float64), SMALL.sensor, seed=None, noise=False)
    g = small_calibrate(normalize(raw, SMALL))
    meas, pred = centre_errors(g, *truth)
    assert g.lenses_missing == 0
    assert rms(meas) < 0.035 and rms(pred) < 0.01


@pytest.mark.parametrize("angle", [1.5, -2.0])
def test_rotated_mla(render_cache, angle):
    errors = ErrorMap.zeros(*SHAPE).with_globals(mla_rotation_deg=angle)
    g = small_calibrate(render_cache.white(SMALL, errors, rpp=RPP, seed=2).image)
    tx, ty = true_centres(SMALL, errors)
    meas, pred = centre_errors(g, tx, ty)
    assert g.lenses_missing == 0
    assert g.rotation_deg == pytest.approx(angle, abs=0.005)
    assert rms(meas) < 0.035 and rms(pred) < 0.01
    assert g.predict(1, 1) == pytest.approx((tx[0, 0], ty[0, 0]), abs=0.02)  # U(1,1) is still the top-left lens


def test_vignetting_does_not_bias_the_centres(white, truth):
    h, w = white.image.shape
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - 0.5 * (w - 1)) ** 2 + (yy - 0.5 * (h - 1)) ** 2) / (0.5 * h) ** 2
    falloff = (1.0 - 0.3 * r2).astype(np.float32)  # down to 40 % in the corners
    g = small_calibrate(white.image * falloff)
    meas, pred = centre_errors(g, *truth)
    assert g.lenses_missing == 0
    assert rms(meas) < 0.035 and rms(pred) < 0.01
    assert g.flux[0, 0] < 0.6 * g.flux[11, 11]  # the flux sees the falloff


def test_cropped_frame_cuts_border_lenses_without_bias(white, truth):
    # cut 2-5 px off the border sub-images on every side
    top, bottom, left, right = 9, 11, 10, 12
    img = white.image[top:-bottom, left:-right]
    g = small_calibrate(img)
    assert (g.rows, g.cols) == SHAPE and g.lenses_missing == 0
    border = np.zeros(SHAPE, bool)
    border[[0, -1], :] = border[:, [0, -1]] = True
    assert np.array_equal(g.clipped, border)
    meas, pred = centre_errors(g, *truth, dx=left, dy=top)
    assert rms(meas[~border]) < 0.035 and rms(meas[border]) < 0.06
    assert rms(pred) < 0.01


def test_expected_shape_anchors_u11_when_a_whole_row_is_cropped_away(white, truth):
    top = 30  # the first lens row (centres at y ~ 17) leaves the frame
    img = white.image[top:, :]
    g = small_calibrate(img)
    assert (g.rows, g.cols) == SHAPE
    assert g.missing[0].all() and not g.missing[1:].any()
    assert g.predict(1, 1) == pytest.approx((truth[0][0, 0], truth[1][0, 0] - top), abs=0.03)
    assert np.isnan(g.measured_x_px[0]).all()
    # without the expected shape only what is visible is indexed
    visible = small_calibrate(img, expected_shape=None)
    assert (visible.rows, visible.cols) == (SHAPE[0] - 1, SHAPE[1])
    assert visible.predict(1, 1) == pytest.approx((truth[0][1, 0], truth[1][1, 0] - top), abs=0.03)


def test_missing_and_dim_lenses_are_events_not_failures(white, truth):
    img = white.image.copy()
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    dark, dim = (5, 5), (8, 15)
    for (m, n), factor in ((dark, 0.0), (dim, 0.15)):
        inner = np.hypot(xx - truth[0][m - 1, n - 1], yy - truth[1][m - 1, n - 1]) < 9.5
        img[inner] *= factor
    g = small_calibrate(img)
    assert (g.rows, g.cols) == SHAPE
    assert set(map(tuple, np.argwhere(g.missing) + 1)) == {dark, dim}
    for m, n in (dark, dim):
        assert np.isnan(g.measured_x_px[m - 1, n - 1]) and np.isnan(g.residual_px[m - 1, n - 1])
        assert g.grid_x_px[m - 1, n - 1] == pytest.approx(truth[0][m - 1, n - 1], abs=0.02)
    meas, pred = centre_errors(g, *truth)
    assert rms(meas[~g.missing]) < 0.04 and rms(pred) < 0.01


def test_pitch_error_shows_as_that_lens_residual_only(render_cache):
    m, n = PITCH_LENS
    errors = ErrorMap.zeros(*SHAPE).with_lens(m, n, pitch_um=2.0, pitch_dir_deg=0.0)
    g = small_calibrate(render_cache.white(SMALL, errors, rpp=4 * RPP, seed=3).image)
    lay = SMALL.layout
    b, f = lay.pupil_to_mla_mm, lay.z_sensor_mm - lay.z_mla_mm
    expected = 2.0 * (b + f) / b / SMALL.sensor.pixel_um  # 0.401 px
    tx, ty = true_centres(SMALL, errors)
    t0x, _ = true_centres(SMALL)
    assert tx[m - 1, n - 1] - t0x[m - 1, n - 1] == pytest.approx(expected, abs=0.003)  # the yardstick agrees
    assert g.residual_x_px[m - 1, n - 1] == pytest.approx(expected, abs=0.04)
    assert abs(g.residual_y_px[m - 1, n - 1]) < 0.04
    near = g.residual_px[m - 2:m + 1, n - 2:n + 1].copy()
    near[1, 1] = np.nan
    assert np.nanmax(near) < 0.06, near  # neighbours stay put
    others = np.ones(SHAPE, bool)
    others[m - 1, n - 1] = False
    assert rms(g.residual_px[others]) < 0.03


@pytest.mark.parametrize("angle,offset", [(2.0, (3.3, -5.7)), (-2.0, (-7.1, 2.2)), (0.7, (10.02, 10.02))])
def test_synthetic_rotation_and_arbitrary_offset(angle, offset):
    img, tx, ty = synthetic_white(rotation_deg=angle, offset=offset, noise=0.05, seed=4)
    g = calibrate(img, expected_pitch_px=20.05, expected_shape=tx.shape)
    meas, pred = centre_errors(g, tx, ty)
    assert g.lenses_missing == 0
    assert g.rotation_deg == pytest.approx(angle, abs=0.005)
    assert g.pitch_px == pytest.approx((20.05, 20.05), abs=0.002)
    assert rms(meas) < 0.03 and np.max(pred) < 0.02
    blind = calibrate(img)  # no expectations at all
    assert blind.shape == tx.shape and np.max(np.hypot(blind.grid_x_px - tx, blind.grid_y_px - ty)) < 0.02


@pytest.mark.parametrize("shift", [(0.8, -0.5), (-1.4, 0.6)])
def test_synthetic_shifted_lens_reads_its_full_shift(shift):
    """The joint disc model separates a lens' rim from its neighbours' (crosstalk ~2 %), and lenses up to
    ~1.5 px off the lattice are captured."""
    shifts = np.zeros((18, 19, 2))
    shifts[9, 9] = shift
    img, tx, ty = synthetic_white(shifts=shifts)
    g = calibrate(img, expected_shape=tx.shape)
    assert (g.residual_x_px[9, 9], g.residual_y_px[9, 9]) == pytest.approx(shift, abs=0.02)
    near = g.residual_px[8:11, 8:11].copy()
    near[1, 1] = 0
    assert near.max() < 0.03 * math.hypot(*shift)


# ------------------------------------------------------------------------------------ the compiled disc fit


def _reference_normals(img, k, cx, cy, amp, radius, edge, sx, sy, half_band, weighted, floor=0.05):
    """NumPy reference of calibrate_kernels.disc_normals for lens k: every lens' disc everywhere (no tail
    cut, double precision), the taper window, noise weights and Jacobian as the kernel's docstring says."""
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    model = np.zeros((h, w))
    for j in range(cx.size):
        u, v = xx - cx[j], yy - cy[j]
        e = 1.0 / (1.0 + np.exp(np.clip((np.hypot(u, v) + 1e-4 - radius[j]) / edge, -50, 50)))
        model += (amp[j] + sx[j] * u + sy[j] * v) * e
    u, v = xx - cx[k], yy - cy[k]
    r = np.hypot(u, v) + 1e-4
    d = r - radius[k]
    wt = np.clip(half_band - np.abs(d), 0.0, 1.0)
    sel = wt > 0
    u, v, r, d, wt, mod = u[sel], v[sel], r[sel], d[sel], wt[sel], model[sel]
    res = img[sel] - mod
    if weighted:
        wt = wt * amp[k] / np.maximum(mod, floor * amp[k])
    e = 1.0 / (1.0 + np.exp(d / edge))
    ag = e * (1 - e) * (amp[k] + sx[k] * u + sy[k] * v) / edge
    jac = np.stack([e, ag * u / r - e * sx[k], ag * v / r - e * sy[k], ag, d * ag / edge])
    return (jac * wt) @ jac.T, (jac * wt) @ res, float(res @ res), int(sel.sum())


@pytest.mark.parametrize("halves", [False, True])
@pytest.mark.parametrize("weighted", [False, True])
def test_disc_kernel_matches_a_numpy_reference(weighted, halves):
    """The fused kernel (float32 profiles, neighbours' discs cut 10 edge widths out) against plain NumPy, in
    both pixel orders (`halves`: the hex fit's, whose neighbours' discs run on the vector units)."""
    from mlaqc.inspection import calibrate_kernels as kernels
    from mlaqc.inspection.disc_fit import _lattice_neighbours

    img, tx, ty = synthetic_white(shape=(110, 130), rows=5, cols=6, noise=0.05, seed=7)
    rng = np.random.default_rng(1)
    cx, cy = tx.ravel() + rng.normal(0, 0.1, tx.size), ty.ravel() + rng.normal(0, 0.1, tx.size)
    n = cx.size
    amp = 0.6 + rng.normal(0, 0.02, n)
    radius = 10.2 + rng.normal(0, 0.1, n)
    sx, sy = rng.normal(0, 2e-3, n), rng.normal(0, 2e-3, n)
    edge, half_band = 0.3, 2.0
    jj, ii = np.meshgrid(np.arange(6), np.arange(5))
    neighbours = _lattice_neighbours(jj.ravel(), ii.ravel())
    lenses = np.arange(n)
    normal, rhs = np.empty((n, 5, 5)), np.empty((n, 5))
    rss, npix = np.empty(n), np.empty(n, np.int64)
    kernels.disc_normals(img, lenses, cx, cy, amp, radius, np.full(n, 1 / edge), sx, sy, neighbours,
                         np.zeros(n, bool), np.zeros(n, bool), half_band, weighted, True, 0.05, halves, normal, rhs, rss, npix)
    for k in (0, 8, 14, 29):  # corner (cut by the frame), edge, inner lenses
        _assert_matches_reference(k, (normal, rhs, rss, npix), img, cx, cy, amp, radius, edge, sx, sy, half_band, weighted)


def _assert_matches_reference(k, got, img, cx, cy, amp, radius, edge, sx, sy, half_band, weighted):
    """Lens k's normal equations from the kernel (`got`: normal, rhs, rss, npix) against `_reference_normals`;
    the Gauss-Newton centre step agrees to far below the noise."""
    normal, rhs, rss, npix = got
    ref_n, ref_r, ref_rss, ref_npix = _reference_normals(img, k, cx, cy, amp, radius, edge, sx, sy, half_band, weighted)
    assert npix[k] == ref_npix
    np.testing.assert_allclose(normal[k], ref_n, rtol=1e-4, atol=1e-5 * np.abs(ref_n).max())
    np.testing.assert_allclose(rhs[k], ref_r, rtol=1e-3, atol=1e-4 * np.sqrt(np.abs(ref_n).max() * ref_rss))
    assert rss[k] == pytest.approx(ref_rss, rel=1e-4)
    step = np.linalg.solve(normal[k][:4, :4], rhs[k][:4])
    ref_step = np.linalg.solve(ref_n[:4, :4], ref_r[:4])
    assert np.abs(step[1:3] - ref_step[1:3]).max() < 1e-4


@pytest.mark.parametrize("halves", [False, True])
@pytest.mark.parametrize("weighted", [False, True])
def test_disc_kernel_on_a_hex_layout_matches_a_numpy_reference(weighted, halves):
    """The kernel with the hex neighbour table (six side neighbours, each disc overlapping the lens' rim)
    against plain NumPy, lenses cut by the frame included, in both pixel orders."""
    from mlaqc.inspection import calibrate_kernels as kernels
    from mlaqc.inspection.disc_fit import _lattice_neighbours

    pitch, edge, half_band = 20.05, 0.3, 2.0
    jj, ii = (a.ravel() for a in np.meshgrid(np.arange(6), np.arange(5)))  # axial: a1 = (p, 0), a2 at 60 deg
    rng = np.random.default_rng(3)
    cx = 6.0 + pitch * (jj + 0.5 * ii) + rng.normal(0, 0.1, jj.size)
    cy = 7.0 + pitch * math.sqrt(3.0) / 2.0 * ii + rng.normal(0, 0.1, jj.size)
    n = cx.size
    amp = 0.6 + rng.normal(0, 0.02, n)
    radius = 10.2 + rng.normal(0, 0.1, n)
    sx, sy = rng.normal(0, 2e-3, n), rng.normal(0, 2e-3, n)
    h, w = 90, 170
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.zeros((h, w))
    for k in range(n):  # the frame: the true discs (sharper rims, other radii) and noise
        img += 0.6 / (1.0 + np.exp((np.hypot(xx - cx[k] - 0.2, yy - cy[k] + 0.1) - 10.0) / 0.25))
    img = (img + rng.normal(0, 0.02, img.shape)).astype(np.float32)
    neighbours = _lattice_neighbours(jj, ii, 1, "hex")
    normal, rhs = np.empty((n, 5, 5)), np.empty((n, 5))
    rss, npix = np.empty(n), np.empty(n, np.int64)
    kernels.disc_normals(img, np.arange(n), cx, cy, amp, radius, np.full(n, 1 / edge), sx, sy, neighbours,
                         np.zeros(n, bool), np.zeros(n, bool), half_band, weighted, True, 0.05, halves, normal, rhs,
                         rss, npix)
    for k in (0, 3, 8, 15, 29):  # corners and edges cut by the frame, inner lenses with six neighbours
        _assert_matches_reference(k, (normal, rhs, rss, npix), img, cx, cy, amp, radius, edge, sx, sy, half_band, weighted)


def test_second_ring_of_neighbours_changes_nothing_where_discs_do_not_reach(monkeypatch):
    """Large discs bring the second ring of lattice neighbours in; where it is out of reach, the fit is the same."""
    import mlaqc.inspection.disc_fit as disc_fit
    img, tx, ty = synthetic_white(noise=0.05, seed=5)
    first = calibrate(img, expected_shape=tx.shape)
    table = disc_fit._lattice_neighbours
    monkeypatch.setattr(disc_fit, "_lattice_neighbours", lambda j, i, *_: table(j, i, 2))
    second = calibrate(img, expected_shape=tx.shape)
    np.testing.assert_allclose(second.measured_x_px, first.measured_x_px, atol=1e-9)
    np.testing.assert_allclose(second.measured_y_px, first.measured_y_px, atol=1e-9)


# ------------------------------------------------------------------------------------ JSON


def test_grid_json_round_trip(perfect, tmp_path):
    path = tmp_path / "grid.json"
    perfect.save(path)
    back = load_grid(path)
    assert (back.rows, back.cols, back.image_shape) == (perfect.rows, perfect.cols, perfect.image_shape)
    for name in ("measured_x_px", "measured_y_px", "grid_x_px", "grid_y_px", "residual_px", "flux", "radius_px"):
        np.testing.assert_allclose(getattr(back, name), getattr(perfect, name), atol=2e-6, equal_nan=True)
    assert np.array_equal(back.missing, perfect.missing) and np.array_equal(back.clipped, perfect.clipped)
    np.testing.assert_allclose(back.predict(np.arange(1, 25), 3), perfect.predict(np.arange(1, 25), 3), atol=1e-9)
    assert back.pitch_px == perfect.pitch_px and back.rotation_deg == perfect.rotation_deg
    data = json.loads(path.read_text())
    assert data["format"] == "mlaqc-grid" and len(data["lenses"]) == 24 * 24
    first = data["lenses"][0]
    assert (first["m"], first["n"]) == (1, 1) and first["grid_x_px"] == pytest.approx(perfect.origin_px[0], abs=1e-5)


def test_predict_matches_the_grid_arrays(perfect):
    m, n = np.mgrid[1:25, 1:25]
    x, y = perfect.predict(m, n)
    np.testing.assert_allclose(x, perfect.grid_x_px, atol=1e-9)
    np.testing.assert_allclose(y, perfect.grid_y_px, atol=1e-9)
    assert perfect.predict(1, 1) == pytest.approx(perfect.origin_px)


def _grid_dict(perfect):
    return json.loads(json.dumps(perfect.to_json_dict()))


@pytest.mark.parametrize("mutate,message", [
    (lambda d: d.update(format="other"), "not an mlaqc grid"),
    (lambda d: d.update(version=9), "version"),
    (lambda d: d["shape"].update(rows=0), "header"),
    (lambda d: d["model"].pop("homography"), "homography"),
    (lambda d: d["lenses"].pop(), "must list all"),
    (lambda d: d["lenses"][3].update(m=99), "needs integer m"),
    (lambda d: d["lenses"][3].update(flux="bright"), "must be a number"),
    (lambda d: d["lenses"][3].update(grid_x_px=None), "no grid"),
    (lambda d: d["lenses"][3].update(measured_x_px=None), "not marked missing"),
    (lambda d: d["lenses"][3].update(missing="no"), "true or false"),
    (lambda d: d["lenses"].__setitem__(4, dict(d["lenses"][3])), "listed twice"),
])
def test_load_grid_names_the_problem(perfect, tmp_path, mutate, message):
    d = _grid_dict(perfect)
    mutate(d)
    path = tmp_path / "g.json"
    path.write_text(json.dumps(d))
    with pytest.raises(InputError, match=message):
        load_grid(path)


def test_load_grid_missing_or_corrupt_file(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_grid(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InputError, match="not readable JSON"):
        load_grid(tmp_path / "bad.json")


# ------------------------------------------------------------------------------------ bad input


def _one_sentence(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text and text.count(". ") == 0
    return text


@pytest.mark.parametrize("make,message", [
    (lambda img: np.zeros_like(img), "black"),
    (lambda img: np.random.default_rng(0).normal(0, 0.001, img.shape).astype(np.float32), "black|no periodic"),
    (lambda img: np.ones_like(img), "saturated"),
    (lambda img: np.minimum(img * 4.0, 1.0), "saturated"),
    (lambda img: np.random.default_rng(0).random(img.shape).astype(np.float32), "no periodic"),
    (lambda img: img[200:260, 200:260], "microlens"),
    (lambda img: img[None], "2-D"),
    (lambda img: np.where(img > 0.3, np.nan, img), "NaN"),
])
def test_bad_images_raise_input_error(white, make, message):
    with pytest.raises(InputError, match=message) as exc:
        small_calibrate(make(white.image))
    _one_sentence(exc)


def test_pitch_far_from_expected(white):
    with pytest.raises(InputError, match="far from the expected") as exc:
        calibrate(white.image, expected_pitch_px=30.0)
    _one_sentence(exc)


def test_expected_array_larger_than_the_image(white):
    with pytest.raises(InputError, match="expected 102x102"):
        calibrate(white.image, expected_pitch_px=PITCH, expected_shape=(102, 102))


def test_bad_arguments(white):
    with pytest.raises(InputError, match="expected pitch"):
        calibrate(white.image, expected_pitch_px=-1.0)
    with pytest.raises(InputError, match="expected shape"):
        calibrate(white.image, expected_shape=(24,))


# ------------------------------------------------------------------------------------ CLI


@pytest.fixture
def small_config(tmp_path):
    from mlaqc.optics.config import config_to_toml

    path = tmp_path / "small.toml"
    path.write_text(config_to_toml(SMALL))
    return path


def test_cli_calibrate_writes_grid_json(white, small_config, tmp_path, capsys):
    raw = tmp_path / "white.tif"
    write_raw(raw, white.raw, bits=SMALL.sensor.bit_depth, cfa=None, black_level=SMALL.sensor.black_level_dn,
              white_level=white_level(SMALL.sensor))
    out = tmp_path / "grid.json"
    assert main(["calibrate", str(raw), "--out", str(out), "--config", str(small_config)]) == 0
    text = capsys.readouterr().out
    assert "24x24 lenses" in text and "576 found, 0 missing" in text and "rotation" in text
    g = load_grid(out)
    assert g.shape == SHAPE and g.lenses_missing == 0
    assert g.pitch_px[0] == pytest.approx(PITCH, abs=0.01)


def test_cli_bad_input_exits_2_without_output(white, small_config, tmp_path, capsys):
    raw = tmp_path / "black.tif"
    write_raw(raw, np.full_like(white.raw, SMALL.sensor.black_level_dn), bits=SMALL.sensor.bit_depth, cfa=None,
              black_level=SMALL.sensor.black_level_dn, white_level=white_level(SMALL.sensor))
    out = tmp_path / "grid.json"
    assert main(["calibrate", str(raw), "--out", str(out), "--config", str(small_config)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mlaqc calibrate: error:") and err.count("\n") == 1 and "black" in err
    assert not out.exists() and not list(tmp_path.glob("*.json*"))
    # a frame of the wrong camera (MLA shape) is refused too
    good = tmp_path / "white.tif"
    write_raw(good, white.raw, bits=SMALL.sensor.bit_depth, cfa=None, black_level=SMALL.sensor.black_level_dn,
              white_level=white_level(SMALL.sensor))
    assert main(["calibrate", str(good), "--out", str(out)]) == 2
    assert "102x102" in capsys.readouterr().err and not out.exists()
    assert main(["calibrate", str(tmp_path / "missing.tif"), "--out", str(out)]) == 2
    assert main(["calibrate", str(good), "--out", str(tmp_path / "grid.txt")]) == 2
    assert main(["calibrate", str(good), "--out", str(tmp_path / "no" / "grid.json")]) == 2
    assert not out.exists()


def test_grid_is_frozen(perfect):
    with pytest.raises(Exception):
        perfect.rows = 3  # type: ignore[misc]
    assert isinstance(perfect, Grid) and math.isfinite(perfect.edge_width_px)
