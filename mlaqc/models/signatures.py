"""Signature table of the inverse model: how each error type, at each magnitude, changes a lens' indexes.

Rendered by the tracer on a 9 x 9-lens patch of the camera (hex: 9 columns x 11 rows, `patch_shape`) (same optics, geometry and pixels), the error
on the centre lens and the same random draws with and without it, so the differences are nearly free of
Monte-Carlo noise. Directional errors are rendered at direction 0; their features are taken along and
across the shift they cause, so a measured lens is compared after rotating into its own shift direction.
On hex, where a shift across the rows registers otherwise than one along them, pitch and decenter are
rendered at 90° too (`SignatureTable.across`, `to_along`). Rendered at several sub-image blurs (`BLUR_VARIANTS`: the geometric image, the modelled diffraction and
crosstalk, and wider), each with the rim width the calibration measures on it, so that a frame is
classified with the tables interpolated to its own rim width (`SignatureSet.matched`). Cached on disk
keyed by the optics; the default camera's tables ship in the package.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mlaqc.inspection.metrics import compute_metrics
from mlaqc.inspection.metrics_kernels import N_RING
from mlaqc.models.reference import ReferenceModel, build_reference, geometry_hash_view, mla_hash_view
from mlaqc.models.store import stored_json
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.formation import apply_formation, blur_key, formation_kernels
from mlaqc.optics.lattice import SQRT3_2, Lattice
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene

FEATURES = ("shift_par", "shift_perp", "asym_par", "asym_perp", "blur", "flux", "ssim", "sharpness")
RINGS = tuple(f"ring{k}" for k in range(N_RING))  # the residual profile: same in every direction
PATCH = 9
TABLE_VERSION = 5  # 5: indexes against the bilinearly interpolated reference, tapered window edge
# The blurs the tables are rendered at: None = the tracer's geometric image alone; a number = the sensor
# formation (diffraction, crosstalk: mlaqc.optics.formation) plus a Gaussian of that sigma in px (a
# defocused main lens, a wider pixel response, another wavelength). A frame is classified with the tables
# interpolated to its own measured rim width.
BLUR_VARIANTS: tuple[float | None, ...] = (None, 0.0, 0.4, 0.7, 1.0)


@dataclass(frozen=True)
class ErrorKind:
    """One error type of the table: magnitudes rendered, their unit, and the error-map fields."""

    name: str
    magnitudes: tuple[float, ...]
    unit: str
    directional: bool
    fields: Callable[[float], dict[str, float]]


KINDS = (
    ErrorKind("pitch", (0.5, 1.0, 2.0, 3.0, 5.0, 8.0), "µm", True, lambda v: {"pitch_um": v, "pitch_dir_deg": 0.0}),
    ErrorKind("decenter", (2.0, 5.0, 8.0, 12.0, 20.0), "µm", True, lambda v: {"decenter_um": v, "decenter_dir_deg": 0.0}),
    ErrorKind("radius", (-0.3, -0.2, -0.1, -0.05, -0.02, 0.02, 0.05, 0.1, 0.2, 0.3), "rel", False,
              lambda v: {"radius_front_rel": v, "radius_back_rel": v}),
    ErrorKind("tilt", (1.0, 2.0, 4.0, 8.0), "deg", True, lambda v: {"tilt_x_deg": v}),
    ErrorKind("thickness", (-8.0, -4.0, -2.0, 2.0, 4.0, 8.0), "µm", False, lambda v: {"thickness_um": v}),
)
KIND_BY_NAME = {k.name: k for k in KINDS}


def physical_kinds(cfg: CameraConfig) -> tuple[ErrorKind, ...]:
    """The error kinds this MLA can have: no decenter where a surface is flat (plano-convex), since shifting
    a plane against the other surface changes nothing; a shifted lens is then a pitch error."""
    if cfg.mla.flat_sided:
        return tuple(k for k in KINDS if k.name != "decenter")
    return KINDS


@dataclass(frozen=True)
class SignatureTable:
    """features[kind] is (len(magnitudes), len(FEATURES)) and rings[kind] (len(magnitudes), len(RINGS));
    phi0_deg[kind] is the direction of the shift an error at direction 0 causes (so error direction =
    measured shift direction - phi0). `settings`: how the table was rendered (rays, seed), for the record."""

    magnitudes: dict[str, np.ndarray]
    features: dict[str, np.ndarray]
    phi0_deg: dict[str, float]
    key: str
    rings: dict[str, np.ndarray]
    settings: dict = dataclasses.field(default_factory=dict)
    # hex only: the ACROSS_KINDS rendered across the rows (ACROSS_DEG), each (len(magnitudes), FEATURES +
    # RINGS) taken along its own shift as `features` are; empty on a square lattice (isotropic there)
    across: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    def to_json_dict(self) -> dict:
        kinds = {k: {"magnitudes": self.magnitudes[k].tolist(), "features": self.features[k].tolist(),
                     "rings": self.rings[k].tolist(), "phi0_deg": self.phi0_deg[k]} for k in self.magnitudes}
        for k, a in self.across.items():
            kinds[k]["across"] = a.tolist()
        return {"format": "mlaqc-signatures", "version": TABLE_VERSION, "key": self.key, "features": list(FEATURES),
                "rings": list(RINGS), "settings": self.settings, "kinds": kinds}

    @classmethod
    def from_json_dict(cls, d: dict) -> SignatureTable:
        kinds = d["kinds"]
        return cls({k: np.asarray(v["magnitudes"], float) for k, v in kinds.items()},
                   {k: np.asarray(v["features"], float) for k, v in kinds.items()},
                   {k: float(v["phi0_deg"]) for k, v in kinds.items()}, d["key"],
                   {k: np.asarray(v["rings"], float) for k, v in kinds.items()}, dict(d.get("settings", {})),
                   {k: np.asarray(v["across"], float) for k, v in kinds.items() if "across" in v})

    def across_table(self) -> SignatureTable:
        """The table as a lens shifted across the rows sees it: the ACROSS_KINDS' curves rendered at
        ACROSS_DEG, their shift and tilt columns kept from along the rows (a lens' y offset and tilt are
        mapped to the along-row scale first, `to_along`); this table itself where nothing was rendered
        across (square, older tables)."""
        if not self.across:
            return self
        cache = self.__dict__.setdefault("_across", {})
        if "t" not in cache:
            n = len(FEATURES)
            feats, rings = dict(self.features), dict(self.rings)
            for k, a in self.across.items():
                feats[k] = np.concatenate([self.features[k][:, :4], a[:, 4:n]], axis=1)
                rings[k] = a[:, n:]
            cache["t"] = SignatureTable(dict(self.magnitudes), feats, dict(self.phi0_deg), self.key, rings,
                                        dict(self.settings))
        return cache["t"]


@dataclass(frozen=True)
class SignatureSet:
    """The signature tables of one optics at several sub-image blurs, sharpest first; each table's
    `settings["edge_width_px"]` is the rim width the calibration measures on its healthy lenses."""

    tables: tuple[SignatureTable, ...]
    key: str

    def edge_widths(self) -> np.ndarray:
        return np.array([t.settings.get("edge_width_px", np.nan) for t in self.tables], float)

    def matched(self, edge_width_px: float) -> SignatureTable:
        """The table for a frame whose rim width is `edge_width_px`: linear between the two variants that
        bracket it, the nearest end outside them (and the formation's variant if it is unknown)."""
        widths = self.edge_widths()
        ok = np.isfinite(widths)
        if not ok.any() or len(self.tables) == 1:
            return self.tables[0]
        if not np.isfinite(edge_width_px):
            default = [k for k, t in enumerate(self.tables) if t.settings.get("extra_blur_px") == 0.0]
            return self.tables[default[0] if default else 0]
        order = np.argsort(np.where(ok, widths, np.inf))[: int(ok.sum())]
        w = np.clip(edge_width_px, widths[order[0]], widths[order[-1]])
        cache = self.__dict__.setdefault("_matched", {})
        key = round(float(w), 3)
        if key not in cache:
            j = int(np.clip(np.searchsorted(widths[order], w), 1, len(order) - 1))
            lo, hi = self.tables[order[j - 1]], self.tables[order[j]]
            frac = float((w - widths[order[j - 1]]) / max(widths[order[j]] - widths[order[j - 1]], 1e-12))
            cache[key] = _blend(lo, hi, frac, key)
        return cache[key]

    def to_json_dict(self) -> dict:
        return {"format": "mlaqc-signatures", "version": TABLE_VERSION, "key": self.key,
                "variants": [t.to_json_dict() for t in self.tables]}

    @classmethod
    def from_json_dict(cls, d: dict) -> SignatureSet:
        return cls(tuple(SignatureTable.from_json_dict(v) for v in d["variants"]), d["key"])


def _blend(lo: SignatureTable, hi: SignatureTable, frac: float, edge_width_px: float) -> SignatureTable:
    """lo and hi (same kinds and magnitudes) mixed linearly: (1 - frac) lo + frac hi."""
    mix = {name: {k: (1 - frac) * getattr(lo, name)[k] + frac * getattr(hi, name)[k] for k in lo.magnitudes}
           for name in ("features", "rings")}
    phi0 = {k: lo.phi0_deg[k] if frac < 0.5 else hi.phi0_deg[k] for k in lo.magnitudes}
    across = {k: (1 - frac) * lo.across[k] + frac * hi.across[k] for k in lo.across if k in hi.across}
    settings = {**lo.settings, "edge_width_px": edge_width_px,
                "blended": [lo.settings.get("extra_blur_px"), hi.settings.get("extra_blur_px"), frac]}
    for name in ("shift_gain_y", "asym_gain_y"):
        if name in lo.settings and name in hi.settings:
            settings[name] = (1 - frac) * lo.settings[name] + frac * hi.settings[name]
    return SignatureTable(dict(lo.magnitudes), mix["features"], phi0, lo.key, mix["rings"], settings, across)


def signature_key(cfg: CameraConfig) -> str:
    """Hash of what shapes a single lens' sub-image: optics, geometry, pixel size, Fresnel."""
    d = cfg.to_dict()
    mla = {k: v for k, v in mla_hash_view(d["mla"]).items() if k not in ("count_w", "count_h")}
    keep = {"main_lens": d["main_lens"], "mla": mla, "geometry": geometry_hash_view(d["geometry"]), "pixel_um": cfg.pixel_at_mla_um,
            "fresnel": d["trace"]["fresnel"], "version": TABLE_VERSION, **blur_key(cfg)}
    if cfg.mla.packing == "hex":  # hex tables also hold the renders across the rows (ACROSS_DEG)
        keep["y_probe"] = Y_PROBE
    if cfg.mla.flat_sided:  # (tables of both surfaces curved, every table before, keep their keys)
        keep["kinds"] = [k.name for k in physical_kinds(cfg)]
    if window_half_px(cfg) != 10:  # tables rendered before the window followed the pitch were cut 21 px wide
        keep["window_half_px"] = window_half_px(cfg)
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]


def patch_shape(packing: str, lenses: int = PATCH) -> tuple[int, int]:
    """(rows, cols) of the patch: lenses x lenses square; hex `lenses` columns and enough rows (odd) to
    reach as far up and down as the columns reach sideways (rows are sqrt(3)/2 pitch apart: 11 for 9)."""
    if packing != "hex":
        return lenses, lenses
    half = int(np.ceil((lenses // 2) / SQRT3_2))
    return 2 * half + 1, lenses


def patch_centre(cfg: CameraConfig) -> tuple[int, int]:
    """0-based (row, col) of the patch's centre lens (the one the errors are put on): every neighbour
    it has, and the next ring's, are in the patch."""
    return cfg.mla.count_h // 2, cfg.mla.count_w // 2


def patch_config(cfg: CameraConfig, lenses: int = PATCH) -> CameraConfig:
    """The same camera cut down to a patch of `lenses` columns (`patch_shape`) on a sensor just large
    enough (the array's outline, `Lattice.extent`, plus 8 px a side)."""
    rows, cols = patch_shape(cfg.mla.packing, lenses)
    width, height = Lattice(cfg.mla.packing, rows, cols, cfg.layout.subimage_pitch_px).extent
    w_px, h_px = (int(np.ceil(v)) + 16 for v in (width, height))
    w_px, h_px = w_px + w_px % 2, h_px + h_px % 2
    return dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, count_w=cols, count_h=rows),
                               sensor=dataclasses.replace(cfg.sensor, width_px=w_px, height_px=h_px))


def nominal_windows(img: np.ndarray, cfg: CameraConfig, half: int | None = None):
    """(rows, cols, h, w) windows around each lens' nominal sub-image centre, and that centre in window
    coordinates: for simulated images whose grid is known exactly (signatures, tests). `half` defaults to
    the inspection's own, half the sub-image pitch (pipeline.inspect_image)."""
    from mlaqc.inspection.subimages import cut_windows

    if half is None:
        half = window_half_px(cfg)

    lat = Lattice(cfg.mla.packing, cfg.mla.count_h, cfg.mla.count_w, cfg.layout.subimage_pitch_px)
    x, y = lat.centres()
    gx = (img.shape[1] - 1) / 2 + x
    gy = (img.shape[0] - 1) / 2 + y
    win, _, ox, oy = cut_windows(img, gx, gy, 2 * half + 1, 2 * half + 1)
    return win, gx - ox, gy - oy


def window_half_px(cfg: CameraConfig) -> int:
    """Half the side of the window a lens' sub-image is cut in: half the sub-image pitch, whole pixels."""
    return int(np.floor(cfg.layout.subimage_pitch_px / 2))


def um_per_px_at_mla(cfg: CameraConfig) -> float:
    """A sub-image shift of 1 px corresponds to this many µm of lens shift in the MLA plane."""
    return cfg.sensor.pixel_um * (cfg.mla.pitch_um / cfg.sensor.pixel_um) / cfg.layout.subimage_pitch_px


def lens_features(metrics, m: int, n: int, direction_deg: float | None = None) -> np.ndarray:
    """FEATURES of lens [m, n] (0-based) from a mapping of (rows, cols) arrays (metrics or their local
    deviations); shift/asymmetry taken along/across `direction_deg` (image convention, counterclockwise
    from +x towards the top) or along the lens' own shift if None."""
    dx, dy = metrics["offset_x_px"][m, n], metrics["offset_y_px"][m, n]
    if direction_deg is None:
        r = max(float(np.hypot(dx, dy)), 1e-12)  # no shift at all: along/across projections are 0
        ux, uy = dx / r, dy / r
    else:
        a = np.radians(direction_deg)
        ux, uy = np.cos(a), -np.sin(a)
    ax, ay = metrics["asym_x"][m, n], metrics["asym_y"][m, n]
    return np.array([dx * ux + dy * uy, dy * ux - dx * uy, ax * ux + ay * uy, ay * ux - ax * uy,
                     metrics["blur"][m, n], metrics["flux"][m, n], metrics["ssim"][m, n], metrics["sharpness"][m, n]])


def patch_errors(kinds=KINDS, packing: str = "square") -> list[ErrorMap]:
    """The patch's error maps in table order: the perfect patch, then each kind at each magnitude on the
    centre lens (`patch_centre`); on hex then the ACROSS_KINDS at each magnitude across the rows."""
    rows, cols = patch_shape(packing)
    r, c = rows // 2, cols // 2
    maps = [ErrorMap.zeros(rows, cols, packing)]
    for kind in kinds:
        maps += [ErrorMap.zeros(rows, cols, packing).with_lens(r + 1, c + 1, **kind.fields(v)) for v in kind.magnitudes]
    for kind in _across_kinds(kinds, packing):
        maps += [ErrorMap.zeros(rows, cols, packing).with_lens(r + 1, c + 1, **_across_fields(kind, v))
                 for v in kind.magnitudes]
    return maps


# Hex sub-images of a pitch-wide disc overlap the rows above and below (rows are 0.87 pitch apart), so a
# lens shifted across the rows (y) registers at about half the shift along them (x), less the larger it is
# (pitch 1 µm: 0.54, 8 µm: 0.42 of x), and tilts, blurs and dims its sub-image otherwise: on hex the
# position kinds are rendered across the rows too (`SignatureTable.across`).
ACROSS_DEG = 90.0
ACROSS_KINDS = ("pitch", "decenter")
Y_PROBE = {"pitch_um": 2.0, "pitch_dir_deg": 90.0}  # the across render the recorded constant gains are read at


def _across_kinds(kinds, packing: str) -> list[ErrorKind]:
    return [k for k in kinds if k.name in ACROSS_KINDS] if packing == "hex" else []


def _across_fields(kind: ErrorKind, magnitude: float) -> dict[str, float]:
    return {f"{kind.name}_um": magnitude, f"{kind.name}_dir_deg": ACROSS_DEG}


def shift_gain_y(table: SignatureTable) -> float:
    """How much less a lens shift across the rows (y) moves its registered sub-image than one along them
    (x), at the Y_PROBE's size: 1 on a square lattice (see ACROSS_DEG). Kept for the record; the
    identification maps a y offset by `to_along`, which follows the gain over the rendered sizes."""
    return float(table.settings.get("shift_gain_y", 1.0) or 1.0)


def gains_y(table: SignatureTable) -> tuple[float, float]:
    """(`shift_gain_y`, asym_gain_y): the Y_PROBE's registered shift and intensity tilt over the same
    pitch error's along x (1, 1 on a square lattice)."""
    return shift_gain_y(table), float(table.settings.get("asym_gain_y", 1.0) or 1.0)


def along_curve(table: SignatureTable, column: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(across, along): the feature `column` (0 shift_par, 2 asym_par) that each ACROSS_KINDS' magnitude
    gives across the rows and along them, over every rendered magnitude of every such kind, sorted by
    `across` and made non-decreasing in both (a monotone map); None without across renders. A kind's
    curve is taken up to where it stops rising (a 20 µm decenter registers less across the rows than
    12 µm: the disc's rim has left the window's overlap strips)."""
    pts = [pt for k in table.across if k in table.features
           for pt in _rising(np.abs(table.across[k][:, column]), np.abs(table.features[k][:, column]))]
    if not pts:
        return None
    pts.sort()
    across, along = np.array(pts).T
    return np.maximum.accumulate(across), np.maximum.accumulate(along)


def _rising(across: np.ndarray, along: np.ndarray) -> list[tuple[float, float]]:
    """The (across, along) pairs of one kind's magnitudes, up to the first that does not rise in both."""
    stop = len(across)
    for i in range(1, len(across)):
        if across[i] <= across[i - 1] or along[i] <= along[i - 1]:
            stop = i
            break
    return list(zip(across[:stop].tolist(), along[:stop].tolist()))


def to_along(table: SignatureTable, value: np.ndarray, column: int) -> np.ndarray:
    """A y offset (column 0) or y tilt (column 2) across the rows, mapped to the size the same error
    gives along them: monotone through the table's across / along pairs (`along_curve`), linear through
    zero below the smallest, at the largest pair's ratio beyond it; sign kept. The constant gain
    (`gains_y`) where no across curve was rendered; unchanged on a square lattice."""
    value = np.asarray(value, dtype=np.float64)
    curve = along_curve(table, column)
    if curve is None:
        gain = gains_y(table)[0 if column == 0 else 1]
        return value / gain if gain > 0 else value
    return np.sign(value) * _along_size(_from_zero(curve), np.abs(value))


def _from_zero(curve: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """An `along_curve` with the point (0, 0) put first: the map is linear through zero below its first."""
    return np.concatenate([[0.0], curve[0]]), np.concatenate([[0.0], curve[1]])


def _along_size(curve: tuple[np.ndarray, np.ndarray], mag: np.ndarray) -> np.ndarray:
    """`to_along` of a size (>= 0) through a `_from_zero` curve, at its last ratio beyond it."""
    across, along = curve
    out = np.interp(mag, across, along)
    return np.where(mag > across[-1], mag * (along[-1] / across[-1]), out)


def to_along_xy(table: SignatureTable, x: np.ndarray, y: np.ndarray, column: int, steps: int = 28) -> np.ndarray:
    """The y part of a lens' (x, y) offset (column 0) or tilt (column 2) mapped to the along-row scale at
    the across gain of the whole vector's size, not of its y part's: a diagonal shift's y part registers
    at the gain of its full size (hex Table 1, decenter 7 µm in 24 directions: registered y / sin of the
    direction is 0.287-0.293 px from 15° to 90°, where a gain of the y part's size would differ by 6 %;
    mapped by its y part alone the direction read up to 1° further towards the rows).

    x is on the along scale already. The vector's size is that of a pure y shift registering c across
    the rows: c solves to_along(c)² (1 - y²/c²) = x² (one root, the left side rising from 0 at c = |y|),
    found by bisection, and y maps to y to_along(c) / c. A pure y value maps exactly as `to_along`;
    below the smallest rendered size, where the gain is constant, so does every vector; unchanged on a
    square lattice."""
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    curve = along_curve(table, column)
    if curve is None:
        return np.array(to_along(table, y, column), dtype=np.float64)
    curve = _from_zero(curve)
    out = np.array(np.sign(y) * _along_size(curve, np.abs(y)), dtype=np.float64)
    across, along = curve[0][1:], curve[1][1:]
    ratio = along[across > 0] / across[across > 0]
    if ratio.size == 0:
        return out
    ax, ay = np.abs(x), np.abs(y)
    size0 = np.sqrt(ay ** 2 + (ax / ratio[0]) ** 2)  # c on the constant-gain stretch
    big = np.isfinite(size0) & (size0 > across[across > 0][0]) & (ax > 0)
    if not big.any():
        return out
    ax, ay = ax[big], ay[big]
    lo, hi = ay, np.sqrt(ay ** 2 + (ax / ratio.min()) ** 2) * (1 + 1e-12)  # to_along(c) >= c * min ratio
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        short = _along_size(curve, mid) ** 2 * (1.0 - (ay / mid) ** 2) < ax ** 2
        lo, hi = np.where(short, mid, lo), np.where(short, hi, mid)
    c = 0.5 * (lo + hi)
    out[big] = y[big] * _along_size(curve, c) / c
    return out


def along_gain_small(table: SignatureTable, column: int) -> float:
    """d(along)/d(across) of `to_along` at small sizes: how a y spread scales with it (noise is small)."""
    curve = along_curve(table, column)
    if curve is None:
        gain = gains_y(table)[0 if column == 0 else 1]
        return 1.0 / gain if gain > 0 else 1.0
    return float(curve[1][0] / curve[0][0]) if curve[0][0] > 0 else 1.0


def _render_patch(patch: CameraConfig, errors: ErrorMap, rays_per_pixel: float, seed: int) -> np.ndarray:
    return Renderer(patch, errors).render(WhiteScene(), rays_per_pixel=rays_per_pixel, seed=seed).photons


def render_patches(cfg: CameraConfig, *, rays_per_pixel: float = 400.0, kinds=KINDS, seed: int = 99, progress=None,
                   client=None) -> list[np.ndarray]:
    """The geometric renders of `patch_errors(kinds)`, one after the other on this machine's cores, or
    one task each on a Dask `client`'s workers (the same images: renders are deterministic)."""
    patch = patch_config(cfg)
    maps = patch_errors(kinds, cfg.mla.packing)
    if client is None:
        images = []
        for i, errors in enumerate(maps, 1):
            images.append(_render_patch(patch, errors, rays_per_pixel, seed))
            if progress:
                progress(i, len(maps))
        return images
    from mlaqc.cluster import TASK_RETRIES, follow

    futures = {client.submit(_render_patch, patch, e, rays_per_pixel, seed, retries=TASK_RETRIES): i
               for i, e in enumerate(maps)}
    images: list = [None] * len(maps)
    for done, (i, img) in enumerate(follow(futures, "rendering signatures", progress=False), 1):
        images[i] = img
        if progress:
            progress(done, len(maps))
    return images


def build_signatures(cfg: CameraConfig, *, rays_per_pixel: float = 400.0, kinds=KINDS, seed: int = 99,
                     model: ReferenceModel | None = None, progress=None,
                     extra_blur_px: float | None = None, images: list[np.ndarray] | None = None) -> SignatureTable:
    """Render every kind at every magnitude on the patch and tabulate the feature changes; the images
    blurred as `BLUR_VARIANTS` says for `extra_blur_px` (None: the geometric image alone). `images`:
    the renders of `render_patches` with the same settings, when they are at hand already."""
    patch = patch_config(cfg)
    model = model or build_reference(patch, rays_per_lens=2_000_000)
    r, c = patch_centre(patch)
    um_px = um_per_px_at_mla(patch)
    if images is None:
        images = render_patches(cfg, rays_per_pixel=rays_per_pixel, kinds=kinds, seed=seed, progress=progress)
    images = [_blurred(img, patch, extra_blur_px) for img in images]

    def metrics_of(img: np.ndarray):
        win, cx, cy = nominal_windows(img / img.max(), patch)
        return compute_metrics(win, cx, cy, model, um_per_px_at_mla=um_px)

    base = metrics_of(images[0])
    edge_width = _edge_width(images[0], patch)
    mags, feats, phi0, rings = {}, {}, {}, {}
    first = 1
    for kind in kinds:
        mets = [metrics_of(img) for img in images[first:first + len(kind.magnitudes)]]
        first += len(kind.magnitudes)
        # features are taken along the shift that an error at direction 0 causes
        phi = _shift_direction(mets[len(mets) // 2:], r, c) if kind.directional else 0.0
        base_phi = lens_features(base, r, c, phi)
        mags[kind.name] = np.asarray(kind.magnitudes, float)
        feats[kind.name] = np.asarray([lens_features(m_, r, c, phi) - base_phi for m_ in mets])
        rings[kind.name] = np.asarray([[m_[k][r, c] - base[k][r, c] for k in RINGS] for m_ in mets])
        phi0[kind.name] = phi
    settings = {"rays_per_pixel": rays_per_pixel, "seed": seed, "patch_lenses": PATCH,
                "extra_blur_px": extra_blur_px, "edge_width_px": edge_width}
    across = {}
    for kind in _across_kinds(kinds, patch.mla.packing):
        mets = [metrics_of(img) for img in images[first:first + len(kind.magnitudes)]]
        first += len(kind.magnitudes)
        phi = _shift_direction(mets[len(mets) // 2:], r, c)
        base_phi = lens_features(base, r, c, phi)
        across[kind.name] = np.asarray([np.concatenate([lens_features(m_, r, c, phi) - base_phi,
                                                        [m_[k][r, c] - base[k][r, c] for k in RINGS]]) for m_ in mets])
    if "pitch" in across:  # the constant gains at the Y_PROBE's size, for the record (`gains_y`)
        p = Y_PROBE["pitch_um"]
        settings["shift_gain_y"] = float(np.interp(p, mags["pitch"], across["pitch"][:, 0])
                                         / np.interp(p, mags["pitch"], feats["pitch"][:, 0]))
        settings["asym_gain_y"] = float(np.interp(p, mags["pitch"], across["pitch"][:, 2])
                                        / np.interp(p, mags["pitch"], feats["pitch"][:, 2]))
    return SignatureTable(mags, feats, phi0, signature_key(cfg), rings, settings, across)


def _shift_direction(mets: list, r: int, c: int) -> float:
    """The mean direction (deg, image convention) of lens [r, c]'s registered shift over `mets`."""
    return float(np.degrees(np.angle(sum(np.exp(1j * np.arctan2(-m_["offset_y_px"][r, c], m_["offset_x_px"][r, c]))
                                         for m_ in mets))))


def build_signature_set(cfg: CameraConfig, *, rays_per_pixel: float = 400.0, progress=None,
                        client=None) -> SignatureSet:
    """`build_signatures` at every blur of BLUR_VARIANTS, from one set of renders (on a Dask `client`'s
    workers if given) and one patch reference for all."""
    model = build_reference(patch_config(cfg), rays_per_lens=2_000_000)
    kinds = physical_kinds(cfg)
    images = render_patches(cfg, rays_per_pixel=rays_per_pixel, kinds=kinds, progress=progress, client=client)
    tables = tuple(build_signatures(cfg, rays_per_pixel=rays_per_pixel, kinds=kinds, model=model, extra_blur_px=blur,
                                    images=images)
                   for blur in BLUR_VARIANTS)
    return SignatureSet(tables, signature_key(cfg))


def _blurred(img: np.ndarray, cfg: CameraConfig, extra_blur_px: float | None) -> np.ndarray:
    """The patch render as a sensor of this blur would see it (no PRNU: a fixed pattern is not blur)."""
    if extra_blur_px is None:
        return img
    out = apply_formation(img, cfg, formation_kernels(cfg, img.shape, with_prnu=False))
    if extra_blur_px <= 0:
        return out
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(out, extra_blur_px, mode="constant")


def _edge_width(img: np.ndarray, cfg: CameraConfig) -> float:
    """The rim width the calibration measures on a healthy patch render (what a frame's grid reports)."""
    from mlaqc.inspection.calibrate import calibrate_for

    # at 80 % of full scale, as an exposed frame: a noise-free render scaled to its own peak would put a
    # flat-topped sub-image (a telecentric main lens: no cos^4 fall-off) at full scale and read as saturated
    grid = calibrate_for((img / (1.25 * img.max())).astype(np.float32), cfg)
    return float(grid.edge_width_px)


def signature_table(cfg: CameraConfig, *, build_if_missing: bool = True, progress=None, client=None,
                    rebuild: bool = False) -> SignatureSet:
    """The tables for `cfg`'s optics: from the package, else the disk cache, else rendered (on a Dask
    `client` if given) and cached (`mlaqc.models.store`); `rebuild` renders them again whatever is stored."""
    return stored_json(f"signatures_{signature_key(cfg)}.json",
                       lambda: build_signature_set(cfg, progress=progress, client=client),
                       SignatureSet.to_json_dict, SignatureSet.from_json_dict, rebuild=rebuild,
                       build_if_missing=build_if_missing)
