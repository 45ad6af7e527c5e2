"""The camera packed for the compiled tracer (`mlaqc.optics.raytrace_kernels`): the flat tables and settings
its kernels read, and one batch traced and binned. Kept apart from the kernels so that a change here does
not invalidate Numba's cache of them (keyed on the kernels' own file)."""

from __future__ import annotations

import contextlib
from typing import Iterator

import numpy as np

from mlaqc.compiled import compile_notice
from mlaqc.numba_callee_ir import remembered_callee_irs
from mlaqc.numba_inliner import shared_scope_copies
from mlaqc.numba_liveness import bitset_liveness
from mlaqc.numba_ssa import ssa_skipping_blocks
from mlaqc.numba_typing_memo import remembered_call_types
from mlaqc.optics.scene import FOUR_OVER_PI
from mlaqc.optics.kernel_layout import IMAGE_SIDE, NO_TEXTURE
from mlaqc.optics.kernel_layout import (  # the settings' indices
    S_AX0, S_AY0, S_C1, S_C2, S_CB, S_CBW, S_CC0, S_CLEAR, S_CLEARGAP, S_COLS, S_COUNT, S_CR0, S_FRES, S_GROT, S_H,
    S_HALFBM, S_INVKR, S_INVP, S_INVPIX, S_J0, S_MODE, S_N, S_NMLA, S_P, S_PCOLS, S_PIX, S_PRUNE, S_PX, S_PY, S_R00,
    S_R01, S_R10, S_R11, S_RCIRC2, S_RIM2, S_ROWS, S_RPUPIL, S_SHIFTX, S_SHIFTY, S_SOBOL, S_SQUARE, S_SQW, S_SX0,
    S_SY0, S_T, S_TEXHX, S_TEXHY, S_TEXTURE, S_W, S_X0, S_X1, S_Y0, S_Y1, S_ZEXIT, S_ZFRONT, S_ZMLA, S_ZOBJ,
    S_ZSENS, S_ZSTART)
from mlaqc.optics.raytrace_kernels import AVAILABLE, HEX_DIRS, SQUARE_DIRS, bin_hits, kernel, kernel_sag


def pair_limits(mla) -> np.ndarray:
    """[front / rear, lens k, candidate i]: how far (mm) a point of cell k may lie from k's design centre
    towards candidate i (offset . D_i / p, D_i = c_i - c_k = p times SQUARE_DIRS / HEX_DIRS) with lens k
    still winning against i: Q = |D_i|^2 - 2 offset . D_i clears the pair's bound q
    (MicrolensArray.pair_clearance_mm2) while the projection is <= (|D_i|^2 - q) / 2p. +inf for the cell
    itself and candidates off the array, -inf where the pair's bound fails."""
    dirs = HEX_DIRS if mla.hex else SQUARE_DIRS
    out = []
    for rear in (False, True):
        q = mla.pair_clearance_mm2(rear)
        lim = np.empty_like(q)
        for i, (kc, ok) in enumerate(mla.neighbours(mla.gx, mla.gy)):
            dx, dy = mla.gx[kc] - mla.gx, mla.gy[kc] - mla.gy
            on = ok & (kc != np.arange(kc.size))
            if not np.allclose(np.stack([dx, dy])[:, on] / mla.p, dirs[i][:, None], rtol=0.0, atol=1e-9):
                raise AssertionError("candidate directions do not match the lattice")
            with np.errstate(invalid="ignore"):
                lim[:, i] = np.where(on, (dx * dx + dy * dy - q[:, i]) / (2.0 * mla.p), np.inf)
        out.append(lim)
    return np.ascontiguousarray(np.stack(out))


@contextlib.contextmanager
def _faster_compile() -> Iterator[None]:
    """Numba's front end without its quadratic or repeated work while a tracer variant compiles (the
    numba_* patches; each gives Numba's own result and is in place only where Numba has the shape it
    was written against)."""
    with shared_scope_copies(), bitset_liveness(), ssa_skipping_blocks(), remembered_call_types(), \
            remembered_callee_irs():
        yield


class FastCamera:
    """Packs a `raytrace.Camera` into the flat tables the kernel reads; one per Renderer."""

    def __init__(self, camera, image_region, source_region, texture_half_mm, cells=None) -> None:
        """`cells` (a scene.CellGrid) switches on the low-discrepancy sampler."""
        mla, main, cfg = camera.mla, camera.main, camera.cfg
        self._warm = False  # a batch has run: the kernel variant is compiled (or loaded)
        self.tab = np.ascontiguousarray(np.stack([mla.fx, mla.fy, mla.dx, mla.dy, mla.c1, mla.c2, mla.z_rear]))
        self.margins = (np.ascontiguousarray(np.stack([mla.margin_front, mla.margin_rear, mla.gx, mla.gy]))
                        if mla.sag else None)
        self.lims = pair_limits(mla) if mla.sag else None
        # per-lens tilts: None (not identities) where there are none, a kernel variant without those
        # rotations (they are in most passes); a global rotation is a run-time switch (S_GROT)
        self.rot = np.ascontiguousarray(mla.rot) if mla.tilted else None
        self.grot = np.ascontiguousarray(camera.rot if camera.rotated else np.eye(3), dtype=np.float64)
        self.lat = np.zeros(1) if mla.hex else None  # a marker: hex cells (its value is unused)
        self.circ = (np.ascontiguousarray(np.stack([mla.gx, mla.gy, (mla.r_circle + mla.circle_reach) ** 2,
                                                    mla.circle_clearance_mm()]))
                     if mla.circle else None)  # rows C_GX, C_GY, C_REACH2, C_CLEAR
        s = np.zeros(S_COUNT)
        s[S_C1], s[S_C2], s[S_T], s[S_N], s[S_RIM2] = main.c1, main.c2, main.z2, main.n, main.rim2
        s[S_FRES] = float(cfg.trace.fresnel)
        s[S_ZOBJ] = camera.layout.z_scene_mm
        s[S_TEXHX], s[S_TEXHY] = texture_half_mm
        s[S_P], s[S_AX0], s[S_AY0], s[S_ROWS], s[S_COLS] = mla.p, mla.x0, mla.y0, mla.rows, mla.cols
        s[S_ZFRONT], s[S_NMLA], s[S_CLEAR] = mla.z_front, mla.n, float(mla.clear_corners)
        s[S_HALFBM] = mla.half_black_mm
        s[S_RCIRC2] = mla.r_circle ** 2
        s[S_CLEARGAP] = float(mla.clear_gap)
        s[S_PRUNE] = 1.0  # tests set 0.0: the exhaustive re-trace
        s[S_GROT] = float(camera.rotated)
        s[S_ZMLA], s[S_ZSENS] = camera.z_mla, camera.z_sensor
        s[S_SHIFTX], s[S_SHIFTY] = camera.shift_x, camera.shift_y
        s[S_PIX], s[S_SX0], s[S_SY0], s[S_W], s[S_H] = camera.pixel, camera.sx0, camera.sy0, camera.width, camera.height
        s[S_INVP], s[S_INVPIX] = 1.0 / mla.p, 1.0 / camera.pixel
        if cells is not None:
            s[S_SOBOL], s[S_CB], s[S_CBW] = 1.0, 1.0, 1.0  # point and object-side batches: one "cell"
            s[S_R00], s[S_R01], s[S_R10], s[S_R11] = cells.r00, cells.r01, cells.r10, cells.r11
            self.padded_cols = cells.padded_cols
            rp = image_region.exit_radius_mm
            sq = cells.square_half_mm or rp
            s[S_INVKR], s[S_SQUARE], s[S_SQW] = 1.0 / cells.shift_r_mm, sq, FOUR_OVER_PI * (sq / rp) ** 2
        self.shift_coef = np.asarray(cells.shift_coef if cells is not None else (1.0,) + (0.0,) * 7, dtype=np.float64)
        self.base = s
        self.image_region = image_region
        self.source_region = source_region

    def call(self, mode: int, key: int, n: int, tile=None, point=None, texture=None, cells=None):
        """The kernel of this camera's variant and its arguments for one batch (output arrays included).
        `cells` = (row0, col0, rows, cols, first point) of a stratified image-side job."""
        s = self.base.copy()
        s[S_MODE] = mode
        if cells is not None:
            s[S_CR0], s[S_CC0], bh, s[S_CBW], s[S_J0] = cells
            s[S_CB], s[S_PCOLS] = bh * cells[3], self.padded_cols
        if mode == IMAGE_SIDE:
            s[S_ZSTART], s[S_ZEXIT], s[S_RPUPIL] = self.image_region.z_mla_mm, self.image_region.z_exit_mm, self.image_region.exit_radius_mm
            if point is not None:  # a point's image (ideal main lens): rays from the exit pupil through it
                s[S_ZSTART], tile = s[S_ZOBJ], (point[0], point[0], point[1], point[1])
        else:
            s[S_ZSTART], s[S_RPUPIL] = self.source_region.z_object_mm, self.source_region.pupil_radius_mm
        if tile is not None:
            s[S_X0], s[S_X1], s[S_Y0], s[S_Y1] = tile
        if point is not None:
            s[S_PX], s[S_PY] = point
        s[S_TEXTURE] = float(texture is not None)
        tex = NO_TEXTURE if texture is None else np.ascontiguousarray(texture, dtype=np.float64)
        rows = np.empty(n, np.int32)
        cols = np.empty(n, np.int32)
        w = np.empty(n)
        box = np.array([2 ** 31, -1, 2 ** 31, -1], np.int64)
        args = (s, np.uint64(key), n, self.tab, self.rot, self.grot, tex, self.shift_coef, rows, cols, w, box)
        args += (self.margins, self.lims, self.lat) if self.margins is not None else (self.lat, self.circ)
        return (kernel if self.margins is None else kernel_sag), args

    def trace_hits(self, mode: int, key: int, n: int, tile=None, point=None, texture=None, cells=None):
        """Trace one batch; (row, col, weight) of the rays that reached the sensor and their bounding box."""
        if not AVAILABLE:
            raise RuntimeError("numba is not installed; use the NumPy engine")
        trace, args = self.call(mode, key, n, tile, point, texture, cells)
        if self._warm:
            k = trace(*args)
        else:  # the variant's first batch: a compile on first use is said, not silent
            with compile_notice("the ray tracer"), _faster_compile():
                k = trace(*args)
            self._warm = True
        rows, cols, w, box = args[8:12]
        return rows[:k], cols[:k], w[:k], box

    def trace(self, mode: int, key: int, n: int, tile=None, point=None, texture=None, cells=None):
        """Trace one batch; returns (flat pixel index, weight) of the rays that reached the sensor, in ray order."""
        rows, cols, w, _ = self.trace_hits(mode, key, n, tile, point, texture, cells)
        return rows.astype(np.int64) * int(self.base[S_W]) + cols, w

    def trace_binned(self, mode: int, key: int, n: int, tile=None, point=None, texture=None, cells=None):
        """Trace one batch and sum it per pixel: (row0, col0, patch, hits) over the hits' bounding box."""
        rows, cols, w, box = self.trace_hits(mode, key, n, tile, point, texture, cells)
        patch = bin_hits(rows, cols, w, len(w), box)
        return (int(box[0]), int(box[2]), patch, len(w)) if len(w) else (0, 0, patch, 0)
