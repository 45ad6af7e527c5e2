"""Test-wide settings: Qt offscreen, a parallel Numba warm-up, and (under pytest-xdist) the GUI tests
run while no other test does."""

import atexit
import contextlib
import os
import shutil
import tempfile
import time

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.pop("MLAQC_SCHEDULER", None)  # a developer's cluster must not take over the tests that inspect locally
# the warm-up below compiles the tracer's variants; no test starts a background compile of its own
os.environ["MLAQC_BACKGROUND_COMPILE"] = "0"
# every inspection records into a results database (mlaqc.resultsdb): the tests' go into one of the run's own,
# never the developer's (set before xdist starts its workers, which inherit it); a test that reads records
# names its own with --db
if "MLAQC_TEST_DB_DIR" not in os.environ:
    os.environ["MLAQC_TEST_DB_DIR"] = tempfile.mkdtemp(prefix="mlaqc-test-db-")
    os.environ["MLAQC_DB"] = os.path.join(os.environ["MLAQC_TEST_DB_DIR"], "results.sqlite")
    # removed when the process that made it ends (the workers inherit it and leave it be)
    atexit.register(shutil.rmtree, os.environ["MLAQC_TEST_DB_DIR"], ignore_errors=True)

# ------------------------------------------------------------------------------------ Numba warm-up
# The tracer's kernel has twelve compiled variants (mlaqc.optics.tracer_variants: lens boundaries x lattice x
# per-lens tilts). `pip install -e .` compiles the fixtures' five into Numba's cache (setup.py), in the
# package's __pycache__ (or $NUMBA_CACHE_DIR); the warm-up compiles the rest there, where every process
# finds them: pytest, xdist workers, the `mlaqc` subprocesses and the Dask workers of the cluster tests.
# Before the first test, one process per core compiles or loads each variant (and compiles the inspection
# kernels' JIT rest): on CI's fresh clone the seven the install left out compile here, both cores at once
# (about a minute); once they are in the cache, a second or two in all. No test compiles its own. The warm-up runs for whole folders
# (`pytest`, `pytest tests`), not for a run of named files or tests, which compiles only what it uses;
# MLAQC_TEST_WARMUP=1 or 0 turns it on or off whatever the run.


def _warm_jobs() -> tuple:
    from mlaqc.optics.tracer_variants import VARIANTS

    return ("inspection", *VARIANTS)


def warm_job(job) -> tuple[float, str]:
    """Compile (or load from the cache) the kernels one job uses; (seconds taken, error or '')."""
    start = time.perf_counter()
    try:
        if job == "inspection":
            _inspect_analytic_frame()
        else:
            from mlaqc.optics.tracer_variants import compile_variant

            seconds, error = compile_variant(job)
            if error:
                return seconds, f"{job.name}: {error}"
    except Exception as exc:  # noqa: BLE001 - a failed warm-up only costs time: the tests will say what broke
        return time.perf_counter() - start, f"{job}: {type(exc).__name__}: {exc}"
    return time.perf_counter() - start, ""


def _inspect_analytic_frame() -> None:
    """Inspect a healthy analytic frame of the small camera (calibration, metrics, identification)."""
    from pathlib import Path

    import numpy as np

    from analytic_frames import AnalyticModel
    from mlaqc.inspection.pipeline import inspect_image
    from mlaqc.optics.config import load_config

    cfg = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")
    model = AnalyticModel(shape=(cfg.sensor.height_px, cfg.sensor.width_px),
                          lenses=(cfg.mla.count_h, cfg.mla.count_w), exit_pupil_px=900.0, rotation_deg=0.7)
    inspect_image(model.render().astype(np.float32), cfg)


def _wants_warmup(config) -> bool:
    if hasattr(config, "workerinput"):
        return False  # an xdist worker: the controller warmed up before starting it
    switch = os.environ.get("MLAQC_TEST_WARMUP", "")
    if switch in ("0", "1"):
        return switch == "1"

    return all((config.invocation_params.dir / arg.split("::")[0]).is_dir() for arg in config.args)


def _warm_numba(config) -> None:
    if not _wants_warmup(config):
        return
    try:
        from mlaqc.optics import raytrace_kernels
    except ImportError:
        return
    if not raytrace_kernels.AVAILABLE:
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from mlaqc.parallel import cores as core_count

    cores = core_count()
    start = time.perf_counter()
    # spawn: fresh interpreters (no forked pytest or Qt state), which import this file as `conftest`
    jobs = _warm_jobs()
    with ProcessPoolExecutor(max_workers=max(1, min(cores, len(jobs))),
                             mp_context=multiprocessing.get_context("spawn")) as pool:
        results = list(pool.map(warm_job, jobs))
    spent = time.perf_counter() - start
    out = config.get_terminal_writer()
    for _, error in results:
        if error:
            out.line(f"numba warm-up failed (the tests compile what they need): {error}")
    if spent > 10:  # a cold cache: say where the time went
        out.line(f"numba warm-up: {len(results)} jobs in {spent:.0f} s on {cores} cores "
                 f"({sum(s for s, _ in results):.0f} s of compilation)")
    if not any(error for _, error in results):
        from mlaqc.optics.tracer_background import mark_all_compiled

        mark_all_compiled()  # a later `mlaqc` command in this checkout starts no background compile


def pytest_sessionstart(session):
    _warm_numba(session.config)


# ------------------------------------------------------------------------------ pytest-xdist
# Under `-n N` the GUI tests (modules test_gui*) hold their wall-clock bounds (a stage stopped
# mid-move by closing the window, live-view rates) only with the cores to themselves, as in a serial
# run: each runs under an exclusive lock, every other test under a shared one, so that a GUI test
# waits for the other workers' current tests and they wait for it. A turnstile lock keeps a waiting
# GUI test from being overtaken by the next shared test. The lock files live in a folder the xdist
# controller makes for the run (before it starts the workers, which inherit its path).
EXCLUSIVE_MODULES = ("test_gui",)
LOCK_DIR_ENV = "MLAQC_TEST_LOCK_DIR"


def pytest_configure(config):
    if not hasattr(config, "workerinput") and getattr(config.option, "numprocesses", None):
        config._mlaqc_lock_dir = tempfile.mkdtemp(prefix="mlaqc-xdist-locks-")
        os.environ[LOCK_DIR_ENV] = config._mlaqc_lock_dir


def pytest_unconfigure(config):
    folder = getattr(config, "_mlaqc_lock_dir", None)
    if folder:
        os.environ.pop(LOCK_DIR_ENV, None)
        shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def _run_lock(folder: str, exclusive: bool):
    import fcntl

    with open(os.path.join(folder, "turnstile"), "a") as gate, open(os.path.join(folder, "run"), "a") as run:
        fcntl.flock(gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(run, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        finally:
            fcntl.flock(gate, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(run, fcntl.LOCK_UN)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    folder = os.environ.get(LOCK_DIR_ENV) if hasattr(item.config, "workerinput") else None
    if not folder or not os.path.isdir(folder):
        yield
        return
    with _run_lock(folder, item.path.name.startswith(EXCLUSIVE_MODULES)):
        yield


@pytest.fixture
def offline_window(qtbot):
    """The app on the small camera with its devices not connected; on close every worker thread has ended."""
    from pathlib import Path

    from gui.app import MainWindow

    w = MainWindow("mock://", "mock://", str(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml"),
                   connect=False)
    w.show()
    yield w
    w.close()
    assert all(t.thread.isFinished() for t in w.threads.values()), \
        [n for n, t in w.threads.items() if not t.thread.isFinished()]
