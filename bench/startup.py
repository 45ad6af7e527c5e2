"""Start-up benchmark (issue #23): what a user waits for, as whole processes, side by side with other code.

    python bench/startup.py                        # this checkout alone
    python bench/startup.py --old /path/to/checkout  # and another checkout of mlaqc, interleaved run by run

Figures (median of --runs, min-max beside it):
- warm `mlaqc inspect` of the tracer-made 2048² frame bench/inspection.py renders (report set included);
- first run after install: the same with an empty Numba cache (NUMBA_CACHE_DIR set to a new folder),
  which is where a fresh install stands (for this checkout: kernels compiled ahead of time at install);
- `mlaqc --help` and `mlaqc inspect --help`;
- the report set of that frame in-process (render_report: every file's bytes, nothing written).
Bars: warm <= 0.5x the old code's (with --old), first run <= 2x the warm time, help <= 0.3 s, report set
<= 0.2 s. The host's speed drifts: only figures taken in the same run compare.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def whole(cmd: list[str], env: dict[str, str]) -> float:
    """Seconds one whole process takes (it must succeed or FAIL the QC: exit 0 or 1). Run outside any
    checkout: `python -m` puts the working folder first on the import path, before PYTHONPATH."""
    t = time.perf_counter()
    done = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                          cwd=tempfile.gettempdir())
    if done.returncode not in (0, 1):
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr.strip()[-400:]}")
    return time.perf_counter() - t


def line(name: str, values: list[float], bar: str = "") -> float:
    med = statistics.median(values)
    print(f"  {name:<44} {med:7.3f} s  ({min(values):.3f}-{max(values):.3f}){'  ' + bar if bar else ''}", flush=True)
    return med


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=9)
    ap.add_argument("--old", help="a checkout of another mlaqc version, run with PYTHONPATH (interleaved)")
    args = ap.parse_args()
    from inspection import frame_path

    from mlaqc.optics.config import default_config

    frame = str(frame_path(default_config()))
    out = Path(tempfile.mkdtemp(prefix="mlaqc-startup-"))
    versions = {"new": dict(os.environ)}
    if args.old:
        versions["old"] = {**os.environ, "PYTHONPATH": str(Path(args.old).resolve())}
    py = [sys.executable, "-m", "mlaqc"]
    inspect = py + ["inspect", frame, "--out", str(out / "r"), "-q"]
    for env in versions.values():
        whole(inspect, env)  # warm each once (Numba's cache, the page cache)

    times: dict[tuple[str, str], list[float]] = {}
    for _ in range(args.runs):  # interleaved: a drift of the host's speed hits both alike
        for name, env in versions.items():
            times.setdefault((name, "warm"), []).append(whole(inspect, env))
            times.setdefault((name, "help"), []).append(whole(py + ["--help"], env))
            times.setdefault((name, "inspect help"), []).append(whole(py + ["inspect", "--help"], env))
    first_runs = max(1, min(args.runs, 3))
    for name, env in versions.items():  # an empty kernel cache each time: the first run after install
        for _ in range(first_runs):
            fresh = {**env, "NUMBA_CACHE_DIR": tempfile.mkdtemp(prefix="mlaqc-numba-")}
            times.setdefault((name, "first"), []).append(whole(inspect, fresh))

    print(f"whole processes on {os.cpu_count()} cores, median of {args.runs} ({first_runs} for first runs):")
    warm = {}
    for name in versions:
        print(f" {name}:")
        warm[name] = line("warm `mlaqc inspect` (2048² frame + report)", times[(name, "warm")])
        first = line("first run (empty kernel cache)", times[(name, "first")])
        print(f"  {'':<44} {first / warm[name]:7.2f} x warm  (bar <= 2x)")
        line("`mlaqc --help`", times[(name, "help")], "(bar <= 0.3 s)")
        line("`mlaqc inspect --help`", times[(name, "inspect help")], "(bar <= 0.3 s)")
    if "old" in warm:
        ratios = [a / b for a, b in zip(times[("new", "warm")], times[("old", "warm")])]
        print(f" warm new / old, run by run: median {statistics.median(ratios):.3f} "
              f"({min(ratios):.3f}-{max(ratios):.3f})  (bar <= 0.5)")
    report_set(frame, args.runs)
    return 0


def report_set(frame: str, runs: int) -> None:
    """The report set of one inspection rendered in-process: the first time (lazy references, first
    calls) and the best of `runs` after it."""
    from mlaqc.inspection.pipeline import inspect_file
    from mlaqc.optics.config import default_config
    from mlaqc.report.write import render_report

    result = inspect_file(frame, default_config())
    t = time.perf_counter()
    render_report(result)
    first = time.perf_counter() - t
    later = []
    for _ in range(runs):
        t = time.perf_counter()
        render_report(result)
        later.append(time.perf_counter() - t)
    print(f" report set of {result.grid.rows * result.grid.cols:,} lenses in-process: first {first:.3f} s, "
          f"then median {statistics.median(later):.3f} s (best {min(later):.3f})  (bar <= 0.2 s)")


if __name__ == "__main__":
    sys.exit(main())
