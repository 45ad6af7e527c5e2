"""Workers of the QC app: every device and every long job runs off the GUI thread.

This module holds the threads' plumbing (`WorkerThread`, `one_sentence`) and the workers of the devices and
of file writes; the inspection job and the display view it prepares are in gui.inspection_worker, the scan
in gui.scan_worker.

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
- ``inspection``: `InspectionWorker` (gui.inspection_worker) loads, calibrates and inspects, then
  precomputes everything the display needs (levels, ring positions, a k-d tree of lens centres) so the
  GUI thread only draws.
  With through-focus frames it then reads them on the result's grid (mlaqc.inspection.throughfocus) and
  combines both measurements (mlaqc.inspection.combine).
  Cancel is a `CancelToken` checked between stages; a cancelled job's result is never shown.
- ``frames``: `FrameWorker` (gui.inspection_worker, beside the checks it runs) checks the through-focus
  pinhole frames the operator picks (their records, sizes and +u / -u pairs) and loads one of them for
  display when the frame selector asks, so neither waits for a running inspection nor blocks the GUI.
- ``io``: `IoWorker` writes report sets (`mlaqc.report.write_report`) and saves frames; on close the
  app waits for it, so a report is never left half written.
- ``scan``: `ScanWorker` (gui.scan_worker) runs `drivers.scan.ScanRunner` with the devices the app
  already has open (the device panels are locked meanwhile, STOP excepted). Pause waits between
  positions; abort raises inside the runner, which stops the stage and leaves the manifest consistent.

The GUI talks to workers only by signals connected with queued connections; the only objects shared
across threads are thread-safe by contract: the stage (its command lock and any-thread `stop()`),
the mock camera's stage attachment (reads `last_position`), `FrameMailbox`, `CancelToken`
(gui.inspection_worker) and `ScanControl` (gui.scan_worker), threading primitives.
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
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
