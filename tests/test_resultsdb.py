"""The results database (mlaqc.resultsdb): inspections recorded as their reports say, once, whole or not at
all, by several writers at once; failures said in one sentence with the reports still written; and the lot
views (yield, Pareto, repeating defects) against lots whose truth is seeded."""

import json
import math
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import analytic_frames as am
import pgserver
from test_scan_inspect import PLAN as SCAN_PLAN
from mlaqc.cli import main
from mlaqc.optics.config import load_config
from mlaqc.resultsdb import lot as views
from mlaqc.resultsdb import store
from mlaqc.resultsdb.record import Identity, record_from_report
from mlaqc.resultsdb.store import DatabaseError, open_database

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
SMALL_TOML = str(FIXTURES / "small_camera.toml")
SMALL = load_config(SMALL_TOML)
BITS = 12


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Two analytic frames of the small camera (not the tracer's): one with a shifted and a dimmed lens, one
    healthy; 12-bit TIFFs with level tags."""
    d = tmp_path_factory.mktemp("frames")
    cfg = SMALL
    base = am.AnalyticModel(shape=(cfg.sensor.height_px, cfg.sensor.width_px), lenses=(cfg.mla.count_h, cfg.mla.count_w),
                            pitch_px=cfg.layout.subimage_pitch_px, radius_px=0.49 * cfg.layout.subimage_pitch_px)
    out = {}
    for name, anomalies in (("flawed", (am.Anomaly(8, 9, "shift", 0.8, 30.0), am.Anomaly(14, 6, "dim", 0.6))),
                            ("healthy", ())):
        img = base.with_anomalies(anomalies).render()
        counts = am.to_counts(am.expose(img, 0.005, np.random.default_rng(3)), BITS)
        out[name] = str(am.write_container(d / f"{name}.tif", counts, BITS, 0))
    return out


@pytest.fixture(scope="module")
def pg():
    """A throwaway PostgreSQL server (tests/pgserver.py)."""
    server, why = pgserver.start()
    if server is None:
        if pgserver.REQUIRED:
            pytest.fail(why)
        pytest.skip(why)
    yield server
    server.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def target(request, tmp_path):
    """A fresh results database of each kind: an SQLite file, a PostgreSQL database."""
    if request.param == "sqlite":
        return str(tmp_path / "r.sqlite")
    return request.getfixturevalue("pg").new_database()


def _rows(target, sql, params=()):
    with open_database(target, create=False) as db:
        return db.query(sql, params)


def _inspect(args) -> int:
    return main(["inspect", *args, "-c", SMALL_TOML, "--quiet"])


def test_an_inspection_is_recorded_as_its_report_says(frames, tmp_path):
    db_path = str(tmp_path / "r.sqlite")
    status = _inspect([frames["flawed"], "-o", str(tmp_path / "out"), "--db", db_path, "--lot", "L7", "--wafer", "W03",
                       "--array", "A12"])
    assert status == 1
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert {(d["row"], d["col"]) for d in report["defects"]} >= {(9, 10), (15, 7)}  # the seeded lenses (1-based)
    with sqlite3.connect(db_path) as conn:
        (row,) = conn.execute("SELECT lot, wafer, array_id, verdict, flagged, pitch_x_px, rotation_deg, grid_rms_px, "
                              "limit_pitch_um, config_hash, software_version, source, id FROM inspections").fetchall()
        lenses = conn.execute("SELECT m, n, error_type, magnitude, direction_deg, within_tolerance FROM flagged_lenses "
                              "WHERE inspection_id = ? ORDER BY m, n", (row[-1],)).fetchall()
        config = conn.execute("SELECT body FROM configs WHERE hash = ?", (row[9],)).fetchone()[0]
    g = report["grid_summary"]
    # the same numbers, bit for bit (SQLite REAL is the double report.json holds)
    assert row[:8] == ("L7", "W03", "A12", "FAIL", len(report["defects"]), g["pitch_x_px"], g["rotation_deg"],
                       g["rms_residual_px"])
    assert row[8] == report["detection_limit"]["pitch_um"]
    assert row[10] == report["mlaqc_version"] and row[11] == report["source"]
    assert json.loads(config) == report["config"]
    want = sorted((d["row"], d["col"], d["error_type"], d["magnitude"], d["direction_deg"], int(d["within_tolerance"]))
                  for d in report["defects"])
    assert sorted(lenses) == want


def test_a_batch_run_again_is_recorded_once(frames, tmp_path, target):
    args = [frames["flawed"], frames["healthy"], "-o", str(tmp_path / "out"), "--db", target, "--lot", "L1"]
    assert _inspect(args) == 1
    assert _inspect(args) == 1
    assert _rows(target, "SELECT COUNT(*), COUNT(DISTINCT source) FROM inspections") == [(2, 2)]
    (flagged,), = _rows(target, "SELECT SUM(flagged) FROM inspections")
    assert _rows(target, "SELECT COUNT(*) FROM flagged_lenses") == [(flagged,)] and flagged >= 2


def test_no_db_records_nothing(frames, tmp_path):
    db_path = tmp_path / "r.sqlite"
    assert _inspect([frames["healthy"], "-o", str(tmp_path / "out"), "--db", str(db_path), "--no-db"]) == 0
    assert not db_path.exists()


def test_a_database_that_cannot_be_written_keeps_the_report(frames, tmp_path, capsys):
    (tmp_path / "folder.sqlite").mkdir()
    status = _inspect([frames["healthy"], "-o", str(tmp_path / "out"), "--db", str(tmp_path / "folder.sqlite")])
    assert status == 4
    assert (tmp_path / "out" / "report.json").is_file()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "results database" in err[0] and "folder" in err[0]


def test_an_array_option_on_a_batch_is_refused(frames, tmp_path):
    status = _inspect([frames["healthy"], frames["flawed"], "-o", str(tmp_path / "out"), "--array", "A1",
                       "--db", str(tmp_path / "r.sqlite")])
    assert status == 2
    assert not (tmp_path / "out").exists() and not (tmp_path / "r.sqlite").exists()


# ------------------------------------------------------------------------------------------- failures

def _report(verdict="FAIL", defects=(), rows=20, cols=20, pitch=20.0) -> dict:
    """A report.json's content with what the database keeps (the rest of a report is not read)."""
    return {"created_utc": "2026-12-01T10:00:00+00:00", "source": "frame.tif", "verdict": verdict,
            "mlaqc_version": "0.1.0", "grid": {"packing": "square"},
            "summary": {"rows": rows, "cols": cols, "found": rows * cols, "missing": 0, "flagged": len(defects),
                        "out_of_tolerance": sum(not d.get("within_tolerance", False) for d in defects),
                        "by_error_type": {}},
            "grid_summary": {"pitch_x_px": pitch, "pitch_y_px": pitch, "rotation_deg": 0.01, "rms_residual_px": 0.005},
            "detection_limit": {"pitch_um": 0.5}, "assembly": {}, "config": {"mla": {"pitch_um": 100.0}},
            "defects": [{"within_tolerance": False, "magnitude": 1.0, "unit": "µm", "score": 9.0, **d} for d in defects]}


def test_a_newer_schema_is_refused(target):
    with open_database(target) as db, db._transaction() as cur:
        cur.execute("UPDATE schema_info SET version = 99")
    with pytest.raises(DatabaseError, match="schema version 99, newer than this mlaqc"):
        open_database(target)
    with pytest.raises(DatabaseError, match="newer"):
        open_database(target, create=False)


def test_an_unreachable_server_is_one_sentence(frames, tmp_path, capsys):
    pytest.importorskip("psycopg")
    url = f"postgresql://nobody:secret@/results?host={tmp_path}&port=1"  # no server on that socket
    status = _inspect([frames["healthy"], "-o", str(tmp_path / "out"), "--db", url])
    assert status == 4 and (tmp_path / "out" / "report.json").is_file()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot reach the results database postgresql://nobody@" in err[0]
    assert "secret" not in err[0]


def test_a_file_that_is_no_database_is_said(tmp_path):
    path = tmp_path / "r.sqlite"
    path.write_bytes(b"this is a text file, not a database" * 100)
    with pytest.raises(DatabaseError, match="not an SQLite database"):
        open_database(str(path))
    assert path.read_bytes().startswith(b"this is a text file")  # left as it was
    other = tmp_path / "other.sqlite"
    with sqlite3.connect(other) as conn:
        conn.execute("CREATE TABLE notes (x TEXT)")
    with pytest.raises(DatabaseError, match="not an mlaqc results database"):
        open_database(str(other))


def test_a_locked_database_is_said_after_waiting(tmp_path, monkeypatch):
    path = str(tmp_path / "r.sqlite")
    open_database(path).close()
    monkeypatch.setattr(store, "BUSY_TIMEOUT_S", 0.3)
    holder = sqlite3.connect(path, isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")
    try:
        db = open_database(path)
    except DatabaseError as exc:  # the migration's check already waits on the lock
        assert "locked" in str(exc)
    else:
        with db, pytest.raises(DatabaseError, match="locked by another writer"):
            db.record(record_from_report(_report()), Identity(lot="L"))
    finally:
        holder.rollback()
        holder.close()
    with open_database(path) as db:  # free again: recorded
        db.record(record_from_report(_report()), Identity(lot="L"))
        assert db.query("SELECT COUNT(*) FROM inspections") == [(1,)]


def test_a_read_only_database_is_said(tmp_path, monkeypatch):
    path = str(tmp_path / "r.sqlite")
    open_database(path).close()
    real = sqlite3.connect

    def read_only(target, *a, **k):  # what a write-protected file or share gives (root ignores chmod)
        return real(f"file:{target}?mode=ro", *a, uri=True, **k)

    monkeypatch.setattr(store.sqlite3, "connect", read_only)
    db = open_database(path, create=False)
    with db, pytest.raises(DatabaseError, match="read-only"):
        db.record(record_from_report(_report()), Identity(lot="L"))


WRITER = textwrap.dedent("""
    import sys
    from mlaqc.resultsdb.record import Identity, record_from_report
    from mlaqc.resultsdb.store import open_database
    sys.path.insert(0, {tests!r})
    from test_resultsdb import _report
    path, name, count = sys.argv[1], sys.argv[2], int(sys.argv[3])
    defects = [dict(row=1 + k // 20, col=1 + k % 20, error_type="pitch", direction_deg=10.0) for k in range(200)]
    rec = record_from_report(_report(defects=defects))
    with open_database(path) as db:
        for i in range(count):
            db.record(rec, Identity(lot="L", wafer=name, array=f"A{{i:05d}}"), None)
            if i == 0:
                print("started", flush=True)
""")


def _writer(path, name, count) -> subprocess.Popen:
    script = WRITER.format(tests=str(Path(__file__).parent))
    return subprocess.Popen([sys.executable, "-c", script, path, name, str(count)], stdout=subprocess.PIPE, text=True)


def _whole(target) -> tuple[int, int]:
    """(inspections, inspections whose flagged lens rows are all there), after an integrity check."""
    if "://" not in target:
        with sqlite3.connect(target) as conn:
            assert conn.execute("PRAGMA integrity_check").fetchone() == ("ok",)
    try:
        rows = _rows(target, "SELECT i.flagged, (SELECT COUNT(*) FROM flagged_lenses f WHERE f.inspection_id = i.id) "
                             "FROM inspections i")
    except DatabaseError:  # not created yet
        return 0, 0
    return len(rows), sum(a == b for a, b in rows)


def test_a_writer_killed_mid_way_leaves_no_partial_record(target):
    path = target
    proc = _writer(path, "W1", 100_000)
    assert proc.stdout.readline().strip() == "started"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and _whole(path)[0] < 30:
        time.sleep(0.05)
    proc.kill()  # SIGKILL: no handler, no rollback of its own
    proc.wait()
    count, whole = _whole(path)
    assert count >= 30 and whole == count
    # and the database goes on: the same writer run again records on top
    again = _writer(path, "W2", 5)
    assert again.wait(60) == 0
    assert _whole(path) == (count + 5, count + 5)


def test_two_writers_at_once_lose_nothing(target):
    path = target
    open_database(path).close()
    procs = [_writer(path, name, 1000) for name in ("W1", "W2")]
    assert [p.wait(300) for p in procs] == [0, 0]
    assert _whole(path) == (2000, 2000)


# ------------------------------------------------------------------------------------------- lot views

def _seeded_lot(path, arrays=50, master_share=0.8, seed=4):
    """A lot of 20 x 20-lens arrays on two wafers: U(5,7) shifted (pitch, 30° ± 5°) in `master_share` of the
    arrays (the master's defect), 3 random flags of random types elsewhere in every array, a FAIL verdict
    where an out-of-tolerance flag is; the assembly's distance and rotation read on all but every tenth
    array, its tilts on none. Returns the truth."""
    rng = np.random.default_rng(seed)
    assembly_rng = np.random.default_rng(seed + 1000)  # (apart: the defects' draws stay as they were)
    types = ("pitch", "radius", "dim", "tilt", "decenter")
    master = set(rng.choice(arrays, int(round(master_share * arrays)), replace=False).tolist())
    truth = {"passed": {}, "arrays": {"W1": 0, "W2": 0}, "master": len(master)}
    with open_database(path) as db:
        for a in range(arrays):
            defects = []
            if a in master:
                defects.append(dict(row=5, col=7, error_type="pitch", direction_deg=float(30 + rng.normal(0, 5)),
                                    magnitude=1.2, within_tolerance=False))
            for _ in range(3):
                m, n = (int(v) for v in rng.integers(1, 21, 2))
                if (m, n) == (5, 7):
                    continue
                kind = str(rng.choice(types))
                defects.append(dict(row=m, col=n, error_type=kind, direction_deg=float(rng.uniform(0, 360)),
                                    within_tolerance=bool(rng.random() < 0.7)))
            failed = any(not d["within_tolerance"] for d in defects)
            wafer = "W1" if a < arrays // 2 else "W2"
            truth["arrays"][wafer] += 1
            truth["passed"][wafer] = truth["passed"].get(wafer, 0) + (not failed)
            report = _report("FAIL" if failed else "PASS", defects)
            report["source"] = f"a{a}.tif"
            distance, rotation = assembly_rng.normal(0.0, 0.5), assembly_rng.normal(0.0, 0.01)
            if a % 10 != 9:
                report["assembly"] = {"mla_sensor_distance_um": {"value": distance, "sigma": 0.1},
                                      "mla_rotation_deg": {"value": rotation, "sigma": 0.002}}
            db.record(record_from_report(report), Identity(lot="L9", wafer=wafer, array=f"A{a:03d}"), None)
    return truth


def test_yield_and_pareto_of_a_seeded_lot(target):
    path = target
    truth = _seeded_lot(path)
    with open_database(path, create=False) as db:
        table = views.yield_table(db, "L9")
        pareto = views.pareto(db, "L9")
    assert [(r["wafer"], r["arrays"], r["passed"]) for r in table] == \
        [(w, truth["arrays"][w], truth["passed"][w]) for w in ("W1", "W2")]
    assert pareto[0]["error_type"] == "pitch"  # the master's defect fails most arrays
    assert pareto[0]["arrays_failed"] >= truth["master"]
    assert math.isclose(sum(r["share"] for r in pareto), 1.0)


def test_the_masters_defect_is_named_and_chance_is_not(target):
    path = target
    truth = _seeded_lot(path)
    with open_database(path, create=False) as db:
        found = views.repeating_defects(db, "L9")
        counts, arrays, shape = views.stacked_map(db, "L9")
    assert [(d.m, d.n, d.error_type) for d in found] == [(5, 7, "pitch")]
    d = found[0]
    assert d.arrays == truth["master"] and d.of_arrays == arrays == 50 and shape == (20, 20)
    assert abs(d.direction_deg - 30) < 5 and d.direction_r > 0.9 and d.p_chance < 1e-6
    assert counts[(5, 7)] >= truth["master"]
    assert "U(5,7) repeats: pitch at" in d.sentence()


def test_a_lot_of_random_defects_has_no_repeats(target):
    path = target
    _seeded_lot(path, master_share=0.0, seed=11)
    with open_database(path, create=False) as db:
        assert views.repeating_defects(db, "L9") == []


def test_lot_command(tmp_path, capsys, target):
    path = target
    _seeded_lot(path)
    assert main(["lot", "repeats", "--db", path, "--lot", "L9"]) == 0
    assert "U(5,7) repeats: pitch" in capsys.readouterr().out
    assert main(["lot", "yield", "--db", path, "--json"]) == 0
    assert sum(r["arrays"] for r in json.loads(capsys.readouterr().out)) == 50
    assert main(["lot", "history", "--db", path, "--array", "A007"]) == 0
    out = capsys.readouterr().out
    assert "A007" in out and "L9" in out
    assert main(["lot", "yield", "--db", str(tmp_path / "none.sqlite")]) == 4
    assert "no results database" in capsys.readouterr().err
    assert not (tmp_path / "none.sqlite").exists()
    assert main(["lot", "history", "--db", path]) == 2


@pytest.mark.timeout(300)
def test_a_scan_records_each_array_by_its_position(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text(SCAN_PLAN)  # two positions of a 2 x 1 wafer, as the scan's own inspection test
    db_path = str(tmp_path / "r.sqlite")
    status = main(["scan", "--camera", "mock://?wafer=2x1&defects=3&defect_types=decenter&seed=4&rpp=40",
                   "--stage", "mock://", "--plan", str(plan), "--out", str(tmp_path / "scan"), "--inspect",
                   "--db", db_path, "--lot", "L2", "--wafer", "W05", "--quiet"])
    assert status == 1  # every array has seeded defects: FAIL
    summaries = {json.loads(p.read_text())["source"]: json.loads(p.read_text())
                 for p in (tmp_path / "scan").glob("*.inspect.json")}
    rows = _rows(db_path, "SELECT id, lot, wafer, position, source, verdict, flagged FROM inspections ORDER BY position")
    assert [r[1:4] for r in rows] == [("L2", "W05", "W(1,1)"), ("L2", "W05", "W(1,2)")]
    for ident, *_, source, verdict, flagged in rows:
        summary = summaries[source]
        assert (verdict, flagged) == (summary["verdict"], len(summary["defects"]))
        lenses = _rows(db_path, "SELECT m, n, error_type FROM flagged_lenses WHERE inspection_id = ?", (ident,))
        assert sorted(lenses) == sorted((d["row"], d["col"], d["error_type"]) for d in summary["defects"])


def test_lot_chart_names_the_arrays_of_a_drift(target, capsys):
    """Pitch alternating ±1e-4 px about 20 px for 40 arrays (±0.56 sigma of the moving range: in control by
    every rule), then creeping up by a quarter of that sigma per array: both charts call the drift within 8
    arrays of its onset (the I-MR chart: the alternation hides the trend rule; 2 of 3 beyond 2 sigma calls
    it), nothing before it. The CUSUM's centre and sigma are those of the arrays before its first call."""
    sigma = 2e-4 / 1.128
    pitches = []
    with open_database(target) as db:
        for a in range(60):
            pitch = 20.0 + (1e-4 if a % 2 else -1e-4) + (0.25 * sigma * (a - 39) if a >= 40 else 0.0)
            pitches.append(pitch)
            report = _report("PASS", pitch=pitch)
            report["source"] = f"a{a:02d}.tif"
            report["created_utc"] = f"2026-12-01T10:{a:02d}:00+00:00"
            db.record(record_from_report(report), Identity(lot="L5", wafer="W1", array=f"A{a:02d}"), None)
    for chart in ("cusum", "imr"):
        assert main(["lot", "chart", "--db", target, "--lot", "L5", "--reading", "pitch_x_px", "--chart", chart,
                     "--json"]) == 0
        data = json.loads(capsys.readouterr().out)
        called = sorted(int(label.split("/A")[1]) for label in data["out_of_control"])
        assert data["chart"] == chart and called and 40 <= called[0] <= 48, (chart, called)
        if chart == "imr":
            assert data["centre"] == pytest.approx(20.0) and data["sigma"] == pytest.approx(sigma)
        else:
            before = np.array(pitches[: called[0]])
            assert data["centre"] == pytest.approx(before.mean(), abs=1e-12)
            assert data["sigma"] == pytest.approx(before.std(ddof=1), rel=1e-6)
    assert main(["lot", "chart", "--db", target, "--reading", "nonsense"]) == 2
    assert main(["lot", "chart", "--db", target, "--chart", "imr", "--rules", "7"]) == 2
    assert main(["lot", "chart", "--db", target, "--rules", "1,5"]) == 2  # run rules belong to the I-MR chart
    assert main(["lot", "chart", "--db", target, "--cusum-h", "0"]) == 2
    assert main(["lot", "chart", "--db", target, "--chart", "imr", "--rules", ""]) == 2
    assert main(["lot", "chart", "--db", target, "--chart", "imr", "--cusum-h", "5"]) == 2
    err = capsys.readouterr().err
    assert "--rules chooses the run rules" in err and "--cusum-h is the CUSUM chart's" in err
    assert main(["lot", "yield", "--db", target, "--lot", "L5", "--rules", "1"]) == 0  # (not a chart: not read)


def test_an_infinite_reading_is_named_not_charted(target, capsys):
    """A reading stored as infinity (a grid fit that did not converge) has no place on a chart: it is left
    out, and the chart says which array it was, in its summary line and its JSON."""
    with open_database(target) as db:
        for a in range(25):
            report = _report("PASS", pitch=float("inf") if a == 7 else 20.0 + 1e-4 * (a % 3))
            report["source"] = f"a{a:02d}.tif"
            report["created_utc"] = f"2026-12-01T10:{a:02d}:00+00:00"
            db.record(record_from_report(report), Identity(lot="L6", wafer="W1", array=f"A{a:02d}"), None)
    assert main(["lot", "chart", "--db", target, "--lot", "L6", "--reading", "pitch_x_px", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["not_charted"] == ["L6/W1/A07"] and len(data["values"]) == 24
    assert "L6/W1/A07" not in data["arrays"] and all(math.isfinite(v) for v in data["values"])
    assert main(["lot", "chart", "--db", target, "--lot", "L6", "--reading", "pitch_x_px"]) == 0
    assert "1 not charted, their reading not finite: L6/W1/A07" in capsys.readouterr().out


def test_arrays_without_a_reading_are_named_not_read(target, capsys, tmp_path):
    """An assembly reading the frame did not read or could not determine is stored as NULL: the chart
    leaves those arrays off and names them (JSON: all; summary: the first 10, then how many more)."""
    unread = {3, 5, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17}
    with open_database(target) as db:
        for a in range(25):
            report = _report("PASS")
            if a not in unread:
                report["assembly"] = {"mla_sensor_distance_um": {"value": 1.0 + 0.01 * (a % 3), "sigma": 0.1}}
            report["source"] = f"c{a:02d}.tif"
            report["created_utc"] = f"2026-12-01T11:{a:02d}:00+00:00"
            db.record(record_from_report(report), Identity(lot="L8", wafer="W1", array=f"C{a:02d}"), None)
    assert main(["lot", "chart", "--db", target, "--lot", "L8", "--reading", "distance_um", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["not_read"] == [f"L8/W1/C{a:02d}" for a in sorted(unread)] and len(data["values"]) == 13
    assert data["not_charted"] == [] and not set(data["not_read"]) & set(data["arrays"])
    assert main(["lot", "chart", "--db", target, "--lot", "L8", "--reading", "distance_um"]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert line.endswith("12 without this reading (not read or not determined): L8/W1/C03, L8/W1/C05, L8/W1/C08, "
                         "L8/W1/C09, L8/W1/C10, L8/W1/C11, L8/W1/C12, L8/W1/C13, L8/W1/C14, L8/W1/C15 and 2 more")
    assert main(["lot", "chart", "--db", target, "--lot", "L8", "--reading", "pitch_x_px", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["not_read"] == []  # every frame read its grid
    out = tmp_path / "lot.html"
    assert main(["lot", "report", "--db", target, "--lot", "L8", "--out", str(out)]) == 0
    assert "12 without this reading (not read or not determined): L8/W1/C03" in out.read_text()


def test_a_lot_with_no_finite_reading_charts_nothing_and_says_so(target, capsys, tmp_path):
    """Every array's reading infinite: the chart's centre is JSON null (not NaN, which is not
    JSON), and the lot report, which charts nothing under 3 arrays, still names them."""
    with open_database(target) as db:
        for a in range(2):
            report = _report("PASS", pitch=float("inf"))
            report["source"] = f"b{a}.tif"
            db.record(record_from_report(report), Identity(lot="L7", wafer="W1", array=f"B{a}"), None)
    assert main(["lot", "chart", "--db", target, "--lot", "L7", "--reading", "pitch_x_px", "--json"]) == 0

    def refuse(name):
        raise ValueError(f"{name} is not JSON")

    data = json.loads(capsys.readouterr().out, parse_constant=refuse)
    assert data["centre"] is None and data["values"] == [] and data["not_charted"] == ["L7/W1/B0", "L7/W1/B1"]
    out = tmp_path / "lot.html"
    assert main(["lot", "report", "--db", target, "--lot", "L7", "--out", str(out)]) == 0
    assert "not charted (reading not finite): L7/W1/B0; L7/W1/B1" in out.read_text()


@pytest.mark.timeout(300)
def test_a_batch_killed_then_run_again_records_every_frame_once(frames, tmp_path):
    """`mlaqc inspect` on 8 frames killed (SIGKILL) once some are recorded, then run again: each frame
    recorded exactly once, whole."""
    import shutil

    raws = []
    for k in range(8):
        raws.append(str(tmp_path / f"f{k}.tif"))
        shutil.copy(frames["flawed" if k % 2 else "healthy"], raws[-1])
    db_path = str(tmp_path / "r.sqlite")
    cmd = [sys.executable, "-m", "mlaqc", "inspect", *raws, "-c", SMALL_TOML, "-o", str(tmp_path / "out"),
           "--db", db_path, "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and _whole(db_path)[0] < 2 and proc.poll() is None:
        time.sleep(0.02)
    proc.kill()
    proc.wait()
    first, whole = _whole(db_path)
    assert 1 <= first < 8 and whole == first  # killed part-way: what is there is whole
    assert subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode == 1
    assert _whole(db_path) == (8, 8)
    assert _rows(db_path, "SELECT COUNT(DISTINCT source) FROM inspections") == [(8,)]
