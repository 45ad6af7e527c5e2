"""Light-field decoding with the array's measured errors against the lattice other tools decode with
(issue #41 bars). A textured scene and a point-source scene, both off the plane the MLA sees in focus (so
that the views differ: parallax), rendered through the camera with the paper's nine example errors plus
random ones, and through the same camera with an error-free array. The flawed frames are decoded with

  (a) the design lattice, (b) the lattice calibrated on the flawed array's white frame (what PlenoptiCam,
  LFToolbox and plenpy do), (c) the measured per-lens model (an inspection's report of that white frame),
  and (c) + fill: the lenses it gives a confidence under 0.5 (a focal error blurring their views by over
  2 px) refilled along the scene's parallax (`fill.filled`, what `mlaqc decode --fill` does);

the error-free frame with its own calibrated lattice. Every decode is devignetted by its array's white.
Each view is compared with the error-free frame's, at the flawed lenses' (s, t) and everywhere else, on
every sample the decode gives any weight, and so are refocused images (PSNR). Noise-free runs also print
two limits no decoder passes: the pixel grid's own (`phase_floor`: the error-free light field itself
decoded from pixels half a pixel across) and an oracle's (`oracle_affine`: each flawed lens resampled by
the affine map that best fits the error-free views). Frames are cached in /tmp.

    python bench/decode.py                                         # Table 1, noise-free and noisy
    python bench/decode.py --config fixtures/hex_camera.toml
    python bench/decode.py --config fixtures/lfm_40x_relay.toml   # the light-field microscope (datasheet optics)
    python bench/decode.py --timing                                # a 2048² frame decoded in-process
    python bench/decode.py --geometry                              # error-free views against exact rays
    python bench/decode.py --plenopticam /tmp/plcvenv/bin/python   # against PlenoptiCam (see plenopticam_decode.py)
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mlaqc.decode.frames import load_decode_frame
from mlaqc.decode.fill import filled
from mlaqc.decode.lightfield import rectangular, refocus, view_offsets
from mlaqc.decode.scene import decode_scene
from mlaqc.decode.sampling import design_sampling, lattice_sampling, measured_sampling, report_grid
from mlaqc.inspection.calibrate import calibrate_for
from mlaqc.inspection.pipeline import inspect_image, load_frame
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap, lens_error_fields, physical_types, random_defects
from mlaqc.optics.scene import PointScene, TextureScene, WhiteScene
from mlaqc.optics.simulate import simulate, write_simulation
from mlaqc.report.document import build_report_dict

sys.path.insert(0, str(Path(__file__).parent))
from paper_examples import NINE, placements  # noqa: E402  (bench/ is on sys.path)

CACHE = Path(tempfile.gettempdir()) / "mlaqc_bench_decode"


def flawed_map(cfg, random_count: int, seed: int) -> tuple[ErrorMap, list[tuple[int, int, str]]]:
    """The paper's nine examples plus `random_count` random pitch/decenter/radius errors elsewhere. On a
    plano-convex MLA a decenter changes nothing: its three examples become pitch errors of that size."""
    rows, cols, packing = cfg.mla.count_h, cfg.mla.count_w, cfg.mla.packing
    types = physical_types(("pitch", "decenter", "radius"), cfg.mla)
    em = random_defects(rows, cols, random_count, seed, types=types, packing=packing)
    for (m, n), (kind, mag, d) in zip(placements(rows, cols, packing), NINE):
        kind = kind if kind in types else "pitch"
        em = em.with_lens(m, n, **lens_error_fields(kind, mag, d))
    flawed = [(int(m) + 1, int(n) + 1) for m, n in zip(*np.nonzero(em.defective()))]
    return em, flawed


def scene_config(cfg, defocus_mm: float):
    """The camera with its object plane moved `defocus_mm` further out, the MLA where it was (an ideal main
    lens: the scene's image `defocus_mm` before the MLA): the scene is out of the MLA's focus, so every view
    sees it from its own pupil point."""
    lay = cfg.layout
    if lay.main is None:
        return dataclasses.replace(cfg, geometry=dataclasses.replace(cfg.geometry, image_defocus_mm=defocus_mm))
    geo = dataclasses.replace(cfg.geometry, mla_distance_mm=lay.mla_distance_mm,
                              object_distance_mm=lay.object_distance_mm + defocus_mm)
    return dataclasses.replace(cfg, geometry=geo)


def texture(size: int = 512, seed: int = 3) -> TextureScene:
    """A band-limited random texture with a few sharp edges: detail at every scale the views resolve."""
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(size)
    fx, fy = np.meshgrid(f, f)
    spectrum = (rng.normal(size=(size, size)) + 1j * rng.normal(size=(size, size))) / (0.02 + np.hypot(fx, fy))
    img = np.real(np.fft.ifft2(spectrum))
    img = (img - img.min()) / np.ptp(img)
    yy, xx = np.mgrid[0:size, 0:size]
    img = 0.6 * img + 0.3 * (((xx // 64) + (yy // 64)) % 2) + 0.1
    return TextureScene(radiance=img / img.max())


def points(cfg, spacing_lenses: float = 7.0) -> PointScene:
    """Point sources on a square lattice over the object plane (an ideal lens: the scene's image plane),
    `spacing_lenses` lens images apart."""
    lay = cfg.layout
    mag = 1.0 if lay.main is None else lay.object_distance_mm / lay.mla_distance_mm  # object mm per image mm
    step = spacing_lenses * cfg.mla.pitch_um * 1e-3 * mag
    half = 0.45 * cfg.mla.count_w * cfg.mla.pitch_um * 1e-3 * mag
    xs = np.arange(-half, half + 1e-9, step)
    pts = tuple((float(x), float(y)) for x in xs for y in xs)
    return PointScene(pts, photons=4e7)


def rendered(cfg, scene, errors: ErrorMap, name: str, rpp: float, noise: bool, seed: int = 11) -> Path:
    """The raw of `scene` through `cfg` with `errors`, rendered once and cached."""
    key = hashlib.sha1(repr((cfg.to_dict(), name, errors.to_json_dict(), rpp, noise, seed)).encode()).hexdigest()[:12]
    path = CACHE / f"{name}_{key}.tiff"
    if not path.exists():
        CACHE.mkdir(exist_ok=True)
        t0 = time.perf_counter()
        sim = simulate(cfg, scene, errors, rays_per_pixel=rpp, seed=seed, noise=noise)
        write_simulation(str(path), sim, cfg)
        print(f"  rendered {name} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    return path


def rms(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> float:
    return float(np.sqrt(np.sum(w * (a - b) ** 2) / max(np.sum(w), 1e-30)))


def psnr(img: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    err = float(np.mean((img[mask] - ref[mask]) ** 2))
    peak = float(np.percentile(ref[mask], 99.5))
    return 10 * np.log10(peak * peak / max(err, 1e-30))


def lens_mask(shape, lenses, grow: int = 0) -> np.ndarray:
    mask = np.zeros(shape, bool)
    for m, n in lenses:
        mask[max(0, m - 1 - grow):m + grow, max(0, n - 1 - grow):n + grow] = True
    return mask


def compare(cfg, scene_name, scene, flawed_em, flawed_lenses, clean_em, rpp, noise, defocus_mm, slope, picture=None):
    scfg = scene_config(cfg, defocus_mm)
    raws = {k: rendered(c, s, e, k if k.startswith("white") else f"{k}_{scene_name}", rpp, noise)
            for k, c, s, e in (("white_flawed", cfg, WhiteScene(), flawed_em), ("white_clean", cfg, WhiteScene(), clean_em),
                               ("scene_flawed", scfg, scene, flawed_em), ("scene_clean", scfg, scene, clean_em))}
    # the white frames are the same for both scenes: one cache entry each
    white_f, white_c = (load_frame(str(raws[k]), cfg) for k in ("white_flawed", "white_clean"))
    grid_f, grid_c = calibrate_for(white_f, cfg), calibrate_for(white_c, cfg)
    report = build_report_dict(inspect_image(white_f, cfg, grid=grid_f), config_dict=cfg.to_dict())
    found = {(d["row"], d["col"]) for d in report["defects"]}
    measured = measured_sampling(report_grid(report, "(in memory)"), report)
    samplings = {"a design": design_sampling(cfg, white_f.shape), "b lattice": lattice_sampling(grid_f),
                 "c measured": measured, "c + fill": measured}
    img_f = load_decode_frame(str(raws["scene_flawed"]), cfg)
    img_c = load_decode_frame(str(raws["scene_clean"]), cfg)
    wf, wc = load_decode_frame(str(raws["white_flawed"]), cfg), load_decode_frame(str(raws["white_clean"]), cfg)
    ref_s = lattice_sampling(grid_c)
    offs = view_offsets(min(s.radius_px for s in samplings.values()))
    ref = rectangular(decode_scene(img_c, ref_s, offs, wc))
    ref_img, _ = refocus(ref, slope)
    rows, cols = ref.spatial_shape
    flawed_mask = lens_mask((cfg.mla.count_h, cfg.mla.count_w), flawed_lenses)
    near = lens_mask((cfg.mla.count_h, cfg.mla.count_w), flawed_lenses, grow=int(np.ceil(abs(slope) * offs[-1])) + 1)
    if ref.packing == "rect":  # compare on the resampled grid: a flawed lens marks the cells it feeds
        flawed_mask = rect_mask(flawed_mask, rows)
        near = rect_mask(near, rows)
    elsewhere = ~near
    kinds = flawed_em.lens_type()
    type_masks = {}
    for t in sorted({kinds[m - 1, n - 1] for m, n in flawed_lenses}):
        mk = lens_mask(flawed_mask.shape if ref.packing != "rect" else kinds.shape,
                       [(m, n) for m, n in flawed_lenses if kinds[m - 1, n - 1] == t])
        type_masks[t] = rect_mask(mk, rows) if ref.packing == "rect" else mk
    print(f"  {scene_name}: {len(flawed_lenses)} flawed lenses ({len(found & set(flawed_lenses))} flagged by the "
          f"inspection, {len(found - set(flawed_lenses))} others), {len(offs)}x{len(offs)} views, refocus slope {slope:g}")
    out = {}
    decoded = {}
    for name, smp in samplings.items():
        lf = decode_scene(img_f, smp, offs, wf)
        dropped = 0 if lf.foreign is None else int(lf.foreign[:, :, lens_mask(kinds.shape, flawed_lenses)].sum())
        if name.endswith("fill"):  # lenses of confidence under 0.5 refilled along the scene's parallax
            lf = filled(lf, lenses=smp.inside)
        lf = rectangular(lf)  # (as `mlaqc decode`: filled on the array's own lattice, then resampled)
        decoded[name] = lf
        w = (lf.weights > 0) & (ref.weights > 0.2)  # every sample the decode gives any weight, however low
        wf_ = w.astype(np.float64)
        at = rms(lf.values, ref.values, wf_ * flawed_mask)
        rest = rms(lf.values, ref.values, wf_ * elsewhere)
        img, den = refocus(lf, slope)
        ok = den > 0.5 * np.median(den)
        p_at = psnr(img, ref_img, ok & near)
        p_rest = psnr(img, ref_img, ok & elsewhere)
        out[name] = (at, rest, p_at, p_rest)
        per_type = ", ".join(f"{t} {rms(lf.values, ref.values, wf_ * m):.4f}" for t, m in type_masks.items())
        print(f"    {name:11s}: view RMS at flawed lenses {at:.4f} ({per_type}), elsewhere {rest:.4f}; refocused "
              f"PSNR near flawed lenses {p_at:.2f} dB, elsewhere {p_rest:.2f} dB")
        if dropped:
            print(f"                 {dropped} of the flawed lenses' samples hold mostly another lens' light: "
                  f"{'refilled' if name.endswith('fill') else 'dropped (not compared)'}")
    if picture is not None and ref.packing == "square":
        before_after(picture, decoded["b lattice"], decoded["c measured"], ref, flawed_em)
    # the render's own error: the error-free frame again with other rays, decoded the same way
    again = load_decode_frame(str(rendered(scfg, scene, clean_em, f"scene_clean_{scene_name}_seed2", rpp, noise, seed=12)), cfg)
    lf = rectangular(decode_scene(again, ref_s, offs, wc))
    wf_ = ((lf.weights > 0) & (ref.weights > 0.2)).astype(np.float64)  # the samples the rows compare
    print(f"    floor      : the error-free frame rendered again with other rays: view RMS at the flawed lenses' "
          f"(s, t) {rms(lf.values, ref.values, wf_ * flawed_mask):.4f}, elsewhere {rms(lf.values, ref.values, wf_ * elsewhere):.4f}")
    if not noise:  # the limits: with noise, another frame's noise would be measured with them
        phase_floor(cfg, scfg, scene_name, scene, clean_em, rpp, offs, ref, flawed_mask, elsewhere, out["b lattice"][0])
        oracle_affine(img_f, wf, measured, ref, flawed_lenses, out["b lattice"][0])
    ab, rb, pb, qb = out["b lattice"]
    for name in ("c measured", "c + fill"):
        ac, rc, pc, qc = out[name]
        print(f"    ({name})/(b) at flawed lenses {ac / ab:.3f} (bar <= 0.333); elsewhere {rc / rb:.4f} (bar <= 1.02); "
              f"refocused PSNR gain near flawed {pc - pb:+.2f} dB, elsewhere {qc - qb:+.2f} dB")
    return out


def before_after(path: str, lattice, measured, ref, em: ErrorMap, half: int = 5) -> None:
    """A PNG: one outer view around the paper's 10 µm decentered lens (at 90°), decoded on the calibrated
    lattice, as measured, and from the error-free array, with each decode's difference from the error-free
    view (x 10), 12 px per lens."""
    import cv2

    rows, cols = em.shape
    m, n = placements(rows, cols)[5]  # NINE[5]: decenter 10 µm at 90°
    k = len(ref.view_offsets_px) // 2
    j, i = k, k + int(round(0.6 * k))  # a view 0.6 of the pupil radius to the right
    win = (slice(m - 1 - half, m + half), slice(n - 1 - half, n + half))
    views = [lf.values[j, i][win] for lf in (lattice, measured, ref)]
    lo, hi = float(np.percentile(views[2], 1)), float(np.percentile(views[2], 99))
    tiles = [np.clip((v - lo) / (hi - lo), 0, 1) for v in views]
    tiles += [np.clip(0.5 + 10 * (v - views[2]) / (hi - lo), 0, 1) for v in views[:2]]
    big = [cv2.resize((255 * t).astype(np.uint8), None, fx=12, fy=12, interpolation=cv2.INTER_NEAREST) for t in tiles]
    labels = ("lattice (b)", "measured (c)", "error-free", "(b) - error-free x10", "(c) - error-free x10")
    for b, text in zip(big, labels):
        cv2.rectangle(b, (half * 12, half * 12), (half * 12 + 11, half * 12 + 11), 255, 1)
        cv2.rectangle(b, (0, 0), (8 + 7 * len(text), 19), 0, -1)
        cv2.putText(b, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, 255, 1, cv2.LINE_AA)
    gap = np.full((big[0].shape[0], 6), 128, np.uint8)
    row = np.hstack([x for b in big for x in (b, gap)][:-1])
    cv2.imwrite(path, row)
    print(f"  wrote {path}: view ({j - k:+d}, {i - k:+d}) px around U({m},{n}), the 10 µm decentered lens (framed)")


def rect_mask(mask: np.ndarray, t_count: int) -> np.ndarray:
    """A hex (rows, cols) lens mask carried to the rectangular grid: a cell is marked if a lens it
    interpolates from is."""
    from mlaqc.decode.lightfield import LightField

    rows, cols = mask.shape
    lf = LightField(mask[None, None].astype(np.float32), np.ones((1, 1, rows, cols), np.float32), np.zeros(1), "hex")
    return rectangular(lf).values[0, 0] > 0


def phase_floor(cfg, scfg, scene_name, scene, clean_em, rpp, offs, ref, flawed_mask, elsewhere, b_at) -> None:
    """The pixel grid's own limit, which no decoder passes: the error-free array on a sensor one pixel wider
    and taller (the sensor stays centred on the axis, so its pixels sit half a pixel across the optics:
    the same light field, sampled at another phase) and on one two pixels larger (a whole pixel: the same
    phase, other rays), each decoded on its own calibrated lattice, against the error-free decode. The
    half-pixel figure less the whole-pixel one in quadrature is the pixel phase's share: a perfect decode
    of a lens whose sub-image moved half a pixel differs from the reference by that much."""
    got = {}
    for grow in (1, 2):
        c = dataclasses.replace(cfg, sensor=dataclasses.replace(cfg.sensor, width_px=cfg.sensor.width_px + grow,
                                                                height_px=cfg.sensor.height_px + grow))
        sc = dataclasses.replace(scfg, sensor=c.sensor)
        white = rendered(c, WhiteScene(), clean_em, f"white_grown{grow}", rpp, False)
        frame = rendered(sc, scene, clean_em, f"scene_grown{grow}_{scene_name}", rpp, False)
        smp = lattice_sampling(calibrate_for(load_frame(str(white), c), c))
        lf = rectangular(decode_scene(load_decode_frame(str(frame), c), smp, offs, load_decode_frame(str(white), c)))
        w = ((lf.weights > 0) & (ref.weights > 0.2)).astype(np.float64)
        got[grow] = tuple(rms(lf.values, ref.values, w * m) for m in (flawed_mask, elsewhere))
    (h_at, h_rest), (o_at, o_rest) = got[1], got[2]
    share = np.sqrt(max(h_at ** 2 - o_at ** 2, 0.0))
    print(f"    pixel phase: the error-free light field from pixels half a pixel across, view RMS at the flawed lenses' "
          f"(s, t) {h_at:.4f} (elsewhere {h_rest:.4f}); a whole pixel across (other rays only) {o_at:.4f} "
          f"({o_rest:.4f}); the phase's share {share:.4f} = {share / b_at:.3f} of (b)")


def oracle_affine(img, white, measured, ref, flawed_lenses, b_at) -> None:
    """A bound on resampling: each flawed lens sampled through the affine map of its view offsets (6
    parameters, from its measured centre) fitted by least squares to the error-free views themselves, an
    oracle no decoder has. What it leaves is not where the lens sends its light but what the lens did to it
    (blur, aberration) and the pixels' phase. Square arrays (U(m,n) indexes the views directly)."""
    from scipy.optimize import least_squares

    from mlaqc.decode.lightfield import bilinear

    if ref.packing != "square":
        return
    o = ref.view_offsets_px
    ou, ov = np.meshgrid(o, o)
    sq_c = sq_fit = n_all = 0.0
    for m, n in flawed_lenses:
        want, w = ref.values[:, :, m - 1, n - 1], ref.weights[:, :, m - 1, n - 1] > 0.2
        x0, y0 = measured.x_px[m - 1, n - 1] + ou, measured.y_px[m - 1, n - 1] + ov

        def resid(p, x0=x0, y0=y0, want=want, w=w):
            xs, ys = x0 + p[0] + p[2] * ou + p[3] * ov, y0 + p[1] + p[4] * ou + p[5] * ov
            v, _ = bilinear(img, xs, ys)
            d, _ = bilinear(white, xs, ys)
            return (np.where(d > 0, v / np.where(d > 0, d, 1.0), 0.0) - want)[w]

        r0 = resid(np.zeros(6))
        fit = least_squares(resid, np.zeros(6), diff_step=1e-3)
        sq_c, sq_fit, n_all = sq_c + np.sum(r0 ** 2), sq_fit + np.sum(fit.fun ** 2), n_all + r0.size
    best = np.sqrt(sq_fit / n_all)
    print(f"    oracle: each flawed lens resampled by the affine map fitted to the error-free views: view RMS "
          f"{best:.4f} at the flawed lenses ({np.sqrt(sq_c / n_all):.4f} unfitted) = {best / b_at:.3f} of (b)")


def timing(cfg, repeats: int = 5) -> None:
    """A full-sensor frame decoded in-process (all views, devignetted, hex resampled), best of `repeats`."""
    em = ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w, cfg.mla.packing)
    path = rendered(cfg, WhiteScene(), em, "white_clean", 50.0, True)
    img = load_decode_frame(str(path), cfg)
    grid = calibrate_for(load_frame(str(path), cfg), cfg)
    smp = lattice_sampling(grid)
    offs = view_offsets(smp.radius_px)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        rectangular(decode_scene(img, smp, offs, img))
        best = min(best, time.perf_counter() - t0)
    print(f"decode of a {img.shape[1]}x{img.shape[0]} frame ({cfg.mla.count_w}x{cfg.mla.count_h} lenses, "
          f"{len(offs)}x{len(offs)} views), with its white's decode and the devignetting: {best:.3f} s (best of {repeats})")


def geometry(defocus_mm: float, rpp: float = 300.0) -> None:
    """The error-free small camera and one point source `defocus_mm` beyond focus: in every view inside 0.8 of
    the pupil's image, the decoded spot's centroid (in lenses) against where the exact ray through that
    view's pupil point meets the MLA (tests/lens_rays.py: Snell's law through the singlet)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    from lens_rays import views_against_rays

    cfg = load_config(str(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml"))
    scfg, obj = scene_config(cfg, defocus_mm), (0.25, -0.15)
    em = ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w)
    white = rendered(cfg, WhiteScene(), em, "small_white", 60.0, False)
    point = rendered(scfg, PointScene((obj,), photons=4e7), em, f"small_point_{defocus_mm:g}", rpp, False)
    smp = lattice_sampling(calibrate_for(load_frame(str(white), cfg), cfg))
    offs = view_offsets(smp.radius_px)
    lf = decode_scene(load_decode_frame(str(point), cfg), smp, offs, load_decode_frame(str(white), cfg))
    got, want = views_against_rays(lf, smp.radius_px, cfg, scfg, obj)
    err = got - want
    slope = [np.polyfit(want[:, k], got[:, k], 1)[0] for k in (0, 1)]
    print(f"point {defocus_mm:g} mm beyond focus, {len(got)} views: decoded - exact rays, s {err[:, 0].mean():+.3f} "
          f"(RMS {np.sqrt(np.mean(err[:, 0] ** 2)):.3f}) lens, t {err[:, 1].mean():+.3f} (RMS "
          f"{np.sqrt(np.mean(err[:, 1] ** 2)):.3f}) lens; slope decoded/exact {slope[0]:.3f}, {slope[1]:.3f}; the views "
          f"span {np.ptp(want[:, 0]):.1f} lenses (paraxial: {2 * 0.8 * smp.radius_px * scene_slope(cfg, defocus_mm):.1f}); "
          "a view sees the point in one lens: quantization alone gives 0.29 lens RMS")


def against_plenopticam(cfg, python: str, defocus_mm: float, rpp: float) -> None:
    """The noise-free flawed and error-free texture frames decoded by PlenoptiCam (bench/plenopticam_decode.py,
    run by `python`, a venv with PlenoptiCam: its docstring says how) and by mlaqc, each devignetted and each
    against its own decode of the error-free frame: view RMS relative to the median view value, every view
    inside the pupil's image, at the flawed lenses and elsewhere; and the time each takes (calibration and
    decode of the flawed pair)."""
    import subprocess

    flawed_em, flawed = flawed_map(cfg, 20, 4)
    clean_em = ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w, cfg.mla.packing)
    scfg, scene = scene_config(cfg, defocus_mm), texture()
    raw = {k: rendered(c, s_, e, k if k.startswith("white") else f"{k}_texture", rpp, False)
           for k, c, s_, e in (("white_flawed", cfg, WhiteScene(), flawed_em), ("white_clean", cfg, WhiteScene(), clean_em),
                               ("scene_flawed", scfg, scene, flawed_em), ("scene_clean", scfg, scene, clean_em))}
    mask = lens_mask((cfg.mla.count_h, cfg.mla.count_w), flawed)
    theirs = {}
    for k in ("flawed", "clean"):
        out = CACHE / f"plenopticam_{k}.npz"
        subprocess.run([python, str(Path(__file__).parent / "plenopticam_decode.py"), "--white", str(raw[f"white_{k}"]),
                        "--scene", str(raw[f"scene_{k}"]), "--out", str(out), "--white-sigma", "2", "--devignette"],
                       check=True, capture_output=True)
        theirs[k] = np.load(out)
    vf, vc = theirs["flawed"]["views"].astype(float), theirs["clean"]["views"].astype(float)
    n = vf.shape[0] // 2
    disc = (np.hypot(*np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1))) <= n + 0.4)[:, :, None, None]
    ok = np.isfinite(vf) & np.isfinite(vc) & (vc > 0) & disc
    inner = mask[1:-1, 1:-1]  # PlenoptiCam drops the outermost ring: its lens (r, c) is U(r + 2, c + 2)
    rel = (vf - vc) / np.median(vc[ok])
    print(f"PlenoptiCam {vf.shape[2]}x{vf.shape[3]} lenses, {vf.shape[0]}x{vf.shape[1]} views: view RMS / median at "
          f"flawed lenses {np.sqrt(np.mean(rel[ok & inner] ** 2)):.4f}, elsewhere {np.sqrt(np.mean(rel[ok & ~inner] ** 2)):.4f}; "
          f"{float(theirs['flawed']['t_total']):.2f} s (calibration {float(theirs['flawed']['t_calibrate']):.2f} s)")
    t0 = time.perf_counter()
    white = load_frame(str(raw["white_flawed"]), cfg)
    grid_f = calibrate_for(white, cfg)
    t_cal = time.perf_counter() - t0
    report = build_report_dict(inspect_image(white, cfg, grid=grid_f), config_dict=cfg.to_dict())
    grid_c = calibrate_for(load_frame(str(raw["white_clean"]), cfg), cfg)
    img = {k: load_decode_frame(str(v), cfg) for k, v in raw.items()}
    offs = view_offsets(0.5 * cfg.layout.subimage_pitch_px)
    ref_s = lattice_sampling(grid_c)
    ref = decode_scene(img["scene_clean"], ref_s, offs, img["white_clean"])
    for name, smp in (("calibrated lattice", lattice_sampling(grid_f)),
                      ("measured", measured_sampling(report_grid(report, "(in memory)"), report))):
        t0 = time.perf_counter()
        lf = decode_scene(img["scene_flawed"], smp, offs, img["white_flawed"])
        t_dec = time.perf_counter() - t0
        ok = (lf.weights > 0) & (ref.weights > 0)
        rel = (lf.values - ref.values) / np.median(ref.values[ok])
        print(f"mlaqc, {name}: view RMS / median at flawed lenses {np.sqrt(np.mean(rel[ok & mask] ** 2)):.4f}, elsewhere "
              f"{np.sqrt(np.mean(rel[ok & ~mask] ** 2)):.4f}; calibration {t_cal:.2f} s + decode {t_dec:.2f} s (frames in memory)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", "-c", default="fixtures/paper_table1.toml")
    ap.add_argument("--rays-per-pixel", type=float, default=200.0)
    ap.add_argument("--random", type=int, default=20, help="random defects besides the paper's nine")
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--defocus-mm", type=float, help="object plane beyond the MLA's focus, mm (default 2); an "
                    "ideal main lens: the scene's image before the MLA (default 15: 9.4 µm in a dry 40x sample)")
    ap.add_argument("--slope", type=float, help="refocus slope, lenses per view pixel (default: the scene's)")
    ap.add_argument("--noise", choices=("both", "off", "on"), default="both")
    ap.add_argument("--timing", action="store_true")
    ap.add_argument("--geometry", action="store_true", help="decoded views of a point against exact rays")
    ap.add_argument("--picture", metavar="PNG", help="write a before/after picture of one view (texture, noise-free)")
    ap.add_argument("--plenopticam", metavar="PYTHON", help="compare with PlenoptiCam run by this interpreter")
    args = ap.parse_args()
    if args.geometry:
        for d in (1.0, 2.0, 4.0):
            geometry(d)
        return 0
    cfg = load_config(args.config)
    if args.defocus_mm is None:
        args.defocus_mm = 15.0 if cfg.main_lens.ideal else 2.0
    if args.plenopticam:
        against_plenopticam(cfg, args.plenopticam, args.defocus_mm, args.rays_per_pixel)
        return 0
    if args.timing:
        timing(cfg)
        return 0
    flawed_em, flawed = flawed_map(cfg, args.random, args.seed)
    clean_em = ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w, cfg.mla.packing)
    slope = args.slope if args.slope is not None else scene_slope(cfg, args.defocus_mm)
    for noise in {"both": (False, True), "off": (False,), "on": (True,)}[args.noise]:
        print(f"{args.config}: {'noisy' if noise else 'noise-free'} frames, {args.rays_per_pixel:g} rays/pixel, "
              f"object {args.defocus_mm:g} mm beyond focus")
        for name, scene in (("texture", texture()), ("points", points(cfg))):
            compare(cfg, name, scene, flawed_em, flawed, clean_em, args.rays_per_pixel, noise, args.defocus_mm, slope,
                    args.picture if name == "texture" and not noise else None)
    return 0


def scene_slope(cfg, defocus_mm: float) -> float:
    """The refocus slope that brings the defocused object plane into focus near the axis (paraxial): its
    image lies dz before the MLA; the view u px out looks through the pupil point P = -(u / r) R (the
    sub-image is the pupil's image, inverted), whose ray through the image point meets the MLA P dz / b'
    from it, so a point moves R dz / (b' r) per view pixel, in lens pitches. The Table 1 singlet's
    spherical aberration makes outer views move more (tests/lens_rays.py traces it exactly)."""
    from mlaqc.optics.paraxial import image_distance

    lay, slay = cfg.layout, scene_config(cfg, defocus_mm).layout
    if lay.main is None:  # an ideal lens: the scene's image is given, b' from its exit pupil
        b_img = lay.pupil_to_mla_mm - defocus_mm
    else:
        b_img = image_distance(lay.main.efl, slay.object_distance_mm + lay.main.front_principal)
    dz = lay.pupil_to_mla_mm - b_img
    r_px = design_sampling(cfg, (cfg.sensor.height_px, cfg.sensor.width_px)).radius_px
    return float(dz / b_img * lay.exit_radius_mm / r_px / (cfg.mla.pitch_um * 1e-3))


if __name__ == "__main__":
    sys.exit(main())
