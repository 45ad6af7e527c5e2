"""The array's edge lenses in calibration (mlaqc.inspection.calibrate `_edge_offsets_removed`): a lens at the
array's edge sees its neighbours' rims on one side only, so a disc fit whose rim is not the optics' reads
every lens of an edge line alike off its centre. Checked against the true centres of analytic frames
(tests/analytic_frames.py: Airy rims, no code shared with the fit): the microscope fixture's sub-images
(46.15 px, an Airy radius of 4.75 px) on a 12 x 12 array, where the two outer rings are half the lenses."""

import json

import numpy as np
import pytest

import analytic_frames as am
from mlaqc.errors import InputError
from mlaqc.inspection.calibrate import calibrate
from mlaqc.inspection.grid import Grid, load_grid

LENSES = 12


def _frame(anomalies=(), noise=0.0):
    model = am.AnalyticModel(shape=(620, 600), lenses=(LENSES, LENSES), pitch_px=46.154, radius_px=23.0, rim="airy",
                             airy_radius_px=4.75, exit_pupil_px=1e12, phase_px=(0.37, 0.21), rotation_deg=0.3,
                             anomalies=tuple(anomalies))
    img = model.render()
    if noise:
        img = am.expose(img, noise, np.random.default_rng(4))
    return model, (0.8 * img / img.max()).astype(np.float32)


def _errors(model, grid):
    cx, cy = model.centres()
    ok = model.inside() & ~grid.clipped & ~grid.missing
    m, n = np.mgrid[:LENSES, :LENSES]
    ring = np.minimum.reduce([m, n, LENSES - 1 - m, LENSES - 1 - n])
    return np.hypot(grid.measured_x_px - cx, grid.measured_y_px - cy), np.hypot(grid.grid_x_px - cx, grid.grid_y_px - cy), ok, ring


@pytest.fixture(scope="module")
def healthy():
    model, img = _frame()
    return model, calibrate(img, expected_pitch_px=46.154, expected_shape=(LENSES, LENSES))


def test_edge_lenses_are_measured_as_well_as_inner_ones(healthy):
    """Measured centres 0.005 px RMS from the truth (0.054 before: the outer ring read 0.10 px inward), the
    outer ring's within 0.04 px; the model's prediction within 0.01 px everywhere (0.13 px off at the edge
    before: its terms took up part of the edge's offset)."""
    model, grid = healthy
    err, grid_err, ok, ring = _errors(model, grid)
    assert ok[ring == 0].sum() >= 40
    assert np.sqrt(np.mean(err[ok] ** 2)) < 0.01 and err[ok & (ring == 0)].max() < 0.04
    assert grid_err[ok].max() < 0.015


def test_the_offsets_taken_off_are_named_and_point_inward(healthy):
    _, grid = healthy
    offsets = {name: (n, dx, dy) for name, n, dx, dy in grid.edge_offsets}
    assert set(offsets) >= {"ring 0 top", "ring 0 bottom", "ring 0 left", "ring 0 right"}
    assert 0.06 < offsets["ring 0 top"][2] < 0.15 and -0.15 < offsets["ring 0 bottom"][2] < -0.06
    assert 0.06 < offsets["ring 0 left"][1] < 0.15 and -0.15 < offsets["ring 0 right"][1] < -0.06
    assert not [name for name in offsets if not name.startswith("ring 0")]  # the outer ring's lines only


@pytest.mark.parametrize("row, col", [(0, 5), (6, 11), (1, 4)])
def test_a_lens_own_shift_stays(row, col):
    """An edge lens moved 0.4 px keeps its move: the offset taken off is its line's, not its own. Its own
    read-off changes with its gap to its neighbours (moved 0.2 px outward, the outer ring's lens read 0.043 px
    inward before, not 0.1), so it keeps an error of up to two thirds of its line's offset; a lens off the
    outer ring 0.02 px at most."""
    model, img = _frame([am.Anomaly(row, col, "shift", 0.4, 30.0)], noise=0.01)
    grid = calibrate(img, expected_pitch_px=46.154, expected_shape=(LENSES, LENSES))
    err, _, ok, _ = _errors(model, grid)
    assert err[row, col] < (0.08 if min(row, col, LENSES - 1 - row, LENSES - 1 - col) == 0 else 0.02)
    assert np.hypot(grid.residual_x_px[row, col], grid.residual_y_px[row, col]) == pytest.approx(0.4, abs=0.07)


def test_edge_offsets_in_grid_json(healthy, tmp_path):
    _, grid = healthy
    grid.save(tmp_path / "grid.json")
    back = load_grid(tmp_path / "grid.json")
    assert back.edge_offsets == grid.edge_offsets
    data = json.loads((tmp_path / "grid.json").read_text())
    assert data["model"]["edge_offsets_px"][0].keys() == {"group", "lenses", "x", "y"}
    del data["model"]["edge_offsets_px"]  # a grid written before them
    assert Grid.from_json_dict(data).edge_offsets == ()
    for bad in ([{"group": "ring 0 top", "x": 0.1}], [{"group": "ring 9 top", "lenses": 5, "x": 0.0, "y": 0.1}],
                [{"group": "ring 0 top", "lenses": 5, "x": 0.0, "y": 0.1}] * 2,
                [{"group": "ring 0 top", "lenses": 5, "x": 0.1, "y": 0.1}],
                [{"group": "ring 0 top", "lenses": LENSES + 1, "x": 0.0, "y": 0.1}]):  # more than the side has
        data["model"]["edge_offsets_px"] = bad
        with pytest.raises(InputError, match="edge_offsets_px"):
            Grid.from_json_dict(data)


def test_uncorrected_centres_are_the_disc_fits(healthy, monkeypatch):
    """`Grid.uncorrected_centres` gives back what the fit read (the assembly reading's input, as its shipped
    calibrations were built): the same frame calibrated with no edge group large enough to be corrected."""
    from mlaqc.inspection import calibrate as cal

    model, grid = healthy
    _, img = _frame()
    monkeypatch.setattr(cal, "EDGE_GROUP_MIN", 10**6)
    raw = calibrate(img, expected_pitch_px=46.154, expected_shape=(LENSES, LENSES))
    assert raw.edge_offsets == ()
    x, y = grid.uncorrected_centres()
    np.testing.assert_allclose(x, raw.measured_x_px, rtol=0, atol=1e-9)
    np.testing.assert_allclose(y, raw.measured_y_px, rtol=0, atol=1e-9)


def test_a_hex_arrays_edges_and_row_ends():
    """Hex (16 x 14, the row ends that stick out a group of their own, which read more of their neighbours'
    rims): the centres' RMS down from what the fit read (0.021 against 0.029 px: the second ring's own
    offset, 0.03 px outward here, is not taken off), each outer line's offset pointing inward, the model
    within 0.06 px (0.03 before: its terms rest on the lines inside the outer ones)."""
    model = am.AnalyticModel(shape=(720, 720), lenses=(16, 14), pitch_px=46.154, radius_px=23.0, rim="airy",
                             airy_radius_px=4.75, exit_pupil_px=1e12, phase_px=(0.37, 0.21), rotation_deg=0.3,
                             packing="hex")
    img = model.render()
    grid = calibrate((0.8 * img / img.max()).astype(np.float32), expected_pitch_px=46.154, expected_shape=(16, 14),
                     packing="hex")
    cx, cy = model.centres()
    ok = model.inside() & ~grid.clipped & ~grid.missing
    raw_x, raw_y = grid.uncorrected_centres()
    rms = np.sqrt(np.mean(((grid.measured_x_px - cx) ** 2 + (grid.measured_y_px - cy) ** 2)[ok]))
    raw = np.sqrt(np.mean(((raw_x - cx) ** 2 + (raw_y - cy) ** 2)[ok]))
    assert rms < 0.8 * raw, (rms, raw)
    assert np.hypot(grid.grid_x_px - cx, grid.grid_y_px - cy)[ok].max() < 0.06
    offsets = {name: (dx, dy) for name, _, dx, dy in grid.edge_offsets}
    assert {"ring 0 left, row ends that stick out", "ring 0 left"} <= set(offsets)
    assert not [name for name in offsets if not name.startswith("ring 0")]
    assert offsets["ring 0 top"][1] > 0.03 and offsets["ring 0 bottom"][1] < -0.03
    assert offsets["ring 0 left, row ends that stick out"][0] > offsets["ring 0 left"][0] > 0
    assert offsets["ring 0 right, row ends that stick out"][0] < offsets["ring 0 right"][0] < 0


@pytest.mark.parametrize("side", [7, 8])
def test_the_smallest_arrays_settle(side, caplog):
    """7 x 7 and 8 x 8: the model and the outer lines' offsets settle (in 15 and 13 fits), centres 0.008 px
    RMS against 0.046 px as the fit read them; with the second ring's lines freed too they did not settle in
    40 rounds, and where they did, the model rested on the 3 x 3 middle (0.029 px)."""
    model = am.AnalyticModel(shape=(360 + 40 * (side - 7),) * 2, lenses=(side, side), pitch_px=46.154, radius_px=23.0,
                             rim="airy", airy_radius_px=4.75, exit_pupil_px=1e12, phase_px=(0.37, 0.21), rotation_deg=0.3)
    img = model.render()
    grid = calibrate((0.8 * img / img.max()).astype(np.float32), expected_pitch_px=46.154, expected_shape=(side, side))
    assert "did not settle" not in caplog.text and grid.edge_offsets
    cx, cy = model.centres()
    ok = model.inside() & ~grid.clipped & ~grid.missing
    assert np.sqrt(np.mean(((grid.measured_x_px - cx) ** 2 + (grid.measured_y_px - cy) ** 2)[ok])) < 0.012
    assert np.hypot(grid.grid_x_px - cx, grid.grid_y_px - cy)[ok].max() < 0.01
