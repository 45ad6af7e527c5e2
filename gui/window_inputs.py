"""The main window's inspection inputs: raw file, white, dark and through-focus frames, camera config, preview."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtWidgets import QFileDialog

from gui.inspection_worker import through_focus_label
from mlaqc.errors import InputError

RAW_FILTER = "Raw images (*.dng *.DNG *.tif *.tiff *.png *.npy *.nef *.cr2 *.arw *.raf *.orf *.rw2);;All files (*)"


class InspectionInputsMixin:
    """Part of gui.app.MainWindow: what the next inspection reads (frames checked in the frames worker)."""

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

    # ------------------------------------------------------------------ config and preview

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
