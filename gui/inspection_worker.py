"""The inspection job and the display view it prepares, off the GUI thread (threading model: gui.workers).

`InspectionWorker` (the ``inspection`` thread) loads, calibrates and inspects in stages a `CancelToken` can
stop between, reads the through-focus pinhole frames on the result's grid when there are some, and hands
back an `InspectionView`: the result plus everything the display needs (levels, defect rings, a k-d tree
of lens centres, a hex grid's cells), so the GUI thread only draws. `FrameWorker` (the ``frames`` thread)
checks the through-focus frames the operator picks and loads one for display, with the same checks
(`describe_through_focus`) and display levels (`spot_levels`). Kept apart from gui.workers' device workers:
this is the part of the app that runs mlaqc.inspection.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
import numpy as np
from PySide6.QtCore import QObject, Signal, Slot

from gui.workers import one_sentence
from mlaqc.errors import InputError


class CancelToken:
    """Set by the GUI, read by a worker between stages."""

    def __init__(self) -> None:
        self._event = threading.Event()

    def cancel(self) -> None:
        self._event.set()

    @property
    def cancelled(self) -> bool:
        return self._event.is_set()


class Cancelled(Exception):
    """Internal: the job was cancelled between two stages."""


@dataclass
class InspectionRequest:
    """What to inspect: a raw file or an in-memory frame (`Grab`-like), optionally a white file."""

    cfg: Any  # mlaqc.optics.config.CameraConfig
    raw: str | None = None
    frame: Any = None  # drivers.camera.Frame
    white: str | None = None
    token: CancelToken = field(default_factory=CancelToken)
    through_focus: tuple[str, ...] = ()  # pinhole frame files (+u / -u pairs), read after the white inspection
    darks: tuple[str, ...] = ()  # dark frame files: their master dark is subtracted from the image and the white


@dataclass(frozen=True)
class TfFrame:
    """One through-focus pinhole frame as the app lists it: its file and how it was taken."""

    path: str
    u_mm: float  # focus offset: the pinholes' image this far behind (+) / in front of (-) the MLA
    offset: tuple[int, int]  # pinhole lattice offset, in lens pitches
    f_number: float
    spacing: int

    @property
    def name(self) -> str:
        return Path(self.path).name

    @property
    def label(self) -> str:
        return f"{self.name} · u = {self.u_mm:+g} mm · offset ({self.offset[0]}, {self.offset[1]})"


def describe_through_focus(paths: Any, cfg: Any, *, check_size: bool = True) -> tuple[TfFrame, ...]:
    """Read each pinhole frame's record (its `.sim.json` / `.meta.json` sidecar) and check the set: one
    series (same f-number and pinhole spacing), every frame once, every +u frame with its -u partner at the
    same offset, and (with `check_size`) every file of the config's sensor size. Returns the frames sorted
    pair by pair (+u first); InputError with one sentence naming the file otherwise."""
    from mlaqc.inspection.pinhole_frames import frame_record
    from mlaqc.inspection.rawio import load_raw

    paths = [str(p) for p in paths]
    if not paths:
        return ()
    s = cfg.sensor
    frames = []
    for path in paths:
        rec = frame_record(path)
        if check_size:
            load_raw(path, expected_shape=(s.height_px, s.width_px))
        frames.append(TfFrame(path, float(rec.focus_offset_mm), (int(rec.offset_lenses[0]), int(rec.offset_lenses[1])),
                              float(rec.f_number), int(rec.spacing_lenses)))
    first = frames[0]
    for f in frames[1:]:
        if (f.f_number, f.spacing) != (first.f_number, first.spacing):
            raise InputError(f"through-focus frame {f.name} was taken at f/{f.f_number:g} with pinholes {f.spacing} "
                             f"lenses apart but {first.name} at f/{first.f_number:g} and {first.spacing}: choose the "
                             "frames of one series")
    slots: dict[tuple[float, tuple[int, int]], dict[int, TfFrame]] = {}
    for f in frames:
        slot = slots.setdefault((abs(f.u_mm), f.offset), {})
        sign = 1 if f.u_mm > 0 else -1
        if sign in slot:
            raise InputError(f"through-focus frames {slot[sign].name} and {f.name} are both u = {f.u_mm:+g} mm at "
                             f"offset {f.offset}: choose each frame once")
        slot[sign] = f
    for (_u, off), slot in slots.items():
        if len(slot) != 2:
            f = next(iter(slot.values()))
            raise InputError(f"through-focus frame {f.name} (u = {f.u_mm:+g} mm, offset {off}) has no partner at "
                             f"u = {-f.u_mm:+g} mm with the same pinhole offset: choose both frames of each pair")
    return tuple(slot[sign] for _, slot in sorted(slots.items()) for sign in (1, -1))


def through_focus_label(frames: tuple[TfFrame, ...]) -> str:
    """'32 frames: 16 +u / −u pairs at u = ±5 mm' (the inspection panel's line; the shipped protocol's set)."""
    if not frames:
        return "none"
    us = ", ".join(f"±{u:g}" for u in sorted({abs(f.u_mm) for f in frames}))
    n = len(frames)
    return f"{n} frames: {n // 2} +u / −u pair{'s' if n // 2 != 1 else ''} at u = {us} mm"


def spot_levels(img: np.ndarray) -> tuple[float, float]:
    """Display levels of a pinhole frame (mostly dark, a few bright spots): from the background to near
    the brightest spots, so both the spots and their spread show."""
    step = max(1, int(math.sqrt(img.size / 1_000_000)))
    s = np.asarray(img[::step, ::step], np.float32)
    s = s[np.isfinite(s)]
    if not s.size:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(s, [1.0, 99.97]))
    if not hi > lo:
        hi = float(s.max()) if s.max() > lo else lo + 1.0
    return lo, hi


@dataclass
class Ring:
    """One defect mark for the overlay."""

    m: int
    n: int
    x: float
    y: float
    error_type: str
    out_of_tolerance: bool
    missing: bool
    tick: tuple[float, float] | None  # end of the direction tick


@dataclass
class InspectionView:
    """An inspection result plus everything the GUI needs to draw it without computing."""

    result: Any  # mlaqc.inspection.results.InspectionResult
    cfg: Any
    source: str
    levels: tuple[float, float]
    centres_x: np.ndarray  # (rows, cols): measured centre, grid centre where not found
    centres_y: np.ndarray
    grid_x: np.ndarray  # finite grid centres (1-D) for the grid overlay
    grid_y: np.ndarray
    pitch_px: float
    rings: list[Ring]
    medians: dict[str, float]
    summary: str
    headline: str
    detail: str
    elapsed_s: float
    _tree: Any = None
    _tree_index: np.ndarray | None = None
    frames: tuple[TfFrame, ...] = ()  # the through-focus frames read into `result` (frame selector order)
    sources: dict[tuple[int, int], str] = field(default_factory=dict)  # lens -> which measurement flagged/read it
    packing: str = "square"  # the grid's lattice (mlaqc.optics.lattice)
    # hex: the affine map lattice units -> pixels fitted to the grid's centres (None: too few lenses), a
    # cell's corner offsets (6, 2) px from its centre, and every cell's outline (x, y; NaN between cells)
    affine: np.ndarray | None = None
    cell_px: np.ndarray | None = None
    cells_x: np.ndarray | None = None
    cells_y: np.ndarray | None = None
    aperture_px: float | None = None  # circular lens apertures (mla.aperture = 'circle'): their diameter in px

    @property
    def hex(self) -> bool:
        return self.packing == "hex"

    def lens_at(self, x: float, y: float) -> tuple[int, int] | None:
        """U(m,n) of the lens whose cell holds pixel (x, y): on a hex grid the hexagon of the lattice laid
        on the grid's centres (`Lattice.nearest`), on a square one the nearest centre within its cell."""
        if self.hex and self.affine is not None:
            return self._hex_lens_at(x, y)
        if self._tree is None:
            return None
        dist, i = self._tree.query((x, y))
        reach = 1.0 / math.sqrt(3.0) if self.hex else 0.72  # the cell's circumradius (square: with some slack)
        if not math.isfinite(dist) or dist > reach * self.pitch_px:
            return None
        flat = int(self._tree_index[i])
        cols = self.centres_x.shape[1]
        return flat // cols + 1, flat % cols + 1

    def centre(self, m: int, n: int) -> tuple[float, float]:
        return float(self.centres_x[m - 1, n - 1]), float(self.centres_y[m - 1, n - 1])

    def _hex_lens_at(self, x: float, y: float) -> tuple[int, int] | None:
        from mlaqc.optics.lattice import Lattice
        from mlaqc.report.view import lens_at_px

        g = self.result.grid
        lattice = Lattice("hex", *self.centres_x.shape)
        r, c, inside = lens_at_px(lattice, self.affine, g.grid_x_px, g.grid_y_px, x, y)
        return (int(r) + 1, int(c) + 1) if bool(inside) else None

    def reference_of(self, m: int, n: int) -> np.ndarray:
        ref = np.asarray(self.result.reference)
        return ref if ref.ndim == 2 else ref[m - 1, n - 1]


def frame_to_image(frame: Any, dark: Any = None) -> np.ndarray:
    """A camera Frame as the prepared float32 image the inspection takes (exposure checked); `dark`: a
    master dark (mlaqc.inspection.darks) checked against the frame and subtracted first."""
    from drivers.capture import Grab
    from mlaqc.inspection.pipeline import prepare
    from mlaqc.inspection.raw_levels import check_exposure
    from mlaqc.inspection.rawio import RawFrame

    g = Grab(frame.data, (frame,), "")
    bits = max(8, int(frame.bits))
    raw = RawFrame(frame.data, bits, frame.cfa, g.black_level, max(g.white_level, g.black_level + 1), {},
                   f"frame {frame.sequence}")
    check_exposure(raw)
    if dark is not None:
        from mlaqc.inspection.darks import FrameFacts, correct

        dark.check(FrameFacts.of(raw, exposure_us=getattr(frame, "exposure_us", None), gain=getattr(frame, "gain", None)),
                   "captured frame")
        return correct([raw], dark)
    return prepare(raw)


def defect_sources(result: Any, white_flagged: Any = None) -> dict[tuple[int, int], str]:
    """Which measurement flagged or read each defect, for the table's Source column: 'white', 'white +
    pinholes' (the white frame flagged it, the +u / -u pairs read its focal error), 'pinholes' (only the
    pairs flagged it), 'white (not covered)' (a radius lens no pair lit fully: its sign is the white
    frame's). Empty without through-focus frames. `white_flagged`: the lenses the white frame flagged."""
    from mlaqc.inspection.combine import SOURCE_KEY

    tf = getattr(result, "through_focus", None)
    if tf is None:
        return {}
    covered = np.asarray(tf.covered, bool)
    out = {}
    for d in result.defects:
        lens = (d.m, d.n)
        if SOURCE_KEY in (d.indexes or {}):
            out[lens] = "white + pinholes" if white_flagged is not None and lens in white_flagged else "pinholes"
        elif d.error_type == "radius" and not covered[d.m - 1, d.n - 1]:
            out[lens] = "white (not covered)"
        else:
            out[lens] = "white"
    return out


def through_focus_summary(tf: Any) -> str:
    """One clause on the through-focus reading: lenses covered, pairs, median focal 1-sigma."""
    sm = tf.summary()
    sig = sm.get("focal_sigma_rel_median")
    return (f"through-focus: {sm['lenses_covered']} lenses read ({100 * sm['coverage']:.0f} %) in "
            f"{len(sm['pairs'])} pair{'s' if len(sm['pairs']) != 1 else ''}, focal 1σ "
            f"{'—' if sig is None else f'{100 * sig:.2f} %'}")


def build_view(result: Any, cfg: Any, source: str, elapsed_s: float, *, frames: tuple[TfFrame, ...] = (),
               white_flagged: Any = None) -> InspectionView:
    """Precompute the display data of an inspection (runs in the worker); `frames`: the through-focus
    frames read into it, `white_flagged`: the lenses the white frame flagged before they were combined."""
    from scipy.spatial import cKDTree

    from mlaqc.inspection.results import METRICS, detection_limit_text

    g = result.grid
    mx, my = np.asarray(g.measured_x_px, float), np.asarray(g.measured_y_px, float)
    gx, gy = np.asarray(g.grid_x_px, float), np.asarray(g.grid_y_px, float)
    found = np.isfinite(mx) & np.isfinite(my)
    cx, cy = np.where(found, mx, gx), np.where(found, my, gy)
    ok = np.isfinite(cx) & np.isfinite(cy)
    idx = np.flatnonzero(ok.ravel())
    tree = cKDTree(np.column_stack([cx.ravel()[idx], cy.ravel()[idx]])) if idx.size else None
    pitch = float(np.mean(g.pitch_px)) if np.all(np.isfinite(g.pitch_px)) else 20.0
    cells = hex_overlay(g, gx, gy) if getattr(g, "packing", "square") == "hex" else {}
    if cells.get("affine") is not None:
        pitch = float(np.hypot(*cells["affine"][:, 0]))  # a row's lens spacing (rows are sqrt(3)/2 of it apart)
    img = np.asarray(result.image, np.float32)
    step = max(1, int(math.sqrt(img.size / 250_000)))
    sample = img[::step, ::step]
    sample = sample[np.isfinite(sample)]
    lo, hi = (np.percentile(sample, [0.5, 99.5]) if sample.size else (0.0, 1.0))
    if not hi > lo:
        hi = lo + 1.0
    missing = np.asarray(g.missing, bool)
    rings: list[Ring] = []
    seen = set()
    for d in result.defects:
        x, y = float(cx[d.m - 1, d.n - 1]), float(cy[d.m - 1, d.n - 1])
        seen.add((d.m, d.n))
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        is_missing = d.error_type == "missing" or bool(missing[d.m - 1, d.n - 1])
        tick = None
        if d.direction_deg is not None and math.isfinite(d.direction_deg) and not is_missing:
            a = math.radians(d.direction_deg)
            tick = (x + 0.4 * pitch * math.cos(a), y - 0.4 * pitch * math.sin(a))
        rings.append(Ring(d.m, d.n, x, y, d.error_type, not d.within_tolerance, is_missing, tick))
    for m, n in zip(*np.nonzero(missing)):
        if (m + 1, n + 1) not in seen and math.isfinite(cx[m, n]) and math.isfinite(cy[m, n]):
            rings.append(Ring(int(m) + 1, int(n) + 1, float(cx[m, n]), float(cy[m, n]), "missing", False, True, None))
    medians = {}
    for name in METRICS:
        a = np.asarray(result.metrics[name], float)
        a = a[np.isfinite(a)]
        medians[name] = float(np.median(a)) if a.size else math.nan
    by_type = Counter(d.error_type for d in result.defects)
    out_tol = sum(1 for d in result.defects if not d.within_tolerance)
    kinds = ", ".join(f"{k} {v}" for k, v in sorted(by_type.items())) or "none"
    headline = (f"{len(result.defects)} flagged of {g.rows}×{g.cols} lenses · {out_tol} out of tolerance · "
                f"{g.lenses_missing} missing")
    detail = (f"{kinds}; {detection_limit_text(result.detection_limit)}; grid pitch {g.pitch_px[0]:.3f} × "
              f"{g.pitch_px[1]:.3f} px, rotation {g.rotation_deg:+.3f}°, RMS residual {g.rms_residual_px:.3f} px")
    assembly = getattr(result, "assembly", None)
    if assembly is not None:  # the array's placement; a bound it exceeds is what failed the verdict
        detail += "; " + assembly.summary_line().strip()
        if assembly.exceeded:
            headline += " · assembly out of bounds: " + "; ".join(assembly.exceeded)
    tf = getattr(result, "through_focus", None)
    summary = f"{headline} ({detail}{'; ' + through_focus_summary(tf) if tf is not None else ''})"
    ok_grid = np.isfinite(gx) & np.isfinite(gy)
    return InspectionView(result, cfg, source, (float(lo), float(hi)), cx, cy, gx[ok_grid], gy[ok_grid], pitch, rings,
                          medians, summary, headline, detail, elapsed_s, tree, idx, frames=tuple(frames),
                          sources=defect_sources(result, white_flagged), packing=getattr(g, "packing", "square"),
                          aperture_px=aperture_px(cfg, pitch), **cells)


def aperture_px(cfg: Any, pitch_px: float) -> float | None:
    """Diameter in pixels of the config's circular lens apertures (None for 100 %-fill cells)."""
    mla = getattr(cfg, "mla", None)
    if getattr(mla, "aperture", "cell") != "circle" or not getattr(mla, "aperture_diameter_um", None):
        return None
    return float(mla.aperture_diameter_um) / float(mla.pitch_um) * pitch_px


def hex_overlay(grid: Any, gx: np.ndarray, gy: np.ndarray) -> dict[str, Any]:
    """A hex grid's cells for the overlay (runs in the worker): the lattice's affine fit to the predicted
    centres, one cell's corner offsets and every lens' hexagon as one NaN-separated polyline."""
    from mlaqc.optics.lattice import Lattice
    from mlaqc.report.view import cell_outline_px, lattice_affine

    affine = lattice_affine(Lattice("hex", int(grid.rows), int(grid.cols)), gx, gy)
    if affine is None:
        return {"affine": None}
    corners = cell_outline_px("hex", affine)
    ok = np.isfinite(gx) & np.isfinite(gy)
    ring = np.vstack([corners, corners[:1], [[np.nan, np.nan]]])  # closed hexagon, then a break
    xs = gx[ok][:, None] + ring[None, :, 0]
    ys = gy[ok][:, None] + ring[None, :, 1]
    return {"affine": affine, "cell_px": corners, "cells_x": xs.ravel(), "cells_y": ys.ravel()}


class InspectionWorker(QObject):
    """Calibration + inspection in the ``inspection`` thread, in stages with progress and cancel."""

    progress = Signal(int, int, str)  # job, percent, stage text
    finished = Signal(int, object)  # job, InspectionView
    failed = Signal(int, str)
    cancelled = Signal(int)
    previewReady = Signal(int, object)  # job, raw counts (H, W) for display
    previewFailed = Signal(int, str)

    @Slot(int, str)
    def preview(self, job: int, path: str) -> None:
        """Load a raw file for display only (its counts, as stored)."""
        try:
            from mlaqc.inspection.rawio import load_raw

            frame = load_raw(path)
        except Exception as exc:  # noqa: BLE001
            self.previewFailed.emit(job, one_sentence(exc))
            return
        self.previewReady.emit(job, frame.data)

    @Slot(int, object)
    def run(self, job: int, req: InspectionRequest) -> None:
        t0 = time.perf_counter()
        token = req.token

        def stage(pct: int, text: str) -> None:
            if token.cancelled:
                raise Cancelled()
            self.progress.emit(job, pct, text)

        try:
            from mlaqc.inspection.array_extent import calibrate_whole
            from mlaqc.inspection.pipeline import inspect_image, load_frame

            cfg = req.cfg
            dark, info, notes = None, None, []
            if req.darks:
                from mlaqc.inspection.darks import load_frames, master_dark_cached, noise_info, noise_notes, with_noise
                from mlaqc.inspection.raw_levels import Levels

                stage(3, "building the master dark")
                s = cfg.sensor
                dark = master_dark_cached(tuple(req.darks), sensor=Levels(s.bit_depth, s.black_level_dn),
                                          pitch_px=cfg.layout.subimage_pitch_px, expected_shape=(s.height_px, s.width_px))
            stage(5, "loading the image")
            if req.frame is not None:
                img = frame_to_image(req.frame, dark)
                source = f"captured frame #{req.frame.sequence}"
                if dark is not None:
                    info = noise_info(1, dark)
                    notes = noise_notes(info)
            elif req.raw and dark is not None:
                img, info = load_frames([req.raw], cfg, None, notes, dark)
                source = str(req.raw)
            elif req.raw:
                img = load_frame(req.raw, cfg)
                source = str(req.raw)
            else:
                raise InputError("there is nothing to inspect: open a raw file or capture a frame first")
            s = cfg.sensor
            if img.shape != (s.height_px, s.width_px):
                raise InputError(f"the image is {img.shape[1]}x{img.shape[0]} px but the camera config's sensor is "
                                 f"{s.width_px}x{s.height_px} px; choose the matching camera config")
            white = img
            if req.white:
                stage(15, "loading the white image")
                white = load_frame(req.white, cfg, dark=dark)
            stage(25, "calibrating the microlens grid")
            grid = calibrate_whole(white, cfg)
            stage(60, "measuring and identifying every lens")
            result = inspect_image(img, cfg, grid=grid, source=source, notes=tuple(notes))
            if info is not None:
                with_noise(result, info)
            frames: tuple[TfFrame, ...] = ()
            white_flagged = None
            if req.through_focus:
                frames = describe_through_focus(req.through_focus, cfg, check_size=False)
                white_flagged = {(d.m, d.n) for d in result.defects}
                result = self._through_focus(result, frames, cfg, stage)
            stage(90, "preparing the view")
            view = build_view(result, cfg, source, time.perf_counter() - t0, frames=frames,
                              white_flagged=white_flagged)
            stage(100, "done")
        except Cancelled:
            self.cancelled.emit(job)
            return
        except Exception as exc:  # noqa: BLE001
            self.failed.emit(job, one_sentence(exc))
            return
        if token.cancelled:
            self.cancelled.emit(job)
        else:
            self.finished.emit(job, view)

    @staticmethod
    def _through_focus(result: Any, frames: tuple[TfFrame, ...], cfg: Any, stage: Any) -> Any:
        """The second measurement: load the pinhole frames (cancellable between frames), read every
        covered lens' focal error and optical centre on `result`'s grid, and combine (as
        `pipeline.with_through_focus`, in stages)."""
        from mlaqc.inspection.array_extent import through_focus_config
        from mlaqc.inspection.combine import combine_through_focus
        from mlaqc.inspection.pinhole_frames import load_pinhole_frames
        from mlaqc.inspection.throughfocus import measure_through_focus

        cfg = through_focus_config(cfg, result.grid)  # an "auto" frame that held the whole array: its counts
        t0 = time.perf_counter()
        loaded = []
        for k, f in enumerate(frames):
            stage(62 + (14 * k) // len(frames), f"reading through-focus frames ({k + 1} of {len(frames)})")
            loaded += load_pinhole_frames([f.path], cfg)
        t1 = time.perf_counter()
        stage(78, "reading through-focus frames: the focal length of every lens")
        tf = measure_through_focus(loaded, result.grid, cfg)
        stage(88, "combining the white and the through-focus readings")
        out = combine_through_focus(result, tf, cfg.qc)
        out.timings_s["load_through_focus"] = round(t1 - t0, 4)
        out.timings_s["through_focus"] = round(time.perf_counter() - t1, 4)
        return out


# ============================================================================================ frames


class FrameWorker(QObject):
    """The ``frames`` thread: checks the through-focus frames the operator picks and loads one for display."""

    described = Signal(int, object)  # job, tuple[TfFrame, ...]
    describeFailed = Signal(int, str)
    frameReady = Signal(int, str, object, object)  # job, path, prepared image (H, W) float32, (lo, hi) levels
    frameFailed = Signal(int, str)

    @Slot(int, object, object)
    def describe(self, job: int, paths: Any, cfg: Any) -> None:
        try:
            frames = describe_through_focus(paths, cfg)
        except Exception as exc:  # noqa: BLE001 - every failure becomes one sentence in the panel
            self.describeFailed.emit(job, one_sentence(exc))
            return
        self.described.emit(job, frames)

    @Slot(int, str, object)
    def loadFrame(self, job: int, path: str, cfg: Any) -> None:
        """A pinhole frame as the analysis sees it (black-subtracted, normalized), with display levels."""
        try:
            from mlaqc.inspection.pinhole_frames import load_pinhole_frames

            img = load_pinhole_frames([path], cfg)[0][0].image()
            levels = spot_levels(img)
        except Exception as exc:  # noqa: BLE001
            self.frameFailed.emit(job, one_sentence(exc))
            return
        self.frameReady.emit(job, path, img, levels)
