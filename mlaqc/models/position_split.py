"""Pitch or decenter: what tells them apart in a white image when lens boundaries are physical.

With `mla.boundaries = "sag-intersection"` a lens ends where its sags meet its neighbours'. A pitch error
moves the whole lens, both boundaries with it: each neighbour along the shift gains or loses a strip of
aperture, which changes its whole sub-image alike (a flux change, no tilt). A surface decenter moves only
the rear surface, so only the rear boundary moves (by about half the decenter): in each neighbour only
the rays that leave the lens through that strip change, which lights one half of its sub-image — an
intensity tilt. Both move the lens' own sub-image alike (decenter by about half as much per µm), so the
neighbours' tilts, taken against the lens' own shift, separate them:

    contrast C = the edge neighbours' tilts towards the lens (`neighbour_contrast`: 4 square, 6 hex)

is small for a pitch error and about four times larger for a decenter of the same shift. With `grid` boundaries no boundary
moves and no neighbour changes at all: a white image cannot separate them (bench/type_separation.py:
1.5 sigma at best), and `position_split` returns None, so the lens stays 'position'.

`PositionSplit` holds C per pixel of the lens' own sub-image shift for each kind, measured on the
tracer's 9 x 9-lens patch (hex: 11 rows x 9 columns, `signatures.patch_shape`) (mlaqc.models.signatures) with the sensor formation applied; cached on disk by
the optics' signature key.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from mlaqc.models.reference import build_reference
from mlaqc.models.store import stored_json
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.lattice import Lattice

FORMAT_VERSION = 1
SPLIT_KINDS = {"pitch": 2.0, "decenter": 4.0}  # rendered magnitudes, µm: the same sub-image shift for both
SPLIT_DIRECTIONS_DEG = (0.0, 45.0)  # along an axis and diagonal: C varies by about 15 % between them
HEX_SPLIT_DIRECTIONS_DEG = (0.0, 30.0)  # hex: towards a neighbour and between two


@dataclass(frozen=True)
class PositionSplit:
    """Neighbour tilt contrast per px of own shift, and own shift per µm, of a pitch error and a decenter."""

    contrast_per_px: dict[str, float]
    shift_px_per_um: dict[str, float]
    key: str

    def separation_per_px(self) -> float:
        """How far apart (contrast units) the two kinds' predictions lie per px of shift."""
        return abs(self.contrast_per_px["decenter"] - self.contrast_per_px["pitch"])

    def to_json_dict(self) -> dict:
        return {"format": "mlaqc-position-split", "version": FORMAT_VERSION} | asdict(self)

    @classmethod
    def from_json_dict(cls, d: dict) -> PositionSplit:
        return cls({k: float(v) for k, v in d["contrast_per_px"].items()},
                   {k: float(v) for k, v in d["shift_px_per_um"].items()}, str(d["key"]))


def neighbour_contrast(asym_x: np.ndarray, asym_y: np.ndarray, packing: str = "square") -> np.ndarray:
    """C of every lens: the sum over its edge neighbours (square: left, right, upper, lower; hex: its 6)
    of each neighbour's tilt projected on the unit vector from that neighbour to the lens (image axes,
    y down); NaN where a neighbour is off the array. On a square lattice: the left and upper
    neighbours' tilts towards it minus the right and lower ones'. Measured on the tracer, a decenter
    makes both neighbours along its axis brighter on the side facing the lens whichever way it points,
    so C does not depend on the direction (a pitch error leaves the neighbours untilted)."""
    c = np.full(asym_x.shape, np.nan)
    if packing == "square":
        c[1:-1, 1:-1] = (asym_x[1:-1, :-2] - asym_x[1:-1, 2:]) + (asym_y[:-2, 1:-1] - asym_y[2:, 1:-1])
        return c
    rows, cols = asym_x.shape
    lat = Lattice(packing, rows, cols)
    nbr = lat.neighbours(diagonal=False)  # (K, 6)
    r = np.arange(rows * cols) // cols
    steps = lat.neighbour_steps(diagonal=False)[r % 2]  # (K, 6, 2) (dr, dc)
    u_n, v_n = lat.uv(r[:, None] + steps[..., 0], steps[..., 1])
    u_0, v_0 = lat.uv(r[:, None], np.zeros((rows * cols, 1)))
    ux, uy = u_0 - u_n, v_0 - v_n  # neighbour -> lens, one pitch long
    ax, ay = asym_x.ravel()[nbr], asym_y.ravel()[nbr]
    total = (ax * ux + ay * uy).sum(axis=1)
    return np.where((nbr >= 0).all(axis=1), total, np.nan).reshape(rows, cols)


def _patch_metrics(cfg: CameraConfig, fields: dict[str, float], rays_per_pixel: float, seed: int, model):
    from mlaqc.inspection.metrics import compute_metrics
    from mlaqc.models.signatures import _blurred, nominal_windows, patch_centre, patch_config, um_per_px_at_mla
    from mlaqc.optics.render import Renderer
    from mlaqc.optics.scene import WhiteScene

    patch = patch_config(cfg)
    r, c = patch_centre(patch)
    errors = ErrorMap.zeros(patch.mla.count_h, patch.mla.count_w, patch.mla.packing)
    errors = errors.with_lens(r + 1, c + 1, **fields) if fields else errors
    img = _blurred(Renderer(patch, errors).render(WhiteScene(), rays_per_pixel=rays_per_pixel, seed=seed).photons, patch, 0.0)
    win, cx, cy = nominal_windows(img / img.max(), patch)
    return compute_metrics(win, cx, cy, model, um_per_px_at_mla=um_per_px_at_mla(patch))


def build_position_split(cfg: CameraConfig, *, rays_per_pixel: float = 1500.0, seed: int = 5) -> PositionSplit:
    """Render the patch healthy, with a pitch error and with a decenter along +x (common random numbers)
    and read each kind's contrast and own shift."""
    from mlaqc.models.signatures import patch_centre, patch_config, signature_key

    model = build_reference(patch_config(cfg), rays_per_lens=2_000_000)  # as the signature tables are
    r, c = patch_centre(patch_config(cfg))
    base = _patch_metrics(cfg, {}, rays_per_pixel, seed, model)
    contrast, shift = {}, {}
    for kind, mag in SPLIT_KINDS.items():
        ks, kc = [], []
        for direction in (HEX_SPLIT_DIRECTIONS_DEG if cfg.mla.packing == "hex" else SPLIT_DIRECTIONS_DEG):
            m = _patch_metrics(cfg, {f"{kind}_um": mag, f"{kind}_dir_deg": direction}, rays_per_pixel, seed, model)
            ds = float(np.hypot(m["offset_x_px"][r, c] - base["offset_x_px"][r, c], m["offset_y_px"][r, c] - base["offset_y_px"][r, c]))
            dc = float(neighbour_contrast(m["asym_x"] - base["asym_x"], m["asym_y"] - base["asym_y"], cfg.mla.packing)[r, c])
            ks.append(ds / mag)
            kc.append(dc / ds if ds else 0.0)
        shift[kind], contrast[kind] = float(np.mean(ks)), float(np.mean(kc))
    return PositionSplit(contrast, shift, signature_key(cfg))


_SPLITS: dict[str, PositionSplit] = {}


def position_split(cfg: CameraConfig) -> PositionSplit | None:
    """The split of `cfg`'s optics (the package's for Table 1 optics, else the disk cache, else rendered,
    about 10 s, and cached), or None with grid boundaries or circular apertures (each centred on its own
    front vertex, as a chrome mask makes them: no boundary is shared), where no neighbour sees either error,
    and on a flat-sided MLA, which has no decenter (a shifted lens is a pitch error)."""
    if cfg.mla.boundaries != "sag-intersection" or cfg.mla.aperture == "circle" or cfg.mla.flat_sided:
        return None
    from mlaqc.models.signatures import signature_key

    key = signature_key(cfg)
    if key not in _SPLITS:
        _SPLITS[key] = stored_json(f"position_split_{key}.json", lambda: build_position_split(cfg),
                                   PositionSplit.to_json_dict, PositionSplit.from_json_dict)
    return _SPLITS[key]


SPLIT_Z = 4.0  # the two kinds' predictions must lie this many sigma apart before a lens is typed (2 sigma each side: 2.3 % wrong)


def contrast_sigma(asym_x_dev: np.ndarray, asym_y_dev: np.ndarray, packing: str = "square") -> float:
    """The frame's spread of C (robust, over every lens) from the asymmetry deviations."""
    return contrast_spread(neighbour_contrast(asym_x_dev, asym_y_dev, packing))


def contrast_spread(contrast: np.ndarray) -> float:
    """`contrast_sigma` of a `neighbour_contrast` map already computed; a tiny floor keeps a noise-free
    frame's z finite."""
    c = contrast[np.isfinite(contrast)]
    if c.size == 0:
        return float("inf")
    return max(1.4826 * float(np.median(np.abs(c - np.median(c)))), 1e-9)


def type_position(split: PositionSplit, contrast: float, shift_px: float, sigma: float) -> tuple[str, float]:
    """'pitch', 'decenter' or (when this frame cannot tell them apart at this shift) 'position', and the
    separation in sigma of the two kinds' predicted contrasts for this shift."""
    z_sep = split.separation_per_px() * abs(shift_px) / sigma
    if not (np.isfinite(contrast) and z_sep >= SPLIT_Z):
        return "position", float(z_sep)
    err = {k: abs(contrast - split.contrast_per_px[k] * abs(shift_px)) for k in ("pitch", "decenter")}
    return min(err, key=err.get), float(z_sep)


def split_limits(split: PositionSplit | None, sigma: float) -> dict | None:
    """The smallest pitch and decenter (µm) this frame types as such rather than 'position'; None when
    it cannot at any size (grid boundaries)."""
    if split is None or not np.isfinite(sigma) or split.separation_per_px() <= 0:
        return None
    shift = SPLIT_Z * sigma / split.separation_per_px()
    return {f"{k}_um": float(f"{shift / max(split.shift_px_per_um[k], 1e-12):.3g}") for k in ("pitch", "decenter")}
