"""Assembly readings on the Table 1 camera (issue 24 part 2 bars), or on another camera (-c, e.g. the Table 1
hex array: fixtures/hex_camera.toml): python bench/assembly.py [-c CONFIG] [--rays-per-pixel R]"""

import argparse
import time

from mlaqc.inspection.assembly import FIELDS, measure_assembly
from mlaqc.models.assembly_model import assembly_model, render_grid
from mlaqc.optics.config import load_config

BARS = {"mla_sensor_distance_um": 3.0, "mla_rotation_deg": 0.01, "mla_tilt_x_deg": 0.1, "mla_tilt_y_deg": 0.1,
        "mla_shift_x_um": 3.0, "mla_shift_y_um": 3.0}
ALL = {"mla_sensor_distance_um": 15.0, "mla_rotation_deg": 0.3, "mla_tilt_x_deg": 0.3, "mla_tilt_y_deg": -0.2,
       "mla_shift_x_um": 20.0, "mla_shift_y_um": -12.0}


def read(cfg, rpp, seed, glob):
    return measure_assembly(render_grid(cfg, glob, rays_per_pixel=rpp, seed=seed), cfg)


def show(name, glob, a):
    ok = True
    print(f"\n{name}")
    for k in FIELDS:
        t = glob.get(k, 0.0)
        err = a.value(k) - t
        z = err / a.sigma[k] if a.sigma[k] > 0 else float("inf")
        good = abs(err) <= BARS[k] and abs(z) <= 3
        ok &= good
        print(f"  {k:24s} true {t:+9.4f} read {a.value(k):+9.4f} ± {a.sigma[k]:.4f}  err {err:+.4f} ({z:+.1f} σ)  "
              f"{'ok' if good else 'MISS'}")
    print(f"  distance from focus: {a.distance_from_focus_um:+.3f} ± {a.distance_from_focus_sigma_um:.3f} µm "
          f"(true {glob.get('mla_sensor_distance_um', 0.0):+.1f})")
    return ok


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("-c", "--config", default="fixtures/paper_table1.toml")
    ap.add_argument("--rays-per-pixel", type=float, default=100.0)
    ap.add_argument("--scales", default="0.25,0.5,1,2")
    args = ap.parse_args()
    cfg = load_config(args.config)
    t = time.time()
    model = assembly_model(cfg)
    print(f"assembly model {model.key}: ready in {time.time() - t:.0f} s (pupil {model.pupil_mm:.2f} mm; "
          f"systematic floor {', '.join(f'{v:.2g}' for v in model.systematic)})")
    results = {"all together": show("all together", ALL, read(cfg, args.rays_per_pixel, 1, ALL))}
    results["no global error"] = show("no global error", {}, read(cfg, args.rays_per_pixel, 2, {}))
    for k, v in ALL.items():
        results[k] = show(f"{k} alone", {k: v}, read(cfg, args.rays_per_pixel, 3, {k: v}))
    print("\naccuracy against size (error alone; reading error and sigma):")
    for k, v in ALL.items():
        row = []
        for s in (float(x) for x in args.scales.split(",")):
            a = read(cfg, args.rays_per_pixel, 4, {k: v * s})
            row.append(f"{v * s:+.3g}: {a.value(k) - v * s:+.4f}±{a.sigma[k]:.4f}")
        print(f"  {k:24s} " + "  ".join(row))
    print(f"\nbars: {'PASS' if all(results.values()) else 'FAIL'} ({', '.join(n for n, r in results.items() if not r) or 'all met'}); "
          f"{time.time() - t:.0f} s")


if __name__ == "__main__":
    main()
