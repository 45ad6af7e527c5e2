"""Camera config: the Table 1 default, TOML round trip, and validation naming the offending key."""

import dataclasses
from pathlib import Path

import pytest

from mlaqc.errors import InputError
from mlaqc.optics.config import config_from_dict, config_to_toml, default_config, load_config

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"


def test_fixture_is_the_builtin_default_and_round_trips():
    assert load_config(FIXTURES / "paper_table1.toml") == default_config()
    import tomllib
    assert config_from_dict(tomllib.loads(config_to_toml(default_config()))) == default_config()


def test_json_round_trip_keeps_derived_geometry_holes():
    import json
    cfg = load_config(FIXTURES / "small_camera.toml")
    assert config_from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_default_geometry_is_f_number_matched():
    lay = default_config().layout
    assert 42.0 / lay.pupil_to_mla_mm == pytest.approx(0.1 / lay.micro.efl, rel=1e-12)  # D/b = p/f
    assert lay.pupil_to_mla_mm == pytest.approx(176.6, abs=0.1)
    assert lay.subimage_pitch_px == pytest.approx(20.048, abs=0.001)


def test_object_distance_alone_puts_the_mla_at_its_image():
    cfg = config_from_dict({"geometry": {"object_distance_mm": 400.0}})
    lay = cfg.layout
    a = 400.0 + lay.main.front_principal
    assert 1 / a + 1 / lay.pupil_to_mla_mm == pytest.approx(1 / lay.main.efl, rel=1e-12)


@pytest.mark.parametrize("data, key", [
    ({"mla": {"pitch_um": -3}}, "mla.pitch_um"),
    ({"mla": {"refractive_index": 1.0}}, "mla.refractive_index"),
    ({"mla": {"radius_front_um": 60.0}}, "mla.radius_front_um"),
    ({"mla": {"count_w": 500}}, "mla.count_w"),
    ({"main_lens": {"thickness_mm": 1.0}}, "main_lens.thickness_mm"),
    ({"main_lens": {"radius_front_mm": 10.0}}, "main_lens.radius_front_mm"),
    ({"sensor": {"bit_depth": 20}}, "sensor.bit_depth"),
    ({"sensor": {"cfa": "RGBW"}}, "sensor.cfa"),
    ({"sensor": {"qe": 1.5}}, "sensor.qe"),
    ({"sensor": {"width_px": "big"}}, "sensor.width_px"),
    ({"sensor": {"pixel_um": float("nan")}}, "sensor.pixel_um"),
    ({"geometry": {"object_distance_mm": 50.0}}, "geometry.object_distance_mm"),
    ({"mla": {"pich_um": 100}}, "mla.pich_um"),
    ({"trace": {"fresnel": 1}}, "trace.fresnel"),
    ({"trace": {"engine": "gpu"}}, "trace.engine"),
])
def test_validation_names_the_offending_key(data, key):
    with pytest.raises(InputError, match=key.replace(".", r"\.")):
        config_from_dict(data)


def test_unknown_section_and_bad_files(tmp_path):
    with pytest.raises(InputError, match="lense"):
        config_from_dict({"lense": {}})
    bad = tmp_path / "bad.toml"
    bad.write_text("[mla\npitch_um = 3\n")
    with pytest.raises(InputError, match="not valid TOML"):
        load_config(bad)
    with pytest.raises(InputError, match="does not exist"):
        load_config(tmp_path / "missing.toml")
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputError):
        load_config(binary)


def test_config_is_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        default_config().mla.pitch_um = 3  # type: ignore[misc]
