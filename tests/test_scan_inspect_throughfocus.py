"""`mlaqc scan --inspect` with through-focus frames: each white frame is inspected once its position is
recorded, together with that position's pinhole frames (one combined verdict, as `mlaqc inspect RAW
--through-focus FRAME ...`); pinhole frames are never inspected as white frames; a failed inspection is an
event and the scan goes on; a resumed scan inspects what a kill or a failure left uninspected.

Mock camera (small 24 x 24-lens config, 1 ray per pixel) over the GRBL simulator with the carrier's axes;
every position shows the same array, so the renders after the first come from the mock's cache."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from drivers.capture import load_sidecar
from drivers.scan import EVENTS_NAME, ScanInterrupted, run_scan
from drivers.scan_manifest import MANIFEST_NAME, read_manifest, verify_scan
from drivers.scan_plan import plan_from_dict
from mlaqc.cli import main
from mlaqc.inspection.pipeline import inspect_file
from mlaqc.optics.config import load_config

REPO = Path(__file__).resolve().parents[1]
SMALL = load_config(REPO / "fixtures" / "small_camera.toml")
CAMERA = "mock://?defects=0&rpp=1"
STAGE = "mock://?aux=z,a,b"
TF = {"focus_offsets_mm": [5.0, -5.0], "f_number": 11.0, "spacing_lenses": 4, "offsets": [[0, 0]],
      "exposure_us": 10000.0, "settle_s": 0.0, "iris": "camera", "white_frames": True}
PLAN_TOML = """
[scan]
settle_s = 0.0
retry_delay_s = 0.0
capture_timeout_s = 5.0
exposure_us = 5000.0

[[positions]]
x_mm = 10.0
y_mm = 10.0
label = "a"

[through_focus]
focus_offsets_mm = [5.0, -5.0]
f_number = 11.0
spacing_lenses = 4
offsets = [[0, 0]]
exposure_us = 10000.0
settle_s = 0.0
iris = "camera"
white_frames = true
"""


def plan(labels: str):
    scan = {"settle_s": 0.0, "retry_delay_s": 0.0, "capture_timeout_s": 5.0, "exposure_us": 5000.0}
    return plan_from_dict({"scan": scan,
                           "positions": [{"x_mm": 10.0, "y_mm": 10.0, "label": c} for c in labels],
                           "through_focus": TF}, "p.toml")


def events(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / EVENTS_NAME).read_text().splitlines()]


@pytest.mark.timeout(300)
def test_scan_inspect_combines_each_white_frame_with_its_pinhole_frames(tmp_path):
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(PLAN_TOML)
    out = tmp_path / "scan"
    assert main(["scan", "--camera", CAMERA, "--stage", STAGE, "--plan", str(plan_path), "--out", str(out),
                 "--inspect", "-q"]) == 0
    assert verify_scan(out) == []
    files = [f["file"] for f in read_manifest(out / MANIFEST_NAME).records[0]["files"]]
    assert files == ["pos_00001.tiff", "pos_00001_tf01.tiff", "pos_00001_tf02.tiff"]
    assert sorted(p.name for p in out.glob("*.inspect.json")) == ["pos_00001.tiff.inspect.json"]  # white frame only
    got = json.loads((out / "pos_00001.tiff.inspect.json").read_text())
    tf = got["through_focus"]
    assert tf["frames"] == ["pos_00001_tf01.tiff", "pos_00001_tf02.tiff"]
    assert len(tf["summary"]["pairs"]) == 1 and tf["summary"]["lenses_covered"] > 0
    assert "flags_read_by_pairs" in tf["summary"] and "through_focus" in got["timings_s"]
    # the verdict and flags are those of `mlaqc inspect RAW --through-focus FRAME ...` on the same frames, here
    # handed over as a frame from other software is: its record in a top-level "through_focus" of its .meta.json
    pinholes = []
    for item in read_manifest(out / MANIFEST_NAME).records[0]["files"][1:]:
        pinholes.append(tmp_path / item["file"])
        shutil.copyfile(out / item["file"], pinholes[-1])
        (tmp_path / (item["file"] + ".meta.json")).write_text(json.dumps({"through_focus": item["through_focus"]}))
    same = inspect_file(out / files[0], SMALL, through_focus=pinholes)
    assert (got["verdict"], got["flagged"]) == (same.verdict, len(same.defects))
    flags = [(d["row"], d["col"], d["error_type"]) for d in got["defects"]]
    assert flags == [(d.m, d.n, d.error_type) for d in same.defects]
    assert not [e for e in events(out) if e["event"] == "inspect_failed"]
    # and `mlaqc inspect` of the scan folder pairs the white frame with the same pinhole frames, their
    # records read from the scan's own sidecars
    assert main(["inspect", str(out), "--config", str(REPO / "fixtures" / "small_camera.toml"),
                 "--out", str(tmp_path / "reports"), "-q"]) == (0 if same.verdict == "PASS" else 1)
    (report,) = (tmp_path / "reports").rglob("report.json")
    doc = json.loads(report.read_text())
    assert doc["verdict"] == same.verdict and len(doc["through_focus"]["summary"]["pairs"]) == 1


@pytest.mark.timeout(120)
def test_failed_or_interrupted_inspections_are_events_and_resume_inspects_them(tmp_path):
    out = tmp_path / "scan"
    calls: list[tuple[str, list[str]]] = []

    def seen(frame) -> str:
        for p in frame.through_focus:  # the position is recorded: every pinhole frame is on disk, with its record
            assert load_sidecar(p)["context"]["through_focus"]["record"]["f_number"] == 11.0
        calls.append((frame.path.name, [p.name for p in frame.through_focus]))
        return frame.record["label"]

    def flaky(frame):
        label = seen(frame)
        if label == "a":
            raise RuntimeError("inspection bug")
        if label == "b":
            raise KeyboardInterrupt  # Ctrl-C while the hook runs: b is recorded but not inspected
        return {"label": label}

    def good(frame):
        return {"label": seen(frame)}

    with pytest.raises(ScanInterrupted):
        run_scan(CAMERA, STAGE, plan("abc"), out, inspect=flaky)
    assert calls == [("pos_00001.tiff", ["pos_00001_tf01.tiff", "pos_00001_tf02.tiff"]),
                     ("pos_00002.tiff", ["pos_00002_tf01.tiff", "pos_00002_tf02.tiff"])]
    failed = [e for e in events(out) if e["event"] == "inspect_failed"]
    assert [(e["file"], e["error"]) for e in failed] == [("pos_00001.tiff", "RuntimeError: inspection bug")]
    assert [r["label"] for r in read_manifest(out / MANIFEST_NAME).records] == ["a", "b"]
    assert not list(out.glob("*.inspect.json"))

    calls.clear()
    result = run_scan(CAMERA, STAGE, plan("abc"), out, resume=True, inspect=good)
    assert (result.resumed, result.captured, result.inspected, result.inspect_failures) == (2, 1, 3, 0)
    assert [c[0] for c in calls] == ["pos_00001.tiff", "pos_00002.tiff", "pos_00003.tiff"]  # a, b caught up first
    assert calls[2][1] == ["pos_00003_tf01.tiff", "pos_00003_tf02.tiff"]
    for n, label in enumerate("abc", start=1):
        assert json.loads((out / f"pos_{n:05d}.tiff.inspect.json").read_text()) == {"label": label}
    assert not list(out.glob("*_tf*.inspect.json"))

    again = run_scan(CAMERA, STAGE, plan("abc"), out, resume=True, inspect=lambda f: pytest.fail("inspected twice"))
    assert (again.resumed, again.inspected) == (3, 0) and verify_scan(out) == []
