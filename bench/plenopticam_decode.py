"""Decode a monochrome light-field TIFF into sub-aperture views with PlenoptiCam, calibrated on a white TIFF.

A reference decoder for benchmarks: it uses only PlenoptiCam (no mlaqc import) and saves its views, the
micro-image centres it found and its timings to an .npz file.

Set up (PlenoptiCam 0.9.3 pins pyinstaller==4.10, a packaging tool that has no wheel for Python 3.11 and is not
used at run time, so it is installed without dependencies; numpy<2 and scipy<1.14 because PlenoptiCam's
scikit-image and scipy.interpolate.interp2d need them):

    python3 -m venv /tmp/plcvenv
    /tmp/plcvenv/bin/pip install plenopticam tifffile
    /tmp/plcvenv/bin/pip install --no-deps plenopticam==0.9.3
    /tmp/plcvenv/bin/pip install "numpy<2" "scipy<1.14" "matplotlib<3.10" "contourpy<1.3.3" "Pillow>=9.0.1" \
        "colour-science<0.4.5" "colour-demosaicing<0.2.6" tifffile==2022.4.8
    /tmp/plcvenv/bin/python bench/plenopticam_decode.py --white W.tiff --scene S.tiff --out OUT.npz [--views 19]

What runs, and what is left out on purpose (so the views are as raw as PlenoptiCam allows):
- Frames are read with tifffile and the black level (sidecar `<file>.sim.json`, else 64) is subtracted.
  PlenoptiCam's own LfpReader is not used: for non-Lytro files it applies an inverse sRGB gamma.
- cfg.lfpimg is left empty, so PlenoptiCam treats the frames as monochrome: no Bayer demosaicing,
  no white balance and no hot-pixel correction (CfaOutliers only runs for Bayer metadata).
- Calibration: LfpCalibrator with cal_meth='area' (its default: LoG of the white, local maxima,
  thresholded-area centroids, sorted into a lens grid); no grid fit, so each lens keeps its own centre.
  PlenoptiCam expects bell-shaped (vignetted) white micro images; on flat cells that fill the pitch its LoG
  has a plateau with four maxima per lens and the sorter stops ("Geometric MLA arrangement not
  recognized" or "Error in MLA dimension estimation"). --white-sigma S (default 0, off) Gaussian-blurs the
  white given to LfpCalibrator only, which makes the cells bell-shaped (S=2 gives one maximum per lens on
  the 20 px square-packed frames); the views never see the blur. PlenoptiCam drops lenses whose maximum
  falls within M/2 px of the frame edge, so its lens grid can lack the outermost ring.
- Alignment: the steps of LfpAligner.main for a monochrome frame, called one by one: LfpDevignetter only
  with --devignette (opt_vign; default off, the views are not divided by the white); no rotation
  (opt_rota=False); LfpResampler with smp_meth='local' (each micro image is interpolated around its own
  centre at the native pixel scale; 'global' instead warps the whole frame by one projective fit and
  rescales the pitch to an odd integer). LfpResampler.main is bypassed because it min-max normalises the
  aligned image to uint16 and pickles it to disk.
- Extraction: LfpCropper and LfpRearranger, the first two steps of LfpExtractor.main. The rest of that
  method is skipped: outlier removal (opt_lier), colour equalisation (opt_colo), LfpContrast (contrast,
  saturation, white balance, gamma; it always runs there), hex-artifact removal (opt_arti), writing views
  to disk, depth (opt_dpth). No refocusing (opt_refo), no debug images (opt_dbug), no console progress
  (opt_prnt), no GUI.

Saved arrays: views (n_v, n_u, rows, cols) float32 in black-subtracted counts, view [j, i] being pixel row j,
column i of every resampled micro image (centre view at [n // 2, n // 2], on each lens's centre; the pupil
is imaged inverted, so pupil offsets have the opposite sign); centres (K, 4) rows of PlenoptiCam's mic_list
(y, x, lens row, lens column), y and x in pixels of the full frame with (0, 0) at the centre of the top-left
pixel; t_calibrate, t_align_extract, t_total in seconds (t_total includes reading the frames).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
import warnings

import numpy as np
import tifffile

warnings.filterwarnings("ignore")  # interp2d deprecation and colour's import notices; not about the data

from scipy.ndimage import gaussian_filter  # noqa: E402

from plenopticam.cfg import PlenopticamConfig  # noqa: E402
from plenopticam.cfg.constants import PARAMS_KEYS, PARAMS_VALS  # noqa: E402
from plenopticam.lfp_aligner.lfp_devignetter import LfpDevignetter  # noqa: E402
from plenopticam.lfp_aligner.lfp_resampler import LfpResampler  # noqa: E402
from plenopticam.lfp_calibrator import LfpCalibrator  # noqa: E402
from plenopticam.lfp_extractor.lfp_cropper import LfpCropper  # noqa: E402
from plenopticam.lfp_extractor.lfp_rearranger import LfpRearranger  # noqa: E402
from plenopticam.misc.status import PlenopticamStatus  # noqa: E402

CENTRES_NOTE = "rows of PlenoptiCam mic_list: y, x (px, frame origin at top-left pixel centre), lens row, lens col"


def read_raw(path: str) -> np.ndarray:
    """Frame as float64 counts above black, so every PlenoptiCam step sees linear signal."""
    black = 64.0
    sidecar = path + ".sim.json"
    if os.path.exists(sidecar):
        with open(sidecar) as f:
            black = float(json.load(f).get("raw", {}).get("black_level", black))
    return tifffile.imread(path).astype(np.float64) - black


def make_config(workdir: str, views: int, resample: str, devignette: bool) -> PlenopticamConfig:
    """PlenoptiCam settings for a bare decode; side files (calibration json) go to `workdir`."""
    cfg = PlenopticamConfig()
    cfg.params = dict(zip(PARAMS_KEYS, PARAMS_VALS))  # defaults, ignoring any cfg.json left by earlier runs
    cfg.lfpimg = {}  # no Bayer metadata: monochrome, no demosaic / white balance / hot-pixel step
    cfg.params.update({
        cfg.lfp_path: os.path.join(workdir, "scene.tiff"),  # export dir; nothing is written there
        cfg.cal_path: os.path.join(workdir, "white.tiff"),
        cfg.cal_meta: os.path.join(workdir, "white.json"),  # LfpCalibrator saves its centres here
        cfg.cal_meth: "area", cfg.smp_meth: resample, cfg.ptc_leng: views,
        cfg.opt_cali: True, cfg.opt_vign: devignette, cfg.opt_rota: False,
        cfg.opt_lier: False, cfg.opt_cont: False, cfg.opt_colo: False, cfg.opt_awb_: False,
        cfg.opt_sat_: False, cfg.opt_view: True, cfg.opt_refo: False, cfg.opt_refi: False,
        cfg.opt_pflu: False, cfg.opt_arti: False, cfg.opt_dbug: False, cfg.opt_prnt: False,
        cfg.opt_dpth: False, cfg.dir_remo: False,
    })
    return cfg


def check(sta: PlenopticamStatus, step: str) -> None:
    """PlenoptiCam reports failures through its status object rather than exceptions."""
    if sta.error or sta.interrupt:
        raise RuntimeError(f"PlenoptiCam {step} failed: {sta.stat_var}")


def calibrate(white: np.ndarray, cfg: PlenopticamConfig, sta: PlenopticamStatus, sigma: float = 0.0) -> np.ndarray:
    """Micro-image centres from the white frame (blurred by `sigma` px if > 0), as PlenoptiCam's mic_list (K, 4)."""
    LfpCalibrator(gaussian_filter(white, sigma) if sigma > 0 else white, cfg, sta).main()
    check(sta, "calibration")
    return np.asarray(cfg.calibs[cfg.mic_list], dtype=np.float64)


def align_extract(scene: np.ndarray, white: np.ndarray, cfg: PlenopticamConfig,
                  sta: PlenopticamStatus) -> np.ndarray:
    """Views (n_v, n_u, rows, cols) float32: LfpAligner's monochrome steps, then crop and rearrange."""
    lfp = scene[..., None]  # PlenoptiCam's resamplers index a channel axis
    if cfg.params[cfg.opt_vign]:
        dev = LfpDevignetter(lfp_img=lfp, wht_img=white[..., None], cfg=cfg, sta=sta)
        dev.main()
        lfp = dev.lfp_img
    res = LfpResampler(lfp_img=lfp, cfg=cfg, sta=sta)
    if cfg.params[cfg.smp_meth] == "local":
        res.local_resampling()
    else:
        res.global_resampling()
    check(sta, "alignment")
    crop = LfpCropper(lfp_img_align=res.lfp_img_align, cfg=cfg, sta=sta)
    crop.main()
    rea = LfpRearranger(crop.lfp_img_align, cfg=cfg, sta=sta)
    rea.main()
    check(sta, "extraction")
    return rea.vp_img_arr.mean(axis=-1).astype(np.float32)  # (n, n, rows, cols, channels) -> channel mean


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--white", required=True, help="white (calibration) TIFF")
    ap.add_argument("--scene", required=True, help="light-field TIFF to decode")
    ap.add_argument("--out", required=True, help="output .npz")
    ap.add_argument("--views", type=int, default=19, help="views per axis (PlenoptiCam patch size, odd, 3..pitch+2)")
    ap.add_argument("--resample", choices=("local", "global"), default="local", help="PlenoptiCam smp_meth")
    ap.add_argument("--devignette", action="store_true", help="divide by the white before resampling (opt_vign)")
    ap.add_argument("--white-sigma", type=float, default=0.0, help="Gaussian blur (px) of the white for calibration")
    args = ap.parse_args()

    t0 = time.perf_counter()
    white, scene = read_raw(args.white), read_raw(args.scene)
    out_dir = os.path.dirname(os.path.abspath(args.out))
    with tempfile.TemporaryDirectory(prefix="plenopticam_", dir=out_dir) as workdir:  # calibration json
        cfg = make_config(workdir, args.views, args.resample, args.devignette)
        sta = PlenopticamStatus()
        t1 = time.perf_counter()
        centres = calibrate(white, cfg, sta, args.white_sigma)
        t2 = time.perf_counter()
        views = align_extract(scene, white, cfg, sta)
        t3 = time.perf_counter()

    timings = {"t_calibrate": t2 - t1, "t_align_extract": t3 - t2, "t_total": t3 - t0}
    np.savez(args.out, views=views, centres=centres, centres_note=CENTRES_NOTE,
             pattern=str(cfg.calibs[cfg.pat_type]), pitch=np.asarray(cfg.calibs[cfg.ptc_mean], dtype=float),
             **{k: np.float64(v) for k, v in timings.items()})
    for k, v in timings.items():
        print(f"{k}: {v:.3f} s")
    print(f"views: {views.shape}")


if __name__ == "__main__":
    main()
