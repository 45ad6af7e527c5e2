"""Scaling benchmark: time and peak memory against work, each case in its own process so its peak
resident memory (ru_maxrss) is its own.

- rays: one white render of 10^6 ... 10^8 rays (10^9 with --huge) on the Table 1 camera — cost linear,
  memory flat;
- lens count: the Table 1 camera (102 x 102 lenses, 2048^2 px) against a 408 x 408-lens MLA on an
  8192^2 sensor (same optics): tracer ns/ray, inspection time per lens, peak memory, and the report set's
  rendering and writing (report.json, lenses.csv, the maps) per lens;
- frames in a batch: 1, 4, 16 frames of 2048^2 px inspected with one reused calibration — seconds per
  frame constant, memory bounded.

    python bench/scaling.py            # a few minutes on 2 cores (first run renders and caches frames)
    python bench/scaling.py --huge     # adds the 10^9-ray render
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CACHE = Path(tempfile.gettempdir()) / "mlaqc_bench_scaling"


def config(lenses: int):
    """The Table 1 camera with a lenses x lenses MLA on a sensor 20 px per lens wide (2048 for 102)."""
    from mlaqc.optics.config import default_config

    cfg = default_config()
    if lenses == cfg.mla.count_w:
        return cfg
    side = 2048 * lenses // 102
    return dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, count_w=lenses, count_h=lenses),
                               sensor=dataclasses.replace(cfg.sensor, width_px=side, height_px=side))


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


# ----------------------------------------------------------------------------- cases (run in a child)

def case_rays(rays: int, lenses: int = 102) -> dict:
    """One white render of `rays` rays with 200 defective lenses (after a warm-up render)."""
    from mlaqc.optics.errormap import random_defects
    from mlaqc.optics.render import Renderer
    from mlaqc.optics.scene import WhiteScene

    cfg = config(lenses)
    r = Renderer(cfg, random_defects(lenses, lenses, 200, seed=3))
    r.render(WhiteScene(), rays=200_000, seed=0)
    base = peak_mib()
    t = time.perf_counter()
    res = r.render(WhiteScene(), rays=rays, seed=1)
    dt = time.perf_counter() - t
    return {"seconds": dt, "mrays_s": res.rays_traced / dt / 1e6, "ns_per_ray": dt / res.rays_traced * 1e9,
            "base_mib": base, "peak_mib": peak_mib(), "image_mib": res.photons.nbytes / 2 ** 20}


def frame_paths(lenses: int, count: int) -> list[Path]:
    """`count` raw frames of the camera with 40 seeded defects (one render, independent sensor noise)."""
    import numpy as np

    from mlaqc.inspection.raw_write import write_raw
    from mlaqc.optics.errormap import random_defects
    from mlaqc.optics.render import Renderer
    from mlaqc.optics.scene import WhiteScene
    from mlaqc.optics.sensor import expose, white_level

    cfg = config(lenses)
    CACHE.mkdir(exist_ok=True)
    paths = [CACHE / f"frame_{lenses}_{i}.tif" for i in range(count)]
    if all(p.exists() for p in paths):
        return paths
    photons_path = CACHE / f"photons_{lenses}.npy"
    if photons_path.exists():
        photons = np.load(photons_path)
    else:
        rpp = 50 if lenses <= 102 else 10
        photons = Renderer(cfg, random_defects(lenses, lenses, 40 * (lenses // 102) ** 2, seed=77)).render(
            WhiteScene(), rays_per_pixel=rpp, seed=77).photons.astype(np.float32)
        np.save(photons_path, photons)
    s = cfg.sensor
    for i, p in enumerate(paths):
        if not p.exists():
            write_raw(p, expose(photons, s, seed=100 + i), bits=s.bit_depth, black_level=s.black_level_dn,
                      white_level=white_level(s))
    return paths


def case_prepare(lenses: int, frames: int) -> dict:
    """Render and cache the frames, the reference model and the signature table (not timed)."""
    from mlaqc.models.reference import reference_model
    from mlaqc.models.signatures import signature_table

    cfg = config(lenses)
    frame_paths(lenses, frames)
    reference_model(cfg), signature_table(cfg)
    return {}


def case_calibrate(lenses: int) -> dict:
    """Calibrate the first frame (load excluded) and save its grid for the inspection cases."""
    from mlaqc.inspection.calibrate import calibrate
    from mlaqc.inspection.pipeline import load_frame

    cfg = config(lenses)
    img = load_frame(frame_paths(lenses, 1)[0], cfg)
    base = peak_mib()
    t = time.perf_counter()
    grid = calibrate(img, expected_pitch_px=cfg.layout.subimage_pitch_px, expected_shape=(lenses, lenses))
    dt = time.perf_counter() - t
    grid.save(CACHE / f"grid_{lenses}.json")
    return {"seconds": dt, "base_mib": base, "peak_mib": peak_mib(), "rms_px": grid.rms_residual_px}


def case_inspect(lenses: int, frames: int) -> dict:
    """Inspect `frames` frames (load + divide + indexes + identify) on the saved grid, after a warm-up."""
    from mlaqc.inspection.calibrate import load_grid
    from mlaqc.inspection.pipeline import inspect_image, load_frame

    cfg = config(lenses)
    paths = frame_paths(lenses, frames)
    grid = load_grid(CACHE / f"grid_{lenses}.json")
    inspect_image(load_frame(paths[0], cfg), cfg, grid=grid)  # warm-up (Numba, FFT plans, models)
    base = peak_mib()
    t = time.perf_counter()
    flagged = []
    for p in paths:
        res = inspect_image(load_frame(p, cfg), cfg, grid=grid)
        flagged.append(len(res.defects))
        del res
    dt = time.perf_counter() - t
    return {"seconds": dt, "per_frame_s": dt / frames, "us_per_lens": dt / frames / lenses ** 2 * 1e6,
            "flagged": flagged, "base_mib": base, "peak_mib": peak_mib()}


def case_report(lenses: int) -> dict:
    """Render and write one frame's report set (inspected on the saved grid first, untimed)."""
    from mlaqc.inspection.calibrate import load_grid
    from mlaqc.inspection.pipeline import inspect_image, load_frame
    from mlaqc.report import render_report, write_report_files

    cfg = config(lenses)
    grid = load_grid(CACHE / f"grid_{lenses}.json")
    res = inspect_image(load_frame(frame_paths(lenses, 1)[0], cfg), cfg, grid=grid)
    render_report(res, cfg.to_dict())  # warm-up (the formatter's kernels, the first PNG's pool)
    base = peak_mib()
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        paths = write_report_files(render_report(res, cfg.to_dict()), Path(tmp) / "report")
        dt = time.perf_counter() - t
        written = sum(p.stat().st_size for p in paths.values())
    return {"seconds": dt, "us_per_lens": dt / lenses ** 2 * 1e6, "mb": written / 1e6, "base_mib": base,
            "peak_mib": peak_mib()}


CASES = {"rays": case_rays, "prepare": case_prepare, "calibrate": case_calibrate, "inspect": case_inspect,
         "report": case_report}


def child(name: str, *args: int) -> dict:
    """Run one case in a fresh interpreter; its result as a dict."""
    cmd = [sys.executable, __file__, "--case", name, *map(str, args)]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"case {name} {args} failed:\n{out.stderr.strip()}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--huge", action="store_true", help="also trace 10^9 rays")
    ap.add_argument("--case", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.case:
        print(json.dumps(CASES[args.case[0]](*map(int, args.case[1:]))))
        return 0
    print(f"machine: {os.cpu_count()} cores; each case in its own process; peak = max resident set (MiB)")
    print("\nrays (Table 1 camera, 200 defective lenses, white scene, all cores):")
    print(f"  {'rays':>14s} {'seconds':>8s} {'M rays/s':>9s} {'ns/ray':>7s} {'peak MiB':>9s} (image {'MiB':s})")
    for rays in (10 ** 6, 10 ** 7, 10 ** 8) + ((10 ** 9,) if args.huge else ()):
        r = child("rays", rays)
        print(f"  {rays:>14,d} {r['seconds']:8.2f} {r['mrays_s']:9.2f} {r['ns_per_ray']:7.1f} {r['peak_mib']:9.0f} "
              f"({r['image_mib']:.0f})")
    print("\nlens count (same optics; 20 px per lens):")
    print(f"  {'MLA':>9s} {'sensor':>11s} {'tracer ns/ray':>13s} {'tracer peak':>11s} {'calibrate s':>11s} "
          f"{'calib. peak':>11s} {'inspect s':>9s} {'µs/lens':>7s} {'inspect peak':>12s} {'report s':>8s} "
          f"{'µs/lens':>7s} {'MB':>5s} {'report peak':>11s}")
    for lenses in (102, 408):
        side = 2048 * lenses // 102
        r = child("rays", 10 ** 8, lenses)
        child("prepare", lenses, 1)
        c = child("calibrate", lenses)
        q = child("inspect", lenses, 1)
        w = child("report", lenses)
        print(f"  {lenses:>4d}x{lenses:<4d} {side:>5d}x{side:<5d} {r['ns_per_ray']:13.1f} {r['peak_mib']:11.0f} "
              f"{c['seconds']:11.3f} {c['peak_mib']:11.0f} {q['per_frame_s']:9.3f} {q['us_per_lens']:7.1f} "
              f"{q['peak_mib']:12.0f} {w['seconds']:8.3f} {w['us_per_lens']:7.1f} {w['mb']:5.0f} {w['peak_mib']:11.0f}")
    print("\nframes in a batch (2048^2, 10,404 lenses, grid reused; load + divide + indexes + identify):")
    print(f"  {'frames':>6s} {'seconds':>8s} {'s/frame':>8s} {'peak MiB':>9s}")
    child("prepare", 102, 16)
    child("calibrate", 102)
    for frames in (1, 4, 16):
        q = child("inspect", 102, frames)
        print(f"  {frames:6d} {q['seconds']:8.2f} {q['per_frame_s']:8.3f} {q['peak_mib']:9.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
