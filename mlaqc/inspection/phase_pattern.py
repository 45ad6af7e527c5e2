"""The sub-pixel phase pattern: what the sub-pixel phase of the lens centres draws in every index map, a
property of the frame that identification (mlaqc.inspection.identify) models and removes, never flags.

A sub-image that differs from the reference in profile (another rim blur, diffraction, pixel MTF) is
registered and indexed with a small error that depends on where it falls on the pixel grid; over a rotated
or non-integer-pitch grid that error draws a pattern across the array which the local median cannot
remove. Per lens group (`lens_classes._groups`: the inner lenses, the edge classes per side, the second
ring and hex row ends where they have their own) it is fitted on Fourier terms of the phase (`phase_basis`,
`PhaseModel`, built once per grid), robustly, and taken off the deviations (`remove_phase_pattern`) and off
the local baselines' trend (`remove_phase_trend`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from mlaqc.inspection.lens_classes import _groups
from mlaqc.inspection.medians import column_medians


def phase_basis(phase_x: np.ndarray, phase_y: np.ndarray, harmonics: int = 2) -> np.ndarray:
    """Fourier basis (…, terms) of a lens' sub-pixel phase (fractional part of its grid centre, x and y):
    how a sub-image samples the pixel grid, the source of index patterns that beat with the pitch."""
    terms = [np.ones_like(phase_x)]
    for k in range(1, harmonics + 1):
        for a in (phase_x, phase_y):
            terms += [np.cos(2 * np.pi * k * a), np.sin(2 * np.pi * k * a)]
    if harmonics > 1:
        for a in (phase_x + phase_y, phase_x - phase_y):
            terms += [np.cos(2 * np.pi * a), np.sin(2 * np.pi * a)]
    return np.stack(terms, axis=-1)


@dataclass(frozen=True)
class PhaseModel:
    """The sub-pixel phase basis of every lens group (`_groups`), built once per frame and shared by all
    the index maps it is fitted to: per group its mask, basis (n, P) and the sum of the basis' outer
    products over its lenses (P², the Gram matrix when no lens is left out)."""

    groups: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]


_PHASE_MODELS: dict[bytes, PhaseModel] = {}


def phase_model(phase: tuple[np.ndarray, np.ndarray], packing: str = "square", centred: bool = False) -> PhaseModel:
    """`PhaseModel` of lenses whose grid centres have sub-pixel phases `phase` (x, y); a group gets two
    harmonics from 80 lenses on, one from 40, none below (too few lenses to fit it). Kept for the last
    few grids: a batch on one saved grid builds it once. `packing`, `centred`: the lattice and the
    baselines' windows (`_groups`)."""
    key = hashlib.sha1(np.ascontiguousarray(phase[0]).tobytes() + np.ascontiguousarray(phase[1]).tobytes()
                       + packing.encode() + bytes([centred])).digest()
    hit = _PHASE_MODELS.get(key)
    if hit is not None:
        return hit
    groups = []
    for sel in _groups(phase[0].shape, packing, centred):
        count = int(sel.sum())
        harmonics = 2 if count >= 80 else 1 if count >= 40 else 0
        if harmonics:
            basis = phase_basis(phase[0][sel], phase[1][sel], harmonics)
            groups.append((sel, basis, _outer_sum(basis)))
    if len(_PHASE_MODELS) >= 4:
        _PHASE_MODELS.pop(next(iter(_PHASE_MODELS)))
    model = _PHASE_MODELS[key] = PhaseModel(tuple(groups))
    return model


def _outer(basis: np.ndarray) -> np.ndarray:
    """Each lens' outer product of its basis row with itself, (n, P²)."""
    n, p = basis.shape
    return (basis[:, :, None] * basis[:, None, :]).reshape(n, p * p)


def _outer_sum(basis: np.ndarray, block: int = 2048) -> np.ndarray:
    """`_outer(basis).sum(axis=0)` to the bit (NumPy adds the rows of an axis-0 sum one after another, so
    each block's sum starts from the total so far: a row of its own), a block of lenses at a time: a
    large group's products are 30 MB, which a fresh process pays for in page faults."""
    total = None
    for a in range(0, len(basis), block):
        part = _outer(basis[a:a + block])
        total = part.sum(axis=0) if total is None else np.concatenate([total[None], part]).sum(axis=0)
    return total


def remove_phase_pattern(planes: list[np.ndarray], model: PhaseModel,
                         exclude: np.ndarray | None = None) -> list[np.ndarray]:
    """Deviation maps minus their fitted dependence on sub-pixel phase, per lens group.

    A sub-image that differs from the reference in profile (another rim blur, diffraction, pixel MTF)
    is registered and indexed with a small error that depends on where it falls on the pixel grid; over
    a rotated or non-integer-pitch grid that error draws a pattern across the array which the local
    median cannot remove. It is a property of the frame, not of a lens: it is fitted (Fourier terms of
    the phase, robustly: outliers beyond 4 sigma left out, so a defect does not bend the fit) and removed.
    `exclude`: lenses also left out of the fit (a defect's neighbours, within 4 sigma but not noise),
    as `_phase_skips` says."""
    stack = np.stack(planes, axis=-1).astype(np.float64)  # (rows, cols, J)
    for (sel, basis, full), skip in zip(model.groups, _phase_skips(model, exclude)):
        stack[sel] = _phase_fit(stack[sel], basis, full, skip)
    return [stack[..., j] for j in range(len(planes))]


def _phase_skips(model: PhaseModel, exclude: np.ndarray | None) -> list[np.ndarray | None]:
    """Per lens group, the lenses of `exclude` its phase fit leaves out: where they are at least 5 % of
    the group (a small array's: fewer hardly bend a robust fit, which leaves the strongest out anyway,
    and refitting a large array moved readings at the reportable size, -2.07 % to -1.99 %) and at least
    four lenses per fitted term are left; else None (all lenses fitted)."""
    skips: list[np.ndarray | None] = []
    for sel, basis, _ in model.groups:
        skip = exclude[sel] if exclude is not None else None
        if skip is not None and not (skip.sum() >= 0.05 * len(skip) and (~skip).sum() >= 4 * basis.shape[1]):
            skip = None
        skips.append(skip)
    return skips


def remove_phase_trend(planes: list[np.ndarray], model: PhaseModel) -> list[np.ndarray]:
    """Smooth maps (local baselines) minus their plain least-squares fit on each group's phase basis:
    a 5 x 5 median keeps the phase pattern, which beats with the pitch over ~20 lenses. No outlier pass:
    a median baseline has none."""
    stack = np.stack(planes, axis=-1).astype(np.float64)
    for sel, basis, full in model.groups:
        y = stack[sel]
        p = basis.shape[1]
        coef = np.linalg.solve(full.reshape(p, p) + 1e-9 * np.eye(p), basis.T @ np.where(np.isfinite(y), y, 0.0))
        stack[sel] = y - basis @ coef
    return [stack[..., j] for j in range(len(planes))]


def _phase_fit(y: np.ndarray, basis: np.ndarray, full: np.ndarray, skip: np.ndarray | None = None) -> np.ndarray:
    """Columns of y (n, J) minus their robust least-squares fit on `basis` (n, P), all columns at once:
    a fit on the finite values, then a refit without those beyond 4 robust sigma of the first. Each
    column's Gram matrix is the full one (`full`, the summed `_outer`) less the few lenses it leaves out;
    `skip` (n,): lenses never fitted (their residuals are still returned)."""
    p = basis.shape[1]
    fit = np.isfinite(y) if skip is None else np.isfinite(y) & ~skip[:, None]
    keep = fit
    y0 = np.where(keep, y, 0.0)
    resid = y
    for step in range(2):
        left_out = ~keep
        rows = np.flatnonzero(left_out.any(axis=1))
        gram = np.broadcast_to(full, (y.shape[1], p * p)) - left_out[rows].T.astype(np.float64) @ _outer(basis[rows])
        gram = gram.reshape(-1, p, p) + 1e-9 * np.eye(p)
        coef = np.linalg.solve(gram, (np.where(keep, y0, 0.0).T @ basis)[..., None])[..., 0]
        coef[keep.sum(axis=0) < 2 * p] = 0.0
        resid = y - basis @ coef.T
        if step == 0:  # every column's robust sigma at once (from at most ~2,000 lenses: enough for a 4-sigma cut)
            sample = (resid if skip is None else np.where(fit, resid, np.nan))[:: max(1, len(resid) // 2000)]
            mad = column_medians(np.abs(sample - column_medians(sample)))
            with np.errstate(invalid="ignore"):
                keep = fit & (np.abs(resid) <= 4 * np.maximum(1.4826 * mad, 1e-9))
    return resid
