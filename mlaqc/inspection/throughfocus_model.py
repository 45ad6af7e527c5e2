"""The through-focus model of one lens' pair of spots (`ModelCurves`): traced through the camera's optics, paraxial, and cached on disk."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from mlaqc.inspection.throughfocus_optics import focal_rel_of_radius, optics
from mlaqc.inspection.throughfocus_spots import MIN_WINDOW_PX, RING_PX, WINDOW_SIGMAS, Spots, _spot_window, moments
from mlaqc.optics.config import CameraConfig, require_thick_main_lens
from mlaqc.optics.lattice import SQRT3_2, Lattice
from mlaqc.optics.throughfocus import ThroughFocus, frame_config

@dataclass(frozen=True)
class ModelCurves:
    """What the camera's optics make of one lens' pair of spots, per shell (squared distance from its
    pinhole, in lenses), traced at the radius errors `eps`:

    - `curves`: the geometric D(eps) - D(0) on the axis (exact second moments of the traced rays, px^2),
      which gives the `gain` over the paraxial slope;
    - `field_a`, `field_b`: how the geometric D(0) changes over the field: at field radius r,
      D(0; r) - D(0; 0) = a(r) + b(r) cos 2 phi, phi the angle between the lens' offset from its pinhole
      and the field direction (the main lens' field curvature and astigmatism);
    - `spot_m2` (traced models only): the second moment the analysis *measures* of each frame's spot of
      the shell's traced lens (`offsets`: (a, b) lenses from the pinhole along and across the field),
      at each field radius and radius error, with the spot's centre at each of P x P sub-pixel positions:
      the traced rays binned into pixels, put through the config's image formation (diffraction,
      crosstalk, as `apply_formation`) and read by `_spot_window` and `moments` in the pair's common
      window, exactly as a frame's spots are. A spot of a pixel or two is undersampled: what its moment
      reads depends on where it falls on the pixels, by up to +-0.25 px^2, by how much swinging with the
      spot's size (a period of about 4 % in eps), and the phase-averaged reading is not the geometric one
      (the window cuts the formation's tails differently for each size). Reading each lens on its own
      spots' model removes both."""

    eps: np.ndarray
    shells: np.ndarray  # (S,) int
    curves: np.ndarray  # (S, E) px^2
    gain: float  # the centre shell's slope at eps = 0 over the paraxial one
    field_mm: np.ndarray = field(default_factory=lambda: np.zeros(1))  # (R,) field radii, from 0
    field_a: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))  # (S, R) px^2
    field_b: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))  # (S, R) px^2
    # (S, 2) traced lens (a, b), a >= b >= 0 (hex: float (x, y) pitches, 0 <= phi <= 30 degrees)
    offsets: np.ndarray = field(default_factory=lambda: np.zeros((1, 2), np.int64))
    spot_m2: np.ndarray | None = None  # (S, R, 2, E, P, P) px^2: [.., frame (+u, -u), eps, y phase, x phase]
    key: str = ""  # `model_key` of a traced model

    def field_offset(self, shell: np.ndarray, dxy: np.ndarray, pin_mm: np.ndarray) -> np.ndarray:
        """D(0) of each lens' disc position and orientation minus its shell's on-axis D(0), px^2."""
        k = self.shell_index(shell)
        r = np.hypot(pin_mm[:, 0], pin_mm[:, 1])
        f2 = self.field_mm ** 2
        a = _interp_rows(r * r, f2, self.field_a, k)
        b = _interp_rows(r * r, f2, self.field_b, k)
        return a + b * _cos2(dxy, pin_mm)

    def shell_index(self, shell: np.ndarray) -> np.ndarray:
        """Index into `shells` of each lens' shell (the nearest one the model has)."""
        s = np.asarray(shell)
        j = np.clip(np.searchsorted(self.shells, s), 1, max(len(self.shells) - 1, 1))
        if len(self.shells) == 1:
            return np.zeros(s.shape, np.int64)
        lo = self.shells[j - 1]
        return np.where(np.abs(s - lo) <= np.abs(self.shells[j] - s), j - 1, j)


def _interp_rows(x: np.ndarray, xp: np.ndarray, fp: np.ndarray, k: np.ndarray) -> np.ndarray:
    """np.interp(x[i], xp, fp[k[i]]) for every i (rows of fp picked per point; held beyond the ends)."""
    if len(xp) == 1:
        return fp[k, 0]
    j = np.clip(np.searchsorted(xp, x) - 1, 0, len(xp) - 2)
    t = np.clip((x - xp[j]) / (xp[j + 1] - xp[j]), 0.0, 1.0)
    return fp[k, j] * (1.0 - t) + fp[k, j + 1] * t


def _cos2(dxy: np.ndarray, pin_mm: np.ndarray) -> np.ndarray:
    """cos 2 phi, phi the angle between each lens' offset from its pinhole and the field direction."""
    r2 = pin_mm[:, 0] ** 2 + pin_mm[:, 1] ** 2
    d2 = (dxy[:, 0] ** 2 + dxy[:, 1] ** 2).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        along = (dxy[:, 0] * pin_mm[:, 0] + dxy[:, 1] * pin_mm[:, 1]) ** 2
        return np.where((d2 > 0) & (r2 > 0), 2.0 * along / (d2 * r2) - 1.0, 0.0)


MODEL_EPS_STEP = 0.005  # the model is traced at radius errors this far apart ...
MODEL_EPS_MAX = 0.15  # ... out to +-15 % (beyond, the end segments extend)
MODEL_EPS = tuple(float(v) for v in np.round(np.arange(-MODEL_EPS_MAX, MODEL_EPS_MAX + 1e-9, MODEL_EPS_STEP), 6))
MODEL_RAYS = 500_000  # pupil rays per frame of the model (a low-discrepancy set; only those reaching a shell's lens are traced on)
MODEL_PHASES = 8  # sub-pixel spot positions per axis at which the model's spots are read
MODEL_FINE = 16  # ray bins per pixel side before the model's spots are pixelated (a multiple of MODEL_PHASES)
SPOT_REACH_MM = 0.03  # a model spot's rays are those within this of its centroid (|1 - sV| <= 0.5)
# a lens alone among healthy ones is traced with the rays that meet the MLA's front vertex plane within this many
# pitches of its centre: a lone lens' aperture reaches 0.54 pitch from it at +15 %, sideways (Table 1)
NEAR_PITCHES = 0.85
FIELD_POINTS = 3  # field radii the model is traced at, 0 to the array's corner, even in r^2 (its D is linear in r^2)
MODEL_FORMAT = 3  # the model's definition (3: each lens traced alone among healthy ones) and its cache file's layout


def model_curves(cfg: CameraConfig, u_mm: float, f_number: float, r_in: float, *, rebuild: bool = False) -> ModelCurves:
    """The camera's model of one lens' pair of spots, shell by shell out to `r_in` lenses (see
    ModelCurves): from the package, else the disk cache (keyed by the optics, the image formation, the
    pixel and the pair geometry: `model_key`; `mlaqc.models.store`), else traced now and cached (Table 1:
    28 s at +-5 mm f/11, its one shell, on one core: each lens traced alone takes 1.6x the 17 s of an array
    of flawed lenses); `rebuild` traces it again whatever is stored."""
    require_thick_main_lens(cfg, "the through-focus measurement (pinhole frames)")
    return _model_curves(cfg, abs(float(u_mm)), float(f_number), round(max(float(r_in), 0.0), 4), rebuild)


def model_key(cfg: CameraConfig, u_mm: float, f_number: float, r_in: float) -> str:
    """Content hash of everything that shapes `model_curves`: the main lens, the MLA's design (and its
    lens count: the field's extent), the distances, the pixel, the formation's blur, Fresnel, the pair
    geometry and the model's own settings."""
    import hashlib
    import json

    from mlaqc.models.reference import geometry_hash_view, mla_hash_view
    from mlaqc.optics.formation import blur_key

    d = cfg.to_dict()
    keep = {"main_lens": d["main_lens"], "mla": mla_hash_view(d["mla"], design=True), "geometry": geometry_hash_view(d["geometry"]),
            "pixel_um": cfg.pixel_at_mla_um, "fresnel": d["trace"]["fresnel"],
            **blur_key(cfg),
            "protocol": [abs(float(u_mm)), float(f_number), round(max(float(r_in), 0.0), 4)],
            "model": [MODEL_FORMAT, list(MODEL_EPS), MODEL_RAYS, MODEL_PHASES, MODEL_FINE, SPOT_REACH_MM, NEAR_PITCHES,
                      FIELD_POINTS, WINDOW_SIGMAS, MIN_WINDOW_PX, RING_PX, int(math.floor(cfg.layout.subimage_pitch_px / 2))]}
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]


_MODEL_ARRAYS = ("eps", "shells", "curves", "field_mm", "field_a", "field_b", "offsets", "spot_m2")


@functools.lru_cache(maxsize=16)
def _model_curves(cfg: CameraConfig, u_mm: float, f_number: float, r_in: float, rebuild: bool = False) -> ModelCurves:
    from mlaqc.models.store import stored

    key = model_key(cfg, u_mm, f_number, r_in)
    return stored(f"throughfocus_{key}.npz", lambda: _as_stored(trace_model(cfg, u_mm, f_number, r_in)),
                  lambda path: load_model(path, key), save_model, rebuild=rebuild)


def _as_stored(curves: ModelCurves) -> ModelCurves:
    """The model as its file keeps it (spot_m2 in float32), so that a traced and a read model read alike."""
    return replace(curves, spot_m2=curves.spot_m2.astype(np.float32).astype(np.float64))


def save_model(curves: ModelCurves, path) -> None:
    """Write `curves` (a traced model) as compressed NPZ, atomically, under its `model_key` (`key`)."""
    import io

    from mlaqc.atomic import write_bytes_atomic

    buf = io.BytesIO()
    np.savez_compressed(buf, key=curves.key, gain=curves.gain,
                        **{k: (getattr(curves, k).astype(np.float32) if k == "spot_m2" else getattr(curves, k))
                           for k in _MODEL_ARRAYS})
    write_bytes_atomic(path, buf.getvalue())


def load_model(path, key: str) -> ModelCurves:
    """Read a model written by `save_model`; ValueError if it is not the model of `key`."""
    with np.load(path, allow_pickle=False) as z:
        if str(z["key"]) != key:
            raise ValueError(f"{path} holds the through-focus model {z['key']}, not {key}")
        arrays = {k: z[k] for k in _MODEL_ARRAYS}
        gain = float(z["gain"])
    arrays["spot_m2"] = arrays["spot_m2"].astype(np.float64)
    return ModelCurves(gain=gain, key=key, **arrays)


class _Landing:
    """The rays of one pinhole (`field_mm` along x from the axis, under the patch's centre lens; `pupil`:
    (2, N) uniform draws on the pupil) that reach lenses `targets` of the patch MLA or their neighbours,
    traced through the main lens once; `land(eps)` traces them on to the sensor, each target's through an
    MLA where that lens alone carries the radius error eps, as a defect sits among healthy lenses: with
    sag-intersection boundaries a lens' aperture is where its sags meet its neighbours', so a lone lens of
    another curvature gains or loses aperture to them (a lone -10 % lens 6 % of its light), which an array
    of such lenses does not. Its spot is then read from every ray that lands near it, its neighbours'
    cells' included."""

    def __init__(self, patch: CameraConfig, tf: ThroughFocus, field_mm: float, targets: np.ndarray, pupil: np.ndarray):
        from mlaqc.optics.errormap import ErrorMap
        from mlaqc.optics.raytrace import Camera
        from mlaqc.optics.render import source_region
        from mlaqc.optics.scene import sample_points
        from mlaqc.optics.throughfocus import magnification

        targets = np.unique(targets)  # numbered in this order
        self.n = patch.mla.count_w
        if patch.mla.packing == "hex":  # the centre lens, not the patch's bounding box, under the pinhole
            rows, cols = patch.mla.count_h, patch.mla.count_w
            xc = float(Lattice.of(patch).position(rows // 2, cols // 2)[0])
            self.zero = ErrorMap.zeros(rows, cols, "hex").with_globals(mla_shift_x_um=1e3 * (field_mm - xc))
        else:
            self.zero = ErrorMap.zeros(self.n, self.n).with_globals(mla_shift_x_um=1e3 * field_mm)
        self.fc = frame_config(patch, tf)
        self.cam = Camera(self.fc, self.zero)
        x_obj = -field_mm / magnification(self.fc)  # the main lens inverts
        r = sample_points(source_region(self.cam), pupil, x_obj, 0.0, square=True)
        self.cam.main.trace(r)
        self.cam.to_mla(r)
        mla = self.cam.mla
        with np.errstate(invalid="ignore", divide="ignore"):
            hx, hy = r.x + (mla.z_front - r.z) * r.L / r.N, r.y + (mla.z_front - r.z) * r.M / r.N
        cell, on = mla.cell_of(hx, hy)
        lit = on & (r.w > 0)
        reach2 = (NEAR_PITCHES * mla.p) ** 2
        picks = [np.flatnonzero(lit & ((hx - mla.gx[t]) ** 2 + (hy - mla.gy[t]) ** 2 <= reach2)) for t in targets]
        # each target's rays together (sums by cumulative sums): those that reach its cell or its edges
        self.lens = np.concatenate([np.full(len(k), i) for i, k in enumerate(picks)])
        self.own = np.concatenate([cell[k] == t for k, t in zip(picks, targets)])
        self.base = [np.concatenate([a[k] for k in picks]) for a in (r.x, r.y, r.z, r.L, r.M, r.N, r.w)]
        self.targets = targets
        self.count = len(targets)
        self.bounds = np.searchsorted(self.lens, np.arange(self.count + 1))

    def lone_arrays(self, e: float) -> list:
        """Per target, the patch MLA in which that lens alone carries the radius error e (the MLA does not
        depend on the frame's object distance: both frames of a pair trace through the same arrays)."""
        from mlaqc.optics.errormap import ErrorMap
        from mlaqc.optics.raytrace import MicrolensArray

        shape = self.zero.shape
        arrays = []
        for target in self.targets:
            rel = np.zeros(shape)
            rel.flat[target] = e
            em = ErrorMap(shape, {**self.zero.lens, "radius_front_rel": rel, "radius_back_rel": rel},
                          self.zero.globals, self.zero.packing)
            arrays.append(MicrolensArray(self.fc, em))
        return arrays

    def land(self, arrays: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sensor x, y (mm, camera frame) and weight of every ray, each target's traced through its own
        array of `lone_arrays` (weight 0: lost, or beyond SPOT_REACH_MM of its lens' spot: a ray the
        vertex-plane cell gave to the wrong lens lands a pitch away)."""
        from mlaqc.optics.raytrace import Rays

        out = []
        for i, mla in enumerate(arrays):
            part = slice(self.bounds[i], self.bounds[i + 1])
            rr = Rays(*(a[part].copy() for a in self.base))
            mla.trace(rr)
            with np.errstate(invalid="ignore", divide="ignore"):
                t = (self.cam.z_sensor - self.cam.z_mla - rr.z) / rr.N
            w = np.where(np.isfinite(rr.w) & np.isfinite(t), rr.w, 0.0)
            out.append((np.where(w > 0, rr.x + t * rr.L, 0.0), np.where(w > 0, rr.y + t * rr.M, 0.0), w))
        x, y, w = (np.concatenate(v) for v in zip(*out))
        mx, my = self.centroid(x, y, w * self.own)  # first about the rays that entered the lens' own cell
        for again in (True, False):
            w = np.where((np.abs(x - mx[self.lens]) < SPOT_REACH_MM) & (np.abs(y - my[self.lens]) < SPOT_REACH_MM), w, 0.0)
            if again:
                mx, my = self.centroid(x, y, w)
        return x, y, w

    def sums(self, v: np.ndarray) -> np.ndarray:
        """Per target, the sum of v over its rays."""
        out = np.zeros(self.count)
        start = self.bounds[:-1]
        some = self.bounds[1:] > start  # (reduceat would give an empty run the next ray's value)
        if some.any():
            out[some] = np.add.reduceat(v, start[some])
        return out

    def centroid(self, x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(invalid="ignore", divide="ignore"):
            sw = self.sums(w)
            return self.sums(w * x) / sw, self.sums(w * y) / sw

    def moment(self, x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Geometric second moment x + y (mm^2) of each target's spot."""
        mx, my = self.centroid(x, y, w)
        dx, dy = x - mx[self.lens], y - my[self.lens]
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.sums(w * (dx * dx + dy * dy)) / self.sums(w)


def _pixelated(land: _Landing, x: np.ndarray, y: np.ndarray, w: np.ndarray, pick: np.ndarray, pixel_mm: float,
               half: int, psf: np.ndarray) -> np.ndarray:
    """(T, P, P, n, n) the spots of `land`'s targets `pick` as a frame holds them, each centred on the
    window's centre pixel shifted by (i, j) / P px (y, x): rays binned into pixels, then the formation's
    PSF (`apply_formation`'s order), n = 2 half + 1. Each spot sums to 1."""
    from scipy.signal import fftconvolve

    P, Q = MODEL_PHASES, MODEL_FINE
    step = Q // P
    hs = int(math.ceil(SPOT_REACH_MM / pixel_mm)) + 1  # the spot's own half-width, whatever its phase
    ns = 2 * hs + 1
    pad = (P - 1) * step
    F = ns * Q + pad
    T = len(pick)
    slot = np.full(land.count, -1)
    slot[pick] = np.arange(T)
    mx, my = (np.nan_to_num(v) for v in land.centroid(x, y, w))  # a lens no ray reaches: no spot
    t = slot[land.lens]
    fx = np.floor(((x - mx[land.lens]) / pixel_mm + hs + 0.5) * Q).astype(np.int64) + pad
    fy = np.floor(((y - my[land.lens]) / pixel_mm + hs + 0.5) * Q).astype(np.int64) + pad
    ok = (t >= 0) & (w > 0) & (fx >= pad) & (fx < F) & (fy >= pad) & (fy < F)
    fine = np.bincount((t[ok] * F + fy[ok]) * F + fx[ok], w[ok], T * F * F).reshape(T, F, F)
    with np.errstate(invalid="ignore", divide="ignore"):
        fine /= fine.sum(axis=(1, 2), keepdims=True)
    integ = np.zeros((T, F + 1, F + 1))
    integ[:, 1:, 1:] = np.cumsum(np.cumsum(fine, axis=1), axis=2)
    bound = np.arange(ns + 1)[None, :] * Q - np.arange(P)[:, None] * step + pad  # (P, ns + 1): phase i shifts by +i/P px
    cut = integ[:, bound[:, :, None, None], bound[None, None, :, :]]  # (T, P, ns + 1, P, ns + 1)
    pix = np.diff(np.diff(cut, axis=2), axis=4).transpose(0, 1, 3, 2, 4)  # (T, P, P, ns, ns)
    if psf.shape != (1, 1):
        pix = np.maximum(fftconvolve(pix, psf[None, None, None], mode="full", axes=(3, 4)), 0.0)
    c = pix.shape[-1] // 2  # the spot's centre pixel
    n = 2 * half + 1
    out = np.zeros((T, P, P, n, n))
    a = min(c, half)
    out[..., half - a:half + a + 1, half - a:half + a + 1] = pix[..., c - a:c + a + 1, c - a:c + a + 1]
    return out


def _read_model_spots(plus: np.ndarray, minus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the analysis measures of model spot images (..., n, n) of the +u and -u frames of one lens at
    the same sub-pixel position: each frame's window (`_spot_window`), the pair's common one, `moments`."""
    shape = plus.shape[:-2]
    out = []
    sps = []
    for img in (plus, minus):
        cells = img.reshape(-1, *img.shape[-2:])
        zeros = np.zeros(len(cells))
        sp = Spots(cells, zeros.astype(np.int64), zeros.astype(np.int64), zeros, 0.0, zeros.astype(bool))
        sps.append((sp, *_spot_window(sp, 1.0)))
    w = np.maximum(sps[0][3], sps[1][3])
    for sp, cx, cy, _ in sps:
        out.append(moments(sp, cx, cy, w, 1.0, variance=False)[2].reshape(shape))
    return out[0], out[1]


def trace_model(cfg: CameraConfig, u_mm: float, f_number: float, r_in: float) -> ModelCurves:
    """Trace `model_curves` (no cache)."""
    from mlaqc.models.signatures import patch_config
    from mlaqc.optics.formation import formation_kernels

    reach = int(math.floor(r_in))
    n = 2 * reach + 3
    patch = patch_config(cfg, n)  # the pinhole's image on the centre lens
    opt = optics(cfg)
    half = int(math.floor(cfg.layout.subimage_pitch_px / 2))
    psf = formation_kernels(cfg, (1, 1), with_prnu=False).psf
    if cfg.mla.packing == "hex":
        shells, along, across, offsets, cos_along, cos_across = _hex_model_lenses(patch, r_in)
        S = len(shells)
    else:
        # one lens per shell, (a, b) with a >= b >= 0 (a along x), and its mirror (b, a) for the field's
        # orientation term
        uniq = {}
        for a in range(reach + 1):
            for b in range(a + 1):
                if a * a + b * b <= r_in * r_in:
                    uniq.setdefault(a * a + b * b, (a, b))
        shells = np.array(sorted(uniq))
        S = len(shells)
        c = n // 2
        along = np.array([(c + uniq[s][1]) * n + (c + uniq[s][0]) for s in shells])  # row c + b, col c + a
        across = np.array([(c + uniq[s][0]) * n + (c + uniq[s][1]) for s in shells])
    eps = np.array(MODEL_EPS)
    zero = int(np.argmin(np.abs(eps)))
    tf = ThroughFocus(focus_offset_mm=u_mm, f_number=f_number)
    frames = (replace(tf, focus_offset_mm=u_mm), replace(tf, focus_offset_mm=-u_mm))
    p = cfg.mla.pitch_um * 1e-3
    if cfg.mla.packing == "hex":
        corner = 0.5 * p * math.hypot(*Lattice.of(cfg).span_uv)
    else:
        corner = 0.5 * p * math.hypot(cfg.mla.count_w - 1, cfg.mla.count_h - 1)
    radii = corner * np.sqrt(np.linspace(0.0, 1.0, FIELD_POINTS))
    targets = np.concatenate([along, across])
    P = MODEL_PHASES
    spot = np.zeros((S, len(radii), 2, len(eps), P, P))
    geo = np.zeros((len(radii), 2, len(eps), 2 * S))  # geometric x + y, mm^2
    slots = np.searchsorted(np.unique(targets), targets)  # _Landing numbers its targets sorted
    from mlaqc.optics import lowdisc

    pupil = lowdisc.batch_uniforms(0x7F0C, MODEL_RAYS, 2)
    for i, rf in enumerate(radii):
        lands = [_Landing(patch, f, rf, targets, pupil) for f in frames]
        for j, e in enumerate(eps):
            imgs = []
            arrays = lands[0].lone_arrays(e)
            for k, land in enumerate(lands):
                x, y, w = land.land(arrays)
                geo[i, k, j] = land.moment(x, y, w)[slots]
                imgs.append(_pixelated(land, x, y, w, slots[:S], opt.pixel_mm, half, psf))
            m2p, m2m = _read_model_spots(imgs[0], imgs[1])
            spot[:, i, 0, j], spot[:, i, 1, j] = m2p, m2m
    d = (geo[:, 0] - geo[:, 1]) / opt.pixel_mm ** 2  # (R, E, 2S)
    curves = d[0, :, :S].T - d[0, zero, :S][:, None]  # (S, E) on the axis
    slope = (curves[0, zero + 1] - curves[0, zero - 1]) / (eps[zero + 1] - eps[zero - 1])
    dc = (focal_rel_of_radius(cfg, eps[zero + 1]) - focal_rel_of_radius(cfg, eps[zero - 1])) \
        / (eps[zero + 1] - eps[zero - 1]) * (1.0 - opt.c0)  # dc/deps of c = 1 - s P at the design lens
    paraxial = -4.0 * opt.aperture_i_px2 * (opt.g(u_mm) + opt.g(-u_mm)) * dc
    d0 = d[:, zero] - d[:1, zero]  # (R, 2S): D(0) over the field, from the axis'
    d_along, d_across = d0[:, :S].T, d0[:, S:].T  # (S, R)
    if cfg.mla.packing == "hex":  # D(0) = a + b cos 2 phi at the two lenses' cos 2 phi
        dc2 = (cos_along - cos_across)[:, None]
        field_b = np.where(shells[:, None] > 0, (d_along - d_across) / np.where(dc2 == 0, 1.0, dc2), 0.0)
        field_a = d_along - field_b * cos_along[:, None]
    else:
        cos2 = np.array([(uniq[s][0] ** 2 - uniq[s][1] ** 2) / s if s else 0.0 for s in shells])
        field_b = np.where(np.abs(cos2)[:, None] > 1e-9, (d_along - d_across) / (2.0 * np.where(cos2 == 0, 1.0, cos2))[:, None], 0.0)
        field_a = 0.5 * (d_along + d_across)
        offsets = np.array([uniq[s] for s in shells], np.int64)
    return ModelCurves(eps, shells, curves, float(slope / paraxial), radii, field_a, field_b, offsets, spot,
                       model_key(cfg, u_mm, f_number, r_in))


def _hex_model_lenses(patch: CameraConfig, r_in: float):
    """The hex model's traced lenses: per shell (dq^2 + dr^2 + dq dr <= r_in^2, axial steps from the patch's
    centre lens) the one at 0 <= phi <= 30 degrees from +x (every hex offset maps onto it by the lattice's
    symmetry) and the same lens turned 60 degrees (a lattice point at another cos 2 phi, for the field's
    orientation term). Returns shells, their flat patch indices (along, turned), offsets (x, y pitches,
    float) and both lenses' cos 2 phi."""
    rows, cols = patch.mla.count_h, patch.mla.count_w
    r0, q0 = rows // 2, cols // 2 - (rows // 2) // 2
    k = int(math.floor(r_in)) + 1
    pick: dict[int, tuple[int, int]] = {}
    for dr in range(k + 1):
        for dq in range(-k, k + 1):
            x, y = dq + 0.5 * dr, SQRT3_2 * dr
            sh = dq * dq + dr * dr + dq * dr
            if sh <= r_in * r_in + 1e-9 and x >= 0 and y <= x / math.sqrt(3.0) + 1e-9:
                pick.setdefault(sh, (dq, dr))
    shells = np.array(sorted(pick), np.int64)

    def flat(dq: int, dr: int) -> int:
        r = r0 + dr
        return r * cols + (q0 + dq) + r // 2

    def cos2(dq: int, dr: int) -> float:
        x, y = dq + 0.5 * dr, SQRT3_2 * dr
        return (x * x - y * y) / (x * x + y * y) if dq or dr else 0.0

    steps = [pick[s] for s in shells]
    turned = [(-dr, dq + dr) for dq, dr in steps]  # 60 degrees round: a1 -> a2, a2 -> a2 - a1
    return (shells, np.array([flat(*v) for v in steps]), np.array([flat(*v) for v in turned]),
            np.array([(dq + 0.5 * dr, SQRT3_2 * dr) for dq, dr in steps], np.float64),
            np.array([cos2(*v) for v in steps]), np.array([cos2(*v) for v in turned]))


def paraxial_curves(cfg: CameraConfig, u_mm: float, shells: np.ndarray) -> ModelCurves:
    """The paraxial D(eps) - D(0) (a scaled-aperture spot, no aberrations), the same for every shell."""
    opt = optics(cfg)
    eps = np.array(MODEL_EPS)
    c = 1.0 - (1.0 - opt.c0) / (1.0 + focal_rel_of_radius(cfg, eps))
    gp, gm = opt.g(u_mm), opt.g(-u_mm)
    d = 2.0 * opt.aperture_i_px2 * ((c - gp) ** 2 - (c + gm) ** 2)
    d = d - d[np.argmin(np.abs(eps))]
    flat = np.zeros((len(shells), 1))
    return ModelCurves(eps, np.asarray(shells), np.tile(d, (len(shells), 1)), 1.0, np.zeros(1), flat, flat)


__all__ = ["ModelCurves", "model_curves", "paraxial_curves", "trace_model", "model_key", "save_model", "load_model"]
