"""What an inspection produces: per-lens metrics, flagged defects, the verdict (DESIGN.md names)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mlaqc.optics.lattice import Lattice

# Every per-lens index: name -> (unit, one-line meaning). Column order of lenses.csv follows this.
METRICS: dict[str, tuple[str, str]] = {
    "flux": ("rel", "sub-image flux relative to an ideal lens at that place (exposure-normalized)"),
    "mean_gray": ("rel", "mean normalized level in the lens' window"),
    "uniformity": ("1", "1 - std/mean of the level over the sub-image's central disc"),
    "entropy": ("bit", "Shannon entropy of the sub-image's grey levels"),
    "sharpness": ("rel", "gradient energy relative to the reference sub-image"),
    "offset_x_px": ("px", "sub-image position minus grid position, x (registration on the reference)"),
    "offset_y_px": ("px", "sub-image position minus grid position, y (down)"),
    "offset_um": ("µm", "size of the offset, referred to the MLA plane"),
    "size_px": ("px", "second-moment radius of the bright part"),
    "ellipticity": ("1", "1 - minor/major axis of the second moments"),
    "blur": ("px²", "extra blur against the reference (sigma²/2 of a Gaussian)"),
    "asym_x": ("rel", "intensity tilt across the sub-image along x"),
    "asym_y": ("rel", "intensity tilt across the sub-image along y (down)"),
    "psnr_db": ("dB", "PSNR against the reference sub-image"),
    "ssim": ("1", "structural similarity against the reference sub-image"),
    "ncc": ("1", "normalized cross-correlation with the reference sub-image"),
    **{f"ring{k}": ("rel", f"residual light (sub-image minus flux-scaled reference) in ring {k} around the lens "
                           f"centre{', ' + r if r else ''}, relative to the reference's light") for k, r in enumerate(
        ("radius < 0.57 half-window", "0.57-0.76", "0.76-0.86", "0.86-0.95", "0.95-1.05", "1.05-1.14"))},
}


@dataclass(frozen=True)
class LensMetrics:
    """One (rows, cols) float array per index in METRICS; NaN where a lens is missing."""

    values: dict[str, np.ndarray]

    def __getitem__(self, name: str) -> np.ndarray:
        return self.values[name]

    @property
    def shape(self) -> tuple[int, int]:
        return next(iter(self.values.values())).shape

    def at(self, m: int, n: int) -> dict[str, float]:
        """All indexes of lens U(m,n) (1-based) as plain floats."""
        return {k: float(v[m - 1, n - 1]) for k, v in self.values.items()}


@dataclass(frozen=True)
class Defect:
    """A flagged lens: what is wrong with it and by how much, in U(m,n) numbering."""

    m: int
    n: int
    # 'pitch', 'decenter', 'position' (pitch or decenter), 'radius', 'tilt', 'thickness', 'dim', 'obscuration', 'scratch',
    # 'missing', 'unknown'
    error_type: str
    magnitude: float  # in `unit`; signed for radius/thickness errors
    unit: str
    direction_deg: float | None  # counterclockwise from the image's +x towards its top; None if not directional
    score: float  # how far outside normal the lens is (robust z), larger = more certain
    within_tolerance: bool  # True if flagged but inside the QC spec for its type
    indexes: dict[str, float] = field(default_factory=dict)
    # other readings that fit about as well: (type, magnitude, unit, direction_deg) each
    alternatives: tuple[tuple[str, float, str, float | None], ...] = ()

    def to_json_dict(self) -> dict[str, Any]:
        d = {"row": self.m, "col": self.n, "error_type": self.error_type,
             "magnitude": finite_or_none(self.magnitude), "unit": self.unit,
             "direction_deg": None if self.direction_deg is None else finite_or_none(self.direction_deg),
             "score": finite_or_none(self.score), "within_tolerance": self.within_tolerance,
             "indexes": {k: finite_or_none(v) for k, v in self.indexes.items()},
             "alternatives": [{"error_type": t, "magnitude": finite_or_none(v), "unit": u,
                               "direction_deg": None if a is None else finite_or_none(a)} for t, v, u, a in self.alternatives]}
        return d


def finite_or_none(v: float) -> float | None:
    """JSON has no NaN: write null instead."""
    return float(v) if np.isfinite(v) else None


class LazyReferences:
    """The reference sub-image of every lens, (rows, cols, h, w) float32, computed when first needed.

    `compute(cx, cy)` returns the references of lenses centred at (cx, cy) (arrays of one shape) with
    shape cx.shape + (h, w); each lens' reference depends on its own centre only. The inspection itself
    never reads them: a report shows a few lenses (`self[m, n]` computes that lens alone), while
    `np.asarray(refs)` computes all of them once and keeps them. Pickles as the plain array."""

    def __init__(self, compute: Callable[[np.ndarray, np.ndarray], np.ndarray], cx: np.ndarray, cy: np.ndarray,
                 window: tuple[int, int]) -> None:
        self._compute = compute
        self._cx, self._cy = np.asarray(cx, dtype=np.float64), np.asarray(cy, dtype=np.float64)
        self.shape = self._cx.shape + tuple(window)
        self._full: np.ndarray | None = None
        self._lock = threading.Lock()

    dtype = np.dtype(np.float32)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def full(self) -> np.ndarray:
        """Every lens' reference (computed once, then kept)."""
        with self._lock:
            if self._full is None:
                self._full = np.asarray(self._compute(self._cx, self._cy), dtype=np.float32).reshape(self.shape)
            return self._full

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        full = self.full()
        return full if dtype is None else full.astype(dtype, copy=False)

    def __getitem__(self, key):
        if self._full is None and isinstance(key, tuple) and len(key) == 2 and all(
                isinstance(k, (int, np.integer)) for k in key):
            m, n = (int(k) + s if k < 0 else int(k) for k, s in zip(key, self.shape[:2]))
            if not (0 <= m < self.shape[0] and 0 <= n < self.shape[1]):
                raise IndexError(f"lens index {key} is outside the {self.shape[0]} x {self.shape[1]} array")
            one = self._compute(self._cx[m:m + 1, n:n + 1], self._cy[m:m + 1, n:n + 1])
            return np.asarray(one, dtype=np.float32).reshape(self.shape[2:])
        return self.full()[key]

    def __len__(self) -> int:
        return self.shape[0]

    def __reduce__(self):
        return (np.asarray, (self.full(),))


@dataclass(frozen=True)
class InspectionResult:
    """Everything `mlaqc inspect` reports; written out by mlaqc.report."""

    verdict: str  # 'PASS' or 'FAIL'
    grid: Any  # mlaqc.inspection.calibrate.Grid
    metrics: LensMetrics
    defects: tuple[Defect, ...]
    flagged: np.ndarray  # (rows, cols) bool
    error_type: np.ndarray  # (rows, cols) str ('' where not flagged)
    image: np.ndarray  # the normalized frame that was inspected, float32 (H, W)
    subimages: np.ndarray  # (rows, cols, h, w) float32
    reference: np.ndarray | LazyReferences  # (rows, cols, h, w) or (h, w) float32 reference sub-image(s)
    source: str  # the raw file inspected
    tolerances: dict[str, float]
    timings_s: dict[str, float]
    notes: tuple[str, ...] = ()
    # what this frame could detect (inspection.detection_limits): per error type the smallest magnitude
    # flagged at the configured threshold, None where no rendered magnitude is detectable
    detection_limit: dict[str, Any] = field(default_factory=dict)
    below_reportable: int = 0  # significant deviations smaller than the minimum reportable error
    not_inspected: int = 0  # lenses whose sub-image leaves the sensor
    measurements: Any = None  # mlaqc.inspection.measure.LensMeasurements: every lens' centre and focal error
    through_focus: Any = None  # mlaqc.inspection.throughfocus_results.ThroughFocusResult when pinhole frames were given
    assembly: Any = None  # mlaqc.inspection.assembly.Assembly: the array's placement in the camera
    lens_boundaries: str = ""  # the config's mla.boundaries the frame was inspected with ('' if not known)

    @property
    def failed(self) -> bool:
        return self.verdict == "FAIL"

    @property
    def lattice(self) -> Lattice:
        """The lattice the per-lens arrays index (the grid's packing; square for grids made before hex)."""
        return Lattice(getattr(self.grid, "packing", "square") or "square", *self.flagged.shape)

    def lattice_facts(self) -> dict[str, Any]:
        """What report.json states about the lattice: `Lattice.to_json_dict()` (packing, rows, cols, row
        step, convention), for its "lattice" entry under "conventions"."""
        return self.lattice.to_json_dict()


def detection_limit_text(limit: dict[str, Any]) -> str:
    """One line for people: the smallest pitch, decenter and radius errors this frame detects."""
    if not limit:
        return "detection limit: not measured"

    def fmt(key: str, scale: float, unit: str) -> str:
        return _limit_fmt(limit, key, scale, unit)

    no_decenter = "pitch_um" in limit and "decenter_um" not in limit  # a flat-sided MLA has none
    parts = [f"pitch {fmt('pitch_um', 1, 'µm')}"]
    if not no_decenter:
        parts.append(f"decenter {fmt('decenter_um', 1, 'µm')}")
    parts.append(f"radius −{fmt('radius_rel_neg', 100, '%')} / +{fmt('radius_rel_pos', 100, '%')}")
    text = "detects at least: " + ", ".join(parts).replace("−not", "not").replace("+not", "not")
    text += _border_text(limit.get("border"), limit)
    text += _noise_text(limit.get("noise"))
    if no_decenter:
        return text + "; no decenter on a flat-sided (plano-convex) MLA: a shifted lens is a pitch error"
    if "pitch_vs_decenter" not in limit:
        return text
    split = limit["pitch_vs_decenter"]
    if split is None:
        return text + ("; pitch vs decenter: not told apart (grid lens boundaries or circular apertures: no boundary "
                       "is shared; reported as 'position')")
    return text + (f"; tells pitch from decenter from {split['pitch_um']:.3g} µm pitch / {split['decenter_um']:.3g} µm "
                   "decenter (sag-intersection lens boundaries)")


def _border_text(border: Any, inner: dict[str, Any]) -> str:
    """The edge zone's limits (detection_limits.edge_zone), where they are another than the inner lenses':
    ' (near the edge: ...)'."""
    keys = ("pitch_um", "decenter_um", "radius_rel_neg", "radius_rel_pos")
    if not isinstance(border, dict) or all(border.get(k) == inner.get(k) for k in keys):
        return ""
    parts = [f"pitch {_limit_fmt(border, 'pitch_um', 1, 'µm')}"]
    if "decenter_um" in border:
        parts.append(f"decenter {_limit_fmt(border, 'decenter_um', 1, 'µm')}")
    neg, pos = _limit_fmt(border, "radius_rel_neg", 100, "%"), _limit_fmt(border, "radius_rel_pos", 100, "%")
    parts.append(f"radius −{neg} / +{pos}")
    return f" (near the edge: {', '.join(parts)})".replace("−not", "not").replace("+not", "not")


def _limit_fmt(limit: dict[str, Any], key: str, scale: float, unit: str) -> str:
    """One limit for people: its value in `unit`, or 'not detectable'."""
    v = limit.get(key)
    return "not detectable" if v is None else f"{v * scale:.3g} {unit}"


def _noise_text(noise: Any) -> str:
    """What a stack and a master dark did to this frame (mlaqc.inspection.darks.noise_info), or ''."""
    if not isinstance(noise, dict):
        return ""
    parts = []
    k = noise.get("frames_averaged", 1)
    if k > 1:
        parts.append(f"an average of {k} frames (pixel noise ×{noise.get('noise_scale', 1.0):.2f})")
    dark = noise.get("dark")
    if dark:
        parts.append(f"dark-subtracted ({dark['frames']} darks, {dark['hot_pixels'] + dark['dead_pixels']} bad pixels)")
    return f" [{'; '.join(parts)}]" if parts else ""
