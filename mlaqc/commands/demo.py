"""`mlaqc demo`: the whole chain on an embedded default — render an MLA with seeded defects, inspect it,
write the report, and compare what was found with what was seeded."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import DefectSpec, physical_types, random_defects
from mlaqc.errors import InputError
from mlaqc.progress import ProgressBar


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `demo` subcommand."""
    p = sub.add_parser("demo", help="simulate an MLA with seeded defects, inspect it, report found vs seeded",
                       description="Render the Table 1 camera's white image with seeded defects (pitch, "
                                   "decenter, radius), inspect it and write the raw, its ground truth and the "
                                   "report set into OUT; print what was found against what was seeded.")
    p.add_argument("--out", "-o", default="mlaqc-demo", help="output folder (default: ./mlaqc-demo)")
    p.add_argument("--config", "-c", help="camera config TOML (default: the paper's Table 1 camera)")
    p.add_argument("--defects", type=int, default=20, help="seeded defective lenses (default 20)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--rays-per-pixel", type=float, default=50.0, help="ray budget (default 50)")
    p.add_argument("--quiet", "-q", action="store_true")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Render, inspect, report, compare; 0 when the chain ran (whatever the verdict)."""
    from mlaqc.commands.inspect import check_out_dir, summary
    from mlaqc.inspection.pipeline import inspect_file
    from mlaqc.report import write_report
    from mlaqc.optics.render import Renderer
    from mlaqc.optics.simulate import simulate, write_simulation

    out = check_out_dir(args.out)
    cfg = load_config(args.config)
    if args.defects < 0:
        raise InputError("--defects must not be negative")
    spec = DefectSpec(pitch_um=(1.0, 4.0), decenter_um=(5.0, 12.0), radius_rel=(0.05, 0.2))
    errors = random_defects(cfg.mla.count_h, cfg.mla.count_w, args.defects, args.seed, spec=spec,
                            types=physical_types(("pitch", "decenter", "radius"), cfg.mla),
                            packing=cfg.mla.packing)
    out.mkdir(exist_ok=True)
    bar = ProgressBar("rendering", enabled=False if args.quiet else None)
    try:
        sim = simulate(cfg, None, errors, rays_per_pixel=args.rays_per_pixel, seed=args.seed, progress=bar,
                       renderer=Renderer(cfg, errors))
    finally:
        bar.close()
    raw = out / "demo_white.dng"
    write_simulation(raw, sim, cfg)
    result = inspect_file(raw, cfg)
    write_report(result, out, config_dict=cfg.to_dict())
    if not args.quiet:
        print(summary(result), file=sys.stderr)
        print(compare(errors, result), file=sys.stderr)
        print(f"  wrote {raw}, {raw.name}.sim.json and the report in {out}/ (open report.html)", file=sys.stderr)
    return 0


def compare(errors, result) -> str:
    """Found vs seeded, by U(m,n)."""
    seeded = errors.defective()
    kinds = errors.lens_type()
    found = result.flagged & seeded
    false = result.flagged & ~seeded
    lines = [f"  seeded {int(seeded.sum())}, found {int(found.sum())}, missed {int((seeded & ~result.flagged).sum())}, "
             f"false flags {int(false.sum())}"]
    by_lens = {(d.m, d.n): d for d in result.defects}
    for m, n in zip(*np.nonzero(seeded)):
        d = by_lens.get((m + 1, n + 1))
        truth = _truth(errors, kinds[m, n], m, n)
        got = _missed(errors, kinds[m, n], m, n, result.detection_limit) if d is None else describe(d)
        lines.append(f"    U({m + 1},{n + 1}): seeded {truth}; found {got}")
    return "\n".join(lines)


def describe(d) -> str:
    """'position 2.1 µm (pitch) or 4.4 µm (decenter)', 'radius -0.05 rel (or +0.17)', ..."""
    if d.error_type == "position":
        return "position " + " or ".join(f"{v:.3g} {u} ({t})" for t, v, u, _ in d.alternatives)
    text = f"{d.error_type} {d.magnitude:+.3g} {d.unit}" if d.unit == "rel" else f"{d.error_type} {d.magnitude:.3g} {d.unit}"
    if d.alternatives:
        text += " (or " + ", ".join(f"{v:+.3g}" for _, v, _, _ in d.alternatives) + ")"
    return text.strip()


def _missed(errors, kind: str, m: int, n: int, limit: dict) -> str:
    """'MISSED', and whether the seeded size was below what this frame detects (an honest miss) or not."""
    e = errors.lens
    rows, cols = e["pitch_um"].shape
    if m in (0, rows - 1) and n in (0, cols - 1):
        return "MISSED (a corner lens: not judged, the report says so)"
    if kind in ("pitch", "decenter"):
        size, key, sign, scale, unit = e[f"{kind}_um"][m, n], f"{kind}_um", "", 1.0, " µm"
    elif kind == "radius":
        rel = e["radius_front_rel"][m, n]
        size, scale, unit = abs(rel), 100.0, " %"
        key, sign = ("radius_rel_pos", "+") if rel > 0 else ("radius_rel_neg", "−")
    else:
        return "MISSED"
    from mlaqc.inspection.detection_limits import edge_zone

    border = bool(edge_zone((rows, cols))[m, n]) and isinstance((limit or {}).get("border"), dict)
    lim = (limit["border"] if border else limit or {}).get(key)
    if lim is None:
        return "MISSED (this frame cannot detect it at any rendered size)" if limit else "MISSED"
    where = "below" if size < lim else "at or above"
    ring = " near the edge" if border else ""
    return f"MISSED ({where} this frame's detection limit{ring}, {sign}{lim * scale:.3g}{unit})"


def _truth(errors, kind: str, m: int, n: int) -> str:
    e = errors.lens
    if kind == "pitch":
        return f"pitch {e['pitch_um'][m, n]:.3g} µm at {e['pitch_dir_deg'][m, n]:.0f} deg"
    if kind == "decenter":
        return f"decenter {e['decenter_um'][m, n]:.3g} µm at {e['decenter_dir_deg'][m, n]:.0f} deg"
    if kind == "radius":
        return f"radius {e['radius_front_rel'][m, n]:+.3g} rel"
    return kind
