"""The inspection pipeline: raw frame -> calibration (grid) -> sub-images -> indexes -> identification
-> verdict. Each stage is a plain function over arrays; `inspect_image` composes them and times them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from mlaqc.compiled import net_clock
from mlaqc.errors import InputError
from mlaqc.inspection.array_extent import (calibrate_whole, config_for_grid, locate_array, partial_array_note,
                                           seen_edges, through_focus_config, whole_array_note, with_counts)
from mlaqc.inspection.assembly import measure_assembly, not_read
from mlaqc.inspection.calibrate import Grid, calibrate_for
from mlaqc.inspection.combine import SOURCE_KEY
from mlaqc.inspection.combine import verdict as overall_verdict
from mlaqc.inspection.flatfield import check_flat_field
from mlaqc.inspection.identify import identify
from mlaqc.inspection.measure import measure_lenses
from mlaqc.inspection.metrics import compute_metrics, reference_images
from mlaqc.inspection.obscuration import obscuration_readings, retype
from mlaqc.inspection.scratches import is_line, next_to_lines, scratch_notes
from mlaqc.inspection.optics_check import anchoring_notes, pitch_notes
from mlaqc.inspection.raw_levels import (Levels, check_exposure, levels_note, normalized, resolve_levels,
                                         suppress_hot_pixels)
from mlaqc.inspection.rawio import RawFrame, load_raw
from mlaqc.inspection.results import InspectionResult, LazyReferences
from mlaqc.inspection.subimages import divide
from mlaqc.models.position_split import position_split
from mlaqc.models.reference import ReferenceModel, config_key, reference_model
from mlaqc.models.signatures import (SignatureSet, SignatureTable, signature_key, signature_table, um_per_px_at_mla,
                                     window_half_px)
from mlaqc.optics.config import CameraConfig


def prepare(frame: RawFrame) -> np.ndarray:
    """Black-subtracted, normalized float32 image with hot pixels suppressed (per CFA channel)."""
    img = normalized(frame)  # a fresh float32 array this function owns: clean it in place
    cleaned, _ = suppress_hot_pixels(img, frame.cfa, inplace=True)
    return cleaned.astype(np.float32, copy=False)


def load_frame(path: str | Path | Sequence[str | Path], cfg: CameraConfig, levels: Levels | None = None,
               notes: list[str] | None = None, dark=None) -> np.ndarray:
    """Load a raw file of the config's sensor size, settle its levels (`resolve_levels`: `levels` stated
    by the user, else the file's, else the config's sensor or the data), check its exposure, and prepare
    it. `notes` gets a sentence when the levels did not come from the file itself. Several paths (frames
    of one state) are averaged into one, and a master dark (`darks.MasterDark`) is subtracted first
    (`darks.load_frames`)."""
    if dark is not None or not isinstance(path, (str, Path)):
        from mlaqc.inspection.darks import load_frames

        return load_frames(path, cfg, levels, notes, dark)[0]
    s = cfg.sensor
    frame = resolve_levels(load_raw(path, expected_shape=(s.height_px, s.width_px)), levels,
                           Levels(s.bit_depth, s.black_level_dn))
    if notes is not None and frame.levels_from != "file":
        notes.append(levels_note(frame))
    check_exposure(frame)
    return prepare(frame)


SAG = "sag-intersection"


def inspect_image(img: np.ndarray, cfg: CameraConfig, *, grid: Grid | None = None, source: str = "",
                  model: ReferenceModel | None = None, table: SignatureTable | SignatureSet | None = None,
                  notes: tuple[str, ...] = ()) -> InspectionResult:
    """Inspect one prepared frame; `grid` from a white image (else the frame calibrates itself); a
    SignatureSet is matched to the rim width the grid measured.

    With `mla.boundaries = "grid"` a shifted lens is reported as 'position'. If the frame has such lenses
    it is inspected again with sag-intersection boundaries, and where that types any of them a decenter
    (its neighbours' sub-images tilt towards it: a boundary moved, which cannot happen with grid
    apertures, where no neighbour sees a pitch error or a decenter; noise alone does it to a
    'position' lens with a probability under 1e-4) the frame is a replicated array's: that inspection
    is the result, with a note saying so (`lens_boundaries` says which model was used)."""
    result = _inspect_image(img, cfg, grid=grid, source=source, model=model, table=table, notes=notes)
    if cfg.mla.boundaries != "grid" or not any(d.error_type == "position" for d in result.defects):
        return result
    sag_cfg = replace(cfg, mla=replace(cfg.mla, boundaries=SAG))
    alt = _inspect_image(img, sag_cfg, grid=grid, source=source, model=model, notes=notes)
    decentered = sum(d.error_type == "decenter" for d in alt.defects)
    if not decentered:
        return result
    note = (f"The config says grid lens boundaries, but this frame is a replicated (sag-intersection) array's: "
            f"{decentered} shifted lens(es) tilt their neighbours' sub-images as only a moved lens boundary "
            f"does. Inspected with mla.boundaries = \"{SAG}\" (pitch and decenter told apart); set it in the config.")
    alt_timings = {k: round(v + result.timings_s.get(k, 0.0), 4) for k, v in alt.timings_s.items()}
    return replace(alt, notes=alt.notes + (note,), timings_s=alt_timings)


def _inspect_image(img: np.ndarray, cfg: CameraConfig, *, grid: Grid | None = None, source: str = "",
                   model: ReferenceModel | None = None, table: SignatureTable | SignatureSet | None = None,
                   notes: tuple[str, ...] = (), counted: bool = False) -> InspectionResult:
    """`inspect_image` with the config's boundary model as given (`counted`: `cfg`'s counts are those an
    "auto" frame found, mlaqc.inspection.array_extent)."""
    t: dict[str, float] = {}
    clock = net_clock()  # a first-use kernel compile is not the stage's time (commands report it apart)

    def lap(name: str) -> None:
        nonlocal clock
        now = net_clock()
        t[name] = round(max(now - clock, 0.0), 4)
        clock = now

    if img.shape != (cfg.sensor.height_px, cfg.sensor.width_px):
        raise InputError(f"image is {img.shape[1]}x{img.shape[0]} px but the camera's sensor is "
                         f"{cfg.sensor.width_px}x{cfg.sensor.height_px}")
    auto_grid, lattice_cfg = None, cfg  # (an "auto" frame's models are the sensor-wide lattice's)
    if grid is not None and (of_grid := config_for_grid(cfg, grid)) is not cfg:  # a white frame located the array
        counted = not of_grid.mla.counts_auto
        cfg, notes = of_grid, tuple(notes) + ((whole_array_note(*grid.shape, from_grid=True),) if counted else ())
    if grid is None and cfg.mla.counts_auto:
        auto_grid, cfg, counts = locate_array(img, cfg)
        lap("calibrate")
        if counts is not None:  # "auto" on a frame that holds the whole array: inspected as that array
            whole = _inspect_image(img, with_counts(cfg, *counts), source=source,
                                   notes=tuple(notes) + (whole_array_note(*counts),), counted=True)
            whole.timings_s["calibrate"] = round(whole.timings_s.get("calibrate", 0.0) + t["calibrate"], 4)
            return whole
    if model is None or table is None:
        cached_model, cached_table = _models(lattice_cfg if cfg.mla.counts_auto else cfg)
        model, table = model or cached_model, table or cached_table
    lap("models")
    own_grid = grid is None
    if not own_grid and grid.packing != cfg.mla.packing:
        raise InputError(f"the grid is for a {grid.packing} lattice but the camera's MLA is "
                         f"{cfg.mla.packing} (mla.packing)")
    if own_grid and auto_grid is None:
        grid = calibrate_for(img, cfg)
        lap("calibrate")
    elif own_grid:
        grid = auto_grid
    found = seen_edges(grid) if cfg.mla.counts_auto and cfg is not lattice_cfg else None  # a cut lattice's edges
    edges = found[1] if found is not None else ()
    notes = (tuple(notes) + pitch_notes(float(np.mean(grid.pitch_px)), cfg)
             + ((partial_array_note(edges),) if edges else anchoring_notes(cfg)))
    half = window_half_px(cfg)
    subs = divide(img, grid, 2 * half + 1)
    sub, cx, cy = subs.data, subs.centre_x_px, subs.centre_y_px
    lap("divide")
    metrics = compute_metrics(sub, cx, cy, model, um_per_px_at_mla=um_per_px_at_mla(cfg))
    lap("indexes")
    # A grid fitted on this very frame measured every lens' position with its joint disc fit. Averaged
    # with the registration offset it is the lowest-noise shift signal (0.0197 px per axis at 50 rays/pixel
    # vs 0.023 px registered alone), and an outlier of either method is halved (the fit alone has a tail).
    position = None
    if own_grid:
        position = (0.5 * (grid.residual_x_px + metrics["offset_x_px"]), 0.5 * (grid.residual_y_px + metrics["offset_y_px"]))
    if isinstance(table, SignatureSet):
        table = table.matched(float(getattr(grid, "edge_width_px", np.nan)))
    phase = (np.mod(grid.grid_x_px, 1.0), np.mod(grid.grid_y_px, 1.0))
    # not inspected: a lens whose rim leaves the frame (the grid's clipped), and one whose index window does:
    # its indexes are read from part of the window (the rim's tail and the neighbours' light off the frame
    # are lost), biased against every other lens', and as a baseline neighbour they bias the next lenses'
    clipped = np.asarray(grid.clipped, bool) | ~subs.valid.all(axis=(-2, -1))
    check_flat_field(np.where(clipped | grid.missing, np.nan, metrics["flux"]),
                     f"frame {source}" if source else "the frame")
    found = identify(metrics, grid.missing | ~np.isfinite(metrics["flux"]), cfg.qc, table, position, phase,
                     outside=clipped, split=position_split(cfg), packing=cfg.mla.packing, aperture=cfg.mla.aperture)
    # dark spots and lines read against the frame's typical sub-image, at each lens' registered centre
    at_x, at_y = cx + metrics["offset_x_px"], cy + metrics["offset_y_px"]  # window pixels
    centres = (grid.grid_x_px + metrics["offset_x_px"], grid.grid_y_px + metrics["offset_y_px"])  # frame pixels
    significant = _significant(found, cfg.qc, clipped)
    spots = obscuration_readings(sub, at_x, at_y, significant, significant & ~grid.missing)
    found = retype(found, spots, cfg.qc, metrics, centres, significant)
    found = _lines_followed(found, sub, at_x, at_y, clipped, grid.missing, cfg.qc, metrics, centres)
    defects, flagged, error_type = found.defects, found.flagged, found.error_type
    notes = notes + scratch_notes(defects) + corner_notes(found.corners_not_judged)
    lap("identify")
    measured = measure_lenses(found, table, cfg, (grid.residual_x_px, grid.residual_y_px) if own_grid else None)
    lap("measure")
    qc = cfg.qc
    assembly = measure_assembly(grid, cfg)
    if counted and assembly.reason.startswith("no assembly calibration"):  # `mlaqc models` on "auto" would not
        assembly = not_read(f"no assembly calibration for this array's counts: give count_w = {grid.cols} and "
                            f"count_h = {grid.rows} in the config and run `mlaqc models --config CONFIG` once")
    assembly = assembly.checked(qc)
    lap("assembly")
    verdict = overall_verdict(defects, qc, assembly)
    # every lens' reference is for the report, which shows a few: computed when (and as far as) it is read
    side = 2 * half + 1
    ref = LazyReferences(lambda x, y: reference_images(model, x, y, side, side), cx, cy, (side, side))
    # the frame is kept as given when already float32 (no 16 MB copy): callers hand over a prepared frame
    return InspectionResult(verdict, grid, metrics, defects, flagged, error_type, np.asarray(img, dtype=np.float32),
                            sub, ref, source, _tolerance_dict(cfg), t,
                            notes=tuple(notes), detection_limit=found.detection_limit,
                            below_reportable=found.below_reportable, not_inspected=found.not_inspected,
                            measurements=measured, assembly=assembly, lens_boundaries=cfg.mla.boundaries)


def corner_notes(corners: int) -> tuple[str, ...]:
    """What the report says about the array's corner lenses on the frame (not judged)."""
    if not corners:
        return ()
    lenses = "lenses are" if corners > 1 else "lens is"
    return (f"the array's {corners} corner {lenses} not judged: a corner is the outermost lens of two edge lines, "
            "no other lens shares its neighbourhood to compare it with (a missing one is still found)",)


def _significant(found, qc, clipped: np.ndarray) -> np.ndarray:
    """The lenses a spot reading may name and leaves out of the typical sub-image: flagged, below the
    reportable size, or taken for a flagged neighbour's echo (over the threshold), the clipped ones not."""
    return found.flagged | found.unreported | ((found.score > qc.detect_sigma) & ~clipped)


def _lines_followed(found, sub, cx, cy, clipped, missing, qc, metrics, centres):
    """`found` with a scratch followed into the neighbours it runs on through: those whose own reading is a
    line too (mlaqc.inspection.scratches.next_to_lines), until no new lens joins."""
    for _ in range(4):  # a line crosses a few sub-images; each pass reaches one lens farther
        nearby = next_to_lines(found.defects, found.flagged.shape) & ~found.flagged & ~clipped & ~missing
        if not nearby.any():
            return found
        significant = _significant(found, qc, clipped)
        lines = {k: r for k, r in obscuration_readings(sub, cx, cy, significant, nearby).items() if is_line(r)}
        if not lines:
            return found
        found = retype(found, lines, qc, metrics, centres, nearby)
    return found


_MODELS: dict[tuple[str, str], tuple[ReferenceModel, SignatureSet]] = {}


def _models(cfg: CameraConfig) -> tuple[ReferenceModel, SignatureSet]:
    """Reference model and signature table of `cfg`'s optics, kept in memory by their content keys: a
    scan or a batch inspects many frames, and reloading them (plus rebuilding the model's derived
    tables) cost 5 ms a frame."""
    key = (config_key(cfg), signature_key(cfg))
    hit = _MODELS.get(key)
    if hit is None:
        hit = (reference_model(cfg), signature_table(cfg))
        if len(_MODELS) >= 4:
            _MODELS.pop(next(iter(_MODELS)))
        _MODELS[key] = hit
    return hit


def _tolerance_dict(cfg: CameraConfig) -> dict[str, float]:
    q = cfg.qc
    return {"pitch_um": q.pitch_um, "decenter_um": q.decenter_um, "radius_rel": q.radius_rel, "tilt_deg": q.tilt_deg,
            "thickness_um": q.thickness_um, "detect_sigma": q.detect_sigma, "report_fraction": q.report_fraction,
            "max_out_of_tolerance": q.max_out_of_tolerance, "max_missing": q.max_missing}


def inspect_file(raw: str | Path | Sequence[str | Path], cfg: CameraConfig, *,
                 white: str | Path | Sequence[str | Path] | None = None, levels: Levels | None = None,
                 through_focus: Sequence[str | Path] = (), dark=None) -> InspectionResult:
    """Load, calibrate (on `white` if given) and inspect a raw file; `levels` as in `load_frame`.
    `through_focus`: pinhole frames of the same array (mlaqc.inspection.pinhole_frames), read on the
    inspected frame's grid and combined with it (mlaqc.inspection.combine). `raw` and `white` may each be
    several frames of one state (averaged into one); `dark`: a master dark (mlaqc.inspection.darks)
    subtracted from every frame first."""
    t0 = net_clock()
    notes: list[str] = []
    info = None
    if dark is not None or not isinstance(raw, (str, Path)):
        from mlaqc.inspection.darks import load_frames

        img, info = load_frames(raw, cfg, levels, notes, dark)
    else:
        img = load_frame(raw, cfg, levels, notes)
    grid = None
    if white is not None:
        wimg = load_frame(white, cfg, levels, dark=dark)
        grid = calibrate_whole(wimg, cfg)
    load_s = max(net_clock() - t0, 0.0)
    source = raw if isinstance(raw, (str, Path)) else list(raw)[0]
    result = inspect_image(img, cfg, grid=grid, source=str(source), notes=tuple(notes))
    result.timings_s["load"] = round(load_s, 4)
    if info is not None:
        from mlaqc.inspection.darks import with_noise

        with_noise(result, info)
    if through_focus:
        result = with_through_focus(result, through_focus, cfg, levels)
    return result


def with_through_focus(result: InspectionResult, paths: Sequence[str | Path], cfg: CameraConfig,
                       levels: Levels | None = None) -> InspectionResult:
    """`result` with the through-focus pinhole frames at `paths` read on its grid and combined into it."""
    from mlaqc.inspection.combine import combine_through_focus
    from mlaqc.inspection.pinhole_frames import load_pinhole_frames
    from mlaqc.inspection.throughfocus import measure_through_focus

    cfg = through_focus_config(cfg, result.grid)  # an "auto" frame that held the whole array: read with its counts
    t0 = net_clock()
    frames = load_pinhole_frames(paths, cfg, levels)
    t1 = net_clock()
    tf = measure_through_focus(frames, result.grid, cfg)
    out = combine_through_focus(result, tf, cfg.qc)
    out.timings_s["load_through_focus"] = round(max(t1 - t0, 0.0), 4)
    out.timings_s["through_focus"] = round(max(net_clock() - t1, 0.0), 4)
    return out


def scan_frame_hook(frame) -> dict:
    """`mlaqc scan --inspect`: inspect a white frame as soon as its position is recorded.

    `frame` is a drivers.scan.ScanFrame (duck-typed here: the core never imports drivers). Its
    `through_focus` lists the pinhole frames recorded at the same position (a plan with a [through_focus]
    step); they are read on this frame's grid and combined with it, as `mlaqc inspect RAW --through-focus
    FRAME ...` does (`with_through_focus`), so the verdict is the combined one (each frame's record is in
    its scan sidecar, `pinhole_frames.frame_record`). The camera config comes from the manifest header:
    the camera's own when it reports one (the mock does), else the one the through-focus step used, else
    the default. Dark frames in the scan folder (`darks.scan_dark_frames`) are subtracted (their master
    built once). Returns a summary the scan writes beside the raw as `<raw>.inspect.json`; with pinhole
    frames it has `through_focus`: their names and the pairs' summary (as report.json's); `lattice`: the
    lattice U(m,n) indexes, with its convention; `config`: the camera config it was inspected with."""
    from mlaqc.optics.config import config_from_dict, default_config

    header = frame.header
    cfg_dict = (header.get("camera_settings") or {}).get("config") or (header.get("through_focus") or {}).get("config")
    cfg = config_from_dict(cfg_dict, source="scan manifest") if cfg_dict else default_config()
    pinholes = tuple(Path(p) for p in getattr(frame, "through_focus", ()) or ())
    from mlaqc.inspection.darks import master_dark_cached, scan_dark_frames

    dark_paths = scan_dark_frames(Path(frame.path).parent)  # dark frames captured into the scan folder
    s = cfg.sensor
    dark = master_dark_cached(dark_paths, sensor=Levels(s.bit_depth, s.black_level_dn),
                              pitch_px=cfg.layout.subimage_pitch_px,
                              expected_shape=(s.height_px, s.width_px)) if dark_paths else None
    result = inspect_file(frame.path, cfg, through_focus=pinholes, dark=dark)
    out = {"verdict": result.verdict, "flagged": len(result.defects), "detection_limit": result.detection_limit,
           "defects": [d.to_json_dict() | {"indexes": None} | _pairs_z(d.indexes.get(SOURCE_KEY))
                       for d in result.defects],
           "grid": {"pitch_px": list(result.grid.pitch_px), "rotation_deg": result.grid.rotation_deg,
                    "rms_residual_px": result.grid.rms_residual_px},
           "lattice": result.lattice_facts(),
           "assembly": _plain(result.assembly.to_json_dict()) if result.assembly is not None else None,
           "timings_s": result.timings_s, "config": cfg.to_dict(), "source": str(frame.path)}
    tf = getattr(result, "through_focus", None)
    if tf is not None:
        read = sum(1 for d in result.defects if SOURCE_KEY in d.indexes)
        out["through_focus"] = {"frames": [Path(p).name for p in pinholes],
                                "summary": _plain(tf.summary() | {"flags_read_by_pairs": read})}
    return out


def _pairs_z(z: float | None) -> dict:
    """A flagged lens the through-focus pairs read: their significance (`through_focus_z`)."""
    return {} if z is None else {SOURCE_KEY: _plain(float(z))}


def _plain(value):
    """JSON-safe: numpy scalars to Python numbers, NaN/inf to None, tuples to lists."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
