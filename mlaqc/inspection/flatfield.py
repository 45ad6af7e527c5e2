"""Is this frame a flat field? A white frame lights every lens alike but for a smooth illumination
(vignetting, a lamp's fall-off) and its noise; a scene (a sample in a microscope, a textured target) or a
frame lit through a structured mask varies from lens to lens. Inspecting one as a white frame would type its
structure as defects, so it is refused in one sentence.

The statistic: the lenses' brightness (flux against the reference) with a quadratic surface over the array
removed, its robust spread s; against the spread between neighbouring lenses n (their difference / sqrt 2,
which is what noise alone gives each lens). A white frame has s ~ n (measured: 0.1-3 %, noise-free to noisy
renders of four optics); a scene has s well above both n and a few per cent. Robust (median-based): dim or
missing lenses of a defective array, up to a quarter of them, do not move it.
"""

from __future__ import annotations

import numpy as np

from mlaqc.errors import InputError

MIN_SPREAD = 0.05  # lens-to-lens brightness beyond a smooth illumination that no white frame has
NOISE_FACTOR = 1.5  # ... nor this many times what the frame's lens-to-lens noise gives
MIN_LENSES = 25  # fewer lenses do not pin a quadratic surface and a spread


def brightness_spread(flux: np.ndarray) -> tuple[float, float]:
    """(s, n): the robust spread of per-lens brightness about a quadratic surface over the array, and the
    spread neighbouring lenses' differences give one lens (noise); NaN lenses are left out."""
    ok = np.isfinite(flux) & (flux > 0)
    if ok.sum() < MIN_LENSES:
        return float("nan"), float("nan")
    rows, cols = flux.shape
    m, n = np.nonzero(ok)
    level = float(np.median(flux[ok]))
    f = flux[ok] / level
    u, v = (n - 0.5 * cols) / cols, (m - 0.5 * rows) / rows
    design = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1)
    resid = f - design @ np.linalg.lstsq(design, f, rcond=None)[0]
    spread = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    rel = np.where(ok, flux / level, np.nan)
    diffs = np.concatenate([(rel[:, 1:] - rel[:, :-1]).ravel(), (rel[1:] - rel[:-1]).ravel()])
    diffs = diffs[np.isfinite(diffs)]
    noise = 1.4826 * float(np.median(np.abs(diffs - np.median(diffs)))) / np.sqrt(2.0) if diffs.size else 0.0
    return spread, noise


def check_flat_field(flux: np.ndarray, what: str = "the frame") -> None:
    """InputError when the per-lens brightness `flux` (rows, cols; NaN where not measured) is not a flat
    field's (see the module note)."""
    spread, noise = brightness_spread(np.asarray(flux, dtype=np.float64))
    if np.isfinite(spread) and spread > max(MIN_SPREAD, NOISE_FACTOR * noise):
        raise InputError(f"{what} is not a flat field: its lenses' brightness varies by {spread:.1%} rms from lens to "
                         f"lens beyond a smooth illumination (a white frame's varies as its noise, {noise:.1%} here); "
                         "inspection needs a white frame (uniform illumination), not a scene")
