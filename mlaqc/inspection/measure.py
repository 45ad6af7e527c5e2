"""Per-lens measured quantities with uncertainties: where each lens' optical centre sits, and how far
its focal length is off — for every lens, not only the flagged ones, so that array-wide trends show.

Values are taken against the array's typical lens (`identify._readings`: the local deviation, phase
pattern removed, plus its neighbourhood's trend over the array), not against the neighbourhood alone: a
slow trend across the array (form error growing towards the corners, a pitch drift) is what a process
engineer looks for, and a local baseline would remove it.

- centre: the sub-image's displacement, turned into the lens' optical-centre displacement in the MLA
  plane (see `_centre`): a pitch error Δp moves it by Δp, a rear-surface decenter δ by about δ/2 (the
  axis through both centres of curvature). A white image alone cannot say which of the two it was.
- focal length error: the radius-of-curvature reading of the lens' focus indexes (blur, flux, SSIM,
  sharpness, ring profile; not its shift) on the table's curve (both radii scaled by 1 + ε), turned into
  Δf by the thick-lens power (Δf/f = ε to 0.4 % of ε at Table 1's thickness). The chi-square is scaled
  by the Birge ratio where the best fits leave more than the fit claims (the indexes are correlated). It can have two minima (+10 % defocuses like 0 % around the camera's best focus at
  +5 %): the reading is the one nearest zero of those within 2 sigma of the best, the farthest other one
  is `focal_alt_rel`; the 1-sigma is the chi-square's curvature at the reading; the sign counts as
  resolved when every reading of the other sign is at least 2 sigma worse. Left out (NaN): lenses
  flagged as shifted or tilted, whose focus indexes carry that error.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from mlaqc.inspection.measure_kernels import coarse_chi2, focal_scan
from mlaqc.inspection.detection import kind_curve, response
from mlaqc.inspection.identify import RINGS, Identification, _unit_noise, class_centred
from mlaqc.inspection.spreads import robust_sigma
from mlaqc.parallel import run_parts
from mlaqc.models.signatures import FEATURES, SignatureTable, to_along_xy
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.paraxial import thick_lens

SIGN_RESOLVED_CHI2 = 4.0  # the other sign's best reading this much worse (2 sigma): the sign is known
_FOCUS_NAMES = ("blur", "flux", "ssim", "sharpness")  # FEATURES[4:], in order

#: Per-lens measurement columns: name -> (unit, meaning); lenses.csv and report.json use this order.
MEASUREMENTS: dict[str, tuple[str, str]] = {
    "centre_dx_um": ("µm", "optical-centre displacement along x (right), MLA plane, vs the array's typical lens"),
    "centre_dy_um": ("µm", "optical-centre displacement along y (down)"),
    "centre_sigma_um": ("µm", "1-sigma uncertainty of each centre component on this frame"),
    "focal_rel": ("1", "focal-length error Δf/f read from the lens' focus (on the radius-error curve)"),
    "focal_um": ("µm", "focal-length error Δf"),
    "focal_sigma_rel": ("1", "1-sigma uncertainty of focal_rel"),
    "focal_alt_rel": ("1", "another focal error the frame cannot rule out (within 2 sigma); empty if none"),
    "focal_sign_resolved": ("1", "1 if the sign of the focal error is known (other sign ≥ 2 sigma worse), else 0"),
}


@dataclass(frozen=True)
class LensMeasurements:
    """One (rows, cols) array per MEASUREMENTS name; NaN where a lens was not measured."""

    values: dict[str, np.ndarray]
    focal_length_um: float  # the design microlens' effective focal length

    def __getitem__(self, name: str) -> np.ndarray:
        return self.values[name]

    def summary(self) -> dict[str, float | None]:
        """Array-wide figures: RMS centre displacement, median focal error, and how many signs are known."""
        dx, dy, f = self["centre_dx_um"], self["centre_dy_um"], self["focal_rel"]
        ok = np.isfinite(dx) & np.isfinite(dy)
        okf = np.isfinite(f)

        def num(x) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {"centre_rms_um": num(np.sqrt(np.mean(dx[ok] ** 2 + dy[ok] ** 2))) if ok.any() else None,
                "centre_sigma_median_um": num(np.nanmedian(self["centre_sigma_um"])) if ok.any() else None,
                "focal_rel_median": num(np.median(f[okf])) if okf.any() else None,
                "focal_sigma_rel_median": num(np.nanmedian(self["focal_sigma_rel"])) if okf.any() else None,
                "focal_sign_resolved": int(np.nansum(self["focal_sign_resolved"])),
                "focal_length_um": self.focal_length_um}


def focal_length_um(cfg: CameraConfig) -> float:
    """The design microlens' effective focal length (paraxial thick lens), µm."""
    m = cfg.mla
    return thick_lens(m.radius_front_um, m.radius_back_um, m.thickness_um, m.refractive_index).efl


def focal_change_um(cfg: CameraConfig, radius_rel: np.ndarray) -> np.ndarray:
    """Δf (µm) of the microlens with both radii scaled by 1 + radius_rel, thickness kept (thick-lens power)."""
    m = cfg.mla
    s = 1.0 + np.asarray(radius_rel, dtype=np.float64)
    return thick_lens(m.radius_front_um * s, m.radius_back_um * s, m.thickness_um, m.refractive_index).efl \
        - focal_length_um(cfg)


def _centre(found: Identification, table: SignatureTable, cfg: CameraConfig, disc=None):
    """Optical-centre displacement (µm, x right and y down) and its per-lens 1-sigma.

    `disc`: the residuals (x, y) of this frame's own grid fit, px. Its disc fit finds the sub-image's
    edge to 0.005 px on frames it did not make (tests/test_analytic_frames.py), so it is taken at the
    geometric scale p / (sub-image pitch) µm per px, against the typical lens of its edge class. Without
    it (a saved grid) the registration offsets are used at the signature table's pitch response, which
    carries the registration's gain on the tracer's sub-images; on sub-images of another profile that
    gain differs (measured 0.84 on analytic discs against 0.96 on the tracer's)."""
    r = found.readings
    if disc is not None:
        dx, dy = class_centred([np.asarray(disc[0], float), np.asarray(disc[1], float)], cfg.mla.packing)
        um_per_px = cfg.mla.pitch_um / cfg.layout.subimage_pitch_px
    else:
        dx, dy = r["offset_x_px"], to_along_xy(table, r["offset_x_px"], r["offset_y_px"], 0)  # (hex: y registers low)
        px_per_um = abs(float(response(table, "pitch", 1.0)[0])) if "pitch" in table.magnitudes else 0.0
        um_per_px = 1.0 / px_per_um if px_per_um > 0 else np.nan
    sigma_px = 0.5 * (_pair_sigma(dx) + _pair_sigma(dy))
    return dx * um_per_px, dy * um_per_px, np.full(dx.shape, sigma_px * um_per_px)


def _pair_sigma(a: np.ndarray) -> float:
    """A map's noise per lens from the differences of neighbours along rows and columns (a smooth trend
    cancels in them): robust spread over sqrt(2). On a hex lattice too every such pair is a pair of
    neighbours: U(m,n) and U(m+1,n) are one pitch apart on either row parity."""
    d = np.concatenate([np.diff(a, axis=0).ravel(), np.diff(a, axis=1).ravel()])
    d = d[np.isfinite(d)]
    return robust_sigma(d) / np.sqrt(2.0) if d.size > 20 else np.nan


COARSE = 8  # the scan's curve takes every COARSE-th point of the table's dense curve (5 per rendered step)


def _focal_chi2(feats: np.ndarray, found: Identification, table: SignatureTable):
    """The focus fit's inputs: the dense radius curve (magnitudes, unit-noise features), every lens'
    unit-noise features, its chi-square against the coarse curve (every COARSE-th point), which lenses
    had all their focus indexes, and the fit's degrees of freedom. feats: (L, FEATURES + RINGS), shift
    and asymmetry columns unused (they say where a lens points, not how it focuses)."""
    dense_m, dense_f = kind_curve(table, "radius", 0)
    sig = np.array(found.feature_sigmas, dtype=np.float64)
    sig[:4] = np.inf
    whiten = found.noise.rings.whiten if found.noise is not None else None
    uv, ug = _unit_noise(feats, sig, whiten), np.ascontiguousarray(_unit_noise(dense_f, sig, whiten))
    ok = np.isfinite(uv).all(axis=1)
    uv = np.ascontiguousarray(np.where(ok[:, None], uv, 0.0))
    dof = int(np.count_nonzero(np.any(ug != 0, axis=0))) - 1  # the focus indexes used, less the magnitude
    chi2 = np.empty((len(uv), (len(ug) - 1) // COARSE + 1))
    # compiled, not BLAS: the same bits on every machine and thread count; lens ranges on the cores
    _on_cores(lambda a, b: coarse_chi2(uv[a:b], ug, COARSE, chi2[a:b]), len(uv))
    return (dense_m, ug, uv, chi2), ok, dof


def _focal(fit, scale: float):
    """Per lens: the reading, its 1-sigma, another reading the frame cannot rule out (NaN if none) and
    whether the sign is known, from the chi-square curves scaled by `scale`² (see `_birge_scale`).

    The curve can have two minima (+10 % defocuses like 0 % around a best focus at +5 %). Of the local
    minima within 2 sigma (chi-square + 4) of the best on the coarse curve, the one nearest zero is the
    reading (most lenses are healthy; a lens that must be defective shows no such minimum) and the
    farthest other one the alternative. The reading is then refined on the dense curve around it, by a
    parabola through its best three points, whose curvature gives the 1-sigma."""
    dense_m, ug, uv, chi2 = fit
    n = len(chi2)
    value, sigma, alt, resolved = np.empty(n), np.empty(n), np.empty(n), np.empty(n, np.bool_)
    step = float(np.median(np.diff(dense_m[::COARSE])))
    _on_cores(lambda a, b: focal_scan(chi2[a:b], dense_m, ug, uv[a:b], COARSE, 1.0 / (scale * scale),
                                       SIGN_RESOLVED_CHI2, 3.0 * step, value[a:b], sigma[a:b], alt[a:b],
                                       resolved[a:b]), n)
    return value, sigma, alt, resolved


def _on_cores(run, n: int) -> None:
    """run(a, b) over lens ranges [a, b) covering n lenses, one per core (the kernels release the GIL;
    each lens is computed alone, so the result does not depend on the split)."""
    workers = max(1, min(os.cpu_count() or 1, n // 1024))
    edges = np.linspace(0, n, workers + 1).astype(int)
    parts = [(int(a), int(b)) for a, b in pairwise(edges) if b > a]
    if len(parts) <= 1:
        run(0, n)
    else:
        run_parts(lambda ab: run(*ab), parts, os.cpu_count() or 1)  # the process' pool; len(parts) bounds the threads


def _birge_scale(chi2_min: np.ndarray, dof: int) -> float:
    """How much wider the readings scatter than the fit's sigmas say (>= 1): the square root of the
    median best-fit chi-square over its expected median for `dof` degrees of freedom (the Birge ratio).
    The fit counts the focus indexes as independent, but they are correlated; the median is not moved
    by the few defective lenses."""
    finite = chi2_min[np.isfinite(chi2_min)]
    if finite.size < 50 or dof < 1:
        return 1.0
    expected = dof * (1.0 - 2.0 / (9.0 * dof)) ** 3  # the chi-square median (Wilson-Hilferty; 0.4 % at dof 2)
    return float(max(1.0, np.sqrt(np.median(finite) / expected)))


def measure_lenses(found: Identification, table: SignatureTable, cfg: CameraConfig, disc=None) -> LensMeasurements:
    """Every lens' centre displacement and focal-length error with uncertainties (see the module note),
    from the readings `identify` left (NaN where a lens was not inspected or is missing); `disc`: the
    residuals (x, y) px of a grid fitted on this very frame (see `_centre`)."""
    r = found.readings
    shape = found.flagged.shape
    drop = (found.error_type == "missing") | ~np.isfinite(r["flux"])  # missing, or not inspected (off the sensor)
    cx, cy, csig = (np.where(drop, np.nan, a) for a in _centre(found, table, cfg, disc))
    feats = np.zeros((shape[0] * shape[1], len(FEATURES) + len(RINGS)))
    feats[:, 4:] = np.stack([r[k].ravel() for k in (*_FOCUS_NAMES, *RINGS)], axis=1)
    fit, ok, dof = _focal_chi2(feats, found, table)
    focus_kind = np.isin(found.error_type, np.array(["radius", "thickness"], dtype=object))
    other = (found.flagged & ~focus_kind).ravel()
    ok &= ~other  # a lens flagged as shifted or tilted: its focus indexes carry that error
    k = _birge_scale(np.where(ok, fit[3].min(axis=1), np.nan), dof)
    f_rel, f_sig, f_alt, f_res = (np.where(ok, a, np.nan).reshape(shape) for a in _focal(fit, k))  # k in f_sig
    f0 = focal_length_um(cfg)
    values = {"centre_dx_um": cx, "centre_dy_um": cy, "centre_sigma_um": np.where(np.isfinite(cx), csig, np.nan),
              "focal_rel": focal_change_um(cfg, f_rel) / f0, "focal_um": focal_change_um(cfg, f_rel),
              "focal_sigma_rel": np.where(np.isfinite(f_rel), f_sig, np.nan),
              "focal_alt_rel": focal_change_um(cfg, f_alt) / f0,
              "focal_sign_resolved": np.where(np.isfinite(f_rel), f_res, np.nan)}
    return LensMeasurements(values, f0)


__all__ = ["MEASUREMENTS", "LensMeasurements", "measure_lenses", "focal_length_um", "focal_change_um"]
