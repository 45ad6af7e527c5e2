"""Light-field decoding (mlaqc.decode, `mlaqc decode`): checked against analytic light fields that share no
code with the decoder or the tracer (each sub-image a disc whose content is a known function of the pupil
point and the lens), and the command's behaviour on good and bad input."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mlaqc.cli import main
from mlaqc.decode.frames import demosaiced
from mlaqc.decode.fill import filled
from mlaqc.decode.lightfield import LightField, bilinear, decode, devignetted, rectangular, refocus, view_offsets
from mlaqc.decode.sampling import LensSampling, measured_sampling
from mlaqc.errors import InputError

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
PITCH, RADIUS, ROWS, COLS = 16.0, 7.5, 9, 11


def centres(shift: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Square lattice centres (PITCH apart, a sub-pixel phase), with some lenses' sub-images moved."""
    r, c = np.mgrid[0:ROWS, 0:COLS].astype(float)
    x, y = 10.3 + c * PITCH, 9.6 + r * PITCH
    for (m, n), (dx, dy) in (shift or {}).items():
        x[m, n] += dx
        y[m, n] += dy
    return x, y


def radiance(s, t, u, v):
    """The analytic light field: lens (t, s) seen through the pupil point at offset (u, v) px: linear in
    the view (bilinear interpolation reads it exactly), different for every lens."""
    return 1.0 + 0.05 * s - 0.03 * t + 0.02 * u - 0.015 * v + 0.004 * s * u


def frame(x, y, field=radiance, shape=(150, 180)) -> np.ndarray:
    """Every pixel inside a lens' disc carries field(s, t, offset); the gaps are dark."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    img = np.zeros(shape)
    for t in range(ROWS):
        for s in range(COLS):
            u, v = xx - x[t, s], yy - y[t, s]
            inside = np.hypot(u, v) <= RADIUS
            img[inside] = field(s, t, u[inside], v[inside])
    return img


def sampling_at(x, y, shape=(150, 180), weight=None) -> LensSampling:
    return LensSampling(x, y, np.ones_like(x), np.ones_like(x) if weight is None else weight, "square", PITCH,
                        RADIUS, shape, "lattice")


def test_bilinear_reads_a_bilinear_function_exactly():
    yy, xx = np.mgrid[0:40, 0:50].astype(float)
    img = (2.0 + 0.3 * xx - 0.2 * yy + 0.01 * xx * yy).astype(np.float32)
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 49, 500), rng.uniform(0, 39, 500)
    got, ok = bilinear(img, x, y)
    assert ok.all()
    np.testing.assert_allclose(got, 2.0 + 0.3 * x - 0.2 * y + 0.01 * x * y, rtol=2e-6)
    out, ok = bilinear(img, np.array([-0.5, 49.5, np.nan]), np.array([3.0, 3.0, 3.0]))
    assert not ok.any() and np.all(out == 0)


def test_view_offsets_stay_inside_the_pupil_image():
    assert view_offsets(7.5).tolist() == list(range(-6, 7))
    assert view_offsets(7.5, 5).tolist() == [-2, -1, 0, 1, 2]
    with pytest.raises(InputError, match="odd"):
        view_offsets(7.5, 4)
    with pytest.raises(InputError, match="beyond its radius"):
        view_offsets(7.5, 17)


def test_decode_recovers_the_analytic_light_field():
    x, y = centres()
    lf = decode(frame(x, y).astype(np.float32), sampling_at(x, y), view_offsets(RADIUS))
    o = lf.view_offsets_px
    v, u, t, s = np.meshgrid(o, o, np.arange(ROWS), np.arange(COLS), indexing="ij")
    used = lf.weights > 0
    assert used.mean() > 0.6  # the views inside the disc (radius - 0.5 px), every lens
    # a hard-edged disc: the views whose 2 x 2 pixels all lie inside it (a real rim is soft: devignetting)
    inner = used & (np.hypot(u, v) <= RADIUS - 1.5)
    np.testing.assert_allclose(lf.values[inner], radiance(s, t, u, v)[inner], rtol=1e-5)
    assert np.all(lf.values[~used] == lf.values[~used])  # finite everywhere


def test_measured_centres_undo_a_lens_that_moved():
    """A lens whose sub-image moved (pitch, decenter, tilt) decoded on the lattice reads the wrong pupil
    points; at its measured centre (a flagged lens in the report) it reads the right ones."""
    moved = {(4, 5): (1.3, -0.7)}
    x0, y0 = centres()
    x, y = centres(moved)
    img = frame(x, y).astype(np.float32)
    offs = view_offsets(RADIUS, 9)
    truth = decode(frame(x0, y0).astype(np.float32), sampling_at(x0, y0), offs)
    on_lattice = decode(img, sampling_at(x0, y0), offs)
    grid = SimpleNamespace(grid_x_px=x0, grid_y_px=y0, measured_x_px=x + 0.001, measured_y_px=y - 0.001,
                           missing=np.zeros(x.shape, bool), pitch_px=(PITCH, PITCH), radius_px=np.full(x.shape, RADIUS),
                           image_shape=img.shape, packing="square", shape=x.shape)
    report = {"defects": [{"row": 5, "col": 6, "error_type": "decenter"}, {"row": 2, "col": 2, "error_type": "missing"}]}
    smp = measured_sampling(grid, report)
    assert smp.x_px[4, 5] == pytest.approx(x[4, 5] + 0.001) and smp.x_px[3, 3] == x0[3, 3]  # only flagged lenses move
    measured = decode(img, smp, offs)
    both = (on_lattice.weights > 0) & (truth.weights > 0)
    both &= (np.hypot(offs[:, None], offs[None, :]) <= RADIUS - 3.0)[:, :, None, None]  # all reads inside the disc
    err_lattice = np.abs(on_lattice.values - truth.values)[both[:, :, 4, 5], 4, 5]
    # the measured centre is 0.0014 px off: the samples read the analytic field 0.02 * 0.0014 off at most
    err_measured = np.abs(measured.values - truth.values)[both[:, :, 4, 5], 4, 5]
    assert err_lattice.max() > 0.02 and err_measured.max() < 2e-4
    assert np.all(measured.weights[:, :, 1, 1] == 0)  # the missing lens carries no light field
    healthy = np.ones(x.shape, bool)
    healthy[4, 5] = healthy[1, 1] = False
    assert np.array_equal(measured.values[:, :, healthy], on_lattice.values[:, :, healthy])


def test_devignetting_leaves_the_scene():
    """A scene frame = white frame x scene radiance per lens: the devignetted light field is the scene's
    radiance in every view, whatever the white's fall-off inside the sub-image."""
    x, y = centres()
    white = frame(x, y, lambda s, t, u, v: 0.9 - 0.004 * (u * u + v * v))
    scene = frame(x, y, lambda s, t, u, v: (0.9 - 0.004 * (u * u + v * v)) * (0.2 + 0.07 * s + 0.03 * t))
    smp = sampling_at(x, y)
    offs = view_offsets(RADIUS)
    lf = devignetted(decode(scene.astype(np.float32), smp, offs), decode(white.astype(np.float32), smp, offs))
    t, s = np.mgrid[0:ROWS, 0:COLS]
    used = lf.weights > 0
    expected = np.broadcast_to(0.2 + 0.07 * s + 0.03 * t, lf.values.shape)
    inner = used & (np.hypot(*np.meshgrid(offs, offs, indexing="ij")) <= RADIUS - 1.5)[:, :, None, None]
    np.testing.assert_allclose(lf.values[inner], expected[inner], rtol=2e-3)  # bilinear on a quadratic white
    assert lf.devignetted and lf.weights.max() <= 1.0


def test_a_hex_array_resampled_onto_a_rectangular_grid():
    """Values linear in the lattice position come out linear in the rectangular (s, t) grid, exactly."""
    rows, cols = 12, 10
    r, c = np.mgrid[0:rows, 0:cols]
    u = c + 0.5 * (r % 2)  # hex: odd 0-based rows (m even) half a pitch right
    v = r * np.sqrt(3) / 2
    field = 3.0 + 0.2 * u - 0.1 * v
    lf = LightField(np.broadcast_to(field, (3, 3, rows, cols)).astype(np.float32), np.ones((3, 3, rows, cols), np.float32),
                    np.array([-1.0, 0.0, 1.0]), "hex")
    rect = rectangular(lf)
    t, s = np.mgrid[0:rect.spatial_shape[0], 0:rect.spatial_shape[1]]
    assert rect.packing == "rect" and rect.spatial_shape == (int((rows - 1) * np.sqrt(3) / 2) + 1, cols)
    inner = rect.weights[0, 0] > 0.999  # cells interpolated wholly from lenses of the array
    assert inner.mean() > 0.8
    np.testing.assert_allclose(rect.values[0, 0][inner], (3.0 + 0.2 * s - 0.1 * t)[inner], atol=1e-5)


def test_refocusing_brings_a_parallax_shifted_spot_into_focus():
    """Views of a spot that moves `slope` lenses per view pixel: refocused at that slope the spot is as
    sharp as in one view; at 0 it is smeared."""
    o = np.arange(-3.0, 4.0)
    slope = 1.5
    t, s = np.mgrid[0:31, 0:31].astype(float)
    vals = np.array([[np.exp(-((s + slope * ui - 15) ** 2 + (t + slope * vj - 15) ** 2) / 8.0) for ui in o] for vj in o])
    lf = LightField(vals.astype(np.float32), np.ones(vals.shape, np.float32), o, "square")
    sharp, _ = refocus(lf, -slope)
    flat, _ = refocus(lf, 0.0)
    assert sharp[15, 15] > 0.95 and flat[15, 15] < 0.5
    assert np.unravel_index(np.argmax(sharp), sharp.shape) == (15, 15)


def test_filling_a_lens_from_its_neighbours():
    x, y = centres()
    w = np.ones(x.shape)
    w[4, 5] = 0.0
    lf = decode(frame(x, y, lambda s, t, u, v: 0 * u + 1.0 + 0.1 * s).astype(np.float32), sampling_at(x, y, weight=w),
                view_offsets(RADIUS, 3))
    out = filled(lf)
    np.testing.assert_allclose(out.values[:, :, 4, 5], 1.0 + 0.1 * 5, rtol=1e-5)  # linear: the neighbours' mean
    assert 0 < out.weights[1, 1, 4, 5] <= 0.5 and np.array_equal(out.values[:, :, 3, 3], lf.values[:, :, 3, 3])


def parallax_field(slope: float, views: int = 21, size: int = 24, seed: int = 7, packing: str = "square") -> LightField:
    """An analytic light field of a textured plane off the MLA's focus: the lens at (x, y) pitches sees in
    view (u, v) I(x - slope u, y - slope v) (what `refocus` at -slope brings into focus), I a smooth random
    texture known everywhere. Hex: 0-based odd rows half a pitch right, rows sqrt(3)/2 apart."""
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(6, 4))

    def texture(x, y):  # a sum of plane waves: detail down to about two lenses
        return 1.0 + sum(0.1 * np.sin(a * x + b * y + c) * d for a, b, c, d in k * [[1.3, 1.3, 3, 1]])

    o = np.arange(views, dtype=np.float64) - views // 2
    t, s = np.mgrid[0:size, 0:size].astype(float)
    x, y = (s + 0.5 * (t % 2), t * np.sqrt(3) / 2) if packing == "hex" else (s, t)
    vals = texture(x[None, None] - slope * o[None, :, None, None], y[None, None] - slope * o[:, None, None, None])
    return LightField(vals.astype(np.float32), np.ones(vals.shape, np.float32), o, packing)


@pytest.mark.parametrize("slope, packing", [(0.12, "square"), (-0.2, "square"), (0.3, "square"), (0.2, "hex"),
                                            (-0.12, "hex")])
def test_a_lens_is_refilled_along_the_scenes_parallax(slope, packing):
    """A lens without light field in a plane scene out of focus: its neighbours see what it would have seen
    1/slope views further on per pitch of their offset; refilled along that, its views are the scene's (to
    the views' linear interpolation), several times closer than the mean of its neighbours in each view."""
    truth = parallax_field(slope, packing=packing)
    w = truth.weights.copy()
    vals = truth.values.copy()
    w[:, :, 11, 12] = 0.1  # a lens of low confidence whose views are blurred (their mean kept)
    vals[:, :, 11, 12] = vals[:, :, 11, 12].mean()
    for t, s in ((5, 5), (17, 8), (10, 16)):  # three without light field (rows odd and even: on hex their
        w[:, :, t, s] = 0.0                    # neighbours above and below differ), one next to another's
        vals[:, :, t, s] = 0.0
    lf = replace(truth, values=vals, weights=w)
    out = filled(lf)
    inner = np.abs(truth.view_offsets_px) <= 10 - 1.0 / abs(slope) + 2  # views every neighbour reaches
    for t, s in ((11, 12), (5, 5), (17, 8), (10, 16)):
        got, want = out.values[:, :, t, s], truth.values[:, :, t, s]
        plain = np.mean([truth.values[:, :, t + a, s + b] for a, b in neighbour_steps(packing, t)], axis=0)
        err = np.sqrt(np.mean((got - want)[np.ix_(inner, inner)] ** 2))
        err_plain = np.sqrt(np.mean((plain - want)[np.ix_(inner, inner)] ** 2))
        assert err < 0.2 * err_plain and err < 0.01
        assert 0 < out.weights[10, 10, t, s] <= 0.5
    assert np.array_equal(out.values[:, :, 3, 3], lf.values[:, :, 3, 3])


def neighbour_steps(packing: str, t: int) -> list[tuple[int, int]]:
    """(dt, ds) to a lens' nearest neighbours: square the eight around it, hex the six (0-based odd rows
    shifted half a pitch right: their neighbours above and below are at s and s + 1)."""
    if packing != "hex":
        return [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b]
    odd = t % 2
    return [(0, 1), (0, -1)] + [(a, b + odd) for a in (-1, 1) for b in (-1, 0)]


def test_a_dark_lens_of_low_confidence_is_not_refilled_with_its_neighbours_light():
    """A point scene: a lens whose (blurred) views are dark while its neighbours see a point keeps its own
    dark views: no refill may change the mean light a lens has of its own (a focal error keeps it)."""
    truth = parallax_field(0.2)
    vals = np.zeros_like(truth.values)
    vals[:, :, 8:11, 8:10] = truth.values[:, :, 8:11, 8:10]  # light in the lenses left of U(10, 11) only
    w = truth.weights.copy()
    w[:, :, 9, 10] = 0.2
    out = filled(replace(truth, values=vals, weights=w))
    assert np.all(out.values[:, :, 9, 10] == 0) and np.all(out.weights[:, :, 9, 10] == 0.2)


def test_a_lens_the_frame_does_not_hold_is_not_extrapolated():
    """A border lens without light field because its sub-image is off the frame stays empty when the
    sampling says so (`lenses`: its `inside`); a missing lens inside is refilled."""
    truth = parallax_field(0.2)
    w = truth.weights.copy()
    w[:, :, 0, 7] = w[:, :, 9, 9] = 0.0
    inside = np.ones(w.shape[2:], bool)
    inside[0, :] = False
    out = filled(replace(truth, weights=w), lenses=inside)
    assert np.all(out.weights[:, :, 0, 7] == 0) and np.array_equal(out.values[:, :, 0, 7], truth.values[:, :, 0, 7])
    assert out.weights[10, 10, 9, 9] > 0


def test_a_colour_light_field_is_refilled_channel_by_channel():
    """A demosaiced frame's light field (a channel axis): the lens refilled along the parallax in each of
    red, green and blue, which differ (0.3, 1, 0.6 of the texture plus an offset)."""
    grey = parallax_field(0.2)
    truth = np.stack([0.3 * grey.values + 0.1, grey.values, 0.6 * grey.values + 0.05], axis=-1)
    w = grey.weights.copy()
    w[:, :, 9, 9] = 0.0
    out = filled(replace(grey, values=np.where(w[..., None] > 0, truth, 0.0).astype(np.float32), weights=w))
    inner = np.abs(grey.view_offsets_px) <= 7
    err = np.abs(out.values[:, :, 9, 9] - truth[:, :, 9, 9])[np.ix_(inner, inner)]
    assert err.max() < 0.02 and out.weights[10, 10, 9, 9] > 0


def test_a_scene_in_focus_is_refilled_from_the_neighbours_in_each_view():
    """slope 0: every view sees the same texture; no shift makes the neighbours agree better than none."""
    truth = parallax_field(0.0)
    w = truth.weights.copy()
    w[:, :, 9, 9] = 0.0
    out = filled(replace(truth, weights=w))
    plain = 0.125 * sum(truth.values[:, :, 9 + a, 9 + b] for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b)
    np.testing.assert_allclose(out.values[:, :, 9, 9], plain, rtol=1e-5)


def focal_grid(cfg_path: Path):
    """A calibrated-grid stand-in of `cfg_path`'s array (lattice centres, nothing measured off them)."""
    from mlaqc.optics.config import load_config

    cfg = load_config(cfg_path)
    r, c = np.mgrid[0:8, 0:8].astype(float)
    p = cfg.layout.subimage_pitch_px
    x, y = 30 + c * p, 30 + r * p
    grid = SimpleNamespace(grid_x_px=x, grid_y_px=y, measured_x_px=x, measured_y_px=y, missing=np.zeros(x.shape, bool),
                           pitch_px=(p, p), radius_px=np.full(x.shape, 0.45 * p), image_shape=(int(9 * p + 60),) * 2,
                           packing="square", shape=x.shape)
    return cfg, grid


def test_a_focal_error_lens_is_trusted_by_how_far_it_blurs_its_views():
    """The microscope's plano-convex lens (f = R / (n - 1) = 3 mm, t = 1 mm, n 1.458; sensor at the design
    back focal distance f - t/n): radius +5 % moves its focus to 1.05 f - t/n, which blurs the pupil's
    image, one sub-image pitch (46.15 px) across at the lens, by pitch x |gap - bfd'| / bfd' = 2.81 px; its
    confidence is the inverse. The report's config comes as strict JSON (the flat back written as null)."""
    cfg, grid = focal_grid(FIXTURES / "lfm_40x_relay.toml")
    f, t, n = 3000.0, 1000.0, 1.458
    gap, bfd = f - t / n, 1.05 * f - t / n
    blur = 150.0 / 3.25 * abs(gap - bfd) / bfd
    config = json.loads(json.dumps(cfg.to_dict()).replace("Infinity", "null"))
    report = {"config": config, "defects": [{"row": 3, "col": 4, "error_type": "radius", "magnitude": 0.05},
                                            {"row": 5, "col": 5, "error_type": "pitch", "magnitude": 2.0}]}
    smp = measured_sampling(grid, report)
    assert blur == pytest.approx(2.81, abs=0.01)
    assert smp.weight[2, 3] == pytest.approx(1.0 / blur, rel=2e-3)
    assert smp.weight[4, 4] == 1.0 and smp.weight[0, 0] == 1.0


def test_an_unreadable_magnitude_leaves_a_focal_error_lens_at_full_weight():
    """A report writes a magnitude it could not read as null: the lens is not judged by its blur."""
    cfg, grid = focal_grid(FIXTURES / "paper_table1.toml")
    report = {"config": json.loads(json.dumps(cfg.to_dict())),
              "defects": [{"row": 2, "col": 2, "error_type": "radius", "magnitude": None}]}
    assert measured_sampling(grid, report).weight[1, 1] == 1.0


def test_a_nan_sample_does_not_stop_a_refill():
    """One NaN elsewhere in the light field: the lens' refill is still checked against its own light."""
    truth = parallax_field(0.2)
    vals, w = truth.values.copy(), truth.weights.copy()
    w[:, :, 11, 12] = 0.1
    vals[:, :, 11, 12] = vals[:, :, 11, 12].mean()
    vals[0, 0, 0, 0] = np.nan
    out = filled(replace(truth, values=vals, weights=w))
    assert out.weights[10, 10, 11, 12] > 0.1  # refilled, not kept blurred


def test_a_focal_error_blurring_its_views_under_a_pixel_keeps_full_weight():
    """Table 1 (20 px sub-images): radius +5 % blurs by under a pixel, -10 % by 2.2 px."""
    cfg, grid = focal_grid(FIXTURES / "paper_table1.toml")
    report = {"config": json.loads(json.dumps(cfg.to_dict())),
              "defects": [{"row": 2, "col": 2, "error_type": "radius", "magnitude": 0.05},
                          {"row": 6, "col": 6, "error_type": "radius", "magnitude": -0.1}]}
    smp = measured_sampling(grid, report)
    assert smp.weight[1, 1] == 1.0 and 0.4 < smp.weight[5, 5] < 0.5
    assert measured_sampling(grid, {"defects": report["defects"]}).weight[5, 5] == 1.0  # no config: not judged


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_demosaicing_reads_each_pattern(cfa):
    colour = {"R": 0.8, "G": 0.5, "B": 0.2}
    mosaic = np.zeros((16, 16), np.float32)
    for k, (r0, c0) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        mosaic[r0::2, c0::2] = colour[cfa[k]]
    rgb = demosaiced(mosaic, cfa)
    np.testing.assert_allclose(rgb[4:12, 4:12].reshape(-1, 3).mean(axis=0), [0.8, 0.5, 0.2], atol=0.01)


# ------------------------------------------------------------------------------------------ the command


@pytest.fixture(scope="module")
def small_frames(tmp_path_factory):
    """The small camera's white frame, a textured scene through it, and the white's inspection report."""
    d = tmp_path_factory.mktemp("decode")
    cfg = str(FIXTURES / "small_camera.toml")
    yy, xx = np.mgrid[0:64, 0:64]
    np.save(d / "texture.npy", (0.3 + 0.7 * (((xx // 8) + (yy // 8)) % 2)).astype(np.float64))
    assert main(["simulate", "-c", cfg, "--out", str(d / "white.tiff"), "--rays-per-pixel", "60", "--seed", "1",
                 "--random-defects", "2", "-q"]) == 0
    assert main(["simulate", "-c", cfg, "--out", str(d / "scene.tiff"), "--scene", "texture", "--texture",
                 str(d / "texture.npy"), "--rays-per-pixel", "60", "--seed", "2", "--random-defects", "2", "-q"]) == 0
    main(["inspect", str(d / "white.tiff"), "-c", cfg, "--out", str(d / "report"), "-q", "--no-db"])
    return d, cfg


def test_decode_command_writes_the_light_field(small_frames):
    d, cfg = small_frames
    out = d / "lf"
    assert main(["decode", str(d / "scene.tiff"), "--white", str(d / "white.tiff"), "--report", str(d / "report"),
                 "-c", cfg, "--refocus", "0,0.1", "--out", str(out), "-q"]) == 0
    doc = json.loads((out / "decode.json").read_text())
    values, weights = np.load(out / "lightfield.npy"), np.load(out / "weights.npy")
    assert list(values.shape) == doc["shape"] and values.shape == weights.shape
    assert values.shape[2:] == (24, 24) and values.shape[0] == values.shape[1] == len(doc["view_offsets_px"])
    assert doc["sampling"] == "measured" and doc["devignetted"] and doc["refocus_slopes"] == [0.0, 0.1]
    assert isinstance(doc["lenses"]["foreign_light_samples"], int)
    assert np.load(out / "refocus.npy").shape == (2, 24, 24)
    for name in ("views.tif", "mosaic.png", "refocus_0.png", "refocus_1.png"):
        assert (out / name).stat().st_size > 0
    import tifffile

    assert tifffile.imread(out / "views.tif").shape == (values.shape[0] * values.shape[1], 24, 24)
    # the scene's checkerboard survives the devignetting: bright and dark lenses in the centre view
    centre = values[values.shape[0] // 2, values.shape[1] // 2]
    assert np.percentile(centre, 90) > 1.8 * np.percentile(centre, 10)


@pytest.mark.parametrize("case", ["white-as-scene", "wrong-size", "other-array-report", "even-views", "bad-slopes",
                                  "no-such-raw"])
def test_decode_refuses_bad_input_and_writes_nothing(small_frames, case, capsys):
    d, cfg = small_frames
    out = d / f"bad-{case}"
    scene, extra = str(d / "scene.tiff"), []
    if case == "white-as-scene":
        scene = str(d / "white.tiff")
    elif case == "wrong-size":
        np.save(d / "wrong.npy", np.full((100, 120), 500, np.uint16))
        scene = str(d / "wrong.npy")
    elif case == "other-array-report":
        rep = json.loads((d / "report" / "report.json").read_text())
        for lens in rep["grid"]["lenses"]:
            lens["grid_x_px"] += 7.0
        (d / "shifted.json").write_text(json.dumps(rep))
        extra = ["--report", str(d / "shifted.json")]
    elif case == "even-views":
        extra = ["--views", "4"]
    elif case == "bad-slopes":
        extra = ["--refocus", "near,far"]
    else:
        scene = str(d / "nothing.tiff")
    code = main(["decode", scene, "--white", str(d / "white.tiff"), "-c", cfg, "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert code == 2 and err.count("error:") == 1
    assert not out.exists() or not any(out.iterdir())


def test_decoded_views_of_a_point_follow_the_main_lens_rays(tmp_path):
    """The error-free small camera, a point source 2 mm beyond the in-focus plane: in every view inside
    0.8 of the pupil's image, the lens that sees the point is the one the exact ray (tests/lens_rays.py,
    Snell's law through the singlet, its spherical aberration included) from the point through that view's
    pupil point reaches. A view sees the point in one lens, so the centroid is quantized to whole lenses:
    uniform quantization alone gives 0.29 lens RMS."""
    import dataclasses

    from lens_rays import views_against_rays
    from mlaqc.decode.frames import load_decode_frame
    from mlaqc.decode.sampling import lattice_sampling
    from mlaqc.inspection.calibrate import calibrate_for
    from mlaqc.inspection.pipeline import load_frame
    from mlaqc.optics.config import load_config
    from mlaqc.optics.scene import PointScene
    from mlaqc.optics.simulate import simulate, write_simulation

    cfg = load_config(FIXTURES / "small_camera.toml")
    lay = cfg.layout
    scfg = dataclasses.replace(cfg, geometry=dataclasses.replace(
        cfg.geometry, mla_distance_mm=lay.mla_distance_mm, object_distance_mm=lay.object_distance_mm + 2.0))
    obj = (0.25, -0.15)
    write_simulation(tmp_path / "w.tiff", simulate(cfg, rays_per_pixel=40, seed=1, noise=False), cfg)
    write_simulation(tmp_path / "p.tiff", simulate(scfg, PointScene((obj,), 4e7), rays_per_pixel=150, seed=2,
                                                   noise=False), scfg)
    smp = lattice_sampling(calibrate_for(load_frame(str(tmp_path / "w.tiff"), cfg), cfg))
    offs = view_offsets(smp.radius_px)
    lf = devignetted(decode(load_decode_frame(str(tmp_path / "p.tiff"), cfg), smp, offs),
                     decode(load_decode_frame(str(tmp_path / "w.tiff"), cfg), smp, offs))
    got, want = views_against_rays(lf, smp.radius_px, cfg, scfg, obj)
    assert len(got) > 150 and np.all(np.isfinite(want))
    err = got - want
    assert np.all(np.abs(err.mean(axis=0)) < 0.1)  # no offset between the decoded and the real geometry
    assert np.all(np.sqrt((err ** 2).mean(axis=0)) < 0.3)  # within the lens quantization
    for k in (0, 1):  # the views span ~18 lenses (aberration): measured against exact, slope ~1
        assert 0.93 < np.polyfit(want[:, k], got[:, k], 1)[0] < 1.05


def test_decode_on_a_dask_cluster_equals_the_local_run(small_frames, tmp_path, monkeypatch):
    """Two frames (one bad) on a local Dask cluster: the good one's light field bit for bit the local run's,
    the bad one one sentence and exit 2."""
    distributed = pytest.importorskip("distributed")
    monkeypatch.delenv("MLAQC_SCHEDULER", raising=False)
    d, cfg = small_frames
    (tmp_path / "broken.tiff").write_bytes(b"II*\x00 not a tiff")
    args = [str(d / "scene.tiff"), str(tmp_path / "broken.tiff"), "--white", str(d / "white.tiff"), "-c", cfg, "-q"]
    assert main(["decode", *args, "--out", str(tmp_path / "here")]) == 2
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as lc:
        assert main(["decode", *args, "--out", str(tmp_path / "there"), "--scheduler", lc.scheduler_address]) == 2
    for name in ("lightfield.npy", "weights.npy", "refocus.npy"):
        assert np.array_equal(np.load(tmp_path / "here" / "scene" / name), np.load(tmp_path / "there" / "scene" / name))
    assert not (tmp_path / "there" / "broken").exists() or not any((tmp_path / "there" / "broken").iterdir())


def test_a_colour_light_field_keeps_its_channels_through_every_step(tmp_path):
    """An RGB frame (a demosaiced Bayer frame): each channel decoded, devignetted, refocused and written as
    its own, the weights shared."""
    from mlaqc.decode.output import write_lightfield

    x, y = centres()
    gains = np.array([0.5, 1.0, 0.25], np.float32)
    mono = frame(x, y).astype(np.float32)
    white = frame(x, y, lambda s, t, u, v: 0 * u + 0.8).astype(np.float32)
    rgb, white_rgb = mono[..., None] * gains, white[..., None] * gains
    smp, offs = sampling_at(x, y), view_offsets(RADIUS, 5)
    lf = devignetted(decode(rgb, smp, offs), decode(white_rgb, smp, offs))
    grey = devignetted(decode(mono, smp, offs), decode(white, smp, offs))
    assert lf.values.shape == grey.values.shape + (3,) and lf.weights.shape == grey.weights.shape
    np.testing.assert_allclose(lf.values, np.repeat(grey.values[..., None], 3, axis=-1), rtol=1e-5)
    img, _ = refocus(lf, 0.3)
    grey_img, _ = refocus(grey, 0.3)
    np.testing.assert_allclose(img[..., 1], grey_img, rtol=1e-5)
    paths = write_lightfield(tmp_path, lf, [(0.3, img)], {"source": "rgb"})
    assert np.load(paths["values"]).shape == lf.values.shape
    import cv2

    assert cv2.imread(str(paths["mosaic"]), cv2.IMREAD_UNCHANGED).shape[2] == 3
    assert json.loads(paths["json"].read_text())["axes"][-1].startswith("channel")


def test_a_hex_array_decodes_onto_a_rectangular_grid(tmp_path):
    cfg = str(FIXTURES / "hex_small_camera.toml")
    yy, xx = np.mgrid[0:64, 0:64]
    np.save(tmp_path / "texture.npy", (0.3 + 0.7 * (((xx // 8) + (yy // 8)) % 2)).astype(np.float64))
    assert main(["simulate", "-c", cfg, "--out", str(tmp_path / "white.tiff"), "--rays-per-pixel", "40", "-q"]) == 0
    assert main(["simulate", "-c", cfg, "--out", str(tmp_path / "scene.tiff"), "--scene", "texture", "--texture",
                 str(tmp_path / "texture.npy"), "--rays-per-pixel", "40", "-q"]) == 0
    out = tmp_path / "lf"
    assert main(["decode", str(tmp_path / "scene.tiff"), "--white", str(tmp_path / "white.tiff"), "-c", cfg,
                 "--out", str(out), "-q"]) == 0
    doc = json.loads((out / "decode.json").read_text())
    rows = int((28 - 1) * np.sqrt(3) / 2) + 1  # the hex rows, p sqrt(3)/2 apart, resampled one pitch apart
    assert doc["lens_grid"] == "rect" and doc["lenses"]["packing"] == "hex" and doc["shape"][2:] == [rows, 24]
    centre = np.load(out / "lightfield.npy")[doc["shape"][0] // 2, doc["shape"][1] // 2]
    assert np.percentile(centre[2:-2, 2:-2], 90) > 1.8 * np.percentile(centre[2:-2, 2:-2], 10)  # the checkerboard


def test_a_white_of_another_colour_kind_is_one_sentence():
    from mlaqc.decode.scene import decode_scene

    x, y = centres()
    mono = frame(x, y).astype(np.float32)
    with pytest.raises(InputError, match="differ in colour"):
        decode_scene(np.repeat(mono[..., None], 3, axis=2), sampling_at(x, y), view_offsets(RADIUS, 3), mono, "scene.dng")
