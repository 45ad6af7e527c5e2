"""The frame's own noise per lens class (mlaqc.inspection.spreads.class_sigmas): a small array's few
defects must not set it (issue #22: 9 defects among a 24 x 24 array's 384 inner lenses read its spreads
10-20 times the noise), while a wide systematic tail still widens it."""

from __future__ import annotations

import numpy as np

from mlaqc.inspection.spreads import class_sigmas
from mlaqc.inspection.lens_classes import noise_classes, second_ring


def _noise(shape=(24, 24), seed=3) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal(shape)


def test_a_few_strong_defects_among_the_inner_lenses_do_not_set_their_spread():
    dev = _noise()
    for m in (5, 11, 17):
        for n in (5, 11, 17):
            dev[m, n] = 60.0 * (-1) ** (m + n)  # 9 defects: 2.3 % of the 384 inner lenses
    inner = noise_classes(dev.shape) == 2
    assert class_sigmas(dev)[inner].max() < 1.4  # the Gaussian noise's own (1), not the defects'
    assert class_sigmas(_noise())[inner].max() < 1.4


def test_a_wide_systematic_tail_still_widens_the_spread():
    """3 % of the inner lenses at 5 sigma (within TAIL_OUTLIER: a pattern, not defects): the 99th
    percentile follows them, so that they do not cross a 6-sigma threshold."""
    dev = _noise()
    inner = np.flatnonzero((noise_classes(dev.shape) == 2).ravel())
    dev.ravel()[inner[::33]] = 5.0
    sig = class_sigmas(dev)[noise_classes(dev.shape) == 2].max()
    assert sig > 5.0 / 6.0 * 1.2 and 5.0 / sig < 6.0



def test_a_wider_second_ring_is_judged_against_its_own_spread():
    """The second ring in three times as noisy as the rest (its windows, cut to 3 or 4 rows, read the
    frame's systematics otherwise): its lenses get their own, wider spread. On
    12 x 12 the ring is too small to measure its own (28 lenses), and keeps the inner one."""
    dev = _noise((60, 60))
    second = second_ring(dev.shape)
    dev[second] *= 3.0
    sig = class_sigmas(dev)
    rest = (noise_classes(dev.shape) == 2) & ~second
    assert 2.4 < np.median(sig[second]) < 4.0  # about 3
    assert np.median(sig[second]) > 1.5 * np.median(sig[rest])  # (the rest's tail holds the ring too)
    small = _noise((12, 12))
    small[second_ring(small.shape)] *= 3.0
    assert np.ptp(class_sigmas(small)[noise_classes(small.shape) == 2]) == 0.0


def test_an_edge_side_wider_than_the_rest_is_judged_against_its_own_spread():
    """One side of the outer ring five times as noisy as the others (the hex row ends of an Airy-rimmed
    frame read sharpness 2x the ring's spread, flagged at 6.2 sigma): its lenses get their own robust
    spread, which one defect among them does not move. A side of fewer than SECOND_RING_MIN lenses is
    too small to measure its own and keeps the ring's."""
    dev = _noise((60, 200))
    dev[:, 0] *= 5.0
    cls = noise_classes(dev.shape)
    side = cls[:, 0] == 0  # (the corners are a class of their own)
    sig = class_sigmas(dev)
    assert 4.2 < np.median(sig[side, 0]) < 6.0
    assert np.median(sig[0, cls[0] == 0]) < 4.0  # the other sides keep the ring's spread
    dev[30, 0] = 60.0  # a defect on that side
    assert np.allclose(class_sigmas(dev)[side, 0], sig[side, 0], rtol=0.05)
    small = _noise((30, 30))
    small[:, 0] *= 5.0
    ring = noise_classes(small.shape) == 0
    assert np.ptp(class_sigmas(small)[ring]) == 0.0
    clipped = _noise((60, 200))  # a side off the sensor but for two lenses, one a defect: too few values
    clipped[:, 0] = np.nan
    clipped[20, 0], clipped[30, 0] = 0.5, 60.0
    assert class_sigmas(clipped)[30, 0] < 2.0
