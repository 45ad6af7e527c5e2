"""How separable are error types in one lens' sub-image? Paired renders (same random draws) of a 9 x 9-lens
patch with one error on the centre lens give its difference image nearly free of Monte-Carlo noise;
this prints each difference's size against the noise of one render, how much of a decenter's
difference a scaled pitch difference leaves unexplained, and how +5 % and -5 % radius errors compare.

    python bench/type_separation.py                       # white image, 300 rays/pixel
    python bench/type_separation.py --defocus-mm -4 --texture-px 8   # a textured object moved 4 mm
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np
from scipy.ndimage import gaussian_filter

from mlaqc.config import Geometry, default_config
from mlaqc.errormap import ErrorMap
from mlaqc.render import Renderer
from mlaqc.scene import TextureScene, WhiteScene
from mlaqc.signatures import nominal_windows, patch_config

CASES = {"pitch 2 µm": dict(pitch_um=2.0, pitch_dir_deg=0.0), "decenter 5 µm": dict(decenter_um=5.0, decenter_dir_deg=0.0),
         "radius +5 %": dict(radius_front_rel=0.05, radius_back_rel=0.05),
         "radius -5 %": dict(radius_front_rel=-0.05, radius_back_rel=-0.05)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--defocus-mm", type=float, default=0.0, help="move the object plane (0: white image)")
    ap.add_argument("--texture-px", type=float, default=8.0, help="texture smoothing, in texels (textured runs)")
    ap.add_argument("--rays-per-pixel", type=float, default=300.0)
    args = ap.parse_args()
    base = default_config()
    lay = base.layout
    geo = Geometry(object_distance_mm=lay.object_distance_mm + args.defocus_mm, mla_distance_mm=lay.mla_distance_mm)
    cfg = patch_config(dataclasses.replace(base, geometry=geo))
    scene = WhiteScene()
    if args.defocus_mm:
        tex = gaussian_filter(np.random.default_rng(0).random((600, 600)), args.texture_px)
        scene = TextureScene((tex - tex.min()) / np.ptp(tex))
    c = 4

    def window(errors: ErrorMap, seed: int = 5) -> np.ndarray:
        img = Renderer(cfg, errors).render(scene, rays_per_pixel=args.rays_per_pixel, seed=seed).photons
        return nominal_windows(img, cfg)[0][c, c].ravel()

    nominal = window(ErrorMap.zeros(9, 9))
    sigma = np.std(window(ErrorMap.zeros(9, 9), seed=6) - nominal) / np.sqrt(2)  # one render's noise per pixel
    diff = {name: window(ErrorMap.zeros(9, 9).with_lens(c + 1, c + 1, **kw)) - nominal for name, kw in CASES.items()}
    print(f"{'scene':s}: {'white' if not args.defocus_mm else f'texture, object moved {args.defocus_mm:+g} mm'}; "
          f"{args.rays_per_pixel:g} rays/pixel; noise {sigma:.3g} per pixel of one render; window {nominal.size} px")
    for name, d in diff.items():
        print(f"  {name:14s} difference: {np.sqrt(np.mean(d * d)) / sigma:5.2f} noise rms per pixel, "
              f"{np.linalg.norm(d) / sigma:6.1f} noise over the window")
    p, q = diff["pitch 2 µm"], diff["decenter 5 µm"]
    a = p @ q / (p @ p)
    print(f"  decenter = {a:.3f} x pitch + residual of {np.linalg.norm(q - a * p) / sigma:.1f} noise over the window "
          f"(cosine {p @ q / np.linalg.norm(p) / np.linalg.norm(q):.4f})")
    r1, r2 = diff["radius +5 %"], diff["radius -5 %"]
    print(f"  cosine(radius +5 %, radius -5 %) = {r1 @ r2 / np.linalg.norm(r1) / np.linalg.norm(r2):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
