"""Dark frames and frame stacks (issue #24, part 1): the master dark (median, sigma-clipped mean), its
hot and dead pixels, the subtraction that recovers a clean frame from one with a camera's dark pattern
(amplifier glow in a corner up to 400 DN, ±6 DN column offsets, 2,000 hot pixels), stacks averaged to
one, the checks (size, bit depth, exposure, gain, a lit "dark"), and the CLI end to end on the small
camera's analytic frames (tests/analytic_frames.py: no code shared with the tracer)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import analytic_frames as am
from mlaqc.cli import main
from mlaqc.errors import InputError
from mlaqc.inspection import darks
from mlaqc.inspection.raw_levels import normalized
from mlaqc.inspection.raw_write import write_raw
from mlaqc.inspection.rawio import RawFrame
from mlaqc.optics.config import load_config

ROOT = Path(__file__).resolve().parent.parent
SMALL_TOML = str(ROOT / "fixtures" / "small_camera.toml")
SMALL = load_config(SMALL_TOML)
BITS, BLACK, READ = 12, 64, 3.0
SPAN = (1 << BITS) - 1 - BLACK


def dark_stack(pattern: np.ndarray, n: int, seed: int = 1, read: float = READ) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [am.dark_frame(pattern, read, rng, BITS, BLACK) for _ in range(n)]


def write_darks(folder: Path, frames, exposure_us=1000.0, gain=1.0, stem="dark") -> list[str]:
    paths = []
    for k, counts in enumerate(frames):
        p = folder / f"{stem}{k}.tiff"
        write_raw(p, counts, bits=BITS, black_level=BLACK)
        meta(p, dark=True, exposure_us=exposure_us, gain=gain)
        paths.append(str(p))
    return paths


def meta(path: Path, *, dark: bool, exposure_us=1000.0, gain=1.0, shape=None) -> None:
    """The `.meta.json` sidecar `mlaqc capture` writes (the fields the checks read)."""
    h, w = shape or SMALL.sensor.height_px, SMALL.sensor.width_px
    Path(str(path) + ".meta.json").write_text(json.dumps(
        {"format": "mlaqc-frame", "version": 1, "file": Path(path).name, "dark": dark, "bits": BITS, "cfa": None,
         "width": w, "height": h, "black_level": BLACK, "exposure_us": exposure_us, "gain": gain}))


def build(frames, tmp_path: Path, **kw) -> darks.MasterDark:
    return darks.build_master_dark(write_darks(tmp_path, frames), **kw)


# ------------------------------------------------------------------------------------ master dark


def test_dark_subtraction_recovers_the_clean_frame_within_noise(tmp_path):
    """A smooth lit frame plus the dark pattern plus read noise, less the master of 4 darks: the clean
    frame within the noise (frame's read noise and the master's in quadrature), the hot pixels replaced by
    their neighbours; without the dark the glow is 400 DN and the hot pixels stand out."""
    shape = (512, 512)
    pattern = am.DarkPattern(shape=shape)  # glow 400 DN in a corner, ±6 DN columns, 2,000 hot pixels
    level = pattern.level()
    master = build(dark_stack(level, 4), tmp_path)
    y, x = np.mgrid[:shape[0], :shape[1]]
    clean = 0.3 + 0.4 * np.exp(-((x - 200.0) ** 2 + (y - 300.0) ** 2) / 2e4)  # a smooth field, 0..1 of the span
    rng = np.random.default_rng(9)
    counts = np.rint(BLACK + clean * SPAN + level + READ * rng.standard_normal(shape)).astype(np.uint16)
    frame = RawFrame(counts, BITS, None, BLACK, (1 << BITS) - 1)
    img = darks.correct([frame], master)
    err = (img - clean) * SPAN  # counts
    good = ~master.bad
    expected = np.hypot(READ, master.noise_dn)
    assert abs(err[good].mean()) < 0.1
    assert err[good].std() == pytest.approx(np.hypot(expected, 1 / np.sqrt(12)), rel=0.08)
    assert np.abs(err[good]).max() < 6 * expected
    assert np.abs(err[master.bad]).max() < 6 * expected  # hot pixels: their neighbours' median of a smooth field
    raw_err = (normalized(frame) - clean) * SPAN  # no dark: the pattern is all there
    assert raw_err[0, -1] > 350 and raw_err.max() > 1000


def test_master_dark_median_and_clipped_mean(tmp_path):
    """Nine darks, each with 300 cosmic-ray hits: the median and the sigma-clipped mean both reject them
    (the plain mean would not); the clipped mean is the less noisy, and each master's stated noise is its
    measured one."""
    shape = (256, 256)
    level = am.DarkPattern(shape=shape, hot=100).level()
    frames = dark_stack(level, 9, seed=3)
    rng = np.random.default_rng(4)
    for f in frames:
        hit = rng.choice(f.size, 300, replace=False)
        f.ravel()[hit] = np.minimum(f.ravel()[hit] + 500, (1 << BITS) - 1)
    paths = write_darks(tmp_path, frames)
    truth = BLACK + level
    errors = {}
    for method in ("median", "mean"):
        m = darks.build_master_dark(paths, method=method)
        assert m.method == method and m.frames == 9
        assert m.read_noise_dn == pytest.approx(np.hypot(READ, 1 / np.sqrt(12)), rel=0.05)
        err = m.level - truth
        assert np.abs(err).max() < 7 * m.noise_dn  # no hit survives
        assert err.std() == pytest.approx(np.hypot(m.noise_dn, 0.29 / 3), rel=0.1)
        errors[method] = err.std()
    assert errors["mean"] < 0.93 * errors["median"]  # √(π/2) → about 1.2 at nine frames
    plain = np.mean(np.stack(frames).astype(float), axis=0) - truth
    assert np.abs(plain).max() > 40  # what the rejection is for


@pytest.mark.parametrize("cfa", [None, "RGGB"])
def test_hot_and_dead_pixel_map_found_exactly(tmp_path, cfa):
    """2,000 hot pixels (40 to 3,000 DN) and 50 dead ones (reading 0) under glow and column offsets, on
    a 1024 x 1024 frame: found exactly, mono and Bayer."""
    pattern = am.DarkPattern(shape=(1024, 1024), seed=31)
    level = pattern.level()
    rng = np.random.default_rng(5)
    dead = rng.choice(level.size, 60, replace=False)
    hot = np.zeros(level.shape, bool)
    hot[pattern.hot_pixels()] = True
    dead = np.unravel_index(dead[~hot.ravel()[dead]][:50], level.shape)
    level[dead] = -BLACK  # reads 0: well below its neighbours
    paths = []
    for k, counts in enumerate(dark_stack(level, 4, seed=6)):
        paths.append(tmp_path / f"d{k}.tiff")
        write_raw(paths[-1], counts, bits=BITS, cfa=cfa, black_level=BLACK)
    m = darks.build_master_dark(paths)
    want_dead = np.zeros(level.shape, bool)
    want_dead[dead] = True
    assert np.array_equal(m.hot, hot)
    assert np.array_equal(m.dead, want_dead)
    assert m.summary()["hot_pixels"] == 2000 and m.summary()["dead_pixels"] == 50


def test_a_stack_of_frames_lowers_the_noise_by_root_n():
    """Four frames of one state averaged: the pixel noise halves; the noise info says 1/√4."""
    rng = np.random.default_rng(2)
    clean = np.full((128, 128), 0.5)
    frames = [RawFrame(np.rint(BLACK + clean * SPAN + 20 * rng.standard_normal(clean.shape)).astype(np.uint16), BITS,
                       None, BLACK, (1 << BITS) - 1) for _ in range(4)]
    one = darks.correct(frames[:1])
    four = darks.correct(frames)
    assert np.std(four - 0.5) == pytest.approx(0.5 * np.std(one - 0.5), rel=0.08)
    info = darks.noise_info(4, None)
    assert info["frames_averaged"] == 4 and info["noise_scale"] == 0.5
    assert "1/√4" in darks.noise_notes(info)[0]


# ------------------------------------------------------------------------------------ bad input


def lit_white(tmp_path: Path, scale: float = 1.0, name: str = "lit.tiff") -> Path:
    """A white frame of the small camera (analytic), `scale` of the white level, with a dark sidecar."""
    m = am.AnalyticModel(shape=(496, 496), lenses=(24, 24), exit_pupil_px=900.0, rotation_deg=0.7)
    counts = np.rint(BLACK + scale * 0.8 * SPAN * m.render() + READ * np.random.default_rng(1).standard_normal((496, 496)))
    path = tmp_path / name
    write_raw(path, counts.astype(np.uint16), bits=BITS, black_level=BLACK)
    meta(path, dark=True)
    return path


def test_a_lit_dark_is_refused(tmp_path):
    """A "dark" with the light on is refused by its median; one with a dim leak (2 % of the white level,
    median within the darks' tolerance) by the sub-image lattice it shows; real darks pass."""
    pitch = SMALL.layout.subimage_pitch_px
    with pytest.raises(InputError, match=r"dark frame lit\.tiff is lit: its median"):
        darks.build_master_dark([lit_white(tmp_path)], pitch_px=pitch)
    dim = lit_white(tmp_path, 0.02, "dim.tiff")
    darks.build_master_dark([dim])  # no lattice check without the pitch: the median alone lets it through
    with pytest.raises(InputError, match=r"dark frame dim\.tiff is lit: it shows the microlenses' sub-images"):
        darks.build_master_dark([dim], pitch_px=pitch)
    # one lit frame among good darks is found (a median master would hide it)
    level = am.DarkPattern(shape=(496, 496), hot=300).level()
    good = write_darks(tmp_path, dark_stack(level, 3))
    with pytest.raises(InputError, match="dim.tiff is lit"):
        darks.build_master_dark([*good, dim], pitch_px=pitch)
    m = darks.build_master_dark(good, pitch_px=pitch)
    assert m.hot.sum() == 300
    assert darks.lattice_ratio(np.asarray(m.level), pitch) < 50


def test_darks_and_frames_must_match(tmp_path):
    """Size, bit depth, exposure and gain (from the sidecars) each in one sentence; a stack's frames too."""
    level = am.DarkPattern(shape=(496, 496), hot=100).level()
    m = build(dark_stack(level, 2), tmp_path)
    base = darks.FrameFacts("f.tiff", (496, 496), BITS, None, False, 1000.0, 1.0)
    m.check(base)
    cases = [(dict(shape=(480, 480)), "is 496x496 px but the frame f.tiff is 480x480 px"),
             (dict(bits=14), "has 12-bit counts but the frame f.tiff has 14-bit counts"),
             (dict(exposure_us=2000.0), "was exposed 1000 µs but the frame f.tiff 2000 µs"),
             (dict(gain=4.0), "was taken at gain 1 but the frame f.tiff at 4")]
    for change, text in cases:
        with pytest.raises(InputError, match=text) as exc:
            m.check(base.__class__(**{**base.__dict__, **change}))
        assert str(exc.value).count(". ") == 0  # one sentence
    m.check(base.__class__(**{**base.__dict__, "exposure_us": None, "gain": None}))  # unknown: not checked
    other = darks.FrameFacts("g.tiff", (496, 496), BITS, None, False, 1500.0, 1.0)
    with pytest.raises(InputError, match="frames averaged into one must share"):
        darks.compare(base, other, "frame", "frame")


# ------------------------------------------------------------------------------------ CLI


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """Small-camera analytic frames: white frames with 4 seeded anomalies, with and without the dark
    pattern (glow, columns, 2,000 hot pixels: 0.8 % of this small sensor), 4 dark frames, all 12-bit TIFFs
    with sidecars."""
    d = tmp_path_factory.mktemp("darks_cli")
    model = am.AnalyticModel(shape=(496, 496), lenses=(24, 24), exit_pupil_px=900.0, rotation_deg=0.7)
    rng = np.random.default_rng(3)
    model = model.with_anomalies(am.random_anomalies(model, 4, rng, kinds=("shift", "dim", "blur", "size")))
    irr = model.render()
    level = am.DarkPattern(shape=(496, 496)).level()

    def white(name: str, pattern: bool, seed: int) -> str:
        r = np.random.default_rng(seed)
        counts = BLACK + am.expose(irr, 0.01, r) * 0.8 * SPAN + (level if pattern else 0) + READ * r.standard_normal(irr.shape)
        path = d / name
        write_raw(path, np.clip(np.rint(counts), 0, (1 << BITS) - 1).astype(np.uint16), bits=BITS, black_level=BLACK)
        meta(path, dark=False)
        return str(path)

    files = {"clean": white("clean.tiff", False, 10), "white": [white(f"white{k}.tiff", True, 20 + k) for k in range(4)],
             "darks": write_darks(d, dark_stack(level, 4, seed=7)), "dir": d}
    return files


def run_cli(*args, config=SMALL_TOML) -> int:
    return main(["inspect", *map(str, args), "-c", str(config), "-q"])


def flagged(folder: Path) -> set:
    return {(d["row"], d["col"]) for d in json.loads((folder / "report.json").read_text())["defects"]}


def test_cli_with_dark_flags_what_the_clean_frame_flags(bench, tmp_path):
    """Inspected with --dark, the patterned frame flags the same lenses as the pattern-free one; without
    it, the hot pixels (dense here) defeat the white frame's own guess. With the default (sag-intersection)
    signature tables they cost detection: significant deviations below the reportable size and a worse
    limit; with grid tables, whose tilt signature the hot pixels mimic above its reportable size, healthy
    lenses are flagged as well (run with `boundaries = "grid"` set explicitly to show it). report.json's
    detection limit and notes say what the dark did."""
    run_cli(bench["clean"], "--out", tmp_path / "clean")
    run_cli(bench["white"][0], "--out", tmp_path / "raw")
    run_cli(bench["white"][0], "--dark", *bench["darks"], "--out", tmp_path / "dark")
    assert flagged(tmp_path / "dark") == flagged(tmp_path / "clean")
    reports = {k: json.loads((tmp_path / k / "report.json").read_text()) for k in ("clean", "raw", "dark")}
    assert reports["raw"]["summary"]["below_reportable"] > reports["dark"]["summary"]["below_reportable"]
    for key in ("pitch_um", "radius_rel_pos"):
        assert reports["raw"]["detection_limit"][key] > reports["dark"]["detection_limit"][key]
    grid = tmp_path / "grid.toml"
    grid.write_text(Path(SMALL_TOML).read_text().replace("[mla]", '[mla]\nboundaries = "grid"'))
    for name, args in (("clean", [bench["clean"]]), ("raw", [bench["white"][0]]),
                       ("dark", [bench["white"][0], "--dark", *bench["darks"]])):
        run_cli(*args, "--out", tmp_path / f"grid_{name}", config=grid)
    assert flagged(tmp_path / "grid_dark") == flagged(tmp_path / "grid_clean")
    assert len(flagged(tmp_path / "grid_raw")) > len(flagged(tmp_path / "grid_clean"))
    report = json.loads((tmp_path / "dark" / "report.json").read_text())
    noise = report["detection_limit"]["noise"]
    assert noise["frames_averaged"] == 1 and noise["dark"]["frames"] == 4 and noise["dark"]["hot_pixels"] == 2000
    assert any(n.startswith("Dark-subtracted") for n in report["notes"])
    assert "noise" not in json.loads((tmp_path / "clean" / "report.json").read_text())["detection_limit"]


def test_cli_stack_white_and_calibrate(bench, tmp_path):
    """--stack 4 averages four raws into one report; --white takes several frames; calibrate too."""
    assert run_cli(*bench["white"], "--stack", "4", "--dark", *bench["darks"], "--out", tmp_path / "s") in (0, 1)
    report = json.loads((tmp_path / "s" / "report.json").read_text())
    assert report["detection_limit"]["noise"]["frames_averaged"] == 4
    assert report["detection_limit"]["noise"]["noise_scale"] == 0.5
    assert any(n.startswith("Averaged from 4 frames") for n in report["notes"])
    assert not (tmp_path / "s" / "batch.csv").exists()
    assert run_cli(bench["white"][0], "--white", *bench["white"][1:], "--dark", *bench["darks"],
                   "--out", tmp_path / "w") in (0, 1)
    grid = tmp_path / "grid.json"
    assert main(["calibrate", *bench["white"][:2], "--dark", *bench["darks"], "--dark-method", "mean",
                 "-c", SMALL_TOML, "--out", str(grid), "-q"]) == 0
    from mlaqc.inspection.calibrate import load_grid

    assert (load_grid(grid).rows, load_grid(grid).cols) == (24, 24)


def test_cli_batch_builds_the_master_dark_once(bench, tmp_path, monkeypatch):
    calls = []
    real = darks.build_master_dark
    monkeypatch.setattr(darks, "build_master_dark", lambda *a, **k: calls.append(a) or real(*a, **k))
    assert run_cli(*bench["white"][:3], "--dark", *bench["darks"], "--out", tmp_path / "b") in (0, 1)
    assert len(calls) == 1
    assert len((tmp_path / "b" / "batch.csv").read_text().splitlines()) == 4


def test_cli_scan_folder_finds_its_dark_frames(bench, tmp_path):
    """A scan folder (manifest.jsonl) with dark frames beside it, their sidecars saying dark: used."""
    scan = tmp_path / "scan"
    scan.mkdir()
    files = []
    for k, src in enumerate(bench["white"][:2]):
        name = f"pos_{k + 1:05d}.tiff"
        (scan / name).write_bytes(Path(src).read_bytes())
        meta(scan / name, dark=False)
        files.append({"type": "position", "index": k + 1, "files": [{"file": name, "through_focus": None}]})
    (scan / "manifest.jsonl").write_text("\n".join(json.dumps(r) for r in [{"type": "header"}, *files]) + "\n")
    write_darks(scan, [darks.load_raw(p).data for p in bench["darks"]], stem="dark_")
    assert run_cli(scan, "--out", tmp_path / "r") in (0, 1)
    for k in (1, 2):
        report = json.loads((tmp_path / "r" / f"pos_{k:05d}" / "report.json").read_text())
        assert report["detection_limit"]["noise"]["dark"]["frames"] == 4
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["batch.csv", "pos_00001", "pos_00002"]
    # `mlaqc scan --inspect` finds them too, as each position is recorded
    from types import SimpleNamespace

    from mlaqc.inspection.pipeline import scan_frame_hook

    header = {"camera_settings": {"config": json.loads(json.dumps(SMALL.to_dict()))}}  # as the manifest holds it
    out = scan_frame_hook(SimpleNamespace(header=header,
                                          path=str(scan / "pos_00001.tiff"), through_focus=()))
    assert out["detection_limit"]["noise"]["dark"]["hot_pixels"] == 2000


@pytest.mark.parametrize("case", ["size", "bits", "exposure", "gain", "lit", "stack-gain", "stack-dark-gain",
                                  "stack-count"])
def test_cli_bad_input_exit_2_and_nothing_written(bench, tmp_path, capsys, case):
    d = tmp_path / "in"
    d.mkdir()
    level = am.DarkPattern(shape=(496, 496), hot=50).level()
    raws = [bench["white"][0]]
    extra = []
    if case == "size":
        dk = [str(d / "d.tiff")]
        write_raw(dk[0], dark_stack(am.DarkPattern(shape=(480, 480), hot=10).level(), 1)[0], bits=BITS,
                  black_level=BLACK)
        text = "is 480x480 px but the camera's sensor is 496x496 px"
    elif case == "bits":
        dk = [str(d / "d.tiff")]
        write_raw(dk[0], dark_stack(level, 1)[0], bits=14, black_level=BLACK)
        text = "has 14-bit counts but the frame"
    elif case == "exposure":
        dk = write_darks(d, dark_stack(level, 2), exposure_us=2000.0)
        text = "was exposed 2000 µs but the frame white0.tiff 1000 µs"
    elif case == "gain":
        dk = write_darks(d, dark_stack(level, 2), gain=2.0)
        text = "was taken at gain 2 but the frame white0.tiff at 1"
    elif case == "lit":
        dk = [str(lit_white(d, 0.02))]
        text = "is lit: it shows the microlenses' sub-images"
    elif case in ("stack-gain", "stack-dark-gain"):
        dk = bench["darks"] if case == "stack-dark-gain" else []
        other = d / "other.tiff"
        other.write_bytes(Path(bench["white"][1]).read_bytes())
        meta(other, dark=False, gain=3.0)
        raws, extra = [bench["white"][0], str(other)], ["--stack", "2"]
        text = ("the dark frame dark0.tiff was taken at gain 1 but the frame other.tiff at 3" if dk else
                "the frame white0.tiff was taken at gain 1 but the frame other.tiff at 3: frames averaged into one")
    else:
        dk = bench["darks"]
        raws, extra = bench["white"][:3], ["--stack", "2"]
        text = "--stack 2 averages every 2 raws into one, but 3 raws were given"
    out = tmp_path / "out"
    capsys.readouterr()
    assert run_cli(*raws, *extra, *(["--dark", *dk] if dk else []), "--out", out) == 2
    err = capsys.readouterr().err
    assert text in err and err.count("\n") == 1, err
    assert not out.exists()


def test_a_dask_task_gets_the_batch_master_dark_and_stack(bench):
    """What a Dask worker runs (`inspect_remote`): the master dark travels in the BatchSpec (once per
    batch), the stack's paths with the task; run here, without a cluster."""
    import pickle

    from mlaqc.commands.inspect import BatchSpec, inspect_remote

    raw = bench["white"][0]
    spec = pickle.loads(pickle.dumps(BatchSpec(SMALL, None, None, SMALL.to_dict(),
                                               {raw: darks.build_master_dark(bench["darks"])})))
    out = inspect_remote(spec, raw, raw, True, (), tuple(bench["white"][:2]))
    report = json.loads(out["contents"]["json"])
    assert report["detection_limit"]["noise"]["frames_averaged"] == 2
    assert report["detection_limit"]["noise"]["dark"]["frames"] == 4
