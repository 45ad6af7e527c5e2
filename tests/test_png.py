"""The report's PNG encoder (mlaqc.report.png): any decoder reads back exactly the image, banded or not,
with ISA-L or with zlib."""

import zlib

import cv2
import numpy as np
import pytest

from mlaqc.report import png


def _decode(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return img[:, :, ::-1] if img.ndim == 3 else img


@pytest.mark.parametrize("shape", [(1, 1), (7, 5), (600, 900), (1100, 1300, 3), (3, 4, 3)])
@pytest.mark.parametrize("level", [0, 1, 3, 6, 9])
def test_pixels_come_back_exactly(shape, level):
    rng = np.random.default_rng(sum(shape) + level)
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    img[: shape[0] // 2] //= 16  # flat parts as well as noise
    data = png.encode_png(img, level)
    assert data.startswith(b"\x89PNG\r\n\x1a\n")
    assert np.array_equal(_decode(data), img)


def test_bands_join_into_one_valid_stream(monkeypatch):
    """Many bands (tiny band size): the zlib stream decompresses to the filtered rows, Adler-32 checked."""
    monkeypatch.setattr(png, "BAND_BYTES", 100)
    img = np.random.default_rng(1).integers(0, 256, (300, 70, 3), dtype=np.uint8)
    data = png.encode_png(img, 1)
    idat = data[data.index(b"IDAT") + 4: data.index(b"IEND") - 8]
    rows = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(300, 1 + 70 * 3)
    assert (rows[:, 0] == 0).all() and np.array_equal(rows[:, 1:].reshape(img.shape), img)
    assert np.array_equal(_decode(data), img)


def test_zlib_alone_gives_the_same_pixels(monkeypatch):
    monkeypatch.setattr(png, "_deflate", zlib)
    img = np.random.default_rng(2).integers(0, 256, (200, 300, 3), dtype=np.uint8)
    assert np.array_equal(_decode(png.encode_png(img, 1)), img)


def test_bad_images_are_refused():
    for bad in (np.zeros((4, 4), np.float32), np.zeros((4, 4, 4), np.uint8), np.zeros(4, np.uint8),
                np.zeros((0, 5), np.uint8), np.zeros((3, 0, 3), np.uint8)):
        with pytest.raises(ValueError):
            png.encode_png(bad)
