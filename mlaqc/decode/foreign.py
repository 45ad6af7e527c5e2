"""Samples that hold another lens' light. A flawed lens can send part of its light into a neighbour's
sub-image and take in part of a neighbour's: a decentered singlet's rear surface meets its neighbours' sags
off the cell edge, so rays that enter one lens leave through the next, and a lens whose sub-image moved
sits closer to one neighbour. The white frame shows it: such a sample receives more white than a healthy
lens there would, the share a healthy lens would not receive being foreign light. Dividing by the white
keeps the mixture as if it were the lens' own; here it is measured, the sample's confidence lowered by it,
and samples mostly foreign (under PURITY_MIN own light) dropped, for `fill.filled` to refill.

The healthy expectation is the median white of the lens' unflagged neighbours in the same view (the
white varies smoothly over the array), judged on the flagged lenses and their neighbours only: elsewhere
an inspection found nothing that moves light between lenses."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from mlaqc.inspection.medians import last_axis_medians
from mlaqc.optics.lattice import Lattice

if TYPE_CHECKING:
    from mlaqc.decode.lightfield import LightField

# a sample whose white is more than 1 / PURITY_MIN of a healthy lens' (over a quarter more light) holds
# mostly what it should not: its weight becomes 0 (measured on the Table 1 texture, bench/decode.py: the
# decentered lenses' rim samples hold 20-45 % foreign light, their views' worst errors)
PURITY_MIN = 0.8
MIN_HEALTHY = 2  # healthy neighbours a lens' expectation needs


def foreign_share(white: LightField, flagged: np.ndarray) -> np.ndarray:
    """Per sample (nv, nu, rows, cols): the share of its white a healthy lens there would not receive,
    1 - expected / own where the sample has more white than expected; 0 where it has not, where it cannot
    be judged, and on lenses neither flagged nor beside a flagged one. A lens brighter all over (more
    transmission, a larger pupil image) is not foreign light: its samples are judged against its median
    excess, foreign light being where a lens has more than the rest of it."""
    w = white.values if white.values.ndim == 4 else white.values.mean(axis=-1)
    share = np.zeros(w.shape, np.float32)
    rows, cols = flagged.shape
    nb = Lattice(white.packing, rows, cols).neighbours()  # (lenses, k) flat indices, -1 off the array
    flat = flagged.ravel()
    healthy = (nb >= 0) & ~flat[np.maximum(nb, 0)]
    near = flat.copy()
    near[nb[flat][nb[flat] >= 0]] = True
    k = np.flatnonzero(near & (healthy.sum(axis=1) >= MIN_HEALTHY))
    if not len(k):
        return share
    t, s = np.divmod(k, cols)
    wf, ww = w.reshape(w.shape[:2] + (-1,)), white.weights.reshape(w.shape[:2] + (-1,))
    around = np.stack([np.where(healthy[k, j][None, None] & (ww[:, :, nb[k, j]] > 0) & (wf[:, :, nb[k, j]] > 0),
                                wf[:, :, nb[k, j]], np.nan) for j in range(nb.shape[1])], axis=-1)
    expected, _ = last_axis_medians(around)
    own = w[:, :, t, s]
    judged = (np.isfinite(around).sum(axis=-1) >= MIN_HEALTHY) & (own > 0) & (white.weights[:, :, t, s] > 0)
    with np.errstate(all="ignore"):
        ratio = np.where(judged, own / expected, np.nan)
    typical, seen = last_axis_medians(ratio.reshape(-1, len(k)).T)  # each lens over its views
    ratio = ratio / np.maximum(np.where(seen, typical, 1.0), 1.0)[None, None]
    with np.errstate(all="ignore"):
        share[:, :, t, s] = np.where(judged, np.clip(1.0 - 1.0 / ratio, 0.0, 1.0), 0.0)
    return share


def without_foreign_light(lf: LightField, share: np.ndarray) -> LightField:
    """`lf` with each sample's weight scaled by its own-light share (1 - `share`), samples under PURITY_MIN
    dropped (weight 0) and marked in `foreign` for a refill."""
    foreign = (share > 1.0 - PURITY_MIN) & (lf.weights > 0)
    weights = np.where(foreign, 0.0, lf.weights * (1.0 - share)).astype(np.float32)
    return replace(lf, weights=weights, foreign=foreign)

