"""The `--bit-depth` / `--black-level` options every command that reads raws shares."""

from __future__ import annotations

import argparse

from mlaqc.inspection.raw_levels import Levels


def add_level_options(p: argparse.ArgumentParser) -> None:
    """Add the options; without them the levels come from the file, the config's [sensor] or the data."""
    p.add_argument("--bit-depth", type=int, metavar="BITS",
                   help="significant bits of the raw counts (8..16), e.g. 12 for 12-bit data in a 16-bit TIFF "
                        "(default: the file's tags, else the config's [sensor] if the data fit it, else the data)")
    p.add_argument("--black-level", type=int, metavar="DN",
                   help="black level in counts (default: the file's tags, else the config's [sensor] if the data "
                        "fit it, else the darkest pixels)")


def stated_levels(args: argparse.Namespace) -> Levels:
    """The levels the user stated on the command line (InputError if impossible)."""
    return Levels(getattr(args, "bit_depth", None), getattr(args, "black_level", None))
