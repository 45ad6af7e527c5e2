"""Headless capture: files and sidecars, checksums, averages, dark frames, warnings, CLI exit codes."""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np
import pytest

from drivers.camera import open_camera
from drivers.capture import (SIDECAR_SUFFIX, capture, grab, load_sidecar, save_frame, sidecar_path, verify_frame)
from mlaqc.cli import main
from mlaqc.errors import InputError
from mlaqc.inspection.rawio import load_raw

URL = "mock://?rpp=1&seed=4"


def sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def listing(folder):
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else None


def test_frames_with_sidecars_and_checksums(tmp_path):
    cam = open_camera(URL)
    saved = capture(cam, tmp_path / "out", frames=3, exposure_us=4000, gain=1.5, position_mm=(10.0, 10.0))
    names = [s.path.name for s in saved]
    assert names == ["frame_000001.tiff", "frame_000002.tiff", "frame_000003.tiff"]
    assert listing(tmp_path / "out") == sorted(names + [n + SIDECAR_SUFFIX for n in names])
    for k, item in enumerate(saved, start=1):
        rec = json.loads(sidecar_path(item.path).read_text())
        assert rec == load_sidecar(item.path)
        assert rec["format"] == "mlaqc-frame" and rec["file"] == item.path.name
        assert rec["sha256"] == sha(item.path) == item.sha256 and rec["bytes"] == item.path.stat().st_size
        assert (rec["sequence"], rec["sequences"], rec["sequence_gap"]) == (k, [k], 0)
        assert (rec["exposure_us"], rec["gain"]) == (4000.0, 1.5)  # read back
        assert (rec["pixel_format"], rec["bits"], rec["cfa"], rec["width"], rec["height"]) == ("Y16", 12, None, 496, 496)
        assert rec["black_level"] == 64 and rec["white_level"] == cam.capture().extra["white_level"]
        assert rec["stage_position_mm"] == [10.0, 10.0] and rec["dark"] is False
        assert rec["device"] == URL and rec["camera"].startswith("mock camera")
        assert rec["versions"]["mlaqc"] and rec["versions"]["numpy"] == np.__version__
        assert rec["device_extra"]["truth"]["array"] == "W(1,1)"
        assert isinstance(rec["device_timestamp_s"], float) and rec["host_time"].endswith("+00:00")
        assert rec["average"]["frames"] == 1 and rec["warnings"] == []
        raw = load_raw(item.path)
        assert (raw.bits, raw.black_level, raw.white_level, raw.data.dtype) == (12, 64, rec["white_level"], np.uint16)
        assert raw.metadata["acquisition"]["sequence"] == k  # provenance also inside the raw file
        assert verify_frame(item.path, rec["sha256"]) is None
    item = saved[0]
    item.path.write_bytes(item.path.read_bytes()[:-10] + b"0123456789")
    assert "checksum" in verify_frame(item.path)
    sidecar_path(saved[1].path).unlink()
    assert "no sidecar" in verify_frame(saved[1].path)


def test_average_is_the_rounded_mean_of_k_frames(tmp_path):
    cam, twin = open_camera(URL), open_camera(URL)  # same seed: the twin delivers the same frames
    item = capture(cam, tmp_path, frames=1, average=4, file_format="dng")[0]
    stack = np.stack([twin.capture().data.astype(np.float64) for _ in range(4)])
    expected = np.rint(stack.mean(axis=0)).astype(np.uint16)
    raw = load_raw(item.path)
    assert item.path.name == "frame_000001.dng" and raw.bits == 12
    assert np.array_equal(raw.data, expected)
    rec = item.record
    assert rec["sequences"] == [1, 2, 3, 4] and rec["average"] == {
        "frames": 4, "method": "mean, rounded half to even", "significant_bits": 12}
    assert len(rec["device_timestamps_s"]) == 4 and rec["sha256"] == sha(item.path)


def test_dark_frames_and_exposure_warnings(tmp_path):
    dark_cam = open_camera(URL + "&light=0")
    dark = capture(dark_cam, tmp_path, frames=2, dark=True)
    assert [d.path.name for d in dark] == ["dark_000001.tiff", "dark_000002.tiff"]
    assert all(d.warnings == [] and d.record["dark"] for d in dark)  # black is legitimate for darks
    warned: list[str] = []
    black = capture(dark_cam, tmp_path, frames=1, prefix="lit", on_warning=warned.append)[0]
    assert any("black" in w for w in black.warnings) and warned and "lit_000001.tiff" in warned[0]
    lit = capture(open_camera(URL), tmp_path, frames=1, dark=True, prefix="notdark")[0]
    assert any("not dark" in w for w in lit.warnings)
    cam = open_camera(URL + "&faults=saturated@1,drop@3x2")
    sat = save_frame(tmp_path / "sat.tiff", grab(cam))
    assert any("saturated" in w for w in sat.warnings)
    gap = save_frame(tmp_path / "gap.tiff", grab(cam, average=2))
    assert gap.record["sequence_gap"] == 2 and any("lost" in w for w in gap.warnings)


def test_python_api_refuses_before_writing(tmp_path):
    cam = open_camera(URL)
    (tmp_path / "frame_000002.tiff").write_bytes(b"keep me")
    with pytest.raises(InputError, match="frame_000002.tiff"):
        capture(cam, tmp_path, frames=3)
    assert listing(tmp_path) == ["frame_000002.tiff"] and (tmp_path / "frame_000002.tiff").read_bytes() == b"keep me"
    with pytest.raises(InputError, match="frames"):
        capture(cam, tmp_path / "new", frames=0)
    with pytest.raises(InputError, match="exposure"):
        capture(cam, tmp_path / "new", exposure_us=1e12)
    with pytest.raises(InputError, match="format"):
        capture(cam, tmp_path / "new", file_format="png")
    assert not (tmp_path / "new").exists()


# --------------------------------------------------------------------------------------------- CLI


def test_cli_capture_writes_frames(tmp_path, capsys):
    out = tmp_path / "cap"
    rc = main(["capture", "--camera", URL, "--out", str(out), "--frames", "2", "--average", "3",
               "--exposure-us", "3000", "--gain", "2", "--format", "tiff"])
    assert rc == 0
    assert listing(out) == ["frame_000001.tiff", "frame_000001.tiff.meta.json",
                            "frame_000002.tiff", "frame_000002.tiff.meta.json"]
    rec = load_sidecar(out / "frame_000002.tiff")
    assert rec["sequences"] == [4, 5, 6] and (rec["exposure_us"], rec["gain"]) == (3000.0, 2.0)
    assert rec["sha256"] == sha(out / "frame_000002.tiff")
    assert "wrote 2 frames (each the average of 3)" in capsys.readouterr().err


def test_cli_dark_capture(tmp_path, capsys):
    assert main(["capture", "--camera", URL + "&light=0", "--out", str(tmp_path / "d"), "--dark", "-q"]) == 0
    assert listing(tmp_path / "d") == ["dark_000001.tiff", "dark_000001.tiff.meta.json"]
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("camera", ["nonsense", "mock://?bogus=1", "warpcam://x", "mock://?wafer=abc"])
def test_cli_bad_url_exits_2_without_files(tmp_path, capsys, camera):
    out = tmp_path / "never"
    assert main(["capture", "--camera", camera, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mlaqc capture: error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists() and listing(tmp_path) == []


def test_cli_bad_out_dir_exits_2_without_files(tmp_path, capsys):
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    assert main(["capture", "--camera", URL, "--out", str(a_file)]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert main(["capture", "--camera", URL, "--out", str(tmp_path / "missing" / "deeper")]) == 2
    assert "does not exist" in capsys.readouterr().err
    existing = tmp_path / "old"
    existing.mkdir()
    (existing / "frame_000001.tiff.meta.json").write_text("{}")
    assert main(["capture", "--camera", URL, "--out", str(existing)]) == 2
    assert "already holds" in capsys.readouterr().err
    assert listing(tmp_path) == ["file.txt", "old"] and listing(existing) == ["frame_000001.tiff.meta.json"]
    for bad in (["--frames", "0"], ["--average", "-2"], ["--exposure-us", "-5"], ["--gain", "nan"],
                ["--exposure-us", "1e12"], ["--timeout-s", "0"], ["--prefix", "../evil"]):
        assert main(["capture", "--camera", URL, "--out", str(tmp_path / "n"), *bad]) == 2, bad
        assert capsys.readouterr().err.count("\n") == 1
    assert not (tmp_path / "n").exists()


def test_cli_unwritable_out_dir(tmp_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root can write anywhere")
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    assert main(["capture", "--camera", URL, "--out", str(locked)]) == 2
    assert "not writable" in capsys.readouterr().err


def test_cli_device_failure_exits_3_without_files(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["capture", "--camera", "v4l2:///dev/no-such-video-node", "--out", str(out)]) == 3
    assert "not found" in capsys.readouterr().err and not out.exists()
    assert main(["capture", "--camera", URL + "&faults=disconnect@1", "--out", str(out)]) == 3
    assert "disconnected" in capsys.readouterr().err and not out.exists()
    assert main(["capture", "--camera", URL + "&faults=timeout@1", "--timeout-s", "0.2", "--out", str(out)]) == 3
    assert "timed out" in capsys.readouterr().err and not out.exists()
