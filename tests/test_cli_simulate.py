"""`mlaqc simulate` and `mlaqc errormap` from the command line: outputs, round trips, bad input."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rawpy

from mlaqc.cli import main
from mlaqc.inspection.rawio import load_raw

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
SMALL = str(FIXTURES / "small_camera.toml")


def run(*args):
    return main([str(a) for a in args])


def test_help_lists_the_commands():
    out = subprocess.run([sys.executable, "-m", "mlaqc.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    for cmd in ("simulate", "errormap"):
        assert cmd in out.stdout


@pytest.mark.parametrize("suffix", [".dng", ".tiff", ".npy", ".png"])
def test_simulate_writes_raw_and_ground_truth(tmp_path, suffix):
    out = tmp_path / f"white{suffix}"
    assert run("simulate", "-c", SMALL, "--random-defects", 3, "--seed", 4, "--rays-per-pixel", 2, "-q", "--out", out) == 0
    rec = json.loads((tmp_path / f"white{suffix}.sim.json").read_text())
    # the default (stratified) sampler rounds to a whole number of rays for each of the 26 x 26 padded cells
    assert rec["seed"] == 4 and abs(rec["rays_traced"] - 2 * 496 * 496) <= 26 * 26 / 2
    assert len(rec["error_map"]["lenses"]) == 3
    assert rec["config"]["mla"]["count_w"] == 24
    frame = load_raw(out, expected_shape=(496, 496))
    assert frame.bits == 12 and frame.black_level == 64
    import hashlib
    assert hashlib.sha256(out.read_bytes()).hexdigest() == rec["raw"]["sha256"]


def test_dng_round_trips_through_rawpy_bit_exactly(tmp_path):
    out = tmp_path / "w.npy"
    dng = tmp_path / "w.dng"
    for p in (out, dng):
        assert run("simulate", "-c", SMALL, "--seed", 9, "--rays-per-pixel", 1, "-q", "--out", p) == 0
    ref = np.load(out)
    with rawpy.imread(str(dng)) as raw:
        assert np.array_equal(raw.raw_image, ref)
        assert raw.white_level == json.loads((tmp_path / "w.dng.sim.json").read_text())["raw"]["white_level"]


def test_seeded_simulations_are_bit_identical(tmp_path):
    a, b, c = tmp_path / "a.npy", tmp_path / "b.npy", tmp_path / "c.npy"
    for p, seed in ((a, 1), (b, 1), (c, 2)):
        assert run("simulate", "-c", SMALL, "--seed", seed, "--random-defects", 2, "--rays-per-pixel", 1, "-q", "--out", p) == 0
    assert np.array_equal(np.load(a), np.load(b))
    assert not np.array_equal(np.load(a), np.load(c))


def test_cfa_dng(tmp_path):
    cfg = tmp_path / "cfa.toml"
    cfg.write_text((FIXTURES / "small_camera.toml").read_text() + 'cfa = "RGGB"\n')
    out = tmp_path / "cfa.dng"
    assert run("simulate", "-c", cfg, "--rays-per-pixel", 1, "-q", "--out", out) == 0
    with rawpy.imread(str(out)) as raw:
        assert raw.raw_pattern.tolist() == [[0, 1], [3, 2]]


def test_point_and_texture_scenes(tmp_path):
    assert run("simulate", "-c", SMALL, "--scene", "points", "--points", "0,0;0.5,-0.5", "--rays", 20000, "-q",
               "--no-noise", "--out", tmp_path / "p.npy") == 0
    assert np.load(tmp_path / "p.npy").max() > 64
    tex = tmp_path / "t.npy"
    np.save(tex, np.tile(np.linspace(0, 1, 32), (32, 1)))
    assert run("simulate", "-c", SMALL, "--scene", "texture", "--texture", tex, "--rays-per-pixel", 1, "-q",
               "--out", tmp_path / "t_out.npy") == 0


@pytest.mark.parametrize("args, message", [
    (["--out", "{d}/x.jpg"], "must end in one of"),
    (["--out", "{d}/nodir/x.npy"], "does not exist"),
    (["--out", "{d}/x.npy", "--errors", "{d}/missing.json"], "does not exist"),
    (["--out", "{d}/x.npy", "--config", "{d}/bad.toml"], "not valid TOML"),
    (["--out", "{d}/x.npy", "--scene", "points"], "needs --points"),
    (["--out", "{d}/x.npy", "--scene", "points", "--points", "1;2"], "is not 'x,y'"),
    (["--out", "{d}/x.npy", "--scene", "texture", "--texture", "{d}/bad.toml"], "texture image"),
    (["--out", "{d}/x.npy", "--rays-per-pixel", "-1"], "positive"),
    (["--out", "{d}/x.npy", "--random-defects", "100000"], "cannot place"),
    (["--out", "{d}/x.npy", "--errors", "{d}/wrongshape.json"], "5x5 MLA"),
])
def test_bad_input_is_one_sentence_exit_2_and_no_files(tmp_path, capsys, args, message):
    (tmp_path / "bad.toml").write_text("[mla\n")
    (tmp_path / "wrongshape.json").write_text(json.dumps(
        {"format": "mlaqc-error-map", "version": 1, "shape": {"rows": 5, "cols": 5}, "lenses": []}))
    before = set(tmp_path.iterdir())
    code = run("simulate", "-c" if "--config" not in args else "--quiet", *([SMALL] if "--config" not in args else []),
               *[a.format(d=tmp_path) for a in args])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
    assert set(tmp_path.iterdir()) == before


def test_errormap_command(tmp_path, capsys):
    out = tmp_path / "m.json"
    assert run("errormap", "-c", SMALL, "random", 5, "--seed", 3, "--out", out) == 0
    assert run("errormap", "-c", SMALL, "check", out) == 0
    assert len(capsys.readouterr().out.strip().splitlines()) == 5
    assert run("errormap", "check", out) == 2  # 24x24 map against the 102x102 default camera
