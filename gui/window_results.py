"""The main window's inspection runs and their display: verdict, flagged-lens table, frame selector, lens selection."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtCore import QItemSelectionModel, QModelIndex, Qt

from gui.inspection_worker import CancelToken, InspectionRequest, through_focus_summary
from gui.widgets import DefectTableModel


class InspectionResultsMixin:
    """Part of gui.app.MainWindow: runs and cancels inspections in the worker and shows their results."""

    # ------------------------------------------------------------------ running an inspection

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

    # ------------------------------------------------------------------ frame selector

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
