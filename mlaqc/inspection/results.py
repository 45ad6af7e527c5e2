"""What an inspection produces: per-lens metrics, flagged defects, the verdict (DESIGN.md names)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

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
    error_type: str  # 'pitch', 'decenter', 'position' (pitch or decenter), 'radius', 'tilt', 'thickness', 'missing'
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
             "magnitude": _finite(self.magnitude), "unit": self.unit,
             "direction_deg": None if self.direction_deg is None else _finite(self.direction_deg),
             "score": _finite(self.score), "within_tolerance": self.within_tolerance,
             "indexes": {k: _finite(v) for k, v in self.indexes.items()},
             "alternatives": [{"error_type": t, "magnitude": _finite(v), "unit": u,
                               "direction_deg": None if a is None else _finite(a)} for t, v, u, a in self.alternatives]}
        return d


def _finite(v: float) -> float | None:
    """JSON has no NaN: write null instead."""
    return float(v) if np.isfinite(v) else None


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
    reference: np.ndarray  # (rows, cols, h, w) or (h, w) float32 reference sub-image(s)
    source: str  # the raw file inspected
    tolerances: dict[str, float]
    timings_s: dict[str, float]
    notes: tuple[str, ...] = ()
    # what this frame could detect (identify.detection_limits): per error type the smallest magnitude
    # flagged at the configured threshold, None where no rendered magnitude is detectable
    detection_limit: dict[str, Any] = field(default_factory=dict)
    below_reportable: int = 0  # significant deviations smaller than the minimum reportable error
    not_inspected: int = 0  # lenses whose sub-image leaves the sensor
    measurements: Any = None  # mlaqc.inspection.measure.LensMeasurements: every lens' centre and focal error

    @property
    def failed(self) -> bool:
        return self.verdict == "FAIL"


def detection_limit_text(limit: dict[str, Any]) -> str:
    """One line for people: the smallest pitch, decenter and radius errors this frame detects."""
    if not limit:
        return "detection limit: not measured"

    def fmt(key: str, scale: float, unit: str) -> str:
        v = limit.get(key)
        return "not detectable" if v is None else f"{v * scale:.3g} {unit}"

    parts = [f"pitch {fmt('pitch_um', 1, 'µm')}", f"decenter {fmt('decenter_um', 1, 'µm')}",
             f"radius −{fmt('radius_rel_neg', 100, '%')} / +{fmt('radius_rel_pos', 100, '%')}"]
    return "detects at least: " + ", ".join(parts).replace("−not", "not").replace("+not", "not")
