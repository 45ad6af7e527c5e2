"""The mlaqc QC desktop app: the main window (its signals, state, camera config and closing) and `run`.

`MainWindow` is assembled from mixins, one module each: gui.window_layout (docks, menus, widget signals),
gui.window_workers (the worker threads and their queued connections), gui.window_devices (camera and stage),
gui.window_inputs (what an inspection reads), gui.window_results (inspection runs and their display),
gui.window_reports (report export and lot history in the io worker) and gui.window_scans (scans).
Everything slow runs in the workers of gui.workers, gui.inspection_worker and gui.scan_worker (one thread
per device, one for inspection, one for file writes, one for scans); the window only connects signals
(queued across threads) and updates widgets. See gui.workers for the threading model.
"""

from __future__ import annotations

import gc
import logging
import sys
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtCore import QTimer, Signal
from PySide6.QtWidgets import QApplication, QFileDialog, QMainWindow

from gui.inspection_worker import CancelToken
from gui.scan_worker import ScanControl
from gui.window_devices import DevicesMixin
from gui.window_inputs import InspectionInputsMixin
from gui.window_layout import WindowLayoutMixin
from gui.window_reports import ReportsHistoryMixin
from gui.window_results import InspectionResultsMixin
from gui.window_scans import ScansMixin
from gui.window_workers import WorkerWiringMixin
from gui.workers import FrameMailbox

log = logging.getLogger(__name__)

DEFAULT_CAMERA_URL = "mock://?wafer=3x3"
DEFAULT_STAGE_URL = "sim+grbl://"


# The mixins come before QMainWindow, so their methods take precedence over Qt's as when they were defined here.
class MainWindow(WindowLayoutMixin, WorkerWiringMixin, DevicesMixin, InspectionInputsMixin, InspectionResultsMixin,
                 ReportsHistoryMixin, ScansMixin, QMainWindow):
    """The QC operator's window. Public methods double as the test API (no modal dialogs needed)."""

    # requests to the workers (queued connections)
    _cam_connect = Signal(str)
    _cam_disconnect = Signal()
    _cam_exposure = Signal(float)
    _cam_gain = Signal(float)
    _cam_format = Signal(str)
    _cam_capture = Signal()
    _cam_live_start = Signal()
    _cam_live_stop = Signal()
    _cam_attach = Signal(object)
    _cam_read = Signal()
    _cam_shutdown = Signal()
    _stage_connect = Signal(str)
    _stage_disconnect = Signal()
    _stage_home = Signal()
    _stage_move_to = Signal(float, float)
    _stage_move_by = Signal(float, float)
    _stage_lent = Signal(bool)
    _stage_shutdown = Signal()
    _ctl_stage = Signal(object)
    _ctl_stop = Signal()
    _ctl_shutdown = Signal()
    _inspect = Signal(int, object)
    _preview = Signal(int, str)
    _write_report = Signal(int, object, str, object)
    _read_history = Signal(int, str)
    _save_frame = Signal(int, object, str, object)
    _scan = Signal(object)
    _describe_tf = Signal(int, object, object)
    _load_tf_frame = Signal(int, str, object)

    # notifications (for tests and scripting)
    inspectionShown = Signal(object)
    frameShown = Signal(int)  # the frame selector's entry now on display (0: the inspected frame)
    throughFocusChanged = Signal(object)  # the through-focus frames in use (a tuple of TfFrame; empty: none)
    scanFinished = Signal(str, str)
    reportWritten = Signal(object)
    historyShown = Signal(object)


    def __init__(self, camera_url: str = DEFAULT_CAMERA_URL, stage_url: str = DEFAULT_STAGE_URL,
                 config_path: str | None = None, *, connect: bool = True) -> None:
        super().__init__()
        self.setWindowTitle("mlaqc — microlens-array QC")
        self.resize(1680, 1050)
        self.camera_url, self.stage_url = camera_url, stage_url
        self.cfg_path: str | None = None
        self.cfg_explicit: Any = None  # a config the operator chose (else the camera's, else Table 1)
        self.camera_cfg: Any = None
        self.camera_obj: Any = None
        self.stage_obj: Any = None
        self.stage_state: dict[str, Any] = {"pos": None, "connected": False, "homed": False}
        self.camera_state = "disconnected"
        self.last_frame: Any = None
        self.input: tuple[str, Any] | None = None  # ('raw', path) or ('frame', Frame)
        self.white: str | None = None
        self.darks: tuple[str, ...] = ()  # dark frames: their master dark is subtracted before inspection
        self.tf_frames: tuple[Any, ...] = ()  # through-focus frames in use (gui.inspection_worker.TfFrame), checked
        self.tf_pending: tuple[str, ...] | None = None  # paths chosen, being checked by the frames worker
        self.tf_job = 0
        self.frame_job = 0  # the through-focus frame asked for display
        self.frame_cache: OrderedDict[str, tuple[Any, Any]] = OrderedDict()  # path -> (image, levels)
        self.view: Any = None  # the InspectionView on display
        self.job = 0
        self.token: CancelToken | None = None
        self.preview_job = 0
        self.io_job = 0
        self._history_job = -1  # the io job reading the lot history (its failure is the history panel's)
        self.scan_control: ScanControl | None = None
        self.scan_plan: Any = None
        self.scan_plan_path: str | None = None
        self.scan_plan_text: str | None = None  # set when the plan in use came from the editor
        self.scan_out: str | None = None
        self.scan_files: dict[int, str] = {}
        self.scan_current: int | None = None
        self.scan_running = False
        self.can_resume = False
        self.io_busy = False
        self._closed = False
        self.mailbox = FrameMailbox()
        self.errors: list[str] = []  # every error shown (tests read it)

        self._build_ui()
        self._start_workers()
        if config_path:
            self.load_config(config_path)
        else:
            self._update_config_label()
        if connect:
            self.connect_camera(camera_url)
            self.connect_stage(stage_url)
        QTimer.singleShot(0, self._freeze_startup_heap)

    def _freeze_startup_heap(self) -> None:
        """Move everything alive after start-up out of the garbage collector's sight (`gc.freeze`).

        A full collection walks every tracked object while holding the GIL, which stalls the GUI thread
        (measured 50-90 ms with the test suite loaded). Qt, pyqtgraph, numpy and our modules never die,
        so they need not be walked again; later collections only see what the session allocates.
        """
        gc.collect()
        gc.freeze()

    # ============================================================================== helpers

    def log(self, text: str, level: str = "info") -> None:
        self.log_view.add(text, level)
        if level == "error":
            self.errors.append(text)
            self.statusBar().showMessage(text, 8000)

    @property
    def cfg(self) -> Any:
        """The camera config inspections use: the operator's choice, else the camera's, else Table 1."""
        if self.cfg_explicit is not None:
            return self.cfg_explicit
        if self.camera_cfg is not None:
            return self.camera_cfg
        from mlaqc.optics.config import default_config

        return default_config()

    def _update_config_label(self) -> None:
        c = self.cfg
        where = (Path(self.cfg_path).name if self.cfg_explicit is not None and self.cfg_path
                 else "from the camera" if self.camera_cfg is not None else "Table 1 (default)")
        packing = " hex" if getattr(c.mla, "packing", "square") == "hex" else ""
        self.inspection_panel.config.setText(f"{where}: {c.mla.count_h}×{c.mla.count_w}{packing} lenses, "
                                             f"{c.sensor.width_px}×{c.sensor.height_px} px")

    def _ask_open(self, title: str, filt: str) -> str | None:
        path, _ = QFileDialog.getOpenFileName(self, title, "", filt)
        return path or None

    # ============================================================================== closing

    def closeEvent(self, event: Any) -> None:
        self.shutdown()
        event.accept()

    def shutdown(self) -> None:
        """Stop moving devices, finish writes and join every thread (bounded waits); idempotent."""
        if self._closed:
            return
        self._closed = True
        t0 = time.perf_counter()
        if self.scan_control is not None:
            self.scan_control.abort()
        if self.token is not None:
            self.token.cancel()
        self._ctl_stop.emit()  # halt the stage first, from its never-blocked control thread
        self._cam_live_stop.emit()
        th = self.threads
        ok = th["scan"].stop(30.0)
        ok &= th["inspection"].stop(120.0)
        ok &= th["io"].stop(300.0)  # a report being written is finished, never cut
        ok &= th["frames"].stop(30.0)
        self.lightfield_panel.shutdown()
        self._cam_shutdown.emit()
        ok &= th["camera"].thread.wait(15_000)
        self._stage_shutdown.emit()
        ok &= th["stage"].thread.wait(15_000)
        self._ctl_shutdown.emit()
        ok &= th["stage-control"].thread.wait(5_000)
        if not ok:
            log.error("some worker threads did not finish; the app exits anyway")
        self.shutdown_s = time.perf_counter() - t0


def run(camera_url: str = DEFAULT_CAMERA_URL, stage_url: str = DEFAULT_STAGE_URL, config: str | None = None,
        argv: list[str] | None = None) -> int:
    """Create the application and the main window, run the event loop; 0 on a normal exit."""
    app = QApplication.instance() or QApplication(argv if argv is not None else sys.argv[:1])
    app.setApplicationName("mlaqc")
    app.setStyle("Fusion")
    win = MainWindow(camera_url, stage_url, config)
    app.aboutToQuit.connect(win.shutdown)
    win.show()
    return int(app.exec())
