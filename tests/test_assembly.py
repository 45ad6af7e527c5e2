"""Assembly readings (mlaqc/inspection/assembly.py) on rendered small-camera frames with known global errors,
read through the shipped assembly calibration (mlaqc/models/assembly_model.py), and in the report."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mlaqc.inspection.assembly import FIELDS, measure_assembly
from mlaqc.models.assembly_model import AssemblyModel, _nested, assembly_key, assembly_model, render_grid
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.simulate import simulate

FIXTURE = Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml"
CFG = load_config(FIXTURE)
TABLE1 = load_config(FIXTURE.parent / "paper_table1.toml")
# issue #24's bars (a whole Table 1 array); the 24 x 24 array (2.4 mm) reads its tilts to about ±0.2°
# (sigma-checked only)
TOL = {"mla_sensor_distance_um": 3.0, "mla_rotation_deg": 0.01, "mla_tilt_x_deg": 0.1, "mla_tilt_y_deg": 0.1,
       "mla_shift_x_um": 3.0, "mla_shift_y_um": 3.0}
ALL = {"mla_sensor_distance_um": 15.0, "mla_rotation_deg": 0.3, "mla_tilt_x_deg": 0.3, "mla_tilt_y_deg": -0.2,
       "mla_shift_x_um": 20.0, "mla_shift_y_um": -12.0}


def _grid(seed: int, rpp: float = 20, cfg=CFG, **glob):
    return render_grid(cfg, glob, rays_per_pixel=rpp, seed=seed)


def test_the_small_cameras_calibration_is_shipped():
    model = assembly_model(CFG, build_if_missing=False)  # FileNotFoundError if a first inspection had to render it
    assert model.key == assembly_key(CFG) and 170 < model.pupil_mm < 190  # the main lens' rear principal plane: 179 mm


@pytest.mark.parametrize("fixture", ["hex_camera", "circle_camera", "hex_circle_camera"])
def test_the_table1_sized_fixtures_calibrations_are_shipped(fixture, tmp_path, monkeypatch):
    """The Table 1-sized hex and round-lens fixtures' calibrations ship (their 59 frames take minutes): found
    with an empty cache, under their own keys, and physical: the main lens' rear principal plane, each error
    read about 1:1 (the projection fit models the sub-image centres to first order; tilts a few % large)."""
    monkeypatch.setenv("MLAQC_CACHE", str(tmp_path))  # the package's data only
    cfg = load_config(FIXTURE.parent / f"{fixture}.toml")
    model = assembly_model(cfg, build_if_missing=False)
    assert model.key == assembly_key(cfg) != assembly_key(TABLE1) and 170 < model.pupil_mm < 190
    assert all(0.9 < model.poly[j][j][0] < 1.15 for j in range(6))


CASES = [{k: v} for k, v in ALL.items()] + [ALL]


@pytest.mark.parametrize("glob", CASES, ids=["distance", "rotation", "tilt_x", "tilt_y", "shift_x", "shift_y", "all"])
def test_readings_match_known_global_errors(glob):
    a = measure_assembly(_grid(3, **glob), CFG)
    assert a.read and a.lenses_used == CFG.mla.count_w * CFG.mla.count_h and not a.note
    for k in FIELDS:
        truth = glob.get(k, 0.0)
        err = a.value(k) - truth
        assert abs(err) <= 3.5 * a.sigma[k], (k, err, a.sigma[k])
        if "tilt" not in k:
            assert abs(err) <= TOL[k] and (truth == 0 or abs(err) < 0.5 * abs(truth)), (k, a.value(k), truth)


def test_table1_reads_all_six_errors_at_once_within_the_issues_bars():
    a = measure_assembly(_grid(8, cfg=TABLE1, **ALL), TABLE1)
    assert a.read and not a.note
    for k in FIELDS:
        err = a.value(k) - ALL[k]
        assert abs(err) <= TOL[k] and abs(err) <= 3 * a.sigma[k], (k, a.value(k), ALL[k], a.sigma[k])


@pytest.mark.parametrize("cfg", [TABLE1, load_config(FIXTURE.parent / "hex_small_camera.toml")], ids=["table1", "hex"])
def test_a_tilt_beyond_the_calibration_is_read_uncalibrated_and_still_fails_its_bound(cfg):
    """(hex small: its calibration's tilt systematic is 5 deg, wider than the calibrated range, yet the frame
    reads the tilt to 0.03 deg: the reading stays, and so does its bound.)"""
    a = measure_assembly(_grid(9, cfg=cfg, mla_tilt_x_deg=1.5), cfg)
    assert "beyond the calibrated range" in a.note and "not determined" not in a.note
    assert a.value("mla_tilt_x_deg") == pytest.approx(1.5, rel=0.1) and a.sigma["mla_tilt_x_deg"] > 0.1
    qc = dataclasses.replace(cfg.qc, assembly_tilt_deg=1.0)
    assert any("mla_tilt_x_deg" in line for line in a.checked(qc).exceeded)


@pytest.mark.parametrize("seed", [11, 12])
def test_a_frame_with_no_global_error_reads_zero_within_3_sigma(seed):
    a = measure_assembly(_grid(seed), CFG)
    for k in FIELDS:
        assert abs(a.value(k)) <= 3 * a.sigma[k], (k, a.value(k), a.sigma[k])
    assert abs(a.distance_from_focus_um) <= 3 * a.distance_from_focus_sigma_um + 0.5


def test_distance_from_focus_agrees_with_the_grids():
    a = measure_assembly(_grid(5, mla_sensor_distance_um=-25.0), CFG)
    assert a.value("mla_sensor_distance_um") == pytest.approx(-25.0, abs=3.0)
    assert a.distance_from_focus_um == pytest.approx(-25.0, abs=3.0)


def test_a_partial_grid_is_not_read_and_says_why():
    grid = _grid(3)
    cut = type(grid)(**{**grid.__dict__, "rows": 10, "cols": 10})
    a = measure_assembly(cut, CFG)
    assert not a.read and "whole array" in a.reason
    d = a.to_json_dict()
    assert d["mla_rotation_deg"] == {"value": None, "sigma": None} and "not_read" in d


def test_a_damaged_model_file_is_refused():
    good = assembly_model(CFG, build_if_missing=False).to_json_dict()
    for bad in ({"poly": [[0.0]]}, {"version": 0}, {"zero_sigma": [1.0]}, {"single_fit": [0.0] * 5},
                {"zero": [float("nan")] * 7}):
        with pytest.raises(ValueError):
            AssemblyModel.from_json_dict(good | bad)
    with pytest.raises(ValueError):
        AssemblyModel.from_json_dict([good])


def test_optics_without_a_calibration_or_with_a_damaged_one_are_not_read_and_say_why(tmp_path, monkeypatch):
    monkeypatch.setenv("MLAQC_CACHE", str(tmp_path))
    other = dataclasses.replace(CFG, main_lens=dataclasses.replace(CFG.main_lens, diameter_mm=40.0))
    grid = _grid(3)
    a = measure_assembly(grid, other)
    assert not a.read and "mlaqc models" in a.reason
    (tmp_path / f"assembly_{assembly_key(other)}.json").write_text('{"format": "mlaqc-assembly-model", "zero": [1')
    b = measure_assembly(grid, other)
    assert not b.read and "mlaqc models" in b.reason  # a damaged entry is no calibration: nothing crashes


def test_a_frame_showing_a_corner_of_the_array_is_not_read():
    grid = _grid(3)
    keep = np.zeros(grid.shape, bool)
    keep[:6, :6] = True  # 36 of 576 lenses
    corner = type(grid)(**{**grid.__dict__, "measured_x_px": np.where(keep, grid.measured_x_px, np.nan),
                           "measured_y_px": np.where(keep, grid.measured_y_px, np.nan)})
    a = measure_assembly(corner, CFG)
    assert not a.read and "36 of the 576 lenses" in a.reason
    qc = dataclasses.replace(CFG.qc, assembly_distance_um=5.0)
    checked = a.checked(qc)
    assert not checked.exceeded and "not checked" in checked.note and "not checked" in checked.summary_line()


def test_bounds_fail_the_verdict_with_their_own_line_in_every_output(tmp_path):
    em = ErrorMap.zeros(CFG.mla.count_h, CFG.mla.count_w).with_globals(mla_rotation_deg=0.3)
    raw = tmp_path / "frame.npy"
    np.save(raw, simulate(CFG, errors=em, rays_per_pixel=20, seed=4).raw)
    cfg_path = tmp_path / "cam.toml"
    cfg_path.write_text(FIXTURE.read_text() + "\n[qc]\nassembly_rotation_deg = 0.1\nassembly_distance_um = 10\n")
    out = tmp_path / "rep"
    run = subprocess.run([sys.executable, "-m", "mlaqc", "inspect", str(raw), "--config", str(cfg_path),
                          "--out", str(out)], capture_output=True, text=True)
    assert run.returncode == 1, run.stderr
    said = run.stderr  # the bench summary
    assert "FAIL: assembly mla_rotation_deg = +0.3" in said and "qc.assembly_rotation_deg = 0.1" in said
    assert said.count("FAIL: assembly") == 1 and "  assembly: distance" in said
    report = json.loads((out / "report.json").read_text())
    asm = report["assembly"]
    assert report["verdict"] == "FAIL" and len(asm["out_of_bounds"]) == 1
    assert asm["mla_rotation_deg"]["value"] == pytest.approx(0.3, abs=0.01)
    assert set(FIELDS) <= set(asm) and "assumptions" in asm
    html = (out / "report.html").read_text()
    assert 'id="assembly"' in html and "exceeds qc.assembly_rotation_deg" in html


def test_a_negative_bound_is_a_config_error(tmp_path):
    cfg_path = tmp_path / "cam.toml"
    cfg_path.write_text(FIXTURE.read_text() + "\n[qc]\nassembly_tilt_deg = -1\n")
    run = subprocess.run([sys.executable, "-m", "mlaqc", "inspect", "none.npy", "--config", str(cfg_path),
                          "--out", str(tmp_path / "rep")], capture_output=True, text=True)
    assert run.returncode == 2 and "qc.assembly_tilt_deg" in run.stderr and not (tmp_path / "rep").exists()


def test_the_model_is_inverted_exactly_and_its_slopes_are_its_derivative():
    rng = np.random.default_rng(0)
    poly = np.zeros((6, 7, 3))
    poly[:, :6, 0] = np.eye(6) + 0.05 * rng.standard_normal((6, 6))
    poly[:, :, 1:] = 0.01 * rng.standard_normal((6, 7, 2))
    cross = 0.01 * np.triu(np.ones((6, 6)), 1)[None, :, :, None] * rng.standard_normal((2, 6, 6, 7))
    model = AssemblyModel(179.0, tuple(rng.standard_normal(7)), (0.0,) * 7, _nested(poly), (0.0,) * 6, 40.0, "k",
                          _nested(cross))
    true = np.array([3.0, 0.2, -0.3, 0.1, 1.5, -2.0])
    got, _ = model.solve(model.raw(true))
    assert np.allclose(got, true, atol=1e-9)
    h = 1e-6
    numeric = np.stack([(model.raw(true + h * e) - model.raw(true - h * e)) / (2 * h) for e in np.eye(6)], axis=1)
    assert np.allclose(model.slopes(true), numeric, atol=1e-6)
    assert AssemblyModel.from_json_dict(model.to_json_dict()) == model


def test_a_calibration_frame_that_cannot_be_calibrated_is_named(monkeypatch):
    """Building the assembly calibration stops at the first frame the grid cannot be found in, and says
    which placement it was (not only the calibration's own sentence)."""
    import mlaqc.models.assembly_model as am
    from mlaqc.errors import InputError

    def render(cfg, glob, **kw):
        if glob.get("mla_tilt_y_deg"):
            raise InputError("only 5 of the expected microlenses were found")
        return object()  # read by the read_grid below

    monkeypatch.setattr(am, "render_grid", render)
    monkeypatch.setattr(am, "read_grid", lambda grid, cfg, b: (np.zeros(am.COMPONENTS), np.ones(am.COMPONENTS)))
    cfg = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")
    with pytest.raises(InputError, match=r"frame at mla_tilt_y_deg = -0\.6 could not be calibrated: only 5"):
        am.build_assembly_model(cfg)


def test_a_reading_the_frame_cannot_determine_is_not_given_a_number():
    """A telecentric main lens keeps the sub-image pitch at the lens pitch at any MLA-sensor distance: the
    projection fit's distance then carries a 1-sigma wider than the whole calibrated range, and its value
    is whatever the other terms left over (the analytic microscope frame: -903 +- 262 µm on a healthy
    array). Such a reading is left unread and said so, in the console, the JSON and the bounds check."""
    from mlaqc.inspection.assembly import Assembly, _undetermined
    from mlaqc.optics.config import QC

    micro = load_config(FIXTURE.parent / "lfm_40x_relay.toml")
    extent = np.array([40.0, 0.6, 0.6, 0.6, 40.0, 40.0])
    values = dict(zip(FIELDS, (-903.0, 0.0, 0.08, 0.1, 1.2, 0.7)))
    sigma = dict(zip(FIELDS, (262.0, 0.0015, 5.0, 1.3, 3.2, 1.8)))  # with the calibration's systematic error
    frame = np.array([302.0, 0.0015, 0.5, 1.3, 3.0, 1.7])  # the fit's own 1-sigma: tilt y wider than -0.6 to 0.6
    a = _undetermined(Assembly(values, sigma, lenses_used=1936), frame, extent, micro)
    assert np.isnan(a.value("mla_sensor_distance_um")) and np.isnan(a.value("mla_tilt_y_deg"))
    assert a.value("mla_tilt_x_deg") == 0.08 and a.value("mla_shift_x_um") == 1.2  # 1-sigma inside the range: kept
    line = a.summary_line()
    assert "distance not determined" in line and "/ not determined" in line and "nan" not in line
    assert a.value("mla_tilt_x_deg") == 0.08  # a wide systematic error alone does not unread it
    assert "telecentric" in a.note and "mla_sensor_distance_um (the frame's 1σ 302 µm against -40 to 40)" in a.note
    js = json.loads(json.dumps(a.to_json_dict()))
    assert js["mla_sensor_distance_um"] == {"value": None, "sigma": None}
    checked = a.checked(dataclasses.replace(QC(), assembly_distance_um=5.0))
    assert checked.exceeded == () and "qc.assembly_distance_um not checked on mla_sensor_distance_um" in checked.note
    assert "?" in a.short_text()
    # a non-telecentric camera's loose reading is named without the telecentric reason; a tight one is untouched
    loose = _undetermined(Assembly(values, sigma), frame, extent, TABLE1)
    assert "telecentric" not in loose.note and "not determined" in loose.note
    tight = Assembly(values, sigma)
    assert _undetermined(tight, np.array([79.0, 0.001, 0.5, 1.1, 3.0, 1.7]), extent, micro) is tight  # within width
