"""The files `mlaqc decode` writes for one frame, each atomically, decode.json last (its presence means the
set is complete): the light field and its weights (.npy), the sub-aperture views as a TIFF stack, a PNG
mosaic of the views, and the refocused images (.npy and a PNG each)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc import __version__
from mlaqc.atomic import atomic_path, write_bytes_atomic, write_json_atomic
from mlaqc.decode.lightfield import LightField

FORMAT = "mlaqc-lightfield"
VERSION = 1
FILES = {"values": "lightfield.npy", "weights": "weights.npy", "views": "views.tif", "mosaic": "mosaic.png",
         "refocus": "refocus.npy", "json": "decode.json"}
AXES = ("v: view row, the pupil point's offset down from the sub-image centre (view_offsets_px)",
        "u: view column, its offset to the right",
        "t: lens row (U(m,n) = [m-1, n-1]; a hex array's rows resampled one pitch apart: 'rect')",
        "s: lens column")


def write_lightfield(out: Path, lf: LightField, refocused: list[tuple[float, np.ndarray]], facts: dict[str, Any]) -> dict[str, Path]:
    """Write the set into folder `out` (created if missing); returns {key: path}."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {k: out / v for k, v in FILES.items()}
    _save_npy(paths["values"], lf.values)
    _save_npy(paths["weights"], lf.weights)
    _save_views_tiff(paths["views"], lf)
    write_bytes_atomic(paths["mosaic"], _png(mosaic(lf)))
    slopes = [s for s, _ in refocused]
    if refocused:
        _save_npy(paths["refocus"], np.stack([img for _, img in refocused]).astype(np.float32))
        for i, (slope, img) in enumerate(refocused):
            paths[f"refocus_{i}"] = out / f"refocus_{i}.png"
            write_bytes_atomic(paths[f"refocus_{i}"], _png(_to_16bit(img, np.ones(img.shape[:2], bool))))
    else:
        del paths["refocus"]
    doc = {"format": FORMAT, "version": VERSION, "mlaqc_version": __version__, **facts,
           "axes": list(AXES) + (["channel: R, G, B (demosaiced)"] if lf.values.ndim == 5 else []),
           "shape": list(lf.values.shape), "view_offsets_px": lf.view_offsets_px.tolist(),
           "lens_grid": lf.packing, "lens_spacing_pitches": [1.0, 1.0], "devignetted": lf.devignetted,
           "refocus_slopes": slopes,
           "refocus_meaning": "shift-and-add: E(s,t) = sum w L(u,v,s+slope*u,t+slope*v) / sum w; slope in lenses "
                              "per pixel of view offset, 0 = the plane the MLA sees in focus",
           "files": {k: p.name for k, p in paths.items()}}
    write_json_atomic(paths["json"], doc)
    return paths


def _save_npy(path: Path, a: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, np.ascontiguousarray(a), allow_pickle=False)


def _save_views_tiff(path: Path, lf: LightField) -> None:
    """Every sub-aperture view as one page, row by row of views (page j * nu + i is view (j, i))."""
    import tifffile

    nv, nu = lf.values.shape[:2]
    pages = lf.values.reshape((nv * nu,) + lf.values.shape[2:])
    meta = {"mlaqc": FORMAT, "views": [nv, nu], "view_offsets_px": lf.view_offsets_px.tolist()}
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, pages, photometric="rgb" if lf.values.ndim == 5 else "minisblack",
                         description=json.dumps(meta), metadata=None)


def mosaic(lf: LightField, gap: int = 1) -> np.ndarray:
    """The views tiled as they sit in the pupil (view (j, i) at tile row j, column i), `gap` px apart,
    16-bit, scaled to the light field's 99.5th percentile; samples of no weight black."""
    nv, nu, rows, cols = lf.weights.shape
    extra = lf.values.shape[4:]
    tile_h, tile_w = rows + gap, cols + gap
    canvas = np.zeros((nv * tile_h - gap, nu * tile_w - gap) + extra, np.float32)
    shown = np.zeros(canvas.shape[:2], bool)
    for j in range(nv):
        for i in range(nu):
            canvas[j * tile_h:j * tile_h + rows, i * tile_w:i * tile_w + cols] = lf.values[j, i]
            shown[j * tile_h:j * tile_h + rows, i * tile_w:i * tile_w + cols] = lf.weights[j, i] > 0
    return _to_16bit(canvas, shown)


def _to_16bit(img: np.ndarray, shown: np.ndarray) -> np.ndarray:
    vals = img[shown] if img.ndim == 2 else img[shown].ravel()
    top = float(np.percentile(vals, 99.5)) if vals.size else 1.0
    top = top if top > 0 else 1.0
    scaled = np.clip(img / top, 0, 1) * 65535.0
    scaled[~shown] = 0
    return scaled.astype(np.uint16)


def _png(img: np.ndarray) -> bytes:
    """PNG bytes of a 16-bit grey or RGB image."""
    import cv2

    ok, buf = cv2.imencode(".png", img[..., ::-1] if img.ndim == 3 else img)
    if not ok:
        raise OSError("PNG encoding failed")
    return buf.tobytes()
