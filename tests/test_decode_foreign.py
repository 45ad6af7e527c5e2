"""Samples holding another lens' light (mlaqc.decode.foreign): an analytic frame in which one flagged lens'
rim receives a neighbour's light, in the white and in the scene alike, as a decentered lens' does. The
decoder must find exactly those samples from the white, drop them when mostly foreign, and `filled` must
refill them from the neighbours while the lens keeps its own views elsewhere."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mlaqc.decode.fill import filled
from mlaqc.decode.foreign import PURITY_MIN, foreign_share, without_foreign_light
from mlaqc.decode.lightfield import LightField, decode, devignetted, view_offsets
from mlaqc.decode.scene import decode_scene
from mlaqc.decode.sampling import measured_sampling
from mlaqc.inspection.medians import last_axis_medians
from test_decode import RADIUS, centres, frame, sampling_at

LENS = (4, 5)  # 0-based: U(5,6)
STRIP_PX = 4.0  # pixels more than this right of the lens' centre hold the foreign light
FOREIGN_RADIANCE = 3.0


def scene_field(s, t, u, v):
    """The same in every view, linear over the lenses: the neighbours' mean in a view is exact."""
    return 0 * u + 1.0 + 0.1 * s - 0.05 * t


def frames(extra: float):
    """(white, scene, centres): every lens a disc; LENS' pixels right of STRIP_PX get `extra` white and
    `extra` x FOREIGN_RADIANCE of scene on top of their own."""
    x, y = centres()
    white = frame(x, y, lambda s, t, u, v: 0 * u + 1.0)
    scene = frame(x, y, scene_field)
    yy, xx = np.mgrid[0:white.shape[0], 0:white.shape[1]].astype(float)
    m, n = LENS
    strip = (np.hypot(xx - x[m, n], yy - y[m, n]) <= RADIUS) & (xx - x[m, n] > STRIP_PX)
    white[strip] += extra
    scene[strip] += extra * FOREIGN_RADIANCE
    return white.astype(np.float32), scene.astype(np.float32), (x, y)


def flagged_sampling(x, y, shape):
    grid = SimpleNamespace(grid_x_px=x, grid_y_px=y, measured_x_px=x, measured_y_px=y, missing=np.zeros(x.shape, bool),
                           pitch_px=(16.0, 16.0), radius_px=np.full(x.shape, RADIUS), image_shape=shape,
                           packing="square", shape=x.shape)
    return measured_sampling(grid, {"defects": [{"row": LENS[0] + 1, "col": LENS[1] + 1, "error_type": "decenter"}]})


def rim_and_core(offs):
    """The lens' views wholly inside the foreign strip (bilinear reads 1 px around) and wholly outside it."""
    u = np.broadcast_to(offs[None, :], (len(offs), len(offs)))
    return u >= STRIP_PX + 1.5, u <= STRIP_PX - 1.5


def test_the_white_tells_the_foreign_share_of_each_sample():
    white, _, (x, y) = frames(extra=0.5)
    smp = flagged_sampling(x, y, white.shape)
    offs = view_offsets(RADIUS)
    share = foreign_share(decode(white, smp, offs), smp.flagged)
    rim, core = rim_and_core(offs)
    disc = np.hypot(offs[:, None], offs[None, :]) <= RADIUS - 0.5
    m, n = LENS
    np.testing.assert_allclose(share[:, :, m, n][rim & disc], 1.0 - 1.0 / 1.5, rtol=1e-5)  # a third is foreign
    assert np.all(share[:, :, m, n][core] == 0)
    others = np.ones(x.shape, bool)
    others[m, n] = False
    assert np.all(share[:, :, others] == 0)  # the healthy lenses receive what a healthy lens does


def test_mostly_foreign_samples_are_dropped_and_refilled():
    white, scene, (x, y) = frames(extra=0.5)
    smp = flagged_sampling(x, y, white.shape)
    offs = view_offsets(RADIUS)
    lf = decode_scene(scene, smp, offs, white)
    rim, core = rim_and_core(offs)
    m, n = LENS
    disc = lf.weights[:, :, m + 1, n] > 0  # a healthy lens' samples: the views inside the pupil's image
    truth = scene_field(n, m, 0.0, 0.0)
    assert np.all(lf.weights[:, :, m, n][rim & disc] == 0) and np.all(lf.foreign[:, :, m, n][rim & disc])
    np.testing.assert_allclose(lf.values[:, :, m, n][core & disc], truth, rtol=1e-5)
    assert np.all(lf.weights[:, :, m, n][core & disc] == 1.0)
    out = filled(lf, lenses=smp.inside)
    np.testing.assert_allclose(out.values[:, :, m, n][rim & disc], truth, rtol=1e-5)  # the neighbours' light field
    assert np.all(out.weights[:, :, m, n][rim & disc] > 0)
    kept = ~lf.foreign[:, :, m, n]  # its own views kept (a view reading both sides of the strip's edge may go)
    assert kept[core].all()
    np.testing.assert_array_equal(out.values[:, :, m, n][kept], lf.values[:, :, m, n][kept])
    others = np.ones(x.shape, bool)
    others[m, n] = False
    np.testing.assert_array_equal(out.values[:, :, others], lf.values[:, :, others])


def test_a_little_foreign_light_lowers_the_weight_only():
    white, scene, (x, y) = frames(extra=0.1)  # 1/11 of the rim's white: under 1 - PURITY_MIN
    smp = flagged_sampling(x, y, white.shape)
    offs = view_offsets(RADIUS)
    lf = decode_scene(scene, smp, offs, white)
    rim, _ = rim_and_core(offs)
    m, n = LENS
    disc = lf.weights[:, :, m + 1, n] > 0
    assert 1.0 / 11.0 < 1.0 - PURITY_MIN
    np.testing.assert_allclose(lf.weights[:, :, m, n][rim & disc], 1.0 / 1.1, rtol=1e-5)
    assert not lf.foreign.any()


def test_without_a_report_nothing_is_judged():
    """The calibrated lattice (no flagged lenses) decodes the mixture as other tools do."""
    white, scene, (x, y) = frames(extra=0.5)
    offs = view_offsets(RADIUS)
    lf = decode_scene(scene, sampling_at(x, y, white.shape), offs, white)
    assert lf.foreign is None and lf.weights.max() == 1.0
    rim, _ = rim_and_core(offs)
    m, n = LENS
    seen = rim & (lf.weights[:, :, m, n] > 0)
    np.testing.assert_allclose(lf.values[:, :, m, n][seen], (scene_field(n, m, 0, 0) + 0.5 * FOREIGN_RADIANCE) / 1.5,
                               rtol=1e-5)


@pytest.mark.parametrize("packing, colour", [("hex", False), ("square", True), ("hex", True)])
def test_foreign_light_on_either_lattice_in_colour_and_at_the_edge(packing, colour):
    """Light fields given directly: two flagged lenses, one on the array's first row (neighbours on one
    side), take half a white's worth of another lens' light in their views u >= 2; a third is brighter
    all over (more transmission), which is not foreign light. The scene is linear across the row (the
    neighbours' mean is exact, on hex too: the next row's two sit half a pitch either side)."""
    rows, cols, n = 6, 7, 9
    o = np.arange(n, dtype=float) - n // 2
    t, s = np.mgrid[0:rows, 0:cols].astype(float)
    x = s + (0.5 * (t % 2) if packing == "hex" else 0.0)
    truth = np.broadcast_to(1.0 + 0.1 * x, (n, n, rows, cols)).copy()
    white = np.ones((n, n, rows, cols))
    rim = np.broadcast_to(o[None, :, None, None] >= 2, white.shape)
    flagged = np.zeros((rows, cols), bool)
    for m, c in ((0, 3), (3, 3)):
        flagged[m, c] = True
        white[:, :, m, c] += 0.5 * rim[:, :, m, c]
    flagged[3, 5] = True
    white[:, :, 3, 5] *= 1.4  # brighter all over
    scene = truth * white + np.where(white > 1.2, 0.5 * FOREIGN_RADIANCE, 0.0) * (rim & flagged[None, None])
    scene[:, :, 3, 5] = truth[:, :, 3, 5] * white[:, :, 3, 5]
    if colour:
        tint = np.array([1.0, 0.5, 2.0])
        white, scene, truth = white[..., None] * tint, scene[..., None] * tint, truth[..., None] * np.ones(3)
    ones = np.ones((n, n, rows, cols), np.float32)
    w_lf = LightField(white.astype(np.float32), ones, o, packing)
    lf = devignetted(LightField(scene.astype(np.float32), ones, o, packing), w_lf)
    lf = without_foreign_light(lf, foreign_share(w_lf, flagged))
    expect = rim & flagged[None, None]
    expect[:, :, 3, 5] = False
    np.testing.assert_array_equal(lf.foreign, expect)
    assert np.all(lf.weights[~expect] == 1.0)
    out = filled(lf)
    np.testing.assert_allclose(out.values[expect], truth[expect], rtol=1e-5)
    assert np.all(out.weights[expect] > 0) and not out.foreign.any()
    np.testing.assert_array_equal(out.values[~expect], lf.values[~expect])


def test_the_median_of_the_neighbours_skips_the_missing_ones():
    rng = np.random.default_rng(3)
    stack = rng.normal(size=(8, 5, 7)).astype(np.float32)
    stack[rng.random(stack.shape) < 0.4] = np.nan
    stack[:, 0, 0] = np.nan  # no neighbour at all
    got, seen = last_axis_medians(np.moveaxis(stack, 0, -1))  # what foreign_share takes its expectation by
    got = np.where(seen, got, np.nan)
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
        want = np.nanmedian(stack, axis=0)
    np.testing.assert_allclose(got, want, rtol=1e-6, equal_nan=True)
    np.testing.assert_array_equal(seen, np.isfinite(stack).sum(axis=0) > 0)
