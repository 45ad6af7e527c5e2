"""The `mlaqc` command line: one console script, one subcommand per job.

Each subcommand lives in a module with `register(subparsers)` that adds its parser and sets `func`.
Hardware (`drivers`) and GUI commands are reached only from here, lazily, as DESIGN.md asks.
Exit status: 0 success (or PASS), 1 FAIL, 2 bad input, 3 device error, 130 interrupted.
"""

from __future__ import annotations

import argparse
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


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every available subcommand."""
    parser = argparse.ArgumentParser(
        prog="mlaqc",
        description="Microlens-array QC: simulate, capture, calibrate and inspect plenoptic raw images.",
    )
    parser.add_argument("--version", action="version", version=f"mlaqc {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name and name.startswith(exc.name):
                continue  # that part of the product is not installed or not written yet
            raise
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one subcommand; map errors to one sentence on stderr and an exit status."""
    parser = build_parser()
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


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
