"""A dim lens: a transmission loss (a coating, an absorbing residue over the whole lens) that changes how
much light a lens passes but not the shape of its sub-image. Its signature needs no render: every index
that measures shape (shift, asymmetry, rim width, structure, sharpness, the residual profile) is unchanged
by a uniform scale, and the flux index (the sub-image's flux against the reference) falls by the loss. It
joins the rendered kinds only when a flagged lens is classified, so detection is untouched; a lens whose
shape changed with its flux (a radius or thickness error defocuses it) still fits its own kind better.
"""

from __future__ import annotations

import numpy as np

from mlaqc.models.signatures import FEATURES, KIND_BY_NAME, RINGS, ErrorKind, SignatureTable

# relative change of the lens' transmission (negative: a loss); a fully opaque lens is 'missing'
DIM = ErrorKind("dim", (-0.8, -0.6, -0.4, -0.3, -0.2, -0.15, -0.1, -0.07, -0.05, -0.03, -0.02), "rel", False,
                lambda v: {})
CLASSIFIED_KINDS = {**KIND_BY_NAME, DIM.name: DIM}  # what a flagged lens may be typed as


def with_dim(table: SignatureTable) -> SignatureTable:
    """`table` with the dim kind's analytic curve added (features zero but the flux's, rings zero); made once
    per table, as `across_table` is, so its dense curves are computed once for every frame."""
    if DIM.name in table.magnitudes:
        return table
    cache = table.__dict__.setdefault("_with_dim", {})
    if "t" not in cache:
        mags = np.asarray(DIM.magnitudes, float)
        feats = np.zeros((mags.size, len(FEATURES)))
        feats[:, FEATURES.index("flux")] = mags
        cache["t"] = SignatureTable({**table.magnitudes, DIM.name: mags}, {**table.features, DIM.name: feats},
                                    {**table.phi0_deg, DIM.name: 0.0}, table.key,
                                    {**table.rings, DIM.name: np.zeros((mags.size, len(RINGS)))},
                                    dict(table.settings), dict(table.across))
    return cache["t"]
