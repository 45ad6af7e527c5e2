"""`mlaqc simulate`: render a raw image of the camera (with an error map) and write it with its ground truth."""

from __future__ import annotations

import argparse
import math
import sys

from mlaqc.cluster import add_scheduler_option, check_address, connect, scheduler_address
from mlaqc.errors import InputError
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ERROR_TYPES, ErrorMap, load_error_map, random_defects
from mlaqc.optics.scene import PointScene, Scene, TextureScene, WhiteScene
from mlaqc.optics.simulate import RAW_SUFFIXES, check_output, simulate, write_simulation
from mlaqc.progress import ProgressBar


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `simulate` subcommand."""
    p = sub.add_parser("simulate", help="render a raw image with the ray-traced camera model",
                       description="Render a raw image of the plenoptic camera with per-lens errors "
                                   "and write it (TIFF 16-bit, DNG, NPY or PNG) with a .sim.json ground-truth record.")
    p.add_argument("--out", "-o", required=True, help=f"output raw file ({', '.join(RAW_SUFFIXES)})")
    p.add_argument("--config", "-c", help="camera config TOML (default: the paper's Table 1 camera)")
    p.add_argument("--scene", choices=("white", "points", "texture"), default="white",
                   help="white: uniform Lambertian plane (calibration image); points: point sources; texture: an image")
    p.add_argument("--points", help="point sources on the object plane, 'x,y;x,y' in mm (scene 'points')")
    p.add_argument("--point-photons", type=float, default=1e6, help="photons each point sends into the pupil")
    p.add_argument("--texture", help="image file whose grey levels are the object radiance (scene 'texture')")
    grp = p.add_mutually_exclusive_group()
    grp.add_argument("--errors", "-e", help="JSON error map (keyed by U(m,n))")
    grp.add_argument("--random-defects", type=int, metavar="N", help="seed N random defective lenses")
    p.add_argument("--defect-types", default="pitch,decenter,radius",
                   help=f"comma-separated types for --random-defects, from {','.join(ERROR_TYPES)}")
    rays = p.add_mutually_exclusive_group()
    rays.add_argument("--rays", type=int, help="total rays to trace")
    rays.add_argument("--rays-per-pixel", type=float, help="rays per sensor pixel (default: the config's)")
    p.add_argument("--seed", type=int, default=0, help="random seed (render, noise and random defects)")
    p.add_argument("--no-noise", action="store_true", help="write the expected signal without shot/read noise")
    p.add_argument("--threads", type=int, help="worker threads (default: one per core)")
    p.add_argument("--engine", choices=("auto", "numba", "numpy"), help="tracer engine (default: the config's)")
    p.add_argument("--sampler", choices=("sobol", "random"),
                   help="sobol: low-discrepancy, stratified per microlens; random: plain Monte-Carlo (default: the config's)")
    add_scheduler_option(p)
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar or summary")
    p.set_defaults(func=run)


def parse_points(text: str | None) -> tuple[tuple[float, float], ...]:
    """'x,y;x,y' -> ((x, y), ...) in mm; InputError with the bad part named."""
    if not text:
        raise InputError("scene 'points' needs --points 'x,y;x,y' (object-plane positions in mm)")
    pts = []
    for part in text.split(";"):
        try:
            x, y = (float(v) for v in part.split(","))
        except ValueError:
            raise InputError(f"--points entry {part!r} is not 'x,y' in mm") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise InputError(f"--points entry {part!r} is not finite")
        pts.append((x, y))
    return tuple(pts)


def build_scene(args: argparse.Namespace) -> Scene:
    """The scene the options describe."""
    if args.scene == "points":
        if not (args.point_photons > 0 and math.isfinite(args.point_photons)):
            raise InputError("--point-photons must be a positive number")
        return PointScene(parse_points(args.points), args.point_photons)
    if args.scene == "texture":
        if not args.texture:
            raise InputError("scene 'texture' needs --texture IMAGE")
        return TextureScene.from_file(args.texture)
    return WhiteScene()


def build_errors(args: argparse.Namespace, rows: int, cols: int) -> ErrorMap:
    """The error map from --errors, --random-defects, or a perfect array."""
    if args.errors:
        return load_error_map(args.errors, (rows, cols))
    if args.random_defects is not None:
        if args.random_defects < 0:
            raise InputError("--random-defects must not be negative")
        types = tuple(t.strip() for t in args.defect_types.split(",") if t.strip())
        return random_defects(rows, cols, args.random_defects, args.seed, types=types)
    return ErrorMap.zeros(rows, cols)


def run(args: argparse.Namespace) -> int:
    """Render and write; 0 on success."""
    check_output(args.out)
    cfg = load_config(args.config)
    if args.threads is not None and not 1 <= args.threads <= 256:
        raise InputError("--threads must be between 1 and 256")
    scene = build_scene(args)
    errors = build_errors(args, cfg.mla.count_h, cfg.mla.count_w)
    from mlaqc.optics.render import Renderer

    renderer = Renderer(cfg, errors, engine=args.engine, sampler=args.sampler)
    address = scheduler_address(args.scheduler)
    bar = ProgressBar("rendering", enabled=False if args.quiet else None)
    kw = dict(rays=args.rays, rays_per_pixel=args.rays_per_pixel, seed=args.seed, noise=not args.no_noise,
              threads=args.threads, progress=bar, renderer=renderer)
    try:
        if address is None:
            sim = simulate(cfg, scene, errors, **kw)
        else:
            with connect(check_address(address), quiet=args.quiet) as client:
                sim = simulate(cfg, scene, errors, client=client, **kw)
    finally:
        bar.close()
    sidecar = write_simulation(args.out, sim, cfg)
    if not args.quiet:
        r = sim.render
        print(f"wrote {args.out} and {sidecar.name}: {r.rays_traced:,} rays in {r.seconds:.1f} s "
              f"({r.rays_traced / max(r.seconds, 1e-9) / 1e6:.1f} M rays/s, {sim.engine}), "
              f"{int(errors.defective().sum())} defective lenses", file=sys.stderr)
    return 0
