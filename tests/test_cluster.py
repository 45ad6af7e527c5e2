"""`mlaqc inspect --scheduler`: batch inspection on a Dask cluster (mlaqc.cluster), against the local run.

One LocalCluster of two single-threaded worker processes serves the module; the frames are the batch
tests' (tests/test_inspect_batch.py: 24 x 24 lenses, 496 x 496 px).
"""

import csv
import gc
import io
import json
import operator
import os
import socket
import sys
import threading
from pathlib import Path

import cloudpickle
import pytest

from mlaqc import cluster
from mlaqc.cli import main
from mlaqc.commands.inspect import BatchSpec, inspect_remote
from mlaqc.optics.config import load_config
from mlaqc.report import write as report_write
from test_inspect_batch import SEEDED, SMALL_TOML, raws  # noqa: F401  (raws is a fixture)

distributed = pytest.importorskip("distributed")
dask = pytest.importorskip("dask")

# The worker plugin below is defined here, a module the workers cannot import: send it by value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])

BATCH = ["defects.npy", "perfect.npy", "truncated.npy", "perfect.npy"]
REPORTS = ("defects", "perfect", "perfect-2")


@pytest.fixture(autouse=True)
def no_scheduler_from_the_environment(monkeypatch):
    """A developer's own $MLAQC_SCHEDULER must not turn the local runs here into cluster runs."""
    monkeypatch.delenv(cluster.ENV_VAR, raising=False)


@pytest.fixture(scope="module")
def dask_cluster():
    # a task is given up after its second worker died on it (Dask's default: the fourth), to keep the test short
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as lc:
            yield lc


@pytest.fixture(scope="module")
def grid(raws, tmp_path_factory):  # noqa: F811
    path = tmp_path_factory.mktemp("grid") / "grid.json"
    assert main(["calibrate", str(raws / "white.npy"), "-c", SMALL_TOML, "-o", str(path), "-q"]) == 0
    return path


def inspect(frames, grid, out, *extra) -> int:
    return main(["inspect", *map(str, frames), "--grid", str(grid), "-c", SMALL_TOML, "-o", str(out), *extra])


def batch_rows(out: Path) -> list[dict]:
    """batch.csv without what differs between runs: the time, and the --out folder around each report."""
    rows = list(csv.DictReader((out / "batch.csv").open()))
    return [{**r, "seconds": bool(r["seconds"]), "report": Path(r["report"]).name if r["report"] else ""} for r in rows]


def report_json(folder: Path) -> dict:
    rep = json.loads((folder / "report.json").read_text())
    del rep["timings_s"], rep["created_utc"]
    return rep


def test_cluster_reports_equal_the_local_run(raws, grid, dask_cluster, tmp_path, monkeypatch):  # noqa: F811
    monkeypatch.chdir(raws)  # relative raw names: the workers, elsewhere, must still find them
    here, there = tmp_path / "here", tmp_path / "there"
    assert inspect(BATCH, grid, here, "-q") == 2
    assert inspect(BATCH, grid, there, "-q", "--scheduler", dask_cluster.scheduler_address) == 2
    assert batch_rows(there) == batch_rows(here)  # same verdicts, counts, folders, error sentence
    assert [r["verdict"] for r in batch_rows(there)] == ["FAIL", "PASS", "ERROR", "PASS"]
    for name in REPORTS:
        for file in ("lenses.csv", "defect_map.png", "defect_map_small.png"):
            assert (there / name / file).read_bytes() == (here / name / file).read_bytes(), (name, file)
        assert report_json(there / name) == report_json(here / name)
    flagged = {(d["row"], d["col"]) for d in report_json(there / "defects")["defects"]}
    assert flagged == set(SEEDED)
    assert not (there / "truncated").exists()


def test_single_raw_on_the_cluster(raws, dask_cluster, tmp_path, capsys):  # noqa: F811
    out = tmp_path / "one"
    code = main(["inspect", str(raws / "defects.npy"), "--white", str(raws / "white.npy"), "-c", SMALL_TOML,
                 "-o", str(out), "--scheduler", dask_cluster.scheduler_address])
    err = capsys.readouterr().err
    assert code == 1 and "FAIL: 3 flagged lenses" in err and (out / "report.json").exists()
    assert main(["inspect", str(raws / "truncated.npy"), "-c", SMALL_TOML, "-o", str(tmp_path / "bad"), "-q",
                 "--scheduler", dask_cluster.scheduler_address]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "truncated" in err and not (tmp_path / "bad").exists()


class KillOnce(distributed.WorkerPlugin):
    """Kill the worker process that starts a task whose key contains `word`, the first time only."""

    def __init__(self, word: str, marker: str) -> None:
        self.word, self.marker = word, marker

    def transition(self, key, start, finish, **kwargs):
        if finish == "executing" and self.word in str(key) and not os.path.exists(self.marker):
            Path(self.marker).write_text(str(os.getpid()))
            os._exit(1)  # no clean-up, no goodbye to the scheduler: as if the machine went down


def test_a_worker_killed_mid_batch_costs_no_frame_and_no_second_write(raws, grid, dask_cluster, tmp_path,  # noqa: F811
                                                                      monkeypatch):
    writes: dict[str, int] = {}
    real = report_write._write_bytes

    def counted(path, data):
        writes[path.parent.name] = writes.get(path.parent.name, 0) + 1
        real(path, data)

    monkeypatch.setattr(report_write, "_write_bytes", counted)
    marker = tmp_path / "killed"
    frames = [raws / n for n in ("perfect.npy", "defects.npy", "white.npy", "perfect.npy", "defects.npy")]
    out = tmp_path / "reports"
    with distributed.Client(dask_cluster, set_as_default=False) as admin:
        admin.register_plugin(KillOnce("inspect-00002-", str(marker)), name="kill-once")
        try:
            code = inspect(frames, grid, out, "-q", "--scheduler", dask_cluster.scheduler_address)
        finally:
            admin.unregister_worker_plugin("kill-once")
    assert marker.exists()  # a worker did die while starting frame 2
    assert code == 1
    rows = batch_rows(out)
    assert [r["verdict"] for r in rows] == ["PASS", "FAIL", "PASS", "PASS", "FAIL"]
    names = ["perfect", "defects", "white", "perfect-2", "defects-2"]
    assert [r["report"] for r in rows] == names
    assert writes == {name: len(report_write.REPORT_FILES) for name in names}  # every file of every set written once
    for name in names:
        assert sorted(p.name for p in (out / name).iterdir()) == sorted(report_write.REPORT_FILES.values())
    assert {(d["row"], d["col"]) for d in report_json(out / "defects")["defects"]} == set(SEEDED)


class KillAlways(distributed.WorkerPlugin):
    """Kill every worker process that starts a task whose key contains `word`."""

    def __init__(self, word: str) -> None:
        self.word = word

    def transition(self, key, start, finish, **kwargs):
        if finish == "executing" and self.word in str(key):
            os._exit(1)


def test_workers_dying_on_a_frame_over_and_over_is_one_sentence_exit_3(raws, grid, dask_cluster, tmp_path,  # noqa: F811
                                                                       capsys):
    out = tmp_path / "reports"
    with distributed.Client(dask_cluster, set_as_default=False) as admin:
        admin.register_plugin(KillAlways("inspect-00001-"), name="kill-always")
        try:
            code = inspect([raws / "defects.npy", raws / "perfect.npy"], grid, out, "-q",
                           "--scheduler", dask_cluster.scheduler_address)
        finally:
            admin.unregister_worker_plugin("kill-always")
    err = capsys.readouterr().err
    # the sentence names the task Dask gave up on: frame 1, or frame 2 queued on the same dying workers
    assert code == 3 and err.count("\n") == 1, err
    assert "Dask workers in turn died while running task 'inspect-0000" in err
    assert not (out / "batch.csv").exists() and not (out / "defects").exists()


def test_scan_folder_on_the_cluster(raws, grid, dask_cluster, tmp_path):  # noqa: F811
    scan = tmp_path / "scan"
    scan.mkdir()
    lines = [{"type": "header", "format": "mlaqc-scan-manifest", "version": 1}]
    for k, name in enumerate(["perfect.npy", "defects.npy"], 1):
        (scan / f"pos_{k:05d}.npy").write_bytes((raws / name).read_bytes())
        lines.append({"type": "position", "index": k, "files": [{"file": f"pos_{k:05d}.npy"}]})
    (scan / "manifest.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines) + '{"type": "posi')  # torn
    out = tmp_path / "reports"
    assert inspect([scan], grid, out, "-q", "--scheduler", dask_cluster.scheduler_address) == 1
    assert [(r["raw"], r["verdict"], r["report"]) for r in batch_rows(out)] == [
        (str(scan / "pos_00001.npy"), "PASS", "pos_00001"), (str(scan / "pos_00002.npy"), "FAIL", "pos_00002")]
    assert inspect([tmp_path], grid, tmp_path / "r2", "-q") == 2  # a folder without a manifest is bad input


def test_mlaqc_scheduler_environment_variable(raws, grid, dask_cluster, tmp_path, monkeypatch, capsys):  # noqa: F811
    assert cluster.scheduler_address(None) is None
    monkeypatch.setenv(cluster.ENV_VAR, dask_cluster.scheduler_address)
    assert cluster.scheduler_address(None) == dask_cluster.scheduler_address
    assert cluster.scheduler_address("local:1") == "local:1"  # the option wins
    out = tmp_path / "reports"
    assert inspect([raws / "perfect.npy", raws / "defects.npy"], grid, out) == 1
    err = capsys.readouterr().err
    assert f"at {dask_cluster.scheduler_address}" in err and "Dask: " in err
    assert [r["verdict"] for r in batch_rows(out)] == ["PASS", "FAIL"]
    monkeypatch.setenv(cluster.ENV_VAR, "  ")
    assert cluster.scheduler_address(None) is None


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_is_one_sentence_exit_3(raws, tmp_path, monkeypatch, capsys):  # noqa: F811
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 1.0)
    frames = [raws / "perfect.npy", raws / "defects.npy"]
    out = tmp_path / "reports"
    code = main(["inspect", *map(str, frames), "-c", SMALL_TOML, "-o", str(out),
                 "--scheduler", f"tcp://127.0.0.1:{_closed_port()}"])
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1 and "cannot reach the Dask scheduler" in err, err
    assert not out.exists()  # nothing written
    monkeypatch.setenv(cluster.ENV_VAR, f"127.0.0.1:{_closed_port()}")
    assert main(["inspect", *map(str, frames), "-c", SMALL_TOML, "-o", str(out), "-q"]) == 3
    assert "cannot reach" in capsys.readouterr().err


def _garbage_service() -> socket.socket:
    """A listening socket that answers every connection with HTTP garbage (no Dask scheduler)."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)

    def answer_garbage():
        while True:
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            with conn:
                conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n" * 8)

    threading.Thread(target=answer_garbage, daemon=True).start()
    return srv


def _live_clients() -> int:
    """Dask Clients alive in this process; a weak proxy whose object is gone (Numba's compiler leaves some) is
    not one, and asking it raises."""
    count = 0
    for o in gc.get_objects():
        try:
            count += isinstance(o, distributed.Client)
        except ReferenceError:
            pass
    return count


@pytest.mark.parametrize("service", ["garbage", "closed port"])
def test_a_failed_connection_leaves_no_client_for_the_garbage_collector(raws, tmp_path, monkeypatch, capsys,  # noqa: F811
                                                                         service):
    """A Client whose connection failed sits in a reference cycle; finalized by a later collection, its
    close() ran inside the next Dask start and hung it (distributed's loop-runner lock: the suite hung in
    a LocalCluster start). mlaqc finalizes it before saying why the cluster failed."""
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 4.0)
    srv = _garbage_service() if service == "garbage" else None
    port = srv.getsockname()[1] if srv else _closed_port()
    frames = [str(raws / "perfect.npy")]
    gc.collect()
    gc.disable()  # only mlaqc's own collection may finalize it
    try:
        before = _live_clients()
        code = main(["inspect", *frames, "-c", SMALL_TOML, "-o", str(tmp_path / "r"),
                     "--scheduler", f"tcp://127.0.0.1:{port}"])
        after = _live_clients()
    finally:
        gc.enable()
        if srv:
            srv.close()
    assert code == 3, capsys.readouterr().err
    assert after == before


def test_a_service_that_is_no_scheduler_and_bad_addresses(raws, tmp_path, monkeypatch, capsys):  # noqa: F811
    # 4 s: long enough that the garbage service's answer, not a timeout, ends the handshake on a loaded
    # machine (at 1 s it once timed out under the parallel suite); the worker-less scheduler waits it out
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 4.0)
    srv = _garbage_service()
    frames = [str(raws / "perfect.npy"), str(raws / "defects.npy")]
    try:
        code = main(["inspect", *frames, "-c", SMALL_TOML, "-o", str(tmp_path / "r"),
                     "--scheduler", f"tcp://127.0.0.1:{srv.getsockname()[1]}"])
    finally:
        srv.close()
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1 and "did not answer as a Dask scheduler" in err, err
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as empty:
        code = main(["inspect", *frames, "-c", SMALL_TOML, "-o", str(tmp_path / "r"),
                     "--scheduler", empty.scheduler_address])
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1 and "has no workers" in err, err
    for bad in ("local:0", "local:two", "foo://host:1"):
        assert main(["inspect", *frames, "-c", SMALL_TOML, "-o", str(tmp_path / "r"), "--scheduler", bad]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and bad in err
    assert not (tmp_path / "r").exists()


def test_follow_draws_progress_and_yields_every_result(dask_cluster):
    stream = io.StringIO()
    with distributed.Client(dask_cluster, set_as_default=False) as client:
        futures = {client.submit(operator.mul, k, 10, pure=False): k for k in range(6)}
        got = dict(cluster.follow(futures, "multiplying", progress=True, stream=stream))
    assert got == {k: 10 * k for k in range(6)}
    assert "multiplying [" in stream.getvalue() and "100.0%" in stream.getvalue()


def test_a_worker_that_cannot_see_the_raw_says_so(raws, grid, dask_cluster, tmp_path,  # noqa: F811
                                                  monkeypatch, capsys):
    cfg = load_config(SMALL_TOML)
    spec = BatchSpec(cfg, None, None, cfg.to_dict())
    missing = str(tmp_path / "elsewhere.npy")
    assert set(inspect_remote(spec, "elsewhere.npy", missing, True)) == {"unseen"}
    assert "does not exist" in inspect_remote(spec, "elsewhere.npy", missing, False)["error"]
    # this process "sees" a file the workers do not: the run stops with one sentence, exit status 3
    real_exists = os.path.exists
    monkeypatch.setattr(os.path, "exists", lambda p: p == missing or real_exists(p))
    code = inspect([raws / "perfect.npy", missing], grid, tmp_path / "r", "-q",
                   "--scheduler", dask_cluster.scheduler_address)
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1 and "cannot see" in err and "shared filesystem" in err, err
    assert not (tmp_path / "r" / "batch.csv").exists()
