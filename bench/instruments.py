"""The datasheet-described instruments (fixtures/lfm_40x_relay.toml, fixtures/handheld_hex_bayer.toml) on
frames the tracer did not make: the analytic model of tests/analytic_frames.py (discs with an Airy rim, no
code shared with the tracer) given each fixture's first-order optics, at several noise levels from
noise-free up, written in real containers and inspected as a user's file would be. Prints per cell: false
flags, recall of the seeded anomalies, how many of the shifted, dimmed, missing and resized discs are typed
pitch, dim, missing and a focal type (radius or thickness: see TYPE_OF), centre RMS against the true
centres, the frame's detection limits and the inspection's time; then the same frames as a scene (a smooth
random brightness over the lenses, as a fluorescent sample gives), which must be refused, not inspected.

    python bench/instruments.py            # both fixtures, noise 0 / 1 / 3 %, 24 anomalies each
    python bench/instruments.py --quick    # noise 0 and 1 % only
    python bench/instruments.py -c fixtures/lfm_40x_relay.toml --seed 5

The analytic disc is the exit pupil's image: radius f / (2 N) over the pixel as the MLA's focal plane sees
it (a relay's magnification included), capped at half the pitch; its rim the microlens' Airy edge (first
zero 1.22 λ f / p); cos⁴ vignetting from the exit pupil's distance (none when telecentric); a resized disc
keeps its lens' light (the pupil's image rescaled: the same light over another area; a disc shrunk at
constant level lost 23 % of its flux and read, rightly, as a dim lens on noise-free frames). A Bayer sensor's
sites get its configured QE before the noise.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))

import analytic_frames as am  # noqa: E402
from robustness import Cell, _match_truth, centre_rms, print_cells, score  # noqa: E402

from mlaqc.errors import InputError  # noqa: E402
from mlaqc.inspection.pipeline import inspect_file  # noqa: E402
from mlaqc.optics.config import load_config  # noqa: E402
from mlaqc.optics.datasheet import telecentric  # noqa: E402
from mlaqc.optics.sensor import cfa_site_colours  # noqa: E402

FIXTURES = ("fixtures/lfm_40x_relay.toml", "fixtures/handheld_hex_bayer.toml")
BITS, BLACK = 16, 0


def analytic_model(cfg) -> am.AnalyticModel:
    """The analytic frame of a config's first-order optics (see the module note)."""
    lay, pix = cfg.layout, cfg.pixel_at_mla_um
    pitch = lay.subimage_pitch_px
    radius = min(lay.micro.efl * 1e3 / (2.0 * lay.image_f_number) / pix, 0.5 * pitch)
    airy = 1.22 * cfg.geometry.wavelength_nm * 1e-3 * (lay.micro.efl * 1e3 / cfg.mla.pitch_um) / pix
    far = cfg.main_lens.ideal and telecentric(cfg.main_lens.exit_pupil_mm)
    pupil_px = 1e12 if far else lay.pupil_to_mla_mm * 1e3 / pix
    return am.AnalyticModel(shape=(cfg.sensor.height_px, cfg.sensor.width_px), lenses=(cfg.mla.count_h, cfg.mla.count_w),
                            pitch_px=pitch, radius_px=radius, rim="airy", airy_radius_px=airy, exit_pupil_px=pupil_px,
                            packing=cfg.mla.packing, phase_px=(0.37, 0.21), resize_keeps_flux=True)


def sensor_qe(cfg, shape) -> np.ndarray | float:
    """Per-pixel QE relative to the best site (1 on a monochrome sensor)."""
    s = cfg.sensor
    if s.cfa == "none":
        return 1.0
    qe = np.asarray(s.cfa_qe)[cfa_site_colours(s.cfa, *shape)]
    return qe / qe.max()


def write_frame(path: Path, irradiance: np.ndarray, cfg, noise: float, rng) -> Path:
    """The frame as a camera writes it: QE per site, shot and read noise, 16-bit TIFF with level tags."""
    signal = am.expose(irradiance * sensor_qe(cfg, irradiance.shape), noise, rng)
    return am.write_container(path, am.to_counts(signal, BITS, BLACK, white_fraction=0.8), BITS, BLACK)


def run_cell(cfg, name: str, noise: float, seed: int, tmp: Path) -> Cell:
    rng = np.random.default_rng(seed)
    model = analytic_model(cfg)
    anomalies = am.random_anomalies(model, 24, rng)
    model = model.with_anomalies(anomalies)
    path = write_frame(tmp / f"{name}.tif", model.render(), cfg, noise, rng)
    t0 = time.perf_counter()
    result = inspect_file(path, cfg)
    cell = Cell(f"{name} analytic noise {noise:.0%}", seconds=time.perf_counter() - t0)
    truth = {(a.row + 1, a.col + 1): {"kind": f"{a.kind} {a.magnitude:.2f}", "magnitude": None} for a in anomalies}
    matched = _match_truth(result, model, truth)
    score(cell, result, matched)
    cell.centre_rms_px, cell.grid_rms_px = centre_rms(result, model, set(truth))
    flagged = {(d.m, d.n): d.error_type for d in result.defects}
    typed = [(TYPE_OF[t["kind"].split()[0]], flagged.get(key)) for key, t in matched.items()
             if t["kind"].split()[0] in TYPE_OF]
    resized = sorted(flagged.get(key) or "none" for key, t in matched.items() if t["kind"].startswith("size"))
    cell.name += (f" [typed {sum(got in want for want, got in typed)}/{len(typed)}; resized read as "
                  f"{', '.join(f'{k} {resized.count(k)}' for k in dict.fromkeys(resized))}]")
    return cell


# the physical types an analytic anomaly is: a whole disc moved, its light scaled, none, its size changed.
# A resized disc (the pupil's image scaled, its rim as sharp) is a focal-type change: the pupil's image
# scales with the distance from the lens' rear principal plane to the sensor, which a radius error moves
# on a thick biconvex lens and an axial (thickness) error on any; the disc model has no blur to tell them
# by, and which the table's signatures read it as depends on the lens' form (the microscope's: radius; the
# hand-held's f/2 lenses: thickness). The bench counts the family; the kind read is printed apart.
TYPE_OF = {"shift": {"pitch", "position"}, "dim": {"dim"}, "missing": {"missing"}, "size": {"radius", "thickness"}}


def scene_refused(cfg, name: str, contrast: float, seed: int, tmp: Path) -> str:
    """The analytic white frame times a smooth random brightness (3 lenses' scale, `contrast` rms)."""
    rng = np.random.default_rng(seed)
    img = analytic_model(cfg).render()
    field = gaussian_filter(rng.standard_normal(img.shape), 3 * cfg.layout.subimage_pitch_px)
    img = img * np.clip(1.0 + contrast * field / field.std(), 0.05, None) * 0.8
    path = write_frame(tmp / f"{name}_scene.tif", img, cfg, 0.01, rng)
    try:
        inspect_file(path, cfg)
    except InputError as exc:
        return f"refused: {exc}"
    return "INSPECTED (not refused)"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", "-c", action="append", help="a fixture (default: both)")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    noises = (0.0, 0.01) if args.quick else (0.0, 0.01, 0.03)
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.config or FIXTURES:
            cfg = load_config(ROOT / path if not Path(path).is_absolute() else path)
            name = Path(path).stem
            lenses = cfg.mla.count_h * cfg.mla.count_w
            print(f"\n{name}: {cfg.mla.count_h} x {cfg.mla.count_w} lenses, sub-image pitch "
                  f"{cfg.layout.subimage_pitch_px:.3f} px, {cfg.mla.packing}, cfa {cfg.sensor.cfa}", flush=True)
            t0 = time.perf_counter()
            inspect_file(write_frame(Path(tmp) / "warm.tif", analytic_model(cfg).render(), cfg, 0.01,
                                     np.random.default_rng(0)), cfg)  # the models rendered (or loaded) once
            print(f"  models ready ({time.perf_counter() - t0:.0f} s, the first time renders them)", flush=True)
            cells = [run_cell(cfg, name, noise, args.seed, Path(tmp)) for noise in noises]
            print_cells(cells)
            worst = max(c.false_flags for c in cells) * 10_000 / lenses
            print(f"  false flags per 10,000 lenses, worst cell: {worst:.1f} (bar <= 1)")
            for contrast in (0.1, 0.3):
                print(f"  a scene of {contrast:.0%} rms lens-to-lens contrast given as white: "
                      f"{scene_refused(cfg, name, contrast, args.seed, Path(tmp))}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
