"""`mlaqc capture` and `mlaqc scan`: headless acquisition from the command line.

Errors end in one sentence and an exit status: 2 for bad input (URL, options, plan, output folder),
3 for a device that failed, 130 for Ctrl-C. Nothing is written before the inputs have been checked.
A scan that ran to its end exits 0 when every position was recorded inspectable and (with --inspect)
passed, else 1: the summary names the positions that failed.
"""

from __future__ import annotations

import argparse
import math
import sys

from mlaqc.commands.recording import Recorder, add_db_options
from mlaqc.errors import InputError
from mlaqc.progress import ProgressBar


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `capture` and `scan` subcommands."""
    c = sub.add_parser(
        "capture", help="capture raw frames (or averages) from a camera with provenance sidecars",
        description="Capture raw frames from a camera into a folder: each frame (or the average of K frames) is "
                    "written atomically as <prefix>_NNNNNN.tiff|dng with a <file>.meta.json sidecar holding the "
                    "sequence number, timestamps, exposure and gain read back, format, bit depth, versions and "
                    "the file's sha256.")
    c.add_argument("--camera", required=True, metavar="URL",
                   help="camera URL, e.g. 'v4l2:///dev/video0?format=Y16' or 'mock://?wafer=3x3'")
    c.add_argument("--out", "-o", required=True, metavar="DIR", help="output folder (created if its parent exists)")
    c.add_argument("--frames", type=int, default=1, metavar="N", help="number of files to write (default 1)")
    c.add_argument("--average", type=int, default=1, metavar="K", help="frames averaged into each file (default 1)")
    c.add_argument("--dark", action="store_true",
                   help="these are dark frames (lens covered / light off): a black frame is expected, a lit one warned about")
    c.add_argument("--exposure-us", type=float, metavar="E", help="set the exposure time in µs (read back into the sidecar)")
    c.add_argument("--gain", type=float, metavar="G", help="set the gain in device units (read back into the sidecar)")
    c.add_argument("--format", dest="file_format", choices=("tiff", "dng"), default="tiff", help="raw file format (default tiff)")
    c.add_argument("--prefix", help="file name prefix (default 'frame', or 'dark' with --dark)")
    c.add_argument("--timeout-s", type=float, default=5.0, metavar="T", help="deadline per frame in seconds (default 5)")
    c.add_argument("--quiet", "-q", action="store_true", help="no progress bar or summary")
    c.set_defaults(func=run_capture)

    s = sub.add_parser(
        "scan", help="XY scan: move, settle, capture at each plan position; resumable",
        description="Run a scan plan (TOML: a raster or a list of positions): at each position move the stage, "
                    "settle, capture and write the frame and its sidecar atomically, then append the position to "
                    "DIR/manifest.jsonl (fsync'd). --resume continues an interrupted scan from its manifest, "
                    "re-checking every recorded frame's checksum. A [through_focus] table adds the through-focus "
                    "pinhole frames at every position (see fixtures/scan_plan_throughfocus.toml): the stage must "
                    "also drive the pinhole mask's Z, A and B axes (stage URL aux=z,a,b).")
    s.add_argument("--camera", required=True, metavar="URL", help="camera URL, e.g. 'mock://?wafer=3x3'")
    s.add_argument("--stage", required=True, metavar="URL",
                   help="stage URL, e.g. 'serial:///dev/ttyUSB0?protocol=grbl' or 'mock://'")
    s.add_argument("--plan", required=True, metavar="PLAN.toml", help="scan plan (see fixtures/scan_plan_raster.toml)")
    s.add_argument("--out", "-o", required=True, metavar="DIR", help="output folder (new or empty, or an earlier scan with --resume)")
    s.add_argument("--resume", action="store_true", help="continue the scan recorded in DIR/manifest.jsonl")
    s.add_argument("--inspect", action="store_true",
                   help="inspect each white frame once its position is recorded, with that position's through-focus "
                        "pinhole frames if the plan takes them (one combined verdict, as `mlaqc inspect RAW "
                        "--through-focus FRAME ...`), into <frame>.inspect.json; a failed inspection is reported and "
                        "the scan goes on (--resume tries it again)")
    s.add_argument("--quiet", "-q", action="store_true", help="no progress bar or summary")
    add_db_options(s, array=False)  # with --inspect: each frame recorded, its position's label the array's
    s.set_defaults(func=run_scan_command)


def _positive(name: str, value: float | None) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a positive number, got {value!r}")


def run_capture(args: argparse.Namespace) -> int:
    """Check everything, open the camera, capture, write; 0 on success."""
    from drivers.camera import camera_from_url
    from drivers.capture import (MAX_AVERAGE, MAX_FRAMES, capture, check_count, check_out_dir, file_suffix,
                                 frame_names, print_warning)

    check_count("--frames", args.frames, MAX_FRAMES)
    check_count("--average", args.average, MAX_AVERAGE)
    _positive("--exposure-us", args.exposure_us)
    _positive("--gain", args.gain)
    _positive("--timeout-s", args.timeout_s)
    camera = camera_from_url(args.camera)
    out = check_out_dir(args.out)
    frame_names(out, args.prefix or ("dark" if args.dark else "frame"), args.frames, file_suffix(args.file_format))
    bar = ProgressBar("capturing", enabled=False if args.quiet else None)
    with camera:
        try:
            saved = capture(camera, out, frames=args.frames, average=args.average, dark=args.dark,
                            exposure_us=args.exposure_us, gain=args.gain, file_format=args.file_format,
                            prefix=args.prefix, timeout_s=args.timeout_s, progress=bar, on_warning=print_warning)
        finally:
            bar.close()
    if not args.quiet:
        first, last = saved[0], saved[-1]
        what = "dark frame" if args.dark else "frame"
        avg = f" (each the average of {args.average})" if args.average > 1 else ""
        names = first.path.name if len(saved) == 1 else f"{first.path.name} .. {last.path.name}"
        print(f"wrote {len(saved)} {what}{'s' if len(saved) != 1 else ''}{avg} to {out}: {names}, "
              f"sidecars *.meta.json; exposure {first.record['exposure_us']:g} µs, gain {first.record['gain']:g}, "
              f"{first.record['bits']}-bit {first.record['pixel_format']}", file=sys.stderr)
    return 0


def run_scan_command(args: argparse.Namespace) -> int:
    """Run or resume a scan; 0 when every position is recorded (and passed, with --inspect), else 1."""
    from drivers.scan import ScanRunner, default_inspect_hook
    from drivers.scan_plan import load_plan

    plan = load_plan(args.plan)
    inspect = None
    recorder = None
    if args.inspect:
        inspect = default_inspect_hook()
        if inspect is None:
            print("note: --inspect: the inspection pipeline (mlaqc.inspection.pipeline.scan_frame_hook) is not available yet, "
                  "so frames are captured and recorded without inspection.", file=sys.stderr)
        else:
            recorder = Recorder(args, "scan")
            inspect = _recording(inspect, recorder)
    bar = ProgressBar("scan", enabled=False if args.quiet else None)

    base: list[int] = []  # positions already done when this run started (a resume): not in the ETA

    def progress(done: int, total: int) -> None:
        if not base:
            base.append(done)
        bar.label = f"scan {done}/{total}"
        bar(done - base[0], total - base[0])

    def on_event(event: dict) -> None:
        if args.quiet:
            return
        kind = event["event"]
        if kind == "device_error":
            _note(bar, f"position {event['index'] + 1} ({event['label']}), attempt {event['attempt']}: "
                       f"{event['device']} error: {event['error']}")
        elif kind == "frame_warning":
            _note(bar, f"{event['file']}: {event['warning']}")
        elif kind == "frame_rejected":
            _note(bar, f"{event['file']} cannot be inspected ({event['reason'].rstrip('.')}); kept, capturing again")
        elif kind == "position_failed":
            _note(bar, f"position {event['index'] + 1} ({event['label']}) FAILED: {event['reason']}")
        elif kind == "invalid_record":
            _note(bar, f"position {event['index'] + 1} will be captured again: {event['reason']}")
        elif kind == "inspect_failed":
            _note(bar, f"{event['file']} was recorded but not inspected: {event['error']}")

    runner = ScanRunner(plan, args.out, camera=args.camera, stage=args.stage, resume=args.resume, inspect=inspect,
                        progress=progress, on_event=on_event)
    try:
        result = runner.run()
    finally:
        bar.close()
        if recorder is not None:
            recorder.close()
    if not args.quiet:
        print(result.summary(), file=sys.stderr)
    status = 0 if result.all_passed else 1
    return recorder.status(status) if recorder is not None else status


def _recording(hook, recorder):
    """The inspection hook, each frame's result recorded in the results database as the scan writes its
    .inspect.json (the position's label names the array)."""
    from mlaqc.commands.recording import record_from_scan_summary

    def inspect(frame):
        summary = hook(frame)
        if isinstance(summary, dict):
            label = (frame.record or {}).get("label")
            recorder.record(record_from_scan_summary(summary), str(frame.out_dir), label)
        return summary

    return inspect


def _note(bar: ProgressBar, text: str) -> None:
    """A warning line that does not collide with the progress bar."""
    if bar._drawn:  # noqa: SLF001 - finish the bar's line first
        bar.close()
    print(f"warning: {text}", file=sys.stderr)
