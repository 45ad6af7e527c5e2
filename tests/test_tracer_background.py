"""The tracer's variants compiled in the background of the first command that traces
(mlaqc.optics.tracer_background, the job mlaqc.optics.tracer_compile_job): started once, never twice at a time, never once every variant is
compiled for the current sources, said on screen; the job compiles what is missing and stamps the cache.
The process start and the compiles are replaced by recorders: nothing here spawns or compiles."""

from __future__ import annotations

import fcntl
import io
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mlaqc.optics import tracer_background as bg
from mlaqc.optics import tracer_compile_job as job
from mlaqc.optics import tracer_variants

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"


@pytest.fixture
def place(tmp_path, monkeypatch):
    """The stamp, log and lock in a folder of the test's own; the switch on; a fresh process' state."""
    monkeypatch.setenv("MLAQC_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv(bg.ENV_SWITCH, "1")
    monkeypatch.setattr(bg, "stamp_path", lambda: tmp_path / "tracer_variants.ready")
    monkeypatch.setattr(bg, "_STARTED", type(bg._STARTED)())
    started = []
    monkeypatch.setattr(bg.subprocess, "Popen", lambda cmd, **kw: started.append((cmd, kw)))
    return tmp_path, started


def test_the_first_tracing_command_starts_one_background_compile(place):
    _, started = place
    said = io.StringIO()
    assert bg.start_if_needed(said) is True
    assert bg.start_if_needed(said) is False  # once per process
    (cmd, kw), = started
    assert cmd[-3:] == ["-m", "mlaqc.optics.tracer_compile_job", str(os.getpid())] and kw["start_new_session"]
    assert kw["env"][bg.ENV_SWITCH] == "0"  # the job itself starts no other
    assert "in the background" in said.getvalue() and str(bg.log_path()) in said.getvalue()


def test_no_background_compile_when_all_are_compiled_one_runs_or_it_is_off(place, monkeypatch):
    tmp, started = place
    bg.mark_all_compiled()
    assert bg.all_compiled() and not bg.start_if_needed(io.StringIO())
    monkeypatch.setattr(bg, "_STARTED", type(bg._STARTED)())
    (tmp / "tracer_variants.ready").write_text("another source\n")  # sources changed since: stale
    assert not bg.all_compiled()
    lock = bg.lock_path()
    lock.parent.mkdir(parents=True, exist_ok=True)
    with open(lock, "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # as the running job holds it
        assert bg.running() and not bg.start_if_needed(io.StringIO())
    assert not bg.running()
    monkeypatch.setattr(bg, "_STARTED", type(bg._STARTED)())
    monkeypatch.setenv(bg.ENV_SWITCH, "0")
    assert not bg.start_if_needed(io.StringIO())
    assert started == []


def test_the_key_follows_numba_and_the_sources(monkeypatch):
    key = bg.sources_key()
    monkeypatch.setattr("importlib.metadata.version", lambda name: "0.0-other")
    assert bg.sources_key() != key


def test_the_job_compiles_what_is_missing_fixtures_first_then_stamps(place, monkeypatch, capsys):
    tmp, _ = place
    ready = {tracer_variants.VARIANTS[0]}  # the install's
    compiled = []
    monkeypatch.setattr(tracer_variants, "is_ready", lambda v: v in ready)

    def compile_all(todo, log=print):
        compiled.extend(todo)
        return [(v, 1.0, "") for v in todo]

    monkeypatch.setattr(tracer_variants, "compile_all", compile_all)
    monkeypatch.setattr(job, "_lowest_priority", lambda: None)
    assert job.main([]) == 0
    assert len(compiled) == len(tracer_variants.VARIANTS) - 1 and tracer_variants.VARIANTS[0] not in compiled
    first = compiled[:3]
    assert all(v.lenses != "grid" and not v.tilted for v in first)  # what the shipped fixtures use comes first
    assert bg.all_compiled()
    assert "compiling 11 tracer variant(s)" in capsys.readouterr().out


def test_a_failed_variant_leaves_no_stamp_and_a_second_job_waits_for_none(place, monkeypatch):
    monkeypatch.setattr(tracer_variants, "is_ready", lambda v: False)
    monkeypatch.setattr(tracer_variants, "compile_all", lambda todo, log=print: [(v, 1.0, "boom") for v in todo])
    monkeypatch.setattr(job, "_lowest_priority", lambda: None)
    assert job.main([]) == 0 and not bg.all_compiled()
    lock = bg.lock_path()
    with open(lock, "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        monkeypatch.setattr(tracer_variants, "compile_all", lambda *a, **k: pytest.fail("a second job compiled"))
        assert job.main([]) == 0


def test_the_job_waits_for_the_command_that_started_it():
    import threading

    starter = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(0.6)"])
    threading.Thread(target=starter.wait, daemon=True).start()  # reaped as its shell would reap it
    t0 = time.monotonic()
    job._after(starter.pid, limit_s=10.0)
    waited = time.monotonic() - t0
    assert 0.3 < waited < 5.0
    t0 = time.monotonic()
    job._after(os.getpid(), limit_s=0.3)  # a command still running: not for ever
    assert time.monotonic() - t0 < 2.0


def test_a_numba_renderer_asks_for_the_background_compile(monkeypatch):
    pytest.importorskip("numba")
    from mlaqc.optics.config import load_config
    from mlaqc.optics.render import Renderer

    asked = []
    monkeypatch.setattr(bg, "start_if_needed", lambda *a, **k: asked.append(1))
    Renderer(load_config(FIXTURES / "small_camera.toml"), engine="numpy")
    assert asked == []
    Renderer(load_config(FIXTURES / "small_camera.toml"), engine="numba")
    assert asked == [1]
