"""Optics from datasheet numbers (mlaqc.optics.datasheet): an objective and tube lens, a camera lens by its
f-number and exit pupil, an MLA by focal length and profile, a relay; checked against first-order optics
(lensmaker's equation, the Abbe sine condition, chief rays) and against sub-image pitches measured on
rendered frames, and every contradiction between keys refused naming the key."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from mlaqc.cli import main
from mlaqc.errors import InputError
from mlaqc.inspection.calibrate import calibrate
from mlaqc.models.signatures import KINDS, physical_kinds, window_half_px
from mlaqc.optics.config import config_from_dict, config_to_toml, default_config, load_config
from mlaqc.optics.datasheet import mla_radii_um, objective
from mlaqc.optics.errormap import ErrorMap, physical_types
from mlaqc.optics.paraxial import thick_lens
from mlaqc.optics.raytrace import MainLens, Rays
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
LFM = load_config(FIXTURES / "lfm_40x_relay.toml")
HANDHELD = load_config(FIXTURES / "handheld_hex_bayer.toml")


def small(cfg, count: int, extra: dict | None = None):
    """The same optics with `count` x `count` lenses on a sensor just holding them (+ 2 lenses a side)."""
    d = json.loads(json.dumps(cfg.to_dict()))
    side = int(math.ceil((count + 2) * cfg.layout.subimage_pitch_px)) // 2 * 2
    d["mla"].update(count_w=count, count_h=count)
    d["sensor"].update(width_px=side, height_px=side, cfa="none")
    for sec, table in (extra or {}).items():
        d.setdefault(sec, {}).update(table)
    return config_from_dict(d)


def measured_pitch_px(cfg) -> float:
    """Sub-image pitch of a noise-free white render, as the calibration measures it (mean of x and y)."""
    photons = Renderer(cfg).render(WhiteScene(), rays_per_pixel=40, seed=3).photons
    grid = calibrate((photons / (1.25 * photons.max())).astype(np.float32),
                     expected_pitch_px=cfg.layout.subimage_pitch_px,
                     expected_shape=(cfg.mla.count_h, cfg.mla.count_w), packing=cfg.mla.packing)
    return float(np.mean(grid.pitch_px))


def test_plano_convex_radius_is_f_times_n_minus_1_and_has_that_focal_length():
    front, back = mla_radii_um(3000.0, 1.458, 1000.0, "plano-convex")
    assert front == pytest.approx(3000.0 * 0.458, rel=1e-15) and math.isinf(back)
    assert thick_lens(front, back, 1000.0, 1.458).efl == pytest.approx(3000.0, rel=1e-12)  # lensmaker, thick
    assert LFM.mla.radius_front_um == pytest.approx(1374.0) and LFM.layout.micro.efl == pytest.approx(3.0, rel=1e-12)


@pytest.mark.parametrize("f_um, n, t_um", [(420.4, 1.56, 10.0), (3000.0, 1.458, 1000.0), (40.0, 1.5, 30.0)])
def test_biconvex_radius_solves_the_thick_lensmaker_equation(f_um, n, t_um):
    front, back = mla_radii_um(f_um, n, t_um, "biconvex")
    assert back == -front
    assert thick_lens(front, back, t_um, n).efl == pytest.approx(f_um, rel=1e-12)


def test_table1_microlens_from_its_focal_length_gives_its_radii():
    cfg = default_config()
    f_um = cfg.layout.micro.efl * 1e3
    again = config_from_dict({"mla": {"focal_length_um": f_um, "profile": "biconvex"}})
    assert again.mla.radius_front_um == pytest.approx(469.0, rel=1e-9)
    assert again.layout.subimage_pitch_px == pytest.approx(cfg.layout.subimage_pitch_px, rel=1e-9)


def test_objective_is_converted_by_the_sine_condition_and_the_tube_lens():
    assert LFM.main_lens.f_number == pytest.approx(40 / (2 * 0.95), rel=1e-12)
    obj = objective(60.0, 1.2, 180.0, 200.0)  # a 60x/1.2 quoted for 200 mm, used with a 180 mm tube lens
    assert obj.magnification == pytest.approx(54.0) and obj.f_number == pytest.approx(54.0 / 2.4)


def test_telecentric_subimage_pitch_is_the_lens_pitch_through_the_relay_to_0_1_percent():
    expected = 150.0 * 2.0 / 6.5  # lens pitch x relay magnification / pixel
    assert LFM.layout.subimage_pitch_px == pytest.approx(expected, rel=1e-5)
    assert measured_pitch_px(small(LFM, 6)) == pytest.approx(expected, rel=1e-3)


def test_finite_exit_pupil_spreads_the_subimages_by_b_plus_gap_over_b():
    cfg = small(HANDHELD, 16, {"main_lens": {"exit_pupil_mm": 10.0}, "mla": {"packing": "square"}})
    lay = cfg.layout
    gap_mm = lay.z_sensor_mm - lay.z_mla_mm
    expected = 20.0 * (10.0 + gap_mm) / 10.0 / 1.4  # chief rays from the pupil's centre
    assert expected / (20.0 / 1.4) - 1 > 3e-3  # the pupil's distance matters at this precision
    assert measured_pitch_px(cfg) == pytest.approx(expected, rel=5e-4)


def test_an_ideal_main_lens_passes_image_side_rays_unchanged():
    lens = MainLens(LFM)
    rng = np.random.default_rng(1)
    n = 1000
    d = rng.normal(size=(3, n)) * [[0.05], [0.05], [0.0]] + [[0.0], [0.0], [-1.0]]
    d /= np.linalg.norm(d, axis=0)
    r = Rays(rng.uniform(-3, 3, n), rng.uniform(-3, 3, n), np.full(n, 50.0), d[0], d[1], d[2], np.ones(n))
    before = np.stack([r.L, r.M, r.N])
    lens.trace_back(r)
    assert np.allclose(np.stack([r.L, r.M, r.N]), before, rtol=0, atol=1e-15)
    assert np.allclose(r.w, 1.0, rtol=0, atol=1e-14)


def test_telecentric_white_frame_has_no_cos4_falloff():
    cfg = small(LFM, 8, {"formation": {"diffraction": False}})
    photons = Renderer(cfg).render(WhiteScene(), rays_per_pixel=40, seed=2).photons
    p = cfg.layout.subimage_pitch_px
    h, w = photons.shape
    c0 = (h - 8 * p) / 2

    def flux(m, n):
        y0, x0 = int(c0 + m * p), int(c0 + n * p)
        return photons[y0:y0 + int(p), x0:x0 + int(p)].sum()

    centre, corner = flux(4, 4), flux(0, 0)
    assert corner / centre == pytest.approx(1.0, abs=5e-3)


def test_datasheet_configs_round_trip_through_toml_and_json():
    for cfg in (LFM, HANDHELD):
        assert config_from_dict(tomllib.loads(config_to_toml(cfg))) == cfg
        assert config_from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_configs_without_the_new_keys_keep_their_dicts():
    d = default_config().to_dict()
    assert "relay" not in d and "f_number" not in d["main_lens"] and "focal_length_um" not in d["mla"]


@pytest.mark.parametrize("data, key", [
    ({"main_lens": {"magnification": 40, "na": 0.95, "f_number": 10}}, "main_lens.f_number"),
    ({"main_lens": {"f_number": 4, "radius_front_mm": 50}}, "main_lens.radius_front_mm"),
    ({"main_lens": {"magnification": 40}}, "main_lens.na"),
    ({"main_lens": {"f_number": 4}}, "main_lens.exit_pupil_mm"),
    ({"main_lens": {"f_number": 0.3, "exit_pupil_mm": 50}}, "main_lens.f_number"),
    ({"main_lens": {"f_number": 4, "exit_pupil_mm": -5}}, "main_lens.exit_pupil_mm"),
    ({"main_lens": {"f_number": 4, "exit_pupil_mm": 50}, "geometry": {"mla_distance_mm": 30}}, "geometry.mla_distance_mm"),
    ({"mla": {"focal_length_um": 420, "radius_front_um": 300}}, "mla.radius_front_um"),
    ({"mla": {"profile": "plano-convex"}}, "mla.profile"),
    ({"mla": {"focal_length_um": 420, "profile": "meniscus"}}, "mla.profile"),
    ({"mla": {"focal_length_um": 5, "profile": "biconvex", "thickness_um": 10}}, "mla.thickness_um"),
    ({"relay": {"magnification": -1.0}}, "relay.magnification"),
    ({"relay": {"magnification": 1.0, "f_number": 8.0}}, "relay.f_number"),  # Table 1's lenses are f/4.2
    ({"relay": {"magnification": 3.0}}, "mla.count_w"),  # the relayed MLA no longer fits the sensor
])
def test_contradicting_or_impossible_optics_keys_are_refused_naming_the_key(data, key):
    with pytest.raises(InputError, match=key.replace(".", r"\.")):
        config_from_dict(data)


def test_a_bad_datasheet_config_exits_2_and_writes_nothing(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[main_lens]\nmagnification = 40\nna = 0.95\nf_number = 10\n")
    out = tmp_path / "x.tiff"
    assert main(["simulate", "-c", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "main_lens.f_number" in err and err.count("\n") == 1
    assert not out.exists() and not list(tmp_path.glob("x.tiff*"))


def test_an_ideal_main_lens_refuses_object_side_sampling_in_one_sentence():
    with pytest.raises(InputError, match="ideal main lens"):
        Renderer(LFM, sampling="object")


def test_a_through_focus_frame_of_an_ideal_main_lens_is_one_sentence(tmp_path, capsys):
    """The pinholes are imaged through the main lens' surfaces, which a datasheet lens does not have: exit 2,
    one sentence naming the keys, no file (it was an AttributeError)."""
    out = tmp_path / "tf.tiff"
    assert main(["simulate", "-c", str(FIXTURES / "lfm_40x_relay.toml"), "--scene", "through-focus",
                 "--focus-offset-mm", "0.5", "--out", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert "ideal main lens" in err and "main_lens.radius_front_mm" in err and err.count("\n") == 1
    assert not list(tmp_path.iterdir())


def test_a_flat_sided_mla_has_no_decenter_kind():
    assert [k.name for k in physical_kinds(LFM)] == [k.name for k in KINDS if k.name != "decenter"]
    assert physical_kinds(default_config()) == KINDS
    assert physical_types(("pitch", "decenter"), LFM.mla) == ("pitch",)
    with pytest.raises(InputError, match="plano-convex"):
        physical_types(("decenter",), LFM.mla)
    em = ErrorMap.zeros(3, 3)
    em.lens["decenter_um"][1, 1] = 10.0  # a decenter of a plano-convex lens moves a plane along itself
    cfg = small(LFM, 3)
    a = Renderer(cfg).render(WhiteScene(), rays_per_pixel=20, seed=1).photons
    b = Renderer(cfg, em).render(WhiteScene(), rays_per_pixel=20, seed=1).photons
    assert np.array_equal(a, b)


def test_windows_follow_the_subimage_pitch():
    assert window_half_px(default_config()) == 10
    assert window_half_px(LFM) == 23


def test_a_frame_whose_pitch_the_config_cannot_explain_is_warned_naming_the_keys():
    from mlaqc.inspection.optics_check import pitch_notes

    expected = LFM.layout.subimage_pitch_px
    assert pitch_notes(expected * 1.004, LFM) == ()  # an array's own pitch scale
    (note,) = pitch_notes(expected * 0.98, LFM)
    assert note.startswith("WARNING") and "relay.magnification" in note and "-2.0%" in note
    (note,) = pitch_notes(default_config().layout.subimage_pitch_px * 1.03, default_config())
    assert "geometry.mla_distance_mm" in note and "relay" not in note


def test_a_flat_back_leaves_the_aperture_to_the_front_sag_alone():
    from mlaqc.optics.formation import aperture_corner_radius_um

    r, t = LFM.mla.radius_front_um, LFM.mla.thickness_um
    assert aperture_corner_radius_um(LFM) == pytest.approx(math.sqrt(r * r - (r - t) ** 2), rel=1e-9)  # sag = t
    assert math.isinf(aperture_corner_radius_um(HANDHELD))  # 30 µm substrate, 3.7 µm sag at the hexagon's corner


def test_models_prints_the_derived_numbers_a_user_checks(capsys):
    from mlaqc.commands.models import print_derived_numbers

    print_derived_numbers(LFM, "lfm.toml")
    err = capsys.readouterr().err
    assert "f/21.05" in err and "46.1540 px" in err and "1374.00 µm" in err and "2314.13 µm" in err
    print_derived_numbers(default_config(), None)
    err = capsys.readouterr().err
    assert "20.0478 px" in err and "417.14 µm" in err and "f/2.5 at infinity" in err
