"""One verdict from the white frame and the through-focus pinhole frames of the same array.

The white frame finds and types every error; the through-focus pairs (mlaqc.inspection.throughfocus) read
each covered lens' focal-length error with its sign at first order. Combined:
- a lens the white frame called `radius` and the pairs covered takes the sign the pairs read where they
  are sure of it (|Δf/f| at least SIGN_Z sigma: the white frame can leave it ambiguous near the camera's
  best focus), and the magnitude of the more precise of the two readings (each with its 1-sigma: the white
  frame's `measure_lenses` focal error, the pairs' `focal_sigma_rel`); an alternative the sign rules out
  is dropped;
- a lens the white frame did not flag is flagged `radius` when its focal reading is significant (z above
  `qc.detect_sigma` against its own uncertainty) and at least the minimum reportable radius error;
- every other flag (position, pitch, decenter, tilt, thickness, missing, unknown) stays as the white frame
  said: a thickness error also moves a lens' focus, so the pairs do not retype it.
The verdict is then taken again over the combined list.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mlaqc.inspection.results import Defect, InspectionResult
from mlaqc.optics.config import QC

SOURCE_KEY = "through_focus_z"  # added to a defect's indexes when the pairs read it
SIGN_Z = 3.0  # the pairs settle a radius error's sign from this significance on


def verdict(defects: tuple[Defect, ...], qc: QC, assembly=None) -> str:
    """PASS or FAIL by the QC limits: out-of-tolerance lenses and missing lenses, each against its maximum,
    and the array's assembly readings (mlaqc.inspection.assembly.Assembly): a `[qc]` bound they exceed."""
    out_of_tol = sum(1 for d in defects if d.error_type != "missing" and not d.within_tolerance)
    missing = sum(1 for d in defects if d.error_type == "missing")
    misplaced = bool(assembly.exceeded) if assembly is not None else False
    return "FAIL" if (out_of_tol > qc.max_out_of_tolerance or missing > qc.max_missing or misplaced) else "PASS"


def combine_through_focus(result: InspectionResult, tf, qc: QC) -> InspectionResult:
    """`result` with the through-focus reading `tf` (a ThroughFocusResult) applied as the module says."""
    radius = np.asarray(tf.radius_rel, dtype=float)
    sigma = np.asarray(tf.focal_sigma_rel, dtype=float)
    focal = np.asarray(tf.focal_rel, dtype=float)
    read = np.asarray(tf.covered, bool) & np.isfinite(radius) & np.isfinite(sigma) & (sigma > 0)
    z = np.where(read, np.abs(focal) / np.where(read, sigma, 1.0), 0.0)
    floor = qc.report_fraction * qc.radius_rel
    flagged = result.flagged.copy()
    error_type = result.error_type.copy()
    defects = []
    white_sigma = _white_focal_sigma(result)
    for d in result.defects:
        i, j = d.m - 1, d.n - 1
        if d.error_type == "radius" and read[i, j]:
            d = _radius_with_pairs(d, float(radius[i, j]), float(z[i, j]), sigma[i, j] < white_sigma[i, j], qc)
        defects.append(d)
    new = read & ~flagged & (z > qc.detect_sigma) & (np.abs(radius) >= floor)
    for i, j in zip(*np.nonzero(new)):
        defects.append(Defect(int(i) + 1, int(j) + 1, "radius", float(radius[i, j]), "rel", None, float(z[i, j]),
                              abs(radius[i, j]) <= qc.radius_rel, result.metrics.at(int(i) + 1, int(j) + 1) | {SOURCE_KEY: float(z[i, j])}))
        flagged[i, j] = True
        error_type[i, j] = "radius"
    defects.sort(key=lambda d: (d.m, d.n))
    defects = tuple(defects)
    return dataclasses.replace(result, defects=defects, flagged=flagged, error_type=error_type,
                               verdict=verdict(defects, qc, result.assembly), through_focus=tf)


def _white_focal_sigma(result: InspectionResult) -> np.ndarray:
    """The white frame's focal-error 1-sigma per lens (inf where it has none)."""
    m = result.measurements
    if m is None:
        return np.full(result.flagged.shape, np.inf)
    s = np.asarray(m["focal_sigma_rel"], dtype=float)
    return np.where(np.isfinite(s), s, np.inf)


def _radius_with_pairs(d: Defect, pairs_radius: float, z: float, pairs_better: bool, qc: QC) -> Defect:
    """A white-frame radius defect with the pairs' reading applied (module note)."""
    white = [d.magnitude] + [a[1] for a in d.alternatives if a[0] == "radius"]  # its reading, then the other sign's
    if z >= SIGN_Z:  # the pairs know the sign: the white reading of that sign, if it has one
        white = [m for m in white if np.sign(m) == np.sign(pairs_radius)]
    mag = pairs_radius if pairs_better or not white else white[0]
    alts = () if z >= SIGN_Z else d.alternatives
    return dataclasses.replace(d, magnitude=float(mag), within_tolerance=abs(mag) <= qc.radius_rel, alternatives=alts,
                               indexes=d.indexes | {SOURCE_KEY: z})
