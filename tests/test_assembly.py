"""Assembly readings (mlaqc/inspection/assembly.py) on rendered small-camera frames with known global errors.

Not yet in the report: on the Table 1 camera the distance reads +2.3 µm with no global error (122 sigma;
bench/assembly.py), so the readings stay out of report.json and the verdict until that bias is modelled."""

from pathlib import Path

import numpy as np
import pytest

from mlaqc.inspection.assembly import FIELDS, measure_assembly
from mlaqc.inspection.calibrate import calibrate
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.sensor import white_level
from mlaqc.optics.simulate import simulate

CFG = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")
# per-field tolerance on the 24 x 24 camera (tilts are poorly conditioned on a 3.4 mm array)
TOL = {"mla_sensor_distance_um": 4.0, "mla_rotation_deg": 0.01, "mla_tilt_x_deg": 0.25, "mla_tilt_y_deg": 0.25,
       "mla_shift_x_um": 1.0, "mla_shift_y_um": 1.0}


def _read(seed=3, **glob):
    em = ErrorMap.zeros(CFG.mla.count_h, CFG.mla.count_w).with_globals(**glob)
    sim = simulate(CFG, errors=em, rays_per_pixel=20, seed=seed)
    blk = CFG.sensor.black_level_dn
    img = (sim.raw.astype(np.float32) - blk) / (white_level(CFG.sensor) - blk)
    grid = calibrate(img, expected_pitch_px=CFG.layout.subimage_pitch_px,
                     expected_shape=(CFG.mla.count_h, CFG.mla.count_w))
    return measure_assembly(grid, CFG)


CASES = [{"mla_sensor_distance_um": 15.0}, {"mla_rotation_deg": 0.3}, {"mla_tilt_x_deg": 0.3},
         {"mla_tilt_y_deg": -0.2}, {"mla_shift_x_um": 20.0, "mla_shift_y_um": -12.0},
         {"mla_sensor_distance_um": 15.0, "mla_rotation_deg": 0.3, "mla_tilt_x_deg": 0.3, "mla_tilt_y_deg": -0.2,
          "mla_shift_x_um": 20.0, "mla_shift_y_um": -12.0}]


@pytest.mark.parametrize("glob", CASES)
def test_readings_match_known_global_errors(glob):
    a = _read(**glob)
    for k in FIELDS:
        truth = glob.get(k, 0.0)
        assert abs(a.value(k) - truth) <= max(TOL[k], 3 * a.sigma[k]), (k, a.value(k), truth, a.sigma[k])


@pytest.mark.xfail(strict=False, reason="model bias (exit-pupil aberration) ~2-3 µm in distance not yet in sigma")
def test_zero_error_frame_reads_zero_within_3_sigma():
    a = _read(seed=11)
    for k in ("mla_sensor_distance_um", "mla_rotation_deg", "mla_tilt_x_deg", "mla_shift_x_um", "mla_shift_y_um"):
        assert abs(a.value(k)) <= 3 * a.sigma[k] + 1e-9, (k, a.value(k), a.sigma[k])


def test_json_and_bounds():
    a = _read(mla_rotation_deg=0.3)
    d = a.to_json_dict()
    assert set(FIELDS) <= set(d) and "assumptions" in d
    assert all(set(d[k]) == {"value", "sigma"} for k in FIELDS)

    class QC:
        assembly_rotation_deg = 0.1
    lines = a.out_of_bounds(QC())
    assert len(lines) == 1 and "mla_rotation_deg" in lines[0]
