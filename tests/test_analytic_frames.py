"""Inspection of frames the tracer did not make (tests/analytic_frames.py): the model's own facts first,
then identification on it at several noise levels, rotations, rims and containers — no flood of flags on
healthy lenses, seeded anomalies found, centres where the model put them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from analytic_frames import Anomaly, AnalyticModel, expose, to_counts, write_container
from mlaqc.inspection.pipeline import inspect_file, inspect_image
from mlaqc.inspection.rawio import load_raw
from mlaqc.optics.config import load_config

SMALL = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")
BARE = dict(prnu_rms=0.0, crosstalk=0.0, exit_pupil_px=1e12)  # one disc, nothing but its rim


def _one(**kw) -> AnalyticModel:
    return AnalyticModel(**{"shape": (48, 48), "lenses": (1, 1), **BARE, **kw})


# ------------------------------------------------------------------------------------ model facts


def test_a_gaussian_rim_disc_holds_pi_r2_plus_sigma2():
    """∫ Φ((r - ρ)/σ) 2πρ dρ = π (r² + σ²): the blurred rim's light, exactly."""
    m = _one(radius_px=9.5, rim_sigma_px=0.6)
    assert m.render().sum() == pytest.approx(math.pi * (9.5 ** 2 + 0.6 ** 2), rel=2e-4)


@pytest.mark.parametrize("phase", [(0.0, 0.0), (0.37, -0.21), (-0.5, 0.5), (0.11, 0.93)])
def test_pixel_integration_puts_the_centroid_on_the_true_centre(phase):
    m = _one(phase_px=phase)
    img = m.render()
    y, x = np.mgrid[: img.shape[0], : img.shape[1]]
    cx, cy = m.centres()
    assert abs((img * x).sum() / img.sum() - cx[0, 0]) < 2e-3
    assert abs((img * y).sum() / img.sum() - cy[0, 0]) < 2e-3


def test_the_rim_crosses_half_height_at_the_radius():
    m = _one(radius_px=9.0, rim_sigma_px=0.5, shape=(64, 64))
    img = m.render()
    row = img[int(m.centres()[1][0, 0])]  # centre at (31.5, 31.5): rows 31 and 32 are 0.5 px off the axis
    cx = m.centres()[0][0, 0]
    x = np.arange(row.size)
    right = (x > cx) & (x < cx + 12)
    r_half = np.interp(0.5, row[right][::-1], (x[right] - cx)[::-1])
    assert math.hypot(r_half, 0.5) == pytest.approx(9.0, abs=0.05)


@pytest.mark.parametrize("rim", ["airy", "gaussian"])
def test_a_smaller_circular_aperture_widens_the_rim_by_its_diffraction(rim):
    """Diffraction's edge width goes as λ f / D: an Airy rim behind a lens 0.8 of the pitch wide is 1.25
    times as wide (25-75 % rise; a wide Airy, so the pixel's own width hardly counts); a Gaussian rim
    (all blur together) widens only by the diffraction share in quadrature, and a lens filling its cell
    leaves it exactly as it was."""

    def width(**kw) -> float:
        m = _one(radius_px=20.0, shape=(96, 96), **kw)
        row = m.render()[int(m.centres()[1][0, 0])]
        cx = m.centres()[0][0, 0]
        x = np.arange(row.size) - cx
        right = (x > 5) & (x < 40)
        prof = row[right][::-1] / row[int(cx)]
        return abs(float(np.interp(0.75, prof, x[right][::-1]) - np.interp(0.25, prof, x[right][::-1])))

    if rim == "airy":
        assert width(rim="airy", airy_radius_px=6.0, aperture_rel=0.8) / width(rim="airy", airy_radius_px=6.0) \
            == pytest.approx(1.25, rel=0.02)
    else:
        wide = width(rim_sigma_px=1.0, airy_radius_px=3.0, aperture_rel=0.8)
        sigma = math.sqrt(1.0 + (0.344 * 3.0) ** 2 * (1 / 0.8 ** 2 - 1))  # 1.27 px
        assert wide / width(rim_sigma_px=1.0) == pytest.approx(sigma, rel=0.04)
        assert np.array_equal(_one(aperture_rel=1.0).render(), _one().render())


def test_a_shift_at_90_degrees_moves_the_sub_image_up():
    base = _one()
    moved = base.with_anomalies([Anomaly(0, 0, "shift", 0.4, 90.0)])
    y = np.mgrid[:48, :48][0]
    cy0 = (base.render() * y).sum() / base.render().sum()
    cy1 = (moved.render() * y).sum() / moved.render().sum()
    assert cy1 - cy0 == pytest.approx(-0.4, abs=2e-3)


def test_dim_and_missing_scale_the_flux():
    base = _one().render().sum()
    assert _one().with_anomalies([Anomaly(0, 0, "dim", 0.7)]).render().sum() == pytest.approx(0.7 * base)
    assert _one().with_anomalies([Anomaly(0, 0, "missing", 0.0)]).render().sum() == 0.0


def test_noise_is_as_stated_and_none_is_exact():
    rng = np.random.default_rng(4)
    flat = np.ones((300, 300))
    assert np.array_equal(expose(flat, 0.0, rng), flat)
    assert np.std(expose(flat, 0.05, rng)) == pytest.approx(math.hypot(0.05, 0.05 / 20), rel=0.05)


def test_containers_round_trip_bit_exactly(tmp_path):
    counts = to_counts(np.linspace(0, 1.3, 64 * 64).reshape(64, 64), 12, black=64)  # the top clips at 4095
    assert counts.dtype == np.uint16 and counts.max() == 4095 and counts.min() == 64
    tagged = load_raw(write_container(tmp_path / "t.tif", counts, 12, 64, tags=True))
    assert np.array_equal(tagged.data, counts) and (tagged.black_level, tagged.white_level) == (64, 4095)
    assert tagged.levels_from == "file"
    bare = load_raw(write_container(tmp_path / "b.tif", counts, 12, 64, tags=False))
    assert np.array_equal(bare.data, counts) and bare.levels_from == "container"
    png = load_raw(write_container(tmp_path / "p.png", to_counts(counts / 4095.0, 8), 8, 0))
    assert png.data.max() <= 255


# ---------------------------------------------------------------------------- identification on it


def _small(**kw) -> AnalyticModel:
    return AnalyticModel(shape=(SMALL.sensor.height_px, SMALL.sensor.width_px),
                         lenses=(SMALL.mla.count_h, SMALL.mla.count_w), exit_pupil_px=900.0, **kw)


SEEDED = (Anomaly(6, 7, "shift", 0.5, 30.0), Anomaly(12, 16, "dim", 0.7), Anomaly(17, 5, "missing", 0.0),
          Anomaly(9, 12, "blur", 2.5), Anomaly(15, 11, "size", 0.88))


def _found(result) -> set[tuple[int, int]]:
    return {(d.m - 1, d.n - 1) for d in result.defects}


@pytest.mark.parametrize("kw", [
    dict(rotation_deg=0.7, phase_px=(0.4, 0.15)),
    dict(rotation_deg=-1.8, phase_px=(-0.25, 0.5), rim="airy", extra_falloff=0.3),
    dict(rotation_deg=0.0, phase_px=(0.5, 0.5), rim_sigma_px=0.9, radius_px=9.4),
])
def test_a_noise_free_healthy_frame_passes_with_no_flags_and_exact_centres(kw):
    m = _small(**kw)
    result = inspect_image(m.render().astype(np.float32), SMALL)
    assert result.verdict == "PASS" and result.defects == ()
    g = result.grid
    x, y = m.centres()
    ok = m.inside() & ~g.clipped
    assert np.sqrt(np.mean((g.measured_x_px - x)[ok] ** 2 + (g.measured_y_px - y)[ok] ** 2)) < 0.01
    assert np.sqrt(np.mean((g.grid_x_px - x)[ok] ** 2 + (g.grid_y_px - y)[ok] ** 2)) < 0.01
    assert all(v is None or v > 0 for k, v in result.detection_limit.items() if k.endswith(("_um", "_pos", "_neg")))


@pytest.mark.parametrize("noise, bits, black, tags", [(0.01, 12, 64, False), (0.01, 14, 128, True),
                                                      (0.05, 8, 0, False), (0.15, 16, 0, True)])
def test_seeded_anomalies_are_found_and_healthy_lenses_are_not_flagged(tmp_path, noise, bits, black, tags):
    m = _small(rotation_deg=0.6, phase_px=(0.2, 0.7)).with_anomalies(SEEDED)
    counts = to_counts(expose(m.render(), noise, np.random.default_rng(7)), bits, black)
    path = write_container(tmp_path / ("f.png" if bits == 8 else "f.tif"), counts, bits, black, tags=tags)
    result = inspect_file(path, SMALL)
    seeded = {(a.row, a.col) for a in SEEDED}
    found = _found(result)
    assert found - seeded == set(), f"healthy lenses flagged: {sorted(found - seeded)}"
    strong = seeded if noise <= 0.05 else {(a.row, a.col) for a in SEEDED if a.kind in ("dim", "missing", "blur")}
    assert strong <= found
    assert result.verdict == "FAIL"


def test_a_frame_at_full_scale_with_no_noise_is_not_called_saturated(tmp_path):
    m = _small(rotation_deg=0.3)
    counts = to_counts(m.render() / m.render().max(), 12, 0, white_fraction=1.0)  # the peak at the white level
    result = inspect_file(write_container(tmp_path / "f.tif", counts, 12, 0, tags=True), SMALL)
    assert result.defects == ()


@pytest.mark.parametrize("kw", [dict(rotation_deg=0.7, phase_px=(0.4, 0.15)),
                                dict(rotation_deg=-1.8, phase_px=(-0.25, 0.5), rim="airy", extra_falloff=0.3)])
def test_a_shifted_sub_image_is_measured_as_its_lens_shift_in_micrometres(kw):
    """The model moves one disc by 0.4 px at 30°: that is a lens shift of 0.4 px × p / (sub-image pitch),
    by the geometry of the chief rays (DESIGN.md §2), whatever made the frame."""
    from mlaqc.models.signatures import um_per_px_at_mla

    m = _small(**kw).with_anomalies([Anomaly(6, 7, "shift", 0.4, 30.0), Anomaly(12, 16, "blur", 1.5)])
    M = inspect_image(m.render().astype(np.float32), SMALL).measurements
    dx, dy = M["centre_dx_um"][6, 7], M["centre_dy_um"][6, 7]
    assert np.hypot(dx, dy) == pytest.approx(0.4 * um_per_px_at_mla(SMALL), rel=0.02)
    assert np.degrees(np.arctan2(-dy, dx)) == pytest.approx(30.0, abs=2.0)
    healthy = np.isfinite(M["centre_dx_um"])
    healthy[5:8, 6:9] = healthy[11:14, 15:18] = False
    rms = np.sqrt(np.mean(M["centre_dx_um"][healthy] ** 2 + M["centre_dy_um"][healthy] ** 2))
    assert rms < 0.01 * um_per_px_at_mla(SMALL) * np.sqrt(2)  # the 0.01 px centre bar, per axis
    assert np.all(np.isfinite(M["centre_sigma_um"][healthy]))
    focal = M["focal_rel"][healthy]  # a noise-free frame: finite readings, none made up from noise
    assert np.isfinite(focal).all() and np.percentile(np.abs(focal), 90) < 0.01
