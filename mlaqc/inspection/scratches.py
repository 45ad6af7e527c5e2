"""Scratches: a dark line across one sub-image or on through its neighbours'.

A lens' dark region (mlaqc.inspection.obscuration) is a line when it is long and narrow: the second
moments of its pixels about their centroid give its length and width (a uniform segment's variance along
it is L²/12) and its axis. Such a lens is typed 'scratch' (its area share against `qc.scratch_area`, its
axis as the direction, 0-180°), and neighbouring scratched lenses whose lines are one line on the sensor
(axes within AXIS_DEG, each centroid within REACH_PX of the other's line) are reported as one scratch.

Physics: every pixel of a sub-image takes light from the whole microlens aperture (the sensor sits at
the microlens' focus, conjugate to the main lens' pupil), so a mark on the lens' curved face dims the
whole sub-image (a 'dim' lens). A line drawn inside the sub-image lies where the light towards one pixel
is narrow: near the sensor-side focus, on the array's back surface or the sensor's cover glass. Frames
at two stage positions tell the two apart (mlaqc.inspection.sensor_dust).
"""

from __future__ import annotations

import math

import numpy as np

ELONGATION = 3.0  # length over width of a line; a round spot is 1, one cut by the interior's edge under 2.5
MIN_LENGTH_PX = 6.0  # a shorter dark region is a spot whatever its shape
MIN_LENGTH_INTERIOR = 0.6  # nor a line shorter than this share of the interior's radius (large sub-images)
AXIS_DEG = 20.0  # neighbours' lines this close in angle (and collinear) are one scratch
REACH_PX = 3.0


def line_shape(dark, dx, dy, sx, sy):
    """Per lens (K) the dark region's (elongation, axis_deg, length_px, width_px) from its pixels' second
    moments about their centroid (sx, sy); `dark` (K, h, w) bool, (dx, dy) the pixels' offsets from the
    lens' centre (y down). The axis is counterclockwise from +x towards the image top, in [0, 180)."""
    n = np.maximum(dark.sum(axis=(1, 2)), 1)
    ex, ey = dx - sx[:, None, None], dy - sy[:, None, None]
    cxx = np.where(dark, ex * ex, 0.0).sum(axis=(1, 2)) / n
    cyy = np.where(dark, ey * ey, 0.0).sum(axis=(1, 2)) / n
    cxy = np.where(dark, ex * ey, 0.0).sum(axis=(1, 2)) / n
    half, diff = 0.5 * (cxx + cyy), np.hypot(0.5 * (cxx - cyy), cxy)
    big, small = half + diff, np.maximum(half - diff, 1.0 / 12.0)  # a one-pixel-wide line's variance floor
    axis = (-np.degrees(0.5 * np.arctan2(2.0 * cxy, cxx - cyy))) % 180.0
    return np.sqrt(big / small), axis, np.sqrt(12.0 * big), np.sqrt(12.0 * small)


def is_line(reading) -> bool:
    """Whether a lens' dark region (an obscuration.SpotReading) is a line: long and narrow."""
    shortest = max(MIN_LENGTH_PX, MIN_LENGTH_INTERIOR * reading.interior_px)
    return reading.elongation >= ELONGATION and reading.length_px >= shortest


def next_to_lines(defects, shape: tuple[int, int]) -> np.ndarray:
    """(rows, cols) bool: the lenses next to a scratched one, where its line may run on though their own
    deviation stayed under the detection threshold (the middle lens of a line through three is darkened
    symmetrically, and shows less than its neighbours, which the line enters from one side)."""
    out = np.zeros(shape, bool)
    for d in defects:
        if d.error_type == "scratch":
            out[max(d.m - 2, 0):d.m + 1, max(d.n - 2, 0):d.n + 1] = True
    return out


def scratch_groups(defects) -> list[list]:
    """The scratched lenses (Defects typed 'scratch', their `spot_x_px`/`spot_y_px` on the sensor) grouped
    into scratches: lattice neighbours whose lines are one line."""
    lenses = [d for d in defects if d.error_type == "scratch"]
    parent = list(range(len(lenses)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, a in enumerate(lenses):
        for j in range(i + 1, len(lenses)):
            if _one_line(a, lenses[j]):
                parent[root(j)] = root(i)
    groups: dict[int, list] = {}
    for i, d in enumerate(lenses):
        groups.setdefault(root(i), []).append(d)
    return sorted(groups.values(), key=lambda g: (g[0].m, g[0].n))


def _one_line(a, b) -> bool:
    """Two scratched lenses next to each other whose lines are one: axes within AXIS_DEG and each one's
    centroid within REACH_PX (or its line's width) of the other's line."""
    if abs(a.m - b.m) > 1 or abs(a.n - b.n) > 1:
        return False
    turn = abs((a.direction_deg - b.direction_deg + 90.0) % 180.0 - 90.0)
    if turn > AXIS_DEG:
        return False
    return _off_line(a, b) <= max(REACH_PX, a.indexes.get("scratch_width_px", 0.0)) and \
        _off_line(b, a) <= max(REACH_PX, b.indexes.get("scratch_width_px", 0.0))


def _off_line(a, b) -> float:
    """The distance (px) of b's centroid from a's line on the sensor."""
    t = math.radians(a.direction_deg)
    ex, ey = b.indexes["spot_x_px"] - a.indexes["spot_x_px"], b.indexes["spot_y_px"] - a.indexes["spot_y_px"]
    return abs(ex * math.sin(t) + ey * math.cos(t))  # the axis (cos t, -sin t) with y down: its normal's part


def scratch_notes(defects) -> tuple[str, ...]:
    """One line per scratch for the console and the report: its lenses, axis and extent on the sensor."""
    notes = []
    for group in scratch_groups(defects):
        names = ", ".join(f"U({d.m},{d.n})" for d in group)
        xs = [d.indexes["spot_x_px"] for d in group]
        ys = [d.indexes["spot_y_px"] for d in group]
        ends = (group[0].indexes.get("scratch_length_px", 0.0) + group[-1].indexes.get("scratch_length_px", 0.0)) / 2
        span = math.hypot(max(xs) - min(xs), max(ys) - min(ys)) + ends  # centroid to centroid, plus the ends
        axis = round(_mean_axis(group)) % 180  # 179.7° is the line at 0°
        notes.append(f"scratch: a dark line at {axis}° through {names} ({len(group)} lens"
                     f"{'es' if len(group) > 1 else ''}, about {span:.0f} px on the sensor); it is drawn inside "
                     "the sub-images, so it lies near the sensor-side focus (the array's back surface or the "
                     "sensor's cover glass), not on the lenses' curved faces; frames at two stage positions "
                     "tell which")
    return tuple(notes)


def _mean_axis(group) -> float:
    """The mean of axes (0-180°) as doubled angles."""
    t = np.radians([2.0 * d.direction_deg for d in group])
    return float(np.degrees(np.arctan2(np.sin(t).mean(), np.cos(t).mean())) / 2.0) % 180.0
