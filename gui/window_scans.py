"""The main window's scans: plan loading and editing, start/pause/abort/resume, progress and the wafer map."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtWidgets import QFileDialog

from gui.scan_worker import ScanControl, ScanRequest
from mlaqc.errors import InputError


class ScansMixin:
    """Part of gui.app.MainWindow: runs scan plans in the scan worker with the window's camera and stage."""

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
