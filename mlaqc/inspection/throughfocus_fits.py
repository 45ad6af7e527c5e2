"""Robust statistics and fits of the through-focus readings: shell and class medians, the sub-pixel phase pattern, the smooth field."""

from __future__ import annotations

import numpy as np

MIN_SHELL_LENSES = 5  # a shell's reference needs this many lenses (else the |u| group's median)
PHASE_MIN_LENSES = 12  # the phase-pattern fit needs this many lenses per fitted term


def _robust_sigma(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    if x.size < 2:
        return float("nan")
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def _phase_terms(frac: np.ndarray) -> np.ndarray:
    """First Fourier harmonic of the spots' sub-pixel phases, x and y summed (a symmetric spot samples
    alike along both), for both frames: (L, 4). frac: (L, 4) phases of (+x, +y, -x, -y)."""
    a = 2.0 * np.pi * frac
    return np.stack([np.cos(a[:, 0]) + np.cos(a[:, 1]), np.sin(a[:, 0]) + np.sin(a[:, 1]),
                     np.cos(a[:, 2]) + np.cos(a[:, 3]), np.sin(a[:, 2]) + np.sin(a[:, 3])], axis=1)


def _shell_groups(shell: np.ndarray) -> np.ndarray:
    """Group index per lens: its shell, or one pooled group for shells with fewer than MIN_SHELL_LENSES."""
    _, inv, cnt = np.unique(shell, return_inverse=True, return_counts=True)
    return np.unique(np.where(cnt[inv] >= MIN_SHELL_LENSES, inv, -1), return_inverse=True)[1]


def _group_median(v: np.ndarray, grp: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Per lens the median of v over the lenses of its group where `use` (all of the group if none)."""
    out = np.full(v.shape, np.nan)
    for j in np.unique(grp):
        sel = grp == j
        pick = sel & use
        vals = v[pick] if pick.any() else v[sel & np.isfinite(v)]
        if vals.size:
            out[sel] = np.median(vals)
    return out


def _pattern_fit(resid: np.ndarray, terms: np.ndarray, grp: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The significant part of resid's regression on `terms` (group medians removed from the terms),
    robust (twice more without the values beyond 4 sigma); zeros when there are too few values."""
    ok = np.isfinite(resid)
    if keep.sum() < PHASE_MIN_LENSES * (len(np.unique(grp)) + terms.shape[1]):
        return np.zeros(len(resid))
    centred = terms - np.stack([_group_median(t, grp, keep) for t in terms.T], axis=1)
    coef = np.zeros(terms.shape[1])
    for _ in range(3):
        a = centred[keep]
        if len(a) < terms.shape[1] * PHASE_MIN_LENSES or np.linalg.cond(a) > 1e3:
            return np.zeros(len(resid))
        coef, *_ = np.linalg.lstsq(a, resid[keep], rcond=None)
        r = resid - centred @ coef
        keep = ok & (np.abs(r) <= 4.0 * max(_robust_sigma(r[keep]), 1e-12))
    sig = _robust_sigma(resid[keep] - centred[keep] @ coef) * np.sqrt(np.diag(np.linalg.pinv(centred[keep].T @ centred[keep])))
    coef = np.where(np.abs(coef) > 3.0 * sig, coef, 0.0)
    return terms @ coef


def reference_fit(m2: np.ndarray, shell: np.ndarray, frac: np.ndarray | None,
                  offset: np.ndarray | None = None) -> np.ndarray:
    """D = m2(+) - m2(-) against its typical value, per lens. m2: (L, 2) second moments of the +u and
    -u spots; frac: (L, 4) their sub-pixel phases (+x, +y, -x, -y), or None; offset: what the typical
    lens' D is known to differ by from lens to lens (the field's, `ModelCurves.field_offset`).

    The typical D is the median of the lens' shell (lenses at its distance from their pinhole, all discs
    and pairs of this |u|; shells with fewer than MIN_SHELL_LENSES lenses pooled). Before that, the
    sub-pixel phase pattern of the typical spots is fitted to what the shells leave (the first harmonic
    of each frame's phases, shell means removed from the terms; robust: twice more without the lenses
    beyond 4 sigma, so defective lenses do not bend it) and removed where it is significant. Its
    amplitude depends on the spot's size, and the fit sees two sizes, the typical +u spot and the
    typical -u spot: a lens' spot is corrected with the amplitude of its own size, linearly between the
    two (held beyond them), so a lens whose focal error swaps the two sizes (c near g) gets the other
    frame's pattern."""
    d = m2[:, 0] - m2[:, 1] - (0.0 if offset is None else offset)
    grp = _shell_groups(shell)
    ok = np.isfinite(d)
    resid = d - _group_median(d, grp, ok)
    s0 = max(_robust_sigma(resid[ok]), 1e-12) if ok.sum() >= 2 else np.inf  # a floor: noise-free frames work
    keep = ok & (np.abs(resid) <= 4.0 * s0)
    corrected = d
    if frac is not None and keep.sum() >= PHASE_MIN_LENSES * (len(np.unique(grp)) + 4):
        terms = _phase_terms(frac)  # (L, 4): (+ cos, + sin, - cos, - sin)
        centred = terms - np.stack([_group_median(t, grp, keep) for t in terms.T], axis=1)
        coef = np.zeros(4)
        for _ in range(3):
            a = centred[keep]
            if len(a) < 4 * PHASE_MIN_LENSES or np.linalg.cond(a) > 1e3:  # the phases do not vary independently of the shells: nothing to fit
                coef[:] = 0.0
                break
            coef, *_ = np.linalg.lstsq(a, resid[keep], rcond=None)
            r = resid - centred @ coef
            keep = ok & (np.abs(r) <= 4.0 * max(_robust_sigma(r[keep]), 1e-12))
        # significant (3 sigma of the coefficients) and physical (a pixel-sized spot: <= 0.3 px^2 per frame)
        sig = _robust_sigma(resid[keep] - centred[keep] @ coef) * np.sqrt(np.diag(np.linalg.pinv(centred[keep].T @ centred[keep])))
        coef = np.where((np.abs(coef) > 3.0 * sig) & (np.abs(coef) < 0.3), coef, 0.0)
        amp_p, amp_m = coef[:2], -coef[2:]  # the m2 patterns of the typical +u and -u spots
        size_p, size_m = np.median(m2[keep, 0]), np.median(m2[keep, 1])
        if abs(size_p - size_m) > 1e-6:
            t = np.clip((m2 - size_m) / (size_p - size_m), 0.0, 1.0)  # (L, 2): 0 = the typical -u size
            amp_plus = amp_m[None, :] + t[:, :1] * (amp_p - amp_m)[None, :]
            amp_minus = amp_m[None, :] + t[:, 1:] * (amp_p - amp_m)[None, :]
        else:
            amp_plus, amp_minus = np.broadcast_to(amp_p, (len(d), 2)), np.broadcast_to(amp_m, (len(d), 2))
        corrected = d - (np.sum(amp_plus * terms[:, :2], axis=1) - np.sum(amp_minus * terms[:, 2:], axis=1))
    return corrected - _group_median(corrected, grp, keep)


def _clipped_rms(r: np.ndarray) -> float:
    """RMS of r within 5 robust sigma: the tails of pixel sampling counted, displaced lenses not."""
    r = r[np.isfinite(r)]
    if r.size < 2:
        return float("nan")
    keep = np.abs(r - np.median(r)) <= 5.0 * max(_robust_sigma(r), 1e-12)
    return float(np.sqrt(np.mean(r[keep] ** 2)))


def _least_squares(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin |a x - b| for a tall, well-scaled a (a few columns): the normal equations (SVD-based lstsq
    where they are singular)."""
    try:
        return np.linalg.solve(a.T @ a, a.T @ b)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(a, b, rcond=None)[0]


def _field_removed(v: np.ndarray, xy: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """v minus its robust least-squares fit on a constant per frame (the mask's placement) plus a
    polynomial of the pinhole positions xy (L, 2) common to all frames of this u (the main lens'
    distortion; quadratic, cubic from 200 values): twice more without the values beyond 4 sigma. The
    frames' constants are eliminated first (the polynomial is fitted to values and terms less their
    frame's means, then each constant is its frame's mean residual: the same least squares)."""
    ok = np.isfinite(v)
    if not ok.any():
        return v
    scale = max(float(np.max(np.abs(xy))), 1e-12)  # terms of order 1: the normal equations stay well conditioned
    x, y = xy[:, 0] / scale, xy[:, 1] / scale
    frames, f = np.unique(frame, return_inverse=True)
    nf = len(frames)
    cols = [x, y, x * x, x * y, y * y]
    if ok.sum() >= 200:
        cols += [x ** 3, x * x * y, x * y * y, y ** 3]
    a = np.stack(cols, axis=1)
    vz = np.where(ok, v, 0.0)
    keep = ok.copy()
    out = v - np.median(v[ok])
    for _ in range(3):
        if keep.sum() <= a.shape[1] + nf:
            break
        fk = f[keep]
        n = np.maximum(np.bincount(fk, minlength=nf), 1).astype(np.float64)
        ak = a[keep]
        # each frame's sums of terms and values
        sums = np.stack([np.bincount(fk, weights=c, minlength=nf) for c in (*ak.T, vz[keep])], axis=1)
        am, vm = sums[:, :-1] / n[:, None], sums[:, -1] / n
        beta = _least_squares(ak - am[fk], vz[keep] - vm[fk])
        out = v - (vm - am @ beta)[f] - a @ beta
        keep = ok & (np.abs(out) <= 4.0 * max(_robust_sigma(out[keep]), 1e-12))
    return out


def _class_centred(v: np.ndarray, cls: np.ndarray, min_count: int = MIN_SHELL_LENSES) -> np.ndarray:
    """v minus the median of its class; classes with fewer than `min_count` members become NaN."""
    out = np.full(v.shape, np.nan)
    ok = np.isfinite(v)
    if not ok.any():
        return out
    labels, inv, cnt = np.unique(cls[ok], return_inverse=True, return_counts=True)
    from scipy import ndimage

    med = np.asarray(ndimage.median(v[ok], cls[ok], labels), dtype=np.float64)
    vals = v[ok] - med[inv]
    vals[cnt[inv] < min_count] = np.nan
    out[ok] = vals
    return out


__all__ = ["reference_fit"]
