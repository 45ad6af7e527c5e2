"""`mlaqc simulate`: render a raw image of the camera (with an error map) and write it with its ground truth."""

from __future__ import annotations

import argparse
import math
import sys

from mlaqc.cluster import add_scheduler_option, check_address, connect, scheduler_address
from mlaqc.errors import InputError
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ERROR_TYPES, ErrorMap, load_error_map, physical_types, random_defects
from mlaqc.optics.scene import PointScene, Scene, TextureScene, WhiteScene
from mlaqc.optics.simulate import RAW_SUFFIXES, check_output, simulate, write_simulation
from mlaqc.optics.throughfocus import F_NUMBER, FOCUS_OFFSET_MM, SPACING_LENSES, ThroughFocus
from mlaqc.optics.throughfocus import frame_config as tf_frame_config
from mlaqc.optics.throughfocus import scene as tf_scene
from mlaqc.progress import ProgressBar


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `simulate` subcommand."""
    p = sub.add_parser("simulate", help="render a raw image with the ray-traced camera model",
                       description="Render a raw image of the plenoptic camera with per-lens errors "
                                   "and write it (TIFF 16-bit, DNG, NPY or PNG) with a .sim.json ground-truth record.")
    p.add_argument("--out", "-o", required=True, help=f"output raw file ({', '.join(RAW_SUFFIXES)})")
    p.add_argument("--config", "-c", help="camera config TOML (default: the paper's Table 1 camera)")
    p.add_argument("--scene", choices=("white", "points", "texture", "through-focus"), default="white",
                   help="white: uniform Lambertian plane (calibration image); points: point sources; texture: an image; "
                        "through-focus: the pinhole lattice of the second measurement (main lens stopped down, "
                        "pinholes imaged --focus-offset-mm behind the MLA)")
    p.add_argument("--points", help="point sources on the object plane, 'x,y;x,y' in mm (scene 'points'; an ideal main lens: in "
                   "the plane it images them onto, geometry.image_defocus_mm before the MLA)")
    p.add_argument("--point-photons", type=float, default=1e6, help="photons each point sends into the pupil")
    p.add_argument("--texture", help="image file whose grey levels are the object radiance (scene 'texture')")
    tf = p.add_argument_group("through-focus scene")
    tf.add_argument("--focus-offset-mm", type=float, metavar="U",
                    help=f"pinholes imaged U mm behind (+) or in front of (-) the MLA (default {FOCUS_OFFSET_MM:g}; "
                         f"the pair is {FOCUS_OFFSET_MM:g} and {-FOCUS_OFFSET_MM:g})")
    tf.add_argument("--f-number", type=float, metavar="N", help=f"main lens stopped to f/N (default {F_NUMBER:g})")
    tf.add_argument("--pinhole-spacing", type=int, metavar="S",
                    help=f"pinhole images S lens pitches apart (default {SPACING_LENSES})")
    tf.add_argument("--pinhole-offset", metavar="X,Y",
                    help="shift of the pinhole lattice in whole lens steps (default 0,0); on a hex array Q,R: Q "
                         "along a row, R rows down (mlaqc.optics.throughfocus)")
    tf.add_argument("--pinhole-photons", type=float, metavar="P",
                    help="photons each pinhole sends into the pupil (default: the protocol's exposure, derived "
                         "from the optics: the brighter frame of the +U / -U pair peaks near 50 %% of full well, "
                         "room for the focused spots of defective lenses; 2.6e5 for the Table 1 camera at ±5 mm, "
                         "f/11)")
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


TF_OPTIONS = ("focus_offset_mm", "f_number", "pinhole_spacing", "pinhole_offset", "pinhole_photons")


def build_protocol(args: argparse.Namespace) -> ThroughFocus | None:
    """The through-focus frame the options describe (scene 'through-focus'), else None; InputError for
    through-focus options given with another scene or out of range."""
    given = [name for name in TF_OPTIONS if getattr(args, name, None) is not None]
    if args.scene != "through-focus":
        if given:
            raise InputError(f"--{given[0].replace('_', '-')} applies only to --scene through-focus")
        return None
    kw: dict = {"focus_offset_mm": FOCUS_OFFSET_MM, "f_number": F_NUMBER, "spacing_lenses": SPACING_LENSES}
    if args.focus_offset_mm is not None:
        kw["focus_offset_mm"] = args.focus_offset_mm
    if args.f_number is not None:
        kw["f_number"] = args.f_number
    if args.pinhole_spacing is not None:
        kw["spacing_lenses"] = args.pinhole_spacing
    if args.pinhole_photons is not None:
        kw["photons_per_pinhole"] = args.pinhole_photons
    if args.pinhole_offset is not None:
        try:
            ox, oy = (int(v) for v in args.pinhole_offset.split(","))
        except ValueError:
            raise InputError(f"--pinhole-offset {args.pinhole_offset!r} must be two whole numbers of lens pitches 'X,Y'") from None
        if ox < 0 or oy < 0:
            raise InputError(f"--pinhole-offset {args.pinhole_offset!r} must not be negative (0 to spacing - 1)")
        kw["offset_lenses"] = (ox, oy)
    tf = ThroughFocus(**kw)
    if max(tf.offset_lenses) >= tf.spacing_lenses:
        raise InputError(f"--pinhole-offset {tf.offset_lenses[0]},{tf.offset_lenses[1]} must be below the pinhole spacing "
                         f"({tf.spacing_lenses})")
    return tf


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


def build_errors(args: argparse.Namespace, mla) -> ErrorMap:
    """The error map from --errors, --random-defects (of the types this MLA can have), or a perfect array,
    on the camera's lattice."""
    rows, cols, packing = mla.count_h, mla.count_w, mla.packing
    if args.errors:
        return load_error_map(args.errors, (rows, cols), packing)
    if args.random_defects is not None:
        if args.random_defects < 0:
            raise InputError("--random-defects must not be negative")
        types = tuple(t.strip() for t in args.defect_types.split(",") if t.strip())
        return random_defects(rows, cols, args.random_defects, args.seed, types=physical_types(types, mla),
                              packing=packing)
    return ErrorMap.zeros(rows, cols, packing)


def run(args: argparse.Namespace) -> int:
    """Render and write; 0 on success."""
    check_output(args.out)
    cfg = load_config(args.config)
    if args.threads is not None and not 1 <= args.threads <= 256:
        raise InputError("--threads must be between 1 and 256")
    protocol = build_protocol(args)
    if protocol is not None:
        render_cfg, scene = tf_frame_config(cfg, protocol), tf_scene(cfg, protocol)
        if not scene.points_mm:
            raise InputError("the through-focus lattice puts no pinhole on the array; choose a smaller --pinhole-offset")
    else:
        render_cfg, scene = cfg, build_scene(args)
    errors = build_errors(args, cfg.mla)
    from mlaqc.optics.render import Renderer

    renderer = Renderer(render_cfg, errors, engine=args.engine, sampler=args.sampler)
    address = scheduler_address(args.scheduler)
    bar = ProgressBar("rendering", enabled=False if args.quiet else None)
    kw = dict(rays=args.rays, rays_per_pixel=args.rays_per_pixel, seed=args.seed, noise=not args.no_noise,
              threads=args.threads, progress=bar, renderer=renderer)
    try:
        if address is None:
            sim = simulate(render_cfg, scene, errors, **kw)
        else:
            with connect(check_address(address), quiet=args.quiet) as client:
                sim = simulate(render_cfg, scene, errors, client=client, **kw)
    finally:
        bar.close()
    sidecar = write_simulation(args.out, sim, cfg, protocol=protocol)
    if not args.quiet:
        r = sim.render
        print(f"wrote {args.out} and {sidecar.name}: {r.rays_traced:,} rays in {r.seconds:.1f} s "
              f"({r.rays_traced / max(r.seconds, 1e-9) / 1e6:.1f} M rays/s, {sim.engine}), "
              f"{int(errors.defective().sum())} defective lenses", file=sys.stderr)
    return 0
