"""The `mlaqc` command line: one console script, one subcommand per job.

Each subcommand lives in a module with `register(subparsers)` that adds its parser and sets `func`.
Hardware (`drivers`) and GUI commands are reached only from here, lazily, as DESIGN.md asks.
Exit status: 0 success (or PASS), 1 FAIL, 2 bad input, 3 device error, 4 results database error,
130 interrupted.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import importlib.util
import sys
from collections.abc import Sequence

from mlaqc import __version__
from mlaqc.errors import MlaqcError

# Every subcommand: the module that registers it, and the line `mlaqc --help` shows for it (the same as
# the module's own `help=`, checked by tests/test_fast_paths.py). `mlaqc COMMAND ...` imports that module
# alone, and `mlaqc --help` none of them: their numerical and hardware imports cost tenths of a second.
COMMANDS = {
    "simulate": ("mlaqc.commands.simulate", "render a raw image with the ray-traced camera model"),
    "errormap": ("mlaqc.commands.errormap", "create or check a per-lens error map (JSON keyed by U(m,n))"),
    "calibrate": ("mlaqc.commands.calibrate", "find every microlens in a white image and write grid.json"),
    "inspect": ("mlaqc.commands.inspect", "inspect raw images: defective lenses, type, size, PASS/FAIL"),
    "models": ("mlaqc.commands.models",
               "build (or rebuild) a camera's reference model, signature tables, through-focus model and assembly calibration"),
    "kernels": ("mlaqc.commands.kernels", "compile the inspection kernels and the ray tracer for this machine (or check them)"),
    "decode": ("mlaqc.commands.decode",
               "decode the light field of scene frames (views, refocusing), corrected by an inspection's report"),
    "lot": ("mlaqc.commands.lot", "lot views of the results database: yield, Pareto, defect map, repeating defects"),
    "demo": ("mlaqc.commands.demo", "simulate an MLA with seeded defects, inspect it, report found vs seeded"),
    "capture": ("drivers.commands", "capture raw frames (or averages) from a camera with provenance sidecars"),
    "scan": ("drivers.commands", "XY scan: move, settle, capture at each plan position; resumable"),
    "gui": ("gui.commands", "the desktop QC app: live view, stage, inspection, scans"),
}
COMMAND_MODULES = tuple(dict.fromkeys(module for module, _ in COMMANDS.values()))


def build_parser(modules: Sequence[str] = COMMAND_MODULES) -> argparse.ArgumentParser:
    """The top-level parser with every available subcommand (of `modules`) fully registered."""
    parser, sub = _top()
    for name in modules:
        module = _import_command(name)
        if module is not None:
            module.register(sub)
    return parser


def _top() -> tuple[argparse.ArgumentParser, argparse._SubParsersAction]:
    parser = argparse.ArgumentParser(
        prog="mlaqc",
        description="Microlens-array QC: simulate, capture, calibrate and inspect plenoptic raw images.",
    )
    parser.add_argument("--version", action="version", version=f"mlaqc {__version__}")
    return parser, parser.add_subparsers(dest="command", metavar="COMMAND")


def _import_command(name: str):
    """The command module, or None when that part of the product is not installed."""
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as exc:
        if exc.name and name.startswith(exc.name):
            return None
        raise


def _installed(module: str) -> bool:
    """Whether a command's module can be imported (found, not imported)."""
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


def _parser_for(argv: Sequence[str]) -> argparse.ArgumentParser:
    """The parser for this command line: the named subcommand's module alone, registered in full; for
    top-level options, help, or an unknown or uninstalled command, every command by name and help line."""
    entry = COMMANDS.get(argv[0]) if argv else None
    if entry is not None:
        parser, sub = _top()
        module = _import_command(entry[0])
        if module is not None:
            module.register(sub)
            if argv[0] in sub.choices:
                return parser
    parser, sub = _top()
    for name, (module, line) in COMMANDS.items():
        if _installed(module):
            sub.add_parser(name, help=line)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one subcommand; map errors to one sentence on stderr and an exit status."""
    process = argv is None  # the process' own command line (the console script, python -m mlaqc)
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _parser_for(argv)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    if process:
        gc.freeze()  # what the imports made lives to the end: collections during the work need not scan it
    try:
        return int(args.func(args) or 0)
    except MlaqcError as exc:
        print(f"mlaqc {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_status
    except KeyboardInterrupt:
        print(f"mlaqc {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:
        if process:
            # The process ends now: the interpreter's teardown then need not search the ~10^5 objects the
            # numerical libraries left for reference cycles (0.15-0.3 s); they are freed all the same.
            gc.freeze()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
