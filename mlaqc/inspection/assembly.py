"""The MLA's assembly errors in physical units, read from the calibrated grid through the camera model.

The projection fit (mlaqc.inspection.projection) gives six raw readings from the lens centres. Calibration
through the camera model (mlaqc.models.assembly_model): the raw readings of the tracer's own
frames of this camera at its design placement, with each error alone and with every pair, give a
second-order model of what the fit reads (zero point, response curves, cross terms), which each frame's
raw readings are solved through (`AssemblyModel.solve`); the sigmas carry the frame's noise, the calibration's noise and
its systematic error (`AssemblyModel.systematic_at`). A second, independent distance comes from the
sub-images' focus: their median radius grows with the gap (0.022 px per µm on Table 1: its 10,404
lenses read it to 0.01 µm), calibrated on the same frames; it does not depend on the MLA's pitch, but on
the main lens' aperture.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from mlaqc.inspection.projection import FIELDS, raw_components
from mlaqc.inspection.results import finite_or_none

UNITS = {"mla_sensor_distance_um": "µm", "mla_rotation_deg": "deg", "mla_tilt_x_deg": "deg",
         "mla_tilt_y_deg": "deg", "mla_shift_x_um": "µm", "mla_shift_y_um": "µm"}
ASSUMPTIONS = ("read from the calibrated lens centres through the camera model (the projection fit calibrated on "
               "the tracer's frames of this camera); held at their design values: the main lens, the MLA's pitch "
               "(a pitch scale error of 1 ppm reads as {ppm_um:.2f} µm of distance) and the sensor (pixel size, "
               "centred on the optical axis); distance = change of the MLA-sensor gap from design; shift = MLA "
               "centre against the sensor centre; rotation about the optical axis, tilts about the sensor's x "
               "(right) and y (down) axes; sigmas: the frame's and the calibration's noise and the calibration's "
               "systematic error; "
               "distance_from_focus_um: the same gap from the sub-images' radius, which assumes the main lens' "
               "aperture at its design value")
# QC keys ([qc]) bounding each reading (absolute value; tilt and shift bound both components)
COVERAGE = 0.5  # the share of the array's lenses the readings need (a corner of it cannot place the array)
RANGE_MARGIN = 1.25  # readings up to this much beyond the rendered range are extrapolated, further ones are not
UNCALIBRATED = 0.10  # relative uncertainty of an uncalibrated reading
QC_KEYS = {"mla_sensor_distance_um": "assembly_distance_um", "mla_rotation_deg": "assembly_rotation_deg",
           "mla_tilt_x_deg": "assembly_tilt_deg", "mla_tilt_y_deg": "assembly_tilt_deg",
           "mla_shift_x_um": "assembly_shift_um", "mla_shift_y_um": "assembly_shift_um"}


@dataclass(frozen=True)
class Assembly:
    """The six global readings (error-map units) with 1-sigma uncertainties; NaN with `reason` when unread,
    and NaN for a reading this frame does not determine (`_undetermined`, said in `note`)."""

    values: dict  # field -> reading
    sigma: dict  # field -> 1-sigma
    distance_from_focus_um: float = float("nan")
    distance_from_focus_sigma_um: float = float("nan")
    lenses_used: int = 0
    rms_residual_px: float = float("nan")
    ppm_um: float = float("nan")  # distance read per ppm of MLA pitch scale error
    reason: str = ""
    note: str = ""  # e.g. a reading beyond the calibrated range
    exceeded: tuple[str, ...] = ()  # one line per `[qc]` bound exceeded (`checked`)

    def value(self, name: str) -> float:
        return float(self.values[name])

    @property
    def read(self) -> bool:
        return not self.reason

    def to_json_dict(self) -> dict:
        out = {k: {"value": finite_or_none(self.value(k)), "sigma": finite_or_none(self.sigma[k])} for k in FIELDS}
        out["distance_from_focus_um"] = {"value": finite_or_none(self.distance_from_focus_um),
                                         "sigma": finite_or_none(self.distance_from_focus_sigma_um)}
        out["assumptions"] = ASSUMPTIONS.format(ppm_um=self.ppm_um) if math.isfinite(self.ppm_um) else \
            ASSUMPTIONS.replace(" (a pitch scale error of 1 ppm reads as {ppm_um:.2f} µm of distance)", "")
        out["lenses_used"] = int(self.lenses_used)
        out["rms_residual_px"] = finite_or_none(self.rms_residual_px)
        out["out_of_bounds"] = list(self.exceeded)
        if self.note:
            out["note"] = self.note
        if self.reason:
            out["not_read"] = self.reason
        return out

    def out_of_bounds(self, qc) -> list[str]:
        """One line per reading beyond its `[qc]` bound (bounds None: unbounded)."""
        lines = []
        for k in FIELDS:
            bound = getattr(qc, QC_KEYS[k], None)
            v = self.value(k)
            if bound is not None and math.isfinite(v) and abs(v) > bound:
                lines.append(f"assembly {k} = {v:+.4g} {UNITS[k]} exceeds qc.{QC_KEYS[k]} = {bound:g}")
        return lines

    def checked(self, qc) -> Assembly:
        """This reading with the `[qc]` bounds it exceeds recorded (they fail the verdict); unread, with
        bounds set, it says they were not checked."""
        if self.reason and any(getattr(qc, key, None) is not None for key in set(QC_KEYS.values())):
            return dataclasses.replace(self, note="its [qc] assembly bounds were not checked")
        unchecked = [f"qc.{QC_KEYS[k]} not checked on {k}, not determined" for k in FIELDS
                     if getattr(qc, QC_KEYS[k], None) is not None and not math.isfinite(self.value(k))]
        note = "; ".join(p for p in (self.note, *unchecked) if p)
        return dataclasses.replace(self, exceeded=tuple(self.out_of_bounds(qc)), note=note)

    def short_text(self) -> str:
        """The readings in a line of about 90 characters (the app's status), sigmas left out."""
        if self.reason:
            return "Assembly: not read"
        def v(name: str, digits: int) -> str:
            x = self.values[name]
            return f"{x:+.{digits}f}" if math.isfinite(x) else "?"

        return (f"Assembly: distance {v('mla_sensor_distance_um', 2)} µm, rotation {v('mla_rotation_deg', 4)}°, "
                f"tilt {v('mla_tilt_x_deg', 3)} / {v('mla_tilt_y_deg', 3)}°, shift "
                f"{v('mla_shift_x_um', 2)} / {v('mla_shift_y_um', 2)} µm"
                + (" (out of bounds)" if self.exceeded else ""))

    def summary_line(self) -> str:
        """The console's `assembly:` line: every reading with its 1-sigma, and the note."""
        if self.reason:
            return f"  assembly: not read ({self.reason})" + (f"; {self.note}" if self.note else "")
        focus = (f" (focus {self.distance_from_focus_um:+.2f} ± {self.distance_from_focus_sigma_um:.2f})"
                 if math.isfinite(self.distance_from_focus_um) else "")
        return (f"  assembly: distance {self._pm('mla_sensor_distance_um', 2, ' µm')}{focus}, "
                f"rotation {self._pm('mla_rotation_deg', 4, ' deg')}, "
                f"tilt x/y {self._pm_pair('mla_tilt_x_deg', 'mla_tilt_y_deg', 3, ' deg')}, "
                f"shift x/y {self._pm_pair('mla_shift_x_um', 'mla_shift_y_um', 2, ' µm')}"
                + (f"; {self.note}" if self.note else ""))

    def _pm(self, name: str, digits: int, unit: str = "") -> str:
        """One reading as 'value ± sigma unit', or 'not determined' (`_undetermined`)."""
        v, s = self.values[name], self.sigma[name]
        return f"{v:+.{digits}f} ± {s:.{digits}f}{unit}" if math.isfinite(v) else "not determined"

    def _pm_pair(self, x: str, y: str, digits: int, unit: str) -> str:
        """'x ± s / y ± s unit', each with its unit where one of them is not determined."""
        first = self._pm(x, digits, "" if math.isfinite(self.values[y]) else unit)
        return f"{first} / {self._pm(y, digits, unit)}"


def not_read(reason: str) -> Assembly:
    """An Assembly with no readings, saying why."""
    nan = float("nan")
    return Assembly({k: nan for k in FIELDS}, {k: nan for k in FIELDS}, reason=reason)


def _focus_distance(model, true: np.ndarray, radius_px: float) -> tuple[float, float]:
    """The distance at which the model's median radius (the other readings held at `true`) is `radius_px`,
    and d radius / d distance there."""
    t = true.copy()
    for _ in range(30):
        slope = model.slopes(t)[6, 0]
        if not slope:
            return float("nan"), 0.0
        step = (radius_px - model.raw(t)[6]) / slope
        t[0] += step
        if abs(step) < 1e-9:
            break
    return float(t[0]), float(model.slopes(t)[6, 0])


def measure_assembly(grid, cfg, model=None) -> Assembly:
    """The six assembly readings from a calibrated `grid` (mlaqc.inspection.calibrate.Grid) of `cfg`'s
    camera, through its assembly model (mlaqc.models.assembly_model; looked up when None: shipped or
    cached, never rendered here — `mlaqc models` renders it once for new optics)."""
    count = cfg.mla.count_h * cfg.mla.count_w
    if cfg.mla.counts_auto:
        return not_read("the frame sees part of the array (mla.count_w / count_h = \"auto\"): the array's placement "
                        "needs its edges in view")
    if grid.shape != (cfg.mla.count_h, cfg.mla.count_w):
        return not_read(f"the grid has {grid.cols} x {grid.rows} lenses, the camera's MLA "
                        f"{cfg.mla.count_w} x {cfg.mla.count_h}: the array's placement needs the whole array")
    if model is None:
        from mlaqc.models.assembly_model import assembly_model

        try:
            model = assembly_model(cfg, build_if_missing=False)
        except FileNotFoundError:
            return not_read("no assembly calibration for these optics yet: `mlaqc models --config CONFIG` renders "
                            "it once")
        except (ValueError, TypeError, KeyError, OSError) as exc:
            return not_read(f"the assembly calibration could not be read ({exc})")
    comps = raw_components(grid, cfg, model.pupil_mm)
    if comps is None or comps[2] < COVERAGE * count:
        used = 0 if comps is None else comps[2]
        return not_read(f"{used} of the {count} lenses were read whole: the array's placement needs at least "
                        f"{COVERAGE:.0%} of them")
    raw, cov, used, rms = comps
    if not np.all(np.isfinite(raw[:6])):
        return not_read("the lens centres could not be fitted")
    try:
        true, slopes = model.solve(raw)
        inv = np.linalg.inv(slopes)
    except np.linalg.LinAlgError:
        return _undetermined(_uncalibrated(model, raw, cov, used, rms), _spread(cov), model.extent(), cfg)
    matched = np.all(np.abs(model.raw(true)[:6] - raw[:6]) <= 1e-6 * (1.0 + np.abs(raw[:6])))
    if not (matched and np.all(np.abs(true) <= RANGE_MARGIN * model.extent())):
        return _undetermined(_uncalibrated(model, raw, cov, used, rms), _spread(cov), model.extent(), cfg)
    cov_true = inv @ (cov[:6, :6] + np.diag(np.square(model.zero_sigma[:6]))) @ inv.T
    sig = np.hypot(np.sqrt(np.clip(np.diag(cov_true), 0, None)), model.systematic_at(true))
    focus, r_slope = _focus_distance(model, true, float(raw[6]))
    focus_sigma = math.hypot(math.sqrt(cov[6, 6]), model.zero_sigma[6]) / abs(r_slope) if r_slope else float("nan")
    gap_mm = cfg.layout.z_sensor_mm - cfg.layout.z_mla_mm
    ppm_um = 1e-3 * (model.pupil_mm + gap_mm) / slopes[0, 0]
    over = [f"{k} {v:+.3g}" for k, v, lim in zip(FIELDS, true, model.extent()) if abs(v) > lim]
    note = f"beyond the rendered range, extrapolated: {', '.join(over)}" if over else ""
    return _undetermined(Assembly(dict(zip(FIELDS, (float(v) for v in true))),
                                  dict(zip(FIELDS, (float(v) for v in sig))),
                                  focus, float(focus_sigma), used, rms, float(ppm_um), note=note),
                         _spread(cov_true), model.extent(), cfg)


def _spread(cov: np.ndarray) -> np.ndarray:
    """The six readings' 1-sigma from this frame's own fit (`cov`'s first 6 x 6), without the
    calibration's systematic error."""
    return np.sqrt(np.clip(np.diag(np.asarray(cov, float)[:6, :6]), 0, None))


def _undetermined(a: Assembly, frame_sigma: np.ndarray, extent: np.ndarray, cfg) -> Assembly:
    """`a` with each reading whose own 1-sigma from this frame (`frame_sigma`: the fit's, not the
    calibration's systematic error, which bounds how far a reading may be off, not whether the frame sees
    it) is wider than the whole range its calibration spans (-`extent` to +`extent`) left unread (NaN) and
    named in the note: the frame cannot tell it from any value of that range, and its number would only
    echo what the fit's other terms left over (an image-side telecentric main lens keeps the sub-image
    pitch the lens pitch at any MLA-sensor distance: the analytic microscope frame read a healthy array's
    distance as -903 µm, its fit's 1-sigma 139 µm, against +-40 calibrated)."""
    own = dict(zip(FIELDS, (float(v) for v in frame_sigma)))
    loose = [k for k, lim in zip(FIELDS, extent) if not own[k] <= 2.0 * lim]
    if not loose:
        return a
    from mlaqc.optics.datasheet import telecentric

    words = ", ".join(f"{k} (the frame's 1σ {own[k]:.3g} {UNITS[k]} against {-lim:g} to {lim:g})"
                      for k, lim in zip(FIELDS, extent) if k in loose)
    why = (": an image-side telecentric main lens keeps the sub-image pitch at the lens pitch whatever the gap"
           if cfg.main_lens.ideal and telecentric(cfg.main_lens.exit_pupil_mm)
           and "mla_sensor_distance_um" in loose else "")
    nan = float("nan")
    note = "; ".join(p for p in (a.note, f"not determined by this frame, its 1σ wider than the whole calibrated "
                                          f"range: {words}{why}") if p)
    return dataclasses.replace(a, values={k: nan if k in loose else v for k, v in a.values.items()},
                               sigma={k: nan if k in loose else v for k, v in a.sigma.items()}, note=note)


def _uncalibrated(model, raw: np.ndarray, cov: np.ndarray, used: int, rms: float) -> Assembly:
    """Readings beyond what the calibration rendered (or that its model cannot reach): the projection
    fit's own, its zero point taken off, with UNCALIBRATED of each value in the sigma (on Table 1 the fit
    reads a tilt 4 % large and the distance's slope is 0.9-1.08) and the validation frames' error."""
    values = raw[:6] - np.asarray(model.zero[:6], float)
    sig = np.sqrt(np.clip(np.diag(cov[:6, :6]), 0, None) + np.square(UNCALIBRATED * values)
                  + np.square(model.systematic))
    extent = ", ".join(f"{k} ±{v:g}" for k, v in zip(FIELDS, model.extent()))
    return Assembly(dict(zip(FIELDS, map(float, values))), dict(zip(FIELDS, map(float, sig))), lenses_used=used,
                    rms_residual_px=rms, note=f"beyond the calibrated range ({extent}): the projection fit's own "
                                              f"readings, good to about {UNCALIBRATED:.0%}")
