"""What a white image can tell at all: the best possible (matched-filter) detection and type separation of
one lens' error, against the noise of a frame at a given ray budget. No detector can beat these figures.

Method: the centre lens of a 9 x 9-lens patch carries the error. Its mean difference image (3 x 3 lenses
around it) is rendered at many rays/pixel in two independent halves; the halves give the difference's own
Monte-Carlo noise, which is removed from its energy (unbiased), so a change too small to see is not
mistaken for one. The frame noise per pixel is measured on two independent exposures (render + sensor)
at the budget asked for. Then:

  detection z   = || difference / noise ||                 (ideal matched filter, known error)
  separation z  = || (decenter - best pitch fit) / noise ||  (pitch fitted over magnitude and direction)

    python bench/type_separation.py [--rays-per-pixel 50] [--truth-rpp 3000]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from mlaqc.models.signatures import patch_config
from mlaqc.optics.config import default_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene
from mlaqc.optics.sensor import expose

C = 4  # centre lens of the 9 x 9 patch
RADIUS = (-0.1, -0.05, -0.03, 0.03, 0.05, 0.08, 0.1, 0.12, 0.15)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays-per-pixel", type=float, default=50.0, help="budget of the frame judged (default: inspection's)")
    ap.add_argument("--truth-rpp", type=float, default=3000.0, help="rays/pixel of each half of the noise-free renders")
    args = ap.parse_args()
    cfg = patch_config(default_config())
    pitch_px = cfg.layout.subimage_pitch_px
    side = cfg.sensor.width_px
    lo = int(round((side - 1) / 2 - 1.5 * pitch_px))
    cut = (slice(lo, lo + int(round(3 * pitch_px))),) * 2  # the 3 x 3 lenses around the centre one

    def render(errors: ErrorMap, rpp: float, seed: int) -> np.ndarray:
        return Renderer(cfg, errors).render(WhiteScene(), rays_per_pixel=rpp, seed=seed).photons

    nominal = [render(ErrorMap.zeros(9, 9), args.truth_rpp, s) for s in (11, 12)]
    scale = float(np.median(nominal[0][cut]))
    frames = [expose(render(ErrorMap.zeros(9, 9), args.rays_per_pixel, s), cfg.sensor, seed=s).astype(float)
              for s in (21, 22)]
    black = cfg.sensor.black_level_dn
    frames = [(f - black) / np.median((f - black)[cut]) for f in frames]
    # noise variance per pixel grows with its level (photon and ray counts): var = gain x level + floor
    level = np.clip(0.5 * (nominal[0] + nominal[1])[cut] / scale, 0.0, None)
    pair_var = 0.5 * (frames[0][cut] - frames[1][cut]) ** 2
    gain, floor = np.linalg.lstsq(np.stack([level.ravel(), np.ones(level.size)], 1), pair_var.ravel(), rcond=None)[0]
    var = np.maximum(gain * level + floor, 1e-3 * gain)

    def difference(**fields) -> tuple[np.ndarray, float]:
        """Mean difference image (relative units) and the energy of its own noise (same units, squared)."""
        em = ErrorMap.zeros(9, 9).with_lens(C + 1, C + 1, **fields)
        halves = [(render(em, args.truth_rpp, s) - n)[cut] / scale for s, n in zip((11, 12), nominal)]
        return 0.5 * (halves[0] + halves[1]), float(np.sum((halves[0] - halves[1]) ** 2 / var)) / 4

    def z(d: np.ndarray, noise_energy: float) -> float:
        return float(np.sqrt(max(np.sum(d * d / var) - noise_energy, 0.0)))

    print(f"frame noise {100 * np.sqrt(gain + floor):.2f} % of the white level per white pixel at {args.rays_per_pixel:g} rays/pixel "
          f"(render + sensor); truth renders 2 x {args.truth_rpp:g} rays/pixel; 3 x 3 lenses, {cut[0].stop - lo} px square")
    print("ideal detection z of one lens' error (matched filter, error known):")
    for r in RADIUS:
        print(f"  radius {100 * r:+5.0f} %: {z(*difference(radius_front_rel=r, radius_back_rel=r)):6.1f}")
    pitch = {(m, a): difference(pitch_um=m, pitch_dir_deg=a) for m in (1.0, 2.0, 3.0) for a in (0.0, 90.0)}
    for m in (1.0, 2.0, 3.0):
        print(f"  pitch {m:g} µm: {z(*pitch[(m, 0.0)]):6.1f}")
    for m in (2.0, 5.0, 10.0):
        dec, e_dec = difference(decenter_um=m, decenter_dir_deg=0.0)
        best = np.inf
        for p in (1.0, 2.0, 3.0):  # pitch of any size (scaled) and direction (0/90 degree basis)
            (b0, e0), (b90, e90) = pitch[(p, 0.0)], pitch[(p, 90.0)]
            basis = np.stack([b0.ravel(), b90.ravel()], axis=1)
            wt = 1.0 / np.sqrt(var.ravel())  # least squares in noise units
            coef, *_ = np.linalg.lstsq(basis * wt[:, None], dec.ravel() * wt, rcond=None)
            rest = (dec.ravel() - basis @ coef).reshape(dec.shape)
            best = min(best, z(rest, e_dec + coef[0] ** 2 * e0 + coef[1] ** 2 * e90))
        print(f"  decenter {m:g} µm: detection {z(dec, e_dec):6.1f}, separation from the best pitch {best:6.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
