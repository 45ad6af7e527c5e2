"""Hex identification accuracy (issue #22): a lens shifted across the rows is read at its true size and
direction, and the second ring of a rotated hex array is as quiet as the inner lenses.

Checked against seeded truth (ray-traced errors of known size and direction, sizes between the table's
rendered ones), against hand-made tables whose across response is known exactly, and against the
analytic model's healthy lenses (every disc alike, so every ring's deviations have the same spread)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from mlaqc.models.signatures import (
    FEATURES,
    RINGS,
    SignatureTable,
    along_curve,
    to_along,
    to_along_xy,
)
from mlaqc.optics.config import load_config

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
HEX = load_config(FIXTURES / "hex_small_camera.toml")
sys.path.insert(0, str(Path(__file__).resolve().parent))


def _table(across_scale: dict[str, np.ndarray] | None) -> SignatureTable:
    """A hand-made table: pitch and decenter shift_par/asym_par linear in the magnitude (0.2 px and 0.03
    per µm); across the rows each column times `across_scale[kind]` per magnitude (None: no across)."""
    n = len(FEATURES) + len(RINGS)
    mags = {"pitch": np.array([1.0, 2.0, 4.0, 8.0]), "decenter": np.array([2.0, 5.0, 10.0])}
    feats, rings, across = {}, {}, {}
    for k, m in mags.items():
        f = np.zeros((len(m), len(FEATURES)))
        f[:, 0], f[:, 2] = 0.2 * m, 0.03 * m
        feats[k], rings[k] = f, np.zeros((len(m), len(RINGS)))
        if across_scale is not None:
            a = np.zeros((len(m), n))
            a[:, 0], a[:, 2] = f[:, 0] * across_scale[k], f[:, 2] * across_scale[k]
            across[k] = a
    return SignatureTable(mags, feats, {"pitch": 0.0, "decenter": 0.0}, "test", rings, {}, across)


def test_a_shift_across_the_rows_at_a_falling_gain_maps_back_to_its_along_size():
    # across = along x gain, the gain falling from 0.55 to 0.40 with size: any reading in between maps
    # to the along size of the same error (piecewise linear through the rendered pairs)
    gain = {"pitch": np.array([0.55, 0.52, 0.47, 0.40]), "decenter": np.array([0.54, 0.50, 0.44])}
    t = _table(gain)
    for kind, g in gain.items():
        along = t.features[kind][:, 0]
        assert np.allclose(to_along(t, along * g, 0), along, rtol=0.03)
        assert np.allclose(to_along(t, -along * g, 0), -along, rtol=0.03)  # odd: the sign is kept
    # a 3 µm pitch error: between the rendered 2 and 4 µm, across 0.6 * ~0.495
    assert to_along(t, 0.6 * 0.495, 0) == pytest.approx(0.6, rel=0.03)
    # monotone over its whole range, linear through zero below the smallest, the last ratio beyond
    x = np.linspace(0.0, 2.0, 401)
    assert np.all(np.diff(to_along(t, x, 0)) >= 0)
    assert to_along(t, 0.01, 0) == pytest.approx(0.01 / 0.55, rel=0.02)
    assert to_along(t, 1.0, 0) == pytest.approx(1.0 / 0.44, rel=1e-9)  # the largest pair: decenter 10 µm


def test_a_diagonal_shift_maps_its_y_part_at_the_gain_of_its_whole_size():
    # a lens shift of size S (px along the rows) at angle a registers (S cos a, S sin a * g(S)) with the
    # across gain g = 0.56 - 0.1 S falling with S: mapped at the gain of its y part alone, y comes out
    # short and the direction turns towards the rows
    g_of = lambda s: 0.56 - 0.1 * s  # noqa: E731
    t = _table({"pitch": g_of(0.2 * np.array([1.0, 2.0, 4.0, 8.0])), "decenter": g_of(0.2 * np.array([2.0, 5.0, 10.0]))})
    size = np.array([0.2, 0.4, 0.8, 1.0, 1.6, 2.0])  # the renders' along sizes, px
    gain = g_of(size)
    for s, g in zip(size, gain):
        for a_deg in (15.0, 30.0, 45.0, 60.0, 75.0, 135.0):
            a = np.radians(a_deg)
            x, y_reg = s * np.cos(a), s * np.sin(a) * g
            y = to_along_xy(t, x, y_reg, 0)
            assert y == pytest.approx(s * np.sin(a), rel=1e-3), (s, a_deg)
            assert np.degrees(np.arctan2(y, x)) == pytest.approx(a_deg, abs=0.05)
    # the old per-part map is off by several per cent at a diagonal (what this replaces)
    y_reg = 1.6 * 0.5 * g_of(1.6)
    assert to_along(t, y_reg, 0) < 0.95 * 1.6 * 0.5
    # a pure y reading maps exactly as to_along, at and between the rendered sizes and beyond them
    ys = np.linspace(-1.2, 1.2, 481)
    assert np.allclose(to_along_xy(t, 0.0, ys, 0), to_along(t, ys, 0), rtol=1e-12, atol=0.0)
    # a curve with a flat step (a kind's point under the running maximum) still gives one answer
    flat = _table({"pitch": np.array([0.55, 0.52, 0.47, 0.40]), "decenter": np.array([0.30, 0.50, 0.44])})
    y_reg = np.linspace(0.05, 0.6, 12)
    a, b = to_along_xy(flat, 0.3, y_reg, 0), to_along_xy(flat, 0.3, y_reg, 0, steps=40)
    assert np.all(np.isfinite(a)) and np.allclose(a, b, rtol=1e-7) and np.all(np.diff(a) > 0)
    assert np.allclose(to_along_xy(flat, 0.0, y_reg, 0), to_along(flat, y_reg, 0), rtol=1e-12)
    v = np.array([-0.3, 0.0, 0.2, 1.5])
    assert np.array_equal(to_along_xy(_table(None), v, v, 0), v)


def test_a_kind_whose_across_response_turns_down_is_cut_where_it_stops_rising():
    # a 10 µm decenter registering less across the rows than 5 µm must not bend the map back
    gain = {"pitch": np.full(4, 0.5), "decenter": np.array([0.5, 0.5, 0.2])}
    across, along = along_curve(_table(gain), 0)
    assert np.all(np.diff(across) >= 0) and np.all(np.diff(along) >= 0)
    assert len(across) == 4 + 2  # every pitch point, the decenter's first two: the turned-down one left out
    assert np.allclose(along / across, 2.0)


def test_a_table_without_across_renders_leaves_readings_unchanged():
    t = _table(None)
    v = np.array([-0.3, 0.0, 0.2, 1.5])
    assert np.array_equal(to_along(t, v, 0), v) and np.array_equal(to_along(t, v, 2), v)
    assert t.across_table() is t


def test_the_shipped_hex_tables_hold_across_renders_and_the_square_ones_none():
    from mlaqc.inspection.pipeline import _models

    hex_set = _models(HEX)[1]
    for t in hex_set.tables:
        assert set(t.across) == {"pitch", "decenter"}
        assert t.across["pitch"].shape == (len(t.magnitudes["pitch"]), len(FEATURES) + len(RINGS))
        # across the rows a pitch error registers at about half its shift along them (0.4-0.6)
        ratio = t.across["pitch"][:, 0] / t.features["pitch"][:, 0]
        assert np.all((ratio > 0.3) & (ratio < 0.65))
    square = _models(load_config(FIXTURES / "small_camera.toml"))[1]
    assert all(not t.across for t in square.tables)


# --- ray-traced errors across the rows and diagonal, at sizes between the rendered ones ----------------

SEEDED = {(8, 6): ("pitch", 4.0, 90.0), (8, 13): ("decenter", 10.0, 90.0), (8, 19): ("pitch", 1.5, 270.0),
          (15, 6): ("decenter", 7.0, 135.0), (15, 13): ("pitch", 2.5, 210.0), (15, 19): ("decenter", 6.0, 300.0),
          (22, 6): ("pitch", 3.0, 30.0), (22, 13): ("decenter", 10.0, 0.0)}


@pytest.fixture(scope="module")
def traced():
    from test_hex_inspect import traced_hex_result

    return traced_hex_result(SEEDED, 400, 5)


def test_shifts_across_the_rows_and_diagonal_read_their_size_within_15_percent(traced):
    found = {(d.m, d.n): d for d in traced.defects}
    assert set(found) == set(SEEDED)
    for key, (kind, mag, direction) in SEEDED.items():
        d = found[key]
        assert d.error_type == kind, (key, d.error_type)
        assert d.magnitude == pytest.approx(mag, rel=0.15), (key, d.magnitude)
        assert abs((d.direction_deg - direction + 180.0) % 360.0 - 180.0) < 8.0, (key, d.direction_deg)


# --- the second ring of a rotated analytic hex array ----------------------------------------------------

def test_the_second_rows_of_a_rotated_hex_array_are_as_quiet_as_the_inner_lenses():
    """Every disc of the analytic model is alike, so the x offset and tilt deviations of the second row
    from the top and bottom must spread as the inner lenses' do (their baselines' windows span 4 rows,
    and the sub-pixel phase pattern they read is fitted on its own: before, 2.7 times wider)."""
    import analytic_frames as am

    from mlaqc.inspection import identify as ident
    from mlaqc.inspection import phase_pattern
    from mlaqc.inspection.calibrate import calibrate_for
    from mlaqc.inspection.metrics import compute_metrics
    from mlaqc.inspection.pipeline import _models
    from mlaqc.inspection.subimages import divide
    from mlaqc.models.signatures import um_per_px_at_mla

    cfg = load_config(FIXTURES / "hex_camera.toml")  # the Table 1 hex camera: 116 rows x 102 columns
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    model = am.AnalyticModel(lenses=(rows, cols), rotation_deg=0.5, phase_px=(0.31, 0.77), packing="hex")
    rng = np.random.default_rng(4)
    img = am.expose(model.render(), 0.01, rng)
    img = (img / np.percentile(img, 99.5)).astype(np.float32)
    grid = calibrate_for(img, cfg)
    half = math.floor(cfg.layout.subimage_pitch_px / 2)
    subs = divide(img, grid, 2 * half + 1)
    ref = _models(cfg)[0]
    metrics = compute_metrics(subs.data, subs.centre_x_px, subs.centre_y_px, ref, um_per_px_at_mla=um_per_px_at_mla(cfg))
    position = (0.5 * (grid.residual_x_px + metrics["offset_x_px"]), 0.5 * (grid.residual_y_px + metrics["offset_y_px"]))
    phase = phase_pattern.phase_model((np.mod(grid.grid_x_px, 1.0), np.mod(grid.grid_y_px, 1.0)), "hex")
    raw, _ = ident._local_planes(metrics, position, phase, "hex")
    dev = ident._deviation_maps(metrics, phase_pattern.remove_phase_pattern(raw, phase), position)[2]
    m, n = np.mgrid[:rows, :cols]
    middle = (n >= 4) & (n < cols - 4)
    second = ((m == 2) | (m == rows - 3)) & middle
    inner = (m >= 5) & (m < rows - 5) & middle

    def spread(a):
        return 1.4826 * np.nanmedian(np.abs(a - np.nanmedian(a)))

    for name in ("offset_x_px", "asym_x"):
        assert spread(dev[name][second]) < 1.4 * spread(dev[name][inner]), name
