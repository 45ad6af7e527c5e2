"""`mlaqc calibrate`: find every microlens in a white image and write the grid (grid.json)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from mlaqc.commands.levels import add_level_options, stated_levels
from mlaqc.errors import InputError
from mlaqc.inspection.array_extent import calibrate_whole
from mlaqc.inspection.flatfield import check_flat_field
from mlaqc.inspection.optics_check import pitch_notes
from mlaqc.inspection.raw_levels import Levels, check_exposure, normalized, resolve_levels, suppress_hot_pixels
from mlaqc.inspection.rawio import load_raw
from mlaqc.optics.config import load_config


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `calibrate` subcommand."""
    p = sub.add_parser("calibrate", help="find every microlens in a white image and write grid.json",
                       description="Calibrate the microlens grid from a white (uniformly lit) raw image: pitch, "
                                   "rotation and every lens' measured centre, residual, flux and size, indexed "
                                   "U(m,n) for the config's MLA shape. Writes grid.json atomically.")
    p.add_argument("white", nargs="+", help="white raw image (DNG or camera raw, TIFF, PNG, NPY); several frames of "
                                             "one state are averaged into one")
    p.add_argument("--dark", "-d", nargs="+", metavar="FRAME",
                   help="dark frames (lens covered, the white's exposure and gain): their master dark is subtracted "
                        "first and its hot and dead pixels replaced")
    p.add_argument("--dark-method", choices=("median", "mean"), default="median",
                   help="master dark: per-pixel median of the dark frames, or their sigma-clipped mean (default median)")
    p.add_argument("--out", "-o", required=True, help="output grid file (.json)")
    p.add_argument("--config", "-c", help="camera config TOML (default: the paper's Table 1 camera)")
    p.add_argument("--quiet", "-q", action="store_true", help="no summary")
    add_level_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Calibrate and write; 0 on success (InputError -> exit 2, no output file)."""
    out = Path(args.out)
    if out.suffix.lower() != ".json":
        raise InputError(f"output {str(out)!r} must end in .json")
    if not out.parent.is_dir():
        raise InputError(f"output folder {str(out.parent)!r} does not exist")
    cfg = load_config(args.config)
    start = time.perf_counter()
    s = cfg.sensor
    whites = [args.white] if isinstance(args.white, str) else list(args.white)
    if len(whites) > 1 or getattr(args, "dark", None):
        from mlaqc.inspection.darks import build_master_dark, load_frames

        dark = None
        if args.dark:
            dark = build_master_dark(args.dark, levels=stated_levels(args), sensor=Levels(s.bit_depth, s.black_level_dn),
                                     method=args.dark_method, pitch_px=cfg.layout.subimage_pitch_px,
                                     expected_shape=(s.height_px, s.width_px))
        img, _ = load_frames(whites, cfg, stated_levels(args), None, dark)
    else:
        frame = resolve_levels(load_raw(whites[0]), stated_levels(args), Levels(s.bit_depth, s.black_level_dn))
        check_exposure(frame)
        img, _ = suppress_hot_pixels(normalized(frame), frame.cfa)
    grid = calibrate_whole(img, cfg)
    check_flat_field(np.where(grid.missing | grid.clipped, np.nan, grid.flux), "the white frame")
    grid.save(out)
    if not args.quiet:
        print(f"wrote {out}: {grid.rows}x{grid.cols} lenses, pitch {grid.pitch_px[0]:.4f} x {grid.pitch_px[1]:.4f} px "
              f"(expected {cfg.layout.subimage_pitch_px:.4f}), rotation {grid.rotation_deg:+.4f} deg, "
              f"{grid.lenses_found} found, {grid.lenses_missing} missing, "
              f"RMS residual {grid.rms_residual_px:.4f} px ({time.perf_counter() - start:.2f} s)")
    for note in pitch_notes(float(np.mean(grid.pitch_px)), cfg):
        print(note, file=sys.stderr)
    return 0
