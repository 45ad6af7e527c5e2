"""A frame that is not a flat field (a scene, a frame lit through a structured mask) is refused in one
sentence; white frames of an independent analytic model pass, noise-free to noisy, with strong smooth
fall-off, and with dim and missing lenses of a defective array."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

import analytic_frames as am
from calib_images import SMALL
from mlaqc.cli import main
from mlaqc.errors import InputError
from mlaqc.inspection.calibrate import calibrate_for
from mlaqc.inspection.flatfield import brightness_spread, check_flat_field

SHAPE = (SMALL.sensor.height_px, SMALL.sensor.width_px)
SMALL_TOML = Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml"


def model(**kw) -> am.AnalyticModel:
    return am.AnalyticModel(shape=SHAPE, lenses=(SMALL.mla.count_h, SMALL.mla.count_w), rotation_deg=0.3,
                            phase_px=(0.3, 0.6), **kw)


def frame(m: am.AnalyticModel, noise: float, seed: int = 1, scene: float = 0.0, scale_lenses: float = 3.0):
    """Normalized frame of the model, times a smooth random brightness of `scene` rms (a sample's)."""
    rng = np.random.default_rng(seed)
    img = m.render()
    if scene:
        field = gaussian_filter(rng.standard_normal(img.shape), scale_lenses * SMALL.layout.subimage_pitch_px)
        img = img * np.clip(1.0 + scene * field / field.std(), 0.05, None)
    return (0.7 * am.expose(img, noise, rng)).astype(np.float32)


def lens_flux(img) -> np.ndarray:
    g = calibrate_for(img, SMALL)
    return np.where(g.missing | g.clipped, np.nan, g.flux)


@pytest.mark.parametrize("noise", [0.0, 0.01, 0.05, 0.15])
def test_white_frames_pass_at_every_noise_level(noise):
    check_flat_field(lens_flux(frame(model(), noise)))


def test_smooth_fall_off_and_a_defective_arrays_dim_and_missing_lenses_pass():
    rng = np.random.default_rng(4)
    m = model(extra_falloff=0.3, exit_pupil_px=900.0)
    bad = [am.Anomaly(int(r), int(c), kind, mag) for (r, c), kind, mag in
           zip(rng.integers(2, 22, (40, 2)), ["dim", "missing"] * 20, rng.uniform(0.3, 0.8, 40))]
    check_flat_field(lens_flux(frame(m.with_anomalies(bad), 0.01)))


@pytest.mark.parametrize("contrast, scale", [(0.1, 3.0), (0.3, 1.0), (0.3, 6.0)])
def test_scene_frames_are_refused_in_one_sentence(contrast, scale):
    flux = lens_flux(frame(model(), 0.01, scene=contrast, scale_lenses=scale))
    spread, noise = brightness_spread(flux)
    assert spread > 0.05 and spread > 1.5 * noise
    with pytest.raises(InputError, match="not a flat field"):
        check_flat_field(flux, "the frame")


def test_inspect_refuses_a_scene_exits_2_and_writes_nothing(tmp_path, capsys):
    counts = am.to_counts(frame(model(), 0.01, scene=0.3) / 0.7, 16)
    path = am.write_container(tmp_path / "scene.tif", counts, 16, 0)
    out = tmp_path / "report"
    assert main(["inspect", str(path), "-c", str(SMALL_TOML), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "not a flat field" in err and err.count("\n") == 1
    assert not out.exists()


def test_a_bayer_white_frame_is_prepared_as_the_monochrome_one(tmp_path):
    """The same analytic white frame through an RGGB sensor (sites at QE 0.45 / 0.6 / 0.6 / 0.4) and a
    monochrome one: the loader balances the sites (raw_levels.normalized), so the same image to the noise (a
    checkerboard of the sites' QE otherwise) and the same lens centres."""
    import dataclasses

    from mlaqc.inspection.pipeline import load_frame
    from mlaqc.inspection.raw_write import write_raw

    irradiance = frame(model(), 0.0) / 0.7
    qe = np.tile(np.array([[0.45, 0.6], [0.6, 0.4]]), (SHAPE[0] // 2, SHAPE[1] // 2))
    rng = np.random.default_rng(2)
    images, grids = [], []
    for name, cfa, gain in (("mono", None, 0.6), ("bayer", "RGGB", qe)):
        counts = am.to_counts(am.expose(irradiance * gain, 0.005, rng), 14, 64)
        path = tmp_path / f"{name}.dng"
        write_raw(path, counts, bits=14, cfa=cfa, black_level=64)
        cfg = dataclasses.replace(SMALL, sensor=dataclasses.replace(SMALL.sensor, cfa=cfa or "none", bit_depth=14,
                                                                    black_level_dn=64))
        images.append(load_frame(path, cfg))
        grids.append(calibrate_for(images[-1], cfg))
    mono, bayer = images
    lit = mono > 0.5 * mono.max()
    ratio = bayer[lit] / mono[lit]
    assert np.std(ratio) / np.mean(ratio) < 0.02  # the sites' QE differ by 1.5x: a checkerboard would show 20 %
    d = np.hypot(grids[1].measured_x_px - grids[0].measured_x_px, grids[1].measured_y_px - grids[0].measured_y_px)
    assert float(np.sqrt(np.nanmean(d ** 2))) < 0.02
