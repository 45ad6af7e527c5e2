"""`mlaqc kernels`: compile the inspection kernels ahead of time for this machine, or say whether they are.

`pip install` does this already (setup.py); the command is for an install that could not (no C compiler
then, `--no-build-isolation` without Numba), a kernel source edited in a development checkout, or a
package folder moved to a machine with another CPU. Without it those runs still work: Numba compiles the
kernels on first use instead (about a minute once, then from its cache).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from mlaqc.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `kernels` subcommand."""
    p = sub.add_parser("kernels", help="compile the inspection kernels ahead of time for this machine (or check them)",
                       description="Compile the inspection kernels ahead of time (numba.pycc) into the package folder "
                                   "(or the user's cache when that is read-only), for this CPU, so no command compiles "
                                   "them. `pip install` does this already; run it after editing a kernel.")
    p.add_argument("--check", action="store_true", help="only say whether the compiled kernels are current (exit 1 if not)")
    p.add_argument("--rebuild", action="store_true", help="compile even when the compiled kernels are current")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
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
