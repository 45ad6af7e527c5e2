"""`mlaqc inspect`: find, classify and size defective microlenses in raw images; write the report sets.

One raw writes its report set into --out. Several raws (a production batch) share one calibration —
from --white, from a saved --grid, or else each frame calibrates itself — and each writes its report set
into --out/<raw name>/, plus --out/batch.csv with one line per frame. A bad frame in a batch is reported
and skipped; the others are still inspected. A scan folder (one with manifest.jsonl, from `mlaqc scan`)
given as RAW stands for its raw files in manifest order.

With --scheduler ADDRESS (or $MLAQC_SCHEDULER; see mlaqc.cluster) the frames are inspected on a Dask
cluster: the config, levels and shared grid travel once (`BatchSpec`, `cluster.share`), each worker
reads its raw by path — the workers must see the same files at the same absolute paths, as on a shared
filesystem; a worker that cannot is one sentence, exit status 3 — inspects it (the reference model and
signature table stay cached in the worker process, `pipeline._models`) and renders its report set in
memory (`inspect_remote`). Only this process writes: each report set atomically as its frame completes,
exactly once even when a worker died and its frame ran again, then batch.csv — the same rows, verdicts
and exit status as on this machine.

--through-focus adds the second measurement (mlaqc.inspection.throughfocus): pinhole frames of the same
array, read on the inspected frame's grid and combined into its report (mlaqc.inspection.combine). A scan
folder whose plan had a [through_focus] step pairs each white frame with the pinhole frames of its position.

--dark FRAME ... (or a scan folder's own dark frames, found from their sidecars) makes one master dark per
batch (mlaqc.inspection.darks), checked against every raw's sidecar before anything is inspected or
written, subtracted from every frame and from --white; --stack N averages every N consecutive raws into
one frame (named by the first), and several --white frames are averaged likewise.

--sensor-dust (a batch, on this machine) inspects every frame before writing any report: a shadow at the
same pixels in frames that show the array at different positions is the sensor's
(mlaqc.inspection.sensor_dust), written once to --out/sensor_dust.json and taken off each frame's lenses.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import os
import socket
import sys
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mlaqc import cluster
from mlaqc.atomic import write_bytes_atomic
from mlaqc.commands.levels import add_level_options, stated_levels
from mlaqc.commands.recording import Recorder, add_db_options, render_with_record
from mlaqc.errors import InputError
from mlaqc.inspection.raw_levels import Levels
from mlaqc.inspection.results import detection_limit_text
from mlaqc.optics.config import CameraConfig, load_config

BATCH_COLUMNS = ("raw", "verdict", "flagged", "out_of_tolerance", "missing", "seconds", "report", "error")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `inspect` subcommand."""
    p = sub.add_parser("inspect", help="inspect raw images: defective lenses, type, size, PASS/FAIL",
                       description="Calibrate the microlens grid, compute every lens' indexes, flag and classify "
                                   "defective lenses, and write report.json, lenses.csv, defect_map.png and "
                                   "report.html. Several raws share one calibration (--white or --grid) and get "
                                   "one report folder each under --out, plus batch.csv. Exit status 0 = every "
                                   "frame PASS, 1 = some frame FAIL, 2 = input error (in a batch: some frame "
                                   "could not be inspected; the others still are), 3 = the Dask cluster failed, 4 = the "
                                   "reports are written but the results database could not record them.")
    p.add_argument("raw", nargs="+", help="raw image(s) (DNG, vendor raw, TIFF, PNG, NPY), or a scan folder")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--white", "-w", nargs="+", metavar="W",
                     help="white image to calibrate the grid on (default: each raw itself); several frames of one "
                          "state are averaged into one")
    src.add_argument("--grid", "-g", help="grid.json from `mlaqc calibrate`, reused without recalibrating")
    p.add_argument("--through-focus", "-t", nargs="+", metavar="FRAME", default=[],
                   help="through-focus pinhole frames of the same array (+u and -u pairs, each with its "
                        ".sim.json or .meta.json record): every covered lens' focal error with its sign, "
                        "combined into the report (one raw only; a scan folder pairs its own)")
    p.add_argument("--dark", "-d", nargs="+", metavar="FRAME",
                   help="dark frames (lens covered, the raws' exposure and gain): their master dark is subtracted "
                        "from every frame first and its hot and dead pixels replaced (default: a scan folder's own "
                        "dark frames, found from their .meta.json sidecars)")
    p.add_argument("--dark-method", choices=("median", "mean"), default="median",
                   help="master dark: per-pixel median of the dark frames, or their sigma-clipped mean (default median)")
    p.add_argument("--stack", type=int, default=1, metavar="N",
                   help="average every N consecutive raws (frames of one state) into one before inspecting: the "
                        "noise drops by √N (default 1)")
    p.add_argument("--sensor-dust", action="store_true",
                   help="batch: a dark spot or line that stays at the same pixels while the array moves (stage "
                        "positions in the frames' sidecars, or a different lens under it) is the sensor's: "
                        "reported once in sensor_dust.json and taken off the lenses' flags (holds every frame's "
                        "result until the batch ends)")
    p.add_argument("--config", "-c", help="camera config TOML (default: the paper's Table 1 camera)")
    p.add_argument("--out", "-o", required=True, help="output folder for the report set(s)")
    p.add_argument("--quiet", "-q", action="store_true", help="no summary on stderr")
    add_level_options(p)
    cluster.add_scheduler_option(p)
    add_db_options(p)
    p.set_defaults(func=run)


def check_out_dir(out: str) -> Path:
    """The report folder: created if its parent exists; refused if it is a file."""
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise InputError(f"output {out!r} exists and is not a folder")
    if not path.parent.is_dir():
        raise InputError(f"the folder containing {out!r} does not exist")
    return path


def summary(result) -> str:
    """A few lines an operator reads at the bench."""
    g = result.grid
    kinds: dict[str, int] = {}
    for d in result.defects:
        kinds[d.error_type] = kinds.get(d.error_type, 0) + 1
    out_tol = sum(1 for d in result.defects if not d.within_tolerance)
    lines = [f"{result.verdict}: {len(result.defects)} flagged lenses ({out_tol} out of tolerance) of {g.rows}x{g.cols}",
             f"  grid: pitch {g.pitch_px[0]:.3f} x {g.pitch_px[1]:.3f} px, rotation {g.rotation_deg:+.3f} deg, "
             f"RMS residual {g.rms_residual_px:.3f} px",
             "  by type: " + (", ".join(f"{k} {v}" for k, v in sorted(kinds.items())) or "none"),
             f"  this frame {detection_limit_text(result.detection_limit)}",
             *([through_focus_text(result.through_focus)] if getattr(result, "through_focus", None) is not None else []),
             *_assembly_lines(getattr(result, "assembly", None)),
             "  time: " + ", ".join(f"{k} {v:.2f} s" for k, v in result.timings_s.items()),
             *(f"  {note}" for note in result.notes if note.startswith("WARNING"))]
    return "\n".join(lines)


def _assembly_lines(assembly) -> list[str]:
    """The array's placement readings, and one FAIL line per `[qc]` bound they exceed."""
    if assembly is None:
        return []
    return [assembly.summary_line(), *(f"  FAIL: {line}" for line in assembly.exceeded)]


def through_focus_text(tf) -> str:
    """One line on the through-focus pairs: how many lenses they read, and how well."""
    sm = tf.summary()
    sig = sm["focal_sigma_rel_median"]
    return (f"  through-focus: {sm['lenses_covered']} lenses read ({100 * sm['coverage']:.1f} %) in {len(sm['pairs'])} "
            f"pairs, focal error 1σ {'–' if sig is None else f'{100 * sig:.2f} %'} (median)")


def shared_grid(args: argparse.Namespace, cfg: CameraConfig, dark=None):
    """The calibration every raw reuses: loaded from --grid, fitted on --white (its frames averaged, the
    master dark `dark` subtracted), or None (self-calibrate)."""
    from mlaqc.inspection.array_extent import calibrate_whole
    from mlaqc.inspection.calibrate import load_grid
    from mlaqc.inspection.pipeline import load_frame

    if args.grid:
        grid = load_grid(args.grid)
        want = (cfg.sensor.height_px, cfg.sensor.width_px)
        counted = cfg.mla.counts_auto and grid.rows <= cfg.mla.count_h and grid.cols <= cfg.mla.count_w  # whole array
        if ((grid.rows, grid.cols) != (cfg.mla.count_h, cfg.mla.count_w) and not counted) or tuple(grid.image_shape) != want:
            raise InputError(f"grid file {args.grid!r} is for {grid.cols}x{grid.rows} lenses on a "
                             f"{grid.image_shape[1]}x{grid.image_shape[0]} px frame, but the camera has "
                             f"{cfg.mla.count_w}x{cfg.mla.count_h} lenses on {want[1]}x{want[0]} px")
        if grid.packing != cfg.mla.packing:  # said here, before any frame is read, naming the file
            raise InputError(f"grid file {args.grid!r} is for a {grid.packing} lattice but the camera's MLA is "
                             f"{cfg.mla.packing} (mla.packing)")
        return grid
    if args.white:
        white = [args.white] if isinstance(args.white, str) else list(args.white)
        img = load_frame(white[0] if len(white) == 1 else white, cfg, stated_levels(args), dark=dark)
        return calibrate_whole(img, cfg)
    return None


def report_folders(out: Path, raws: list[str]) -> list[Path]:
    """--out itself for one raw; --out/<name> for several, names made unique where stems collide."""
    if len(raws) == 1:
        return [out]
    seen: dict[str, int] = {}
    folders = []
    for raw in raws:
        stem = Path(raw).stem or "raw"
        seen[stem] = seen.get(stem, 0) + 1
        folders.append(out / (stem if seen[stem] == 1 else f"{stem}-{seen[stem]}"))
    return folders


def scan_raws(folder: Path) -> list[tuple[str, tuple[str, ...]]]:
    """The white raw files of a scan folder, in manifest order, each with the through-focus frames taken
    at its position (a torn last line, from a kill mid-append, skipped)."""
    manifest = folder / "manifest.jsonl"
    if not manifest.is_file():
        raise InputError(f"{str(folder)!r} is a folder but not a scan folder (it has no manifest.jsonl)")
    try:
        lines = manifest.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"scan manifest {str(manifest)!r} cannot be read ({exc})") from None
    raws = []
    for k, line in enumerate(lines):
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            if k == len(lines) - 1:
                break
            raise InputError(f"scan manifest {str(manifest)!r} is damaged at line {k + 1}") from None
        if isinstance(record, dict) and record.get("type") == "position":
            files = [f for f in record.get("files", []) if isinstance(f, dict) and "file" in f]
            tf = tuple(str(folder / f["file"]) for f in files if f.get("through_focus"))
            raws += [(str(folder / f["file"]), tf) for f in files if not f.get("through_focus")]
    if raws:  # dark frames (their sidecars say so) are the folder's darks, not frames to inspect
        from mlaqc.inspection.darks import scan_dark_frames

        dark = set(scan_dark_frames(folder))
        raws = [(r, tf) for r, tf in raws if r not in dark]
    if not raws:
        raise InputError(f"scan folder {str(folder)!r} records no frames yet")
    return raws


def batch_raws(args_raw: list[str], through_focus: list[str] = (), stack: int = 1,
               stacks: dict[str, tuple[str, ...]] | None = None) -> tuple[list[str], dict[str, tuple[str, ...]], bool]:
    """The raws to inspect (each scan folder replaced by its white frames), the through-focus frames of
    each (from --through-focus for one raw, from the manifest for a scan folder's), and whether they are
    a batch (several raws, or any scan folder: one report folder each plus batch.csv). With `stack` N
    every N consecutive raws are one frame (named by the first; `stacks` gets its N paths)."""
    jobs: list[tuple[str, tuple[str, ...]]] = []
    for raw in args_raw:
        jobs += scan_raws(Path(raw)) if Path(raw).is_dir() else [(raw, ())]
    if stack != 1:
        if stack < 1 or len(jobs) % stack:
            raise InputError(f"--stack {stack} averages every {stack} raws into one, but {len(jobs)} raws were given"
                             if stack >= 1 else f"--stack must be at least 1, not {stack}")
        groups = [jobs[i:i + stack] for i in range(0, len(jobs), stack)]
        if stacks is not None:
            stacks.update({g[0][0]: tuple(r for r, _ in g) for g in groups})
        jobs = [(g[0][0], tuple(f for _, tf in g for f in tf)) for g in groups]
    batch = len(jobs) > 1 or any(Path(r).is_dir() for r in args_raw)
    if through_focus:
        if batch:
            raise InputError("--through-focus goes with one raw: a batch has no single array to pair them with "
                             "(a scan folder pairs the frames of each position itself)")
        jobs = [(jobs[0][0], tuple(through_focus))]
    return [r for r, _ in jobs], {r: tf for r, tf in jobs if tf}, batch


def inspect_raw(raw: str, cfg: CameraConfig, grid, levels: Levels | None = None, *, path: str | None = None,
                through_focus: tuple[str, ...] = (), stack: tuple[str, ...] = (), dark=None):
    """Load and inspect one raw (read from `path` if given; the report names `raw`), with its through-focus
    frames if any; `stack`: the frames of one state averaged into it (paths, `raw` among them); `dark`: a
    master dark (mlaqc.inspection.darks) subtracted first. InputError propagates."""
    from mlaqc.inspection.pipeline import inspect_image, load_frame, with_through_focus

    from mlaqc.compiled import compile_seconds, net_clock

    compiled_before = compile_seconds()
    t0 = net_clock()
    notes: list[str] = []
    info = None
    if len(stack) > 1 or dark is not None:
        from mlaqc.inspection.darks import load_frames

        img, info = load_frames(tuple(stack) if len(stack) > 1 else (path or raw,), cfg, levels, notes, dark)
    else:
        img = load_frame(path or raw, cfg, levels, notes)
    load_s = net_clock() - t0
    result = inspect_image(img, cfg, grid=grid, source=str(raw), notes=tuple(notes))
    result.timings_s["load"] = round(max(load_s, 0.0), 4)  # the dict is mutable; the result is frozen
    if info is not None:
        from mlaqc.inspection.darks import with_noise

        with_noise(result, info)
    result = with_through_focus(result, through_focus, cfg, levels) if through_focus else result
    if compile_seconds() > compiled_before:  # first use without the ahead-of-time kernels: said apart
        result.timings_s["kernel_compile"] = round(compile_seconds() - compiled_before, 4)
    return result


def frame_row(result, folder: Path, seconds: float) -> dict:
    """The batch.csv row of an inspected frame (plus its `summary` text)."""
    return {"verdict": result.verdict, "flagged": len(result.defects),
            "out_of_tolerance": sum(1 for d in result.defects if not d.within_tolerance),
            "missing": sum(1 for d in result.defects if d.error_type == "missing"),
            "seconds": round(seconds, 3), "report": str(folder), "error": "", "summary": summary(result)}


def inspect_one(raw: str, cfg: CameraConfig, grid, folder: Path, levels: Levels | None = None,
                through_focus: tuple[str, ...] = (), stack: tuple[str, ...] = (), dark=None) -> dict:
    """Load, inspect and report one raw; a row of batch.csv (InputError propagates)."""
    from mlaqc.report import write_report_files

    t0 = time.perf_counter()
    result = inspect_raw(raw, cfg, grid, levels, through_focus=through_focus, stack=stack, dark=dark)
    contents = render_with_record(result, cfg.to_dict())
    write_report_files(contents, folder)
    return {"result": result, **frame_row(result, folder, time.perf_counter() - t0), "record": contents["record"]}


def write_batch_csv(path: Path, rows: list[dict]) -> None:
    """One line per frame, written atomically."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=BATCH_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    write_bytes_atomic(path, buf.getvalue().encode())


# ------------------------------------------------------------------------------------- on a Dask cluster

@dataclass(frozen=True)
class BatchSpec:
    """What every frame of a batch shares; travels to each Dask worker once."""

    cfg: CameraConfig
    grid: Any  # the shared Grid, or None: each frame calibrates itself
    levels: Levels | None
    config_dict: dict  # for report.json
    darks: dict = field(default_factory=dict)  # raw -> its master dark (mlaqc.inspection.darks), shared objects


def inspect_remote(spec: BatchSpec, raw: str, path: str, client_sees_it: bool, through_focus: tuple[str, ...] = (),
                   stack: tuple[str, ...] = ()) -> dict:
    """Run on a Dask worker: load the raw at `path` (absolute), inspect it and render its report set in
    memory; nothing is written. Returns {"row": batch.csv row, "contents": {file key: bytes}}, or
    {"error": sentence} for a frame that is bad input (a value, not an exception: Dask must not retry
    it), or {"unseen": host} when this worker cannot see a file the client can."""
    if client_sees_it and not os.path.exists(path):
        return {"unseen": socket.gethostname()}
    t0 = time.perf_counter()
    try:
        result = inspect_raw(raw, spec.cfg, spec.grid, spec.levels, path=path, through_focus=through_focus,
                             stack=stack, dark=spec.darks.get(raw))
        contents = render_with_record(result, spec.config_dict)
    except InputError as exc:
        return {"error": str(exc)}
    return {"row": frame_row(result, Path(), time.perf_counter() - t0), "contents": contents}


def rows_on_cluster(client: Any, raws: list[str], folders: list[Path], spec: BatchSpec,
                    quiet: bool, pinholes: dict[str, tuple[str, ...]] | None = None,
                    stacks: dict[str, tuple[str, ...]] | None = None) -> Iterator[tuple[int, dict]]:
    """(index, row) of every frame inspected on the cluster of `client`, in the order they complete;
    each frame's report set is written here, once, before its row is yielded."""
    from mlaqc.inspection.pipeline import _models
    from mlaqc.report import write_report_files

    _models(spec.cfg)  # build the on-disk model cache once here, not in every worker at the same time
    shared = cluster.share(client, spec, "inspect-spec")
    run_id = uuid.uuid4().hex[:8]
    futures = {}
    for i, raw in enumerate(raws):
        path = os.path.abspath(raw)  # workers have another working directory
        tf = tuple(os.path.abspath(f) for f in (pinholes or {}).get(raw, ()))
        stk = tuple(os.path.abspath(f) for f in (stacks or {}).get(raw, ()))
        fut = client.submit(inspect_remote, shared, raw, path, os.path.exists(path), tf, stk, pure=False,
                            retries=cluster.TASK_RETRIES, key=f"inspect-{i + 1:05d}-{Path(raw).name}-{run_id}")
        futures[fut] = i
    label = f"inspecting {len(raws)} frames on Dask"
    for i, value in cluster.follow(futures, label, progress=False if quiet else None):
        if "unseen" in value:
            raise cluster.unseen(value["unseen"], os.path.abspath(raws[i]))
        if "error" in value:
            # the worker read the absolute path; name the raw as the user gave it, as on this machine
            yield i, error_row(raws[i], value["error"].replace(os.path.abspath(raws[i]), raws[i]))
            continue
        t0 = time.perf_counter()
        try:
            write_report_files(value["contents"], folders[i])
        except InputError as exc:
            yield i, error_row(raws[i], str(exc))
            continue
        row = value["row"]
        yield i, {**row, "report": str(folders[i]), "seconds": round(row["seconds"] + time.perf_counter() - t0, 3),
                  "record": value["contents"].get("record")}


def rows_here(raws: list[str], folders: list[Path], cfg: CameraConfig, grid,
              levels: Levels | None, pinholes: dict[str, tuple[str, ...]] | None = None,
              stacks: dict[str, tuple[str, ...]] | None = None, darks: dict | None = None) -> Iterator[tuple[int, dict]]:
    """(index, row) of every frame inspected in this process, in order."""
    for i, (raw, folder) in enumerate(zip(raws, folders)):
        try:
            row = inspect_one(raw, cfg, grid, folder, levels, (pinholes or {}).get(raw, ()),
                              (stacks or {}).get(raw, ()), (darks or {}).get(raw))
        except InputError as exc:
            yield i, error_row(raw, str(exc))
            continue
        del row["result"]  # its frame and sub-images: a batch keeps only the rows
        yield i, row


def rows_with_sensor_dust(raws: list[str], folders: list[Path], cfg: CameraConfig, grid, levels: Levels | None,
                          out: Path, quiet: bool, pinholes: dict | None = None, stacks: dict | None = None,
                          darks: dict | None = None) -> Iterator[tuple[int, dict]]:
    """(index, row) of every frame, inspected first, then cleared of the sensor's shadows
    (mlaqc.inspection.sensor_dust) and reported; sensor_dust.json written once for the batch. A frame with
    no dark spot or line is reported at once (no shadow can change it): only the others are held."""
    from mlaqc.inspection.sensor_dust import SPOT_TYPES, sensor_shadows

    held: list = [None] * len(raws)
    rows: dict[int, dict] = {}
    seconds: list[float] = []
    for i, raw in enumerate(raws):
        t0 = time.perf_counter()
        try:
            result = inspect_raw(raw, cfg, grid, levels, through_focus=(pinholes or {}).get(raw, ()),
                                 stack=(stacks or {}).get(raw, ()), dark=(darks or {}).get(raw))
        except InputError as exc:
            rows[i] = error_row(raw, str(exc))
            result = None
        seconds.append(time.perf_counter() - t0)
        if result is not None and any(d.error_type in SPOT_TYPES for d in result.defects):
            held[i] = result
        elif result is not None:
            rows[i] = _reported(raw, result, folders[i], cfg, seconds[i])
        if not quiet:
            cluster.echo(f"[{i + 1}/{len(raws)}] {raws[i]}: inspected ({seconds[-1]:.2f} s)")
    meta = [_meta_or_empty(r) for r in raws]
    shadows, held, notes = sensor_shadows(held, meta, cfg)
    doc = {"shadows": [s.to_json_dict() for s in shadows], "notes": list(notes), "frames": len(raws)}
    write_bytes_atomic(out / "sensor_dust.json", (json.dumps(doc, indent=1) + "\n").encode())
    if not quiet:
        for line in [f"{len(shadows)} sensor shadow(s): {out / 'sensor_dust.json'}",
                     *(s.sentence() for s in shadows), *notes]:
            print(line, file=sys.stderr)
    for i, result in enumerate(held):
        if result is not None:
            rows[i] = _reported(raws[i], result, folders[i], cfg, seconds[i])
    for i in range(len(raws)):
        yield i, rows[i]


def _reported(raw: str, result, folder: Path, cfg: CameraConfig, seconds: float) -> dict:
    """Write a frame's report set: its batch row, or an error row when it cannot be written."""
    from mlaqc.report import write_report_files

    try:
        contents = render_with_record(result, cfg.to_dict())
        write_report_files(contents, folder)
    except InputError as exc:
        return error_row(raw, str(exc))
    return {**frame_row(result, folder, seconds), "record": contents["record"]}


def _meta_or_empty(raw: str) -> dict:
    """A raw's sidecar, {} when it has none or it cannot be read (the inspection said so already)."""
    from mlaqc.inspection.darks import read_meta

    try:
        return read_meta(raw)
    except InputError:
        return {}


def error_row(raw: str, sentence: str) -> dict:
    """The batch.csv row of a frame that could not be inspected."""
    return {"raw": raw, "verdict": "ERROR", "error": sentence, "report": ""}


def run(args: argparse.Namespace) -> int:
    """Inspect, report and record; 0 all PASS, 1 some FAIL, 2 some frame was bad input (batch) or bad input,
    3 the Dask cluster failed, 4 the results database did not record every frame (the reports are written)."""
    out = check_out_dir(args.out)
    stacks: dict[str, tuple[str, ...]] = {}
    raws, pinholes, batch = batch_raws(args.raw, args.through_focus, getattr(args, "stack", 1), stacks)
    cfg = load_config(args.config)
    address = cluster.scheduler_address(args.scheduler)
    if address is not None:
        cluster.check_address(address)  # a malformed address is bad input, said before any work
    dust = getattr(args, "sensor_dust", False)
    if dust and (not batch or address is not None):
        raise InputError("--sensor-dust compares the frames of a batch on this machine: give two raws or more "
                         "(or a scan folder), without --scheduler or $MLAQC_SCHEDULER")
    if batch and getattr(args, "array", None):
        raise InputError("--array names one array: give one raw (a batch's frames are named by their scan "
                         "positions' labels, or their raws)")
    levels = stated_levels(args)
    darks, white_dark = master_darks(args, raws, stacks, cfg, levels)
    grid = shared_grid(args, cfg, white_dark)
    folders = report_folders(out, raws) if batch else [out]
    with contextlib.ExitStack() as stack:
        recorder = Recorder(args, "inspect")  # opened before the work: a database that cannot be used is said first
        stack.callback(recorder.close)
        if dust:
            frames = rows_with_sensor_dust(raws, folders, cfg, grid, levels, out, args.quiet, pinholes, stacks, darks)
        elif address is None:
            frames = rows_here(raws, folders, cfg, grid, levels, pinholes, stacks, darks)
        else:  # connected before anything is written: an unreachable cluster leaves no output
            client = stack.enter_context(cluster.connect(address, quiet=args.quiet))
            frames = rows_on_cluster(client, raws, folders, BatchSpec(cfg, grid, levels, cfg.to_dict(), darks),
                                     args.quiet, pinholes, stacks)
        frames = _recorded(frames, recorder, raws)
        if not batch:
            return recorder.status(_single(frames, out, args.quiet))
        out.mkdir(exist_ok=True)
        rows: list[dict] = [{}] * len(raws)
        t0 = time.perf_counter()
        for i, row in frames:
            rows[i] = {**row, "raw": raws[i]}
            if not args.quiet:
                line = (f"ERROR: {row['error']}" if row["verdict"] == "ERROR"
                        else f"{row['verdict']}, {row['flagged']} flagged ({row['seconds']:.2f} s)")
                cluster.echo(f"[{i + 1}/{len(raws)}] {raws[i]}: {line}")
    write_batch_csv(out / "batch.csv", rows)
    verdicts = [r["verdict"] for r in rows]
    if not args.quiet:
        dt = time.perf_counter() - t0
        print(f"{verdicts.count('PASS')} PASS, {verdicts.count('FAIL')} FAIL, {verdicts.count('ERROR')} ERROR "
              f"in {dt:.1f} s ({dt / len(rows):.2f} s/frame); {out / 'batch.csv'}", file=sys.stderr)
    if not args.quiet and recorder.recorded:
        print(f"{recorder.recorded} inspection(s) recorded in {recorder.where}", file=sys.stderr)
    return recorder.status(2 if "ERROR" in verdicts else (1 if "FAIL" in verdicts else 0))


def _recorded(frames: Iterator[tuple[int, dict]], recorder: Recorder, raws: list[str]) -> Iterator[tuple[int, dict]]:
    """The frames' rows, each frame recorded in the results database as its report folder is written (a
    scan frame with its position's label)."""
    for i, row in frames:
        record = row.pop("record", None)
        if record is not None:
            scan = _meta_or_empty(raws[i]).get("scan")
            recorder.record(record, row.get("report"), scan.get("label") if isinstance(scan, dict) else None)
        yield i, row


def master_darks(args: argparse.Namespace, raws: list[str], stacks: dict[str, tuple[str, ...]], cfg: CameraConfig,
                 levels: Levels | None) -> tuple[dict, Any]:
    """({raw: its master dark}, the master dark of --white): from --dark for every raw, else each scan
    folder's own dark frames for its raws; each master built once, and every raw's .meta.json sidecar
    checked against it before anything is inspected or written (InputError: exit 2)."""
    sets: dict[str, tuple[str, ...]] = {}
    if getattr(args, "dark", None):
        sets = {raw: tuple(args.dark) for raw in raws}
    elif any(Path(r).is_dir() for r in args.raw):
        from mlaqc.inspection.darks import scan_dark_frames

        for folder in (Path(r) for r in args.raw if Path(r).is_dir()):
            found = tuple(scan_dark_frames(folder))
            if found:
                sets.update({raw: found for raw in raws if Path(raw).parent == folder})
                if not args.quiet:
                    print(f"{folder}: {len(found)} dark frames found (their sidecars say dark)", file=sys.stderr)
    if not sets:
        return {}, None
    from mlaqc.inspection.darks import build_master_dark, prepare_check
    from mlaqc.inspection.raw_levels import Levels as SensorLevels

    s = cfg.sensor
    masters: dict[tuple[str, ...], Any] = {}
    darks = {}
    for raw, paths in sets.items():
        if paths not in masters:
            masters[paths] = build_master_dark(paths, levels=levels, sensor=SensorLevels(s.bit_depth, s.black_level_dn),
                                               method=getattr(args, "dark_method", "median"),
                                               pitch_px=cfg.layout.subimage_pitch_px,
                                               expected_shape=(s.height_px, s.width_px))
        darks[raw] = masters[paths]
        prepare_check(stacks.get(raw, (raw,)), darks[raw])
    white_dark = next(iter(masters.values())) if len(masters) == 1 else None
    if white_dark is not None and args.white:
        prepare_check([args.white] if isinstance(args.white, str) else args.white, white_dark)
    return darks, white_dark


def _single(frames: Iterator[tuple[int, dict]], out: Path, quiet: bool) -> int:
    """One raw: its report set in --out, the summary on stderr; a bad frame is an InputError (exit 2)."""
    (_, row), = frames
    if row["verdict"] == "ERROR":
        raise InputError(row["error"])
    if not quiet:
        print(row["summary"], file=sys.stderr)
        print(f"  report: {out / 'report.html'}", file=sys.stderr)
    return 1 if row["verdict"] == "FAIL" else 0
