"""`mlaqc gui`: the desktop QC app. Qt is imported only when the command runs, so `mlaqc --help` stays
fast and works on machines without a display."""

from __future__ import annotations

import argparse

DEFAULT_CAMERA_URL = "mock://?wafer=3x3"
DEFAULT_STAGE_URL = "sim+grbl://"


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `gui` subcommand."""
    p = sub.add_parser("gui", help="the desktop QC app: live view, stage, inspection, scans",
                       description="Open the QC operator's window: camera live view and settings, stage jog/home/"
                                   "go-to/STOP, inspection of raw files or captured frames with the defect map, "
                                   "flagged-lens table and per-lens detail, report export, and scans with a wafer "
                                   "map. Defaults run anywhere: a mock camera over a simulated 3x3 wafer and the "
                                   "GRBL stage simulator.")
    p.add_argument("--camera", default=DEFAULT_CAMERA_URL, metavar="URL",
                   help=f"camera URL (default: {DEFAULT_CAMERA_URL}; e.g. v4l2:///dev/video0?format=Y16)")
    p.add_argument("--stage", default=DEFAULT_STAGE_URL, metavar="URL",
                   help=f"stage URL (default: {DEFAULT_STAGE_URL}; e.g. serial:///dev/ttyUSB0?protocol=grbl)")
    p.add_argument("--config", "-c", metavar="C",
                   help="camera config TOML for inspections (default: the mock camera's own config, else Table 1)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check the config, then start Qt and the main window; returns the app's exit status."""
    from mlaqc.errors import InputError

    if args.config:
        from mlaqc.optics.config import load_config

        load_config(args.config)  # a bad config ends here in one sentence (exit 2), before any window opens
    try:
        from gui.app import run as run_app
    except ImportError as exc:  # pragma: no cover - depends on the machine
        raise InputError(f"the GUI needs PySide6 and pyqtgraph, which could not be imported ({exc})") from None
    return run_app(args.camera, args.stage, args.config)
