"""Identification: flag lenses whose indexes leave the normal population, then say what is wrong.

Detection compares every lens with its own neighbourhood (a 5 x 5 local median: mlaqc.inspection.baselines).
What a frame does the same way everywhere is modelled and removed, not flagged: the pattern the sub-pixel
phase of the lens centres draws in every index (mlaqc.inspection.phase_pattern), and the bias and spread
of the edge classes (mlaqc.inspection.lens_classes). Each index is judged against the frame's own noise,
measured per lens class with a tail-aware spread and never below a floor set by the smallest reportable
error, so a noise-free frame is the easy case. Defocus (radius, thickness) is tested on the residual's
ring profile with a matched filter against the table's defocus signatures, whitened by the rings'
covariance over the array. A neighbour of a strong defect whose deviation is that defect's light in its
window is its echo (`spill`), and with the defect it is left out of the noise and of the phase pattern's
fit (`_disturbed`): in a small array a few defects' neighbourhoods are a large share of the lenses, and
the noise of a sub-image must not depend on the array's size. A lens whose window misses lenses (not
inspected, lost, left out) is compared with the median of its neighbours' values less the phase pattern
(`_phase_removed`): the pattern is too fast for a median, and one over other lenses aliases it otherwise.
The deviations, their noise and the score are mlaqc.inspection.detection's; each frame also reports its
detection limit (mlaqc.inspection.detection_limits).

Classification inverts the signature table (matched to the frame's rim width by the caller): the
flagged lens' feature changes, taken along and across its own shift, and its ring profile are fitted by
every error kind over its magnitude (noise-weighted least squares); the best kind gives type, magnitude
and direction; a deviation no kind explains is 'unknown', and a reading below the minimum reportable
size is counted, not flagged, unless the lens exceeds in one of its detection statistics, by a detection,
all that any error of that size gives (`sub_reportable_reach`): then it is no small error of any kind but
a foreign anomaly ('unknown'), however near its shape's reading.

Two limits are physical, not the method's (bench/type_separation.py: the best possible matched filter
against a frame's noise). With grid lens apertures (`mla.boundaries = "grid"`) a pitch error and a surface
decenter below about 10 µm change the sub-images identically to within the noise (both redirect the chief
ray of a lens whose cell stays on the grid), so such a lens is reported as 'position' with both readings,
never as a guess between them. With sag-intersection boundaries a decenter moves only the rear boundary
and tilts the neighbours' sub-images towards the lens, a pitch error moves both and does not: the
neighbours' tilt contrast against the lens' own shift types it (mlaqc.models.position_split) wherever
the frame's noise separates the two, and the frame reports from what size on it does. And a radius error
whose opposite sign fits about as well carries the other reading in `alternatives` (the microlens'
spherical aberration puts best focus in front of the paraxial focus the sensor sits at).

Hex lattices (`packing="hex"`, mlaqc.optics.lattice): a lens' neighbours are the lattice's six, each
along its own direction (echoes, the pitch/decenter contrast); the outer lenses and the row ends that
stick out have baselines (mlaqc.inspection.baselines) and sub-pixel phase patterns (lens_classes' groups)
of their own. A shift across the rows registers at about half its size (the pitch-wide discs overlap the
rows above and below), the less the larger it is, and blurs and dims its sub-image otherwise: the
features are read with the y offset and tilt mapped to the along-row scale (`signatures.to_along`), and
fitted against the kind's curves rendered along and across the rows, mixed by how much of the lens' shift
lies across them (`fit_all`).

Circular apertures (`mla.aperture = "circle"`), and hex: a lens' flux does not answer to its focal
errors behind its circle, so the flux noise floor is ~50 times lower than with cells, low enough for a
median window that is not centred on its lens, or that holds a defect, to read the vignetting as a
deviation. Their baseline windows stay centred near the edges and beside lenses left out, and a second
pass leaves the first pass' flagged lenses out of every baseline (`identify`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from mlaqc.inspection.baselines import local_deviations
from mlaqc.inspection.detection import (DETECTING, DETECTORS, DEVIATION_AXES, DEVIATION_KEYS, FOCUS_KINDS, Noise,
                                        RingNoise, detection_noise, detection_score, detector_values, deviations,
                                        focus_score, focus_templates, kind_curve, min_reportable, noise_floors,
                                        response, ring_noise)
from mlaqc.inspection.detection_limits import detection_limits
from mlaqc.inspection.filters import (
    lattice_max_of_neighbours,
    lattice_neighbours,
    max_filter_nearest,
    with_neighbours,
)
from mlaqc.inspection.lens_classes import corner_lenses, edge_classes, hex_row_ends
from mlaqc.inspection.medians import column_medians, nanmedian_columns
from mlaqc.inspection.phase_pattern import (PhaseModel, _phase_skips, phase_model,
                                            remove_phase_pattern, remove_phase_trend)
from mlaqc.inspection.results import Defect, LensMetrics
from mlaqc.models.position_split import (PositionSplit, contrast_spread, neighbour_contrast, split_limits,
                                         type_position)
from mlaqc.models.signatures import (FEATURES, RINGS, SignatureTable, along_gain_small, lens_features,
                                     to_along_xy)
from mlaqc.models.transmission import CLASSIFIED_KINDS, with_dim
from mlaqc.optics.config import QC
from mlaqc.optics.lattice import Lattice

UNEXPLAINED = 0.75  # a best fit leaving more than this share of the deviation's chi-square: type 'unknown' (measured: tracer defects leave 0.1-0.7, foreign anomalies 0.8-0.95)
_CHI2_AMBIGUOUS = 9.0  # an opposite-sign reading closer than this (3 sigma) is listed as an alternative
TWIN_SHARE = 0.05  # radius and thickness readings whose chi-squares differ by less than this share: alike




# a flagged lens whose centre moved this share of the sub-images' size (their second-moment radius) is its
# own defect, never a neighbour's echo: spilled light moved the echoes' centres by at most 0.014-0.022 of
# it on the Table 1, hex and microscope fixtures' frames (bench/decode.py's, noise-free and noisy), while a
# 7 µm pitch error next to a radius error 8 times its score moved its lens' by 0.07 (and was suppressed)
ECHO_MAX_OFFSET = 0.05


def spill(score: np.ndarray, flagged: np.ndarray, ratio: float = 0.65, asym: tuple | None = None,
          facing_ratio: float = 0.95, offset: tuple | None = None, packing: str = "square",
          moved_px: float = np.inf) -> np.ndarray:
    """Flagged lenses that are the echo of a stronger flagged neighbour: a defect disturbs its neighbours'
    windows (its light spills over). An echo scores under `ratio` times the neighbour; or, when the
    lenses' intensity tilts `asym` (x, y) are given, under `facing_ratio` times it with its tilt along
    the line to that neighbour (light that crossed into or out of its window), as where sub-images touch;
    or, with the lenses' `offset` (x, y), under `facing_ratio` times a neighbour that moved along that line.
    A lens whose own `offset` is `moved_px` or more is never an echo: spilled light does not move a
    sub-image that far. The neighbours are the lattice's (`Lattice.neighbours`: square 8, hex 6), each
    along its own direction from the lens."""
    rows, cols = score.shape
    lat = Lattice(packing, rows, cols)
    nbr = lattice_neighbours(packing, rows, cols)  # (K, k) flat indices, -1 off the array
    flag_score = np.where(flagged, score, 0.0)
    strongest = lattice_max_of_neighbours(flag_score, packing)
    if offset is not None:
        flagged = flagged & ~(np.hypot(*(np.nan_to_num(o) for o in offset)) >= moved_px)
    echo = flagged & (score < ratio * strongest)
    if asym is None and offset is None:
        return echo
    m, n = np.nonzero(flagged & ~echo & (strongest > 0))  # the few lenses that have a flagged neighbour
    if not m.size:
        return echo
    flat = m * cols + n
    others = nbr[flat]  # (L, k)
    # image convention: +x right, +y down, as the lattice's (u, v): the direction to each neighbour
    du, dv = _neighbour_vectors(lat, m, others)
    flat_score = np.concatenate([flag_score.ravel(), [0.0]])  # index -1: off the array, scores 0
    moved = [np.concatenate([np.nan_to_num(o).ravel(), [0.0]]) for o in offset] if offset is not None else None
    for j in range(others.shape[1]):
        other = flat_score[others[:, j]]
        # light that crossed in tilts the window towards the neighbour, light that left tilts it away:
        # either way along the line to it
        along = np.zeros(m.shape, bool)
        if asym is not None:
            along |= _aligned(asym[0][m, n], asym[1][m, n], du[:, j], dv[:, j])
        if moved is not None:
            along |= _aligned(moved[0][others[:, j]], moved[1][others[:, j]], du[:, j], dv[:, j])
        hit = along & (score[m, n] < facing_ratio * other)
        echo[m[hit], n[hit]] = True
    return echo


def _neighbour_vectors(lat: Lattice, r: np.ndarray, others: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(du, dv) (L, k) in pitches from lenses of rows `r` to their neighbours (by the lattice's steps for
    the row's parity, also where the neighbour is off the array)."""
    steps = lat.neighbour_steps(diagonal=True)[r % 2]  # (L, k, 2) (dr, dc)
    u0, v0 = lat.uv(r[:, None], np.zeros_like(r)[:, None])
    u1, v1 = lat.uv(r[:, None] + steps[..., 0], steps[..., 1])
    return u1 - u0, v1 - v0


def _aligned(vx: np.ndarray, vy: np.ndarray, dx, dy) -> np.ndarray:
    """Where the vectors (vx, vy) lie within 45° of the line along (dx, dy), either way."""
    vx, vy = np.nan_to_num(vx), np.nan_to_num(vy)
    return np.abs(vx * dx + vy * dy) > 0.7 * np.maximum(np.hypot(vx, vy), 1e-12) * np.hypot(dx, dy)


def _feature_vector(dev: dict[str, np.ndarray], rings: RingNoise, m: int, n: int) -> tuple[np.ndarray, float]:
    """FEATURES of lens [m, n] from its deviations, along its own shift, then its RINGS changes; and
    that shift's direction."""
    vec = np.concatenate([lens_features(dev, m, n), rings.dev[m, n]])
    return vec, float(np.degrees(np.arctan2(-dev["offset_y_px"][m, n], dev["offset_x_px"][m, n])))


def _feature_sigmas(sig: dict[str, float]) -> np.ndarray:
    s_off = 0.5 * (sig["offset_x_px"] + sig["offset_y_px"])
    s_asym = 0.5 * (sig["asym_x"] + sig["asym_y"])
    return np.array([s_off, s_off, s_asym, s_asym, sig["blur"], sig["flux"], sig["ssim"], sig["sharpness"]])


def _unit_noise(f: np.ndarray, sigmas: np.ndarray, whiten: np.ndarray | None) -> np.ndarray:
    """Feature changes (..., FEATURES [+ RINGS]) in unit-noise coordinates: each feature over its robust
    sigma, the ring profile through its whitening (its rings are correlated); without `whiten` the
    FEATURES alone."""
    n = len(FEATURES)
    head = f[..., :n] / sigmas
    return head if whiten is None else np.concatenate([head, f[..., n:] @ whiten], axis=-1)


def fit_kind(table: SignatureTable, kind: str, vec: np.ndarray, sigmas: np.ndarray, sign: int = 0,
             whiten: np.ndarray | None = None) -> tuple[float, float]:
    """Best magnitude of `kind` for feature changes `vec` and its chi-square (magnitude interpolated
    linearly in the table, through zero); `sign` restricts a signed kind to one side; `whiten`: the
    ring noise (`RingNoise.whiten`) to fit the ring profile too."""
    grid_m, grid_f = kind_curve(table, kind, sign)
    chi2 = _chi2(_unit_noise(vec, sigmas, whiten)[None, :], _unit_noise(grid_f, sigmas, whiten))
    i = int(np.argmin(chi2))
    return float(grid_m[i]), float(chi2[i])


def _chi2(observed: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Misfit of observed feature changes to predicted ones, both in unit-noise coordinates (last axis)."""
    return ((observed - predicted) ** 2).sum(axis=-1)




def fit_all(table: SignatureTable, vecs: np.ndarray, sigmas: np.ndarray,
            whiten: np.ndarray | None = None, across: np.ndarray | None = None) -> list[dict[str, tuple[float, float]]]:
    """`fit_kind` of every kind for many lenses' feature changes `vecs` (L, n_features) at once: per lens
    {kind: (magnitude, chi2)}. Same arithmetic as fit_kind, one array operation per kind. `across` (L,):
    each lens' share across the rows (`_across_share`; hex tables), which mixes the kind's along and
    across curves (same magnitudes) into the one its features are fitted against."""
    out: list[dict[str, tuple[float, float]]] = [{} for _ in range(len(vecs))]
    uv = _unit_noise(vecs, sigmas, whiten)
    other = table.across_table() if across is not None else table
    for kind in table.magnitudes:
        grid_m, grid_f = kind_curve(table, kind, 0)
        pred = _unit_noise(grid_f, sigmas, whiten)[None]
        if other is not table and kind in table.across:
            w = np.asarray(across, dtype=np.float64)[:, None, None]
            pred = (1.0 - w) * pred + w * _unit_noise(kind_curve(other, kind, 0)[1], sigmas, whiten)[None]
        chi2 = _chi2(uv[:, None, :], pred)
        best = np.argmin(chi2, axis=1)
        for q, i in enumerate(best):
            out[q][kind] = (float(grid_m[i]), float(chi2[q, i]))
    return out


def classify(table: SignatureTable, vec: np.ndarray, shift_dir: float, sigmas: np.ndarray,
             fits: dict[str, tuple[float, float]] | None = None, whiten: np.ndarray | None = None):
    """(type, magnitude, unit, direction, alternatives) for one lens' feature changes; `fits`: this lens'
    `fit_all` entry when already computed; `whiten` as in `fit_kind`."""
    fits = fits if fits is not None else {k: fit_kind(table, k, vec, sigmas, whiten=whiten) for k in table.magnitudes}
    best = min(fits, key=lambda k: fits[k][1])
    kind = CLASSIFIED_KINDS[best]
    direction = (shift_dir - table.phi0_deg[best]) % 360.0 if kind.directional else None
    alternatives: tuple = ()
    if best in ("pitch", "decenter") and "pitch" in fits and "decenter" in fits:
        # a white image cannot tell them apart (see the module note): report the pitch reading, list both
        readings = {k: (k, fits[k][0], "µm", (shift_dir - table.phi0_deg[k]) % 360.0) for k in ("pitch", "decenter")}
        return "position", fits["pitch"][0], "µm", readings["pitch"][3], (readings["pitch"], readings["decenter"])
    if not kind.directional and np.any(table.magnitudes[best] < 0) and np.any(table.magnitudes[best] > 0):
        # both signs blur the sub-image: if the other sign fits nearly as well, say so
        other_mag, other_chi2 = fit_kind(table, best, vec, sigmas, sign=-int(np.sign(fits[best][0]) or 1), whiten=whiten)
        if other_chi2 - fits[best][1] < _CHI2_AMBIGUOUS:
            alternatives = ((best, other_mag, kind.unit, None),)
    return best, fits[best][0], kind.unit, direction, alternatives


def _reportable_twin(fits: dict[str, tuple[float, float]], kind: str, mins: dict[str, float]):
    """(the other defocus kind, its magnitude) when `kind` is one of FOCUS_KINDS and the other's reading
    fits about as well (its chi-square within _CHI2_AMBIGUOUS, or TWIN_SHARE of the best one's: a best fit
    far above its degrees of freedom says the table's curves miss this lens by more than the noise, and a
    few per cent of that tells nothing) and is at least its reportable size; else None."""
    if kind not in FOCUS_KINDS:
        return None
    twin = next(k for k in FOCUS_KINDS if k != kind)
    if twin not in fits or fits[twin][1] - fits[kind][1] >= max(_CHI2_AMBIGUOUS, TWIN_SHARE * fits[kind][1]):
        return None
    return (twin, fits[twin][0]) if abs(fits[twin][0]) >= mins.get(twin, 0.0) - 1e-12 else None


def tolerance_for(error_type: str, qc: QC) -> float:
    """The QC limit of a type, in its unit (radius errors are relative)."""
    return {"pitch": qc.pitch_um, "position": qc.pitch_um, "decenter": qc.decenter_um, "radius": qc.radius_rel,
            "dim": qc.dim_rel, "obscuration": qc.obscuration_area, "scratch": qc.scratch_area,
            "tilt": qc.tilt_deg, "thickness": qc.thickness_um}.get(error_type, 0.0)


@dataclass(frozen=True)
class Identification:
    """What `identify` found on one frame: the flagged lenses and what this frame could have found."""

    defects: tuple[Defect, ...]
    flagged: np.ndarray  # (rows, cols) bool
    error_type: np.ndarray  # (rows, cols) object: the flagged lens' type, '' elsewhere
    score: np.ndarray  # (rows, cols) detection z
    detection_limit: dict  # per error type the smallest magnitude this frame detects (detection_limits.py)
    below_reportable: int  # significant deviations smaller than the minimum reportable error (not flagged)
    not_inspected: int  # lenses whose sub-image leaves the sensor
    noise: Noise | None = None  # the frame's noise the detection worked against (for measurements)
    feature_sigmas: tuple[float, ...] = ()  # the classification FEATURES' spreads on this frame
    readings: dict = field(default_factory=dict)  # per-lens index values against the typical lens (`_readings`)
    unreported: np.ndarray | None = None  # (rows, cols) bool: the `below_reportable` lenses (a later reading
    # may name them: mlaqc.inspection.obscuration)
    corners_not_judged: int = 0  # the array's corner lenses on the frame, not judged (lens_classes.corner_lenses)


def _disturbed(score: np.ndarray, qc: QC, outside: np.ndarray, missing: np.ndarray, packing: str) -> np.ndarray:
    """The lenses over the threshold that outscore their neighbours (a defect, not its echo), the missing
    ones, and their lattice neighbours: the lenses whose windows hold a defect's light."""
    source = (score > qc.detect_sigma) & (score >= lattice_max_of_neighbours(score, packing)) & ~outside
    return with_neighbours(source | missing, packing)


def _strength(detect_dev: dict[str, np.ndarray], noise: Noise, score: np.ndarray) -> np.ndarray:
    """Each lens' detection score, its DETECTORS read against the inner lenses' spreads where its own
    class' are wider: what `spill` compares a lens with its neighbours by. An edge lens' spread is its
    class', which a small array's defects widen; read in it, a defect next to the edge scored under the
    inner neighbour its light reached (12 x 12 at 50 rays/pixel: 16 against 20) and was taken for its echo."""
    inner = edge_classes(score.shape) == 2
    if not inner.any():
        return score
    sigma = np.broadcast_to(nanmedian_columns(noise.sigma[inner]), noise.sigma.shape)
    return np.maximum(score, detection_score(detect_dev, Noise(sigma, noise.rings)))


def _local_planes(metrics: LensMetrics, position, phase: PhaseModel | None, packing: str = "square",
                  centred: bool = False, exclude: np.ndarray | None = None) -> tuple[list, dict[str, np.ndarray]]:
    """Every index map's local deviation before the phase pattern is removed (classification, rings, then
    `position`'s; in one pass: the maps share the work), and the local baselines' trend over the array
    (each map's baseline minus its median per edge class, its phase trend removed). `centred`, `exclude`:
    as `local_deviations` takes them."""
    values = _index_values(metrics, position)
    planes = local_deviations(values, _index_axes(position), packing=packing, centred=centred, exclude=exclude)
    trend = class_centred([v - p for v, p in zip(values, planes)], packing)
    if phase is not None:
        trend = remove_phase_trend(trend, phase)
    names = list(DEVIATION_KEYS) + list(RINGS) + (["offset_x_px", "offset_y_px"] if position is not None else [])
    return planes, dict(zip(names, trend))


def _index_values(metrics: LensMetrics, position) -> list[np.ndarray]:
    """The index maps identification reads, in `_local_planes`' order: classification, rings, `position`'s."""
    return [metrics[k] for k in DEVIATION_KEYS] + [metrics[r] for r in RINGS] + list(position or ())


def _index_axes(position) -> list[str]:
    """The axis of each of `_index_values`' maps (`local_deviations`' `axes`)."""
    return DEVIATION_AXES + [""] * len(RINGS) + (["x", "y"] if position is not None else [])


def _phase_removed(values: list[np.ndarray], axes: list[str], raw: list[np.ndarray], phase: PhaseModel | None,
                   disturbed: np.ndarray | None = None, exclude: np.ndarray | None = None,
                   packing: str = "square", centred: bool = False, size: int = 5) -> list[np.ndarray]:
    """`remove_phase_pattern` of the local deviations `raw` of the index maps `values` (along `axes`),
    with the lenses whose baseline window misses lenses (not inspected, lost, `exclude`) taken against
    the local median of the values less the fitted phase pattern.

    The sub-pixel phase pattern is fast (a period of 3-6 lenses on a grid rotated 0.5-1°) and, in some
    maps, strong (along an edge the intensity tilt across it: 0.03 peak to peak against a noise of 0.003,
    the missing neighbour's light entering one side of the window only), so a median does not follow it:
    the deviation from it carries the pattern aliased through the window's phases, which the phase fit
    removes as long as every window holds the same lenses around its own. A window that misses lenses
    holds other phases and leaves its lens 5-10 sigma off: a healthy lens at the end of the inspected
    part of an edge (where the array's corner leaves the sensor), or beside a defect and its echoes left
    out of the baselines (circles), read as 'unknown'. With the pattern taken off the values first the
    median is of a slow field, and which lenses it misses does not matter."""
    if phase is None:
        return raw
    planes = remove_phase_pattern(raw, phase, disturbed)
    lost = ~np.isfinite(np.array(values, dtype=np.float64)).all(axis=0)
    if exclude is not None:
        lost |= exclude
    redo = max_filter_nearest(lost, size) & ~lost  # the lenses whose window misses some
    if not redo.any():
        return planes
    flat = [v - f for v, f in zip(values, _pattern_only([r - p for r, p in zip(raw, planes)], phase))]
    out = [p.copy() for p in planes]
    for cols in _column_strips(redo, 2 * size):
        part = None if exclude is None else exclude[:, cols]
        again = local_deviations([f[:, cols] for f in flat], axes, size, packing, centred, part, redo[:, cols])
        for o, a in zip(out, again):
            o[:, cols] = np.where(redo[:, cols], a, o[:, cols])
    return out


def _column_strips(redo: np.ndarray, margin: int) -> list[slice]:
    """The column ranges, `margin` columns either side of the lenses in `redo`, over which their baselines
    are computed again: a lens' window and the edge rules it meets (`_refine_baselines`, the hex edge
    columns) lie within a window and a ring of it, so a strip's cut edge leaves them as the whole map
    gives them, at the cost of the strip (a hex array's clipped edge columns: 2 strips of 13 columns)."""
    cols = redo.shape[1]
    near = np.convolve(redo.any(axis=0).astype(np.int64), np.ones(2 * margin + 1, np.int64), "same") > 0
    if near.sum() > cols // 2:
        return [slice(0, cols)]
    edges = np.flatnonzero(np.diff(np.concatenate(([0], near.astype(np.int8), [0]))))
    return [slice(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def _pattern_only(fits: list[np.ndarray], phase: PhaseModel) -> list[np.ndarray]:
    """The fitted phase patterns `fits` (one map per index) less each lens group's mean of them: what
    varies with the phase, not the group's own offset (the edge classes' bias, which a window spanning
    two groups must keep as it is in the values: taken off one group's lenses only, it moved a hex
    second-ring lens' flux median by 6 sigma)."""
    out = np.array(fits, dtype=np.float64)
    for sel, *_ in phase.groups:
        part = out[:, sel]
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # (a group with no lens measured: nothing to take off)
            mean = np.nanmean(part, axis=1, keepdims=True)
        out[:, sel] = part - np.where(np.isfinite(mean), mean, 0.0)
    return list(out)


def _deviation_maps(metrics: LensMetrics, planes: list[np.ndarray], position):
    """The classification deviations and their spreads (`deviations`), and the detection deviations (the
    classification ones with the offsets from the lower-noise `position` signal where it is given), from
    `_local_planes`' planes, phase pattern removed."""
    dev, sig = deviations(metrics, planes=planes[:len(DEVIATION_KEYS)])
    return dev, sig, dev if position is None else dict(dev, offset_x_px=planes[-2], offset_y_px=planes[-1])


def _judged(metrics: LensMetrics, position, phase: PhaseModel | None, table: SignatureTable, qc: QC,
            masks: tuple[np.ndarray, np.ndarray], packing: str, centred: bool = False,
            exclude: np.ndarray | None = None, passes: int = 3):
    """Every index map's deviation, the frame's noise and each lens' detection score: (classification
    deviations, their spreads, ring noise, detection deviations, baselines' trend, Noise, score).

    Judged again without the defects' neighbourhoods (`_disturbed`) while they grow, `passes` times at
    most: their light is no noise, nor part of the phase pattern (nine defects 4 apart on 12 x 12 made
    the spreads 1.5-3 x a healthy frame's). `masks`: the lenses outside the sensor and those missing;
    `centred`, `exclude`: the baselines' windows (`local_deviations`)."""
    det_floor, ring_floor = noise_floors(table, qc)
    raw, trend = _local_planes(metrics, position, phase, packing, centred, exclude)
    values = _index_values(metrics, position)
    axes = _index_axes(position)
    planes = _phase_removed(values, axes, raw, phase, exclude=exclude, packing=packing, centred=centred)
    dev, sig, detect_dev = _deviation_maps(metrics, planes, position)
    rings_at = slice(len(DEVIATION_KEYS), len(DEVIATION_KEYS) + len(RINGS))
    disturbed = None
    for step in range(passes + 1):
        rings = ring_noise(metrics, floor=ring_floor, planes=planes[rings_at], exclude=disturbed)
        noise = detection_noise(detect_dev, rings, det_floor, disturbed, packing)
        score = detection_score(detect_dev, noise, focus_score(rings, table))
        grown = _disturbed(score, qc, *masks, packing) | (False if disturbed is None else disturbed)
        if step == passes or not grown.any() or (disturbed is not None and (grown == disturbed).all()):
            break
        disturbed = grown
        if phase is not None and any(skip is not None for skip in _phase_skips(phase, disturbed)):
            planes = _phase_removed(values, axes, raw, phase, disturbed, exclude, packing, centred)
            dev, sig, detect_dev = _deviation_maps(metrics, planes, position)
    return dev, sig, rings, detect_dev, trend, noise, score


def class_centred(planes: list[np.ndarray], packing: str = "square") -> list[np.ndarray]:
    """Each (rows, cols) map minus its median over each edge class (edge lenses carry their own bias);
    on hex the row ends that stick out (`hex_row_ends`) are a class of their own."""
    cls = edge_classes(planes[0].shape)
    if packing == "hex":
        cls = np.where(hex_row_ends(planes[0].shape), 3, cls)
    stack = np.array(planes, dtype=np.float64)
    finite = np.isfinite(stack)
    if len(stack) and (finite == finite[0]).all():  # the usual case: every plane's medians in one call per class
        for c in range(4):
            sel = (cls == c) & finite[0]
            if sel.any():
                stack[:, sel] -= column_medians(stack[:, sel].T)[:, None]  # (np.median's, finite values)
        return list(stack)
    out = []
    for q in stack:
        for c in range(4):
            sel = (cls == c) & np.isfinite(q)
            if sel.any():
                q[sel] -= np.median(q[sel])
        out.append(q)
    return out


def _isotropic(dev: dict[str, np.ndarray], sig: dict[str, float], table: SignatureTable):
    """The classification deviations with the y components of the registration offset and the intensity
    tilt mapped to the size the same lens shift gives along the rows (`signatures.to_along_xy`, at the
    gain of each vector's whole size; hex: a shift across the rows registers at about half its size, the
    less the larger it is, and tilts the sub-image more), so that a lens shift reads alike in every direction, as the table (rendered along
    x) reads it; their spreads with them. Unchanged on a square lattice (no across curves, gains 1)."""
    out, out_sig = dict(dev), dict(sig)
    for x_name, name, column in (("offset_x_px", "offset_y_px", 0), ("asym_x", "asym_y", 2)):
        scale = along_gain_small(table, column)
        if scale != 1.0:
            out[name], out_sig[name] = to_along_xy(table, dev[x_name], dev[name], column), sig[name] * scale
    return out, out_sig


def _across_share(shift_dir_deg: np.ndarray) -> np.ndarray:
    """How much of a lens' shift lies across the rows, sin² of its direction: the weight of the table's
    across curves (`SignatureTable.across_table`) in the curve its features are fitted against."""
    return np.sin(np.radians(np.asarray(shift_dir_deg, dtype=np.float64))) ** 2


def _split_reading(split: PositionSplit, contrast: np.ndarray, m: int, n: int, shift_px: float,
                   sigma: float, readings: tuple):
    """A 'position' lens typed by its neighbours' tilt contrast (`contrast`: `neighbour_contrast` of the
    asymmetry deviations, `type_position`): (kind, magnitude, direction, alternatives), the chosen
    kind's reading from `readings` (pitch, decenter), or unchanged 'position' with both readings where
    this frame cannot tell."""
    kind, _ = type_position(split, float(contrast[m, n]), shift_px, sigma)
    if kind == "position":
        return "position", readings[0][1], readings[0][3], readings
    chosen = readings[0] if kind == "pitch" else readings[1]
    return kind, chosen[1], chosen[3], ()


def _readings(detect_dev: dict[str, np.ndarray], rings: RingNoise, trend: dict[str, np.ndarray]) -> dict:
    """Per-lens values against the array's typical lens: local deviation (phase pattern removed) plus its
    neighbourhood's trend; what `measure.measure_lenses` reads centres and focus from. Flux is the
    exception: its local deviation alone. A slow flux trend over the array is the illumination's and the
    vignetting's (a white target is never quite even, a camera's fall-off never quite the model's), not
    the lenses'; with sag-intersection boundaries a radius error changes its lens' aperture (+10 %: +6 %
    flux), so a +6 % brighter field centre would read as +8 % focal errors there."""
    out = {k: detect_dev[k] + trend[k] for k in ("offset_x_px", "offset_y_px", "blur", "ssim", "sharpness")}
    out["flux"] = detect_dev["flux"]
    out.update({r: rings.dev[..., j] + trend[r] for j, r in enumerate(RINGS)})
    return out


def _beyond_reportable(table: SignatureTable, kind: str, mag: float, power: float, sigmas: np.ndarray,
                       whiten: np.ndarray, dof: int, mins: dict[str, float]) -> bool:
    """Whether a lens whose best reading `mag` of `kind` is below the minimum reportable size deviates
    (`power`: its unit-noise chi-square against no error) clearly more than that kind's error at the
    minimum reportable size would make it: then the small reading is a poor fit, not a small error (a
    blurred or dimmed sub-image read as a -1.8 % radius error on sag-intersection tables, 60 % of it left
    unexplained, was dropped as too small to report)."""
    name = "pitch" if kind == "position" else kind
    if name not in table.magnitudes or kind not in mins:
        return False
    r = response(table, name, (-1.0 if mag < 0 else 1.0) * mins[kind])
    t = _unit_noise(r, sigmas, whiten)
    tt = float(t @ t)
    if not tt > 0.0:  # the reportable size lies outside the table's rendered range: no prediction to exceed
        return False
    # 4 sigma of the non-central chi-square an error of that size gives (variance 2 dof + 4 lambda)
    return power - dof > tt + 4.0 * np.sqrt(2.0 * dof + 4.0 * tt)


def sub_reportable_reach(table: SignatureTable, qc: QC, whiten: np.ndarray) -> tuple[np.ndarray, float]:
    """Per detection statistic (the DETECTORS' values, then the ring matched filter's z) the largest that any
    error of the table's kinds gives at or below its minimum reportable size: what a lens carrying only
    such an error does not exceed, whatever kind its reading names. `whiten`: the frame's ring noise."""
    mins = min_reportable(qc)
    tw = focus_templates(table) @ whiten
    tw /= np.maximum(np.linalg.norm(tw, axis=1, keepdims=True), 1e-300)
    det, focus = np.zeros(len(DETECTORS)), 0.0
    for kind in (k for k in table.magnitudes if k in mins):
        grid_m, grid_f = kind_curve(table, kind, 0)
        sub = grid_f[np.abs(grid_m) <= mins[kind] + 1e-12]  # (never empty: the curve holds the origin)
        det = np.maximum(det, detector_values(sub[:, :len(FEATURES)]).max(axis=0))
        focus = max(focus, float(((sub[:, len(FEATURES):] @ whiten) @ tw.T).max(initial=0.0)))
    return det, focus


def reach_excess(detect_dev: dict[str, np.ndarray], noise: Noise, focus: np.ndarray, reach: tuple[np.ndarray, float],
                 lenses: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Per lens of `lenses` (row and column indices) the largest z by which one of its detection statistics
    (`focus`: the ring matched filter's z map) exceeds `reach` (`sub_reportable_reach`), against its own
    noise: beyond the detection threshold, no error too small to report makes that lens."""
    m, n = lenses
    f = np.stack([detect_dev[k][m, n] for k in DEVIATION_KEYS], axis=-1)
    z = ((detector_values(f) - reach[0]) / noise.sigma[m, n])[:, DETECTING]
    z = np.concatenate([z, (focus[m, n] - reach[1])[:, None]], axis=-1)
    return np.max(np.where(np.isfinite(z), z, -np.inf), axis=-1, initial=-np.inf)


def _reach_excesses(lenses: list[tuple[int, int]], detect_dev: dict[str, np.ndarray], noise: Noise,
                    table: SignatureTable, qc: QC) -> dict[tuple[int, int], float]:
    """`reach_excess` of the flagged `lenses`, by lens: what tells a foreign anomaly whose nearest reading is
    too small to report from an error that small."""
    if not lenses:
        return {}
    rings = noise.rings
    idx = np.array(lenses, dtype=np.int64).T
    out = reach_excess(detect_dev, noise, focus_score(rings, table), sub_reportable_reach(table, qc, rings.whiten),
                       (idx[0], idx[1]))
    return dict(zip(lenses, out.tolist()))


def identify(metrics: LensMetrics, missing: np.ndarray, qc: QC, table: SignatureTable, position=None,
             phase=None, outside: np.ndarray | None = None, split: PositionSplit | None = None,
             packing: str = "square", aperture: str = "cell") -> Identification:
    """Flag, classify and size the defective lenses of one frame, and say what it could detect.

    `position`: optional (dx, dy) per-lens position residuals measured on this frame (the calibration's
    residual averaged with the registration: a lower-noise shift signal that replaces the offsets in detection);
    `phase`: the lenses' sub-pixel phases (x, y), whose index pattern is removed (`remove_phase_pattern`).
    `outside`: lenses whose sub-image (the pipeline: or index window) is not wholly on the sensor; they
    are not inspected (never flagged, never missing) and left out of every statistic.
    A lens is flagged when its deviation is significant (z above `qc.detect_sigma`, against the frame's
    own noise, floored) and its best reading is at least the minimum reportable error of its kind;
    classification always uses the registration features the table was built with. `split`: the optics'
    pitch/decenter split (mlaqc.models.position_split; None with grid boundaries), which types a
    'position' lens as pitch or decenter where this frame's noise allows. `packing`: the lattice the
    (rows, cols) maps index (mlaqc.optics.lattice), which says who a lens' neighbours are. `aperture`:
    the MLA's (`mla.aperture`): with circular apertures, and on hex, the baselines near the edges are
    taken over windows centred on their lens (`_refine_baselines`): a lens' flux does not answer to
    its focal errors behind a circle, so its noise floor is low enough for an off-centre window's
    reading of the vignetting to flag the second row; behind circles the flagged lenses are then left
    out of every baseline and the frame is judged again."""
    centred = packing == "hex" or aperture == "circle"  # (square cells keep the windows they were validated with)
    phase = phase_model(phase, packing, centred) if phase is not None else None
    outside = np.zeros(missing.shape, bool) if outside is None else outside
    if outside.any():
        metrics = LensMetrics({k: np.where(outside, np.nan, v) for k, v in metrics.values.items()})
        position = None if position is None else tuple(np.where(outside, np.nan, p) for p in position)
        missing = missing & ~outside
    threshold = np.full(missing.shape, qc.detect_sigma)
    corners = corner_lenses(missing.shape) & ~outside & ~missing  # not judged (their deviation is always 0)
    # a missing lens' neighbours lack its light: left out of every baseline, or the windows of the lenses
    # two and three away read them (hex, Airy rims, 1 % noise: asymmetry z 6.1-6.3 three lenses off). The
    # missing lens itself stays in (measured: left out too, a Table 1 Airy frame's lens two away read
    # z 8.2, six lenses of one side gone from its window). (Circles leave every flagged lens out in a
    # second pass below; a first pass with the echoes left out shrank their centred windows, which mirror
    # each lens left out, and flagged 3 lenses beside them.)
    echoes = with_neighbours(missing, packing) & ~missing if missing.any() and aperture != "circle" else None
    judged = _judged(metrics, position, phase, table, qc, (outside, missing), packing, centred, echoes)
    flagged = ((judged[-1] > threshold) & ~outside & ~corners) | missing
    if aperture == "circle" and flagged.any():
        # circles: once more with the flagged lenses left out of every baseline, as a lens not measured is.
        # A median over a window spanning a steep trend (vignetting: up to 1.5 % of flux per lens near a
        # Table 1 frame's corners) moves by a rank step when one value in it is an outlier: a missing lens
        # or a defect's echoes in a neighbour's window read as flux deviations of 0.2 %, which the low flux
        # floor of circular apertures (a lens' flux does not answer to its focal errors behind its circle)
        # flagged at z 6-8 on noise-free analytic frames. (Hex cells do not need it: 0-1 false flags per
        # cell on the analytic matrix with or without, for 2x the identification time.)
        judged = _judged(metrics, position, phase, table, qc, (outside, missing), packing, centred, flagged)
        flagged = ((judged[-1] > threshold) & ~outside & ~corners) | missing
    dev, sig, rings, detect_dev, trend, noise, score = judged
    size = metrics.values.get("size_px")
    moved = ECHO_MAX_OFFSET * float(np.nanmedian(size)) if size is not None and np.isfinite(size).any() else np.inf
    flagged &= ~spill(_strength(detect_dev, noise, score), flagged, asym=(dev["asym_x"], dev["asym_y"]),
                      offset=(detect_dev["offset_x_px"], detect_dev["offset_y_px"]), packing=packing,
                      moved_px=moved) | missing
    feat_dev, feat_sig = _isotropic(dev, sig, table)  # what the lens' features are read from
    sigmas = _feature_sigmas(feat_sig)
    error_type = np.full(flagged.shape, "", dtype=object)
    defects = []
    lenses = list(zip(*np.nonzero(flagged & ~missing)))
    features = [_feature_vector(feat_dev, rings, m, n) for m, n in lenses]
    vecs = np.array([f[0] for f in features]) if features else np.zeros((0, len(sigmas) + len(RINGS)))
    across = _across_share([f[1] for f in features]) if table.across else None
    typing = with_dim(table)  # the kinds a flagged lens may be typed as: the rendered ones and a dim lens
    fits = dict(zip(lenses, fit_all(typing, vecs, sigmas, rings.whiten, across)))
    shifts = dict(zip(lenses, features))
    mins = min_reportable(qc)
    contrast = neighbour_contrast(dev["asym_x"], dev["asym_y"], packing) if split is not None else None
    split_sigma = contrast_spread(contrast) if split is not None else float("nan")
    unreported = np.zeros(flagged.shape, bool)  # significant, no error of its kind worth reporting
    excess = _reach_excesses(lenses, detect_dev, noise, table, qc)
    for m, n in zip(*np.nonzero(flagged)):
        indexes = metrics.at(m + 1, n + 1)
        if missing[m, n]:
            defects.append(Defect(int(m) + 1, int(n) + 1, "missing", float("nan"), "", None, float("inf"), False, indexes))
            error_type[m, n] = "missing"
            continue
        vec, shift_dir = shifts[(m, n)]
        kind, mag, unit, direction, alts = classify(typing, vec, shift_dir, sigmas, fits[(m, n)], rings.whiten)
        if kind == "position" and split is not None:
            kind, mag, direction, alts = _split_reading(split, contrast, m, n, vec[0], split_sigma, alts)
        uv = _unit_noise(vec, sigmas, rings.whiten)
        dof = len(uv) - 1  # what noise alone leaves in the best fit's chi-square, on average
        misfit = min(c for _, c in fits[(m, n)].values()) - dof
        if misfit > max(UNEXPLAINED * (float(uv @ uv) - dof), 4.0 * np.sqrt(2.0 * dof)):  # and beyond noise
            # significant, but no error kind of the table explains it: say so rather than force a reading
            kind, mag, unit, direction, alts = "unknown", float("nan"), "", None, ()
        elif abs(mag) < mins.get(kind, 0.0) - 1e-12:
            # a lens one of whose detection statistics exceeds, by a detection, all that any error below
            # the reportable size gives (a rim blurred x2 behind an Airy rim: sharpness z 32-37 where a
            # -2 % radius error gives 7; its -1.2 % radius reading left 60 % unexplained), or which deviates
            # more than an error of its kind at the reportable size would: not a small error of that kind
            if excess[(m, n)] > qc.detect_sigma or _beyond_reportable(typing, kind, mag, float(uv @ uv), sigmas,
                                                                      rings.whiten, dof, mins):
                kind, mag, unit, direction, alts = "unknown", float("nan"), "", None, ()
            elif twin := _reportable_twin(fits[(m, n)], kind, mins):
                # defocused: read as a thickness error too small to report while a radius error worth
                # reporting fits about as well (or the other way round); the frame cannot tell them apart,
                # and its detection limit promises the radius error (a +7.7 % radius read 0.5 µm of
                # thickness and was dropped on a frame stating +5.6 %): the reportable reading, the other
                # as its alternative
                alts = ((kind, mag, unit, None),)
                kind, mag, unit = twin[0], twin[1], CLASSIFIED_KINDS[twin[0]].unit
            else:
                flagged[m, n] = False  # significant, but smaller than any error worth reporting
                unreported[m, n] = True
                continue
        limit = tolerance_for(kind, qc)
        defects.append(Defect(int(m) + 1, int(n) + 1, kind, mag, unit, direction, float(score[m, n]),
                              abs(mag) <= limit, indexes, alternatives=alts))
        error_type[m, n] = kind

    limits = detection_limits(table, qc, noise, ~outside & ~corners)
    if "decenter" in table.magnitudes:  # (a flat-sided MLA has no decenter: nothing to tell pitch from)
        limits["pitch_vs_decenter"] = split_limits(split, split_sigma)
    return Identification(tuple(defects), flagged, error_type, score, limits, int(unreported.sum()),
                          int(outside.sum()), noise, tuple(float(x) for x in sigmas),
                          _readings(detect_dev, rings, trend), unreported, int(corners.sum()))


__all__ = ["identify", "Identification", "classify", "deviations", "detection_score", "FEATURES"]
