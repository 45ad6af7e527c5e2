"""The main window's io-worker jobs: report export, saved frames, and the lot history read from the results database."""

from __future__ import annotations

from pathlib import Path

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtWidgets import QFileDialog


class ReportsHistoryMixin:
    """Part of gui.app.MainWindow: asks the io worker for writes and the lot history and shows its answers."""

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

    def _frame_saved(self, _job: int, path: str) -> None:
        self.log(f"Saved the frame to {path} (with its .meta.json sidecar).", "ok")

    def _io_failed(self, job: int, text: str) -> None:
        if job == self._history_job:
            self.history_panel.show_error(text)
        else:
            self.inspection_panel.error.show_error(text)
        self.log(text, "error")

    # ------------------------------------------------------------------ lot history

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
