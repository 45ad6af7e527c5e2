"""The defects real arrays have (issue #38 part 3) on frames the tracer did not make: the analytic model of
tests/analytic_frames.py given each camera's first-order optics (bench/instruments.py `analytic_model`),
noise-free and at 1 and 3 %. Per camera and noise:

- spots (dust, residue, a dig: part of the sub-image darkened) of 10, 25 and 50 % of the disc at 10 % and
  20 % depth: flagged, typed obscuration, never a shape error nor a scratch;
- scratches (a dark line 0.12 of the disc's radius wide, at least 1 px, and 1.2 radii long, 30 % deep)
  across one lens, and lines through three neighbours: flagged, typed scratch, axis error, one scratch
  reported per line;
- a cover-glass shadow (a spot fixed on the sensor, 40 % of a sub-image, 20 % deep) in two frames of one
  array at stage positions three lenses apart (`--sensor-dust`'s logic, the stage positions as sidecars
  give them), with an array spot: the shadow reported once as the sensor's with 0 lens flags from it, the
  array's spot kept on the same lens in both frames.

    python bench/real_defects.py                  # Table 1 small (square, hex) and the microscope fixture
    python bench/real_defects.py --quick          # noise 0 and 1 %, the small cameras
    python bench/real_defects.py -c fixtures/lfm_40x_relay.toml

16 lenses of each kind per frame, two lenses apart, at least three in from the edge.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))

import analytic_frames as am  # noqa: E402
from instruments import analytic_model, write_frame  # noqa: E402

from mlaqc.inspection.pipeline import inspect_file  # noqa: E402
from mlaqc.inspection.sensor_dust import sensor_shadows  # noqa: E402
from mlaqc.optics.config import load_config  # noqa: E402

CAMERAS = ("fixtures/small_camera.toml", "fixtures/hex_small_camera.toml", "fixtures/lfm_40x_relay.toml")
SHAPE_TYPES = {"pitch", "decenter", "position", "radius", "thickness", "tilt"}


def sites(model: am.AnalyticModel, count: int = 16) -> list[tuple[int, int]]:
    """`count` lenses spread over the array, three or more in from its edge, two or more apart."""
    rows, cols = model.lenses
    step = max(3, int(math.sqrt((rows - 6) * (cols - 6) / count)))
    return [(m, n) for m in range(3, rows - 3, step) for n in range(3, cols - 3, step)][:count]


def inspect(cfg, model, anomalies, noise: float, tmp: Path, name: str = "frame"):
    rng = np.random.default_rng(11)
    return inspect_file(write_frame(tmp / f"{name}.tif", model.with_anomalies(anomalies).render(), cfg, noise, rng), cfg)


def spot_row(cfg, model, noise, area, depth, tmp) -> str:
    rng = np.random.default_rng(5)
    seeded = [am.Anomaly(m, n, "spot", depth, float(rng.uniform(0, 360)), area) for m, n in sites(model)]
    r = inspect(cfg, model, seeded, noise, tmp)
    found = {(d.m - 1, d.n - 1): d for d in r.defects}
    hits = [found.get((a.row, a.col)) for a in seeded]
    typed = sum(d is not None and d.error_type == "obscuration" for d in hits)
    wrong = sorted({d.error_type for d in hits if d is not None} & (SHAPE_TYPES | {"scratch"}))
    false = len(set(found) - {(a.row, a.col) for a in seeded})
    return (f"spot {area:.0%} at {depth:.0%}: flagged {sum(d is not None for d in hits)}/16, obscuration {typed}/16, "
            f"shape or scratch {wrong or 'none'}, other lenses flagged {false}")


def scratch_row(cfg, model, noise, tmp, through: int = 1) -> str:
    rng = np.random.default_rng(6)
    r0 = model.radius_px
    width = max(1.0, 0.12 * r0)
    length = 1.2 * r0 if through == 1 else (through - 1) * model.pitch_px + 1.2 * r0
    keys = sites(model, 16 if through == 1 else 9)
    axis = [0.0 if through > 1 else float(rng.uniform(0, 180)) for _ in keys]  # a longer line: along its row
    seeded = [am.Anomaly(m, n, "scratch", 0.3, t, length_px=length, width_px=width) for (m, n), t in zip(keys, axis)]
    r = inspect(cfg, model, seeded, noise, tmp)
    found = {(d.m - 1, d.n - 1): d for d in r.defects}
    half = through // 2
    crossed = {(m, n + k) for m, n in keys for k in range(-half, half + 1)}
    hits = [found.get(k) for k in crossed]
    typed = [d for d in hits if d is not None and d.error_type == "scratch"]
    errs = [abs((found[(a.row, a.col)].direction_deg - a.direction_deg + 90) % 180 - 90) for a in seeded
            if (a.row, a.col) in found and found[(a.row, a.col)].error_type == "scratch"]
    wrong = sorted({d.error_type for d in hits if d is not None} & SHAPE_TYPES)
    notes = sum(n.startswith("scratch:") for n in r.notes)
    return (f"scratch through {through} lens{'es' if through > 1 else ''} ({width:.1f} x {length:.0f} px, 30 %): "
            f"lenses flagged {sum(d is not None for d in hits)}/{len(crossed)}, scratch {len(typed)}/{len(crossed)}, "
            f"axis error max {max(errs) if errs else float('nan'):.1f}°, shape types {wrong or 'none'}, "
            f"scratches reported {notes} (of {len(keys)}), other lenses flagged {len(set(found) - crossed)}")


def dust_row(cfg, model, noise, tmp) -> str:
    """Two frames three lenses apart (the shift along x), a sensor shadow and an array spot; the array
    larger than the sensor (counts 'auto', lenses numbered from the frame), so the stage positions decide."""
    cfg = auto_counts(cfg, tmp)
    rows, cols = model.lenses
    model = dataclasses.replace(model, lenses=(rows + 8, cols + 8))
    pitch = model.pitch_px
    h, w = model.shape
    shadow = am.SensorSpot(w * 0.55 + 0.3, h * 0.45 + 0.7, 0.63 * model.radius_px, 0.2)
    spot = am.Anomaly(model.lenses[0] // 2 + 2, model.lenses[1] // 2 - 4, "spot", 0.15, 200.0, 0.25)
    results = []
    for k, dx in enumerate((-1.5 * pitch, 1.5 * pitch)):
        moved = dataclasses.replace(model, phase_px=(model.phase_px[0] + dx, model.phase_px[1]), sensor_spots=(shadow,))
        results.append(inspect(cfg, moved, [spot], noise, tmp, f"pos{k}"))
    stage = [{"stage_position_mm": [0.0, 0.0]}, {"stage_position_mm": [3 * cfg.mla.pitch_um / 1000.0, 0.0]}]
    shadows, cleared, _ = sensor_shadows(results, stage, cfg)
    at = [[d for d in r.defects if math.hypot(d.indexes.get("spot_x_px", -1e9) - shadow.x_px,
                                              d.indexes.get("spot_y_px", -1e9) - shadow.y_px) < 3] for r in cleared]
    kept = [sorted((d.m, d.n, d.error_type) for d in r.defects) for r in cleared]
    where = f" at {shadows[0].x_px:.1f}, {shadows[0].y_px:.1f} (true {shadow.x_px:.1f}, {shadow.y_px:.1f})" if shadows else ""
    return (f"sensor shadow, two frames 3 lenses apart: {len(shadows)} sensor shadow(s){where}; lens flags from it "
            f"{sum(map(len, at))}; lenses kept per frame {kept}")


def auto_counts(cfg, tmp: Path):
    """`cfg` with count_w = count_h = "auto" (through its TOML, as a user writes it)."""
    from mlaqc.optics.config import config_to_toml

    text = config_to_toml(cfg)
    lines = [('count_w = "auto"' if ln.startswith("count_w") else 'count_h = "auto"' if ln.startswith("count_h") else ln)
             for ln in text.splitlines()]
    (tmp / "auto.toml").write_text("\n".join(lines) + "\n")
    return load_config(tmp / "auto.toml")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", "-c", action="append", help="a camera (default: three)")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    noises = (0.0, 0.01) if args.quick else (0.0, 0.01, 0.03)
    cams = args.config or (CAMERAS[:2] if args.quick else CAMERAS)
    with tempfile.TemporaryDirectory() as tmp:
        for path in cams:
            cfg = load_config(ROOT / path if not Path(path).is_absolute() else path)
            model = analytic_model(cfg)
            print(f"\n{Path(path).stem}: {cfg.mla.count_h} x {cfg.mla.count_w} lenses, {cfg.mla.packing}, sub-image "
                  f"pitch {cfg.layout.subimage_pitch_px:.2f} px, disc radius {model.radius_px:.1f} px", flush=True)
            for noise in noises:
                t0 = time.perf_counter()
                rows = [spot_row(cfg, model, noise, a, dp, Path(tmp)) for a in (0.1, 0.25, 0.5) for dp in (0.1, 0.2)]
                rows += [scratch_row(cfg, model, noise, Path(tmp)), scratch_row(cfg, model, noise, Path(tmp), 3),
                         dust_row(cfg, model, noise, Path(tmp))]
                print(f"  noise {noise:.0%} ({time.perf_counter() - t0:.0f} s)")
                for row in rows:
                    print(f"    {row}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
