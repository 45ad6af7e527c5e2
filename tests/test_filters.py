"""NumPy maximum filters and the bare pocketfft transform give scipy's results bit for bit."""

import numpy as np
import pytest
import scipy.fft
from scipy.ndimage import maximum_filter

from mlaqc.inspection import fft
from mlaqc.inspection.filters import max_filter_nearest, max_of_neighbours


@pytest.mark.parametrize("size", [1, 3, 5, 7, 4])
@pytest.mark.parametrize("shape", [(1, 1), (2, 9), (12, 12), (31, 17)])
def test_max_filter_nearest_is_scipys(size, shape):
    rng = np.random.default_rng(size * 100 + shape[0])
    for a in (rng.random(shape) < 0.1, rng.normal(size=shape)):
        assert np.array_equal(max_filter_nearest(a, size), maximum_filter(a, size=size, mode="nearest"))


@pytest.mark.parametrize("shape", [(1, 1), (1, 6), (12, 12), (31, 17)])
def test_max_of_neighbours_is_scipys_ring_footprint(shape):
    ring = np.ones((3, 3), bool)
    ring[1, 1] = False
    a = np.where(np.random.default_rng(3).random(shape) < 0.2, np.random.default_rng(4).random(shape) * 10, 0.0)
    assert np.array_equal(max_of_neighbours(a), maximum_filter(a, footprint=ring, mode="constant"))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape", [(64, 64), (1024, 1024), (100, 37)])
def test_rfft2_is_scipy_fft_rfft2_bit_for_bit(dtype, shape):
    a = np.random.default_rng(0).normal(size=shape).astype(dtype)
    for workers in (1, 2):
        got = fft.rfft2(a, workers=workers)
        want = scipy.fft.rfft2(a, workers=workers)
        assert got.dtype == want.dtype and np.array_equal(got, want)


def test_rfft2_without_the_bare_extension_uses_scipy_fft(monkeypatch):
    monkeypatch.setattr(fft, "_EXTENSION", [None])
    a = np.random.default_rng(1).normal(size=(32, 48)).astype(np.float32)
    assert np.array_equal(fft.rfft2(a), scipy.fft.rfft2(a))
