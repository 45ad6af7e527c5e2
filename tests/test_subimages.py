"""Sub-image division: every window lands on its lens U(m,n), with the right sub-pixel offset."""

from __future__ import annotations

import numpy as np
import pytest

from calib_images import synthetic_white
from mlaqc.inspection.calibrate import calibrate
from mlaqc.errors import InputError
from mlaqc.inspection.subimages import SubImages, default_size, divide

ROWS, COLS = 18, 19


@pytest.fixture(scope="module")
def frame():
    """A synthetic white frame (exact centres), slightly rotated and offset, and its calibrated grid."""
    img, tx, ty = synthetic_white(rows=ROWS, cols=COLS, rotation_deg=0.8, offset=(2.3, -1.7))
    return img, tx, ty, calibrate(img, expected_pitch_px=20.05, expected_shape=(ROWS, COLS))


def coded_image(grid, shape):
    """A frame whose pixel nearest each lens' predicted centre holds 1000 m + n, and whose pixel one to the
    right and two down holds -(1000 m + n); everything else 0."""
    img = np.zeros(shape, np.float32)
    m, n = np.mgrid[1:grid.rows + 1, 1:grid.cols + 1]
    code = (1000 * m + n).astype(np.float32)
    cx = np.floor(grid.grid_x_px + 0.5).astype(int)
    cy = np.floor(grid.grid_y_px + 0.5).astype(int)
    inside = (cx >= 0) & (cx + 1 < shape[1]) & (cy >= 0) & (cy + 2 < shape[0])
    img[cy[inside], cx[inside]] = code[inside]
    img[cy[inside] + 2, cx[inside] + 1] = -code[inside]
    return img, code, inside


def test_each_window_holds_its_own_lens(frame):
    img, _, _, grid = frame
    coded, code, inside = coded_image(grid, img.shape)
    sub = divide(coded, grid)
    h, w = sub.window_shape
    assert sub.data.shape == (ROWS, COLS, h, w) and sub.data.dtype == np.float32
    assert (h, w) == (21, 21) and default_size(grid) == 21  # pitch 20.05 -> odd 21
    c = h // 2
    np.testing.assert_array_equal(sub.data[..., c, c][inside], code[inside])
    np.testing.assert_array_equal(sub.data[..., c + 2, c + 1][inside], -code[inside])
    # the code of a lens appears in no other window's centre
    assert len(np.unique(sub.data[..., c, c][inside])) == inside.sum()


def test_sub_pixel_offsets_and_origins(frame):
    img, tx, ty, grid = frame
    sub = divide(img, grid)
    h, w = sub.window_shape
    assert np.all(np.abs(sub.offset_x_px) <= 0.5) and np.all(np.abs(sub.offset_y_px) <= 0.5)
    np.testing.assert_allclose(sub.origin_x_px + sub.centre_x_px, grid.grid_x_px)
    np.testing.assert_allclose(sub.centre_x_px, (w - 1) / 2 + sub.offset_x_px)
    # the window content sits where the offset says: its centroid round the predicted centre (a window
    # wide enough for the whole sub-image and a round, tapered mask, both symmetric about that centre)
    sub = divide(img, grid, size_px=31)
    x, y = sub.window_coords()
    taper = np.clip(12.0 - np.hypot(x, y), 0.0, 1.0)  # a symmetric window round the predicted centre
    wts = np.where(sub.valid, sub.data * taper, 0.0)
    cx = (wts * x).sum(axis=(2, 3)) / wts.sum(axis=(2, 3))
    cy = (wts * y).sum(axis=(2, 3)) / wts.sum(axis=(2, 3))
    full = sub.valid.all(axis=(2, 3))
    full[[0, -1], :] = full[:, [0, -1]] = False  # border lenses lack a neighbour on one side: asymmetric
    # the true centre relative to the grid prediction (grid error ~0.005 px here)
    assert np.abs(cx - (tx - grid.grid_x_px))[full].max() < 0.02
    assert np.abs(cy - (ty - grid.grid_y_px))[full].max() < 0.02
    # window pixel (i, j) is frame pixel (origin_y + i, origin_x + j)
    m, n, i, j = 3, 4, 5, 7
    assert sub.data[m, n, i, j] == img[sub.origin_y_px[m, n] + i, sub.origin_x_px[m, n] + j]


def test_border_windows_are_masked(frame):
    img, _, _, grid = frame
    # crop so that the outer windows reach out of the frame
    top, left = 32, 35
    cropped = img[top:, left:]
    g = calibrate(cropped, expected_pitch_px=20.05, expected_shape=(ROWS, COLS))
    sub = divide(cropped, g)
    assert not sub.valid[0, 0].all() and not sub.valid[:, 0].all(axis=(1, 2)).any()
    assert np.isnan(sub.data[~sub.valid]).all()
    assert np.isfinite(sub.data[sub.valid]).all()
    assert sub.valid[ROWS // 2, COLS // 2].all()
    # valid pixels are the frame's own
    ys = sub.origin_y_px[0, 0] + np.arange(sub.window_shape[0])
    xs = sub.origin_x_px[0, 0] + np.arange(sub.window_shape[1])
    ok = sub.valid[0, 0]
    np.testing.assert_array_equal(sub.data[0, 0][ok], cropped[np.clip(ys, 0, None)[:, None], np.clip(xs, 0, None)[None, :]][ok])
    assert ((ys[:, None] >= 0) & (xs[None, :] >= 0) == ok).all()


@pytest.mark.parametrize("size", [20, (15, 25)])
def test_other_window_sizes(frame, size):
    img, _, _, grid = frame
    sub = divide(img, grid, size_px=size)
    h, w = (size, size) if np.isscalar(size) else size
    assert sub.window_shape == (h, w)
    assert np.all(np.abs(sub.offset_x_px) <= 0.5) and np.all(np.abs(sub.offset_y_px) <= 0.5)
    np.testing.assert_allclose(sub.origin_y_px + sub.centre_y_px, grid.grid_y_px)


def test_bad_arguments(frame):
    img, _, _, grid = frame
    with pytest.raises(InputError, match="calibrated on"):
        divide(img[:-1], grid)
    with pytest.raises(InputError, match="2-D"):
        divide(img[None], grid)
    with pytest.raises(InputError, match="size"):
        divide(img, grid, size_px=0)
    with pytest.raises(InputError, match="size"):
        divide(img, grid, size_px=500)


def test_subimages_is_frozen(frame):
    img, _, _, grid = frame
    sub = divide(img, grid)
    assert isinstance(sub, SubImages) and sub.grid is grid
    with pytest.raises(Exception):
        sub.data = None  # type: ignore[misc]


def test_cut_windows_match_the_fancy_index_gather():
    """The compiled cut == one NumPy fancy-index gather, NaN and valid=False outside the frame."""
    from mlaqc.inspection.subimages import cut_windows

    rng = np.random.default_rng(4)
    img = rng.normal(size=(57, 64))
    x = rng.uniform(-8, 72, (5, 6))
    y = rng.uniform(-8, 65, (5, 6))
    for h, w in ((9, 9), (8, 11)):
        data, valid, ox, oy = cut_windows(img, x, y, h, w)
        ys = oy[..., None] + np.arange(h)
        xs = ox[..., None] + np.arange(w)
        inside = ((ys >= 0) & (ys < 57))[..., :, None] & ((xs >= 0) & (xs < 64))[..., None, :]
        want = img[np.clip(ys, 0, 56)[..., :, None], np.clip(xs, 0, 63)[..., None, :]].astype(np.float32)
        want[~inside] = np.nan
        assert np.array_equal(ox, np.floor(x - 0.5 * (w - 1) + 0.5)) and np.array_equal(oy, np.floor(y - 0.5 * (h - 1) + 0.5))
        assert data.dtype == np.float32 and np.array_equal(valid, inside) and not inside.all()
        assert np.array_equal(data, want, equal_nan=True)
