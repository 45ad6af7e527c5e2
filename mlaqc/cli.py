"""The `mlaqc` command line: one console script, one subcommand per job.

Each subcommand lives in a module with `register(subparsers)` that adds its parser and sets `func`.
Hardware (`drivers`) and GUI commands are reached only from here, lazily, as DESIGN.md asks.
Exit status: 0 success (or PASS), 1 FAIL, 2 bad input, 3 device error, 130 interrupted.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import sys
from collections.abc import Sequence

from mlaqc import __version__
from mlaqc.errors import MlaqcError

# Modules that contribute subcommands, in --help order. Missing optional ones are skipped.
COMMAND_MODULES = (
    "mlaqc.commands.simulate",
    "mlaqc.commands.errormap",
    "mlaqc.commands.calibrate",
    "mlaqc.commands.inspect",
    "mlaqc.commands.models",
    "mlaqc.commands.demo",
    "drivers.commands",
    "gui.commands",
)


# The module that registers each subcommand: `mlaqc COMMAND ...` imports that module alone (importing
# them all, with their numerical and hardware dependencies, cost a few tenths of a second per run).
COMMAND_OWNERS = {
    "simulate": "mlaqc.commands.simulate", "errormap": "mlaqc.commands.errormap",
    "calibrate": "mlaqc.commands.calibrate", "inspect": "mlaqc.commands.inspect",
    "models": "mlaqc.commands.models", "demo": "mlaqc.commands.demo",
    "capture": "drivers.commands", "scan": "drivers.commands", "gui": "gui.commands",
}


def build_parser(modules: Sequence[str] = COMMAND_MODULES) -> argparse.ArgumentParser:
    """The top-level parser with every available subcommand (of `modules`: all of them by default)."""
    return _build(modules)[0]


def _build(modules: Sequence[str]) -> tuple[argparse.ArgumentParser, argparse._SubParsersAction]:
    parser = argparse.ArgumentParser(
        prog="mlaqc",
        description="Microlens-array QC: simulate, capture, calibrate and inspect plenoptic raw images.",
    )
    parser.add_argument("--version", action="version", version=f"mlaqc {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in modules:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name and name.startswith(exc.name):
                continue  # that part of the product is not installed or not written yet
            raise
        module.register(sub)
    return parser, sub


def _parser_for(argv: Sequence[str]) -> argparse.ArgumentParser:
    """The parser for this command line: the named subcommand's module alone when that registers it,
    else every module (top-level options, help, an unknown or uninstalled command)."""
    owner = COMMAND_OWNERS.get(argv[0]) if argv else None
    if owner is not None:
        parser, sub = _build((owner,))
        if argv[0] in sub.choices:
            return parser
    return build_parser()


def main(argv: Sequence[str] | None = None) -> int:
    """Run one subcommand; map errors to one sentence on stderr and an exit status."""
    process = argv is None  # the process' own command line (the console script, python -m mlaqc)
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _parser_for(argv)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
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
