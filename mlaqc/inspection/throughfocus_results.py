"""The through-focus reading's results: the per-lens `ThroughFocusResult`, each pair's `PairReading` and the report's columns."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

# per-lens readings as lenses.csv / report.json name them: column -> (ThroughFocusResult field, unit, meaning)
TF_MEASUREMENTS: dict[str, tuple[str, str, str]] = {
    "tf_focal_rel": ("focal_rel", "1", "focal-length error Δf/f from the through-focus pinhole pairs, vs the typical lens"),
    "tf_focal_sigma_rel": ("focal_sigma_rel", "1", "1-sigma uncertainty of tf_focal_rel"),
    "tf_radius_rel": ("radius_rel", "1", "the same reading as the radius error (both radii scaled) it equals"),
    "tf_centre_dx_um": ("centre_dx_um", "µm", "optical-centre displacement along x from the spot positions (Shack-Hartmann)"),
    "tf_centre_dy_um": ("centre_dy_um", "µm", "optical-centre displacement along y (down) from the spot positions"),
    "tf_centre_sigma_um": ("centre_sigma_um", "µm", "1-sigma uncertainty of each tf centre component"),
}


@dataclass(frozen=True)
class PairReading:
    """One +u / -u pair: what it read and the figures it was read with."""

    focus_offset_mm: float  # |u|
    offset_lenses: tuple[int, int]
    lenses: int  # lenses read in this pair
    g_plus: float  # s / |u'| of the +u frame
    g_minus: float
    gain: float  # the traced model's dD/dc over the paraxial -4 I (g+ + g-), at the design lens
    birge: float  # the sigma scale (>= 1) of this |u|'s readings
    window_px: float  # median moment window half-width
    saturated: int  # lenses left out because a pixel of their spot was saturated


@dataclass(frozen=True)
class ThroughFocusResult:
    """Per-lens (rows, cols) arrays; NaN (or False) where a lens was not read."""

    focal_rel: np.ndarray  # Δf/f against the array's typical lens
    focal_sigma_rel: np.ndarray  # its 1-sigma
    radius_rel: np.ndarray  # the reading as the radius error (both radii scaled by 1 + eps) it equals
    covered: np.ndarray  # bool: read in at least one pair
    delta_px2: np.ndarray  # D - D(typical lens of its shell), px^2, phase pattern removed (mean over pairs)
    centre_dx_um: np.ndarray  # optical-centre displacement, x right, MLA plane, vs the typical lens
    centre_dy_um: np.ndarray  # y down
    centre_sigma_um: np.ndarray  # 1-sigma of each component
    pairs: tuple[PairReading, ...]
    focal_length_um: float  # the design microlens' effective focal length
    timings_s: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """Array-wide figures: coverage, median focal error and sigma, and each pair's figures."""
        ok = self.covered & np.isfinite(self.focal_rel)

        def num(x) -> float | None:
            return float(x) if x is not None and np.isfinite(x) else None

        return {"lenses_covered": int(ok.sum()), "coverage": float(ok.mean()),
                "focal_rel_median": num(np.median(self.focal_rel[ok])) if ok.any() else None,
                "focal_sigma_rel_median": num(np.median(self.focal_sigma_rel[ok])) if ok.any() else None,
                "centre_sigma_um_median": (num(np.nanmedian(self.centre_sigma_um))
                                           if np.isfinite(self.centre_sigma_um).any() else None),
                "focal_length_um": self.focal_length_um,
                "pairs": [{"u_mm": p.focus_offset_mm, "offset": list(p.offset_lenses), "lenses": p.lenses,
                           "gain": p.gain, "birge": p.birge, "window_px": p.window_px,
                           "saturated": p.saturated} for p in self.pairs]}


__all__ = ["ThroughFocusResult", "PairReading"]
