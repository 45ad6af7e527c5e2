"""The mlaqc QC desktop app: main window, docks, and the wiring between widgets and workers.

Everything slow runs in the workers of gui.workers, gui.inspection_worker and gui.scan_worker (one thread
per device, one for inspection, one for file writes, one for scans); this module only connects signals
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
from PySide6.QtCore import QItemSelectionModel, QModelIndex, Qt, QTimer, Signal
from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import (QAbstractItemView, QApplication, QDockWidget, QFileDialog, QHeaderView, QLabel,
                               QMainWindow, QTableView, QVBoxLayout, QWidget)

from gui.history import HistoryPanel
from gui.inspection_worker import (CancelToken, FrameWorker, InspectionRequest, InspectionWorker, through_focus_label,
                                   through_focus_summary)
from gui.lightfield import LightFieldPanel
from gui.panels import CameraPanel, InspectionPanel, ScanPanel, StagePanel
from gui.scan_worker import ScanControl, ScanRequest, ScanWorker
from gui.widgets import (MONO, DefectSortProxy, DefectTableModel, ImagePanel, LensDetail, LogView, StatusDot,
                         VerdictBanner)
from gui.workers import CameraWorker, FrameMailbox, IoWorker, StageControl, StageWorker, WorkerThread
from mlaqc.errors import InputError

log = logging.getLogger(__name__)

DEFAULT_CAMERA_URL = "mock://?wafer=3x3"
DEFAULT_STAGE_URL = "sim+grbl://"
RAW_FILTER = "Raw images (*.dng *.DNG *.tif *.tiff *.png *.npy *.nef *.cr2 *.arw *.raf *.orf *.rw2);;All files (*)"
Q = Qt.ConnectionType.QueuedConnection


class MainWindow(QMainWindow):
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

    # ================================================================================== UI

    def _build_ui(self) -> None:
        central = QWidget()
        lay = QVBoxLayout(central)
        lay.setContentsMargins(4, 4, 4, 4)
        lay.setSpacing(4)
        self.banner = VerdictBanner()
        self.image = ImagePanel()
        lay.addWidget(self.banner)
        lay.addWidget(self.image, 1)
        self.setCentralWidget(central)
        self.setDockOptions(QMainWindow.DockOption.AnimatedDocks | QMainWindow.DockOption.AllowTabbedDocks)
        self.setCorner(Qt.Corner.BottomLeftCorner, Qt.DockWidgetArea.LeftDockWidgetArea)
        self.setCorner(Qt.Corner.BottomRightCorner, Qt.DockWidgetArea.RightDockWidgetArea)

        self.camera_panel = CameraPanel(self.camera_url)
        self.stage_panel = StagePanel(self.stage_url)
        self.inspection_panel = InspectionPanel()
        self.scan_panel = ScanPanel()
        self.history_panel = HistoryPanel()
        self.lightfield_panel = LightFieldPanel()
        self.lens_detail = LensDetail()
        self.log_view = LogView()
        self.table_model = DefectTableModel(self)
        self.table_proxy = DefectSortProxy(self)
        self.table_proxy.setSourceModel(self.table_model)
        self.table = QTableView()
        self.table.setModel(self.table_proxy)
        self.table.setSortingEnabled(True)
        self.table.sortByColumn(-1, Qt.SortOrder.AscendingOrder)  # keep the model's severity order at first
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setAlternatingRowColors(True)
        self.table.verticalHeader().hide()
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table_title = QLabel("No inspection yet.")
        self.table_title.setWordWrap(True)
        table_box = QWidget()
        tl = QVBoxLayout(table_box)
        tl.setContentsMargins(4, 4, 4, 4)
        tl.addWidget(self.table_title)
        tl.addWidget(self.table, 1)

        self.docks: dict[str, QDockWidget] = {}
        L, R, B = (Qt.DockWidgetArea.LeftDockWidgetArea, Qt.DockWidgetArea.RightDockWidgetArea,
                   Qt.DockWidgetArea.BottomDockWidgetArea)
        for key, title, widget, area in (("camera", "Camera", self.camera_panel, L),
                                         ("stage", "Stage", self.stage_panel, L),
                                         ("inspection", "Inspection", self.inspection_panel, R),
                                         ("defects", "Flagged lenses", table_box, R),
                                         ("lens", "Lens detail", self.lens_detail, R),
                                         ("scan", "Scan", self.scan_panel, B),
                                         ("history", "Lot history", self.history_panel, B),
                                         ("lightfield", "Light field", self.lightfield_panel, B),
                                         ("log", "Log", self.log_view, B)):
            dock = QDockWidget(title, self)
            dock.setObjectName(f"dock_{key}")
            dock.setWidget(widget)
            self.addDockWidget(area, dock)
            self.docks[key] = dock
        self.tabifyDockWidget(self.docks["scan"], self.docks["history"])
        self.tabifyDockWidget(self.docks["history"], self.docks["lightfield"])
        self.tabifyDockWidget(self.docks["lightfield"], self.docks["log"])
        self.docks["scan"].raise_()
        self.resizeDocks([self.docks["camera"], self.docks["inspection"]], [330, 470], Qt.Orientation.Horizontal)
        self.resizeDocks([self.docks["scan"]], [250], Qt.Orientation.Vertical)
        self.resizeDocks([self.docks["camera"], self.docks["stage"]], [250, 600], Qt.Orientation.Vertical)
        self.resizeDocks([self.docks["inspection"], self.docks["defects"], self.docks["lens"]], [230, 300, 420],
                         Qt.Orientation.Vertical)

        # status bar
        self.cursor_label = QLabel("")
        self.cursor_label.setFont(MONO)
        self.cam_dot = StatusDot()
        self.stage_dot = StatusDot()
        self.cam_dot.set_state("disconnected", "camera")
        self.stage_dot.set_state("disconnected", "stage")
        self.statusBar().addWidget(self.cursor_label, 1)
        self.statusBar().addPermanentWidget(self.cam_dot)
        self.statusBar().addPermanentWidget(self.stage_dot)

        # menus
        m = self.menuBar().addMenu("&File")
        self._action(m, "Open raw…", self.browse_raw, QKeySequence.StandardKey.Open)
        self._action(m, "Open white image…", self.browse_white)
        self._action(m, "Through-focus frames…", self.browse_through_focus)
        self._action(m, "Dark frames…", self.browse_darks)
        self._action(m, "Camera config…", self.browse_config)
        self._action(m, "Export report…", self.browse_export, "Ctrl+E")
        self._action(m, "Load scan plan…", self.browse_plan)
        m.addSeparator()
        self._action(m, "Quit", self.close, QKeySequence.StandardKey.Quit)
        d = self.menuBar().addMenu("&Devices")
        self._action(d, "Reconnect camera", lambda: self.connect_camera(self.camera_panel.connection.url.text()))
        self._action(d, "Reconnect stage", lambda: self.connect_stage(self.stage_panel.connection.url.text()))
        self._action(d, "STOP stage", self.stop_stage, "Esc")
        v = self.menuBar().addMenu("&View")
        for dock in self.docks.values():
            v.addAction(dock.toggleViewAction())

        # widget signals
        cp, sp, ip, sc = self.camera_panel, self.stage_panel, self.inspection_panel, self.scan_panel
        cp.connection.connectRequested.connect(self.connect_camera)
        cp.connection.disconnectRequested.connect(self._cam_disconnect)
        cp.exposureRequested.connect(self._cam_exposure)
        cp.gainRequested.connect(self._cam_gain)
        cp.formatRequested.connect(self._cam_format)
        cp.liveToggled.connect(self.set_live)
        cp.captureRequested.connect(self.capture_frame)
        cp.saveRequested.connect(self.browse_save_frame)
        self.history_panel.refreshRequested.connect(self.read_history)
        self.inspectionShown.connect(lambda view: self.lightfield_panel.set_inspection(view, self.cfg))
        sp.connection.connectRequested.connect(self.connect_stage)
        sp.connection.disconnectRequested.connect(self._stage_disconnect)
        sp.homeRequested.connect(self._stage_home)
        sp.jogRequested.connect(self._stage_move_by)
        sp.gotoRequested.connect(self._stage_move_to)
        sp.stopRequested.connect(self.stop_stage)
        ip.openRawRequested.connect(self.browse_raw)
        ip.openWhiteRequested.connect(self.browse_white)
        ip.clearWhiteRequested.connect(lambda: self.set_white(None))
        ip.openThroughFocusRequested.connect(self.browse_through_focus)
        ip.clearThroughFocusRequested.connect(self.clear_through_focus)
        ip.openDarksRequested.connect(self.browse_darks)
        ip.clearDarksRequested.connect(lambda: self.set_darks(()))
        ip.useFrameRequested.connect(self.use_last_frame)
        ip.configRequested.connect(self.browse_config)
        ip.runRequested.connect(self.run_inspection)
        ip.cancelRequested.connect(self.cancel_inspection)
        ip.exportRequested.connect(self.browse_export)
        sc.loadPlanRequested.connect(self.browse_plan)
        sc.editPlanRequested.connect(self.edit_plan)
        sc.chooseOutRequested.connect(self.browse_scan_out)
        sc.runRequested.connect(lambda: self.start_scan())
        sc.pauseToggled.connect(self.pause_scan)
        sc.abortRequested.connect(self.abort_scan)
        sc.resumeRequested.connect(lambda: self.start_scan(resume=True))
        sc.wafer.positionClicked.connect(self._wafer_clicked)
        self.image.hovered.connect(self._hovered)
        self.image.clicked.connect(self._image_clicked)
        self.image.frameChosen.connect(self.show_frame_choice)
        self.table.clicked.connect(self._table_clicked)
        self.table.selectionModel().currentRowChanged.connect(lambda cur, _prev: self._table_current_changed(cur))

    def _action(self, menu: Any, text: str, fn: Any, shortcut: Any = None) -> QAction:
        a = QAction(text, self)
        if shortcut is not None:
            a.setShortcut(QKeySequence(shortcut))
            a.setShortcutContext(Qt.ShortcutContext.ApplicationShortcut)
        a.triggered.connect(lambda _checked=False: fn())
        menu.addAction(a)
        return a

    # ============================================================================== workers

    def _start_workers(self) -> None:
        self.camera_worker = CameraWorker(self.mailbox)
        self.stage_worker = StageWorker()
        self.stage_control = StageControl()
        self.inspection_worker = InspectionWorker()
        self.io_worker = IoWorker()
        self.scan_worker = ScanWorker()
        self.frame_worker = FrameWorker()
        cw, sw, sc, iw, io, scw, fw = (self.camera_worker, self.stage_worker, self.stage_control, self.inspection_worker,
                                       self.io_worker, self.scan_worker, self.frame_worker)
        # requests (queued: the slot runs in the worker's thread)
        for sig, slot in ((self._cam_connect, cw.connectCamera), (self._cam_disconnect, cw.disconnectCamera),
                          (self._cam_exposure, cw.setExposure), (self._cam_gain, cw.setGain),
                          (self._cam_format, cw.setFormat), (self._cam_capture, cw.capture),
                          (self._cam_live_start, cw.startLive), (self._cam_live_stop, cw.stopLive),
                          (self._cam_attach, cw.attachStage), (self._cam_read, cw.readSettings),
                          (self._cam_shutdown, cw.shutdown),
                          (self._stage_connect, sw.connectStage), (self._stage_disconnect, sw.disconnectStage),
                          (self._stage_home, sw.home), (self._stage_move_to, sw.moveTo),
                          (self._stage_move_by, sw.moveBy), (self._stage_lent, sw.setLent),
                          (self._stage_shutdown, sw.shutdown),
                          (self._ctl_stage, sc.setStage), (self._ctl_stop, sc.stop), (self._ctl_shutdown, sc.shutdown),
                          (self._inspect, iw.run), (self._preview, iw.preview),
                          (self._write_report, io.writeReport), (self._save_frame, io.saveFrame),
                          (self._read_history, io.readHistory),
                          (self._scan, scw.run), (self._describe_tf, fw.describe), (self._load_tf_frame, fw.loadFrame)):
            sig.connect(slot, Q)
        # results (queued back to the GUI thread)
        cw.stateChanged.connect(self._camera_state, Q)
        cw.settingsRead.connect(self._camera_settings, Q)
        cw.error.connect(self._camera_error, Q)
        cw.frameCaptured.connect(self._frame_captured, Q)
        cw.liveFrameReady.connect(self._live_frame, Q)
        cw.liveChanged.connect(self._live_changed, Q)
        cw.cameraChanged.connect(self._camera_changed, Q)
        sw.stateChanged.connect(self._stage_state, Q)
        sw.info.connect(self._stage_info, Q)
        sw.busyChanged.connect(self.stage_panel.set_busy, Q)
        sw.error.connect(self._stage_error, Q)
        sw.message.connect(self._device_message, Q)
        sw.stageChanged.connect(self._stage_changed, Q)
        sc.position.connect(self._stage_position, Q)
        sc.error.connect(self._stage_error, Q)
        sc.message.connect(self._device_message, Q)
        iw.progress.connect(self._inspection_progress, Q)
        iw.finished.connect(self._inspection_finished, Q)
        iw.failed.connect(self._inspection_failed, Q)
        iw.cancelled.connect(self._inspection_cancelled, Q)
        iw.previewReady.connect(self._preview_ready, Q)
        iw.previewFailed.connect(self._preview_failed, Q)
        fw.described.connect(self._tf_described, Q)
        fw.describeFailed.connect(self._tf_failed, Q)
        fw.frameReady.connect(self._tf_frame_ready, Q)
        fw.frameFailed.connect(self._tf_frame_failed, Q)
        io.reportWritten.connect(self._report_written, Q)
        io.historyRead.connect(self._history_read, Q)
        io.frameSaved.connect(self._frame_saved, Q)
        io.failed.connect(self._io_failed, Q)
        io.busyChanged.connect(self._io_busy, Q)
        scw.positionStarted.connect(self._scan_position_started, Q)
        scw.positionDone.connect(self._scan_position_done, Q)
        scw.progress.connect(self._scan_progress, Q)
        scw.event.connect(self._scan_event, Q)
        scw.pausedChanged.connect(self._scan_paused, Q)
        scw.finished.connect(self._scan_finished, Q)
        # threads last, so no signal is missed
        self.threads = {name: WorkerThread(w, name) for name, w in (
            ("camera", cw), ("stage", sw), ("stage-control", sc), ("inspection", iw), ("io", io), ("scan", scw),
            ("frames", fw))}

    # ============================================================================== helpers
    # Worker signals are connected to bound methods of this window only (never to lambdas): a queued
    # call then runs in the GUI thread, where this QObject lives.

    def _device_message(self, text: str) -> None:
        self.log(text, "warning")

    def _frame_saved(self, _job: int, path: str) -> None:
        self.log(f"Saved the frame to {path} (with its .meta.json sidecar).", "ok")

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

    # ============================================================================== camera

    def connect_camera(self, url: str) -> None:
        self.camera_url = url
        self._cam_connect.emit(url)

    def _camera_state(self, state: str, detail: str) -> None:
        self.camera_state = state
        self.camera_panel.set_state(state, detail)
        self.cam_dot.set_state(state, f"camera {state}")
        if state == "connected":
            self.log(f"Camera connected: {detail}.", "ok")
            if self.stage_obj is not None:
                self._cam_attach.emit(self.stage_obj)
        elif state == "error":
            self.log(f"Camera: {detail}", "error")

    def _camera_changed(self, camera: Any) -> None:
        self.camera_obj = camera

    def _camera_settings(self, s: dict) -> None:
        self.camera_panel.set_settings(s)
        cfg = s.get("camera_config")
        if cfg is not None and cfg is not self.camera_cfg:
            self.camera_cfg = cfg
            self._update_config_label()

    def _camera_error(self, text: str) -> None:
        self.camera_panel.error.show_error(text)
        self.log(f"Camera: {text}", "error")

    def set_live(self, on: bool) -> None:
        if on:
            if self.scan_running:
                self.camera_panel.set_live(False)
                return
            self.image.reset_fps()
            self._cam_live_start.emit()
        else:
            self._cam_live_stop.emit()

    def _live_changed(self, on: bool) -> None:
        self.camera_panel.set_live(on)
        if on:
            self.banner.set_state("LIVE", "LIVE", f"Live view from {self.camera_url}.")
        else:
            self.image.info.setText("")
            if self.banner.verdict == "LIVE":
                self._restore_banner()

    def _live_frame(self) -> None:
        frame = self.mailbox.take()
        if frame is None:
            return
        self.image.show_frame(frame.data, live=True)
        self.camera_panel.fps.setText(f"{self.image.fps:.1f} fps · frame #{frame.sequence} · "
                                      f"{frame.exposure_us:,.0f} µs, gain {frame.gain:.2f}")

    def capture_frame(self) -> None:
        self._cam_capture.emit()

    def _frame_captured(self, frame: Any) -> None:
        self.last_frame = frame
        self.image.show_frame(frame.data)
        truth = frame.extra.get("truth") or {}
        where = f" of {truth['array']}" if truth.get("array") else ""
        self.log(f"Captured frame #{frame.sequence}{where}: {frame.width}×{frame.height} px, {frame.bits} bit, "
                 f"{frame.exposure_us:,.0f} µs.")
        self.use_last_frame()

    def use_last_frame(self) -> None:
        if self.last_frame is None:
            self.inspection_panel.error.show_error("No frame has been captured yet; press Capture frame first.")
            return
        self.input = ("frame", self.last_frame)
        self.inspection_panel.source.setText(f"captured frame #{self.last_frame.sequence}")
        self.inspection_panel.error.clear_error()

    def browse_save_frame(self) -> None:
        if self.last_frame is None:
            self.camera_panel.error.show_error("No frame has been captured yet; press Capture frame first.")
            return
        path, _ = QFileDialog.getSaveFileName(self, "Save frame", f"frame_{self.last_frame.sequence:06d}.tiff",
                                              "TIFF (*.tiff);;DNG (*.dng)")
        if path:
            self.save_frame(path)

    def save_frame(self, path: str) -> None:
        self.io_job += 1
        self._save_frame.emit(self.io_job, self.last_frame, path, self.stage_state.get("pos"))

    # ============================================================================== stage

    def connect_stage(self, url: str) -> None:
        self.stage_url = url
        self._stage_connect.emit(url)

    def stop_stage(self) -> None:
        """STOP: always available; the stage-control thread halts the stage at once."""
        self._ctl_stop.emit()
        if self.scan_running:
            self.abort_scan()

    def home_stage(self) -> None:
        self._stage_home.emit()

    def move_stage(self, x_mm: float, y_mm: float) -> None:
        self._stage_move_to.emit(x_mm, y_mm)

    def jog_stage(self, dx_mm: float, dy_mm: float) -> None:
        self._stage_move_by.emit(dx_mm, dy_mm)

    def _stage_state(self, state: str, detail: str) -> None:
        self.stage_panel.set_state(state, detail)
        self.stage_dot.set_state(state, f"stage {state}")
        if state == "connected":
            self.log(f"Stage connected: {detail}.", "ok")
        elif state == "error":
            self.log(f"Stage: {detail}", "error")

    def _stage_changed(self, stage: Any) -> None:
        self.stage_obj = stage
        self._ctl_stage.emit(stage)
        if not self.scan_running:
            self._cam_attach.emit(stage)

    def _stage_info(self, info: dict) -> None:
        self.stage_panel.set_info(info)

    def _stage_position(self, state: dict) -> None:
        self.stage_state = state
        self.stage_panel.set_position(state)
        self.scan_panel.wafer.set_stage_position(state.get("pos"))

    def _stage_error(self, text: str) -> None:
        self.stage_panel.error.show_error(text)
        self.log(f"Stage: {text}", "error")

    # ============================================================================== inspection

    def browse_raw(self) -> None:
        path = self._ask_open("Open raw image", RAW_FILTER)
        if path:
            self.open_raw(path)

    def browse_white(self) -> None:
        path = self._ask_open("Open white image", RAW_FILTER)
        if path:
            self.set_white(path)

    def browse_config(self) -> None:
        path = self._ask_open("Camera config", "Camera config (*.toml);;All files (*)")
        if path:
            self.load_config(path)

    def open_raw(self, path: str, white: str | None = None) -> None:
        """Choose a raw file as the inspection input (and show it)."""
        self.input = ("raw", str(path))
        self.inspection_panel.source.setText(str(path))
        self.inspection_panel.source.setToolTip(str(path))
        self.inspection_panel.error.clear_error()
        if white is not None:
            self.set_white(white)
        self.preview_job += 1
        self._preview.emit(self.preview_job, str(path))

    def set_white(self, path: str | None) -> None:
        self.white = str(path) if path else None
        self.inspection_panel.white.setText(self.white or "none (the image calibrates itself)")

    def browse_darks(self) -> None:
        paths, _ = QFileDialog.getOpenFileNames(self, "Dark frames (lens covered, the frames' exposure and gain)", "",
                                                RAW_FILTER)
        if paths:
            self.set_darks(paths)

    def set_darks(self, paths: Any) -> None:
        """Subtract the master dark of these frames from every inspected image (checked when it runs)."""
        self.darks = tuple(str(p) for p in paths or ())
        names = [Path(p).name for p in self.darks]
        self.inspection_panel.darks.setText(f"{len(names)} frames ({names[0]} …)" if len(names) > 1
                                            else (names[0] if names else "none"))
        self.inspection_panel.darks.setToolTip("\n".join(self.darks))
        self.log(f"Dark frames in use: {len(names)}." if names else "No dark frames: hot pixels are guessed from the image.")

    # ------------------------------------------------------------------ through-focus frames

    def browse_through_focus(self) -> None:
        paths, _ = QFileDialog.getOpenFileNames(self, "Through-focus frames (+u and −u pairs)", "", RAW_FILTER)
        if paths:
            self.set_through_focus(paths)

    def set_through_focus(self, paths: Any) -> int:
        """Use these pinhole frames with the next inspection; the frames worker checks their records, sizes
        and pairs first (a bad set shows one sentence and is not used). Returns the check's job number."""
        paths = tuple(str(p) for p in (paths or ()))
        if not paths:
            self.clear_through_focus()
            return 0
        self.tf_job += 1
        self.tf_pending = paths
        self.inspection_panel.throughfocus.setText(f"checking {len(paths)} frame{'s' if len(paths) != 1 else ''}…")
        self.inspection_panel.throughfocus.setToolTip("\n".join(paths))
        self._describe_tf.emit(self.tf_job, paths, self.cfg)
        return self.tf_job

    def clear_through_focus(self) -> None:
        self.tf_job += 1  # a check still running is stale
        self.tf_pending = None
        self._set_tf_frames(())

    def _set_tf_frames(self, frames: tuple[Any, ...]) -> None:
        self.tf_frames = tuple(frames)
        self.inspection_panel.throughfocus.setText(through_focus_label(self.tf_frames))
        self.inspection_panel.throughfocus.setToolTip("\n".join(f.label for f in self.tf_frames))
        self.throughFocusChanged.emit(self.tf_frames)

    def _tf_described(self, job: int, frames: Any) -> None:
        if job != self.tf_job:
            return
        self.tf_pending = None
        self.inspection_panel.error.clear_error()
        self._set_tf_frames(frames)
        self.log(f"Through-focus frames in use: {through_focus_label(self.tf_frames)}.")

    def _tf_failed(self, job: int, text: str) -> None:
        if job != self.tf_job:
            return
        self.tf_pending = None
        self._set_tf_frames(())
        self.inspection_panel.error.show_error(text)
        self.log(f"Through-focus frames not used: {text}", "error")

    def show_frame_choice(self, index: int) -> int:
        """Show entry `index` of the frame selector: 0 the inspected frame, k the k-th through-focus frame
        (loaded and prepared in the frames worker; `frameShown` tells when it is on display). Returns the
        load's job number (0 when nothing had to be loaded)."""
        v = self.view
        if v is None or not 0 <= index <= len(v.frames):
            return 0
        on_result = self.image.mode == "result" and self.image.view is v
        if index == 0:
            self.frame_job += 1  # a frame still loading is no longer wanted
            if not (on_result and self.image.frame_index == 0):
                self.image.show_result(v)  # (rings and the selected lens stay)
            self.frameShown.emit(0)
            return 0
        if not on_result:
            self.image.show_result(v)
        path = v.frames[index - 1].path
        self.frame_job += 1
        hit = self.frame_cache.get(path)
        if hit is not None:
            self.frame_cache.move_to_end(path)
            self._display_tf_frame(index, *hit)
            return 0
        self.image.info.setText("loading…")
        self._load_tf_frame.emit(self.frame_job, path, v.cfg)
        return self.frame_job

    FRAME_CACHE = 4  # prepared through-focus frames kept for the selector (16 MB each for Table 1)

    def _tf_frame_ready(self, job: int, path: str, data: Any, levels: Any) -> None:
        v = self.view
        if job != self.frame_job or v is None:
            return
        index = next((k + 1 for k, f in enumerate(v.frames) if f.path == path), 0)
        if not index:
            return
        self.frame_cache[path] = (data, levels)
        while len(self.frame_cache) > self.FRAME_CACHE:
            self.frame_cache.popitem(last=False)
        self._display_tf_frame(index, data, levels)

    def _display_tf_frame(self, index: int, data: Any, levels: Any) -> None:
        self.image.show_result_frame(index, data, levels)
        self.frameShown.emit(index)

    def _tf_frame_failed(self, job: int, text: str) -> None:
        if job != self.frame_job:
            return
        self.image.info.setText("")
        self.image.set_frame_index(self.image.frame_index)
        self.inspection_panel.error.show_error(text)
        self.log(text, "error")

    def load_config(self, path: str) -> bool:
        from mlaqc.optics.config import load_config

        try:
            self.cfg_explicit = load_config(path)
        except InputError as exc:
            self.inspection_panel.error.show_error(str(exc))
            self.log(str(exc), "error")
            return False
        self.cfg_path = str(path)
        self._update_config_label()
        self.log(f"Camera config {path} loaded.")
        return True

    def _preview_ready(self, job: int, data: Any) -> None:
        if job == self.preview_job and not self._busy_inspecting():
            self.image.show_frame(data)

    def _preview_failed(self, job: int, text: str) -> None:
        if job == self.preview_job:
            self.inspection_panel.error.show_error(text)
            self.log(text, "error")

    def _busy_inspecting(self) -> bool:
        return self.token is not None

    def run_inspection(self) -> int:
        """Start calibration + inspection of the chosen input in the worker; returns the job number."""
        if self.input is None:
            self.inspection_panel.error.show_error("Nothing to inspect: open a raw file or capture a frame first.")
            return 0
        if self.token is not None:
            self.token.cancel()
        self.job += 1
        self.token = CancelToken()
        kind, what = self.input
        tf = self.tf_pending if self.tf_pending is not None else tuple(f.path for f in self.tf_frames)
        req = InspectionRequest(self.cfg, raw=what if kind == "raw" else None, frame=what if kind == "frame" else None,
                                white=self.white, token=self.token, through_focus=tf, darks=self.darks)
        self.inspection_panel.error.clear_error()
        self.inspection_panel.set_running(True)
        self.inspection_panel.progress.setValue(0)
        self.banner.set_state("BUSY", "INSPECTING", "Calibrating the grid and measuring every lens…")
        self._inspect.emit(self.job, req)
        return self.job

    def cancel_inspection(self) -> None:
        if self.token is not None:
            self.token.cancel()
            self.token = None
            self.job += 1  # whatever the worker still delivers is stale
            self.inspection_panel.set_running(False)
            self.inspection_panel.status.setText("Cancelled.")
            self.inspection_panel.progress.setValue(0)
            self._restore_banner()
            self.log("Inspection cancelled.", "warning")

    def _inspection_progress(self, job: int, pct: int, text: str) -> None:
        if job == self.job:
            self.inspection_panel.progress.setValue(pct)
            self.inspection_panel.status.setText(text[:1].upper() + text[1:] + "…" if pct < 100 else "Done.")

    def _inspection_finished(self, job: int, view: Any) -> None:
        if job != self.job:
            return
        self.token = None
        self.inspection_panel.set_running(False)
        self.show_inspection(view)

    def show_inspection(self, view: Any) -> None:
        """Display an inspection result: image + rings, verdict, table, first lens selected."""
        self.view = view
        r = view.result
        self.frame_job += 1  # a through-focus frame of the previous result is no longer wanted
        self.frame_cache.clear()
        self.image.clear_result()
        self.image.show_result(view)
        self.image.set_frames([f"White frame · {Path(view.source).name}"] + [f.label for f in view.frames])
        self.table_model.set_defects(r.defects, view.sources)
        self.table.sortByColumn(-1, Qt.SortOrder.AscendingOrder)
        self.table.resizeColumnsToContents()
        out = sum(1 for d in r.defects if not d.within_tolerance)
        tf_line = ""
        if getattr(r, "through_focus", None) is not None:
            pinholes = sum(1 for s in view.sources.values() if "pinholes" in s)
            tf_line = (f"<br><span style='color:#6639ba'>{through_focus_summary(r.through_focus)}; {pinholes} flagged "
                       "lens(es) read by the pinhole pairs (Source column)</span>")
        self.table_title.setText(f"<b>{len(r.defects)}</b> flagged lenses, <b style='color:#cf222e'>{out}</b> out of "
                                 f"tolerance — click a row to zoom to the lens; click a header to sort.{tf_line}")
        self._restore_banner()
        self.inspection_panel.export.setEnabled(True)
        t = ", ".join(f"{k} {v:.2f} s" for k, v in r.timings_s.items())
        assembly = getattr(r, "assembly", None)  # the array's placement, on its own line
        placed = f"\n{assembly.short_text()}" if assembly is not None else ""
        self.inspection_panel.status.setText(f"Done in {view.elapsed_s:.2f} s ({t}).{placed}")
        self.inspection_panel.status.setToolTip(assembly.summary_line().strip() if assembly is not None else "")
        self.lens_detail.clear()
        if r.defects:
            first = self.table_model.defects[0]
            self.select_lens(first.m, first.n)
        self.log(f"{r.verdict}: {view.summary} — {view.source}", "ok" if r.verdict == "PASS" else "warning")
        self.inspectionShown.emit(view)

    def _restore_banner(self) -> None:
        v = self.view
        if v is None:
            self.banner.set_state("IDLE", "NO RESULT", "Open a raw file or capture a frame, then run the inspection.")
            return
        r = v.result
        types = sorted({d.error_type for d in r.defects})
        self.banner.set_state(r.verdict, r.verdict, v.headline, types, detail=f"{v.detail} · {Path(v.source).name}")

    def _inspection_failed(self, job: int, text: str) -> None:
        if job != self.job:
            return
        self.token = None
        self.inspection_panel.set_running(False)
        self.inspection_panel.progress.setValue(0)
        self.inspection_panel.status.setText("")
        self.inspection_panel.error.show_error(text)
        self.banner.set_state("ERROR", "ERROR", text)
        self.log(f"Inspection: {text}", "error")

    def _inspection_cancelled(self, job: int) -> None:
        pass  # the GUI already moved on when Cancel was pressed

    # ------------------------------------------------------------------ lens selection

    def select_lens(self, m: int, n: int, *, zoom: bool = False) -> None:
        """Show lens U(m,n) in the detail panel, mark it on the image, select its table row."""
        if self.view is None:
            return
        rows, cols = self.view.result.grid.rows, self.view.result.grid.cols
        if not (1 <= m <= rows and 1 <= n <= cols):
            return
        if self.image.mode != "result":
            self.image.show_result(self.view)
        self.lens_detail.show_lens(self.view, m, n)
        self.image.select(m, n, zoom=zoom)
        row = self.table_model.row_of(m, n)
        sel = self.table.selectionModel()
        if row >= 0:
            proxy_index = self.table_proxy.mapFromSource(self.table_model.index(row, 0))
            if self.table.currentIndex().row() != proxy_index.row():
                sel.blockSignals(True)
                self.table.setCurrentIndex(proxy_index)
                sel.select(proxy_index, QItemSelectionModel.SelectionFlag.ClearAndSelect
                           | QItemSelectionModel.SelectionFlag.Rows)
                sel.blockSignals(False)
                self.table.viewport().update()
                self.table.scrollTo(proxy_index)
        else:
            sel.clearSelection()

    def _table_clicked(self, index: QModelIndex) -> None:
        if not index.isValid():
            return
        lens = self.table_proxy.data(index.siblingAtColumn(0), DefectTableModel.LENS_ROLE)
        if lens:
            self.select_lens(*lens, zoom=True)

    def _table_current_changed(self, index: QModelIndex) -> None:
        """Keyboard navigation in the table (a re-sort keeps the same lens: no jump)."""
        if index.isValid():
            lens = self.table_proxy.data(index.siblingAtColumn(0), DefectTableModel.LENS_ROLE)
            if lens and tuple(lens) != self.lens_detail.lens:
                self.select_lens(*lens, zoom=True)

    def _image_clicked(self, x: float, y: float) -> None:
        if self.view is None or self.image.mode != "result":
            return
        lens = self.view.lens_at(x, y)
        if lens is not None:
            self.select_lens(*lens)

    def _hovered(self, x: float, y: float, value: Any) -> None:
        parts = [f"x {x:8.2f}  y {y:8.2f} px"]
        if value is not None:
            parts.append(f"value {value:.5g}")
        if self.view is not None and self.image.data is not None and self.image.data.shape == self.view.result.image.shape:
            lens = self.view.lens_at(x, y)
            if lens is not None:
                m, n = lens
                d = next((d for d in self.view.result.defects if (d.m, d.n) == lens), None)
                parts.append(f"U({m},{n})  row {m}, col {n}" + (f"  ← {d.error_type} {d.magnitude:.3g} {d.unit}"
                                                                 if d is not None else ""))
        self.cursor_label.setText("   │   ".join(parts))

    # ------------------------------------------------------------------ report export

    def browse_export(self) -> None:
        if self.view is None:
            self.inspection_panel.error.show_error("There is no inspection result to export yet.")
            return
        path = QFileDialog.getExistingDirectory(self, "Report folder")
        if path:
            self.export_report(path)

    def export_report(self, out_dir: str) -> int:
        """Write the report set of the result on display (in the io worker); returns the job number."""
        if self.view is None:
            self.inspection_panel.error.show_error("There is no inspection result to export yet.")
            return 0
        self.io_job += 1
        cfg = self.view.cfg
        self._write_report.emit(self.io_job, self.view.result, str(out_dir), cfg.to_dict() if cfg is not None else None)
        self.inspection_panel.status.setText(f"Writing the report to {out_dir}…")
        return self.io_job

    def _report_written(self, job: int, paths: dict) -> None:
        self.inspection_panel.status.setText(f"Report written: {paths.get('html', '')}")
        self.log(f"Report written to {Path(paths.get('json', '')).parent} (open report.html).", "ok")
        self.reportWritten.emit(paths)

    def _io_failed(self, job: int, text: str) -> None:
        if job == self._history_job:
            self.history_panel.show_error(text)
        else:
            self.inspection_panel.error.show_error(text)
        self.log(text, "error")

    def read_history(self, lot: str) -> None:
        """Ask the io worker for a lot's arrays (the history panel shows them)."""
        self.io_job += 1
        self._history_job = self.io_job
        self._read_history.emit(self.io_job, lot)

    def _history_read(self, job: int, data: dict) -> None:
        self.history_panel.show_history(data)
        self.historyShown.emit(data)

    def _io_busy(self, busy: bool) -> None:
        self.io_busy = busy

    # ============================================================================== scans

    def browse_plan(self) -> None:
        path = self._ask_open("Scan plan", "Scan plan (*.toml);;All files (*)")
        if path:
            self.load_plan(path)

    def browse_scan_out(self) -> None:
        path = QFileDialog.getExistingDirectory(self, "Scan output folder")
        if path:
            self.scan_panel.out.setText(path)

    def edit_plan(self) -> None:
        """Open the plan editor on the loaded plan's text (or the raster example) and apply the result."""
        from gui.plan_editor import TEMPLATE, PlanEditor

        text = self.scan_plan_text
        if text is None:
            try:
                text = Path(self.scan_plan_path or TEMPLATE).read_text(encoding="utf-8")
            except OSError:
                text = ""
        dialog = PlanEditor(text, self)
        if dialog.exec():
            self.apply_plan_text(dialog.text.toPlainText())

    def apply_plan_text(self, text: str, label: str = "edited plan") -> bool:
        """Use TOML text as the scan plan (after the runner's own validation); False with the error shown."""
        from gui.plan_editor import parse_plan_text

        try:
            plan = parse_plan_text(text, label)
        except InputError as exc:
            self.scan_panel.error.show_error(str(exc))
            self.log(str(exc), "error")
            return False
        self._set_plan(plan, label)
        self.scan_plan_text = text
        return True

    def load_plan(self, path: str) -> bool:
        from drivers.scan_plan import load_plan

        try:
            plan = load_plan(path)
        except InputError as exc:
            self.scan_panel.error.show_error(str(exc))
            self.log(str(exc), "error")
            return False
        self.scan_plan_text = None
        self._set_plan(plan, str(path))
        return True

    def _set_plan(self, plan: Any, path: str) -> None:
        """Show a plan (loaded or edited) in the scan panel and the wafer map."""
        self.scan_plan, self.scan_plan_path = plan, (path if Path(path).suffix == ".toml" else None)
        self.scan_panel.error.clear_error()
        n = len(plan.positions)
        self.scan_panel.plan.setText(f"{Path(path).name}: {plan.kind}, {n} position{'s' if n != 1 else ''}, "
                                     f"{plan.frames_per_position} frame(s) × average {plan.average}")
        self.scan_panel.wafer.set_plan([(p.x_mm, p.y_mm, p.label) for p in plan.positions])
        self.scan_panel.progress.setRange(0, n)
        self.scan_panel.progress.setFormat("%v / %m positions")
        self.scan_panel.progress.setValue(0)
        self.scan_files = {}
        self.can_resume = False
        self._scan_buttons()
        self.log(f"Scan plan {path} in use ({n} positions).")

    def _scan_buttons(self) -> None:
        self.scan_panel.set_running(self.scan_running, can_resume=self.can_resume, has_plan=self.scan_plan is not None)

    def start_scan(self, out_dir: str | None = None, *, resume: bool = False) -> bool:
        """Run the loaded plan with the connected camera and stage (borrowed from their panels)."""
        sp = self.scan_panel
        if self.scan_running:
            return False
        if self.scan_plan is None:
            sp.error.show_error("Load a scan plan first.")
            return False
        if self.camera_obj is None or self.stage_obj is None:
            sp.error.show_error("Connect the camera and the stage before scanning.")
            return False
        if resume:
            out = self.scan_out
        else:
            out = out_dir or sp.out.text().strip() or str(Path.home() / "mlaqc-scans" / time.strftime("scan-%Y%m%d-%H%M%S"))
            if not out_dir and not sp.out.text().strip():
                Path(out).parent.mkdir(parents=True, exist_ok=True)
        if not out:
            sp.error.show_error("Choose an output folder for the scan.")
            return False
        sp.out.setText(out)
        self.scan_out = out
        sp.error.clear_error()
        self._cam_live_stop.emit()
        self.scan_control = ScanControl()
        self.scan_running = True
        self.scan_current = None
        self.camera_panel.set_locked(True)
        self.stage_panel.set_locked(True)
        self._stage_lent.emit(True)
        if not resume:
            self.scan_panel.wafer.set_plan([(p.x_mm, p.y_mm, p.label) for p in self.scan_plan.positions])
            self.scan_files = {}
        self._scan_buttons()
        sp.status.setText("Starting (homing the stage if needed)…")
        req = ScanRequest(self.scan_plan, out, self.camera_obj, self.stage_obj,
                          cfg=self.cfg if sp.inspect.isChecked() else None, resume=resume, control=self.scan_control)
        self._scan.emit(req)
        self.log(f"Scan {'resumed' if resume else 'started'}: {self.scan_plan_path or 'edited plan'} → {out}")
        return True

    def pause_scan(self, on: bool) -> None:
        if self.scan_control is None:
            return
        if on:
            self.scan_control.pause()
            self.scan_panel.status.setText("Pausing after the current position…")
        else:
            self.scan_control.resume()
            self.scan_panel.status.setText("Running…")

    def abort_scan(self) -> None:
        """Abort: the scan stops at once and the stage is halted."""
        if self.scan_control is None or not self.scan_running:
            return
        self.scan_control.abort()
        self._ctl_stop.emit()
        self.scan_panel.status.setText("Aborting — stopping the stage…")

    def _scan_position_started(self, index: int) -> None:
        self.scan_current = index
        self.scan_panel.wafer.set_status(index, "current")
        p = self.scan_plan.positions[index]
        self.scan_panel.status.setText(f"Position {index + 1}/{len(self.scan_plan.positions)}: {p.label} "
                                       f"({p.x_mm:g}, {p.y_mm:g}) mm")

    def _scan_position_done(self, index: int, info: dict) -> None:
        verdict = info.get("verdict")
        status = verdict if verdict in ("PASS", "FAIL", "ERROR") else "captured"
        self.scan_panel.wafer.set_status(index, status, info)
        self.scan_files[index] = info.get("file", "")
        if self.scan_current == index:
            self.scan_current = None

    def _scan_progress(self, done: int, total: int) -> None:
        self.scan_panel.progress.setRange(0, total)
        self.scan_panel.progress.setValue(done)

    def _scan_event(self, ev: dict) -> None:
        kind = ev.get("event")
        if kind in ("device_error", "inspect_failed", "frame_warning", "frame_rejected", "position_failed", "failed"):
            text = ev.get("error") or ev.get("warning") or ev.get("reason") or ev.get("message") or str(ev)
            self.log(f"Scan {kind.replace('_', ' ')}: {text}", "warning")
        elif kind in ("reconnect",):
            self.log(f"Scan: reconnecting the {ev.get('device')}.", "warning")

    def _scan_paused(self, paused: bool) -> None:
        if paused:
            self.scan_panel.status.setText("Paused between positions — press Continue.")

    def _scan_finished(self, outcome: str, message: str) -> None:
        message = message.replace("rerun with --resume to continue", "press Resume to continue")
        self.scan_running = False
        if self.scan_current is not None:
            self.scan_panel.wafer.set_status(self.scan_current, "failed" if outcome == "failed" else "pending")
            self.scan_current = None
        self.camera_panel.set_locked(False)
        self.stage_panel.set_locked(False)
        self._stage_lent.emit(False)
        if self.stage_obj is not None:
            self._cam_attach.emit(self.stage_obj)  # the runner detached its own link on exit
        self._cam_read.emit()
        self.can_resume = outcome != "finished"
        self._scan_buttons()
        c = self.scan_panel.wafer.counts()
        tally = ", ".join(f"{k} {v}" for k, v in sorted(c.items()))
        if outcome == "finished":
            self.scan_panel.status.setText(f"Finished — {tally}.")
            self.log(message, "ok")
        else:
            self.scan_panel.status.setText(f"Scan {outcome} — {tally}.")
            self.scan_panel.error.show_error(message)
            self.log(message, "error" if outcome == "failed" else "warning")
        self.scanFinished.emit(outcome, message)

    def _wafer_clicked(self, index: int) -> None:
        path = self.scan_files.get(index)
        if path and Path(path).exists():
            self.open_raw(path)
            self.log(f"Opened scan position {index + 1}: {path} — press Inspect for its full result.")

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
