"""Reference model of the ideal camera: the white-image sub-image of a perfect lens, rendered by the
tracer at 8x oversampling, and the relative flux of every lens (vignetting).

Built for a config on first use and cached on disk keyed by the config's optics and sensor; the one for
the default (Table 1) camera ships in the package, so inspection works offline at once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mlaqc.atomic import write_bytes_atomic
from mlaqc.models.store import stored
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.lattice import Lattice
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene

OVERSAMPLE = 8
FORMAT_VERSION = 1


@dataclass(frozen=True)
class ReferenceModel:
    """An ideal lens' sub-image on a fine grid, box-filtered to the sensor pixel, and the flux map.

    `template[i, j]` is the mean irradiance over a whole sensor pixel whose centre sits at
    ((j - centre) / OVERSAMPLE, (i - centre) / OVERSAMPLE) px from the lens' sub-image centre.
    """

    template: np.ndarray  # (T, T) float64, box-filtered, peak normalized to 1
    centre: float  # template index of the sub-image centre (both axes)
    oversample: int
    flux: np.ndarray  # (rows, cols) relative flux of each ideal lens, 1 at the array centre
    key: str

    def window_px(self) -> int:
        """Half-size in sensor pixels that the template covers."""
        return int(self.centre // self.oversample)


def mla_hash_view(mla: dict, *, design: bool = False) -> dict:
    """The MLA keys that shape the images, for a content hash: the lens-boundary model only when it is not
    'grid' and the black matrix only when set (so that the keys of the tables shipped before either key
    existed, which were grid tables, stay valid), and the boundary model never for `design` (an error-free
    array: sag-intersection boundaries lie on the grid). The packing and aperture keys likewise only when
    they are not the square, cell-filling array that every table shipped before them was made for."""
    out = dict(mla)
    if out.get("packing", "square") == "square":
        out.pop("packing", None)
    if out.get("aperture", "cell") == "cell":
        for key in ("aperture", "aperture_diameter_um", "gap"):
            out.pop(key, None)
    if design or out.get("boundaries") == "grid":
        out.pop("boundaries", None)
    if not out.get("black_matrix_um"):
        out.pop("black_matrix_um", None)
    return out


def geometry_hash_view(geometry: dict) -> dict:
    """The geometry keys that shape white frames and sub-images, for a content hash: all but where an ideal
    main lens images a scene (`image_defocus_mm`), which places scenes only."""
    return {k: v for k, v in geometry.items() if k != "image_defocus_mm"}


def sensor_hash_view(cfg: CameraConfig) -> dict:
    """The sensor keys that shape the images, for a content hash: its size, and its pixel as the MLA's focal
    plane sees it (a relay's magnification included; the sensor's own pixel when there is no relay)."""
    s = cfg.sensor
    return {"pixel_um": cfg.pixel_at_mla_um, "width_px": s.width_px, "height_px": s.height_px}


def config_key(cfg: CameraConfig) -> str:
    """Hash of everything that shapes the ideal sub-images (optics, geometry, sensor geometry)."""
    d = cfg.to_dict()
    keep = {"main_lens": d["main_lens"], "mla": mla_hash_view(d["mla"], design=True),
            "geometry": geometry_hash_view(d["geometry"]), "sensor": sensor_hash_view(cfg), "fresnel": d["trace"]["fresnel"],
            "format": FORMAT_VERSION}
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]


def reference_model(cfg: CameraConfig, *, build_if_missing: bool = True, rays_per_lens: int = 4_000_000,
                    client=None, rebuild: bool = False) -> ReferenceModel:
    """The reference for `cfg`: from the package, else the disk cache, else rendered now (its full-frame
    flux render on a Dask `client` if given) and cached (`mlaqc.models.store`); `rebuild` renders it
    again whatever is stored."""
    key = config_key(cfg)
    return stored(f"reference_{key}.npz", lambda: build_reference(cfg, rays_per_lens=rays_per_lens, client=client),
                  lambda path: _load(path, key), save_reference, rebuild=rebuild, build_if_missing=build_if_missing)


def save_reference(model: ReferenceModel, path: Path) -> None:
    """Write a reference as compressed NPZ, atomically."""
    buf = io.BytesIO()
    np.savez_compressed(buf, template=model.template.astype(np.float32), centre=model.centre,
                        oversample=model.oversample, flux=model.flux.astype(np.float32), key=model.key)
    write_bytes_atomic(path, buf.getvalue())


def _load(path: Path, key: str) -> ReferenceModel:
    with np.load(path, allow_pickle=False) as z:
        return ReferenceModel(z["template"].astype(np.float64), float(z["centre"]), int(z["oversample"]),
                              z["flux"].astype(np.float64), key)


def build_reference(cfg: CameraConfig, *, rays_per_lens: int = 4_000_000, seed: int = 20180501,
                    client=None) -> ReferenceModel:
    """Render the reference: the sub-image of the lens nearest the axis on a sensor with pixels 8x finer
    (rays through that lens and its neighbours within 1.5 pitches, so the window holds what a real one
    holds: square 8, hex 6), then
    the flux of every ideal lens from a full-frame render, smoothed by a low-order fit."""
    os_ = OVERSAMPLE
    s = cfg.sensor
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    p = cfg.mla.pitch_um * 1e-3
    m0, n0 = rows // 2, cols // 2  # 0-based lens just up-left of (or on) the axis (square)
    if cfg.mla.packing == "square":
        x_c = (n0 + 0.5) * p - 0.5 * cols * p
        y_c = (m0 + 0.5) * p - 0.5 * rows * p
    else:  # the lens whose centre is nearest the axis, from the lattice
        m0, n0 = (int(v) for v in Lattice.of(cfg).nearest(0.0, 0.0)[:2])
        x_c, y_c = (float(v) for v in Lattice.of(cfg).position(m0, n0))
    fine = dataclasses.replace(cfg, sensor=dataclasses.replace(s, pixel_um=s.pixel_um / os_,
                                                                **_fine_crop(cfg, x_c, y_c)))
    renderer = Renderer(fine, ErrorMap.zeros(rows, cols, cfg.mla.packing))
    tile = (x_c - 1.5 * p, x_c + 1.5 * p, y_c - 1.5 * p, y_c + 1.5 * p)
    fine_img = np.zeros(fine.sensor.width_px * fine.sensor.height_px)
    for i in range(max(1, rays_per_lens * 9 // (1 << 20))):
        idx, w = renderer.trace_batch(WhiteScene(), seed + i, 1 << 20, tile=tile)
        fine_img += np.bincount(idx, weights=w, minlength=fine_img.size)
    fine_img = fine_img.reshape(fine.sensor.height_px, fine.sensor.width_px)
    lay = cfg.layout
    pix = cfg.pixel_at_mla_um
    gain = lay.subimage_pitch_px / (cfg.mla.pitch_um / pix)
    # the sub-image centre: chief ray from the pupil centre through the lens centre, on the fine grid
    cx = (fine.sensor.width_px - 1) / 2 + x_c * gain / (pix * 1e-3 / os_)
    cy = (fine.sensor.height_px - 1) / 2 + y_c * gain / (pix * 1e-3 / os_)
    half = int(np.ceil(0.75 * lay.subimage_pitch_px)) * os_ + os_
    template = _box_filter(_cut(fine_img, cx, cy, half), os_)
    template /= template.max()
    flux = _flux_map(cfg, client=client)
    return ReferenceModel(template, float(half), os_, flux, config_key(cfg))


def _fine_crop(cfg: CameraConfig, x_c: float, y_c: float) -> dict[str, int]:
    """Width and height of the 8x-finer sensor, cropped about the axis to just hold the 3 x 3 lenses
    around (x_c, y_c) mm: memory stays a few MiB whatever the real sensor's size. Each crop removes an
    even number of fine pixels per axis (whole coarse pixels per side), so pixel centres stay on the
    full sensor's lattice and the template is the one the full-size fine sensor would give."""
    s, os_, pix = cfg.sensor, OVERSAMPLE, cfg.pixel_at_mla_um
    gain = cfg.layout.subimage_pitch_px / (cfg.mla.pitch_um / pix)
    reach_px = 2.5 * cfg.layout.subimage_pitch_px + 4  # 1.5 pitches of lenses, the template's rim, blur
    out = {}
    for name, full, c_mm in (("width_px", s.width_px, x_c), ("height_px", s.height_px, y_c)):
        half = int(np.ceil(abs(c_mm) * gain / (pix * 1e-3) + reach_px))
        out[name] = min(full, full % 2 + 2 * half) * os_
    return out


def _cut(img: np.ndarray, cx: float, cy: float, half: int) -> np.ndarray:
    """(2*half+1)^2 window whose centre sample sits at (cx, cy), by linear interpolation."""
    from scipy.ndimage import map_coordinates

    off = np.arange(-half, half + 1, dtype=float)
    yy, xx = np.meshgrid(cy + off, cx + off, indexing="ij")
    return map_coordinates(img, [yy, xx], order=1, mode="constant")


def _box_filter(img: np.ndarray, size: int) -> np.ndarray:
    """Mean over a size x size box centred on each sample (what one coarse pixel integrates)."""
    from scipy.ndimage import uniform_filter

    if size % 2 == 0:  # an even box is centred between samples: average the two half-shifted odd ones
        a = uniform_filter(img, size + 1, mode="constant")
        b = uniform_filter(img, size - 1, mode="constant")
        return 0.5 * (a + b)
    return uniform_filter(img, size, mode="constant")


def _flux_map(cfg: CameraConfig, rays_per_pixel: float = 4.0, client=None) -> np.ndarray:
    """Relative flux of every ideal lens: per-cell sums of a white render, fitted by an even quartic."""
    if client is None:
        res = Renderer(cfg).render(WhiteScene(), rays_per_pixel=rays_per_pixel, seed=7)
    else:
        from mlaqc.optics.distributed import render_on_cluster

        res = render_on_cluster(client, Renderer(cfg), WhiteScene(), rays_per_pixel=rays_per_pixel, seed=7)
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    if cfg.mla.packing == "square":
        sums, (m, n), inner = _square_cell_sums(res.photons, cfg)
        r2 = (m / max(rows, 1)) ** 2 + (n / max(cols, 1)) ** 2
        basis = np.stack([np.ones_like(r2), r2, r2 * r2, (m / rows) ** 2 - (n / cols) ** 2]).reshape(4, -1).T
    else:
        sums, (m, n), inner = _lattice_cell_sums(res.photons, cfg)
        r2 = m ** 2 + n ** 2
        basis = np.stack([np.ones_like(r2), r2, r2 * r2, m ** 2 - n ** 2]).reshape(4, -1).T
    coef, *_ = np.linalg.lstsq(basis[inner.ravel()], sums.ravel()[inner.ravel()], rcond=None)
    fit = (basis @ coef).reshape(rows, cols)
    return fit / fit[rows // 2, cols // 2]


def _square_cell_sums(photons: np.ndarray, cfg: CameraConfig):
    """Per-cell photon sums of a square array's white render (separable: pixel rows and columns map to
    lens rows and columns), the lenses' index offsets (m, n) from the array's centre, and the cells
    not cut by the sensor edge (all but the border ones)."""
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    pitch = cfg.layout.subimage_pitch_px
    h, w = photons.shape
    yy = ((np.arange(h) - (h - 1) / 2) / pitch + rows / 2).astype(int)
    xx = ((np.arange(w) - (w - 1) / 2) / pitch + cols / 2).astype(int)
    ok_y, ok_x = (yy >= 0) & (yy < rows), (xx >= 0) & (xx < cols)
    idx = (yy[ok_y][:, None] * cols + xx[ok_x][None, :]).ravel()
    sums = np.bincount(idx, weights=photons[np.ix_(ok_y, ok_x)].ravel(), minlength=rows * cols).reshape(rows, cols)
    m, n = np.meshgrid(np.arange(rows) - (rows - 1) / 2, np.arange(cols) - (cols - 1) / 2, indexing="ij")
    inner = np.ones((rows, cols), bool)
    inner[[0, -1], :] = inner[:, [0, -1]] = False  # border cells may be cut by the sensor edge
    return sums, (m, n), inner


def _lattice_cell_sums(photons: np.ndarray, cfg: CameraConfig):
    """Per-cell photon sums of a white render on any lattice (each pixel to the cell of the sub-image
    lattice it lies in, `Lattice.nearest`), the lenses' centres (y, x) over the array's height and width,
    and the cells not cut by the sensor edge (all but the outer ring)."""
    lat = Lattice(cfg.mla.packing, cfg.mla.count_h, cfg.mla.count_w, cfg.layout.subimage_pitch_px)
    h, w = photons.shape
    sums = np.zeros(lat.rows * lat.cols)
    for i0 in range(0, h, 256):  # 256 pixel rows at a time: a few MB of indices
        y = np.arange(i0, min(i0 + 256, h))[:, None] - (h - 1) / 2
        x = np.arange(w)[None, :] - (w - 1) / 2
        r, c, inside = lat.nearest(*np.broadcast_arrays(x, y))
        sums += np.bincount((r * lat.cols + c)[inside], weights=photons[i0:i0 + len(y)][inside], minlength=sums.size)
    x_c, y_c = lat.centres()
    width, height = lat.extent
    inner = np.ones(lat.shape, bool)
    inner[[0, -1], :] = inner[:, [0, -1]] = False
    return sums.reshape(lat.shape), (y_c / height, x_c / width), inner
