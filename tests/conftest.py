"""Test-wide settings: Qt offscreen, helpers shared across test modules, and a parallel Numba warm-up."""

import os
import time

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.pop("MLAQC_SCHEDULER", None)  # a developer's cluster must not take over the tests that inspect locally

# ------------------------------------------------------------------------------------ Numba warm-up
# The tracer's kernel is compiled once per variant (which of its MLA-rotation, global-rotation and
# texture arguments are None; the lens-boundary model): about 45 s each, single-threaded, most of a
# cold run's time (CI's fresh clone has no compiled code). cache=True keeps each compiled variant in
# the package's __pycache__ (or $NUMBA_CACHE_DIR), where every process finds it: pytest, xdist workers,
# the `mlaqc` subprocesses and the Dask workers of the cluster tests. Before the first test, the
# variants the suite uses (and the inspection kernels) are compiled there by one process per core at
# once. Warm (the usual local case), each job is a cache load: a second or two in all. A variant not
# listed is compiled by the first test that needs it, as before. The warm-up runs for whole folders
# (`pytest`, `pytest tests`), not for a run of named files or tests, which compiles only what it uses;
# MLAQC_TEST_WARMUP=1 or 0 turns it on or off whatever the run.

# (per-lens tilt: MLA rotation array, global MLA rotation: camera rotation array, texture, boundaries)
TRACER_VARIANTS = (
    (False, False, False, "grid"),
    (False, True, False, "grid"),
    (False, False, True, "grid"),
    (True, True, False, "grid"),
    (True, True, True, "grid"),
    (False, True, True, "grid"),
    (True, False, False, "grid"),
    (False, False, False, "sag-intersection"),
    (True, True, False, "sag-intersection"),
)
WARM_JOBS = ("inspection", *TRACER_VARIANTS)


def warm_job(job) -> tuple[float, str]:
    """Compile (or load from the cache) the kernels one job uses; (seconds taken, error or '')."""
    start = time.perf_counter()
    try:
        if job == "inspection":
            _inspect_analytic_frame()
        else:
            _render_variant(*job)
    except Exception as exc:  # noqa: BLE001 - a failed warm-up only costs time: the tests will say what broke
        return time.perf_counter() - start, f"{job}: {type(exc).__name__}: {exc}"
    return time.perf_counter() - start, ""


def _render_variant(tilted: bool, rotated: bool, texture: bool, boundaries: str) -> None:
    """A few rays through a 2 x 2-lens camera with the tracer's kernel for that variant."""
    import numpy as np

    from mlaqc.optics.config import config_from_dict
    from mlaqc.optics.errormap import ErrorMap
    from mlaqc.optics.render import Renderer
    from mlaqc.optics.scene import TextureScene, WhiteScene

    cfg = config_from_dict({"mla": {"count_w": 2, "count_h": 2, "boundaries": boundaries},
                            "sensor": {"width_px": 48, "height_px": 48}})
    errors = ErrorMap.zeros(2, 2)
    if tilted:
        errors = errors.with_lens(1, 1, tilt_x_deg=0.5)
    if rotated:
        errors = errors.with_globals(mla_rotation_deg=0.3)
    scene = TextureScene(np.ones((3, 3))) if texture else WhiteScene()
    Renderer(cfg, errors, engine="numba").render(scene, rays=2_000, seed=0, threads=1)


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
    from pathlib import Path

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

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    start = time.perf_counter()
    # spawn: fresh interpreters (no forked pytest or Qt state), which import this file as `conftest`
    with ProcessPoolExecutor(max_workers=max(1, min(cores, len(WARM_JOBS))),
                             mp_context=multiprocessing.get_context("spawn")) as pool:
        results = list(pool.map(warm_job, WARM_JOBS))
    spent = time.perf_counter() - start
    out = config.get_terminal_writer()
    for _, error in results:
        if error:
            out.line(f"numba warm-up failed (the tests compile what they need): {error}")
    if spent > 10:  # a cold cache: say where the time went
        out.line(f"numba warm-up: {len(results)} jobs in {spent:.0f} s on {cores} cores "
                 f"({sum(s for s, _ in results):.0f} s of compilation)")


def pytest_sessionstart(session):
    _warm_numba(session.config)
