"""Small arrays against Table 1's frame on an independent model (issue #38's bar): 12 x 12 and 24 x 24
analytic frames must find >= 95 % of the lens shifts at and above the pitch detection limit each frame's
report states, border lenses included, and measure the healthy lenses' centres within 1.3x the RMS error
of the 102 x 102 frame's at the same noise. Prints a row per size and noise, the missed lenses (why each
was not flagged) and the bars.

    python bench/small_frames.py                 # 12, 24, 102 lenses a side, noise 0/1/3 %, 5 seeds (2 on 102): ~2 min
    python bench/small_frames.py --quick         # 3 seeds (1 on 102), 102 not at 3 %: ~45 s
    python bench/small_frames.py --hex --quick   # hex arrays (hex_small_camera optics; 102 columns: hex_camera.toml)
    python bench/small_frames.py --spacing 6 --sizes 12 24 --noises 0.01 --seeds 8 --list-misses 100

Per size and noise, each seed draws a rotation (within ±1°) and a sub-pixel phase. The healthy frame of
tests/analytic_frames.py (no code shared with the tracer), written as a 12-bit TIFF with level tags and
inspected as a user's file would be, gives the stated pitch limit L, its false flags, and the RMS error of
its healthy lenses' measured centres against the true ones (bench/robustness.py's `centre_rms`: lenses
wholly on the sensor). Round 1: every `--spacing`-th lens both ways (the outer rows and columns included)
is shifted in a random direction by L x (1.0, 1.1, 1.25, 1.5, 2.0) µm of pitch (a pitch error of d µm moves
a sub-image d (b + f) / b on the sensor). Seeded lenses widen the spread a frame judges by, so the seeded
frame may state a higher limit of its own; then round 2 seeds the same lenses at that limit x the same
factors. The bar's recall counts, over both rounds, the seeded lenses at or above the limit that frame's
report states for where they sit: the edge zone (detection_limits.edge_zone: the three outer rings and the
4 x 4 corner zones) or inside; round 1's recall per factor of the healthy frame's L is shown beside it.
Seeded lenses the inspection does not inspect (window off the sensor: the 102 x 102 frame's outer ring) and
the array's four corner lenses, which the report says it does not judge, are counted apart ("skip").
Each missed lens is listed with its detection score against the threshold, its offset spread against the
inner lenses' median (the inner limit is an inner lens' at that median: inspection.detection_limits) and
why it was not flagged: under the threshold, read below the reportable size, or taken for an echo.
The camera: fixtures/small_camera.toml with N x N lenses on bench/size_limits.py's sensor; 102 is
fixtures/paper_table1.toml.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))

import analytic_frames as am  # noqa: E402
from robustness import _match_truth, centre_rms  # noqa: E402

import mlaqc.inspection.pipeline as pipeline  # noqa: E402
from mlaqc.inspection.detection_limits import edge_zone  # noqa: E402
from mlaqc.inspection.lens_classes import ring_distance  # noqa: E402
from mlaqc.optics.config import CameraConfig, load_config  # noqa: E402

FIXTURES = ROOT / "fixtures"
FACTORS = (1.0, 1.1, 1.25, 1.5, 2.0)  # seeded pitch errors over the frame's stated limit
RECALL_BAR, RMS_BAR = 0.95, 1.3
BITS, BLACK = 12, 64
UM_TO_PX = (am.TABLE1_B_MM + am.TABLE1_F_MM) / am.TABLE1_B_MM / am.TABLE1_PIXEL_UM  # sensor px per µm of pitch


def camera(lenses: int, packing: str = "square") -> CameraConfig:
    """Table 1's optics with `lenses` columns (square: rows too; hex: the rows filling a square), on the
    smallest sensor of a multiple of 16 px holding the array and 4 px a side; 102 is the 2048 x 2048
    fixture (paper_table1.toml, hex_camera.toml)."""
    if lenses == 102:
        return load_config(FIXTURES / ("paper_table1.toml" if packing == "square" else "hex_camera.toml"))
    cfg = load_config(FIXTURES / ("small_camera.toml" if packing == "square" else "hex_small_camera.toml"))
    p = cfg.layout.subimage_pitch_px
    rows = lenses if packing == "square" else 2 * round(lenses / math.sqrt(3.0))
    extent = lenses * p if packing == "square" else max(lenses * p, ((rows - 1) * math.sqrt(3.0) / 2 + 1) * p)
    side = 16 * math.ceil((extent + 8) / 16)
    return dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, count_w=lenses, count_h=rows),
                               sensor=dataclasses.replace(cfg.sensor, width_px=side, height_px=side))


_CAUGHT: list = []


def _capture(identify):
    """pipeline.identify wrapped to keep its Identification (scores, below-reportable lenses) for the misses."""
    def wrapped(*a, **k):
        found = identify(*a, **k)
        _CAUGHT.append(found)
        return found
    return wrapped


pipeline.identify = _capture(pipeline.identify)


def inspect(model: am.AnalyticModel, noise: float, rng: np.random.Generator, cfg: CameraConfig, path: Path):
    """Render, expose, write a 12-bit TIFF with level tags, inspect; (result, identification, seconds)."""
    counts = am.to_counts(am.expose(model.render(), noise, rng), BITS, BLACK)
    am.write_container(path, counts, BITS, BLACK, tags=True)
    _CAUGHT.clear()
    t0 = time.perf_counter()
    result = pipeline.inspect_file(path, cfg)
    return result, (_CAUGHT[-1] if _CAUGHT else None), time.perf_counter() - t0


def not_inspected(result) -> np.ndarray:
    """Lenses the inspection left out: the grid's clipped ones and those whose window leaves the frame."""
    return np.asarray(result.grid.clipped, bool) | np.isnan(np.asarray(result.subimages)).any(axis=(-2, -1))


@dataclass
class Frame:
    """One seed of one (size, noise) cell: the healthy frame and the seeded rounds."""

    size: int
    noise: float
    seed: int
    shape: tuple
    limit: float | None  # the healthy frame's stated pitch limit L (µm)
    clean_false: int
    centre_rms: float
    inner_rms: float
    seeded_limits: list = field(default_factory=list)  # each seeded round's own stated limit
    border_limits: list = field(default_factory=list)  # and its stated limit for the edge zone
    hits: dict = field(default_factory=lambda: defaultdict(lambda: [0, 0]))  # round 1: (where, factor) -> [found, n]
    own: dict = field(default_factory=lambda: defaultdict(lambda: [0, 0]))  # every round, at/above its own limit
    false: int = 0
    unknown: int = 0  # seeded lenses found but typed 'unknown'
    readings: list = field(default_factory=list)  # found lenses' pitch reading (µm) over the seeded pitch error
    skipped: int = 0  # seeded but not inspected
    misses: list = field(default_factory=list)
    seconds: float = 0.0


def inner_rms(result, model) -> float:
    """`centre_rms`'s measured-centre RMS over the inner lenses (edge ring >= 2) alone."""
    g = result.grid
    cx, cy = model.centres()
    if (g.rows, g.cols) != cx.shape:
        return float("nan")
    ok = model.inside() & ~np.asarray(g.clipped, bool) & ~np.asarray(g.missing, bool) & (ring_distance(cx.shape) >= 2)
    return float(np.sqrt(np.mean((g.measured_x_px[ok] - cx[ok]) ** 2 + (g.measured_y_px[ok] - cy[ok]) ** 2)))


def run(size: int, noise: float, seed: int, spacing: int, packing: str, tmp: Path) -> Frame:
    """The healthy frame, then round 1: shifts at the healthy frame's L x FACTORS; where the seeded frame
    states a higher limit of its own (the seeded lenses widen the spread it judges by), round 2: the same
    lenses at that limit x FACTORS. Recall is counted per round over the lenses at or above the limit
    that round's report states, and for round 1 also per factor of the healthy frame's L."""
    cfg = camera(size, packing)
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    rng = np.random.default_rng([seed, size, int(round(noise * 1000)), packing == "hex"])
    rot, phase = float(rng.uniform(-1.0, 1.0)), (float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5)))
    model = am.AnalyticModel(rotation_deg=rot, phase_px=phase, shape=(cfg.sensor.height_px, cfg.sensor.width_px),
                             lenses=(rows, cols), packing=packing)
    clean, _, t_clean = inspect(model, noise, rng, cfg, tmp / "clean.tif")
    limit = clean.detection_limit.get("pitch_um")
    ctr, _grid = centre_rms(clean, model, set())
    fr = Frame(size, noise, seed, (rows, cols), limit, len(clean.defects), ctr, inner_rms(clean, model),
               seconds=t_clean)
    if limit is None:
        return fr
    # every `spacing`-th lens both ways from a random start, and the first and last row and column where
    # that leaves them out with a lens between them and the next seeded one: every frame seeds both rings
    rs, cs = _every(rows, spacing, int(rng.integers(spacing))), _every(cols, spacing, int(rng.integers(spacing)))
    lenses = [(r, c) for r in rs for c in cs]
    factors = np.resize(np.array(FACTORS), len(lenses))
    rng.shuffle(factors)
    directions = rng.uniform(0.0, 360.0, len(lenses))
    base = limit
    for step in (1, 2):
        anomalies = [am.Anomaly(r, c, "shift", float(f * base * UM_TO_PX), float(d))
                     for (r, c), f, d in zip(lenses, factors, directions)]
        seeded_model = model.with_anomalies(anomalies)
        result, found, t = inspect(seeded_model, noise, rng, cfg, tmp / "seeded.tif")
        fr.seconds += t
        own = result.detection_limit.get("pitch_um")
        own_border = (result.detection_limit.get("border") or {}).get("pitch_um", own)
        fr.seeded_limits.append(own)
        fr.border_limits.append(own_border)
        truth = _match_truth(result, seeded_model, {(a.row + 1, a.col + 1): {"factor": float(f), "um": float(f * base)}
                                                    for a, f in zip(anomalies, factors)})
        score_round(fr, step, cfg, result, found, truth, own, own_border)
        if own is None or own <= base * (1 + 1e-9):
            break
        base = own
    return fr


def score_round(fr: Frame, step: int, cfg, result, found, truth: dict, own: float | None,
                own_border: float | None) -> None:
    """Recall of one round: each seeded lens against the limit the report states for its ring (inner, or
    the outer two rings'); the array's corner lenses, which the report says it does not judge, apart."""
    flagged = {(d.m, d.n): d for d in result.defects}
    ring = ring_distance(result.flagged.shape)
    zone = edge_zone(result.flagged.shape)
    rows, cols = result.flagged.shape
    skip = not_inspected(result)
    fr.false += sum(key not in truth for key in flagged)
    for (m, n), t in truth.items():
        if skip[m - 1, n - 1] or (m in (1, rows) and n in (1, cols)):
            fr.skipped += step == 1
            continue
        where = "border" if zone[m - 1, n - 1] else "inner"
        limit = own_border if where == "border" else own
        hit = flagged.get((m, n))
        if step == 1:
            cell = fr.hits[(where, t["factor"])]
            cell[0] += hit is not None
            cell[1] += 1
        at_own = limit is not None and t["um"] >= limit - 1e-9
        if at_own:
            fr.own[where][0] += hit is not None
            fr.own[where][1] += 1
        if hit is not None:
            fr.unknown += hit.error_type == "unknown"
            if hit.error_type in ("pitch", "position", "decenter") and hit.unit == "µm":
                fr.readings.append(abs(hit.magnitude) / t["um"])
        else:
            fr.misses.append(miss_detail(found, cfg, m, n, t["factor"], t["um"], ring[m - 1, n - 1], step, at_own))


def _every(count: int, spacing: int, start: int) -> list[int]:
    """start, start + spacing, ... below count, with 0 and count - 1 added when at least 2 from the rest."""
    out = list(range(start, count, spacing))
    return ([0] if out[0] >= 2 else []) + out + ([count - 1] if count - 1 - out[-1] >= 2 else [])


def miss_detail(found, cfg, m: int, n: int, factor: float, um: float, ring: int, step: int, at_own: bool) -> dict:
    """Why a seeded lens was not flagged: its score against the threshold, and the lens' offset noise
    against the inner lenses' median (the detection limit is stated for an inner lens at that median)."""
    rows, cols = found.score.shape if found is not None else (0, 0)
    corner = m in (1, rows) and n in (1, cols)
    d = {"m": m, "n": n, "ring": "corner" if corner else min(int(ring), 2), "factor": factor, "um": um, "round": step,
         "at_own": at_own}
    if found is None:
        return d
    i, j = m - 1, n - 1
    thr = cfg.qc.detect_sigma
    d["score"], d["threshold"] = float(found.score[i, j]), thr
    sig = found.noise.sigma
    inner = ring_distance(sig.shape[:2]) >= 2
    d["noise_ratio"] = float(sig[i, j, 0] / np.nanmedian(sig[inner][:, 0])) if inner.any() else float("nan")
    unrep = found.unreported is not None and found.unreported[i, j]
    d["why"] = "below reportable" if unrep else ("under threshold" if d["score"] <= thr else "echo (spill)")
    return d


# ------------------------------------------------------------------------------------------- printing

def _pct(h: list[int]) -> str:
    return f"{h[0]}/{h[1]}" if h[1] else "–"


def _sum(frames: list[Frame], where: str | None = None, factor: float | None = None, own: bool = False) -> list[int]:
    out = [0, 0]
    for f in frames:
        items = (((w, None), v) for w, v in f.own.items()) if own else f.hits.items()
        for (w, fa), (a, b) in items:
            if (where is None or w == where) and (factor is None or fa == factor):
                out[0] += a
                out[1] += b
    return out


def _span(values: list) -> str:
    v = [x for x in values if x is not None]
    if not v:
        return "–"
    return f"{min(v):.3g}" if min(v) == max(v) else f"{min(v):.3g}-{max(v):.3g}"


def _median_of(frames: list[Frame]) -> str:
    r = [x for f in frames for x in f.readings]
    return f"{np.median(r):.2f}" if r else "–"


def table(groups: dict, ref_rms: dict) -> list[tuple[str, bool, str]]:
    """Print one row per (size, noise); return the bars (label, ok, detail)."""
    print(f"{'':>14} {'limit µm':^35}  {'recall at/above own L':^29}  {'round 1: recall at L x':^45}")
    print(f"{'size':>8} {'noise':>5} {'clean':>11} {'seeded':>11} {'edge zone':>11}  {'all':>9} {'border':>9} {'inner':>9}  "
          + " ".join(f"{f'×{f:g}':>7}" for f in FACTORS)
          + f" {'false':>5} {'clean':>5} {'unk':>4} {'skip':>4} {'read':>5} {'ctr rms':>8} {'inner':>7} {'/102':>5}")
    bars = []
    for (size, noise), frames in groups.items():
        own, bor, inn = _sum(frames, own=True), _sum(frames, "border", own=True), _sum(frames, "inner", own=True)
        rms = float(np.median([f.centre_rms for f in frames]))
        irms = float(np.median([f.inner_rms for f in frames]))
        ratio = rms / ref_rms[noise] if noise in ref_rms and ref_rms[noise] > 0 else float("nan")
        label = f"{frames[0].shape[1]}x{frames[0].shape[0]}"
        print(f"{label:>8} {noise:>5.0%} {_span([f.limit for f in frames]):>11} "
              f"{_span([x for f in frames for x in f.seeded_limits]):>11} "
              f"{_span([x for f in frames for x in f.border_limits]):>11}  "
              f"{_pct(own):>9} {_pct(bor):>9} {_pct(inn):>9}  "
              + " ".join(f"{_pct(_sum(frames, factor=fa)):>7}" for fa in FACTORS)
              + f" {sum(f.false for f in frames):>5} {sum(f.clean_false for f in frames):>5} "
              f"{sum(f.unknown for f in frames):>4} {sum(f.skipped for f in frames):>4} {_median_of(frames):>5} "
              f"{rms:>8.4f} {irms:>7.4f} "
              f"{'' if size == 102 or not math.isfinite(ratio) else f'{ratio:.2f}':>5}", flush=True)
        if size != 102:
            # (round 1's recall against the healthy frame's L is shown in the table, not a bar: seeded lenses
            # widen the spread the seeded frame judges by, and its report states the higher limit it reaches)
            for name, h in (("recall >= own L", own), ("  border", bor), ("  inner", inn)):
                if h[1]:
                    bars.append((f"{label} {noise:>3.0%} {name}", h[0] >= RECALL_BAR * h[1],
                                 f"{100 * h[0] / h[1]:.1f} % of {h[1]}"))
            if math.isfinite(ratio):
                bars.append((f"{label} {noise:>3.0%} centre RMS / 102x102 <= {RMS_BAR}", ratio <= RMS_BAR,
                             f"{ratio:.2f}: {rms:.4f} vs {ref_rms[noise]:.4f} px"))
            false = sum(f.clean_false for f in frames)
            bars.append((f"{label} {noise:>3.0%} healthy frames: no lens flagged", false == 0, f"{false} flagged"))
    return bars


def print_misses(frames: list[Frame], limit: int) -> None:
    misses = [(f, d) for f in frames for d in f.misses]
    if not misses:
        return
    print(f"\nmissed seeded lenses ({len(misses)}), by size, noise, round, at/above that round's own L, edge ring "
          "(0 outer, 1 next, 2 inner; corner: the array's 4 corner lenses), factor, why:")
    summary = defaultdict(int)
    for f, d in misses:
        summary[(f.size, f"{f.shape[1]}x{f.shape[0]}", f.noise, d["round"], "≥ own L" if d["at_own"] else "< own L",
                 str(d["ring"]),
                 d["factor"], d.get("why", "?"))] += 1
    for k, v in sorted(summary.items()):
        print(f"  {k[1]:>7} {k[2]:>3.0%} round {k[3]} {k[4]:<8} ring {k[5]:<6} ×{k[6]:<5g} {k[7]:<17} {v:>4}")
    if limit:
        print("one by one (score / threshold; the lens' offset spread over the inner lenses' median):")
    for f, d in misses[:limit]:
        print(f"  {f.shape[1]}x{f.shape[0]} {f.noise:.0%} seed {f.seed} round {d['round']} U({d['m']},{d['n']}) "
              f"ring {d['ring']} "
              f"×{d['factor']:g} = {d['um']:.3g} µm: score {d.get('score', float('nan')):.2f} / "
              f"{d.get('threshold', float('nan')):g}, noise ×{d.get('noise_ratio', float('nan')):.2f}, "
              f"{d.get('why', '?')}")
    if len(misses) > limit:
        print(f"  ... {len(misses) - limit} more (--list-misses N)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 seeds on 12 and 24, 1 on 102, and 102 not at 3 %%")
    ap.add_argument("--sizes", type=int, nargs="+", default=[12, 24, 102], help="lenses a side (102: Table 1's frame)")
    ap.add_argument("--noises", type=float, nargs="+", default=[0.0, 0.01, 0.03], help="shot noise at a white pixel")
    ap.add_argument("--seeds", type=int, default=None, help="seeds on the small arrays (default 5; quick 3)")
    ap.add_argument("--seeds-102", type=int, default=None, help="seeds on 102 x 102 (default 2; quick 1)")
    ap.add_argument("--spacing", type=int, default=3, help="every how many lenses a shift is seeded (both ways)")
    ap.add_argument("--hex", action="store_true", help="hex arrays (hex_small_camera optics; 102: hex_camera.toml)")
    ap.add_argument("--list-misses", type=int, default=30, help="missed lenses listed one by one")
    args = ap.parse_args()
    seeds = args.seeds or (3 if args.quick else 5)
    seeds_102 = args.seeds_102 or (1 if args.quick else 2)
    packing = "hex" if args.hex else "square"
    t0 = time.perf_counter()
    groups: dict = {}
    with tempfile.TemporaryDirectory() as d:
        for size in args.sizes:
            for noise in args.noises:
                if args.quick and size == 102 and noise > 0.02:
                    continue
                frames = []
                for seed in range(seeds_102 if size == 102 else seeds):
                    frames.append(run(size, noise, seed, args.spacing, packing, Path(d)))
                groups[(size, noise)] = frames
                print(f"  {size}x{size} noise {noise:.0%}: {len(frames)} frames, "
                      f"{sum(f.seconds for f in frames):.1f} s inspecting", flush=True)
    print(f"\n{packing}; shifts every {args.spacing} lenses both ways at L x {', '.join(f'{f:g}' for f in FACTORS)} "
          "(L: the healthy frame's stated pitch limit; a second round at the seeded frame's own limit where it "
          "states a higher one). Recall over the seeded lenses inspected (border: the edge zone the report states its own limit for, the three outer rings and the 4 x 4 corner zones); false: "
          "flagged, not seeded (seeded frames); clean: flagged on the healthy frames; unk: found, typed "
          "'unknown'; skip: seeded, not inspected; read: median pitch reading over the seeded error (found lenses); "
          "centre RMS (px): healthy frames, median over seeds; /102: "
          "over the 102 x 102 frame's at that noise\n")
    ref_rms = {noise: float(np.median([f.centre_rms for f in fr]))
               for (size, noise), fr in groups.items() if size == 102}
    bars = table(groups, ref_rms)
    print_misses([f for fr in groups.values() for f in fr], args.list_misses)
    print("\nbars:")
    for label, ok, detail in bars:
        print(f"  {label:<52} {'meets' if ok else 'FAILS'}  ({detail})")
    print(f"\n{time.perf_counter() - t0:.0f} s")
    return 0 if all(ok for _, ok, _ in bars) else 1


if __name__ == "__main__":
    sys.exit(main())
