"""The main window's camera and stage: connecting, live view, capture and frame saving, jog/home/STOP, device states."""

from __future__ import annotations

from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtWidgets import QFileDialog


class DevicesMixin:
    """Part of gui.app.MainWindow: requests to the camera and stage workers and their answers."""

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

    def _device_message(self, text: str) -> None:
        self.log(text, "warning")
