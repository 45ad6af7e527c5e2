"""A scene frame's light field as a user wants it: decoded, divided by its white frame's (devignetted), and,
where the sampling knows the flagged lenses (a report), cleared of the light that other lenses send
through them (mlaqc.decode.foreign)."""

from __future__ import annotations

from typing import Any

import numpy as np

from mlaqc.decode.foreign import foreign_share, without_foreign_light
from mlaqc.decode.lightfield import LightField, decode, devignetted
from mlaqc.decode.sampling import LensSampling
from mlaqc.errors import InputError


def decode_scene(img: np.ndarray, sampling: LensSampling, offsets_px: np.ndarray, white: Any = None,
                 source: str = "the frame", share: np.ndarray | None = None) -> LightField:
    """`img`'s light field, divided by the white's (an image, or its LightField decoded at the same samples:
    a batch decodes its white once) when one is given; InputError when the two differ in colour. With a
    white and a sampling that knows the flagged lenses (a report), the samples around them that hold
    another lens' light are weighed by their own light's share (`mlaqc.decode.foreign`; `share`: that
    white's `foreign_share`, which a batch computes once)."""
    lf = decode(img, sampling, offsets_px)
    if white is None:
        return lf
    if not isinstance(white, LightField):
        white = decode(white, sampling, offsets_px)
    if (white.values.ndim == 5) != (lf.values.ndim == 5):
        raise InputError(f"{source} and the white frame differ in colour (one has a colour filter array, the "
                         "other not): they are not of one camera")
    lf = devignetted(lf, white)
    if sampling.flagged is not None and sampling.flagged.any():
        lf = without_foreign_light(lf, foreign_share(white, sampling.flagged) if share is None else share)
    return lf
