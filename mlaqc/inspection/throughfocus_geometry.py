"""Where each lens sits in a through-focus pair: fully lit or not, its nearest pinhole, its offset and shell from it."""

from __future__ import annotations

import numpy as np

from mlaqc.optics.config import CameraConfig
from mlaqc.optics.lattice import SQRT3_2, Lattice
from mlaqc.optics.throughfocus import ThroughFocus, pair_radius_lenses, pinhole_lenses

def coverage(cfg: CameraConfig, tf: ThroughFocus) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For a +u / -u pair at tf's offset: per lens (rows, cols) whether it is fully lit in both frames,
    the index of its nearest pinhole (into `pinhole_lenses`) and its (dx, dy) offset from it in lenses."""
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    pins = pinhole_lenses(cfg, tf)
    r_in = pair_radius_lenses(cfg, tf)
    m, n = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    if len(pins) == 0 or r_in < 0:
        z = np.zeros((rows, cols), np.int64)
        return np.zeros((rows, cols), bool), z, np.stack([z, z], axis=-1)
    if cfg.mla.packing == "hex":
        return _hex_coverage(cfg, pins, r_in)
    pr, pc = np.unique(pins[:, 0]), np.unique(pins[:, 1])
    if len(pins) == len(pr) * len(pc) and np.array_equal(pins, np.stack(np.meshgrid(pr, pc, indexing="ij"), -1).reshape(-1, 2)):
        # a lattice (row-major, as pinhole_lenses lists it): the nearest pinhole is the nearest row's and
        # column's (the first of equals, as argmin over all of them would pick)
        ir = np.argmin((np.arange(rows)[:, None] - pr[None, :]) ** 2, axis=1)
        ic = np.argmin((np.arange(cols)[:, None] - pc[None, :]) ** 2, axis=1)
        near = ir[:, None] * len(pc) + ic[None, :]
    else:
        near = np.argmin((m[..., None] - pins[:, 0]) ** 2 + (n[..., None] - pins[:, 1]) ** 2, axis=-1)
    dxy = np.stack([n - pins[near, 1], m - pins[near, 0]], axis=-1)
    lit = dxy[..., 0] ** 2 + dxy[..., 1] ** 2 <= r_in * r_in
    return lit, near, dxy


def _hex_coverage(cfg: CameraConfig, pins: np.ndarray, r_in: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`coverage` on a hex array: each lens' nearest pinhole by the Lattice positions (a k-d tree) and its
    (dx, dy) offset in pitches (float: half pitches along x, sqrt(3)/2 along y); lit within r_in."""
    from scipy.spatial import cKDTree

    lat = Lattice("hex", cfg.mla.count_h, cfg.mla.count_w)
    x, y = lat.centres()
    px, py = lat.position(pins[:, 0], pins[:, 1])
    _, near = cKDTree(np.stack([px, py], axis=1)).query(np.stack([x.ravel(), y.ravel()], axis=1))
    near = near.reshape(x.shape).astype(np.int64)
    dxy = np.stack([x - px[near], y - py[near]], axis=-1)
    lit = shell_of(dxy) <= r_in * r_in + 1e-9
    return lit, near, dxy


def shell_of(dxy: np.ndarray) -> np.ndarray:
    """Each lens' shell: its squared distance from its pinhole in pitches^2, an integer on both lattices
    (square dx^2 + dy^2; hex dq^2 + dr^2 + dq dr: 0, 1, 3, 4, 7, ...)."""
    d2 = dxy[..., 0] ** 2 + dxy[..., 1] ** 2
    return d2 if dxy.dtype.kind in "iu" else np.rint(d2).astype(np.int64)


def offset_classes(dxy: np.ndarray) -> np.ndarray:
    """(L,) integer label of each lens' (dx, dy) offset from its pinhole: lenses at the same offset share
    one (hex offsets are counted in half pitches along x and rows along y)."""
    if dxy.dtype.kind not in "iu":
        dxy = np.stack([np.rint(2.0 * dxy[:, 0]), np.rint(dxy[:, 1] / SQRT3_2)], axis=1).astype(np.int64)
    reach = int(np.abs(dxy).max()) if dxy.size else 0
    return (dxy[:, 1] + reach) * (2 * reach + 1) + (dxy[:, 0] + reach)


__all__ = ["coverage"]
