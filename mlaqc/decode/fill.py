"""Refilling lenses that carry no usable light field (missing, obscured, a focal error that blurred away
their angular detail) from their neighbours on the array's lattice (square or hex, before a hex array is
resampled): along the scene's parallax where the neighbours agree on one, else each view from the
neighbours' same view. Vectorized over the lenses refilled (a few), a loop over neighbours and candidate
slopes only."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mlaqc.decode.lightfield import LightField, _expand
from mlaqc.optics.lattice import SQRT3_2

# a refill of a lens that has light of its own (a focal error blurs its views but keeps their mean) must
# keep that mean to this share of it (or of the light field's mean level, for a dark lens)
OWN_LIGHT_TOL = 0.1
# relative mismatch a slope's shifted neighbours must beat the unshifted ones by to be used: a scene with
# no detail, or in focus on the MLA, agrees at every slope and keeps the plain mean
PARALLAX_GAIN = 0.8
MIN_VIEWS = 9  # views a slope's shifted neighbours must all reach for it to be judged


def filled(lf: LightField, below: float = 0.5, lenses: np.ndarray | None = None) -> LightField:
    """Lenses whose weight is under `below` in every view refilled from their neighbours, and the samples
    dropped as another lens' light (`lf.foreign`) likewise; with `lenses` ((rows, cols) bool: the
    sampling's `inside`), only those (a lens the frame does not hold is not extrapolated).

    A scene off the plane the MLA sees in focus moves across the lenses from view to view (parallax): what
    a lens sees in view u, its neighbour one pitch along x sees in view u + 1/slope (`refocus`'s
    convention). The nearest neighbours' views are shifted along each candidate slope and the one they
    agree on best is used, so the lens gets its own view of the scene, not a spatial blur of its
    neighbours'; where they agree best with no shift, or the shifted views do not reach a view, the
    weighted mean of the neighbours in that view is used (square: the eight around it, hex: the six). A
    lens with light of its own keeps its views when neither refill keeps their mean (a focal error blurs
    them but keeps it). A refilled sample's weight becomes half the neighbours' mean weight; samples no
    neighbour can supply, and every other lens, are left as they were."""
    w = lf.weights.astype(np.float64)
    vals = lf.values.astype(np.float64)
    good = np.where(w >= below, w, 0.0)
    hex_ = lf.packing == "hex"
    whole = w.max(axis=(0, 1)) < below
    holed = np.zeros_like(whole) if lf.foreign is None else lf.foreign.any(axis=(0, 1))
    doubted = np.argwhere((whole | holed) & (True if lenses is None else lenses))
    if not len(doubted):
        return lf
    t, s = doubted[:, 0], doubted[:, 1]
    around = [_gather(vals, good, tn, sn) for tn, sn, _, _ in _neighbours(hex_, t, s, *w.shape[2:], diagonal=True)]
    num = sum(_expand(g, v) * v for v, g in around)
    den = sum(g for _, g in around)
    own, own_w = vals[:, :, t, s], w[:, :, t, s]
    reach = den > 0
    plain = np.where(_expand(reach, own), num / np.where(_expand(den, own) > 0, _expand(den, own), 1.0), own)
    along = plain
    if len(lf.view_offsets_px) > 2:
        pred, ok = _along_parallax(vals, good, _neighbours(hex_, t, s, *w.shape[2:], diagonal=False))
        along = np.where(_expand(ok, plain), pred, plain)
    lit = np.abs(vals[np.broadcast_to(_expand(good > 0, vals), vals.shape)])
    lit = lit[np.isfinite(lit)]
    level = float(lit.mean()) if lit.size else 0.0  # the light field's mean level, what a dark lens is told by
    use_along, use_plain = (_keeps_own_light(x, own, own_w, level) for x in (along, plain))
    keep_own = (~use_along & ~use_plain)[None, None] | ~reach
    refill = np.where(_expand(use_along[None, None], along), along, plain)
    if lf.foreign is not None:  # a lens with light of its own: only its foreign samples take the refill
        part = ~whole[t, s][None, None]
        keep_own = np.where(part, ~lf.foreign[:, :, t, s] | ~reach, keep_own)
        refill = np.where(_expand(part, refill), along, refill)
    new_vals, new_w = vals.copy(), w.copy()
    new_vals[:, :, t, s] = np.where(_expand(keep_own, own), own, refill)
    new_w[:, :, t, s] = np.where(keep_own, own_w, 0.5 * den / len(around))
    foreign = None if lf.foreign is None else lf.foreign & (new_w == 0)  # those no neighbour could refill
    return replace(lf, values=new_vals.astype(np.float32), weights=new_w.astype(np.float32), foreign=foreign)


def _neighbours(hex_: bool, t: np.ndarray, s: np.ndarray, rows: int, cols: int, diagonal: bool):
    """Lenses (t, s)' nearest neighbours on the lattice: a list of (row, col, dx, dy), the last two the
    neighbour's offset in pitches (x right, y down), rows and columns possibly off the array. Square: the
    four along the axes (and the four diagonal ones with `diagonal`); hex (0-based odd rows shifted half a
    pitch right, rows sqrt(3)/2 apart): the six."""
    if not hex_:
        steps = [(0, 1), (0, -1), (1, 0), (-1, 0)] + ([(1, 1), (1, -1), (-1, 1), (-1, -1)] if diagonal else [])
        return [(t + dt, s + ds, float(ds), float(dt)) for dt, ds in steps]
    odd = (t % 2).astype(t.dtype)  # a shifted row's neighbours above and below are at s and s + 1
    out = [(t, s + 1, 1.0, 0.0), (t, s - 1, -1.0, 0.0)]
    for dt in (1, -1):
        out += [(t + dt, s - 1 + odd, -0.5, dt * SQRT3_2), (t + dt, s + odd, 0.5, dt * SQRT3_2)]
    return out


def _gather(vals: np.ndarray, good: np.ndarray, tn: np.ndarray, sn: np.ndarray):
    """Lenses (tn, sn)'s views and good weights, weight 0 where the lens is off the array."""
    rows, cols = good.shape[2:]
    inside = (tn >= 0) & (tn < rows) & (sn >= 0) & (sn < cols)
    tc, sc = np.clip(tn, 0, rows - 1), np.clip(sn, 0, cols - 1)
    return vals[:, :, tc, sc], np.where(inside[None, None], good[:, :, tc, sc], 0.0)


def _keeps_own_light(refill: np.ndarray, own: np.ndarray, own_w: np.ndarray, level: float) -> np.ndarray:
    """Per lens refilled: True where it has no light field of its own to check against (missing: weight 0
    in most views), or where `refill`'s mean over its own views is its own mean to OWN_LIGHT_TOL."""
    seen = own_w > 0
    n = seen.sum(axis=(0, 1))
    has_own = n >= 0.5 * seen.shape[0] * seen.shape[1] * np.pi / 4  # most of the pupil's views
    sx = _expand(seen, own)
    m_own = np.where(sx, own, 0.0).sum(axis=(0, 1)) / np.maximum(_expand(n, own[0, 0]), 1)
    m_refill = np.where(sx, refill, 0.0).sum(axis=(0, 1)) / np.maximum(_expand(n, own[0, 0]), 1)
    close = np.abs(m_refill - m_own) <= OWN_LIGHT_TOL * np.maximum(np.abs(m_own), level)
    if close.ndim == 2:
        close = close.all(axis=-1)
    return ~has_own | close


def _along_parallax(vals: np.ndarray, good: np.ndarray, around: list):
    """The lenses' views predicted from their `around` neighbours' views shifted along the slope (one per
    lens) on which those predictions agree best: (values (nv, nu, k[, c]), where predicted (nv, nu, k)).
    A coarse search over shifts of 1 to 2 x the view radius a pitch, then a fine one around each lens' best."""
    nv = good.shape[0]
    k = len(around[0][0])
    centre = good[nv // 2, good.shape[1] // 2][None, None]  # the central view: whether a neighbour has light
    usable = sum(_gather(centre, centre, tn, sn)[1][0, 0] > 0 for tn, sn, _, _ in around)
    plain_err, _, _ = _agreement(vals, good, around, np.zeros(k), usable)
    coarse = np.geomspace(1.0, nv - 1.0, 24)  # view px per pitch
    best = (np.full(k, np.inf), np.zeros(k), None, None)  # error, shift, values, where predicted
    for d in np.concatenate([-coarse[::-1], coarse]):
        best = _keep_better(best, vals, good, around, np.full(k, d), usable)
    for f in np.linspace(0.9, 1.1, 11):
        best = _keep_better(best, vals, good, around, best[1] * f, usable)
    err, _, values, ok = best
    return values, ok & (err < PARALLAX_GAIN * plain_err)[None, None]


def _keep_better(best, vals, good, around, shift, usable):
    """`best` (error, shift, values, where predicted) updated, lens by lens, by the candidate `shift`."""
    err, values, ok = _agreement(vals, good, around, shift, usable)
    b_err, b_shift, b_values, b_ok = best
    if b_values is None:
        b_values, b_ok = np.zeros_like(values), np.zeros_like(ok)
    better = err < b_err
    return (np.where(better, err, b_err), np.where(better, shift, b_shift),
            np.where(_expand(better[None, None], values), values, b_values), np.where(better[None, None], ok, b_ok))


def _agreement(vals, good, around, shift, usable):
    """How well the neighbours, their views moved `shift` view px per pitch of their offset (0: not moved),
    agree on the lenses' views: (mismatch relative to the light compared, inf where they cannot be compared;
    their mean (nv, nu, k[, c]); views at least one predicts (nv, nu, k))."""
    preds, oks = zip(*(_shifted_neighbour(vals, good, tn, sn, shift * dy, shift * dx) for tn, sn, dx, dy in around))
    p, ok = np.stack(preds), np.stack(oks)  # (K, nv, nu, k[, c])
    n = ok.sum(axis=0)
    okx = _expand(ok, p)
    mean = np.where(okx, p, 0.0).sum(axis=0) / np.maximum(_expand(n, p[0]), 1)
    dev = np.where(okx, (p - mean[None]) ** 2, 0.0).sum(axis=0)
    energy = mean * mean
    if dev.ndim == 4:
        dev, energy = dev.mean(axis=-1), energy.mean(axis=-1)
    # compared where every neighbour that has a light field predicts (fewer would agree more easily), and
    # relative to the light compared: views where the neighbours see nothing say nothing
    every = (n == usable[None, None]) & (usable[None, None] >= 2)
    cover = every.sum(axis=(0, 1))
    spread = np.where(every, dev, 0.0).sum(axis=(0, 1))
    energy = np.where(every, energy, 0.0).sum(axis=(0, 1))
    err = np.where((cover >= MIN_VIEWS) & (energy > 0), spread / np.where(energy > 0, energy, 1.0), np.inf)
    return err, mean, n >= 1


def _shifted_neighbour(vals, good, tn, sn, dv, du):
    """Lenses (tn, sn)'s views moved by (dv, du) view pixels (one move per lens; bilinear in the view), and
    where they are defined: (values (nv, nu, k[, c]), ok (nv, nu, k))."""
    nv, nu, rows, cols = good.shape
    inside = (tn >= 0) & (tn < rows) & (sn >= 0) & (sn < cols)
    tn, sn = np.clip(tn, 0, rows - 1), np.clip(sn, 0, cols - 1)
    j = np.arange(nv, dtype=np.float64)[:, None, None] + dv[None, None, :] + np.zeros((1, nu, 1))
    i = np.arange(nu, dtype=np.float64)[None, :, None] + du[None, None, :] + np.zeros((nv, 1, 1))
    j0, i0 = np.floor(j), np.floor(i)
    fj, fi = j - j0, i - i0
    ok = (j0 >= 0) & (j0 + (fj > 0) <= nv - 1) & (i0 >= 0) & (i0 + (fi > 0) <= nu - 1) & inside[None, None]
    j0 = np.clip(j0, 0, nv - 1).astype(np.intp)
    i0 = np.clip(i0, 0, nu - 1).astype(np.intp)
    j1, i1 = np.minimum(j0 + 1, nv - 1), np.minimum(i0 + 1, nu - 1)
    out = 0.0
    for jj, ii, wgt in ((j0, i0, (1 - fj) * (1 - fi)), (j0, i1, (1 - fj) * fi), (j1, i0, fj * (1 - fi)), (j1, i1, fj * fi)):
        ok &= (good[jj, ii, tn, sn] > 0) | (wgt == 0)
        v = vals[jj, ii, tn, sn]
        out = out + v * _expand(wgt, v)
    return out, ok
