"""A Bayer sensor's white frame as a monochrome one: each CFA site's channel scaled to a common level.

A white frame is spectrally flat over the array, so each of the four 2 x 2 sites sees the same sub-image
pattern, at its own quantum efficiency (and white balance). Scaling every site by the ratio of its bright
level to the brightest site's leaves a frame whose sub-images are measured as a monochrome sensor's; the
reference model and signatures are rendered monochrome. The bright level is a high quantile of each
site's pixels: the sub-images' plateau, found the same way in all four whatever the lenses' defects.
"""

from __future__ import annotations

import numpy as np

from mlaqc.errors import InputError

BRIGHT_QUANTILE = 0.95  # the plateau of the sub-images (lit area is ~ 60-90 % of a white frame)


def site_levels(img: np.ndarray) -> np.ndarray:
    """(2, 2) bright level of each CFA site of a white frame (the sites' own BRIGHT_QUANTILE)."""
    step = max(1, int(np.sqrt(img.size / 4 / 250_000)))  # a quarter million samples a site are plenty
    return np.array([[float(np.quantile(img[r::2, c::2][::step, ::step], BRIGHT_QUANTILE)) for c in (0, 1)]
                     for r in (0, 1)])


def balance_sites(img: np.ndarray, cfa: str | None) -> np.ndarray:
    """The frame with every CFA site scaled to the brightest site's level (in place; a float array); a
    monochrome frame (`cfa` None) is returned as it is. A site with no light is one clear InputError."""
    if cfa is None:
        return img
    levels = site_levels(img)
    top = float(levels.max())
    if not (top > 0 and np.all(levels > 0.02 * top)):
        raise InputError(f"a CFA site of this {cfa} frame is dark (levels {np.round(levels.ravel(), 4).tolist()} of "
                         "full scale): a white frame lights all four")
    for r in (0, 1):
        for c in (0, 1):
            img[r::2, c::2] *= np.float32(top / levels[r, c])
    return img
