"""The compiled fast path against the NumPy reference where its code differs most: lenses pushed far into
their neighbours' cells (the re-trace near cell edges), tilted lenses, both corner models, both lens
boundary models (the sag-intersection neighbour pass) and the black matrix, the hit compaction and the
in-kernel binning. Renders of the same seed use the same draws in both engines.
"""

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from mlaqc.optics import kernel_jit, kernel_layout, raytrace_kernels
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Renderer, _bin_patch
from mlaqc.optics.scene import WhiteScene

pytestmark = pytest.mark.skipif(not raytrace_kernels.AVAILABLE, reason="numba is not installed")

SMALL = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")


def _harsh_errors() -> ErrorMap:
    """Errors large enough that many rays hit a lens from the neighbouring cell (re-traced), plus tilts."""
    em = ErrorMap.zeros(24, 24)
    rng = np.random.default_rng(5)
    for m, n in rng.integers(2, 23, size=(40, 2)):
        em = em.with_lens(int(m), int(n), pitch_um=float(rng.uniform(10, 35)), pitch_dir_deg=float(rng.uniform(0, 360)),
                          decenter_um=float(rng.uniform(0, 12)), decenter_dir_deg=float(rng.uniform(0, 360)),
                          radius_front_rel=float(rng.uniform(-0.2, 0.2)), thickness_um=float(rng.uniform(-3, 3)))
    em = em.with_lens(10, 10, tilt_x_deg=3, tilt_y_deg=-2).with_lens(11, 12, tilt_x_deg=-1.5, tilt_y_deg=2.5)
    return em.with_globals(mla_rotation_deg=-1.1, mla_tilt_y_deg=0.3, mla_shift_y_um=-20)


def _moderate_errors() -> ErrorMap:
    """Every lens with random pitch, decenter, radius, thickness and tilt errors small enough that the
    sag-intersection fast path is active (margins well below half a pitch), plus global errors."""
    rng = np.random.default_rng(8)
    shape = (24, 24)
    lens = {"pitch_um": rng.uniform(0, 5, shape), "pitch_dir_deg": rng.uniform(0, 360, shape),
            "decenter_um": rng.uniform(0, 5, shape), "decenter_dir_deg": rng.uniform(0, 360, shape),
            "radius_front_rel": rng.uniform(-0.08, 0.08, shape), "radius_back_rel": rng.uniform(-0.08, 0.08, shape),
            "tilt_x_deg": rng.uniform(-0.5, 0.5, shape), "tilt_y_deg": rng.uniform(-0.5, 0.5, shape),
            "thickness_um": rng.uniform(-1.5, 1.5, shape)}
    return ErrorMap(shape, lens).with_globals(mla_rotation_deg=0.7, mla_tilt_x_deg=-0.2, mla_shift_x_um=13)


def _mla(cfg, **mla):
    return dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, **mla))


SAG = "sag-intersection"


@pytest.mark.parametrize("corners, boundaries, black_um, errors", [
    ("opaque", "grid", 0.0, "harsh"), ("clear", "grid", 0.0, "harsh"),
    ("opaque", SAG, 0.0, "harsh"), ("clear", SAG, 0.0, "harsh"),
    ("opaque", SAG, 0.0, "moderate"), ("clear", SAG, 6.0, "moderate"), ("opaque", "grid", 6.0, "moderate")])
def test_fast_path_matches_the_reference_under_large_per_lens_errors(corners, boundaries, black_um, errors):
    cfg = _mla(SMALL, corners=corners, boundaries=boundaries, black_matrix_um=black_um)
    em = _harsh_errors() if errors == "harsh" else _moderate_errors()
    a = Renderer(cfg, em, engine="numpy")
    b = Renderer(cfg, em, engine="numba")
    i1, w1 = a.trace_batch(WhiteScene(), 7, 60_000, tile=(-1.2, 1.2, -1.2, 1.2))
    i2, w2 = b.trace_batch(WhiteScene(), 7, 60_000, tile=(-1.2, 1.2, -1.2, 1.2))
    assert len(i1) > 40_000
    assert np.array_equal(i1, i2)
    assert np.allclose(w1, w2, rtol=1e-13, atol=0)


@pytest.mark.parametrize("boundaries, errors", [("grid", "harsh"), (SAG, "moderate")])
def test_engines_render_the_same_image(boundaries, errors):
    """Same draws, same order of summation per pixel: the images agree to rounding, pixel by pixel."""
    em = _harsh_errors() if errors == "harsh" else _moderate_errors()
    cfg = _mla(SMALL, boundaries=boundaries)
    a = Renderer(cfg, em, engine="numpy").render(WhiteScene(), rays=600_000, seed=4, threads=2)
    b = Renderer(cfg, em, engine="numba").render(WhiteScene(), rays=600_000, seed=4, threads=2)
    assert a.rays_landed == b.rays_landed
    assert np.array_equal(a.photons > 0, b.photons > 0)
    assert np.allclose(a.photons, b.photons, rtol=1e-12, atol=0)



HEX_SMALL = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "hex_small_camera.toml")


def _hex_moderate_errors() -> ErrorMap:
    """Every lens of the small hex array (28 x 24) with random pitch, decenter, radius, thickness and tilt
    errors, plus global errors: margins and circle clearances non-zero on every cell."""
    rng = np.random.default_rng(9)
    shape = (HEX_SMALL.mla.count_h, HEX_SMALL.mla.count_w)
    lens = {"pitch_um": rng.uniform(0, 6, shape), "pitch_dir_deg": rng.uniform(0, 360, shape),
            "decenter_um": rng.uniform(0, 4, shape), "decenter_dir_deg": rng.uniform(0, 360, shape),
            "radius_front_rel": rng.uniform(-0.06, 0.06, shape), "radius_back_rel": rng.uniform(-0.06, 0.06, shape),
            "tilt_x_deg": rng.uniform(-0.4, 0.4, shape), "tilt_y_deg": rng.uniform(-0.4, 0.4, shape),
            "thickness_um": rng.uniform(-1.0, 1.0, shape)}
    return ErrorMap(shape, lens, packing="hex").with_globals(mla_rotation_deg=0.6, mla_tilt_x_deg=-0.2)


def _sparse_defects(packing: str, shape: tuple[int, int], seed: int) -> ErrorMap:
    """A perfect array but for a sparse set of lenses with large pitch or thickness errors: perfect cells
    next to flawed ones, where a cell's margin (its worst neighbour's) exceeds most of its pairs'."""
    rng = np.random.default_rng(seed)
    em = ErrorMap.zeros(*shape, packing=packing)
    for m in range(1, shape[0] - 1, 2):
        for n in range(1, shape[1] - 1, 2):
            if rng.random() < 0.5:
                em = em.with_lens(m, n, pitch_um=float(rng.uniform(1, 4)), pitch_dir_deg=float(rng.uniform(0, 360)))
            else:
                em = em.with_lens(m, n, thickness_um=float(rng.uniform(-3, 3)))
    return em


def _exhaustive(r: Renderer) -> Renderer:
    """The renderer with pruning off: every doubted ray scans all its candidates (the reference path)."""
    r.fast.base[kernel_layout.S_PRUNE] = 0.0
    return r


@pytest.mark.parametrize("packing, mla, errors", [
    ("square", {"boundaries": SAG}, "moderate"), ("square", {"boundaries": SAG, "corners": "clear"}, "sparse"),
    ("hex", {"boundaries": SAG}, "moderate"), ("hex", {"boundaries": SAG}, "sparse"),
    ("square", {"aperture": "circle", "aperture_diameter_um": 96.0, "gap": "clear"}, "moderate"),
    ("hex", {"aperture": "circle", "aperture_diameter_um": 90.0, "gap": "opaque"}, "moderate")])
def test_pruned_retrace_renders_the_exhaustive_image_bit_for_bit(packing, mla, errors):
    """Skipping the candidates that provably cannot win (pair clearances, circle clearances) changes no
    ray: on frames where every cell has rays within its margin / clearance of its edges, the image equals
    bit for bit the one of the exhaustive scan of every doubted ray (same seed, same draws)."""
    base = SMALL if packing == "square" else HEX_SMALL
    cfg = _mla(base, **mla)
    shape = (cfg.mla.count_h, cfg.mla.count_w)
    em = (_sparse_defects(packing, shape, 3) if errors == "sparse"
          else _moderate_errors() if packing == "square" else _hex_moderate_errors())
    a = Renderer(cfg, em, engine="numba")
    lens = a.camera.mla
    if lens.sag:  # rays within microns of the edges of most cells are doubted
        assert np.mean(lens.margin_rear > 0) > 0.5 and np.median(lens.margin_rear[lens.margin_rear > 0]) > 1e-3
    else:
        assert np.mean(lens.circle_clearance_mm() > 0) > 0.5
    got = a.render(WhiteScene(), rays=500_000, seed=6, threads=2)
    ref = _exhaustive(Renderer(cfg, em, engine="numba")).render(WhiteScene(), rays=500_000, seed=6, threads=2)
    assert got.rays_landed == ref.rays_landed > 50_000
    assert np.array_equal(got.photons, ref.photons)

def test_hits_come_in_ray_order_with_their_bounding_box():
    r = Renderer(SMALL, _harsh_errors(), engine="numba")
    rows, cols, w, box = r.fast.trace_hits(kernel_layout.IMAGE_SIDE, 11, 30_000, tile=(-0.4, 0.1, 0.2, 0.5))
    idx, w2 = r.fast.trace(kernel_layout.IMAGE_SIDE, 11, 30_000, tile=(-0.4, 0.1, 0.2, 0.5))
    assert len(w) > 20_000 and np.all(w > 0)
    assert list(box) == [rows.min(), rows.max(), cols.min(), cols.max()]
    assert np.array_equal(idx, rows.astype(np.int64) * SMALL.sensor.width_px + cols) and np.array_equal(w, w2)
    # counter-based draws: a batch's first rays do not depend on how many rays follow them
    idx_short, _ = r.fast.trace(kernel_layout.IMAGE_SIDE, 11, 1000, tile=(-0.4, 0.1, 0.2, 0.5))
    assert np.array_equal(idx_short, idx[:len(idx_short)])


def test_compiled_binning_equals_bincount_bit_for_bit():
    rng = np.random.default_rng(2)
    rows = rng.integers(100, 140, 50_000).astype(np.int32)
    cols = rng.integers(7, 30, 50_000).astype(np.int32)
    w = rng.random(50_000)
    box = np.array([rows.min(), rows.max(), cols.min(), cols.max()], np.int64)
    patch = raytrace_kernels.bin_hits(rows, cols, w, len(w), box)
    r0, c0, ref, n = _bin_patch(rows.astype(np.int64) * 496 + cols, w, 496)
    assert (r0, c0, n) == (box[0], box[2], len(w))
    assert np.array_equal(patch, ref)
    assert raytrace_kernels.bin_hits(rows, cols, w, 0, box).shape == (0, 0)


def test_the_silenced_numba_ssa_warning_matches_numbas_own_message():
    """The kernels silence one pedantic Numba warning at compile time; Numba starts its message with a
    terminal colour code, which a filter matching from the message's start must allow for (it did not, and
    the warnings reached the user on every first compile of the sag-intersection tracer)."""
    errors = pytest.importorskip("numba.core.errors")
    message = str(errors.NumbaIRAssumptionWarning("variable 'v_own_edge_hex_v1' is not in scope."))
    assert re.match(kernel_jit.SSA_SCOPE_WARNING, message, re.I)
    assert not re.match(kernel_jit.SSA_SCOPE_WARNING, "variable 'x' is undefined", re.I)
