"""Sampler benchmark (issue #13): pixel noise of a white image against rays, low-discrepancy (Sobol,
stratified per microlens) vs plain Monte-Carlo, the noise-equivalent throughput, and the full-frame bar.

    python bench/sampling.py            # the noise table and docs/sampling_noise.png (about 3 minutes)
    python bench/sampling.py --frame    # + the 2048^2 Table 1 frame at the budget that beats the sensor
                                        #   (two renders of about 1.5 minutes each)

Noise: two renders that differ only in the seed; per lit pixel (above half the 99th percentile) the
difference over sqrt(2) relative to the pixel's mean, RMS over the pixels. The small camera has the Table 1
optics (its 24 x 24 central lenses), so per-pixel noise is the full camera's. The sensor's own shot noise
at 80 % of full well is 1/sqrt(0.8 * full_well_e) (0.79 % for Table 1): a render whose sampling noise is
below it adds less than the sensor does, and the frame then stands in for a capture.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from mlaqc.optics.config import default_config, load_config
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene

ROOT = Path(__file__).resolve().parent.parent
SMALL = load_config(ROOT / "fixtures" / "small_camera.toml")
BUDGETS = (10, 25, 50, 100, 200, 400, 1000, 2000)


def relative_noise(a: np.ndarray, b: np.ndarray) -> float:
    """RMS over lit pixels of one render's deviation relative to the pixel's mean (from two seeds)."""
    m = 0.5 * (a + b)
    lit = m > 0.5 * np.percentile(m, 99)
    return float(np.sqrt(np.mean(((a - b)[lit] / (np.sqrt(2.0) * m[lit])) ** 2)))


def measure(cfg, sampler: str, rpp: float) -> tuple[float, float, int]:
    """(relative noise, M rays/s wall on all cores, rays per render) at `rpp` rays per pixel."""
    r = Renderer(cfg, sampler=sampler)
    t = time.perf_counter()
    a = r.render(WhiteScene(), rays_per_pixel=rpp, seed=1)
    dt = time.perf_counter() - t
    b = r.render(WhiteScene(), rays_per_pixel=rpp, seed=2)
    return relative_noise(a.photons, b.photons), a.rays_traced / dt / 1e6, a.rays_traced


def table() -> list[tuple]:
    Renderer(SMALL).render(WhiteScene(), rays=10_000, seed=0)  # compile both paths first
    Renderer(SMALL, sampler="random").render(WhiteScene(), rays=10_000, seed=0)
    rows = []
    print("rays/px | noise MC | noise Sobol | ratio | M rays/s MC | M rays/s Sobol | noise-equivalent M rays/s")
    for rpp in BUDGETS:
        n_mc, s_mc, _ = measure(SMALL, "random", rpp)
        n_qm, s_qm, _ = measure(SMALL, "sobol", rpp)
        ratio = n_mc / n_qm
        rows.append((rpp, n_mc, n_qm, ratio, s_mc, s_qm))
        print(f"{rpp:7d} | {100 * n_mc:7.3f} % | {100 * n_qm:9.3f} % | {ratio:5.2f} | {s_mc:11.1f} | {s_qm:14.1f} | "
              f"{s_qm * ratio ** 2:10.0f}", flush=True)
    return rows


def loglog_png(rows, path: Path, floor: float) -> None:
    """Noise against rays per pixel for both samplers, log-log, drawn with OpenCV (no plotting library)."""
    import cv2

    w, h, left, bottom, top, right = 760, 520, 80, 60, 40, 30
    img = np.full((h, w, 3), 255, np.uint8)
    x_lo, x_hi = math.log10(5), math.log10(5000)
    y_lo, y_hi = math.log10(0.001), math.log10(0.5)

    def px(rpp, noise):
        x = left + (math.log10(rpp) - x_lo) / (x_hi - x_lo) * (w - left - right)
        y = h - bottom - (math.log10(noise) - y_lo) / (y_hi - y_lo) * (h - bottom - top)
        return int(round(x)), int(round(y))

    grey, black, font = (210, 210, 210), (0, 0, 0), cv2.FONT_HERSHEY_SIMPLEX
    for dec in (10, 100, 1000):
        cv2.line(img, px(dec, 0.001), px(dec, 0.5), grey, 1)
        cv2.putText(img, str(dec), (px(dec, 0.001)[0] - 12, h - bottom + 22), font, 0.5, black, 1, cv2.LINE_AA)
    for val, label in ((0.001, "0.1 %"), (0.01, "1 %"), (0.1, "10 %")):
        cv2.line(img, px(5, val), px(5000, val), grey, 1)
        cv2.putText(img, label, (8, px(5, val)[1] + 5), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.rectangle(img, (left, top), (w - right, h - bottom), black, 1)
    cv2.line(img, px(5, floor), px(5000, floor), (0, 150, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "sensor shot noise at 80 % of full well", (px(6, floor)[0], px(6, floor)[1] - 6), font, 0.45,
                (0, 150, 0), 1, cv2.LINE_AA)
    for col, idx, name in (((40, 40, 200), 1, "plain Monte-Carlo"), ((200, 90, 20), 2, "Sobol, per microlens")):
        pts = [px(r[0], r[idx]) for r in rows]
        cv2.polylines(img, [np.array(pts, np.int32)], False, col, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 4, col, -1, cv2.LINE_AA)
        y = top + 20 + 22 * (idx - 1)
        cv2.line(img, (w - 250, y - 5), (w - 220, y - 5), col, 2)
        cv2.putText(img, name, (w - 212, y), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.putText(img, "white-image pixel noise vs rays per pixel (Table 1 optics, same rays for both)", (left, 25), font,
                0.5, black, 1, cv2.LINE_AA)
    cv2.putText(img, "rays per pixel", (w // 2 - 50, h - 15), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.imwrite(str(path), img)


def budget_for(rows, target: float) -> float:
    """Rays per pixel at which the Sobol noise falls to `target`, from the table's last two budgets (log-log)."""
    (r1, _, n1, *_), (r2, _, n2, *_) = rows[-2], rows[-1]
    slope = math.log(n2 / n1) / math.log(r2 / r1)
    return r2 * (target / n2) ** (1.0 / slope)


def full_frame(rows, floor: float) -> None:
    """The bar: a 2048^2 Table 1 frame whose sampling noise is below the sensor's. The whole field is a
    little noisier than the small camera's centre (vignetted corners, off-axis lenses), so the budget is
    taken from a 100 rays/pixel pair of the full frame and the table's slope, with a 10 % margin."""
    cfg = default_config()
    r = Renderer(cfg)
    probe = relative_noise(*(r.render(WhiteScene(), rays_per_pixel=100, seed=s).photons for s in (3, 4)))
    (r1, _, n1, *_), (r2, _, n2, *_) = rows[-2], rows[-1]
    slope = math.log(n2 / n1) / math.log(r2 / r1)
    rpp = math.ceil(100 * (0.9 * floor / probe) ** (1.0 / slope))
    t = time.perf_counter()
    a = r.render(WhiteScene(), rays_per_pixel=rpp, seed=1)
    dt = time.perf_counter() - t
    b = r.render(WhiteScene(), rays_per_pixel=rpp, seed=2)
    noise = relative_noise(a.photons, b.photons)
    print(f"\n2048 x 2048 Table 1 white frame, Sobol: {100 * probe:.2f} % at 100 rays/pixel, so {rpp} rays/pixel "
          f"({a.rays_traced / 1e9:.2f} G rays): {dt:.1f} s ({a.rays_traced / dt / 1e6:.1f} M rays/s); sampling noise "
          f"{100 * noise:.3f} % vs the sensor's shot noise at 80 % of full well {100 * floor:.3f} % -> "
          f"{'below' if noise < floor else 'ABOVE'}; bar 120 s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frame", action="store_true", help="also the full-frame bar (Table 1, 2048^2)")
    args = ap.parse_args()
    floor = 1.0 / math.sqrt(0.8 * default_config().sensor.full_well_e)
    rows = table()
    out = ROOT / "docs" / "sampling_noise.png"
    loglog_png(rows, out, floor)
    print(f"\nlog-log plot: {out.relative_to(ROOT)}; Sobol reaches the sensor's shot noise at 80 % of full well "
          f"({100 * floor:.2f} %) at about {budget_for(rows, floor):.0f} rays/pixel")
    if args.frame:
        full_frame(rows, floor)


if __name__ == "__main__":
    main()
