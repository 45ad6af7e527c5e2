"""Scans: plan validation, a 200-position mock scan with faults + SIGKILL + resume, Ctrl-C, retries, CLI errors."""

from __future__ import annotations

import _thread
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from drivers.camera import open_camera
from drivers.capture import load_sidecar
from drivers.scan import ScanFailed, ScanInterrupted, default_inspect_hook, run_scan
from drivers.scan_manifest import MANIFEST_NAME, read_manifest, verify_scan
from drivers.scan_plan import load_plan, plan_from_dict
from drivers.stage import open_stage
from mlaqc.cli import main
from mlaqc.errors import InputError
from waiting import stays, wait_until

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO / "fixtures"


def write_plan(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def records(out: Path) -> list[dict]:
    return read_manifest(out / MANIFEST_NAME).records


def events(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]


def wait_for_records(out: Path, count: int, proc: subprocess.Popen, timeout_s: float) -> int:
    """Poll the manifest until it holds `count` position records (or the process ends)."""

    def recorded() -> int:
        manifest = out / MANIFEST_NAME
        return manifest.read_bytes().count(b"\n") - 1 if manifest.exists() else 0

    wait_until(lambda: recorded() >= count or proc.poll() is not None, timeout_s, poll_s=0.02)
    if recorded() >= count:
        return recorded()
    raise AssertionError(f"the scan did not record {count} positions in {timeout_s} s (exit {proc.poll()}): "
                         f"{proc.stderr.read().decode() if proc.poll() is not None else ''}")


def _sigint_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def scan_cli(*args: str) -> subprocess.Popen:
    """`mlaqc scan` in a child that takes Ctrl-C as from a terminal (a runner that started the tests in
    the background hands down SIGINT ignored, and Python then never raises KeyboardInterrupt)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", "mlaqc.cli", "scan", *args], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=_sigint_default)


@pytest.fixture
def python_sigint():
    """Python's own Ctrl-C handler for the test, whatever SIGINT disposition the runner handed down
    (`_thread.interrupt_main` does nothing while SIGINT is ignored)."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


# --------------------------------------------------------------------------------------------- plans


@pytest.mark.timeout(10)
def test_fixture_plans_load():
    raster = load_plan(FIXTURES / "scan_plan_raster.toml")
    assert raster.kind == "raster" and len(raster.positions) == 9
    assert [(p.x_mm, p.y_mm) for p in raster.positions[:6]] == [
        (10, 10), (15, 10), (20, 10), (20, 15), (15, 15), (10, 15)]  # serpentine
    assert raster.positions[3].label == "r002c003" and raster.positions[3].file_names(1, ".tiff") == ["pos_00004.tiff"]
    listed = load_plan(FIXTURES / "scan_plan_list.toml")
    assert [p.label for p in listed.positions] == ["W(1,1)", "W(1,1)+50um", "W(3,3)"]
    assert (listed.average, listed.retries, listed.exposure_us, listed.kind) == (4, 2, 8000.0, "list")
    ycols = plan_from_dict({"raster": {"origin_mm": [0, 0], "step_mm": [1, 2], "count": [2, 3], "serpentine": False,
                                       "fast_axis": "y"}})
    assert [(p.x_mm, p.y_mm) for p in ycols.positions] == [(0, 0), (0, 2), (0, 4), (1, 0), (1, 2), (1, 4)]
    assert ycols.digest != raster.digest and ycols.positions[1].file_names(2, ".dng") == [
        "pos_00002_f1.dng", "pos_00002_f2.dng"]


GOOD_RASTER = {"origin_mm": [0, 0], "step_mm": [1, 1], "count": [2, 2]}


@pytest.mark.timeout(10)
@pytest.mark.parametrize("data, key", [
    ({}, "exactly one"),
    ({"raster": GOOD_RASTER, "positions": [{"x_mm": 1, "y_mm": 1}]}, "exactly one"),
    ({"raster": GOOD_RASTER, "extra": 1}, "'.extra'"),
    ({"raster": {**GOOD_RASTER, "speed": 3}}, "'raster.speed'"),
    ({"raster": {"step_mm": [1, 1], "count": [2, 2]}}, "'raster.origin_mm' is missing"),
    ({"raster": {**GOOD_RASTER, "count": [2, 0]}}, "'raster.count'"),
    ({"raster": {**GOOD_RASTER, "count": [2.5, 1]}}, "'raster.count'"),
    ({"raster": {**GOOD_RASTER, "step_mm": [0, 1]}}, "'raster.step_mm'"),
    ({"raster": {**GOOD_RASTER, "origin_mm": [1, "a"]}}, "'raster.origin_mm'"),
    ({"raster": {**GOOD_RASTER, "serpentine": "yes"}}, "'raster.serpentine'"),
    ({"raster": {**GOOD_RASTER, "fast_axis": "z"}}, "'raster.fast_axis'"),
    ({"raster": GOOD_RASTER, "scan": {"settle_s": -1}}, "'scan.settle_s'"),
    ({"raster": GOOD_RASTER, "scan": {"retries": 1.5}}, "'scan.retries'"),
    ({"raster": GOOD_RASTER, "scan": {"frames_per_position": 0}}, "'scan.frames_per_position'"),
    ({"raster": GOOD_RASTER, "scan": {"move_timeout_s": 0}}, "'scan.move_timeout_s'"),
    ({"raster": GOOD_RASTER, "scan": {"home": "sometimes"}}, "'scan.home'"),
    ({"raster": GOOD_RASTER, "scan": {"format": "png"}}, "'scan.format'"),
    ({"raster": GOOD_RASTER, "scan": {"exposure": 5}}, "'scan.exposure'"),
    ({"raster": GOOD_RASTER, "scan": 3}, "'scan' must be a table"),
    ({"positions": []}, "'positions'"),
    ({"positions": [{"x_mm": 1}]}, "'positions[0].y_mm' is missing"),
    ({"positions": [{"x_mm": 1, "y_mm": True}]}, "'positions[0].y_mm'"),
    ({"positions": [{"x_mm": 1, "y_mm": 1, "z_mm": 0}]}, "'positions[0].z_mm'"),
    ({"positions": [{"x_mm": 1, "y_mm": 1, "label": "a"}, {"x_mm": 2, "y_mm": 1, "label": "a"}]},
     "'positions[1].label' repeats"),
])
def test_plan_errors_name_the_key(data, key):
    with pytest.raises(InputError, match=key.replace("(", r"\(").replace("[", r"\[").replace("]", r"\]")):
        plan_from_dict(data, "p.toml")


@pytest.mark.timeout(10)
def test_plan_file_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_plan(tmp_path / "nope.toml")
    with pytest.raises(InputError, match="not valid TOML"):
        load_plan(write_plan(tmp_path / "bad.toml", "[raster\n"))


# --------------------------------------------------------------------------------------------- the big one

BIG_PLAN = """
[scan]
settle_s = 0.0
retries = 3
retry_delay_s = 0.0
capture_timeout_s = 0.3
move_timeout_s = 5.0

[raster]
origin_mm = [10.0, 10.0]
step_mm = [5.0, 5.0]
count = [20, 10]
serpentine = true
"""
BIG_CAMERA = "mock://?wafer=20x10&pitch_mm=5&origin_mm=10,10&defects=3&seed=11&rpp=0.25&exposure_us=1500&faults=timeout@15,drop@25x2,black@35"


@pytest.mark.timeout(120)
def test_200_position_scan_survives_faults_kill_and_resume(tmp_path):
    plan_path = write_plan(tmp_path / "plan.toml", BIG_PLAN)
    out = tmp_path / "scan"
    # 1. A CLI scan in a subprocess, killed with SIGKILL part-way (camera faults from the URL fire in it).
    proc = scan_cli("--camera", BIG_CAMERA, "--stage", "mock://", "--plan", str(plan_path), "--out", str(out), "-q")
    try:
        wait_for_records(out, 50, proc, timeout_s=60)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    before = records(out)
    assert 50 <= len(before) < 200
    done = {r["index"] for r in before}
    # 2. Make the worst leftovers of a kill deterministic: an unrecorded frame (kill between the frame write
    #    and the manifest append), a temporary file of an interrupted write, a torn manifest line.
    victim = min(set(range(200)) - done)
    victim_file = out / f"pos_{victim + 1:05d}.tiff"
    victim_file.write_bytes(b"half a frame from the killed run")
    (out / f".pos_{victim + 2:05d}.tiff.x1y2z3.part.tiff").write_bytes(b"partial")
    with open(out / MANIFEST_NAME, "ab") as fh:
        fh.write(b'{"type":"position","index":' + str(victim).encode())
    # 3. Resume in-process with stage and camera faults injected mid-scan.
    faults = {5: lambda r: r.stage.sim.disconnect_mid_move(0.5),  # stage cable pulled mid-move
              15: lambda r: r.camera.inject_fault("timeout"),  # camera timeout
              25: lambda r: r.camera.inject_fault("disconnect", count=2),  # camera unplugged; 1st reopen fails
              35: lambda r: r.stage.sim.alarm_mid_move(1, 0.5),  # GRBL hard-limit alarm mid-move
              45: lambda r: r.stage.sim.disconnect(),  # stage cable pulled between positions
              55: lambda r: r.camera.inject_fault("drop", count=3)}  # frames lost
    attempted = [0]

    def inject(runner, pos):  # called once per position still to do
        action = faults.get(attempted[0])
        attempted[0] += 1
        if action is not None:
            action(runner)

    seen_events: list[dict] = []
    t0 = time.monotonic()
    result = run_scan(BIG_CAMERA, "mock://", plan_path, out, resume=True, before_position=inject,
                      on_event=seen_events.append)
    elapsed = time.monotonic() - t0
    # 4. Every position has exactly one valid frame matching the manifest; nothing stray is left.
    assert verify_scan(out) == []
    recs = records(out)
    assert sorted(r["index"] for r in recs) == list(range(200))
    assert result.resumed == len(done) and result.captured == 200 - len(done) and result.done == 200
    expected_files = {f"pos_{i:05d}.tiff" for i in range(1, 201)}
    rejected = [x for r in recs for x in r.get("rejected", [])]  # (records of the killed run have them too)
    expected_files |= {x["file"] for x in rejected}
    names = {p.name for p in out.iterdir()}
    assert names == expected_files | {n + ".meta.json" for n in expected_files} | {MANIFEST_NAME, "events.jsonl"}
    for rec in recs:
        (item,) = rec["files"]
        assert load_sidecar(out / item["file"])["sha256"] == item["sha256"]
        # ground truth: the frame shows the array centred under the target position
        x, y = rec["target_mm"]
        m, n = round((y - 10) / 5) + 1, round((x - 10) / 5) + 1
        assert rec["truth"]["array"] == f"W({m},{n})" and rec["truth"]["offset_um"] == [0.0, 0.0]
        assert rec["position_mm"] == pytest.approx([x, y], abs=0.002)
    header = read_manifest(out / MANIFEST_NAME).header
    truth = {a["name"]: a for a in header["truth"]["arrays"]}
    assert len(truth) == 200 and all(len(a["error_map"]["lenses"]) == 3 for a in truth.values())
    side = load_sidecar(out / recs[-1]["files"][0]["file"])
    assert side["device_extra"]["truth"]["error_map"] == truth[recs[-1]["truth"]["array"]]["error_map"]
    # 5. The faults really happened and were survived.
    errors = [e for e in seen_events if e["event"] == "device_error"]
    assert {e["device"] for e in errors} == {"stage", "camera"}
    assert any("timed out" in e["error"] for e in errors) and any("disconnected" in e["error"] for e in errors)
    assert any("lost its connection" in e["error"] for e in errors) and any("alarm" in e["error"].lower() for e in errors)
    assert result.reconnects["stage"] >= 3 and result.reconnects["camera"] >= 3 and result.retries >= 7
    kinds = {e["event"] for e in events(out)}
    assert {"removed_temp_file", "manifest_compacted", "reconnect", "frame_warning", "frame_rejected",
            "finished"} <= kinds
    # the black frame (black@35, in each run) was captured again: kept as a rejected frame, not as the position's
    assert rejected and all("is black" in x["reason"] and x["attempt"] == 1 for x in rejected)
    assert all(r["failed"] is None for r in recs)
    warnings = [w for r in recs for w in r["files"][0]["warnings"]]
    assert warnings and all("lost" in w for w in warnings)
    assert len(warnings) <= 3  # only the frame drops (the URL's fires in both runs, plus the injected one)
    rate = result.positions_per_s_excl_motion
    print(f"\nresumed {result.captured} positions in {elapsed:.1f} s: {rate:.1f} positions/s excluding "
          f"{result.motion_s:.2f} s of motion; {result.retries} retries, reconnects {result.reconnects}")


# --------------------------------------------------------------------------------------------- Ctrl-C

SLOW_PLAN = """
[scan]
settle_s = 0.0
retry_delay_s = 0.0

[[positions]]
x_mm = 10.0
y_mm = 10.0
[[positions]]
x_mm = 15.0
y_mm = 10.0
[[positions]]
x_mm = 20.0
y_mm = 10.0
[[positions]]
x_mm = 25.0
y_mm = 10.0
"""


@pytest.mark.timeout(60)
def test_ctrl_c_mid_move_stops_the_stage_and_keeps_the_manifest(tmp_path, capsys, python_sigint):
    plan = write_plan(tmp_path / "plan.toml", SLOW_PLAN)
    out = tmp_path / "scan"
    camera_url = "mock://?wafer=4x1&rpp=0.5&exposure_us=2000"
    stage = open_stage("sim+grbl://?speed_mm_s=20&x_max_mm=30&y_max_mm=12")  # 5 mm moves take 0.25 s
    camera = open_camera(camera_url)

    def interrupt(runner, pos):
        if pos.index == 2:
            threading.Timer(0.08, _thread.interrupt_main).start()  # Ctrl-C 80 ms into the move

    try:
        with pytest.raises(ScanInterrupted) as info:
            run_scan(camera, stage, plan, out, before_position=interrupt)
        assert isinstance(info.value, KeyboardInterrupt) and info.value.exit_status == 130
        msg = str(info.value)
        assert msg.startswith("scan interrupted at position 3 of 4") and "the stage was stopped" in msg
        assert "2 of 4 positions are recorded" in msg and msg.endswith("rerun with --resume to continue.")
        sim = stage.sim
        assert wait_until(lambda: b"!" in sim.realtime_log)  # feed hold sent (the simulator reads on its own thread)
        x1, _ = sim.position_mm
        assert stays(lambda: sim.position_mm[0] == x1, for_s=0.15) and 15.0 < x1 < 20.0  # stopped mid-move, staying
        assert not stage.is_busy()
    finally:
        stage.close()
        camera.close()
    assert [r["index"] for r in records(out)] == [0, 1]
    assert verify_scan(out) == ["2 of 4 positions have no record"]
    assert "interrupted" in {e["event"] for e in events(out)}
    # the CLI resumes it to the end
    assert main(["scan", "--camera", camera_url, "--stage", "mock://", "--plan", str(plan), "--out", str(out),
                 "--resume"]) == 0
    assert verify_scan(out) == [] and [r["index"] for r in records(out)] == [0, 1, 2, 3]
    assert "4 of 4 positions" in capsys.readouterr().err


@pytest.mark.timeout(60)
def test_cli_sigint_exits_130_with_one_sentence(tmp_path):
    plan = write_plan(tmp_path / "plan.toml", BIG_PLAN)
    out = tmp_path / "scan"
    proc = scan_cli("--camera", "mock://?wafer=20x10&rpp=0.5&exposure_us=2000", "--stage", "mock://", "--plan", str(plan),
                    "--out", str(out))
    try:
        wait_for_records(out, 3, proc, timeout_s=40)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = err.decode()
    assert proc.returncode == 130, text
    last = text.strip().splitlines()[-1]
    assert last.startswith("mlaqc scan: error: scan interrupted at position") and "--resume" in last
    assert "Traceback" not in text
    problems = verify_scan(out)
    assert len(problems) == 1 and problems[0].endswith("positions have no record")


# --------------------------------------------------------------------------------------------- faults beyond retries

QUICK_PLAN = """
[scan]
settle_s = 0.0
retries = 2
retry_delay_s = 0.0
capture_timeout_s = 0.2

[raster]
origin_mm = [10.0, 10.0]
step_mm = [5.0, 5.0]
count = [3, 1]
"""


@pytest.mark.timeout(60)
def test_retries_exhausted_stops_safely_with_exit_3(tmp_path, capsys):
    plan = write_plan(tmp_path / "plan.toml", QUICK_PLAN)
    out = tmp_path / "scan"
    camera = "mock://?wafer=3x1&rpp=0.5&exposure_us=2000&faults=disconnect@3x50"  # unplugged at the 3rd frame, for good
    assert main(["scan", "--camera", camera, "--stage", "mock://", "--plan", str(plan), "--out", str(out)]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("mlaqc scan: error: scan stopped at position 3 of 3 (r001c003")
    assert "after 3 attempts" in err[-1] and "2 of 3 positions are recorded" in err[-1] and "--resume" in err[-1]
    assert [r["index"] for r in records(out)] == [0, 1]
    assert verify_scan(out) == ["1 of 3 positions have no record"]
    assert "failed" in {e["event"] for e in events(out)}
    # the camera is back: resume finishes the job
    assert main(["scan", "--camera", "mock://?wafer=3x1&rpp=0.5&exposure_us=2000", "--stage", "mock://", "--plan", str(plan),
                 "--out", str(out), "--resume", "-q"]) == 0
    assert verify_scan(out) == []


# --------------------------------------------------------------------------------------------- frames that cannot be inspected


@pytest.mark.timeout(60)
@pytest.mark.parametrize("fault, word", [("black", "is black"), ("saturated", "is saturated")])
def test_uninspectable_frame_is_captured_again_and_kept(tmp_path, fault, word):
    plan = write_plan(tmp_path / "plan.toml", QUICK_PLAN)
    out = tmp_path / "scan"
    seen: list[dict] = []
    inspected: list[tuple[str, int]] = []
    result = run_scan(f"mock://?wafer=3x1&rpp=0.5&exposure_us=2000&faults={fault}@2", "mock://", plan, out,
                      inspect=lambda f: inspected.append((f.path.name, f.record["index"])) or None,
                      on_event=seen.append)
    assert (result.done, result.retries, result.rejected, result.failed, result.warnings) == (3, 1, 1, [], 0)
    first, second, third = records(out)
    # the retried frame is the position's frame: good, no warning, from the second attempt
    assert (second["attempts"], second["failed"], second["files"][0]["file"]) == (2, None, "pos_00002.tiff")
    assert second["files"][0]["warnings"] == []
    good = load_sidecar(out / "pos_00002.tiff")
    assert good["device_extra"]["mock"]["fault"] is None and good["context"]["scan"]["attempt"] == 2
    # the bad attempt is kept, listed and checksummed: nothing is lost
    (bad,) = second["rejected"]
    assert (bad["file"], bad["attempt"]) == ("pos_00002_rejected1.tiff", 1) and word in bad["reason"]
    side = load_sidecar(out / bad["file"])
    assert side["device_extra"]["mock"]["fault"] == fault and side["sha256"] == bad["sha256"]
    assert side["context"]["rejected"] == bad["reason"] and side["context"]["scan"]["attempt"] == 1
    assert side["sequence"] == 2 and good["sequence"] == 3  # captured again right away
    assert first["rejected"] == third["rejected"] == [] and first["attempts"] == third["attempts"] == 1
    assert [e["file"] for e in seen if e["event"] == "frame_rejected"] == ["pos_00002_rejected1.tiff"]
    assert not [e for e in seen if e["event"] in ("frame_warning", "position_failed", "device_error")]
    assert inspected == [("pos_00001.tiff", 0), ("pos_00002.tiff", 1), ("pos_00003.tiff", 2)]
    assert verify_scan(out) == []


@pytest.mark.timeout(60)
def test_always_black_position_fails_after_its_retries_and_the_scan_goes_on(tmp_path):
    plan = write_plan(tmp_path / "plan.toml", QUICK_PLAN)  # retries = 2: three attempts per position
    out = tmp_path / "scan"
    cam = "mock://?wafer=3x1&rpp=0.5&exposure_us=2000&faults=black@2x3"  # every attempt at position 2 is black
    seen: list[dict] = []
    inspected: list[int] = []
    result = run_scan(cam, "mock://", plan, out, inspect=lambda f: inspected.append(f.record["index"]) or None,
                      on_event=seen.append)
    assert (result.done, result.captured, result.retries, result.rejected) == (3, 3, 2, 2)
    assert result.failed == ["r001c002"] and "1 position FAILED (frames not inspectable: r001c002)" in result.summary()
    first, second, third = records(out)
    assert second["attempts"] == 3 and "is black" in second["failed"] and "after 3 attempts" in second["failed"]
    assert [(x["file"], x["attempt"]) for x in second["rejected"]] == [
        ("pos_00002_rejected1.tiff", 1), ("pos_00002_rejected2.tiff", 2)]
    (last,) = second["files"]  # the last attempt's frame stays the position's frame, flagged by its warning
    assert last["file"] == "pos_00002.tiff" and any("is black" in w for w in last["warnings"])
    assert load_sidecar(out / "pos_00002.tiff")["device_extra"]["mock"]["fault"] == "black"
    assert first["failed"] is None and third["failed"] is None and third["files"][0]["warnings"] == []
    assert load_sidecar(out / "pos_00003.tiff")["device_extra"]["mock"]["fault"] is None
    (failed,) = [e for e in seen if e["event"] == "position_failed"]
    assert (failed["index"], failed["label"], failed["attempts"]) == (1, "r001c002", 3)
    assert inspected == [0, 2]  # a failed position's frame is not handed to the inspection
    assert verify_scan(out) == []
    again = run_scan(cam, "mock://", plan, out, resume=True)
    assert again.captured == 0 and again.failed == ["r001c002"]  # recorded: a resume keeps it, and still says so
    assert not again.all_passed and main(["scan", "--camera", cam, "--stage", "mock://", "--plan", str(plan), "--out",
                                          str(out), "--resume", "-q"]) == 1
    (out / "pos_00002_rejected1.tiff").unlink()
    assert verify_scan(out) == ["position 2, rejected frame: pos_00002_rejected1.tiff is missing"]


@pytest.mark.timeout(60)
def test_resume_recaptures_altered_frames(tmp_path):
    plan = write_plan(tmp_path / "plan.toml", QUICK_PLAN)
    out = tmp_path / "scan"
    cam = "mock://?wafer=3x1&rpp=0.5&exposure_us=2000"
    first = run_scan(cam, "mock://", plan, out)
    assert first.captured == 3
    (out / "pos_00002.tiff").write_bytes(b"tampered")
    (out / "pos_00003.tiff").unlink()
    again = run_scan(cam, "mock://", plan, out, resume=True)
    assert (again.resumed, again.captured) == (1, 2)
    assert verify_scan(out) == [] and sorted(r["index"] for r in records(out)) == [0, 1, 2]
    assert len(records(out)) == 3  # the manifest was compacted, never duplicated
    assert run_scan(cam, "mock://", plan, out, resume=True).captured == 0


# --------------------------------------------------------------------------------------------- refusals and hooks


@pytest.mark.timeout(60)
def test_cli_refusals_exit_2_and_write_nothing(tmp_path, capsys):
    plan = write_plan(tmp_path / "plan.toml", QUICK_PLAN)
    cam = "mock://?wafer=3x1&rpp=0.5&exposure_us=2000"

    def scan(*extra, out=None, camera=cam, stage="mock://", plan_path=plan):
        return main(["scan", "--camera", camera, "--stage", stage, "--plan", str(plan_path),
                     "--out", str(out or tmp_path / "never"), "-q", *extra])

    assert scan(camera="mock://?nope=1") == 2
    assert scan(stage="mock://?nope=1") == 2
    assert scan(stage="serial:///dev/ttyUSB9") == 2  # no protocol given
    assert scan(plan_path=tmp_path / "missing.toml") == 2
    far = write_plan(tmp_path / "far.toml", QUICK_PLAN.replace("[10.0, 10.0]", "[195.0, 10.0]"))
    assert scan(plan_path=far) == 2
    assert "outside the stage's soft limits" in capsys.readouterr().err
    assert not (tmp_path / "never").exists()
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    assert scan(out=busy) == 2 and "not empty" in capsys.readouterr().err
    done = tmp_path / "done"
    assert scan(out=done) == 0
    assert scan(out=done) == 2 and "--resume" in capsys.readouterr().err
    other = write_plan(tmp_path / "other.toml", QUICK_PLAN.replace("count = [3, 1]", "count = [2, 1]"))
    assert scan("--resume", out=done, plan_path=other) == 2 and "different plan" in capsys.readouterr().err
    assert scan("--resume", out=done, camera=cam + "&seed=9") == 2 and "ground truth" in capsys.readouterr().err
    assert scan("--resume", out=done) == 0 and verify_scan(done) == []


@pytest.mark.timeout(60)
def test_inspect_hook_extension_point(tmp_path, capsys):
    plan = write_plan(tmp_path / "plan.toml", QUICK_PLAN)
    cam = "mock://?wafer=3x1&rpp=0.5&exposure_us=2000"
    status = main(["scan", "--camera", cam, "--stage", "mock://", "--plan", str(plan), "--out", str(tmp_path / "a"),
                   "--inspect"])
    err = capsys.readouterr().err
    verdicts = [json.loads(p.read_text())["verdict"] for p in sorted((tmp_path / "a").glob("*.inspect.json"))]
    header = json.loads((tmp_path / "a" / "manifest.jsonl").read_text().splitlines()[0])
    seeded = [bool(a["error_map"]["lenses"]) for a in header["truth"]["arrays"]]
    assert len(verdicts) == 3 and any(seeded)
    # an array with seeded defects fails, and a scan with a FAIL verdict exits 1, naming the positions
    assert [v == "FAIL" for v in verdicts] == seeded and status == 1
    assert f"QC verdict FAIL at {sum(seeded)} position" in err
    calls = []

    def hook(frame):
        record = frame.record
        assert frame.sidecar.name == frame.path.name + ".meta.json" and frame.sidecar.exists()
        assert frame.header["camera_settings"]["config"]["mla"]["count_w"] == 24
        assert frame.header["truth"]["arrays"][record["index"]]["name"] == record["truth"]["array"]
        calls.append((frame.path.name, record["index"]))
        if record["index"] == 1:
            raise RuntimeError("inspection bug")
        return {"lenses_flagged": record["index"]}

    result = run_scan(cam, "mock://", plan, tmp_path / "b", inspect=hook)
    assert calls == [("pos_00001.tiff", 0), ("pos_00002.tiff", 1), ("pos_00003.tiff", 2)]
    assert (result.inspected, result.inspect_failures) == (2, 1)
    assert json.loads((tmp_path / "b" / "pos_00003.tiff.inspect.json").read_text()) == {"lenses_flagged": 2}
    assert not (tmp_path / "b" / "pos_00002.tiff.inspect.json").exists()
    assert verify_scan(tmp_path / "b") == []


@pytest.mark.timeout(60)
def test_multiple_frames_and_averages_per_position(tmp_path):
    plan = write_plan(tmp_path / "plan.toml", QUICK_PLAN.replace("settle_s = 0.0", "settle_s = 0.0\nframes_per_position = 2\naverage = 2\nformat = \"dng\"\nexposure_us = 3000.0"))
    out = tmp_path / "scan"
    with pytest.raises(ScanFailed, match="after 3 attempts"):
        run_scan("mock://?wafer=3x1&rpp=0.5&exposure_us=2000&faults=timeout@9x3", "mock://", plan, out)
    recs = records(out)
    assert [r["index"] for r in recs] == [0, 1] and [f["file"] for f in recs[1]["files"]] == [
        "pos_00002_f1.dng", "pos_00002_f2.dng"]
    side = load_sidecar(out / "pos_00002_f2.dng")
    assert side["sequences"] == [7, 8] and side["exposure_us"] == 3000.0
    assert side["context"]["scan"]["label"] == "r001c002" and side["stage_position_mm"] == [15.0, 10.0]


@pytest.mark.timeout(60)
def test_write_failure_mid_scan_stops_with_one_sentence(tmp_path):
    import shutil

    plan = write_plan(tmp_path / "plan.toml", QUICK_PLAN)
    out = tmp_path / "scan"

    def pull_the_disk(runner, pos):
        if pos.index == 1:
            shutil.rmtree(out)

    with pytest.raises(InputError) as info:
        run_scan("mock://?wafer=3x1&rpp=0.5&exposure_us=2000", "mock://", plan, out, before_position=pull_the_disk)
    msg = str(info.value)
    assert msg.startswith("scan stopped at position 2 of 3 (r001c002") and "Cannot write raw file" in msg
    assert "the stage was stopped" in msg and msg.count("\n") == 0
