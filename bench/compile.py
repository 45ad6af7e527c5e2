"""The tracer compiled once (#40): what a user waits for, as whole processes.

    python bench/compile.py --variants                 # every tracer variant compiled cold (an empty Numba
                                                       # cache of its own), one process per core at a time
    python bench/compile.py --variants --against OLD   # and, back to back, the variants OLD's test suite
                                                       # compiled (tests/conftest.py there) with OLD's code
    python bench/compile.py --first-use                # right after `pip install -e .`: the first
                                                       # `mlaqc simulate` of each fixture and `mlaqc demo`,
                                                       # then the same again (warm), run by run

Bars (#40): the first run of each <= 2x its warm run; the compile side by side with the old code's. Run
--first-use before anything else has used the install (the test suite loads but compiles no variant). The
host's speed drifts 2x from day to day: only figures from one run compare.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from mlaqc.parallel import cores

ROOT = Path(__file__).resolve().parent.parent
FIXTURES = ROOT / "fixtures"

# the new code's variants and the old code's (tests/conftest.py TRACER_VARIANTS before #40), each compiled in
# a fresh interpreter with the tree's own mlaqc first on the path
NEW_JOB = ("from mlaqc.optics.tracer_variants import VARIANTS, compile_variant\n"
           "print(compile_variant(VARIANTS[{i}])[1] or 'ok')")
OLD_JOB = ("import sys; sys.path.insert(0, {tests!r}); import conftest\n"
           "conftest._render_variant(*conftest.TRACER_VARIANTS[{i}]); print('ok')")


def _cold(tree: Path, code: str) -> float:
    """Seconds a fresh interpreter takes to run `code` with `tree`'s mlaqc and an empty Numba cache."""
    with tempfile.TemporaryDirectory(prefix="numba-cold-") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=str(tree))
        t = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                              cwd=tempfile.gettempdir())
        seconds = time.perf_counter() - t
    if done.returncode != 0 or done.stdout.strip().splitlines()[-1:] != ["ok"]:
        raise SystemExit(f"a compile job failed in {tree}: {(done.stdout + done.stderr).strip()[-600:]}")
    return seconds


def variants(against: Path | None) -> None:
    """Cold compile of every variant, this tree's (and OLD's), `cores` jobs at a time; wall and CPU sums."""
    trees = [("this", ROOT, NEW_JOB, 12)]
    if against is not None:
        tests = str(against / "tests")
        count = int(subprocess.run([sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); import conftest;"
                                    " print(len(conftest.TRACER_VARIANTS))", tests], capture_output=True, text=True,
                                   env=dict(os.environ, PYTHONPATH=str(against)), check=True).stdout)
        trees.append(("old", against, OLD_JOB.replace("{tests!r}", repr(tests)), count))
    for label, tree, job, count in trees:
        start = time.perf_counter()
        with ThreadPoolExecutor(max_workers=cores()) as pool:
            seconds = list(pool.map(lambda i: _cold(tree, job.format(i=i)), range(count)))
        wall = time.perf_counter() - start
        print(f"{label} ({tree}): {count} variants, {wall:.0f} s on {cores()} cores ({sum(seconds):.0f} s of "
              f"processes; each {min(seconds):.0f}-{max(seconds):.0f} s, median {sorted(seconds)[count // 2]:.0f} s)",
              flush=True)


def _fixture_runs(tmp: Path) -> dict[str, list[str]]:
    """`mlaqc simulate` arguments of each fixture case the issue names."""
    import numpy as np

    texture = tmp / "texture.npy"
    np.save(texture, np.random.default_rng(0).uniform(0.1, 1.0, (64, 64)))
    quick = ["--rays-per-pixel", "1", "--no-noise", "--quiet"]
    return {
        "square (Table 1)": [*quick],
        "hex": ["-c", str(FIXTURES / "hex_camera.toml"), *quick],
        "circle": ["-c", str(FIXTURES / "circle_camera.toml"), *quick],
        "hex-circle": ["-c", str(FIXTURES / "hex_circle_camera.toml"), *quick],
        "through-focus": ["--scene", "through-focus", "--rays", "2000000", "--no-noise", "--quiet"],
        "texture": ["--scene", "texture", "--texture", str(texture), *quick],
        "tilted error map": ["--random-defects", "20", "--defect-types", "tilt", *quick],
    }


def _whole(cmd: list[str], cwd: Path) -> float:
    """Seconds one whole process takes, with an empty model cache and results database of the run's own
    (the install's Numba cache is what is measured)."""
    env = dict(os.environ, MLAQC_CACHE=str(cwd / "cache"), MLAQC_DB=str(cwd / "results.sqlite"))
    t = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, env=env)
    if done.returncode not in (0, 1):
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr.strip()[-400:]}")
    return time.perf_counter() - t


def first_use() -> None:
    """The first run of each command after install, then a warm run: seconds and their ratio."""
    with tempfile.TemporaryDirectory(prefix="mlaqc-first-") as tmp_name:
        tmp = Path(tmp_name)
        runs = {f"simulate {name}": [sys.executable, "-m", "mlaqc", "simulate", "--out", str(tmp / "f.tiff"), *args]
                for name, args in _fixture_runs(tmp).items()}
        runs["demo"] = [sys.executable, "-m", "mlaqc", "demo", "--out", str(tmp / "demo"), "--quiet"]
        print("first run after install, then warm (whole processes):")
        for name, cmd in runs.items():
            first = _whole(cmd, tmp)
            warm = _whole(cmd, tmp)
            print(f"  {name:28s} first {first:6.1f} s, warm {warm:6.1f} s, x{first / warm:.2f}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", action="store_true", help="cold compile of every tracer variant")
    ap.add_argument("--against", type=Path, metavar="OLD", help="with --variants: also OLD's variants")
    ap.add_argument("--first-use", action="store_true", help="first run of each command after install, then warm")
    args = ap.parse_args()
    if not (args.variants or args.first_use):
        ap.error("say --variants and/or --first-use")
    if args.first_use:
        first_use()
    if args.variants:
        variants(args.against)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
