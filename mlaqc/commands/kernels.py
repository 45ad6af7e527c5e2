"""`mlaqc kernels`: compile the inspection kernels and the ray tracer for this machine, or say whether they are.

`pip install -e .` compiles the inspection kernels and the shipped fixtures' tracer variants (setup.py),
and the first command that traces compiles the other tracer variants in the background
(mlaqc.optics.tracer_background); this command compiles everything in the foreground: for an install that
could not (no C
compiler then, `--no-build-isolation` without Numba, a non-editable install, whose tracer cache the build
cannot place), a kernel source edited in a development checkout, or a package folder moved to a machine
with another CPU. Without it those runs still work: Numba compiles what they use on first use instead
(tens of seconds per kernel, said on screen, then from its cache).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from mlaqc.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `kernels` subcommand."""
    p = sub.add_parser("kernels", help="compile the inspection kernels and the ray tracer for this machine (or check them)",
                       description="Compile the inspection kernels ahead of time (numba.pycc) into the package folder "
                                   "(or the user's cache when that is read-only), and the ray tracer's variants into "
                                   "Numba's cache, for this CPU, so no command compiles them. `pip install -e .` does "
                                   "this already; run it after editing a kernel.")
    p.add_argument("--check", action="store_true", help="only say whether the compiled kernels are current (exit 1 if not)")
    p.add_argument("--rebuild", action="store_true", help="compile even when the compiled kernels are current")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    os.environ["MLAQC_BACKGROUND_COMPILE"] = "0"  # this command compiles (or checks) in the foreground
    inspection = _inspection_kernels(args)
    tracer = _tracer(args.check, args.rebuild)
    return max(inspection, tracer)


def _inspection_kernels(args: argparse.Namespace) -> int:
    from mlaqc import compiled

    current, why = compiled.aot_status()
    if args.check or (current and not args.rebuild):
        print(f"kernels: {'current' if current else 'not compiled ahead of time'} ({why})")
        return 0 if current else 1
    from mlaqc.compiled_build import build_extension, default_target

    target = default_target()
    if not os.access(target.parent, os.W_OK):
        target = compiled.extension_paths()[1]
    try:
        import numba  # noqa: F401 - the compiler itself
    except ImportError:
        raise InputError("compiling the kernels needs Numba (pip install numba).") from None
    print(f"kernels: compiling ahead of time into {target} (about a minute) ...", file=sys.stderr, flush=True)
    try:
        build_extension(Path(target), log=lambda text: print(text, file=sys.stderr))
    except Exception as exc:  # noqa: BLE001 - a compiler's failure: one sentence, the JIT stays in use
        raise InputError(f"could not compile the kernels ahead of time ({type(exc).__name__}: {exc}); "
                         "Numba compiles them on first use instead.") from exc
    return 0


def _tracer(check: bool, rebuild: bool) -> int:
    """The tracer's variants: which are in Numba's cache; compile the missing ones (all with `rebuild`)."""
    from mlaqc.optics import raytrace_kernels, tracer_background
    from mlaqc.optics.tracer_variants import VARIANTS, compile_all, is_ready

    if not raytrace_kernels.AVAILABLE:
        print("tracer: Numba is not installed (the NumPy engine traces instead)")
        return 0 if check else 1
    missing = [v for v in VARIANTS if not is_ready(v)]
    if not missing:
        tracer_background.mark_all_compiled()
    if check or not (missing or rebuild):
        names = "; ".join(v.name for v in missing)
        busy = missing and tracer_background.running()
        print(f"tracer: {len(VARIANTS) - len(missing)} of {len(VARIANTS)} variants compiled"
              + (f"; not: {names}" if missing else "")
              + (f" (a background compile is running: {tracer_background.log_path()})" if busy else ""))
        return 1 if missing else 0
    todo = VARIANTS if rebuild else tuple(missing)
    if rebuild:
        _forget_tracer_cache()
    print(f"tracer: compiling {len(todo)} variant(s) into Numba's cache ...", file=sys.stderr, flush=True)
    failed = [v for v, _, error in compile_all(todo, log=lambda text: print(text, file=sys.stderr)) if error]
    if failed:
        raise InputError(f"could not compile the tracer's {', '.join(v.name for v in failed)}; "
                         "Numba compiles them on first use instead.")
    tracer_background.mark_all_compiled()
    return 0


def _forget_tracer_cache() -> None:
    """Remove the tracer's entries from Numba's cache, so that --rebuild compiles rather than loads."""
    from mlaqc.optics import raytrace_kernels, tracer_background

    tracer_background.forget()
    for kernel in (raytrace_kernels.kernel, raytrace_kernels.kernel_sag):
        try:
            cache_path = Path(kernel._cache._cache_path)
        except AttributeError:
            continue
        stem = f"{Path(raytrace_kernels.__file__).stem}.{kernel.__name__}-"
        for entry in cache_path.glob(f"{stem}*"):
            entry.unlink(missing_ok=True)
