"""Where each lens' sub-image is sampled when the light field is decoded: `LensSampling` and its three
sources, from least to most knowledge of the array.

- `design_sampling`: the design lattice, the config's sub-image pitch centred on the frame (no calibration);
- `lattice_sampling`: a calibrated grid's model (pitch, rotation, shear, radial term): every lens where a
  perfect lens of that fitted lattice would put its sub-image, which is what light-field tools decode with;
- `measured_sampling`: an inspection's report: each lens where it really sends its light (its measured
  sub-image centre, which carries the chief-ray shift of a pitch, decenter or tilt error), and a confidence
  for lenses the inspection found missing, obscured or outside the model's range.

A pixel's place inside a sub-image is the main lens' pupil point its light came through: the sub-image is
the pupil's image, centred on the chief ray through the lens. A lens whose sub-image moved by d sends the
pupil point that a perfect lens sends to x to x + d; sampling at the measured centre undoes it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mlaqc.errors import InputError
from mlaqc.optics.lattice import Lattice

# confidence of a lens the inspection flagged, by its type: a missing or opaque lens carries no light field;
# one whose light the frame shows altered in a way no resampling undoes (a local spot, a scratch, a reading
# outside every model) is kept at reduced weight. A dim lens is divided out by the white. A focal (radius)
# error blurs the lens' pupil image, and so its views, by a disc `focal_blur_px` across: its confidence is
# 1 / that blur in view pixels (capped at 1), so that a lens that has lost its angular detail (blur over 2
# px: `fill.filled` refills it along the scene's parallax) is told from one that blurs a view pixel
# or so, whose own views are better than any neighbour's (measured, bench/decode.py)
LENS_CONFIDENCE = {"missing": 0.0, "obscuration": 0.25, "scratch": 0.25, "unknown": 0.25}


@dataclass(frozen=True, eq=False)
class LensSampling:
    """Every lens' sub-image centre (x, y) in pixels, the scale of its pupil image, and its confidence.

    Arrays have shape (rows, cols), [m-1, n-1] is lens U(m,n). `weight` is 0 where the lens carries no
    usable light field (missing, outside the frame), 1 for a healthy lens.
    """

    x_px: np.ndarray
    y_px: np.ndarray
    scale: np.ndarray
    weight: np.ndarray
    packing: str
    pitch_px: float  # sub-image pitch (mean of the lattice's x and y spacing)
    radius_px: float  # radius of a sub-image (the pupil's image), the views stay inside it
    image_shape: tuple[int, int]
    source: str  # 'design', 'lattice' or 'measured'
    inside: np.ndarray | None = None  # lenses whose sub-image the frame holds (None: all)
    flagged: np.ndarray | None = None  # lenses an inspection flagged (measured sampling only)

    @property
    def shape(self) -> tuple[int, int]:
        return self.x_px.shape  # type: ignore[return-value]


def design_sampling(cfg: Any, image_shape: tuple[int, int]) -> LensSampling:
    """The design lattice: the config's sub-image pitch, the array centred on the frame, no rotation."""
    pitch = float(cfg.layout.subimage_pitch_px)
    lat = Lattice(cfg.mla.packing, cfg.mla.count_h, cfg.mla.count_w, pitch)
    x, y = lat.centres()
    h, w = image_shape
    x, y = x + (w - 1) / 2.0, y + (h - 1) / 2.0
    inside = _inside(x, y, image_shape, 0.5 * pitch)
    return LensSampling(x, y, np.ones_like(x), inside.astype(np.float64), cfg.mla.packing, pitch,
                        _design_radius(cfg), tuple(image_shape), "design", inside)


def lattice_sampling(grid: Any) -> LensSampling:
    """A calibrated grid's model centres (a perfect lens of the fitted lattice), found lenses weight 1."""
    pitch = float(np.mean(grid.pitch_px))
    x, y = np.asarray(grid.grid_x_px, float), np.asarray(grid.grid_y_px, float)
    inside = _inside(x, y, grid.image_shape, 0.5 * pitch)
    weight = (~np.asarray(grid.missing, bool) & inside).astype(np.float64)
    return LensSampling(x, y, np.ones_like(x), weight, grid.packing, pitch, _grid_radius(grid, pitch),
                        tuple(grid.image_shape), "lattice", inside)


def measured_sampling(grid: Any, report: dict[str, Any]) -> LensSampling:
    """Every lens the inspection flagged at its measured sub-image centre, the others where the lattice puts
    them (their offsets are within what the measurement resolves, so the lattice is their best estimate),
    weighted by what the inspection found (LENS_CONFIDENCE)."""
    base = lattice_sampling(grid)
    flagged, confidence = _flags(report, grid.shape, base.pitch_px)
    mx, my = np.asarray(grid.measured_x_px, float), np.asarray(grid.measured_y_px, float)
    use = flagged & np.isfinite(mx) & np.isfinite(my)
    x, y = np.where(use, mx, base.x_px), np.where(use, my, base.y_px)
    weight = base.weight * confidence
    return LensSampling(x, y, base.scale, weight, grid.packing, base.pitch_px, base.radius_px, base.image_shape,
                        "measured", base.inside, flagged)


def report_grid(report: dict[str, Any], source: str) -> Any:
    """The calibrated grid a report.json embeds (the inspection's own), InputError if it has none."""
    from mlaqc.inspection.grid import Grid

    if not isinstance(report.get("grid"), dict):
        raise InputError(f"report {source} holds no calibrated grid (written by an older mlaqc?): inspect the "
                         "array's white frame again")
    return Grid.from_json_dict(report["grid"], f"report {source}")


def check_same_array(grid: Any, report_grid_: Any, source: str) -> None:
    """InputError unless the report's grid is of the same array and frame as `grid`: lattice, lens count,
    frame size, and every lens within a quarter pitch of where `grid` puts it."""
    if report_grid_.packing != grid.packing or report_grid_.shape != grid.shape:
        raise InputError(f"report {source} is for a {report_grid_.cols}x{report_grid_.rows} {report_grid_.packing} "
                         f"array, but the frame's grid has {grid.cols}x{grid.rows} {grid.packing} lenses")
    if tuple(report_grid_.image_shape) != tuple(grid.image_shape):
        h, w = report_grid_.image_shape
        raise InputError(f"report {source} is for a {w}x{h} px frame, but the frame's grid is for "
                         f"{grid.image_shape[1]}x{grid.image_shape[0]} px")
    d = np.hypot(report_grid_.grid_x_px - grid.grid_x_px, report_grid_.grid_y_px - grid.grid_y_px)
    worst = float(np.nanmax(d))
    if worst > 0.25 * float(np.mean(grid.pitch_px)):
        raise InputError(f"report {source} puts the lenses up to {worst:.1f} px from where this frame's grid has "
                         "them: it is of another array or set-up (calibrate on this array's white frame)")


def _inside(x: np.ndarray, y: np.ndarray, shape: tuple[int, int], margin: float) -> np.ndarray:
    """Lenses whose sub-image centre lies at least `margin` px inside the frame."""
    h, w = shape
    return (x >= margin - 0.5) & (x <= w - 0.5 - margin) & (y >= margin - 0.5) & (y <= h - 0.5 - margin)


def _design_radius(cfg: Any) -> float:
    """The pupil image's radius on the sensor: the sub-image pitch times the main lens' f-number matching
    (a matched main lens fills the cell: radius = half the pitch), never more than half the pitch."""
    layout = cfg.layout
    matched = layout.micro.efl * 1e3 / cfg.mla.pitch_um  # the microlens' own f-number
    fill = min(1.0, matched / max(layout.image_f_number, 1e-9))
    return 0.5 * float(layout.subimage_pitch_px) * fill


def _grid_radius(grid: Any, pitch: float) -> float:
    """The sub-images' fitted radius (median over found lenses), at most half the pitch."""
    r = np.asarray(grid.radius_px, float)
    r = r[np.isfinite(r) & ~np.asarray(grid.missing, bool)]
    return float(min(np.median(r), 0.5 * pitch)) if r.size else 0.5 * pitch


def _flags(report: dict[str, Any], shape: tuple[int, int], pitch_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The lenses the report lists as defects, and every lens' confidence (LENS_CONFIDENCE by type, a focal
    error's by its blur, else 1)."""
    flagged, confidence = np.zeros(shape, bool), np.ones(shape)
    micro = _report_microlens(report)
    for d in report.get("defects", []):
        m, n = d["row"] - 1, d["col"] - 1
        flagged[m, n] = True
        c = LENS_CONFIDENCE.get(d["error_type"], 1.0)
        mag = d.get("magnitude")  # null in a report where it could not be read
        if d["error_type"] == "radius" and micro is not None and isinstance(mag, (int, float)) and np.isfinite(mag):
            c = min(1.0, 1.0 / max(focal_blur_px(micro, float(mag), pitch_px), 1e-9))
        confidence[m, n] = min(confidence[m, n], c)
    return flagged, confidence


def _report_microlens(report: dict[str, Any]) -> tuple[Any, float] | None:
    """The design microlens (radii µm, thickness, index) and the sensor's gap (µm) of the config a report
    was inspected with; None when it holds none or an unreadable one."""
    from mlaqc.optics.config import config_from_strict_json

    try:
        cfg = config_from_strict_json(report["config"], source="the report's config")
    except (KeyError, TypeError, AttributeError, InputError):
        return None
    return cfg.mla, cfg.layout.sensor_gap_mm * 1e3


def focal_blur_px(micro: tuple[Any, float], radius_rel: float, pitch_px: float) -> float:
    """Diameter (px, one view pixel apart) of the disc a lens with both radii scaled by 1 + `radius_rel`
    blurs its pupil image by: its light, one lens aperture (a sub-image pitch) wide, converges at its own
    back focal distance instead of at the sensor."""
    from mlaqc.optics.paraxial import thick_lens

    mla, gap_um = micro
    k = 1.0 + radius_rel
    bfd = thick_lens(mla.radius_front_um * k, mla.radius_back_um * k, mla.thickness_um, mla.refractive_index).bfd
    return float(pitch_px * abs(gap_um - bfd) / abs(bfd))
