"""The detection statistic: each lens' feature deviations from its neighbourhood, the noise a frame judges
them against, and the score that flags a lens.

The deviations are the local deviations (mlaqc.inspection.baselines) of eight sub-image features, their
sub-pixel phase pattern removed, and the residual ring profile's, whitened by its covariance over the
array. Their noise is the frame's own, per edge class (`class_sigmas`), never below a floor set by the
smallest reportable error (`noise_floors`), so a noise-free frame is the easy case. The score is the
largest z over the DETECTORS and the ring profile's matched filter against the table's defocus
signatures (`focus_score`). mlaqc.inspection.identify flags and classifies with it; the detection limits a
report states (mlaqc.inspection.detection_limits) read the same statistic on the table's responses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mlaqc.inspection.baselines import local_deviations
from mlaqc.inspection.lens_classes import edge_classes, noise_classes
from mlaqc.inspection.medians import column_medians
from mlaqc.inspection.phase_pattern import PhaseModel, remove_phase_pattern
from mlaqc.inspection.results import LensMetrics
from mlaqc.inspection.spreads import _column_tail_sigmas, _quiet_inner, class_sigmas, robust_sigma, tail_sigma
from mlaqc.models.signatures import FEATURES, RINGS, SignatureTable
from mlaqc.optics.config import QC

LIMIT_MARGIN = 2.0  # a lens at the detection limit scores detect_sigma + 2 on average: found 97.7 % of the time
FOCUS_KINDS = ("radius", "thickness")  # errors that defocus the lens: what the focus test looks for


DEVIATION_KEYS = ("offset_x_px", "offset_y_px", "asym_x", "asym_y", "blur", "flux", "ssim", "sharpness")


DEVIATION_AXES = [k.split("_")[1][0] if k in ("offset_x_px", "offset_y_px", "asym_x", "asym_y") else "" for k in DEVIATION_KEYS]


def deviations(metrics: LensMetrics, phase: PhaseModel | None = None,
               planes: list[np.ndarray] | None = None,
               packing: str = "square") -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Local deviations of the classification features (their sub-pixel phase pattern removed when the
    lenses' `phase` is given; or `planes`, already computed in DEVIATION_KEYS order) and their robust spreads
    over the inner lenses."""
    if planes is None:
        planes = local_deviations([metrics[k] for k in DEVIATION_KEYS], DEVIATION_AXES, packing=packing)
        if phase is not None:
            planes = remove_phase_pattern(planes, phase)
    dev = dict(zip(DEVIATION_KEYS, planes))
    inner = edge_classes(metrics.shape) == 2
    sig = {k: robust_sigma(v[inner]) if np.isfinite(v[inner]).sum() > 8 else robust_sigma(v) for k, v in dev.items()}
    return dev, sig


@dataclass(frozen=True)
class RingNoise:
    """The residual-profile deviations of every lens (rows, cols, len(RINGS)) and their noise: `whiten`
    (L with L L' = inverse covariance) turns a profile change into independent unit-noise components."""

    dev: np.ndarray
    whiten: np.ndarray


def ring_noise(metrics: LensMetrics, phase: PhaseModel | None = None, floor: np.ndarray | None = None,
               planes: list[np.ndarray] | None = None, packing: str = "square",
               exclude: np.ndarray | None = None) -> RingNoise:
    """Local deviations of the ring profile, whitened by their covariance over the array's inner lenses
    (those within 4 robust sigma on every ring: a defect must not widen the noise it is judged against).

    The outer two rows and columns are their own classes: their 5 x 5 neighbourhood reaches past the
    array, and their profile deviations come out biased and wider (measured at 50 rays/pixel: median
    matched-filter z 1.7 against 1.2 inside). Each class' median is taken off and its deviations are
    scaled down to the inner lenses' noise where wider, so that one threshold holds everywhere.
    `phase`: remove the sub-pixel phase pattern (`remove_phase_pattern`); `floor` (per ring): the
    smallest noise the covariance may claim, so a noise-free frame cannot make the whitening explode;
    `planes`: the rings' deviations, already computed; `exclude`: lenses left out of the inner lenses'
    noise (`_quiet_inner`)."""
    if planes is None:
        planes = local_deviations([metrics[r] for r in RINGS], [""] * len(RINGS), packing=packing)
        if phase is not None:
            planes = remove_phase_pattern(planes, phase)
    dev = np.stack(planes, axis=-1)
    cls = edge_classes(dev.shape[:2])
    finite = np.isfinite(dev).all(axis=-1)
    for c in range(3):
        sel = (cls == c) & finite
        if sel.any():
            dev[sel] -= column_medians(dev[sel])  # (np.median's, finite values)
    inner = (cls == 2) & finite
    quiet = _quiet_inner(inner, exclude, 4 * len(RINGS) + 1)  # enough for a covariance, the defects left out
    flat = dev[quiet] if quiet is not inner or inner.sum() > 8 * len(RINGS) else dev[finite]
    sig = np.array([robust_sigma(flat[:, k]) for k in range(flat.shape[1])]) if len(flat) else np.ones(len(RINGS))
    core = (np.abs(flat) < 4 * sig).all(axis=1)
    cov = np.cov(flat[core].T) if core.sum() > 4 * len(RINGS) else np.diag(sig ** 2)
    if floor is not None:
        cov += np.diag(np.asarray(floor, float) ** 2)
    cov += np.eye(len(sig)) * 1e-12 * max(np.trace(cov), 1e-30)  # never singular
    whiten = np.linalg.cholesky(np.linalg.inv(cov))
    cls = noise_classes(dev.shape[:2])
    # edge classes by their tail-aware spread, against the inner lenses' plain robust one (which a few
    # defects among the inner lenses do not inflate, while their tails would in a small array)
    # (whitened: unit noise, the floor included, so the tail's outlier cut assumes at least that)
    left = finite & ~exclude if quiet is not inner else finite  # the inner lenses' spread without the defects
    spread = {c: robust_sigma(w) if c == 2 else tail_sigma(w, 1.0)
              for c, w in ((c, (dev[(cls == c) & (left if c == 2 else finite)] @ whiten).ravel()) for c in range(4))}
    for c in (0, 1, 3):  # (never sharpened: fewer lenses, a less sure spread)
        if np.isfinite(spread[c]) and np.isfinite(spread[2]) and spread[c] > spread[2]:
            dev[cls == c] *= spread[2] / spread[c]
    return RingNoise(dev, whiten)


def focus_templates(table: SignatureTable) -> np.ndarray:
    """Every defocus signature's ring profile (radius and thickness, both signs), one per row."""
    rows = [table.rings[k] for k in FOCUS_KINDS if k in table.rings]
    return np.concatenate(rows) if rows else np.zeros((0, len(RINGS)))


def focus_score(rings: RingNoise, table: SignatureTable) -> np.ndarray:
    """Per lens, the best matched-filter z of its ring-profile change against every defocus signature in
    the table (radius and thickness, both signs): the optimal test for a known profile in Gaussian noise."""
    templates = focus_templates(table)
    if templates.size == 0:
        return np.zeros(rings.dev.shape[:2])
    tw = templates @ rings.whiten  # (M, R) in unit-noise coordinates
    tw /= np.linalg.norm(tw, axis=1, keepdims=True)
    z = np.nan_to_num(rings.dev @ rings.whiten) @ tw.T
    # each edge class' filter outputs scaled to the inner lenses' spread where wider (as the rings are):
    # what matters is the spread along each signature, which the rings' own scaling does not bound
    cls = noise_classes(z.shape[:2])
    inner = np.maximum(column_medians(np.abs(z[cls == 2])) * 1.4826, 1e-9) if (cls == 2).sum() > 20 else None
    for c in (0, 1, 3):
        sel = cls == c
        if inner is not None and sel.sum() > 20:
            z[sel] /= np.maximum(_column_tail_sigmas(z[sel], 1.0) / inner, 1.0)  # unit-noise z: cut from 10
    return z.max(axis=-1)


# Detection quantities read from the feature deviations (FEATURES order). SSIM is measured and used to
# classify, but does not detect: it answers to every change at once, and at the array's edges its tails
# are heavy (measured: z 10-11 on healthy second-row lenses of a 400 rays/pixel tracer frame).
DETECTORS = ("offset", "asym", "blur", "flux", "ssim", "sharpness")
DETECTING = [k for k, name in enumerate(DETECTORS) if name != "ssim"]


def detector_values(f: np.ndarray) -> np.ndarray:
    """The DETECTORS' sizes (…, 6) of feature changes f (…, FEATURES…): offset and asymmetry as lengths."""
    return np.stack([np.hypot(f[..., 0], f[..., 1]), np.hypot(f[..., 2], f[..., 3]), f[..., 4], np.abs(f[..., 5]),
                     -f[..., 6], np.abs(f[..., 7])], axis=-1)


def min_reportable(qc: QC) -> dict[str, float]:
    """The smallest error worth reporting per kind (its unit): `report_fraction` of its tolerance. A
    deviation smaller than what such an error causes is not flagged however significant it is."""
    f = qc.report_fraction
    return {"pitch": f * qc.pitch_um, "position": f * qc.pitch_um, "decenter": f * qc.decenter_um,
            "radius": f * qc.radius_rel, "tilt": f * qc.tilt_deg, "thickness": f * qc.thickness_um,
            "dim": f * qc.dim_rel}


def response(table: SignatureTable, kind: str, magnitude: float) -> np.ndarray:
    """The table's FEATURES + RINGS change for `kind` at `magnitude` (linear between rendered magnitudes,
    through zero); zeros outside the rendered range on that side."""
    grid_m, grid_f = kind_curve(table, kind, 0)
    if not grid_m[0] <= magnitude <= grid_m[-1]:
        return np.zeros(grid_f.shape[1])
    return np.array([np.interp(magnitude, grid_m, grid_f[:, j]) for j in range(grid_f.shape[1])])


def noise_floors(table: SignatureTable, qc: QC) -> tuple[np.ndarray, np.ndarray]:
    """Floors of the DETECTORS' and the rings' noise: a quarter of the largest change any error at its
    minimum reportable size makes, over the detection threshold. The spread a frame measures is used
    above it; below it (a nearly noise-free frame) the floor keeps every z finite and bounded."""
    mins = min_reportable(qc)
    det, ring = np.zeros(len(DETECTORS)), np.zeros(len(RINGS))
    for kind in ("pitch", "decenter", "radius", "thickness"):
        if kind not in table.magnitudes:
            continue
        for sign in (-1, 1):
            r = response(table, kind, sign * mins[kind])
            det = np.maximum(det, np.abs(detector_values(r[:len(FEATURES)])))
            ring = np.maximum(ring, np.abs(r[len(FEATURES):]))
    return det / (4 * qc.detect_sigma), ring / (4 * qc.detect_sigma)


@dataclass(frozen=True)
class Noise:
    """What one frame's detection works against: per lens the spread of each DETECTOR (rows, cols, 6),
    floored (`noise_floors`) and per edge class; and the ring profile's whitening."""

    sigma: np.ndarray
    rings: RingNoise


def detection_noise(dev: dict[str, np.ndarray], rings: RingNoise, det_floor: np.ndarray,
                    exclude: np.ndarray | None = None, packing: str = "square") -> Noise:
    """The per-lens spreads of the DETECTORS from the frame's own deviations (`class_sigmas`; `exclude`:
    lenses left out of the inner, second-ring and edge-group spreads)."""
    floors = np.repeat(det_floor, [2, 2, 1, 1, 1, 1])  # the DETECTORS over the DEVIATION_KEYS' 8 maps
    each = class_sigmas(np.stack([dev[k] for k in DEVIATION_KEYS], axis=-1), floors, exclude, packing)
    sig = np.concatenate([0.5 * (each[..., 0:1] + each[..., 1:2]), 0.5 * (each[..., 2:3] + each[..., 3:4]),
                          each[..., 4:]], axis=-1)
    return Noise(sig, rings)


def detection_score(dev: dict[str, np.ndarray], noise: Noise, focus=None) -> np.ndarray:
    """Largest z over the detection features, per lens; `focus`: the ring-profile matched filter."""
    f = np.stack([dev[k] for k in DEVIATION_KEYS], axis=-1)  # (rows, cols, 8) in FEATURES' layout
    z = (detector_values(f) / noise.sigma)[..., DETECTING]
    if focus is not None:
        z = np.concatenate([z, focus[..., None]], axis=-1)
    return np.nanmax(np.where(np.isfinite(z), z, 0.0), axis=-1)


def kind_curve(table: SignatureTable, kind: str, sign: int) -> tuple[np.ndarray, np.ndarray]:
    """The dense magnitude curve of `kind` (one sign of it if `sign`), FEATURES then RINGS, cached on the
    table object: every flagged lens is fitted against the same curves."""
    cache = table.__dict__.setdefault("_curves", {})
    curve = cache.get((kind, sign))
    if curve is None:
        mags, feats = table.magnitudes[kind], np.concatenate([table.features[kind], table.rings[kind]], axis=1)
        if sign:
            keep = np.sign(mags) == sign
            mags, feats = mags[keep], feats[keep]
        order = np.argsort(mags)
        curve = cache[(kind, sign)] = _dense_curve(mags[order], feats[order])
    return curve


def _dense_curve(mags: np.ndarray, feats: np.ndarray, per_step: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """The table's magnitude curve with the origin added, resampled densely for the fit."""
    if not np.any(mags == 0):
        k = np.searchsorted(mags, 0.0)
        mags = np.insert(mags, k, 0.0)
        feats = np.insert(feats, k, np.zeros(feats.shape[1]), axis=0)
    t = np.linspace(0, len(mags) - 1, (len(mags) - 1) * per_step + 1)
    i0 = np.clip(np.floor(t).astype(int), 0, len(mags) - 2)
    w = (t - i0)[:, None]
    return mags[i0] * (1 - w[:, 0]) + mags[i0 + 1] * w[:, 0], feats[i0] * (1 - w) + feats[i0 + 1] * w
