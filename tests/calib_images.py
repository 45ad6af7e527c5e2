"""Rendered white images for the calibration and sub-image tests, cached on disk, and their ground truth.

Renders are slow (~10 M rays/s), so every image is cached under pytest's cache directory
(`.pytest_cache/d/mlaqc-calib`), keyed by the camera config, error map, ray budget, seed and noise; a
session fixture hands out the cache. Delete that folder to re-render.

Ground truth is computed without any image, by tracing rays (see `true_centres`): the sub-image of lens
U(m,n) in a white image is the image of the main lens' exit pupil formed by that microlens. Its centre is
the centre of the circle on which the images of the pupil's rim land; for an ideal thin microlens that is
where the chief ray from the exit-pupil centre through the lens centre lands (`chief_centres`). The two
differ by the microlens' own distortion of the pupil image (measured: +0.0055 px per mm of field,
outwards) and, beyond ~3.5 mm field, by vignetting of the pupil by the main lens' second rim.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from mlaqc.optics.config import config_to_toml, load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.raytrace import MainLens, MicrolensArray, Rays, direction_vector
from mlaqc.optics.simulate import simulate
from mlaqc.optics.scene import WhiteScene

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
SMALL = load_config(FIXTURES / "small_camera.toml")


@dataclass(frozen=True)
class White:
    """A rendered white frame: raw counts, expected photons and the normalized (black-subtracted) image."""

    raw: np.ndarray
    photons: np.ndarray
    image: np.ndarray  # float32, (raw - black) / (white - black)


def normalize(raw: np.ndarray, cfg) -> np.ndarray:
    """(raw - black) / (white - black) as mlaqc.inspection.raw_levels.normalized does for a mono frame."""
    from mlaqc.optics.sensor import white_level

    black = cfg.sensor.black_level_dn
    return ((raw.astype(np.float32) - black) / np.float32(white_level(cfg.sensor) - black)).astype(np.float32)


class RenderCache:
    """Renders keyed by everything that determines them, kept as .npz files."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)

    def white(self, cfg, errors: ErrorMap | None = None, *, rpp: float = 50, seed: int = 1, noise: bool = True) -> White:
        errors = errors if errors is not None else ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w, cfg.mla.packing)
        key = hashlib.sha256(json.dumps([config_to_toml(cfg), errors.to_json_dict(), rpp, seed, noise],
                                        sort_keys=True).encode()).hexdigest()[:20]
        path = self.folder / f"white-{key}.npz"
        if path.exists():
            with np.load(path) as z:
                raw, photons = z["raw"], z["photons"]
        else:
            sim = simulate(cfg, WhiteScene(), errors, rays_per_pixel=rpp, seed=seed, noise=noise)
            raw, photons = sim.raw, sim.render.photons.astype(np.float32)
            tmp = path.with_name(path.stem + ".part.npz")
            np.savez(tmp, raw=raw, photons=photons)
            tmp.replace(path)
        return White(raw, photons, normalize(raw, cfg))


@pytest.fixture(scope="session")
def render_cache(request, tmp_path_factory) -> RenderCache:
    cache = getattr(request.config, "cache", None)  # None with -p no:cacheprovider: render per session
    return RenderCache(cache.mkdir("mlaqc-calib") if cache is not None else tmp_path_factory.mktemp("mlaqc-calib"))


# ------------------------------------------------------------------------------------------ ground truth


def _lens_centres_mm(cfg, errors: ErrorMap | None):
    """Camera-frame (x, y) in mm of every lens' optical centre: nominal grid + pitch errors, then the MLA's
    global rotation (counterclockwise as displayed) and shift."""
    rows, cols = cfg.mla.count_h, cfg.mla.count_w
    p = cfg.mla.pitch_um * 1e-3
    v, u = np.mgrid[0:rows, 0:cols].astype(float)
    x = (u + 0.5 - 0.5 * cols) * p
    y = (v + 0.5 - 0.5 * rows) * p
    if errors is not None:
        ux, uy = direction_vector(errors.lens["pitch_dir_deg"])
        x = x + errors.lens["pitch_um"] * 1e-3 * ux
        y = y + errors.lens["pitch_um"] * 1e-3 * uy
        th = np.radians(errors.globals["mla_rotation_deg"])
        x, y = x * np.cos(th) + y * np.sin(th), -x * np.sin(th) + y * np.cos(th)
        x = x + errors.globals["mla_shift_x_um"] * 1e-3
        y = y + errors.globals["mla_shift_y_um"] * 1e-3
    return x, y


def _pupil_image(cfg, rho_mm: float, n_dir: int = 601, n_ap: int = 11) -> tuple[float, float]:
    """Radial sensor position (mm) of (rim-circle centre, chief ray) of the sub-image of a lens at rho_mm.

    The visible pupil is found by tracing a fan of directions back from the lens centre through the main
    lens (its rims vignette); its rim directions are then traced forward through a real microlens (the
    nearest lens of a perfect MLA, moved to rho) over its aperture, and a circle is fitted to where they
    land. The chief ray goes from the visible pupil's centroid through the lens' nodal points."""
    lay = cfg.layout
    main = MainLens(cfg)
    mla = MicrolensArray(cfg)
    p = cfg.mla.pitch_um * 1e-3
    # the lens whose centre lies nearest (rho, rho)/sqrt(2); reported at its own radius
    col = int(np.clip(np.floor((rho_mm / np.sqrt(2) - mla.x0) / p), 0, cfg.mla.count_w - 1))
    row = int(np.clip(np.floor((rho_mm / np.sqrt(2) - mla.y0) / p), 0, cfg.mla.count_h - 1))
    X, Y = mla.x0 + (col + 0.5) * p, mla.y0 + (row + 0.5) * p
    rho = float(np.hypot(X, Y))
    tmax = 0.7 * cfg.main_lens.diameter_mm / lay.pupil_to_mla_mm + rho / lay.pupil_to_mla_mm
    t = np.linspace(-tmax, tmax, n_dir)
    tx, ty = (g.ravel() for g in np.meshgrid(t, t))
    nrm = np.sqrt(1 + tx * tx + ty * ty)
    k = tx.size
    r = Rays(np.full(k, X), np.full(k, Y), np.full(k, lay.z_mla_mm), -tx / nrm, -ty / nrm, -1 / nrm, np.ones(k))
    main.trace_back(r)
    visible = (r.w > 0).reshape(n_dir, n_dir)
    rim = (visible & ~ndimage.binary_erosion(visible)).ravel()
    rtx, rty = tx[rim], ty[rim]
    a = ((np.arange(n_ap) + 0.5) / n_ap - 0.5) * 0.9 * p
    ax, ay = (g.ravel() for g in np.meshgrid(a, a))
    TX, TY = np.repeat(rtx, ax.size), np.repeat(rty, ax.size)
    AX, AY = np.tile(ax, rtx.size), np.tile(ay, rtx.size)
    nn = np.sqrt(1 + TX * TX + TY * TY)
    z0 = -0.05  # MLA frame: mid-plane at 0
    rays = Rays(X + AX + TX * z0, Y + AY + TY * z0, np.full(TX.size, z0), TX / nn, TY / nn, 1 / nn, np.ones(TX.size))
    mla.trace(rays)
    rays.advance((lay.z_sensor_mm - lay.z_mla_mm - rays.z) / rays.N)
    w = rays.w.reshape(rtx.size, ax.size)
    lx = (rays.x.reshape(w.shape) * w).sum(1) / w.sum(1)
    ly = (rays.y.reshape(w.shape) * w).sum(1) / w.sum(1)
    c = np.linalg.lstsq(np.stack([lx, ly, np.ones_like(lx)], 1), lx * lx + ly * ly, rcond=None)[0]
    cx, cy = 0.5 * c[0], 0.5 * c[1]
    circle = float(np.hypot(cx, cy))
    # chief ray: through the rear nodal point (H') to the sensor, direction of the visible pupil's centroid
    z_h = lay.z_mla_mm + 0.5 * cfg.mla.thickness_um * 1e-3 - lay.micro.rear_principal
    f = lay.z_sensor_mm - z_h
    chief = float(np.hypot(X + f * tx[visible.ravel()].mean(), Y + f * ty[visible.ravel()].mean()))
    return rho, circle, chief


_RADIAL_CACHE: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
N_RADII = 16


def radial_maps(cfg):
    """(rho, circle, chief): sub-image centre radius (mm on the sensor) against the lens' radius (mm)."""
    key = config_to_toml(cfg)
    if key not in _RADIAL_CACHE:
        p = cfg.mla.pitch_um * 1e-3
        rmax = 0.5 * p * np.hypot(cfg.mla.count_w, cfg.mla.count_h)
        samples = [_pupil_image(cfg, r) for r in np.linspace(0.0, rmax, N_RADII)]
        _RADIAL_CACHE[key] = tuple(np.array(v) for v in zip(*samples))
    return _RADIAL_CACHE[key]


def _centres_px(cfg, errors, which: int):
    rho_s, circle, chief = radial_maps(cfg)
    gain = (circle if which == 0 else chief) / rho_s  # sub-image centre radius per lens radius
    x, y = _lens_centres_mm(cfg, errors)
    g = np.interp(np.hypot(x, y), rho_s, gain)
    s = cfg.sensor
    return x * g / (s.pixel_um * 1e-3) + 0.5 * (s.width_px - 1), y * g / (s.pixel_um * 1e-3) + 0.5 * (s.height_px - 1)


def true_centres(cfg, errors: ErrorMap | None = None):
    """(x, y) pixel arrays (rows, cols): centre of each lens' white-image sub-image, by ray tracing."""
    return _centres_px(cfg, errors, 0)


def chief_centres(cfg, errors: ErrorMap | None = None):
    """(x, y) pixel arrays: where the chief ray from the exit-pupil centre through each lens centre lands."""
    return _centres_px(cfg, errors, 1)


def layout_centres(cfg, errors: ErrorMap | None = None):
    """(x, y): the first-order layout's centres, `layout.subimage_pitch_px` apart about the sensor centre."""
    x, y = _lens_centres_mm(cfg, errors)
    g = cfg.layout.subimage_pitch_px / (cfg.mla.pitch_um * 1e-3)
    s = cfg.sensor
    return x * g + 0.5 * (s.width_px - 1), y * g + 0.5 * (s.height_px - 1)


# ------------------------------------------------------------------------------------- synthetic frames


def synthetic_white(shape=(420, 440), rows=18, cols=19, pitch=20.05, rotation_deg=0.0, offset=(0.0, 0.0),
                    radius=10.2, edge=0.3, level=0.6, noise=0.0, seed=0, shifts=None):
    """A white-like frame of touching discs with exactly known centres (no optics, no render).

    Lens U(m,n) sits at frame centre + offset + R(rotation) ((n - (cols+1)/2) p, (m - (rows+1)/2) p), plus
    `shifts[m-1, n-1]` (x, y) px if given; each disc is a logistic edge of width `edge`, integrated over
    the pixel area (4x4 supersampling). Noise: Gaussian with variance noise^2 * level * signal.
    Returns (image float32, true_x, true_y)."""
    h, w = shape
    th = np.radians(rotation_deg)
    v, u = np.mgrid[0:rows, 0:cols].astype(float)
    x = (u - 0.5 * (cols - 1)) * pitch
    y = (v - 0.5 * (rows - 1)) * pitch
    tx = 0.5 * (w - 1) + offset[0] + x * np.cos(th) + y * np.sin(th)
    ty = 0.5 * (h - 1) + offset[1] - x * np.sin(th) + y * np.cos(th)
    if shifts is not None:
        tx = tx + shifts[..., 0]
        ty = ty + shifts[..., 1]
    reach = int(np.ceil(radius + 6 * edge + 2))
    dy, dx = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    dy, dx = dy.ravel(), dx.ravel()
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    img = np.zeros(h * w)
    cx, cy = tx.ravel(), ty.ravel()
    ix, iy = np.rint(cx).astype(int), np.rint(cy).astype(int)
    px, py = ix[:, None] + dx[None, :], iy[:, None] + dy[None, :]
    ok = (px >= 0) & (px < w) & (py >= 0) & (py < h)
    val = np.zeros(px.shape)
    for sy in sub:
        for sx in sub:
            r = np.hypot(px + sx - cx[:, None], py + sy - cy[:, None])
            val += 1.0 / (1.0 + np.exp(np.clip((r - radius) / edge, -50, 50)))
    val *= level / sub.size ** 2
    img += np.bincount((py * w + px)[ok], weights=val[ok], minlength=h * w)
    img = img.reshape(h, w)
    if noise:
        rng = np.random.default_rng(seed)
        img = img + rng.normal(0.0, 1.0, img.shape) * noise * np.sqrt(level * np.maximum(img, 0.0))
    return img.astype(np.float32), tx, ty
