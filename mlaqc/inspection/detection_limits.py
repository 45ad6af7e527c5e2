"""What a frame can detect: per error type the smallest magnitude from which a lens of this frame is flagged.

The signature table's response to each error kind is read against this frame's own noise (the DETECTORS'
spreads per lens, and the ring matched filter): a magnitude is detectable where the response exceeds the
detection threshold by LIMIT_MARGIN (97.7 % of such lenses flagged), at it and every larger rendered
magnitude. Stated twice: for the inner lenses (at their median spread), and for the lenses near the edge
(`edge_zone`: the three outer rings and the 4 x 4 corner zones; the worst of them: their spreads are their
own classes', sides' and rings', wider, and on a small array they are most of the lenses). Never below the
reportable size times FLOOR_MARGIN: readings scatter about the truth (on the independent analytic model a
shift reads 0.88-0.92 of it: the tables' gain is the tracer's), so an error at the reportable size itself is
reported about half the time. The array's four corner lenses
are not judged (`lens_classes.corner_lenses`).
"""

from __future__ import annotations

import numpy as np

from mlaqc.inspection.detection import (DETECTING, FOCUS_KINDS, LIMIT_MARGIN, Noise, detector_values, focus_templates,
                                        kind_curve, min_reportable)
from mlaqc.inspection.medians import nanmedian_columns
from mlaqc.inspection.lens_classes import corner_lenses, noise_classes, ring_distance
from mlaqc.models.signatures import FEATURES, SignatureTable
from mlaqc.optics.config import QC

FLOOR_MARGIN = 1.2
KINDS = (("pitch", "µm"), ("decenter", "µm"), ("radius", "rel"), ("thickness", "µm"))


def edge_zone(shape: tuple[int, int]) -> np.ndarray:
    """(rows, cols) bool: the lenses whose spreads are not the inner lenses' (their own edge classes, sides,
    second ring or corner zone, `spreads.class_sigmas`): the three outer rings and the 4 x 4 corner zones."""
    return (ring_distance(shape) <= 2) | (noise_classes(shape) == 3)


def detection_limits(table: SignatureTable, qc: QC, noise: Noise, judged: np.ndarray | None = None) -> dict:
    """Per error type (radius and thickness per sign) the smallest magnitude an inner lens of this frame is
    flagged from, None where even the largest rendered one is not; under "border" the same for the judged
    lenses (`judged`, default all but the corners) of the `edge_zone`."""
    shape = noise.sigma.shape[:2]
    zone = edge_zone(shape)
    judged = ~corner_lenses(shape) if judged is None else judged
    inner = ~zone & judged
    inner = inner if inner.any() else judged if judged.any() else np.ones(shape, bool)
    at_median = _limits_at(table, qc, noise, nanmedian_columns(noise.sigma[inner])[None])
    limits: dict = {k: v[0] for k, v in at_median.items()}
    border = zone & judged
    if border.any() and (~zone).any():
        # (a lens' spreads are its class' and side's: a few distinct rows, not one per lens)
        per_lens = _limits_at(table, qc, noise, np.unique(noise.sigma[border], axis=0))
        limits["border"] = {k: _worst(v) for k, v in per_lens.items()}
    limits["detect_sigma"] = qc.detect_sigma
    limits["min_reportable"] = {k: v for k, v in min_reportable(qc).items() if k != "position"}
    return limits


def _worst(values: list[float | None]) -> float | None:
    """The largest limit over lenses; None if any lens cannot detect the kind at all."""
    return None if any(v is None for v in values) else float(max(values))


def _limits_at(table: SignatureTable, qc: QC, noise: Noise, sigma: np.ndarray) -> dict[str, list[float | None]]:
    """Per limit key, one limit per row of `sigma` (S, DETECTORS): the detectors' spreads of a lens."""
    templates = focus_templates(table)
    mins = min_reportable(qc)
    out: dict[str, list[float | None]] = {}
    for kind, unit in KINDS:
        if kind not in table.magnitudes:
            continue
        grid_m, grid_f = kind_curve(table, kind, 0)
        det = detector_values(grid_f[:, :len(FEATURES)])  # (G, DETECTORS)
        z = (det[None, :, :] / sigma[:, None, :])[..., DETECTING].max(axis=-1)  # (S, G)
        if kind in FOCUS_KINDS and templates.size:
            tw = templates @ noise.rings.whiten
            tw /= np.linalg.norm(tw, axis=1, keepdims=True)
            z = np.maximum(z, ((grid_f[:, len(FEATURES):] @ noise.rings.whiten) @ tw.T).max(axis=1)[None, :])
        ok = (z > qc.detect_sigma + LIMIT_MARGIN) & (np.abs(grid_m) >= FLOOR_MARGIN * mins[kind] - 1e-12)[None, :]
        signs = ((+1, "+"), (-1, "-")) if np.any(grid_m < 0) else ((+1, ""),)
        for sign, tag in signs:
            side = np.sign(grid_m) == sign
            name = f"{kind}_{'um' if unit == 'µm' else 'rel'}" + ({"+": "_pos", "-": "_neg"}.get(tag, ""))
            out[name] = [_lowest_from_which_all(np.abs(grid_m[side]), row[side]) for row in ok]
    return out


def _lowest_from_which_all(mags: np.ndarray, ok: np.ndarray) -> float | None:
    """The smallest magnitude from which every larger one (to the largest rendered) is detectable: a
    response need not grow with the error (a radius error first sharpens the sub-image, then blurs it)."""
    order = np.argsort(mags)
    mags, ok = mags[order], ok[order]
    if not ok.size or not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    first = bad[-1] + 1 if bad.size else 0
    return float(f"{mags[first]:.4g}")
