"""`mlaqc decode`: the 4D light field of scene frames, each lens sampled where it really sends its light when
an inspection's report of the array is given (mlaqc.decode)."""

from __future__ import annotations

import argparse
import contextlib
import os
import socket
import sys
import time
import uuid
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc import cluster
from mlaqc.commands.levels import add_level_options, stated_levels
from mlaqc.errors import InputError

HELP = "decode the light field of scene frames (views, refocusing), corrected by an inspection's report"


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `decode` subcommand."""
    p = sub.add_parser("decode", help=HELP, description=(
        "Decode the 4D light field L(v, u, t, s) of scene raws: every lens' sub-image sampled at every view "
        "(a pupil point), devignetted by the white frame. With --report (an inspection of this array's white "
        "frame) each flagged lens is sampled at its measured sub-image centre and lenses found missing, "
        "obscured or outside the model's range carry a lower weight. Writes lightfield.npy, weights.npy, "
        "views.tif, mosaic.png, refocus.npy / refocus_<i>.png and decode.json into DIR (DIR/<raw name>/ each "
        "for several raws)."))
    p.add_argument("raw", nargs="+", help="scene raw frames (DNG or camera raw, TIFF, PNG, NPY)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--white", "-w", nargs="+", metavar="W",
                     help="white frame(s) of this array and set-up: calibrated, and divided out (devignetting)")
    src.add_argument("--grid", "-g", help="a saved calibration (mlaqc calibrate); no devignetting without --white")
    p.add_argument("--report", "-r", help="report.json (or its folder) of an inspection of this array: decode "
                                          "each flagged lens where it really sends its light")
    p.add_argument("--lattice", choices=("calibrated", "design"), default="calibrated",
                   help="without --report: the calibrated lattice's centres (default) or the design's "
                        "(the config's pitch, centred; for comparison)")
    p.add_argument("--views", type=int, metavar="N",
                   help="N x N views (odd; default: every whole pixel inside the pupil's image less one)")
    p.add_argument("--refocus", metavar="S[,S...]", default="0",
                   help="refocus slopes, lenses per pixel of view offset (default 0: the plane in focus "
                        "on the MLA); 'none' for no refocusing")
    p.add_argument("--fill", action="store_true",
                   help="refill lenses of weight under 0.5 (missing, obscured, a radius error blurring its views by "
                        "over 2 px) from their neighbours in (s, t), along the scene's parallax where they agree on it")
    p.add_argument("--config", "-c", help="camera config TOML (default: the paper's Table 1 camera)")
    p.add_argument("--out", "-o", required=True, help="output folder")
    p.add_argument("--quiet", "-q", action="store_true", help="no summary")
    cluster.add_scheduler_option(p)
    add_level_options(p)
    p.set_defaults(func=run)


def parse_slopes(text: str) -> list[float]:
    """'0,-0.1,0.2' -> floats; 'none' -> []."""
    if text.strip().lower() == "none":
        return []
    try:
        slopes = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--refocus must be numbers separated by commas (or 'none'), got {text!r}") from None
    if not slopes or not all(np.isfinite(slopes)) or max(abs(s) for s in slopes) > 10:
        raise InputError(f"--refocus slopes must be finite numbers within +-10 lenses per view pixel, got {text!r}")
    return slopes


@dataclass(frozen=True)
class DecodeSpec:
    """What decoding a frame needs besides the frame: sent once to every Dask worker."""

    cfg: Any
    levels: Any
    setup: dict[str, Any]
    slopes: tuple[float, ...]
    fill: bool


def run(args: argparse.Namespace) -> int:
    """Decode every raw; 0 when all were written, 2 on bad input (nothing written for that frame), 3 when
    the Dask cluster failed."""
    from mlaqc.commands.inspect import check_out_dir
    from mlaqc.decode.output import write_lightfield
    from mlaqc.optics.config import load_config

    out = check_out_dir(args.out)
    slopes = parse_slopes(args.refocus)
    cfg = load_config(args.config)
    address = cluster.scheduler_address(args.scheduler)
    if address is not None:
        cluster.check_address(address)  # a malformed address is bad input, said before any work
    levels = stated_levels(args)
    spec = DecodeSpec(cfg, levels, _setup(args, cfg, levels), tuple(slopes), bool(args.fill))
    raws = list(args.raw)
    folders = [out] if len(raws) == 1 else _folders(out, raws)
    failed = 0
    with contextlib.ExitStack() as stack:
        if address is None:
            results = ((i, decoded_here(spec, raw)) for i, raw in enumerate(raws))
        else:  # connected before anything is written: an unreachable cluster leaves no output
            client = stack.enter_context(cluster.connect(address, quiet=args.quiet))
            results = decoded_on_cluster(client, spec, raws, args.quiet)
        for i, value in results:
            if "error" in value:
                if len(raws) == 1:
                    raise InputError(value["error"])
                failed += 1
                print(f"mlaqc decode: {raws[i]}: {value['error']}", file=sys.stderr)
                continue
            write_lightfield(folders[i], value["lf"], value["refocused"], value["facts"])
            if not args.quiet:
                print(_summary(folders[i], value["lf"], value["facts"]))
    return 2 if failed else 0


def decoded_here(spec: DecodeSpec, raw: str, path: str | None = None) -> dict[str, Any]:
    """One frame decoded and refocused in memory: {"lf", "refocused", "facts"}, or {"error": sentence} for
    a frame that is bad input (a value, not an exception: Dask must not retry it)."""
    from mlaqc.decode.lightfield import refocus

    t0 = time.perf_counter()
    try:
        lf, facts = decode_raw(path or raw, spec)
        refocused = [(s, refocus(lf, s)[0]) for s in spec.slopes]
    except InputError as exc:
        return {"error": str(exc).replace(path, raw) if path else str(exc)}
    facts["source"] = str(raw)
    facts["seconds"] = round(time.perf_counter() - t0, 3)
    return {"lf": lf, "refocused": refocused, "facts": facts}


def decode_remote(spec: DecodeSpec, raw: str, path: str, client_sees_it: bool) -> dict[str, Any]:
    """Run on a Dask worker: `decoded_here` of the raw at the absolute `path`, or {"unseen": host} when this
    worker cannot see a file the client can."""
    if client_sees_it and not os.path.exists(path):
        return {"unseen": socket.gethostname()}
    return decoded_here(spec, raw, path)


def decoded_on_cluster(client: Any, spec: DecodeSpec, raws: list[str], quiet: bool):
    """(index, result) of every frame decoded on the cluster of `client`, as they complete."""
    shared = cluster.share(client, spec, "decode-spec")
    run_id = uuid.uuid4().hex[:8]
    futures = {}
    for i, raw in enumerate(raws):
        path = os.path.abspath(raw)  # workers have another working directory
        fut = client.submit(decode_remote, shared, raw, path, os.path.exists(path), pure=False,
                            retries=cluster.TASK_RETRIES, key=f"decode-{i + 1:05d}-{Path(raw).name}-{run_id}")
        futures[fut] = i
    for i, value in cluster.follow(futures, f"decoding {len(raws)} frames on Dask", progress=False if quiet else None):
        if "unseen" in value:
            raise cluster.unseen(value["unseen"], os.path.abspath(raws[i]))
        yield i, value


def _folders(out: Path, raws: list[str]) -> list[Path]:
    from mlaqc.commands.inspect import report_folders

    return report_folders(out, raws)


def _setup(args: argparse.Namespace, cfg: Any, levels) -> dict[str, Any]:
    """The sampling (from the grid, the white's calibration, or the report) and the white's light field."""
    from mlaqc.commands.inspect import shared_grid
    from mlaqc.decode import sampling as smp
    from mlaqc.decode.foreign import foreign_share
    from mlaqc.decode.frames import averaged
    from mlaqc.decode.lightfield import decode, view_offsets

    grid = shared_grid(args, cfg)  # --grid checked against the camera, or calibrated on --white
    if args.report:
        from mlaqc.report.document import load_report

        report = load_report(args.report)
        rgrid = smp.report_grid(report, args.report)
        smp.check_same_array(grid, rgrid, args.report)
        sampling = smp.measured_sampling(rgrid, report)
    elif args.lattice == "design":
        sampling = smp.design_sampling(cfg, (cfg.sensor.height_px, cfg.sensor.width_px))
    else:
        sampling = smp.lattice_sampling(grid)
    offsets = view_offsets(sampling.radius_px, args.views)
    white_lf = decode(averaged(list(args.white), cfg, levels), sampling, offsets) if args.white else None
    judged = white_lf is not None and sampling.flagged is not None and sampling.flagged.any()
    share = foreign_share(white_lf, sampling.flagged) if judged else None  # once, for every frame
    return {"sampling": sampling, "offsets": offsets, "white_lf": white_lf, "foreign_share": share}


def decode_raw(raw: str, spec: DecodeSpec):
    """One scene frame's light field (devignetted, hex resampled, filled as asked) and its facts."""
    from mlaqc.decode.frames import load_decode_frame
    from mlaqc.decode.fill import filled
    from mlaqc.decode.lightfield import rectangular
    from mlaqc.decode.scene import decode_scene

    sampling, white_lf = spec.setup["sampling"], spec.setup["white_lf"]
    lf = decode_scene(load_decode_frame(raw, spec.cfg, spec.levels), sampling, spec.setup["offsets"], white_lf, raw,
                      spec.setup["foreign_share"])
    check_scene(lf, raw)
    foreign = 0 if lf.foreign is None else int(np.count_nonzero(lf.foreign))
    if spec.fill:
        lf = filled(lf, lenses=sampling.inside)
    unfilled = 0 if lf.foreign is None else int(np.count_nonzero(lf.foreign))
    lf = replace(rectangular(lf), foreign=None)  # counted: not carried further (a Dask worker returns it)
    lens_weight = sampling.weight
    facts = {"sampling": sampling.source, "devignetted": white_lf is not None,  # (the source: decoded_here's)
             "lenses": {"rows": int(sampling.shape[0]), "cols": int(sampling.shape[1]),
                        "packing": sampling.packing, "pitch_px": round(sampling.pitch_px, 4),
                        "subimage_radius_px": round(sampling.radius_px, 3),
                        "without_light_field": int(np.count_nonzero(lens_weight == 0)),
                        "reduced_weight": int(np.count_nonzero((lens_weight > 0) & (lens_weight < 1))),
                        "foreign_light_samples": foreign, "foreign_light_refilled": foreign - unfilled,
                        "filled": spec.fill}}
    return lf, facts


def check_scene(lf, raw: str) -> None:
    """InputError when the frame is a flat field: its lenses' brightness varies only as a smooth
    illumination does (mlaqc.inspection.flatfield), so there is no scene to decode."""
    from mlaqc.inspection.flatfield import MIN_SPREAD, NOISE_FACTOR, brightness_spread

    vals = lf.values if lf.values.ndim == 4 else lf.values.mean(axis=-1)
    w = lf.weights
    with np.errstate(all="ignore"):
        flux = np.where(w.sum(axis=(0, 1)) > 0, (vals * w).sum(axis=(0, 1)) / w.sum(axis=(0, 1)), np.nan)
    spread, noise = brightness_spread(flux)
    if np.isfinite(spread) and spread <= max(MIN_SPREAD, NOISE_FACTOR * noise):
        raise InputError(f"{raw} is a flat field (its lenses' brightness varies by {spread:.1%} beyond a smooth "
                         "illumination): a white frame holds no scene to decode; give it as --white")


def _summary(folder: Path, lf, facts: dict[str, Any]) -> str:
    nv, nu, rows, cols = lf.weights.shape
    lenses = facts["lenses"]
    how = {"measured": "each flagged lens at its measured centre (report)", "lattice": "the calibrated lattice",
           "design": "the design lattice"}[facts["sampling"]]
    return (f"wrote {folder}: {nv}x{nu} views of {cols}x{rows} lenses ({lf.packing}), sampled on {how}, "
            f"{'devignetted' if facts['devignetted'] else 'not devignetted (no --white)'}; "
            f"{lenses['without_light_field']} lenses without light field, {lenses['reduced_weight']} at reduced "
            f"weight{_foreign_text(lenses)} ({facts['seconds']:.2f} s)")


def _foreign_text(lenses: dict[str, Any]) -> str:
    n, refilled = lenses["foreign_light_samples"], lenses["foreign_light_refilled"]
    if not n:
        return ""
    return (f", {n} samples mostly another lens' light dropped"
            + (f" ({refilled} refilled from the neighbours)" if lenses["filled"] else ""))
