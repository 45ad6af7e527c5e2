"""The per-lens indexes are continuous in the lens' sub-pixel position.

A sub-image whose profile differs from the reference's (here: rounded-square cells with dark gaps between
them, or discs with a Gaussian rim, where the tracer's reference has bright seams where neighbours
overlap) is registered with a step gain below 1. With the reference snapped to a 1/8-px phase, the
measured offset was that phase plus a fraction of the rest, so it jumped wherever the snapped phase
changed; and as the lens centre crossed half a pixel its window, cut on the nearest pixel, swapped a
mismatched edge column from one side to the other: the offset jumped by 0.1 px (a blind test's false
`position` and `unknown` flags, all at that phase). Both are gone: the reference is interpolated at the
lens' position and the window's outermost pixels fade out of every index taken against it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.special import erfc

from analytic_frames import GL_NODES, GL_WEIGHTS, AnalyticModel
from mlaqc.inspection.metrics import compute_metrics
from mlaqc.inspection.pipeline import inspect_image
from mlaqc.inspection.subimages import cut_windows
from mlaqc.models.reference import reference_model
from mlaqc.optics.config import load_config

SMALL = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")
PITCH = SMALL.layout.subimage_pitch_px


def cells(shape, lenses, pitch, phase, rotation_deg=0.0, gap=0.8, radius=11.2, sigma=0.45, white=0.8):
    """A white frame of rounded-square sub-images, as a camera whose cells are square apertures (side
    pitch - gap) cut by the main lens' pupil image (a disc of `radius`), every edge blurred by a Gaussian of
    `sigma` px; `white` at the plateau. Exact pixel integrals (4 x 4 Gauss-Legendre points). Returns the
    frame and the lens centres (x, y). Shares nothing with the tracer or tests/analytic_frames' discs."""
    h, w = shape
    rows, cols = lenses
    a = math.radians(rotation_deg)
    m, n = np.meshgrid(np.arange(rows) - (rows - 1) / 2, np.arange(cols) - (cols - 1) / 2, indexing="ij")
    cx = (w - 1) / 2 + phase[0] + pitch * (n * math.cos(a) + m * math.sin(a))
    cy = (h - 1) / 2 + phase[1] + pitch * (m * math.cos(a) - n * math.sin(a))
    half = 0.5 * (pitch - gap)

    def inside(d):  # a blurred edge: 1 well inside (d < 0), 0 well outside
        return 0.5 * erfc(d / (math.sqrt(2.0) * sigma))

    img = np.zeros(shape)
    off = np.arange(-(int(radius + 4 * sigma) + 1), int(radius + 4 * sigma) + 2)
    for x0, y0 in zip(cx.ravel(), cy.ravel()):
        px, py = np.meshgrid(np.rint(x0) + off, np.rint(y0) + off)
        val = np.zeros(px.shape)
        for i, wy in zip(GL_NODES, GL_WEIGHTS):
            for j, wx in zip(GL_NODES, GL_WEIGHTS):
                dx, dy = px + j - x0, py + i - y0
                u, v = dx * math.cos(a) - dy * math.sin(a), dx * math.sin(a) + dy * math.cos(a)
                val += wy * wx * inside(np.abs(u) - half) * inside(np.abs(v) - half) * inside(np.hypot(dx, dy) - radius)
        ok = (px >= 0) & (px < w) & (py >= 0) & (py < h)
        np.add.at(img, (py[ok].astype(int), px[ok].astype(int)), white * val[ok])
    return img, cx, cy


def _centre_lens(kind: str, phase: tuple[float, float]):
    """A 3 x 3-lens patch whose centre lens sits at sub-pixel `phase`: its image and centre."""
    shift = (0.5 + phase[0], 0.5 + phase[1])  # the 80 x 80 patch's centre is at 39.5
    if kind == "cells":
        img, cx, cy = cells((80, 80), (3, 3), PITCH, shift)
    else:
        m = AnalyticModel(shape=(80, 80), lenses=(3, 3), pitch_px=PITCH, phase_px=shift, prnu_rms=0.0,
                          crosstalk=0.0, exit_pupil_px=1e9)
        img, (cx, cy) = m.render(), m.centres()
    return img.astype(np.float32), cx[1, 1], cy[1, 1]


# the largest change of an index from one 0.01-px step of the lens to the next (the snapped reference and
# the window cut made 0.05-0.1 px in the offset, 0.06 in the tilt, 0.02-0.04 in the sharpness)
STEP_TOLERANCE = {"offset_x_px": 0.005, "offset_y_px": 0.005, "asym_x": 0.005, "asym_y": 0.005, "blur": 0.004,
                  "flux": 0.0002, "sharpness": 0.005, **{f"ring{k}": 0.0005 for k in range(6)}}


@pytest.mark.parametrize("kind", ["cells", "discs"])
@pytest.mark.parametrize("axis", [0, 1])
def test_indexes_are_continuous_in_the_sub_pixel_phase(kind, axis):
    """The centre lens swept over phases 0.30-0.60 px in 0.01 px steps along x (then y), across half a
    pixel (where its window is cut one pixel over) and three 1/8-px reference phases: no index jumps, and
    the offset from the true centre stays small."""
    model = reference_model(SMALL)
    phases = np.round(np.arange(0.30, 0.6001, 0.01), 3)
    wins, cxs, cys = [], [], []
    for p in phases:
        img, x0, y0 = _centre_lens(kind, (p, 0.2) if axis == 0 else (0.2, p))
        win, _, ox, oy = cut_windows(img, np.array([x0]), np.array([y0]), 21, 21)
        wins.append(win[0])
        cxs.append(x0 - ox[0])
        cys.append(y0 - oy[0])
    cxs, cys = np.array(cxs), np.array(cys)
    along = cxs if axis == 0 else cys
    assert along[0] > 10.0 > along[-1]  # the window was cut one pixel over within the sweep
    met = compute_metrics(np.array(wins)[None], cxs[None], cys[None], model, um_per_px_at_mla=1.0, threads=1)
    for name, tol in STEP_TOLERANCE.items():
        steps = np.abs(np.diff(met[name][0]))
        assert steps.max() < tol, (name, float(steps.max()), float(phases[1:][np.argmax(steps)]))
    offset = met["offset_x_px" if axis == 0 else "offset_y_px"][0]
    assert np.abs(offset).max() < 0.04  # was up to 0.1 px on the cells


def test_a_healthy_frame_of_lenses_straddling_half_a_pixel_has_no_flags():
    """A noise-free frame of rounded-square cells at a pitch of 20.02 px: the sub-pixel phase walks by 0.02
    per lens, so neighbouring lenses sit on both sides of half a pixel in x and in y (where windows are
    cut one pixel over) all across the array. No lens is flagged (the snapped reference and the window
    cut flagged two as `position` at z 9.6)."""
    img, cx, cy = cells((SMALL.sensor.height_px, SMALL.sensor.width_px), (SMALL.mla.count_h, SMALL.mla.count_w),
                        20.02, (0.02, 0.3), rotation_deg=0.05)
    near = (np.abs(np.mod(cx, 1.0) - 0.5) < 0.05) | (np.abs(np.mod(cy, 1.0) - 0.5) < 0.05)
    assert near.sum() >= 100
    result = inspect_image(img.astype(np.float32), SMALL)
    assert result.verdict == "PASS" and result.defects == (), [(d.m, d.n, d.error_type, d.score)
                                                               for d in result.defects]
    ok = ~result.grid.clipped  # (the lattice is the frame's: a disc model on square cells is good to 0.013 px)
    assert np.sqrt(np.mean((result.grid.grid_x_px - cx)[ok] ** 2 + (result.grid.grid_y_px - cy)[ok] ** 2)) < 0.03
