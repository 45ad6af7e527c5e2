"""The per-lens measurement of the calibration (mlaqc.inspection.calibrate): every sub-image's centre,
radius and amplitude from one joint fit of the white frame by a sum of discs (`_measure`, `_DiscFit`),
and the lattice bookkeeping it sweeps by (`_colours`, `_lattice_neighbours`). Kept on its own so the fit
can be worked on without the lattice finding, indexing and grid model round it; it takes the lattice
positions to start from and returns what it found per position (`_Discs`).

Every sub-image is measured by a joint least-squares fit of the frame by a sum of discs, one per lens:
lens k adds (a_k + slope . (x - c_k)) * e((R_k - |x - c_k|) / s) to the model, e a logistic edge.
Gauss-Newton on (a_k, c_k, R_k) of all lenses at once: one compiled pass per lens
(mlaqc.inspection.calibrate_kernels) builds its normal equations straight from the frame, evaluating its own
disc and its lattice neighbours' where they reach its pixels (no frame-sized model, no scatter; hex: the
neighbours' discs in long vectorized runs, `HALVES_ORDER`), blocks of lenses on a thread pool.
Why not a thresholded centre of gravity: in the f-number-matched camera the sub-images touch and even
overlap (radius 10.2 px at a 20.05 px pitch), so a cell-window centroid is governed by where the window
is put, not by the lens (it even moves the wrong way). The position information sits in each disc's
rim; the joint model separates a lens' rim from its neighbours' in the overlap zones, so a shifted
lens reads its full shift and its neighbours read ~2 % of it. Details that matter:
- each lens is fitted on an annulus round its rim, tapered and centred on its current estimate (a
  window fixed to the pixel grid would pull a not-yet-right model off centre); its amplitude on its
  plateau too (the pixels well inside, clear of its neighbours' light): on the rim alone amplitude and
  radius trade off, and a photon-starved frame (~1 photon per pixel) sent them oscillating until
  healthy lenses read as missing;
- red-black sweeps (hex: three colours, (j + 2 i) mod 3): side neighbours (whose discs overlap) never
  step together;
- noise weights ~ 1 / signal (Monte-Carlo and photon noise), except round lenses far off the lattice;
- intensity slopes across each sub-image (illumination falloff, vignetting) come from the smooth
  field of the lens amplitudes (a plane through the 5 x 5 lenses round each: a neighbour pair's
  difference put its amplitudes' noise into every centre, 2 % of their spread at 15 % noise) and are
  held fixed (fitting them per lens costs precision);
- the edge width and typical radius come from a central block first; lenses the sharp edge cannot
  pull in (more than ~1.5 px off the lattice) are captured with a wide edge of their own, then they
  and their neighbours are fitted again with the sharp one;
- pixels outside the frame are simply left out, so lenses cut by the frame are measured unbiased;
- the first weighted sweep is not damped as an oscillation (it answers a new objective), so three
  sweeps settle nearly every lens;
- the model has no background term: where the cell corners, well clear of the fitted rims, hold over
  15 % of the sub-images' light (clear gaps between circular lenses, a low black level), the calibration
  takes a smooth surface through them off and measures every lens again (its `_without_background`).

Pixel conventions as mlaqc.inspection.grid's.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from mlaqc.errors import InputError
from mlaqc.inspection import calibrate_kernels as kernels
from mlaqc.parallel import thread_map

# Thresholds (relative units unless stated).
MIN_VALID_FRACTION = 0.35  # lenses with less of their rim than this inside the frame are not measured
MIN_LENSES = 9

# The disc fit (see _measure). Lengths in pixels.
BLOCK_SWEEPS = 5  # sweeps on the central block that sets the edge width and typical radius
SUBSET = 16  # that block is SUBSET x SUBSET lenses
N_SWEEPS = 3  # sweeps over every lens (the first unweighted)
MAX_EXTRA = 10  # more sweeps, for the lenses not yet settled and their neighbours only
SETTLED_PX = 0.02  # a lens has settled when its step is under this
BAND = 1.5  # each lens is fitted on |r - R| <= BAND (+ a 0.5 px taper) round its rim
SLOPE_REACH = 2  # a lens' intensity slope: the plane through the amplitudes of the 5 x 5 lenses round it
PLATEAU_EDGES = 3.0  # its amplitude on its plateau too: the pixels this many edge widths inside the band
WEIGHT_FLOOR = 0.05  # noise weights ~ 1 / signal, the signal floored at this fraction of the plateau
COUPLED_PX = 0.3  # lenses this far off the lattice, and their neighbours, are fitted unweighted
WIDE_EDGE = 1.0  # lenses the sharp edge cannot capture get an edge at least this wide for a while
N_LENS_PARAMS = 4  # amplitude, centre x, centre y, radius
BLOCK_LENSES = 512  # lenses per work block of the thread pool
# the disc kernel's pixel order (calibrate_kernels.disc_normals' `halves`): the neighbours' discs on the vector
# units, summed in another order. Hex: its six side neighbours' discs are most of the work (the kernel 40 %
# faster). Square keeps its span order and so its results to the last bit (`halves` would make its
# calibration 26 % faster, its centres moving by < 1e-4 px)
HALVES_ORDER = {"square": False, "hex": True}


# --------------------------------------------------------------------------------------- disc fitting


def _workers() -> int:
    return max(1, min(4, os.cpu_count() or 1))


@dataclass
class _Discs:
    """What the disc fit found, per candidate lattice position."""

    cx: np.ndarray
    cy: np.ndarray
    amp: np.ndarray
    radius: np.ndarray
    edge: float
    valid_fraction: np.ndarray


def _disc_offsets(reach: float, inner: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    hw = int(math.ceil(reach))
    dy, dx = np.mgrid[-hw:hw + 1, -hw:hw + 1]
    r = np.hypot(dx, dy)
    keep = (r <= reach) & (r >= inner)
    return dy[keep].astype(np.int32), dx[keep].astype(np.int32)


class _DiscFit:
    """Joint fit of the frame by one logistic-edged disc per lens (see the module docstring).

    Each lens is fitted on the pixels of an annulus about its current rim (the plateau inside carries no
    position information). The model on those pixels is the lens' own disc plus the discs of its lattice
    neighbours that reach them, evaluated afresh from the current parameters in one compiled pass per
    lens (mlaqc.inspection.calibrate_kernels), so overlapping neighbours are accounted for without a frame-sized
    model. Blocks of lenses run on a thread pool (the kernel releases the GIL).
    """

    def __init__(self, img: np.ndarray, cx: np.ndarray, cy: np.ndarray, radius0: float,
                 neighbours: np.ndarray, colour: np.ndarray | None = None, halves: bool = False,
                 spacing_px: float = math.inf) -> None:
        self.img = img
        self.spacing_px = spacing_px  # between nearest lattice neighbours: bounds the plateau clear of their light
        self.halves = halves  # the kernel's pixel order for vectorized neighbour discs (hex; see disc_normals)
        self.h, self.w = img.shape
        self.cx, self.cy = cx.astype(np.float64).copy(), cy.astype(np.float64).copy()
        self.n = cx.size
        self.radius = np.full(self.n, radius0)
        self.edge = 0.8
        self.amp = np.zeros(self.n)
        self.slope_x = np.zeros(self.n)  # plateau level change per radius, x and y
        self.slope_y = np.zeros(self.n)
        self.r_norm = float(radius0)
        self.band = BAND
        self.neighbours = np.ascontiguousarray(neighbours, dtype=np.int64)
        self.prev_step = np.zeros((self.n, N_LENS_PARAMS))
        self.last_step = np.zeros(self.n)
        self.rss = np.zeros(self.n)
        self.npix = np.zeros(self.n, np.int64)
        self.valid_fraction = np.ones(self.n)
        self.colour = np.zeros(self.n, np.int8) if colour is None else colour.astype(np.int8)
        if np.any(np.diff(self.colour) < 0):
            raise ValueError("lenses must be sorted by colour")
        self.n_red = int(np.count_nonzero(self.colour == 0))
        self.n_colours = max(2, int(self.colour.max()) + 1) if self.n else 2
        self.coupled = np.zeros(self.n, bool)  # lenses next to (or being) a lens far off the lattice
        self.wide = None  # lenses fitted with a wide edge (capture of far-off lenses)
        self.wide_edge = 1.0
        self.workers = min(_workers(), -(-self.n // 16))

    def _map(self, fn, lenses: np.ndarray) -> None:
        """fn(block) over blocks of `lenses` (an index array), on the process' pool: a multiple of the
        worker count of equal blocks (small sets are split too), so the workers finish together."""
        n_blocks = self.workers * -(-lenses.size // (self.workers * BLOCK_LENSES))
        size = max(16, -(-lenses.size // max(n_blocks, 1)))
        blocks = [slice(b, min(b + size, lenses.size)) for b in range(0, lenses.size, size)]
        if self.workers > 1:
            thread_map(fn, blocks)
        else:
            for b in blocks:
                fn(b)

    def set_band(self, band: float) -> None:
        """Fit each lens on |r - R| <= band (+ a 0.5 px taper); note how much of each rim is in the frame."""
        self.band = band
        self.valid_fraction = self.rim_in_frame()

    def rim_in_frame(self) -> np.ndarray:
        """Fraction of each sub-image's rim (|r - R| <= 1 px about its rounded centre) inside the frame."""
        out = np.ones(self.n)
        r0 = float(np.median(self.radius))
        dy, dx = _disc_offsets(r0 + 1.0, max(0.0, r0 - 1.0))
        gx, gy = np.rint(self.cx).astype(np.int64), np.rint(self.cy).astype(np.int64)
        hw = math.ceil(r0 + 1.0)
        edge = np.flatnonzero((gx - hw < 0) | (gx + hw >= self.w) | (gy - hw < 0) | (gy + hw >= self.h))
        if edge.size:
            iy, ix = gy[edge, None] + dy[None, :], gx[edge, None] + dx[None, :]
            out[edge] = ((iy >= 0) & (iy < self.h) & (ix >= 0) & (ix < self.w)).mean(axis=1)
        return out

    def init_amplitude(self, radius: float) -> None:
        """Amplitude guess: the mean level of the pixels well inside each lens' disc (0 off the frame)."""
        self.amp = kernels.plateau_mean(self.img, self.cx, self.cy, max(1, int(0.4 * radius)))

    def set_slopes(self, lat_j: np.ndarray, lat_i: np.ndarray, basis: np.ndarray, active: np.ndarray) -> None:
        """Intensity slope across each sub-image from the smooth field of lens amplitudes (non-uniform
        illumination, vignetting): the gradient of a plane fitted to the amplitudes of the lenses within
        SLOPE_REACH lattice steps, turned into x/y slopes per disc radius. Held fixed in the fit (fitting
        them per lens would cost precision)."""
        j0, i0 = lat_j.min(), lat_i.min()
        shape = (lat_i.max() - i0 + 1, lat_j.max() - j0 + 1)
        amp, on = np.zeros(shape), np.zeros(shape)
        amp[lat_i - i0, lat_j - j0] = np.where(active, self.amp, 0.0)
        on[lat_i - i0, lat_j - j0] = active
        dj, di = _plane_gradient(amp, on, SLOPE_REACH)
        dj, di = dj[lat_i - i0, lat_j - j0], di[lat_i - i0, lat_j - j0]
        grad = np.linalg.solve(basis.T, np.stack([dj, di]))  # d amp / d(x, y) per px
        self.slope_x = np.where(active, grad[0] * self.r_norm, 0.0)
        self.slope_y = np.where(active, grad[1] * self.r_norm, 0.0)

    def _plateau_inset(self, edge: float) -> float:
        """How far inside its rim a lens' plateau ends: clear of the fitted annulus and of the rim's tail
        (PLATEAU_EDGES edge widths), and of its neighbours' light."""
        tail = PLATEAU_EDGES * edge
        return max(self.band + 0.5 + tail, 2.0 * self.r_norm + tail + 0.5 - self.spacing_px)

    def _normals(self, idx: np.ndarray, edge: float, weighted: bool, fit_edge: bool):
        """Normal equations (n, 5, 5), right-hand sides (n, 5) of lenses `idx` against the frame residual;
        notes each lens' residual sum of squares and pixel count (a fit-quality figure).

        Parameters per lens: amplitude, centre x and y, radius (+ the global edge width in slot 4)."""
        inv_edge = np.full(self.n, 1.0 / edge)
        wide = np.zeros(self.n, bool) if self.wide is None else self.wide
        if self.wide is not None:
            inv_edge[wide] = 1.0 / self.wide_edge
        k = 1.0 / self.r_norm
        sx, sy = self.slope_x * k, self.slope_y * k
        normal = np.empty((idx.size, kernels.N_NORMAL, kernels.N_NORMAL))
        rhs = np.empty((idx.size, kernels.N_NORMAL))
        rss = np.empty(idx.size)
        npix = np.empty(idx.size, np.int64)

        inset = self._plateau_inset(edge if self.wide is None else max(edge, self.wide_edge))

        def block(b: slice) -> None:
            kernels.disc_normals(self.img, idx[b], self.cx, self.cy, self.amp, self.radius, inv_edge, sx, sy,
                                 self.neighbours, self.coupled, wide, self.band + 0.5, weighted, fit_edge,
                                 WEIGHT_FLOOR, self.halves, normal[b], rhs[b], rss[b], npix[b])
            kernels.add_plateau(self.img, idx[b], self.cx, self.cy, self.amp, self.radius, sx, sy, inset,
                                normal[b], rhs[b])

        self._map(block, idx)
        self.rss[idx], self.npix[idx] = rss, npix
        return normal, rhs

    def sweep(self, edge: float | None, active: np.ndarray, weighted: bool, lenses: np.ndarray | None = None) -> None:
        """One Gauss-Newton step for every lens (or `lenses`), by colour (square red-black, hex three): lenses
        of one lattice colour step together, then the next colour steps against their new positions (side
        neighbours, whose discs overlap, never step at the same time, so overlapping pairs cannot run away)."""
        # each lens once: `iterate` updates its lenses by fancy index, which must not repeat a lens
        idx = np.arange(self.n) if lenses is None else np.unique(np.asarray(lenses))
        for colour in range(self.n_colours):
            part = idx[self.colour[idx] == colour]
            if part.size:
                self.iterate(edge, active, weighted, part)

    def iterate(self, edge: float | None, active: np.ndarray, weighted: bool, idx: np.ndarray) -> None:
        """One Gauss-Newton step for lenses `idx` (inactive ones: amplitude only), the others held; with
        `edge` None the global edge width steps too (eliminated exactly through each lens' block)."""
        if edge is not None:
            self.edge = edge
            normal, rhs = self._normals(idx, edge, weighted, False)
            kernels.apply_steps(idx, normal, rhs, active, self.amp, self.cx, self.cy, self.radius, self.prev_step,
                                self.last_step, self.r_norm - 1.0, self.r_norm + 1.0)
            return
        s = self.edge
        normal, rhs = self._normals(idx, s, weighted, True)
        act = active[idx]
        npar = N_LENS_PARAMS
        diag = np.arange(npar)
        normal[:, diag, diag] += 1e-6 * (1.0 + normal[:, diag, diag])
        frozen = np.flatnonzero(~act)
        if frozen.size:
            normal[frozen, 1:, :] = 0.0
            normal[frozen, :, 1:] = 0.0
            normal[np.ix_(frozen, np.arange(1, normal.shape[1]), np.arange(1, normal.shape[1]))] = \
                np.eye(normal.shape[1] - 1)
            rhs[frozen, 1:] = 0.0
        cross = normal[:, :npar, npar]
        sol = np.linalg.solve(normal[:, :npar, :npar], np.stack([rhs[:, :npar], cross], axis=2))
        num = float(np.sum(rhs[act, npar]) - np.sum(np.einsum("li,li->l", cross, sol[:, :, 0])[act]))
        den = float(np.sum(normal[act, npar, npar]) - np.sum(np.einsum("li,li->l", cross, sol[:, :, 1])[act]))
        ds = float(np.clip(num / den, -0.5 * s, 0.5 * s)) if den > 0 else 0.0
        step = sol[:, :, 0] - sol[:, :, 1] * np.where(act, ds, 0.0)[:, None]
        self.edge = float(np.clip(s + ds, 0.05, 5.0))
        step[:, 1:] = np.clip(step[:, 1:], -1.0, 1.0)
        # damp lenses that oscillate (the step reverses the last one); as kernels.apply_steps
        flip = np.einsum("li,li->l", step[:, 1:3], self.prev_step[idx, 1:3]) < 0
        step[flip, 1:] *= 0.5
        # idx holds each lens once (`sweep` makes it unique, one colour class): a per-lens update, not an
        # accumulation of hits, written as one
        self.amp[idx] = self.amp[idx] + step[:, 0]
        self.cx[idx] = self.cx[idx] + step[:, 1]
        self.cy[idx] = self.cy[idx] + step[:, 2]
        # a lens' sub-image radius may differ from the typical one by a pixel (size defects), no more:
        # two strongly overlapping discs could otherwise trade radius against amplitude without end
        self.radius[idx] = np.clip(self.radius[idx] + step[:, 3], self.r_norm - 1.0, self.r_norm + 1.0)
        self.prev_step[idx] = step
        self.last_step[idx] = np.hypot(step[:, 1], step[:, 2])


def _plane_gradient(field: np.ndarray, on: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray]:
    """Gradient (d/dcolumn, d/drow) at every cell of a 2-D field of the least-squares plane through the
    cells marked `on` within `reach` steps; 0 where fewer than three, or only collinear ones, are there.
    A full window is point-symmetric, so a quadratic field's gradient comes out unbiased; 5 x 5 has 1/25
    of a two-cell central difference's noise variance."""
    rows, cols = field.shape
    pf, po = np.pad(field, reach), np.pad(on, reach)
    n, sj, si, sjj, sji, sii, sa, saj, sai = np.zeros((9, rows, cols))
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            o = po[reach + di: reach + di + rows, reach + dj: reach + dj + cols]
            a = pf[reach + di: reach + di + rows, reach + dj: reach + dj + cols]
            n += o
            sj += dj * o
            si += di * o
            sjj += dj * dj * o
            sji += dj * di * o
            sii += di * di * o
            sa += a
            saj += dj * a
            sai += di * a
    with np.errstate(divide="ignore", invalid="ignore"):
        mj, mi = sj / n, si / n
        cjj, cji, cii = sjj - n * mj * mj, sji - n * mj * mi, sii - n * mi * mi
        bj, bi = saj - sa * mj, sai - sa * mi
        det = cjj * cii - cji * cji
        ok = (n >= 3) & (det > 1e-9 * np.maximum(n, 1) ** 2)
        gj = np.where(ok, (bj * cii - bi * cji) / det, 0.0)
        gi = np.where(ok, (bi * cjj - bj * cji) / det, 0.0)
    return gj, gi


def _colours(lat_j: np.ndarray, lat_i: np.ndarray, packing: str) -> np.ndarray:
    """Sweep colour of each lattice point such that side neighbours (whose discs overlap) differ: square
    red-black, hex (j + 2 i) mod 3 (its six neighbours step j, i or i - j by one)."""
    if packing == "hex":
        return (lat_j + 2 * lat_i) % 3
    return (lat_i + lat_j) % 2


def _measure(img: np.ndarray, px: np.ndarray, py: np.ndarray, lat_j: np.ndarray, lat_i: np.ndarray,
             basis: np.ndarray, radius0: float, packing: str = "square") -> tuple[_Discs, np.ndarray]:
    """Joint disc fit of every lens (see the module docstring), in two stages:

    1. a central block of lenses, from a wide edge down: the edge width, the typical radius and a lattice
       good to a few hundredths of a pixel everywhere (the Fourier one is good to ~0.1 px at the corners);
    2. every lens, from there: N_SWEEPS sweeps, the capture of lenses far off the lattice, then more
       sweeps for the lenses that still move and their neighbours only.
    """
    pitch = float(np.sqrt(abs(np.linalg.det(basis))))
    band = BAND * max(1.0, pitch / 20.0)
    # lattice neighbours whose discs can overlap a lens' fitting annulus: the first ring, and the second
    # too for discs large against the pitch
    spacing = float(np.min(np.hypot(basis[0], basis[1])))
    second = (math.sqrt(3.0) if packing == "hex" else 2.0) * spacing  # distance to the second ring
    ring = 1 if second > 2.0 * radius0 + band + 0.5 + 4.0 else 2
    # stage 1: a block of about SUBSET x SUBSET lenses round the brightest part of the centre
    cj, ci = np.median(lat_j), np.median(lat_i)
    half = SUBSET // 2
    # its lenses are fitted with one ring of lenses round them held on the lattice (amplitude only); hex:
    # two rings, as the first ring's amplitude, fitted with its outer neighbours (not in the block) left
    # out, is inflated by their overlaps and would push the block's edge lenses inwards (0.05 px measured)
    pad = 2 if packing == "hex" else 1
    block = (np.abs(lat_j - cj) <= half + pad) & (np.abs(lat_i - ci) <= half + pad)
    inner = (np.abs(lat_j - cj) <= half) & (np.abs(lat_i - ci) <= half)
    colour = _colours(lat_j, lat_i, packing)
    px, py = px.copy(), py.copy()
    lattice_x, lattice_y = px, py
    halves = HALVES_ORDER[packing]
    sub = _DiscFit(img, px[block], py[block], radius0, _lattice_neighbours(lat_j[block], lat_i[block], ring, packing),
                   colour[block], halves, spacing)
    sub.init_amplitude(radius0)
    sub.set_band(band)
    ref = float(np.percentile(sub.amp, 90)) if sub.amp.size else 0.0
    act = inner[block] & (sub.amp > 0.2 * ref) & (sub.valid_fraction >= MIN_VALID_FRACTION)
    if np.count_nonzero(act) >= MIN_LENSES:
        sub.sweep(max(0.8, 0.05 * pitch), act, weighted=False)
        sub.edge = max(0.4, 0.025 * pitch)
        for it in range(BLOCK_SWEEPS):
            sub.sweep(None, act, weighted=it >= 1)
        radius0 = float(np.median(sub.radius[act]))
        edge0 = sub.edge
        # a better lattice from the block's centres (the Fourier pitch is good to ~1e-4): every lens
        # then starts within a few hundredths of a pixel; the block's lenses start where they were found
        design = np.stack([np.ones(act.sum()), lat_j[block][act], lat_i[block][act]], 1)
        coef = np.linalg.lstsq(design, np.stack([sub.cx[act], sub.cy[act]], 1), rcond=None)[0]
        if np.count_nonzero(act) >= 25:
            px = coef[0, 0] + coef[1, 0] * lat_j + coef[2, 0] * lat_i
            py = coef[0, 1] + coef[1, 1] * lat_j + coef[2, 1] * lat_i
        lattice_x, lattice_y = px.copy(), py.copy()
        done = np.flatnonzero(block)[act]
        px[done], py[done] = sub.cx[act], sub.cy[act]
    else:
        edge0 = max(0.4, 0.025 * pitch)
    # stage 2: every lens
    neighbours = _lattice_neighbours(lat_j, lat_i, ring, packing)
    fit = _DiscFit(img, px, py, radius0, neighbours, colour, halves, spacing)
    fit.edge = edge0
    fit.init_amplitude(radius0)
    ref = float(np.percentile(fit.amp, 90)) if fit.amp.size else 0.0
    fit.set_band(band)
    active = (fit.amp > 0.2 * ref) & (fit.valid_fraction >= MIN_VALID_FRACTION)
    if np.count_nonzero(active) < MIN_LENSES:
        raise InputError(f"only {int(np.count_nonzero(active))} microlens sub-images found in the white image "
                         f"(at least {MIN_LENSES} are needed)")
    side = neighbours[:, :_FIRST_RING[packing]]  # the first ring: who is coupled to whom
    for it in range(N_SWEEPS):
        if it == 1:
            fit.set_slopes(lat_j, lat_i, basis, active)
            off = active & (np.hypot(fit.cx - lattice_x, fit.cy - lattice_y) > COUPLED_PX)
            fit.coupled[_with_neighbours(np.flatnonzero(off), side)] = True
            # a new objective (weights, slopes): its first step is no oscillation to damp
            fit.prev_step[:] = 0.0
        fit.sweep(fit.edge, active, weighted=it >= 1)  # the edge width is known from the block
    # lenses the sharp edge cannot pull in (beyond ~1 px off the lattice: big defects) fit badly; they
    # are captured with a wide edge of their own, then refined; only they and their neighbours step
    per_px = fit.rss / np.maximum(fit.npix, 1)
    typical = float(np.median(per_px[active]))
    far = active & ((per_px > 3.0 * typical) | (fit.last_step > 0.3))
    if far.any():
        fit.wide, fit.wide_edge = far, max(WIDE_EDGE, 4.0 * fit.edge)
        group = _with_neighbours(np.flatnonzero(far), side)
        fit.coupled[group] = True
        for _ in range(3):
            fit.sweep(fit.edge, active, weighted=True, lenses=group)
        fit.wide = None
        # where the wide edges left the group is no fit of the sharp one: it steps again below
        fit.last_step[group] = np.inf
    for _ in range(MAX_EXTRA):  # until every lens has settled
        moving = np.flatnonzero(active & (fit.last_step > SETTLED_PX))
        if not moving.size:
            break
        fit.sweep(fit.edge, active, weighted=True, lenses=_with_neighbours(moving, side))
    fit.valid_fraction = fit.rim_in_frame()
    discs = _Discs(fit.cx, fit.cy, fit.amp, fit.radius, fit.edge, fit.valid_fraction)
    return discs, active


_FIRST_RING = {"square": 8, "hex": 6}  # neighbours in the first ring (square: edges and diagonals)


def _lattice_neighbours(lat_j: np.ndarray, lat_i: np.ndarray, ring: int = 1, packing: str = "square") -> np.ndarray:
    """(n, k) indices of each candidate's lattice neighbours within `ring` steps (-1 where there is none),
    nearest ring first: square (2 ring + 1)^2 - 1 (the first 8 the first ring), hex 3 ring (ring + 1)
    (the first 6 the first ring; axial steps (dj, di) with max(|dj|, |di|, |dj + di|) <= ring)."""
    j0, i0 = lat_j.min(), lat_i.min()
    table = np.full((lat_i.max() - i0 + 1 + 2 * ring, lat_j.max() - j0 + 1 + 2 * ring), -1)
    table[lat_i - i0 + ring, lat_j - j0 + ring] = np.arange(lat_j.size)
    if packing == "hex":
        steps = lambda o: max(abs(o[0]), abs(o[1]), abs(o[0] + o[1]))  # noqa: E731 (hex distance)
    else:
        steps = lambda o: max(abs(o[0]), abs(o[1]))  # noqa: E731
    offsets = sorted(((di, dj) for di in range(-ring, ring + 1) for dj in range(-ring, ring + 1)
                      if (di or dj) and steps((di, dj)) <= ring), key=steps)
    return np.stack([table[lat_i - i0 + ring + di, lat_j - j0 + ring + dj] for di, dj in offsets], axis=1)


def _with_neighbours(lenses: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    out = np.concatenate([lenses, neighbours[lenses].ravel()])
    return np.unique(out[out >= 0])
