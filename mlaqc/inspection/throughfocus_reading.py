"""Each lens' radius error read on the model: its D on the traced model of its own spots (`read_traced`) or inverted on the curves."""

from __future__ import annotations

import math

import numpy as np

from mlaqc.inspection import throughfocus_kernels as kern
from mlaqc.inspection.throughfocus_fits import (_class_centred, _field_removed, _group_median, _pattern_fit, _phase_terms,
                                                _robust_sigma, _shell_groups)
from mlaqc.inspection.throughfocus_geometry import offset_classes
from mlaqc.inspection.throughfocus_model import ModelCurves, _cos2, _interp_rows

def _invert(curves: ModelCurves, shell: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """eps with curve_shell(eps) = x (piecewise linear, extended linearly past the ends) and the curve's
    slope there; a shell the model lacks takes the nearest one."""
    return _invert_rows(curves.curves[curves.shell_index(shell)], curves.eps, x)


def _invert_rows(cv: np.ndarray, e: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of cv (L, E), decreasing in e: the e where it crosses x (piecewise linear, the end
    segments extended) and its slope there."""
    seg = np.sum(cv[:, 1:-1] >= x[:, None], axis=1)  # 0 .. E-2
    lo = np.take_along_axis(cv, seg[:, None], 1)[:, 0]
    hi = np.take_along_axis(cv, seg[:, None] + 1, 1)[:, 0]
    slope = (hi - lo) / (e[seg + 1] - e[seg])
    with np.errstate(invalid="ignore", divide="ignore"):
        out = e[seg] + (x - lo) / slope
    return out, slope


def true_phases(pos: np.ndarray, m2: np.ndarray, dxy: np.ndarray, pin_mm: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(L, 4) sub-pixel positions in [0, 1) of the centres of each lens' +u and -u spots (x, y each).

    A spot of a pixel or less is centroided towards its pixel's centre (the sampled centroid locks to
    the pixels), the more the smaller it is, so each frame's own centroid would give the small spots a
    phase pattern of their own. The larger of the lens' two spots is centroided within a few hundredths
    of a pixel (ModelCurves' spots); the other frame's spot sits where the offset between the frames'
    spots puts it: the median of the lenses at the same (dx, dy) from their pinhole plus a smooth
    field and a constant per pair (`_field_removed`), fitted over all lenses, so locking averages out."""
    delta = pos[:, :2] - pos[:, 2:]
    cls = offset_classes(dxy)
    smooth = np.empty_like(delta)
    for j in range(2):
        rest = _field_removed(_class_centred(delta[:, j], cls), pin_mm, frame)
        smooth[:, j] = np.where(np.isfinite(rest), delta[:, j] - rest, delta[:, j])
    plus_big = (m2[:, 0] >= m2[:, 1])[:, None]
    centre_p = np.where(plus_big, pos[:, :2], pos[:, 2:] + smooth)
    centre_m = np.where(plus_big, pos[:, :2] - smooth, pos[:, 2:])
    c = np.concatenate([centre_p, centre_m], axis=1)
    return c - np.floor(c)


def _lens_model_index(curves: ModelCurves, shell: np.ndarray, dxy: np.ndarray, pin_mm: np.ndarray,
                      phases: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each lens' model spots sit in curves.spot_m2 (flattened): (L, 2, 8) indices at eps node 0
    (add node * P * P) and weights (2 field radii x 4 phase neighbours, per frame), and the lens'
    shell index. The model was traced with its field along +x and its lens at (a, b) from the pinhole:
    each lens is mirrored / transposed onto that (its offset from its pinhole; on the disc's centre, its
    field direction), its spots' phases with it."""
    S, R, _, E, P, _ = curves.spot_m2.shape
    k = curves.shell_index(shell)
    v = np.where((curves.offsets[k] == 0).all(axis=1)[:, None], pin_mm, dxy.astype(np.float64))
    sx = np.where(v[:, 0] < 0, -1.0, 1.0)
    sy = np.where(v[:, 1] < 0, -1.0, 1.0)
    swap = np.abs(v[:, 1]) > np.abs(v[:, 0])
    f2 = curves.field_mm ** 2
    r2 = pin_mm[:, 0] ** 2 + pin_mm[:, 1] ** 2
    if R > 1:
        jr = np.clip(np.searchsorted(f2, r2) - 1, 0, R - 2)
        tr = np.clip((r2 - f2[jr]) / (f2[jr + 1] - f2[jr]), 0.0, 1.0)
    else:
        jr, tr = np.zeros(len(k), np.int64), np.zeros(len(k))
    idx = np.zeros((len(k), 2, 8), np.int64)
    wts = np.zeros((len(k), 2, 8))
    for f in range(2):
        px = np.mod(sx * phases[:, 2 * f], 1.0)
        py = np.mod(sy * phases[:, 2 * f + 1], 1.0)
        px, py = np.where(swap, py, px), np.where(swap, px, py)
        ax, ay = px * P, py * P
        x0, y0 = np.floor(ax).astype(np.int64), np.floor(ay).astype(np.int64)
        tx, ty = ax - x0, ay - y0
        c = 0
        for dr, wr in ((0, 1.0 - tr), (1, tr)):
            base = ((k * R + np.minimum(jr + dr, R - 1)) * 2 + f) * E * P * P
            for dy, wy in ((0, 1.0 - ty), (1, ty)):
                for dx, wx in ((0, 1.0 - tx), (1, tx)):
                    idx[:, f, c] = base + ((y0 + dy) % P) * P + (x0 + dx) % P
                    wts[:, f, c] = wr * wy * wx
                    c += 1
    return idx, wts, k


def _lens_model(flat: np.ndarray, idx: np.ndarray, wts: np.ndarray, nodes: np.ndarray, stride: int) -> np.ndarray:
    """(L, K) model D = m2(+u) - m2(-u) of each lens at eps nodes (L, K): its model spots' moments
    (flat[idx + node * stride]) weighted by `wts`, per frame. Compiled: throughfocus_kernels."""
    nodes = np.ascontiguousarray(nodes, dtype=np.int64)
    if len(idx) and (nodes.min() < 0 or idx.max() + nodes.max() * stride >= flat.size or idx.min() < 0):
        raise ValueError("a lens' model index lies outside the model")  # the kernel reads without bounds checks
    out = np.empty(nodes.shape)
    kern.lens_model_kernel(np.ascontiguousarray(flat, dtype=np.float64), np.ascontiguousarray(idx, dtype=np.int64),
                           np.ascontiguousarray(wts, dtype=np.float64), nodes, int(stride), out)
    return out


BRACKET_NODES = 6  # the lens' own model is read this many eps nodes either side of its first reading
SUBSTEPS = 8  # points per node interval at which the lens' likelihood is summed


def read_traced(curves: ModelCurves, m2: np.ndarray, var: np.ndarray, pos: np.ndarray, shell: np.ndarray,
                dxy: np.ndarray, pin_mm: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radius error, its 1-sigma (before the Birge ratio) and D against the lens' own model at eps = 0
    (px^2) of every lens (all pairs of one |u|; `var`: the variance of its D) on the traced model of its
    own spots (ModelCurves.spot_m2).

    D = m2(+) - m2(-) of a lens is modelled as the model's D at its shell, field radius and its spots'
    sub-pixel positions (`true_phases`), plus the field's orientation term for shells off the disc's
    centre (`field_b`, geometric), plus a constant per shell group: the typical lens' offset from the
    model (a defocus common to all lenses: the sensor's distance; what the model leaves out of the
    blur). The constant is the group's median of D less the lens' model at eps = 0; what remains of a
    sub-pixel pattern beyond the model (fitted on the first harmonic of the phases, robustly, as
    `reference_fit` does) is removed; the lens' D is then read on the phase-averaged model curve (the
    first reading), and then on its own curve between BRACKET_NODES nodes either side of that: the mean
    and sd of eps under the likelihood of its D there."""
    S, R, _, E, P, _ = curves.spot_m2.shape
    eps = curves.eps
    zero = int(np.argmin(np.abs(eps)))
    flat = curves.spot_m2.reshape(-1)
    phases = true_phases(pos, m2, dxy, pin_mm, frame)
    idx, wts, k = _lens_model_index(curves, shell, dxy, pin_mm, phases)
    cos_t = np.array([(a * a - b * b) / (a * a + b * b) if a or b else 0.0 for a, b in curves.offsets])
    r2 = pin_mm[:, 0] ** 2 + pin_mm[:, 1] ** 2
    orient = _interp_rows(r2, curves.field_mm ** 2, curves.field_b, k) * (_cos2(dxy, pin_mm) - cos_t[k])
    d = m2[:, 0] - m2[:, 1] - orient
    c0 = _lens_model(flat, idx, wts, np.full((len(d), 1), zero), P * P)[:, 0]
    grp = _shell_groups(shell)
    ok = np.isfinite(d) & np.isfinite(c0)
    y = d - c0
    resid = y - _group_median(y, grp, ok)
    s0 = max(_robust_sigma(resid[ok]), 1e-12) if ok.sum() >= 2 else np.inf
    keep = ok & (np.abs(resid) <= 4.0 * s0)
    y = y - _pattern_fit(resid, _phase_terms(phases), grp, keep)
    y = y - _group_median(y, grp, keep)  # D against the lens' own model at eps = 0
    x = c0 + y
    # the first reading: the phase-averaged model of its shell and field radius
    avg = curves.spot_m2.mean(axis=(-1, -2))  # (S, R, 2, E)
    avg = avg[:, :, 0] - avg[:, :, 1]  # (S, R, E)
    f2 = curves.field_mm ** 2
    if R > 1:
        jr = np.clip(np.searchsorted(f2, r2) - 1, 0, R - 2)
        tr = np.clip((r2 - f2[jr]) / (f2[jr + 1] - f2[jr]), 0.0, 1.0)[:, None]
        cbar = avg[k, jr] * (1.0 - tr) + avg[k, jr + 1] * tr
    else:
        cbar = avg[k, 0]
    first, slope = _invert_rows(cbar - cbar[:, zero:zero + 1], eps, y)
    # then its own: the mean and sd of eps under the likelihood of x on the lens' own curve, between
    # BRACKET_NODES nodes either side of the first reading (the phase pattern cannot move a reading
    # further): where the curve is steep that is its crossing and the noise over the slope; where a
    # pixel-sized spot's moment stalls over a few % of eps at its phase, the reading is honestly vague
    noise = np.sqrt(np.maximum(var, 0.0) + _extra_variance(y, var, keep))
    j0 = np.clip(np.searchsorted(eps, np.where(np.isfinite(first), first, 0.0)), BRACKET_NODES,
                 E - 1 - BRACKET_NODES)
    nodes = j0[:, None] + np.arange(-BRACKET_NODES, BRACKET_NODES + 1)[None, :]
    own, own_sd = _likelihood_mean(_lens_model(flat, idx, wts, nodes, P * P), eps[nodes], x, noise)
    inside = np.isfinite(own) & (first >= eps[0]) & (first <= eps[-1])  # beyond the model: the first reading
    out = np.where(inside, own, first)
    sigma = np.where(inside, own_sd, noise / np.abs(slope))
    return out, sigma, y


def _extra_variance(y: np.ndarray, var: np.ndarray, keep: np.ndarray) -> float:
    """What the typical lenses' scatter about their own models holds beyond their quoted noise (px^4):
    the robust variance of y over `keep` less the median quoted variance, never below 0."""
    if keep.sum() < 20:
        return 0.0
    return max(_robust_sigma(y[keep]) ** 2 - float(np.median(var[keep])), 0.0)


def _likelihood_mean(cv: np.ndarray, e: np.ndarray, x: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and sd of e under exp(-(c(e) - x)^2 / 2 noise^2), c the piecewise-linear curve through the
    nodes (cv, e) (L, K) of each row (e equally spaced along a row), summed at SUBSTEPS points per
    interval (flat prior on the span). Compiled: throughfocus_kernels.likelihood_kernel."""
    L = len(cv)
    m1, var = np.empty(L), np.empty(L)
    kern.likelihood_kernel(np.ascontiguousarray(cv, dtype=np.float64), np.ascontiguousarray(x, dtype=np.float64),
                           np.ascontiguousarray(noise, dtype=np.float64), SUBSTEPS, m1, var)
    step = (e[:, 1] - e[:, 0]) / SUBSTEPS
    sd = np.sqrt(np.maximum(var, 0.0)) * step
    return e[:, 0] + m1 * step, np.maximum(sd, step / math.sqrt(12.0))


__all__ = ["read_traced", "true_phases"]
