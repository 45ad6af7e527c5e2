"""Identification: flag lenses whose indexes leave the normal population, then say what is wrong.

Detection compares every lens with its own neighbourhood (5 x 5 local median, which cancels vignetting,
exposure and slow field variation) in units of the array's robust spread (1.4826 MAD): a real capture
differs from the model in exposure and illumination, and inspection must still work. Defocus (radius,
thickness) is tested on the residual's ring profile with a matched filter against the table's defocus
signatures, whitened by the rings' covariance over the array.

Classification inverts the signature table: the flagged lens' feature changes, taken along and across
its own shift, and its ring profile are fitted by every error kind over its magnitude (noise-weighted
least squares); the best kind gives type, magnitude and direction.

Two limits are physical, not the method's (bench/type_separation.py: the best possible matched filter
against a frame's noise). In a white image a pitch error and a surface decenter below about 10 µm change
the sub-images identically to within the noise (both redirect the chief ray of a lens whose cell stays
on the grid), so such a lens is reported as 'position' with both readings, never as a guess between
them. And the default camera's best focus lies at about +5 % radius (spherical aberration puts it in
front of the paraxial focus the sensor sits at): a radius error of +5 to +10 % hardly defocuses the
sub-image (at 50 rays/pixel the ideal z is 2.5 to 5), while -5 % or +15 % clearly does. A radius or
thickness error whose opposite sign fits about as well carries the other reading in `alternatives`.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from scipy.ndimage import maximum_filter, median_filter

from mlaqc.inspection.metrics_kernels import median_baselines
from mlaqc.inspection.results import Defect, LensMetrics
from mlaqc.models.signatures import FEATURES, KIND_BY_NAME, RINGS, SignatureTable, lens_features
from mlaqc.optics.config import QC

# Features whose change is tested for detection, and on which side (+1 up, -1 down, 0 both).
DETECT = {"offset": 0, "asym": 0, "blur": +1, "flux": 0, "ssim": -1, "sharpness": 0}
_CHI2_AMBIGUOUS = 9.0  # an opposite-sign reading closer than this (3 sigma) is listed as an alternative
FOCUS_KINDS = ("radius", "thickness")  # errors that defocus the lens: what the focus test looks for


def local_deviation(values: np.ndarray, size: int = 5, axis: str = "") -> np.ndarray:
    """values minus a NaN-robust local baseline: the median over size x size lenses inside the array;
    along an edge the running median of that edge (its lenses miss the same neighbours). A corner lens
    misses neighbours on two sides: for an x index (axis='x') it is compared along its left/right edge,
    otherwise along its top/bottom edge (and flagged only at 1.5 x the threshold, see `identify`)."""
    return local_deviations([values], [axis], size)[0]


def local_deviations(planes: list[np.ndarray], axes: list[str], size: int = 5) -> list[np.ndarray]:
    """`local_deviation` of several (rows, cols) index maps at once: one compiled median pass over all of
    them (scipy's median_filter cost 16 ms per map); even sizes or all-NaN maps take the scipy route."""
    fills = []
    for values in planes:
        finite = np.isfinite(values)
        fills.append(values if finite.all() else np.where(finite, values, np.nanmedian(values)))
    stack = np.array(fills, dtype=np.float64)
    if size % 2 == 1 and np.isfinite(stack).all():
        base = np.empty_like(stack)
        x_axis = np.array([a == "x" for a in axes])
        workers = min(len(stack) // 2, os.cpu_count() or 1)  # the kernel releases the GIL: planes in parallel
        if workers > 1:
            cuts = np.linspace(0, len(stack), workers + 1).astype(int)
            with ThreadPoolExecutor(workers) as pool:
                list(pool.map(lambda ab: median_baselines(stack[ab[0]:ab[1]], int(size), x_axis[ab[0]:ab[1]],
                                                          base[ab[0]:ab[1]]), pairwise(cuts)))
        else:
            median_baselines(stack, int(size), x_axis, base)
    else:
        base = np.stack([_scipy_baseline(f, size, a) for f, a in zip(stack, axes)])
    return [values - b for values, b in zip(planes, base)]


def _scipy_baseline(fill: np.ndarray, size: int, axis: str) -> np.ndarray:
    """The local median baseline of one NaN-filled map with scipy (the reference formulation)."""
    base = median_filter(fill, size=size, mode="nearest")
    rows, cols = fill.shape
    if rows >= size and cols >= size:
        horizontal = ((0, slice(None)), (-1, slice(None)))
        vertical = ((slice(None), 0), (slice(None), -1))
        order = horizontal + vertical if axis == "x" else vertical + horizontal  # the last one wins at corners
        for sl in order:
            base[sl] = median_filter(fill[sl], size=size, mode="nearest")
    return base


def robust_sigma(dev: np.ndarray) -> float:
    """1.4826 x median absolute deviation (NaN ignored); a tiny floor keeps z finite."""
    d = dev[np.isfinite(dev)]
    if d.size == 0:
        return np.inf
    return max(1.4826 * float(np.median(np.abs(d - np.median(d)))), 1e-9)


def deviations(metrics: LensMetrics) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Local deviations of the classification features and their robust spreads."""
    names = ("offset_x_px", "offset_y_px", "asym_x", "asym_y", "blur", "flux", "ssim", "sharpness")
    axes = [k.split("_")[1][0] if k in ("offset_x_px", "offset_y_px", "asym_x", "asym_y") else "" for k in names]
    dev = dict(zip(names, local_deviations([metrics[k] for k in names], axes)))
    sig = {k: robust_sigma(v) for k, v in dev.items()}
    return dev, sig


@dataclass(frozen=True)
class RingNoise:
    """The residual-profile deviations of every lens (rows, cols, len(RINGS)) and their noise: `whiten`
    (L with L L' = inverse covariance) turns a profile change into independent unit-noise components."""

    dev: np.ndarray
    whiten: np.ndarray


def ring_noise(metrics: LensMetrics) -> RingNoise:
    """Local deviations of the ring profile, whitened by their covariance over the array's inner lenses
    (those within 4 robust sigma on every ring: a defect must not widen the noise it is judged against).

    The outer two rows and columns are their own classes: their 5 x 5 neighbourhood reaches past the
    array, and their profile deviations come out biased and wider (measured at 50 rays/pixel: median
    matched-filter z 1.7 against 1.2 inside). Each class' median is taken off and its deviations are
    scaled down to the inner lenses' noise where wider, so that one threshold holds everywhere."""
    dev = np.stack(local_deviations([metrics[r] for r in RINGS], [""] * len(RINGS)), axis=-1)
    rows, cols = dev.shape[:2]
    m, n = np.ogrid[:rows, :cols]
    cls = np.minimum(np.minimum(m, n), np.minimum(rows - 1 - m, cols - 1 - n)).clip(max=2)
    finite = np.isfinite(dev).all(axis=-1)
    for c in range(3):
        sel = (cls == c) & finite
        if sel.any():
            dev[sel] -= np.median(dev[sel], axis=0)
    flat = dev[(cls == 2) & finite] if ((cls == 2) & finite).sum() > 8 * len(RINGS) else dev[finite]
    sig = np.array([robust_sigma(flat[:, k]) for k in range(flat.shape[1])]) if len(flat) else np.ones(len(RINGS))
    core = (np.abs(flat) < 4 * sig).all(axis=1)
    cov = np.cov(flat[core].T) if core.sum() > 4 * len(RINGS) else np.diag(sig ** 2)
    cov += np.eye(len(sig)) * 1e-12 * np.trace(cov)  # never singular
    whiten = np.linalg.cholesky(np.linalg.inv(cov))
    spread = {c: robust_sigma((dev[(cls == c) & finite] @ whiten).ravel()) for c in range(3)}
    for c in (0, 1):  # (never sharpened: fewer lenses, a less sure spread)
        if np.isfinite(spread[c]) and np.isfinite(spread[2]) and spread[c] > spread[2]:
            dev[cls == c] *= spread[2] / spread[c]
    return RingNoise(dev, whiten)


def focus_score(rings: RingNoise, table: SignatureTable) -> np.ndarray:
    """Per lens, the best matched-filter z of its ring-profile change against every defocus signature in
    the table (radius and thickness, both signs): the optimal test for a known profile in Gaussian noise."""
    templates = np.concatenate([table.rings[k] for k in FOCUS_KINDS if k in table.rings])
    if templates.size == 0:
        return np.zeros(rings.dev.shape[:2])
    tw = templates @ rings.whiten  # (M, R) in unit-noise coordinates
    tw /= np.linalg.norm(tw, axis=1, keepdims=True)
    z = np.nan_to_num(rings.dev @ rings.whiten) @ tw.T
    return z.max(axis=-1)


def detection_score(dev: dict[str, np.ndarray], sig: dict[str, float], position=None, focus=None) -> np.ndarray:
    """Largest robust z over the detection features, per lens. `position` (dx, dy): a lower-noise
    position signal to detect shifts with (the calibration's per-lens residual on the same frame);
    `focus`: the ring-profile matched filter (`focus_score`)."""
    if position is not None:
        px, py = local_deviations([position[0], position[1]], ["x", "y"])
        dev = dict(dev, offset_x_px=px, offset_y_px=py)
        sig = dict(sig, offset_x_px=robust_sigma(dev["offset_x_px"]), offset_y_px=robust_sigma(dev["offset_y_px"]))
    s_off = 0.5 * (sig["offset_x_px"] + sig["offset_y_px"])
    s_asym = 0.5 * (sig["asym_x"] + sig["asym_y"])
    zs = [np.hypot(dev["offset_x_px"], dev["offset_y_px"]) / s_off,
          np.hypot(dev["asym_x"], dev["asym_y"]) / s_asym,
          dev["blur"] / sig["blur"], np.abs(dev["flux"]) / sig["flux"],
          -dev["ssim"] / sig["ssim"], np.abs(dev["sharpness"]) / sig["sharpness"]]
    if focus is not None:
        zs.append(focus)
    return np.nanmax(np.stack([np.where(np.isfinite(z), z, 0.0) for z in zs]), axis=0)


def spill(score: np.ndarray, flagged: np.ndarray, ratio: float = 0.5) -> np.ndarray:
    """Flagged lenses next to a flagged neighbour more than 1/ratio times as abnormal: a strong defect
    disturbs its neighbours' windows (its light spills over), so they are taken as its echo."""
    ring = np.ones((3, 3), bool)
    ring[1, 1] = False
    strongest = maximum_filter(np.where(flagged, score, 0.0), footprint=ring, mode="constant")
    return flagged & (score < ratio * strongest)


def _feature_vector(dev: dict[str, np.ndarray], rings: RingNoise, m: int, n: int) -> tuple[np.ndarray, float]:
    """FEATURES of lens [m, n] from its deviations, along its own shift, then its RINGS changes; and
    that shift's direction."""
    vec = np.concatenate([lens_features(dev, m, n), rings.dev[m, n]])
    return vec, float(np.degrees(np.arctan2(-dev["offset_y_px"][m, n], dev["offset_x_px"][m, n])))


def _feature_sigmas(sig: dict[str, float]) -> np.ndarray:
    s_off = 0.5 * (sig["offset_x_px"] + sig["offset_y_px"])
    s_asym = 0.5 * (sig["asym_x"] + sig["asym_y"])
    return np.array([s_off, s_off, s_asym, s_asym, sig["blur"], sig["flux"], sig["ssim"], sig["sharpness"]])


def _unit_noise(f: np.ndarray, sigmas: np.ndarray, whiten: np.ndarray | None) -> np.ndarray:
    """Feature changes (..., FEATURES [+ RINGS]) in unit-noise coordinates: each feature over its robust
    sigma, the ring profile through its whitening (its rings are correlated); without `whiten` the
    FEATURES alone."""
    n = len(FEATURES)
    head = f[..., :n] / sigmas
    return head if whiten is None else np.concatenate([head, f[..., n:] @ whiten], axis=-1)


def fit_kind(table: SignatureTable, kind: str, vec: np.ndarray, sigmas: np.ndarray, sign: int = 0,
             whiten: np.ndarray | None = None) -> tuple[float, float]:
    """Best magnitude of `kind` for feature changes `vec` and its chi-square (magnitude interpolated
    linearly in the table, through zero); `sign` restricts a signed kind to one side; `whiten`: the
    ring noise (`RingNoise.whiten`) to fit the ring profile too."""
    grid_m, grid_f = _kind_curve(table, kind, sign)
    chi2 = ((_unit_noise(vec, sigmas, whiten)[None, :] - _unit_noise(grid_f, sigmas, whiten)) ** 2).sum(axis=1)
    i = int(np.argmin(chi2))
    return float(grid_m[i]), float(chi2[i])


def _kind_curve(table: SignatureTable, kind: str, sign: int) -> tuple[np.ndarray, np.ndarray]:
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


def fit_all(table: SignatureTable, vecs: np.ndarray, sigmas: np.ndarray,
            whiten: np.ndarray | None = None) -> list[dict[str, tuple[float, float]]]:
    """`fit_kind` of every kind for many lenses' feature changes `vecs` (L, n_features) at once: per lens
    {kind: (magnitude, chi2)}. Same arithmetic as fit_kind, one array operation per kind."""
    out: list[dict[str, tuple[float, float]]] = [{} for _ in range(len(vecs))]
    uv = _unit_noise(vecs, sigmas, whiten)
    for kind in table.magnitudes:
        grid_m, grid_f = _kind_curve(table, kind, 0)
        chi2 = ((uv[:, None, :] - _unit_noise(grid_f, sigmas, whiten)[None]) ** 2).sum(axis=2)
        best = np.argmin(chi2, axis=1)
        for q, i in enumerate(best):
            out[q][kind] = (float(grid_m[i]), float(chi2[q, i]))
    return out


def classify(table: SignatureTable, vec: np.ndarray, shift_dir: float, sigmas: np.ndarray,
             fits: dict[str, tuple[float, float]] | None = None, whiten: np.ndarray | None = None):
    """(type, magnitude, unit, direction, alternatives) for one lens' feature changes; `fits`: this lens'
    `fit_all` entry when already computed; `whiten` as in `fit_kind`."""
    fits = fits if fits is not None else {k: fit_kind(table, k, vec, sigmas, whiten=whiten) for k in table.magnitudes}
    best = min(fits, key=lambda k: fits[k][1])
    kind = KIND_BY_NAME[best]
    direction = (shift_dir - table.phi0_deg[best]) % 360.0 if kind.directional else None
    alternatives: tuple = ()
    if best in ("pitch", "decenter") and "pitch" in fits and "decenter" in fits:
        # a white image cannot tell them apart (see the module note): report the pitch reading, list both
        readings = {k: (k, fits[k][0], "µm", (shift_dir - table.phi0_deg[k]) % 360.0) for k in ("pitch", "decenter")}
        return "position", fits["pitch"][0], "µm", readings["pitch"][3], (readings["pitch"], readings["decenter"])
    if not kind.directional and np.any(table.magnitudes[best] < 0) and np.any(table.magnitudes[best] > 0):
        # both signs blur the sub-image: if the other sign fits nearly as well, say so
        other_mag, other_chi2 = fit_kind(table, best, vec, sigmas, sign=-int(np.sign(fits[best][0]) or 1), whiten=whiten)
        if other_chi2 - fits[best][1] < _CHI2_AMBIGUOUS:
            alternatives = ((best, other_mag, kind.unit, None),)
    return best, fits[best][0], kind.unit, direction, alternatives


def tolerance_for(error_type: str, qc: QC) -> float:
    """The QC limit of a type, in its unit (radius errors are relative)."""
    return {"pitch": qc.pitch_um, "position": qc.pitch_um, "decenter": qc.decenter_um, "radius": qc.radius_rel,
            "tilt": qc.tilt_deg, "thickness": qc.thickness_um}.get(error_type, 0.0)


def identify(metrics: LensMetrics, missing: np.ndarray, qc: QC, table: SignatureTable, position=None):
    """Flag, classify and size the defective lenses; returns (defects, flagged mask, type per lens, score).

    `position`: optional (dx, dy) per-lens position residuals measured on this frame (see
    `detection_score`); classification always uses the registration features the table was built with."""
    dev, sig = deviations(metrics)
    rings = ring_noise(metrics)
    score = detection_score(dev, sig, position, focus_score(rings, table))
    threshold = np.full(score.shape, qc.detect_sigma)
    threshold[[0, 0, -1, -1], [0, -1, 0, -1]] *= 1.5  # corner windows hold dark margin on two sides: noisier
    flagged = (score > threshold) | missing
    flagged &= ~spill(score, flagged) | missing
    sigmas = _feature_sigmas(sig)
    error_type = np.full(flagged.shape, "", dtype=object)
    defects = []
    lenses = list(zip(*np.nonzero(flagged & ~missing)))
    features = [_feature_vector(dev, rings, m, n) for m, n in lenses]
    vecs = np.array([f[0] for f in features]) if features else np.zeros((0, len(sigmas) + len(RINGS)))
    fits = dict(zip(lenses, fit_all(table, vecs, sigmas, rings.whiten)))
    shifts = dict(zip(lenses, features))
    for m, n in zip(*np.nonzero(flagged)):
        indexes = metrics.at(m + 1, n + 1)
        if missing[m, n]:
            defects.append(Defect(int(m) + 1, int(n) + 1, "missing", float("nan"), "", None, float("inf"), False, indexes))
            error_type[m, n] = "missing"
            continue
        vec, shift_dir = shifts[(m, n)]
        kind, mag, unit, direction, alts = classify(table, vec, shift_dir, sigmas, fits[(m, n)], rings.whiten)
        limit = tolerance_for(kind, qc)
        defects.append(Defect(int(m) + 1, int(n) + 1, kind, mag, unit, direction, float(score[m, n]),
                              abs(mag) <= limit, indexes, alternatives=alts))
        error_type[m, n] = kind
    return tuple(defects), flagged, error_type, score


__all__ = ["identify", "classify", "deviations", "detection_score", "FEATURES"]
