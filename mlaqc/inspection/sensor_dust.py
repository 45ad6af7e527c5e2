"""Sensor-side shadows: dust or a mark on the sensor's cover glass stays at the same pixels when the array
moves; a defect of the array moves with it.

Across a batch of frames of one camera, every local dark region (a lens typed 'obscuration' or 'scratch',
its centroid on the sensor in `spot_x_px`/`spot_y_px`) is matched with the others at the same pixels
(within TOLERANCE_PX, or a tenth of the sub-image pitch). Where two such frames show the array at
positions at least half a lens pitch apart — their sidecars' stage positions (`mlaqc capture`/`scan`)
say so, or, with the lenses numbered from the array's corner (fixed counts), a different lens sits under
the shadow — the shadow is the sensor's: reported once for the batch, and taken off every frame's lens
flags (their verdicts recomputed). Where no frame pair tells the array moved, nothing is taken off and
the report says why.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mlaqc.inspection.combine import verdict as overall_verdict

TOLERANCE_PX = 2.0
SPOT_TYPES = ("obscuration", "scratch")


@dataclass(frozen=True)
class SensorShadow:
    """A shadow that keeps its pixels while the array moves: where it is on the sensor, its size and loss,
    and the lenses it was taken off (frame, U(m,n))."""

    x_px: float
    y_px: float
    area: float  # share of a sub-image's disc it darkens in a frame (the mean over the frames)
    depth: float  # its loss
    kind: str  # 'obscuration' (a spot) or 'scratch' (a line)
    lenses: tuple[tuple[str, int, int], ...]

    def to_json_dict(self) -> dict[str, Any]:
        return {"x_px": round(self.x_px, 2), "y_px": round(self.y_px, 2), "area": round(self.area, 4),
                "depth": round(self.depth, 4), "kind": self.kind,
                "lenses": [{"frame": f, "row": m, "col": n} for f, m, n in self.lenses]}

    def sentence(self) -> str:
        """One line for the console and each frame's report."""
        frames = len({f for f, _, _ in self.lenses})
        where = "; ".join(f"U({m},{n}) in {f}" for f, m, n in self.lenses)
        shape = "line" if self.kind == "scratch" else "spot"
        return (f"sensor shadow at x {self.x_px:.1f}, y {self.y_px:.1f} px (a {shape}, {self.area:.0%} of a "
                f"sub-image, {self.depth:.0%} deep) stays at these pixels while the array moves, in {frames} "
                f"frames: the sensor's (cover-glass dust), not counted against {where}")


def sensor_shadows(results: list, meta: list[dict], cfg) -> tuple[list[SensorShadow], list, tuple[str, ...]]:
    """(the shadows, `results` with their lens flags taken off, notes for the whole batch); `meta` each
    frame's sidecar ({} without one). Results of None (frames that failed) are passed through."""
    spots = [(i, d) for i, r in enumerate(results) if r is not None for d in r.defects
             if d.error_type in SPOT_TYPES and "spot_x_px" in d.indexes]
    tol = max(TOLERANCE_PX, 0.1 * cfg.layout.subimage_pitch_px)
    shadows, taken, undecided = [], set(), 0
    for group in _same_pixels(spots, tol):
        if len({i for i, _ in group}) < 2:
            continue
        if not _array_moved(group, meta, cfg, results):
            undecided += 1
            continue
        shadows.append(group)
        taken.update((i, d.m, d.n) for i, d in group)
    # one shadow over the rims of two sub-images darkens each: its parts, less than a sub-image apart, are one
    shadows = [_shadow(g, results) for g in _joined(shadows, 0.5 * cfg.layout.subimage_pitch_px)]
    notes = ()
    if undecided:
        notes = (f"{undecided} dark region(s) sit at the same pixels in several frames, but no two of those frames "
                 "are known to show the array at different positions (no stage position in their sidecars, and "
                 "lenses numbered from the frame): kept as the lenses' defects; frames at stage positions at "
                 "least half a lens apart tell a sensor shadow from the array's",)
    amended = [r if r is None else _without(r, {(m, n) for j, m, n in taken if j == i}, shadows, cfg)
               for i, r in enumerate(results)]
    return shadows, amended, notes


def _same_pixels(spots: list, tol: float) -> list[list]:
    """The spots grouped by position: each joins the first group (one spot per frame) whose mean lies within
    `tol` px; groups kept in a grid of `tol` cells with running sums, so a long batch's many spots cost
    no more per spot than a short one's."""
    groups: list[list] = []
    sums: list[list[float]] = []  # per group: sum x, sum y, count
    cells: dict[tuple[int, int], list[int]] = {}
    for i, d in spots:
        x, y = d.indexes["spot_x_px"], d.indexes["spot_y_px"]
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        cx, cy = int(math.floor(x / tol)), int(math.floor(y / tol))
        near = [g for dx in (-1, 0, 1) for dy in (-1, 0, 1) for g in cells.get((cx + dx, cy + dy), ())]
        for g in sorted(near):
            sx, sy, n = sums[g]
            if math.hypot(x - sx / n, y - sy / n) <= tol and all(j != i for j, _ in groups[g]):
                groups[g].append((i, d))
                sums[g] = [sx + x, sy + y, n + 1]
                break
        else:
            groups.append([(i, d)])
            sums.append([x, y, 1])
            cells.setdefault((cx, cy), []).append(len(groups) - 1)
    return groups


def _joined(groups: list[list], reach_px: float) -> list[list]:
    """Groups whose mean positions lie within `reach_px` of each other's, joined (transitively)."""
    out: list[list] = []
    for g in groups:
        xy = _centre(g)
        near = [h for h in out if math.dist(_centre(h), xy) <= reach_px]
        for h in near:
            out.remove(h)
            g = h + g
        out.append(g)
    return out


def _centre(group: list) -> tuple[float, float]:
    return (float(np.mean([d.indexes["spot_x_px"] for _, d in group])),
            float(np.mean([d.indexes["spot_y_px"] for _, d in group])))


def _array_moved(group: list, meta: list[dict], cfg, results: list) -> bool:
    """Whether two frames of the group show the array at positions half a lens pitch or more apart: by
    their stage positions, else (lenses numbered from the array's corner) by a different lens under it."""
    for a in range(len(group)):
        for b in range(a + 1, len(group)):
            (i, da), (j, db) = group[a], group[b]
            pi, pj = _stage_mm(meta[i]), _stage_mm(meta[j])
            if pi is not None and pj is not None:
                if math.hypot(pi[0] - pj[0], pi[1] - pj[1]) * 1000.0 >= 0.5 * cfg.mla.pitch_um:
                    return True
                continue
            if not cfg.mla.counts_auto and (da.m, da.n) != (db.m, db.n):
                return True
    return False


def _stage_mm(meta: dict) -> tuple[float, float] | None:
    """A sidecar's stage position (mm), or None."""
    p = meta.get("stage_position_mm") if isinstance(meta, dict) else None
    if not isinstance(p, (list, tuple)) or len(p) < 2:
        return None
    try:
        x, y = float(p[0]), float(p[1])
    except (TypeError, ValueError):
        return None
    return (x, y) if math.isfinite(x) and math.isfinite(y) else None


def _shadow(group: list, results: list) -> SensorShadow:
    """The shadow its parts (frame index, Defect) make: the parts' area-weighted mean position, the area
    they cover in a frame (the mean over the frames) and their mean depth."""
    ds = [d for _, d in group]
    area = np.array([d.indexes.get("spot_area", d.magnitude) for d in ds], dtype=float)
    frames = sorted({i for i, _ in group})
    per_frame = [sum(a for (i, _), a in zip(group, area) if i == f) for f in frames]
    kinds = [d.error_type for d in ds]
    return SensorShadow(float(np.average([d.indexes["spot_x_px"] for d in ds], weights=area)),
                        float(np.average([d.indexes["spot_y_px"] for d in ds], weights=area)),
                        float(np.mean(per_frame)),
                        float(np.mean([d.indexes.get("spot_depth", float("nan")) for d in ds])),
                        max(set(kinds), key=kinds.count),
                        tuple((results[i].source, d.m, d.n) for i, d in group))


def _without(result, lenses: set, shadows: list[SensorShadow], cfg):
    """`result` without the lens flags in `lenses` (U(m,n)), its verdict recomputed, a note per shadow it
    shows."""
    mine = [s for s in shadows if any(f == result.source for f, _, _ in s.lenses)]
    if not lenses and not mine:
        return result
    defects = tuple(d for d in result.defects if (d.m, d.n) not in lenses)
    flagged, error_type = result.flagged.copy(), result.error_type.copy()
    for m, n in lenses:
        flagged[m - 1, n - 1], error_type[m - 1, n - 1] = False, ""
    return dataclasses.replace(result, defects=defects, flagged=flagged, error_type=error_type,
                               verdict=overall_verdict(defects, cfg.qc, result.assembly),
                               notes=tuple(result.notes) + tuple(s.sentence() for s in mine))
