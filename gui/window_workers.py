"""The main window's worker threads: creating them and connecting requests and results across threads (queued)."""

from __future__ import annotations

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtCore import Qt

from gui.inspection_worker import FrameWorker, InspectionWorker
from gui.scan_worker import ScanWorker
from gui.workers import CameraWorker, IoWorker, StageControl, StageWorker, WorkerThread

Q = Qt.ConnectionType.QueuedConnection


class WorkerWiringMixin:
    """Part of gui.app.MainWindow: starts the workers (threading model: gui.workers).

    Worker signals are connected to bound methods of the window only (never to lambdas): a queued
    call then runs in the GUI thread, where the window lives.
    """

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
