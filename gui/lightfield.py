"""The light-field panel: the decoded views of the frame the app inspected (or of a scene frame, divided by
that white), one view at a time (two sliders: the pupil point) or refocused (a slope slider). Decoding
and refocusing run in the panel's own worker thread (`DecodeWorker`); the panel only shows what it hands
back, so a 2048² frame never blocks the window.

On the white frame itself a view shows each lens' light through one pupil point: a lens whose sub-image
moved (pitch, decenter, tilt) stands out in the outer views on the calibrated lattice, and evens out when
sampled as the inspection measured it."""

from __future__ import annotations

from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QObject, Qt, Signal, Slot
from PySide6.QtWidgets import (QComboBox, QFileDialog, QGridLayout, QHBoxLayout, QLabel, QPushButton, QSlider,
                               QVBoxLayout, QWidget)

from gui.widgets import ErrorLabel
from gui.workers import WorkerThread

SLOPE_STEP = 0.01  # lenses per view pixel, one refocus slider step


class DecodeWorker(QObject):
    """Decodes and refocuses off the GUI thread; every answer carries the job it answers."""

    decoded = Signal(int, object)  # job, LightField
    refocused = Signal(int, float, object)  # job, slope, image
    failed = Signal(int, str)

    def __init__(self) -> None:
        super().__init__()
        self.lf: Any = None

    @Slot(int, object)
    def decode(self, job: int, req: dict) -> None:
        try:
            self.lf = decode_request(req)
            self.decoded.emit(job, self.lf)
        except Exception as exc:  # noqa: BLE001 - any failure is one sentence in the panel
            self.failed.emit(job, _sentence(exc))

    @Slot(int, float)
    def refocus(self, job: int, slope: float) -> None:
        from mlaqc.decode.lightfield import refocus

        if self.lf is None:
            return
        try:
            self.refocused.emit(job, slope, refocus(self.lf, slope)[0])
        except Exception as exc:  # noqa: BLE001
            self.failed.emit(job, _sentence(exc))


def _sentence(exc: BaseException) -> str:
    text = str(exc).strip() or exc.__class__.__name__
    return text if text.endswith(".") else text + "."


def decode_request(req: dict) -> Any:
    """The light field a request asks for: {'image', 'white' (or None), 'grid', 'defects', 'measured',
    'scene_path', 'cfg'}; a scene is loaded here and divided by the white."""
    from mlaqc.decode import sampling as smp
    from mlaqc.decode.lightfield import rectangular, view_offsets
    from mlaqc.decode.scene import decode_scene

    grid = req["grid"]
    report = {"defects": [{"row": d.m, "col": d.n, "error_type": d.error_type} for d in req["defects"]]}
    sampling = smp.measured_sampling(grid, report) if req["measured"] else smp.lattice_sampling(grid)
    offsets = view_offsets(sampling.radius_px)
    white = np.asarray(req["image"], np.float32)
    if not req.get("scene_path"):
        return rectangular(decode_scene(white, sampling, offsets))
    from mlaqc.decode.frames import load_decode_frame

    scene = load_decode_frame(req["scene_path"], req["cfg"])
    scene = scene.mean(axis=2) if scene.ndim == 3 else scene  # the inspected frame is a luminance
    return rectangular(decode_scene(scene, sampling, offsets, white, req["scene_path"]))


class LightFieldPanel(QWidget):
    """View and refocus sliders over a decoded light field; `set_inspection` arms it after an inspection."""

    _decode = Signal(int, object)
    _refocus = Signal(int, float)

    def __init__(self) -> None:
        super().__init__()
        self.job = 0
        self.lf: Any = None
        self.source: dict[str, Any] | None = None
        self.worker = DecodeWorker()
        self.thread: WorkerThread | None = None
        self.decode_btn = QPushButton("Decode the inspected frame")
        self.scene_btn = QPushButton("Scene raw…")
        self.scene_btn.setToolTip("decode a scene frame of this array and set-up, divided by the inspected white")
        self.sampling = QComboBox()
        self.sampling.addItems(["as measured (flagged lenses at their centres)", "calibrated lattice"])
        self.mode = QComboBox()
        self.mode.addItems(["one view", "refocused"])
        self.u = _slider()
        self.v = _slider()
        self.slope = _slider()
        self.slope.setRange(-100, 100)
        self.status = QLabel("Run an inspection, then decode its frame here.")
        self.status.setWordWrap(True)
        self.error = ErrorLabel()
        self.glw = pg.GraphicsLayoutWidget()
        self.vb = pg.ViewBox(lockAspect=True, invertY=True, enableMenu=False)
        self.glw.addItem(self.vb)
        self.img = pg.ImageItem()
        self.vb.addItem(self.img)
        for w in (self.decode_btn, self.scene_btn):
            w.setEnabled(False)
        top = QHBoxLayout()
        top.addWidget(self.decode_btn)
        top.addWidget(self.scene_btn)
        top.addWidget(self.sampling, 1)
        grid = QGridLayout()
        for row, (text, widget) in enumerate((("show", self.mode), ("view u", self.u), ("view v", self.v),
                                               ("refocus slope", self.slope))):
            grid.addWidget(QLabel(text), row, 0)
            grid.addWidget(widget, row, 1)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(4, 4, 4, 4)
        lay.addLayout(top)
        lay.addLayout(grid)
        lay.addWidget(self.status)
        lay.addWidget(self.error)
        lay.addWidget(self.glw, 1)
        self.decode_btn.clicked.connect(lambda: self.request_decode(None))
        self.scene_btn.clicked.connect(self._browse_scene)
        for s in (self.u, self.v):
            s.valueChanged.connect(self._show_view)
        self.slope.valueChanged.connect(self._ask_refocus)
        self.mode.currentIndexChanged.connect(self._mode_changed)

    # ------------------------------------------------------------------ worker

    def _ensure_thread(self) -> None:
        if self.thread is None:
            self.thread = WorkerThread(self.worker, "lightfield")
            self._decode.connect(self.worker.decode)
            self._refocus.connect(self.worker.refocus)
            self.worker.decoded.connect(self._decoded)
            self.worker.refocused.connect(self._refocused)
            self.worker.failed.connect(self._failed)

    def shutdown(self) -> None:
        """Join the worker thread (after any decode it is running); idempotent."""
        if self.thread is not None:
            self.thread.stop(60.0)
            self.thread = None

    # ------------------------------------------------------------------ requests

    def set_inspection(self, view: Any, cfg: Any) -> None:
        """Arm the panel with an inspection's frame, grid and flags (no decoding until asked)."""
        r = view.result
        self.source = {"image": r.image, "grid": r.grid, "defects": tuple(r.defects), "cfg": cfg}
        self.decode_btn.setEnabled(True)
        self.scene_btn.setEnabled(True)
        self.status.setText(f"Ready: {len(r.defects)} flagged lenses; decode the inspected frame or a scene frame.")

    def request_decode(self, scene_path: str | None) -> int:
        """Ask the worker for a light field; returns the job number (0: nothing to decode)."""
        if self.source is None:
            return 0
        self._ensure_thread()
        self.job += 1
        self.error.clear_error()
        self.status.setText("Decoding…")
        req = {**self.source, "measured": self.sampling.currentIndex() == 0, "scene_path": scene_path}
        self._decode.emit(self.job, req)
        return self.job

    def _browse_scene(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Scene raw", "", "Raw images (*.dng *.tif *.tiff *.png *.npy);;All (*)")
        if path:
            self.request_decode(path)

    # ------------------------------------------------------------------ answers

    def _decoded(self, job: int, lf: Any) -> None:
        if job != self.job:
            return
        self.lf = lf
        half = len(lf.view_offsets_px) // 2
        for s in (self.u, self.v):
            s.blockSignals(True)
            s.setRange(-half, half)
            s.setValue(0)
            s.blockSignals(False)
        nv, nu, rows, cols = lf.weights.shape
        kind = "devignetted scene" if lf.devignetted else "frame as it is"
        self.status.setText(f"{nv}x{nu} views of {cols}x{rows} lenses ({lf.packing}, {kind}).")
        self._mode_changed()

    def _failed(self, job: int, text: str) -> None:
        if job == self.job:
            self.status.setText("")
            self.error.show_error(text)

    def _mode_changed(self) -> None:
        if self.mode.currentIndex() == 0:
            self._show_view()
        else:
            self._ask_refocus()

    def _show_view(self) -> None:
        if self.lf is None or self.mode.currentIndex() != 0:
            return
        half = len(self.lf.view_offsets_px) // 2
        j, i = self.v.value() + half, self.u.value() + half
        shown = np.where(self.lf.weights[j, i] > 0, self.lf.values[j, i], np.nan)
        self._show(shown)

    def _ask_refocus(self) -> None:
        if self.lf is None or self.mode.currentIndex() != 1:
            return
        self._refocus.emit(self.job, self.slope.value() * SLOPE_STEP)

    def _refocused(self, job: int, slope: float, image: Any) -> None:
        if job == self.job and self.mode.currentIndex() == 1 and abs(slope - self.slope.value() * SLOPE_STEP) < 1e-9:
            self._show(image)

    def _show(self, image: np.ndarray) -> None:
        finite = image[np.isfinite(image)]
        lo, hi = (float(np.percentile(finite, 0.5)), float(np.percentile(finite, 99.5))) if finite.size else (0.0, 1.0)
        self.img.setImage(np.nan_to_num(image, nan=lo), levels=(lo, hi if hi > lo else lo + 1.0))


def _slider() -> QSlider:
    s = QSlider(Qt.Orientation.Horizontal)
    s.setRange(0, 0)
    return s
