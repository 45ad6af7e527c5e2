"""Workers of the QC app: every device and every long job runs off the GUI thread.

Threads (one QThread each, the worker QObject moved into it):

- ``camera``: `CameraWorker` owns the camera. Opens, closes, reconnects it, reads back and applies
  exposure/gain/format, captures single frames, and runs live view as a zero-interval QTimer in its own
  thread, so a stop or a settings change is handled between two frames. Live frames go through a
  `FrameMailbox` (the newest frame wins): the worker only signals when the GUI has taken the previous
  frame, so a slow display drops frames instead of queueing them without bound.
- ``stage``: `StageWorker` owns the stage's commands (connect, home, move, go-to). Commands block in that
  thread only. An idle poll reads the position back now and then, so a pulled cable is noticed.
- ``stage-control``: `StageControl` never runs a blocking command. It calls `stage.stop()` (documented
  as safe from any thread: an out-of-band halt) the moment STOP is pressed even while the stage thread
  is blocked in a move, and it publishes `last_position` (no I/O) at 20 Hz for the live display.
- ``inspection``: `InspectionWorker` loads, calibrates and inspects, then precomputes everything the
  display needs (levels, ring positions, a k-d tree of lens centres) so the GUI thread only draws.
  With through-focus frames it then reads them on the result's grid (mlaqc.inspection.throughfocus) and
  combines both measurements (mlaqc.inspection.combine).
  Cancel is a `CancelToken` checked between stages; a cancelled job's result is never shown.
- ``frames``: `FrameWorker` checks the through-focus pinhole frames the operator picks (their records,
  sizes and +u / -u pairs) and loads one of them for display when the frame selector asks, so neither
  waits for a running inspection nor blocks the GUI.
- ``io``: `IoWorker` writes report sets (`mlaqc.report.write_report`) and saves frames; on close the
  app waits for it, so a report is never left half written.
- ``scan``: `ScanWorker` runs `drivers.scan.ScanRunner` with the devices the app already has open (the
  device panels are locked meanwhile, STOP excepted). Pause waits between positions; abort raises
  inside the runner, which stops the stage and leaves the manifest consistent.

The GUI talks to workers only by signals connected with queued connections; the only objects shared
across threads are thread-safe by contract: the stage (its command lock and any-thread `stop()`),
the mock camera's stage attachment (reads `last_position`), `FrameMailbox`, `CancelToken` and
`ScanControl` (threading primitives).
"""

from __future__ import annotations

import logging
import math
import threading
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
import numpy as np
from PySide6.QtCore import QMetaObject, QObject, Qt, QThread, QTimer, Signal, Slot

from mlaqc.errors import DeviceError, InputError, MlaqcError

log = logging.getLogger(__name__)

LIVE_CAPTURE_TIMEOUT_S = 5.0
STAGE_MONITOR_MS = 50
STAGE_IDLE_POLL_MS = 1000
HOME_TIMEOUT_S = 120.0
MOVE_TIMEOUT_S = 60.0


def one_sentence(exc: BaseException) -> str:
    """An operator-facing sentence for an exception: mlaqc errors are already one; others get a prefix."""
    if isinstance(exc, MlaqcError):
        text = str(exc).strip()
    else:
        text = f"unexpected {type(exc).__name__}: {exc}".strip()
        log.error("unexpected error in a worker:\n%s", "".join(traceback.format_exception(exc)))
    text = " ".join(text.split())
    return text if text.endswith((".", "!", "?")) else text + "."


class _Quitter(QObject):
    """Lives in a worker thread; ends that thread's event loop when its queued turn comes."""

    @Slot()
    def quit(self) -> None:
        QThread.currentThread().quit()


class WorkerThread:
    """A QThread owning one worker QObject; `stop()` drains its queued requests, then joins it."""

    def __init__(self, worker: QObject, name: str) -> None:
        self.worker = worker
        self.thread = QThread()
        self.thread.setObjectName(name)
        self.name = name
        worker.moveToThread(self.thread)
        self._quitter = _Quitter()
        self._quitter.moveToThread(self.thread)
        self.thread.start()

    def stop(self, timeout_s: float) -> bool:
        """Quit the thread's event loop after the requests already queued to it, and wait; False on timeout.

        `QThread.quit()` from here would end the loop before a request posted just now (a report asked for
        right before closing) is delivered; a quit queued behind it runs after it, in order.
        """
        QMetaObject.invokeMethod(self._quitter, "quit", Qt.ConnectionType.QueuedConnection)
        ok = self.thread.wait(int(timeout_s * 1000))
        if not ok:
            log.error("thread %s did not finish within %.1f s", self.name, timeout_s)
        return ok


# ============================================================================================ camera


class FrameMailbox:
    """Hands the newest live frame from the camera thread to the GUI: one slot, newest wins."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._frame: Any = None
        self._pending = False
        self.put_count = 0
        self.dropped = 0

    def put(self, frame: Any) -> bool:
        """Store `frame`; True if the GUI has to be told (it had taken the previous one)."""
        with self._lock:
            self.put_count += 1
            if self._pending:
                self.dropped += 1
            self._frame = frame
            was_pending, self._pending = self._pending, True
            return not was_pending

    def take(self) -> Any:
        """The newest frame (None if there is none); the next put signals again."""
        with self._lock:
            frame, self._frame, self._pending = self._frame, None, False
            return frame


def _lists(obj: Any) -> Any:
    """Tuples to lists, recursively (a config dict as TOML would give it)."""
    if isinstance(obj, dict):
        return {k: _lists(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_lists(v) for v in obj]
    return obj


class CameraWorker(QObject):
    """Owns one camera in the ``camera`` thread; see the module docstring."""

    stateChanged = Signal(str, str)  # state ('disconnected', 'connecting', 'connected', 'error'), detail
    settingsRead = Signal(object)  # dict read back from the camera
    error = Signal(str)  # one sentence
    frameCaptured = Signal(object)  # a drivers.camera.Frame from "capture"
    liveFrameReady = Signal()  # take the frame from the mailbox
    liveChanged = Signal(bool)
    cameraChanged = Signal(object)  # the Camera object (or None): for the scan worker

    def __init__(self, mailbox: FrameMailbox) -> None:
        super().__init__()
        self.mailbox = mailbox
        self.camera: Any = None
        self.url: str | None = None
        self._stage: Any = None
        self._live = False
        self._live_timer = QTimer(self)
        self._live_timer.setInterval(0)
        self._live_timer.timeout.connect(self._live_tick)
        self.live_frames = 0
        self.live_started = 0.0

    # ------------------------------------------------------------------ connection

    @Slot(str)
    def connectCamera(self, url: str) -> None:
        """Open the camera at `url`; reopen it if it is the same URL (keeps e.g. the mock's render cache)."""
        self._stop_live()
        self.stateChanged.emit("connecting", url)
        try:
            if self.camera is not None and url == self.url:
                self.camera.reopen(timeout_s=LIVE_CAPTURE_TIMEOUT_S)
            else:
                self._close_camera()
                from drivers.camera import open_camera

                self.camera = open_camera(url)
                self.url = url
            self._attach()
            settings = self._settings()
        except Exception as exc:  # noqa: BLE001 - every failure becomes one sentence in the panel
            msg = one_sentence(exc)
            self.stateChanged.emit("error", msg)
            self.error.emit(msg)
            return
        self.cameraChanged.emit(self.camera)
        self.stateChanged.emit("connected", str(getattr(self.camera, "name", url)))
        self.settingsRead.emit(settings)

    def _settings(self) -> dict[str, Any]:
        """Settings read back, plus the camera's optics config when it has one (the mock does)."""
        settings = dict(self.camera.settings())
        cfg = getattr(self.camera, "cfg", None)
        if cfg is None and isinstance(settings.get("config"), dict):
            try:
                from mlaqc.optics.config import config_from_dict

                cfg = config_from_dict(_lists(settings["config"]), f"camera {self.url}")
            except InputError:
                cfg = None
        settings["camera_config"] = cfg
        return settings

    @Slot()
    def disconnectCamera(self) -> None:
        self._stop_live()
        self._close_camera()
        self.stateChanged.emit("disconnected", "")

    def _close_camera(self) -> None:
        cam, self.camera = self.camera, None
        if cam is not None:
            self.cameraChanged.emit(None)
            try:
                cam.close()
            except Exception as exc:  # noqa: BLE001
                log.warning("closing the camera: %s", exc)

    @Slot(object)
    def attachStage(self, stage: Any) -> None:
        """Follow `stage` (a mock camera renders what lies under it); None detaches."""
        self._stage = stage
        self._attach()

    def _attach(self) -> None:
        attach = getattr(self.camera, "attach_stage", None)
        if callable(attach):
            stage = self._stage
            attach(None if stage is None else (lambda: stage.last_position))

    # ------------------------------------------------------------------ settings

    @Slot()
    def readSettings(self) -> None:
        if self._require():
            self._guard(lambda: self.settingsRead.emit(self._settings()))

    @Slot(float)
    def setExposure(self, exposure_us: float) -> None:
        if self._require():
            self._guard(lambda: (self.camera.set_exposure_us(exposure_us), self.settingsRead.emit(self._settings())))

    @Slot(float)
    def setGain(self, gain: float) -> None:
        if self._require():
            self._guard(lambda: (self.camera.set_gain(gain), self.settingsRead.emit(self._settings())))

    @Slot(str)
    def setFormat(self, pixel_format: str) -> None:
        if self._require():
            self._guard(lambda: (self.camera.set_format(pixel_format), self.settingsRead.emit(self._settings())))

    def _require(self) -> bool:
        if self.camera is None:
            self.error.emit("The camera is not connected; press Connect first.")
            return False
        return True

    def _guard(self, fn: Any) -> bool:
        """Run a camera call; report a failure as one sentence (and a lost device as state 'error')."""
        try:
            fn()
            return True
        except Exception as exc:  # noqa: BLE001
            msg = one_sentence(exc)
            self.error.emit(msg)
            if isinstance(exc, DeviceError) and not getattr(self.camera, "is_open", True):
                self.stateChanged.emit("error", msg)
            return False

    # ------------------------------------------------------------------ frames

    @Slot()
    def capture(self) -> None:
        """One frame, delivered by `frameCaptured` (live view keeps running)."""
        if not self._require():
            return
        frames: list[Any] = []
        if self._guard(lambda: frames.append(self.camera.capture(LIVE_CAPTURE_TIMEOUT_S))):
            self.frameCaptured.emit(frames[0])

    @Slot()
    def startLive(self) -> None:
        if not self._require() or self._live:
            return
        self._live = True
        self.live_frames = 0
        self.live_started = time.perf_counter()
        self._live_timer.start()
        self.liveChanged.emit(True)

    @Slot()
    def stopLive(self) -> None:
        self._stop_live()

    def _stop_live(self) -> None:
        if self._live:
            self._live = False
            self._live_timer.stop()
            self.liveChanged.emit(False)

    def _live_tick(self) -> None:
        if not self._live or self.camera is None:
            self._stop_live()
            return
        try:
            frame = self.camera.capture(LIVE_CAPTURE_TIMEOUT_S)
        except Exception as exc:  # noqa: BLE001
            self._stop_live()
            msg = one_sentence(exc)
            self.error.emit(msg)
            if not getattr(self.camera, "is_open", True):
                self.stateChanged.emit("error", msg)
            return
        self.live_frames += 1
        if self.mailbox.put(frame):
            self.liveFrameReady.emit()

    @Slot()
    def shutdown(self) -> None:
        """Stop live view and close the camera; then end this thread's event loop."""
        self._stop_live()
        self._close_camera()
        QThread.currentThread().quit()


# ============================================================================================= stage


class StageWorker(QObject):
    """Owns the stage's commands in the ``stage`` thread (blocking calls happen here only)."""

    stateChanged = Signal(str, str)  # 'disconnected', 'connecting', 'connected', 'error'; detail
    info = Signal(object)  # {'name', 'limits': (x0, x1, y0, y1), 'homed'}
    busyChanged = Signal(bool, str)  # busy, what
    error = Signal(str)
    message = Signal(str)
    stageChanged = Signal(object)  # the Stage object (or None)

    def __init__(self) -> None:
        super().__init__()
        self.stage: Any = None
        self.url: str | None = None
        self._poll = QTimer(self)
        self._poll.setInterval(STAGE_IDLE_POLL_MS)
        self._poll.timeout.connect(self._idle_poll)
        self._lent = False  # the scan worker is using the stage: no polling meanwhile

    @Slot(str)
    def connectStage(self, url: str) -> None:
        """(Re)connect: a stage on a simulator cannot be re-plugged, so reconnect = close and open anew."""
        self.stateChanged.emit("connecting", url)
        self._close_stage()
        try:
            from drivers.stage import open_stage

            self.stage = open_stage(url)
            self.url = url
        except Exception as exc:  # noqa: BLE001
            msg = one_sentence(exc)
            self.stateChanged.emit("error", msg)
            self.error.emit(msg)
            return
        self.stageChanged.emit(self.stage)
        self.stateChanged.emit("connected", self.stage.name)
        self._emit_info()
        if not self._poll.isActive():
            self._poll.start()

    @Slot()
    def disconnectStage(self) -> None:
        self._close_stage()
        self.stateChanged.emit("disconnected", "")

    def _close_stage(self) -> None:
        stage, self.stage = self.stage, None
        if stage is not None:
            self.stageChanged.emit(None)
            try:
                stage.close()
            except Exception as exc:  # noqa: BLE001
                log.warning("closing the stage: %s", exc)

    def _emit_info(self) -> None:
        s = self.stage
        if s is None:
            return
        lim = s.limits
        self.info.emit({"name": s.name, "limits": (lim.x_min_mm, lim.x_max_mm, lim.y_min_mm, lim.y_max_mm),
                        "homed": s.homed, "connected": s.is_connected})

    @Slot(bool)
    def setLent(self, lent: bool) -> None:
        self._lent = lent

    def _command(self, what: str, fn: Any) -> None:
        if self.stage is None:
            self.error.emit("The stage is not connected; press Connect first.")
            return
        if self._lent:
            self.error.emit(f"The stage is busy with a scan; {what} was not sent.")
            return
        self.busyChanged.emit(True, what)
        try:
            fn()
        except Exception as exc:  # noqa: BLE001
            from drivers.stage import StageStopped

            msg = one_sentence(exc)
            if isinstance(exc, StageStopped):
                self.message.emit(msg)
            else:
                self.error.emit(msg)
                if not self.stage.is_connected:
                    self.stateChanged.emit("error", msg)
        finally:
            self.busyChanged.emit(False, "")
            self._emit_info()

    @Slot()
    def home(self) -> None:
        self._command("homing", lambda: self.stage.home(timeout_s=HOME_TIMEOUT_S))

    @Slot(float, float)
    def moveTo(self, x_mm: float, y_mm: float) -> None:
        self._command(f"a move to ({x_mm:g}, {y_mm:g}) mm", lambda: self.stage.move_to(x_mm, y_mm, timeout_s=MOVE_TIMEOUT_S))

    @Slot(float, float)
    def moveBy(self, dx_mm: float, dy_mm: float) -> None:
        self._command(f"a jog by ({dx_mm:g}, {dy_mm:g}) mm",
                      lambda: self.stage.move_by(dx_mm, dy_mm, timeout_s=MOVE_TIMEOUT_S))

    def _idle_poll(self) -> None:
        """Ask the device for its position now and then, so a dead link shows without a command."""
        s = self.stage
        if s is None or self._lent or not s.is_connected:
            return
        try:
            s.position(timeout_s=1.0)
        except Exception as exc:  # noqa: BLE001
            if not s.is_connected:
                msg = one_sentence(exc)
                self.error.emit(msg)
                self.stateChanged.emit("error", msg)
                self._emit_info()

    @Slot()
    def shutdown(self) -> None:
        self._poll.stop()
        self._close_stage()
        QThread.currentThread().quit()


class StageControl(QObject):
    """The ``stage-control`` thread: STOP at once, and the live position (no blocking commands)."""

    position = Signal(object)  # {'pos': (x, y) | None, 'connected', 'homed'}
    error = Signal(str)
    message = Signal(str)

    def __init__(self) -> None:
        super().__init__()
        self.stage: Any = None
        self._timer = QTimer(self)
        self._timer.setInterval(STAGE_MONITOR_MS)
        self._timer.timeout.connect(self._publish)
        self._last: Any = None

    @Slot(object)
    def setStage(self, stage: Any) -> None:
        self.stage = stage
        self._last = None
        if not self._timer.isActive():
            self._timer.start()
        self._publish()

    @Slot()
    def stop(self) -> None:
        """Halt the stage now (out-of-band; cancels the running and queued moves)."""
        s = self.stage
        if s is None:
            return
        try:
            s.stop()
            self.message.emit(f"STOP sent to {s.name}.")
        except Exception as exc:  # noqa: BLE001
            self.error.emit(one_sentence(exc))

    def _publish(self) -> None:
        s = self.stage
        state = {"pos": None, "connected": False, "homed": False} if s is None else {
            "pos": s.last_position, "connected": s.is_connected, "homed": s.homed}
        if state != self._last:
            self._last = state
            self.position.emit(state)

    @Slot()
    def shutdown(self) -> None:
        self._timer.stop()
        QThread.currentThread().quit()


# ======================================================================================== inspection


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
    from mlaqc.inspection.rawio import RawFrame, check_exposure

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
            from mlaqc.inspection.calibrate import calibrate_for
            from mlaqc.inspection.pipeline import inspect_image, load_frame

            cfg = req.cfg
            dark, info, notes = None, None, []
            if req.darks:
                from mlaqc.inspection.darks import load_frames, master_dark_cached, noise_info, noise_notes, with_noise
                from mlaqc.inspection.rawio import Levels

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
            grid = calibrate_for(white, cfg)
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
        from mlaqc.inspection.combine import combine_through_focus
        from mlaqc.inspection.pinhole_frames import load_pinhole_frames
        from mlaqc.inspection.throughfocus import measure_through_focus

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


# ================================================================================================ io


class IoWorker(QObject):
    """Writes report sets and frames in the ``io`` thread; the app waits for it on close."""

    reportWritten = Signal(int, object)  # job, {key: path}
    historyRead = Signal(int, object)  # job, gui.history.read_history's dict
    frameSaved = Signal(int, str)
    failed = Signal(int, str)
    busyChanged = Signal(bool)

    @Slot(int, object, str, object)
    def writeReport(self, job: int, result: Any, out_dir: str, config_dict: Any) -> None:
        """Write the report set, then record the inspection in the results database (mlaqc.resultsdb, its
        default target: $MLAQC_DB or the user's data folder); a database that cannot record it is said
        after the report is written."""
        from mlaqc.commands.recording import render_with_record
        from mlaqc.report import write_report_files

        self.busyChanged.emit(True)
        try:
            contents = render_with_record(result, config_dict)
            paths = write_report_files(contents, out_dir)
        except Exception as exc:  # noqa: BLE001
            self.failed.emit(job, one_sentence(exc))
        else:
            self.reportWritten.emit(job, {k: str(v) for k, v in paths.items()})
            self._record(job, contents["record"], out_dir)
        finally:
            self.busyChanged.emit(False)

    def _record(self, job: int, record: bytes, out_dir: str) -> None:
        import json

        from mlaqc.resultsdb import DatabaseError, Identity, open_database

        try:
            with open_database() as db:
                db.record(json.loads(record), Identity.here(), out_dir)
        except DatabaseError as exc:
            self.failed.emit(job, f"the report is written, but {exc}")

    @Slot(int, str)
    def readHistory(self, job: int, lot: str) -> None:
        """A lot's arrays from the results database (gui.history.read_history)."""
        from gui.history import read_history

        self.busyChanged.emit(True)
        try:
            data = read_history(lot)
        except Exception as exc:  # noqa: BLE001
            self.failed.emit(job, one_sentence(exc))
        else:
            self.historyRead.emit(job, data)
        finally:
            self.busyChanged.emit(False)

    @Slot(int, object, str, object)
    def saveFrame(self, job: int, frame: Any, path: str, position_mm: Any) -> None:
        from drivers.capture import Grab, save_frame

        self.busyChanged.emit(True)
        try:
            saved = save_frame(path, Grab(frame.data, (frame,), frame.device), position_mm=position_mm)
        except Exception as exc:  # noqa: BLE001
            self.failed.emit(job, one_sentence(exc))
        else:
            self.frameSaved.emit(job, str(saved.path))
        finally:
            self.busyChanged.emit(False)


# ============================================================================================== scan


class ScanAborted(KeyboardInterrupt):
    """Raised inside the scan runner when the operator aborts (the runner treats it like Ctrl-C)."""


class ScanControl:
    """Pause/abort flags shared by the GUI (sets) and the scan worker (waits/reads)."""

    def __init__(self) -> None:
        self._abort = threading.Event()
        self._running = threading.Event()
        self._running.set()

    def abort(self) -> None:
        self._abort.set()
        self._running.set()

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

    @property
    def aborted(self) -> bool:
        return self._abort.is_set()

    @property
    def paused(self) -> bool:
        return not self._running.is_set()

    def check(self) -> None:
        if self._abort.is_set():
            raise ScanAborted()

    def wait_while_paused(self, on_pause: Any = None) -> None:
        """Block while paused (abort wakes it); raise ScanAborted if aborted."""
        self.check()
        if not self._running.is_set():
            if on_pause is not None:
                on_pause(True)
            while not self._running.wait(0.05):
                pass
            if on_pause is not None:
                on_pause(False)
        self.check()


class _AbortableStage:
    """The stage as the scan runner sees it: motion raises ScanAborted once the operator aborted."""

    def __init__(self, stage: Any, control: ScanControl) -> None:
        self._stage = stage
        self._control = control

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stage, name)

    def _motion(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        from drivers.stage import StageStopped

        self._control.check()
        try:
            return fn(*args, **kwargs)
        except StageStopped:
            if self._control.aborted:
                raise ScanAborted() from None
            raise

    def home(self, *a: Any, **k: Any) -> None:
        return self._motion(self._stage.home, *a, **k)

    def move_to(self, *a: Any, **k: Any) -> None:
        return self._motion(self._stage.move_to, *a, **k)

    def move_by(self, *a: Any, **k: Any) -> None:
        return self._motion(self._stage.move_by, *a, **k)


class _AbortableCamera:
    """The camera as the scan runner sees it: no new capture starts once the operator aborted."""

    def __init__(self, camera: Any, control: ScanControl) -> None:
        self._camera = camera
        self._control = control

    def __getattr__(self, name: str) -> Any:
        return getattr(self._camera, name)

    def capture(self, *a: Any, **k: Any) -> Any:
        self._control.check()
        return self._camera.capture(*a, **k)


@dataclass
class ScanRequest:
    plan: Any  # drivers.scan.ScanPlan
    out_dir: str
    camera: Any
    stage: Any
    cfg: Any = None  # inspect each position when set
    resume: bool = False
    control: ScanControl = field(default_factory=ScanControl)


class ScanWorker(QObject):
    """Runs one scan at a time in the ``scan`` thread."""

    positionStarted = Signal(int)  # plan index
    positionDone = Signal(int, object)  # plan index, {'verdict', 'flagged', 'out_of_tolerance', 'file'}
    progress = Signal(int, int)  # done, total
    event = Signal(object)  # the runner's event dicts
    pausedChanged = Signal(bool)
    finished = Signal(str, object)  # outcome ('finished', 'aborted', 'failed'), message

    @Slot(object)
    def run(self, req: ScanRequest) -> None:
        from drivers.scan import ScanRunner

        control = req.control
        verdicts: dict[int, dict[str, Any]] = {}
        current: list[Any] = []  # the position being attempted

        def before(runner: Any, pos: Any) -> None:
            control.wait_while_paused(self.pausedChanged.emit)
            current[:] = [pos]
            self.positionStarted.emit(pos.index)

        def progress(done: int, total: int) -> None:
            if current:  # called after each recorded (and inspected) position
                pos = current.pop()
                info = dict(verdicts.get(pos.index, {}))
                info.setdefault("verdict", None)
                name = pos.file_names(req.plan.frames_per_position, req.plan.suffix)[0]
                info["file"] = str(Path(req.out_dir) / name)
                self.positionDone.emit(pos.index, info)
            self.progress.emit(done, total)
            control.check()

        def on_event(ev: dict) -> None:
            if ev.get("event") in ("inspect_failed", "position_failed") and "index" in ev:
                verdicts[int(ev["index"])] = {"verdict": "ERROR", "error": str(ev.get("error") or ev.get("reason", ""))}
            self.event.emit(ev)

        inspect_hook = None
        if req.cfg is not None:
            cfg = req.cfg

            def inspect_hook(frame: Any) -> dict:
                from mlaqc.inspection.pipeline import inspect_image, load_frame

                result = inspect_image(load_frame(frame.path, cfg), cfg, source=str(frame.path))
                out = sum(1 for d in result.defects if not d.within_tolerance)
                info = {"verdict": result.verdict, "flagged": len(result.defects), "out_of_tolerance": out,
                        "defects": [d.to_json_dict() for d in result.defects], "source": frame.path.name}
                verdicts[int(frame.record["index"])] = info
                return info

        try:
            runner = ScanRunner(req.plan, req.out_dir, camera=_AbortableCamera(req.camera, control),
                                stage=_AbortableStage(req.stage, control), resume=req.resume, inspect=inspect_hook,
                                progress=progress, before_position=before, on_event=on_event)
            result = runner.run()
        except KeyboardInterrupt as exc:  # ScanInterrupted (our abort, via the runner)
            self.finished.emit("aborted", str(exc) or "scan aborted; the stage was stopped.")
            return
        except Exception as exc:  # noqa: BLE001
            self.finished.emit("failed", one_sentence(exc))
            return
        self.finished.emit("finished", result.summary())
