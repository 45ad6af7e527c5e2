"""Widgets of the QC app: image view with overlays, verdict banner, defect table, lens detail, wafer map, log.

Nothing here blocks or computes much: every widget draws data a worker prepared (gui.workers,
gui.inspection_worker).
Pixel coordinates follow the core's convention: (0, 0) is the centre of the top-left pixel, x right,
y down; lens U(m,n) is row m from the top, column n from the left (1-based). On a hex array (even rows
half a pitch right, mlaqc.optics.lattice) the grid overlay, the defect rings and the selection are the
lenses' hexagonal cells, laid on the image by the worker (gui.inspection_worker.hex_overlay); circular lens
apertures (mla.aperture = 'circle') are drawn in the grid overlay too, so the gaps between them show.
"""

from __future__ import annotations

import math
import time
from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QAbstractTableModel, QModelIndex, QPointF, QRectF, QSortFilterProxyModel, Qt, Signal
from PySide6.QtGui import QBrush, QColor, QFont, QPainterPath, QPen, QPolygonF, QTransform
from PySide6.QtWidgets import (QCheckBox, QComboBox, QGraphicsPolygonItem, QGraphicsRectItem, QHBoxLayout,
                               QHeaderView, QLabel,
                               QPlainTextEdit, QPushButton, QSizePolicy, QTableWidget, QTableWidgetItem, QVBoxLayout,
                               QWidget)

from mlaqc.report import ERROR_COLOURS, VERDICT_COLOURS, error_colour
from mlaqc.inspection.combine import SOURCE_KEY as TF_SOURCE_KEY
from mlaqc.inspection.results import METRICS

pg.setConfigOptions(imageAxisOrder="row-major", antialias=True)

MONO = QFont("DejaVu Sans Mono")
MONO.setStyleHint(QFont.StyleHint.Monospace)


def qcolor(rgb: tuple[int, int, int], alpha: int = 255) -> QColor:
    return QColor(rgb[0], rgb[1], rgb[2], alpha)


def hex_colour(rgb: tuple[int, int, int]) -> str:
    return f"#{rgb[0]:02x}{rgb[1]:02x}{rgb[2]:02x}"


# ====================================================================================== small widgets


class StatusDot(QLabel):
    """A coloured dot and a word: the connection state of a device."""

    COLOURS = {"connected": "#1a7f37", "connecting": "#bf8700", "disconnected": "#8c959f", "error": "#cf222e",
               "busy": "#0969da"}

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.state = ""
        self.set_state("disconnected")

    def set_state(self, state: str, text: str | None = None) -> None:
        self.state = state
        colour = self.COLOURS.get(state, "#8c959f")
        self.setText(f"<span style='color:{colour}; font-size:14pt'>●</span>&nbsp;<b>{text or state}</b>")


class ErrorLabel(QLabel):
    """One sentence in red under a panel (empty = hidden)."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setWordWrap(True)
        self.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.setStyleSheet("QLabel { color: #cf222e; background: #ffebe9; border: 1px solid #ff8182;"
                           " border-radius: 4px; padding: 4px; }")
        self.hide()

    def show_error(self, text: str) -> None:
        self.setText(text)
        self.setVisible(bool(text))

    def clear_error(self) -> None:
        self.show_error("")


class VerdictBanner(QWidget):
    """The PASS/FAIL banner over the image: big verdict word, one summary line, the colour legend."""

    STATES = {"PASS": hex_colour(VERDICT_COLOURS["PASS"]), "FAIL": hex_colour(VERDICT_COLOURS["FAIL"]),
              "IDLE": "#57606a", "BUSY": "#0969da", "LIVE": "#6639ba", "ERROR": "#9a6700"}

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setAutoFillBackground(True)
        lay = QHBoxLayout(self)
        lay.setContentsMargins(16, 6, 16, 6)
        self.word = QLabel()
        f = QFont()
        f.setPointSize(26)
        f.setBold(True)
        self.word.setFont(f)
        self.word.setMinimumWidth(150)
        self.text = QLabel()
        self.text.setWordWrap(True)
        self.text.setTextFormat(Qt.TextFormat.RichText)
        self.legend = QLabel()
        self.legend.setTextFormat(Qt.TextFormat.RichText)
        lay.addWidget(self.word)
        lay.addWidget(self.text, 1)
        lay.addWidget(self.legend)
        self.setSizePolicy(QSizePolicy.Policy.Preferred, QSizePolicy.Policy.Fixed)
        self.setFixedHeight(78)  # a state change must never resize (and so re-render) the image below
        self.verdict = "IDLE"
        self.set_state("IDLE", "NO RESULT", "Open a raw file or capture a frame, then run the inspection.")

    def set_state(self, state: str, word: str, text: str, legend_types: list[str] | None = None, *,
                  detail: str = "") -> None:
        self.verdict = state
        colour = self.STATES.get(state, "#57606a")
        self.setStyleSheet(f"VerdictBanner {{ background: {colour}; border-radius: 6px; }}"
                           " QLabel { color: white; background: transparent; }")
        self.word.setText(word)
        self.headline = text
        html = text.replace("&", "&amp;").replace("<", "&lt;")
        small = detail.replace("&", "&amp;").replace("<", "&lt;")
        self.text.setText(f"<span style='font-size:12pt; font-weight:600'>{html}</span>"
                          + (f"<br><span style='font-size:9pt'>{small}</span>" if small else ""))
        if legend_types:
            items = "".join(
                f"<td><span style='background:{hex_colour(error_colour(t))}; color:{hex_colour(error_colour(t))}'>"
                f"&nbsp;&nbsp;&nbsp;</span>&nbsp;{t}&nbsp;&nbsp;</td>" for t in legend_types)
            self.legend.setText(f"<table style='color:white'><tr>{items}</tr></table>"
                                "<div style='color:#eeeeee; font-size:8pt'>thick ring = out of tolerance</div>")
        else:
            self.legend.setText("")

    def paintEvent(self, event: Any) -> None:  # stylesheet backgrounds on a plain QWidget need this
        from PySide6.QtWidgets import QStyle, QStyleOption
        from PySide6.QtGui import QPainter

        opt = QStyleOption()
        opt.initFrom(self)
        p = QPainter(self)
        self.style().drawPrimitive(QStyle.PrimitiveElement.PE_Widget, opt, p, self)


class LogView(QPlainTextEdit):
    """Timestamped messages; errors in red."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setReadOnly(True)
        self.setMaximumBlockCount(5000)
        self.setFont(MONO)

    def add(self, text: str, level: str = "info") -> None:
        colour = {"error": "#cf222e", "warning": "#9a6700", "ok": "#1a7f37"}.get(level, "#24292f")
        stamp = time.strftime("%H:%M:%S")
        safe = text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
        self.appendHtml(f"<span style='color:#8c959f'>{stamp}</span> <span style='color:{colour}'>{safe}</span>")


# ======================================================================================== image view


class ImagePanel(QWidget):
    """Large image view: pyqtgraph ImageItem + histogram/levels, zoom/pan, overlays, hover and click."""

    hovered = Signal(float, float, object)  # x, y, pixel value (None outside the image)
    clicked = Signal(float, float)
    fitLevelsRequested = Signal()
    frameChosen = Signal(int)  # frame selector: 0 the inspected (white) frame, k the k-th through-focus frame

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.setSpacing(2)
        bar = QHBoxLayout()
        bar.setContentsMargins(4, 0, 4, 0)
        self.fit_button = QPushButton("Fit view")
        self.levels_button = QPushButton("Fit levels")
        self.auto_levels = QCheckBox("Auto levels")
        self.grid_box = QCheckBox("Lens grid")
        self.defects_box = QCheckBox("Defect rings")
        self.defects_box.setChecked(True)
        self.info = QLabel("")
        self.info.setFont(MONO)
        self.frame_label = QLabel("Frame")
        self.frame_box = QComboBox()
        self.frame_box.setToolTip("show the inspected white frame or one of the through-focus pinhole frames "
                                  "under the same defect rings")
        self.frame_box.setSizeAdjustPolicy(QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        self.frame_box.setMinimumContentsLength(16)  # long file names are elided, never widen the window
        self.frame_box.view().setMinimumWidth(380)  # the list shows them whole
        self.frame_box.view().setTextElideMode(Qt.TextElideMode.ElideMiddle)
        for w in (self.fit_button, self.levels_button, self.auto_levels, self.grid_box, self.defects_box,
                  self.frame_label, self.frame_box):
            bar.addWidget(w)
        self.frame_label.hide()
        self.frame_box.hide()
        bar.addStretch(1)
        bar.addWidget(self.info)
        lay.addLayout(bar)

        self.glw = pg.GraphicsLayoutWidget()
        self.glw.setBackground("#1e1e1e")
        self.vb = pg.ViewBox(lockAspect=True, invertY=True, enableMenu=False)
        self.vb.setBackgroundColor("#111111")
        self.glw.addItem(self.vb, row=0, col=0)
        self.img = pg.ImageItem()
        self.img.setTransform(QTransform.fromTranslate(-0.5, -0.5))  # pixel (0, 0) is centred on (0, 0)
        self.vb.addItem(self.img)
        self.hist = pg.HistogramLUTItem()
        self.hist.setImageItem(self.img)
        self.glw.addItem(self.hist, row=0, col=1)

        self.grid_item = pg.ScatterPlotItem(pxMode=True, symbol="+", size=6,
                                            pen=pg.mkPen(80, 220, 255, 150, width=1), brush=None)
        self.halo_item = pg.ScatterPlotItem(pxMode=False, symbol="o", brush=None)
        self.ring_item = pg.ScatterPlotItem(pxMode=False, symbol="o", brush=None)
        self.cross_item = pg.ScatterPlotItem(pxMode=False, symbol="x", brush=pg.mkBrush(qcolor(ERROR_COLOURS["missing"])),
                                             pen=pg.mkPen(0, 0, 0, 200, width=1))
        self.cells_item = pg.PlotCurveItem(pen=pg.mkPen(80, 220, 255, 90, width=1), connect="finite")
        self.cells_item.setZValue(9)  # a hex grid's cells under its centres
        self.vb.addItem(self.cells_item)
        self.apertures_item = pg.ScatterPlotItem(pxMode=False, symbol="o", brush=None,
                                                 pen=pg.mkPen(255, 200, 80, 110, width=1))
        self.apertures_item.setZValue(9)  # circular lens apertures (and the gaps between them)
        self.vb.addItem(self.apertures_item)
        self.tick_items: list[pg.PlotCurveItem] = []
        for item in (self.grid_item, self.halo_item, self.ring_item, self.cross_item):
            item.setZValue(10)
            self.vb.addItem(item)
        self.select_item = QGraphicsRectItem()
        pen = QPen(QColor(255, 255, 255))
        pen.setCosmetic(True)
        pen.setWidthF(2.0)
        pen.setStyle(Qt.PenStyle.DashLine)
        self.select_item.setPen(pen)
        self.select_item.setZValue(20)
        self.select_item.hide()
        self.vb.addItem(self.select_item)
        self.select_hex = QGraphicsPolygonItem()  # the selection on a hex grid: the lens' cell
        self.select_hex.setPen(pen)
        self.select_hex.setZValue(20)
        self.select_hex.hide()
        self.vb.addItem(self.select_hex)
        lay.addWidget(self.glw, 1)

        self.view: Any = None  # gui.inspection_worker.InspectionView drawn now (None: a frame without result)
        self._grid_drawn: Any = None
        self._rings_in_px: bool | None = None
        self._ring_d = 0.0
        self.data: np.ndarray | None = None
        self.mode = "empty"  # 'empty', 'frame', 'live', 'result'
        self.frame_index = 0  # in 'result' mode: 0 the inspected frame, k the k-th through-focus frame
        self._shape: tuple[int, int] | None = None
        self.displayed = 0
        self._fps_t0 = time.perf_counter()
        self._fps_n = 0
        self.fps = 0.0

        self.fit_button.clicked.connect(self.fit_view)
        self.levels_button.clicked.connect(self.fit_levels)
        self.grid_box.toggled.connect(self._update_visibility)
        self.defects_box.toggled.connect(self._update_visibility)
        self.vb.sigRangeChanged.connect(self._update_ring_scale)
        self.glw.scene().sigMouseMoved.connect(self._on_move)
        self.glw.scene().sigMouseClicked.connect(self._on_click)
        self.frame_box.activated.connect(self.frameChosen)

    # ------------------------------------------------------------------ images

    def show_frame(self, data: np.ndarray, *, live: bool = False) -> None:
        """A raw frame (uint16 counts): live view or a captured frame; overlays hidden."""
        first = self.mode not in ("frame", "live") or self._shape != data.shape
        self.data = data
        self.mode = "live" if live else "frame"
        auto = first or self.auto_levels.isChecked()
        if auto:
            lo, hi = robust_levels(data)
            self.img.setImage(data, autoLevels=False, levels=(lo, hi))
            self.hist.setLevels(lo, hi)
        else:
            self.img.setImage(data, autoLevels=False)
        if self._shape != data.shape:
            self._shape = data.shape
            self.fit_view()
        self._update_visibility()
        self._count_frame()

    def show_result(self, view: Any) -> None:
        """An inspection result: its normalized image, levels, grid and defect overlays."""
        self.view = view
        self.data = np.asarray(view.result.image)
        self.mode = "result"
        self.set_frame_index(0)
        self.info.setText("")
        lo, hi = view.levels
        self.img.setImage(self.data, autoLevels=False, levels=(lo, hi))
        self.hist.setLevels(lo, hi)
        self._grid_drawn = None
        self._draw_rings(view)
        if self._shape != self.data.shape:
            self._shape = self.data.shape
            self.fit_view()
        self._update_visibility()

    def set_frames(self, labels: list[str]) -> None:
        """The frame selector's entries (the inspected frame first); shown only with through-focus frames."""
        self.frame_box.blockSignals(True)
        self.frame_box.clear()
        self.frame_box.addItems(labels)
        self.frame_box.setCurrentIndex(0)
        self.frame_box.blockSignals(False)
        on = len(labels) > 1
        self.frame_label.setVisible(on)
        self.frame_box.setVisible(on)

    def set_frame_index(self, index: int) -> None:
        """Record which frame of the result is shown and put the selector on it (without a signal)."""
        self.frame_index = index
        if 0 <= index < self.frame_box.count() and self.frame_box.currentIndex() != index:
            self.frame_box.blockSignals(True)
            self.frame_box.setCurrentIndex(index)
            self.frame_box.blockSignals(False)

    def show_result_frame(self, index: int, data: np.ndarray, levels: tuple[float, float]) -> None:
        """Another frame of the result on display (a through-focus frame the worker prepared, same size):
        the grid, rings and selection stay where they are."""
        if self.view is None or data.shape != np.shape(self.view.result.image):
            return
        self.data = data
        self.mode = "result"
        self.set_frame_index(index)
        self.info.setText("")
        lo, hi = levels
        self.img.setImage(data, autoLevels=False, levels=(lo, hi))
        self.hist.setLevels(lo, hi)
        self._update_visibility()

    def _draw_rings(self, view: Any) -> None:
        for item in self.tick_items:
            self.vb.removeItem(item)
        self.tick_items = []
        d = 0.92 * view.pitch_px
        rings = list(view.rings)
        if not rings:
            for item in (self.halo_item, self.ring_item, self.cross_item):
                item.setData(x=[], y=[])
            return
        rings.sort(key=lambda r: r.out_of_tolerance)  # out-of-tolerance rings on top
        xs = np.array([r.x for r in rings])
        ys = np.array([r.y for r in rings])
        widths = [3.5 if r.out_of_tolerance else 1.8 for r in rings]
        symbol = ring_symbol(view)
        self.halo_item.setData(x=xs, y=ys, size=d, symbol=symbol,
                               pen=[pg.mkPen(0, 0, 0, 220, width=w + 2.5) for w in widths])
        self.ring_item.setData(x=xs, y=ys, size=d, symbol=symbol,
                               pen=[pg.mkPen(qcolor(error_colour(r.error_type)), width=w) for r, w in zip(rings, widths)])
        miss = [r for r in rings if r.missing]
        self.cross_item.setData(x=[r.x for r in miss], y=[r.y for r in miss], size=0.5 * d)
        self._rings_in_px = None
        self._update_ring_scale()
        by_type: dict[str, list[float]] = {}
        for r in rings:
            if r.tick is not None:
                by_type.setdefault(r.error_type, []).extend([r.x, r.y, r.tick[0], r.tick[1]])
        for etype, pts in by_type.items():
            a = np.asarray(pts).reshape(-1, 2)
            for pen in (pg.mkPen(0, 0, 0, 220, width=4.5), pg.mkPen(qcolor(error_colour(etype)), width=2)):
                item = pg.PlotCurveItem(x=a[:, 0], y=a[:, 1], connect="pairs", pen=pen)
                item.setZValue(11)
                self.vb.addItem(item)
                self.tick_items.append(item)

    MIN_RING_PX = 13.0  # rings never shrink below this on screen, so defects show on a whole-wafer view

    def _update_ring_scale(self, *_args: Any) -> None:
        """Rings are one pitch wide in image pixels, but at least MIN_RING_PX screen pixels."""
        view = self.view
        if view is None:
            return
        (x0, x1), _ = self.vb.viewRange()
        scale = self.vb.width() / max(1e-9, x1 - x0)  # screen px per image px
        d = 0.92 * view.pitch_px
        small = d * scale < self.MIN_RING_PX
        if small == self._rings_in_px and self._ring_d == d:
            return
        self._rings_in_px, self._ring_d = small, d
        for item, k in ((self.halo_item, 1.0), (self.ring_item, 1.0), (self.cross_item, 0.5)):
            item.setPxMode(small)
            item.setSize(k * (self.MIN_RING_PX if small else d))

    def clear_result(self) -> None:
        self.view = None
        self._grid_drawn = None
        for item in (self.grid_item, self.halo_item, self.ring_item, self.cross_item, self.cells_item,
                     self.apertures_item):
            item.setData(x=[], y=[])
        for item in self.tick_items:
            self.vb.removeItem(item)
        self.tick_items = []
        self.select_item.hide()
        self.select_hex.hide()

    def _update_visibility(self) -> None:
        on_result = self.mode == "result" and self.view is not None
        show_grid = on_result and self.grid_box.isChecked()
        if show_grid and self._grid_drawn is not self.view:  # 10k points: built only when asked for
            self.grid_item.setData(x=self.view.grid_x, y=self.view.grid_y)
            cells = getattr(self.view, "cells_x", None) is not None
            self.cells_item.setData(x=self.view.cells_x if cells else [], y=self.view.cells_y if cells else [])
            d_ap = getattr(self.view, "aperture_px", None)
            self.apertures_item.setData(x=self.view.grid_x if d_ap else [], y=self.view.grid_y if d_ap else [],
                                        size=d_ap or 1.0)
            self._grid_drawn = self.view
        self.grid_item.setVisible(show_grid)
        self.cells_item.setVisible(show_grid)
        self.apertures_item.setVisible(show_grid)
        rings = on_result and self.defects_box.isChecked()
        for item in (self.halo_item, self.ring_item, self.cross_item, *self.tick_items):
            item.setVisible(rings)
        selected = on_result and self.select_item.data(0) is not None
        on_hex = selected and _cell_px(self.view) is not None
        self.select_item.setVisible(selected and not on_hex)
        self.select_hex.setVisible(on_hex)

    def _count_frame(self) -> None:
        self.displayed += 1
        self._fps_n += 1
        now = time.perf_counter()
        if now - self._fps_t0 >= 1.0:
            self.fps = self._fps_n / (now - self._fps_t0)
            self._fps_t0, self._fps_n = now, 0
            if self.mode == "live":
                self.info.setText(f"live {self.fps:5.1f} fps")
        if self.mode != "live":
            self.info.setText("")

    def reset_fps(self) -> None:
        self._fps_t0, self._fps_n, self.fps = time.perf_counter(), 0, 0.0

    # ------------------------------------------------------------------ navigation

    def fit_view(self) -> None:
        if self._shape is not None:
            h, w = self._shape
            self.vb.setRange(QRectF(-0.5, -0.5, w, h), padding=0.01)

    def fit_levels(self) -> None:
        if self.data is not None:
            lo, hi = robust_levels(self.data)
            self.img.setLevels((lo, hi))
            self.hist.setLevels(lo, hi)

    def select(self, m: int, n: int, *, zoom: bool = False) -> None:
        """Mark lens U(m,n) (a dashed square); `zoom` centres the view on it, a few lenses wide."""
        if self.view is None:
            return
        x, y = self.view.centre(m, n)
        if not (math.isfinite(x) and math.isfinite(y)):
            return
        p = self.view.pitch_px
        self.select_item.setRect(QRectF(x - 0.5 * p, y - 0.5 * p, p, p))
        self.select_item.setData(0, (m, n))
        corners = _cell_px(self.view)
        if corners is not None:
            self.select_hex.setPolygon(QPolygonF([QPointF(x + a, y + b) for a, b in corners.tolist()]))
        self._update_visibility()
        if zoom:
            half = 4.5 * p
            self.vb.setRange(QRectF(x - half, y - half, 2 * half, 2 * half), padding=0)

    # ------------------------------------------------------------------ mouse

    def _scene_to_image(self, pos: Any) -> tuple[float, float] | None:
        if not self.vb.sceneBoundingRect().contains(pos):
            return None
        p = self.vb.mapSceneToView(pos)
        return p.x(), p.y()

    def _on_move(self, pos: Any) -> None:
        xy = self._scene_to_image(pos)
        if xy is None or self.data is None:
            return
        x, y = xy
        ix, iy = int(round(x)), int(round(y))
        h, w = self.data.shape[:2]
        value = float(self.data[iy, ix]) if (0 <= ix < w and 0 <= iy < h) else None
        self.hovered.emit(x, y, value)

    def _on_click(self, ev: Any) -> None:
        if ev.button() != Qt.MouseButton.LeftButton or ev.double():
            return
        xy = self._scene_to_image(ev.scenePos())
        if xy is not None:
            self.clicked.emit(*xy)


def _cell_px(view: Any) -> np.ndarray | None:
    """A hex view's cell corner offsets (6, 2) px, None on a square grid."""
    return getattr(view, "cell_px", None) if getattr(view, "packing", "square") == "hex" else None


def ring_symbol(view: Any) -> Any:
    """The defect ring's scatter symbol: a circle, or on a hex grid the lens' hexagonal cell (a path one
    pitch across its flats, as the circle is one pitch across, turned with the grid)."""
    corners = _cell_px(view)
    if corners is None or not view.pitch_px > 0:
        return "o"
    path = QPainterPath()
    unit = corners / float(view.pitch_px)
    path.moveTo(*unit[0])
    for a, b in unit[1:].tolist():
        path.lineTo(a, b)
    path.closeSubpath()
    return path


def robust_levels(data: np.ndarray) -> tuple[float, float]:
    """0.5 / 99.8 percentiles of a subsample (finite values); never an empty range."""
    step = max(1, int(math.sqrt(data.size / 60_000)))
    s = np.asarray(data[::step, ::step], dtype=np.float32)
    s = s[np.isfinite(s)]
    if not s.size:
        return 0.0, 1.0
    lo, hi = np.percentile(s, [0.5, 99.8])
    if not hi > lo:
        hi = lo + 1.0
    return float(lo), float(hi)


# ====================================================================================== defect table


class DefectTableModel(QAbstractTableModel):
    """Flagged lenses of an inspection; sortable via `DefectSortProxy` (numbers sort as numbers)."""

    COLUMNS = ("Lens", "Type", "Magnitude", "Unit", "Dir (°)", "Score", "Tolerance", "Source")
    SOURCE_TIPS = {"white": "flagged by the white frame",
                   "white + pinholes": "flagged by the white frame and read by the +u / −u pinhole pairs too "
                                       "(they settle the sign of its focal error)",
                   "pinholes": "flagged by the +u / −u pinhole pairs only (a significant focal error the white "
                               "frame did not flag)",
                   "white (not covered)": "flagged by the white frame; no pinhole pair lit this lens fully, so "
                                          "its sign is the white frame's"}
    SORT_ROLE = Qt.ItemDataRole.UserRole
    LENS_ROLE = Qt.ItemDataRole.UserRole + 1

    def __init__(self, parent: Any = None) -> None:
        super().__init__(parent)
        self.defects: list[Any] = []
        self.sources: dict[tuple[int, int], str] = {}

    def set_defects(self, defects: Any, sources: dict[tuple[int, int], str] | None = None) -> None:
        """`sources`: which measurement flagged each lens (gui.inspection_worker.defect_sources); 'white' by default."""
        self.beginResetModel()
        self.sources = dict(sources or {})
        # default order: out of tolerance first, then most certain
        self.defects = sorted(defects, key=lambda d: (d.within_tolerance, -_finite_or(d.score, -1e9)))
        self.endResetModel()

    def rowCount(self, parent: QModelIndex = QModelIndex()) -> int:
        return 0 if parent.isValid() else len(self.defects)

    def columnCount(self, parent: QModelIndex = QModelIndex()) -> int:
        return 0 if parent.isValid() else len(self.COLUMNS)

    def headerData(self, section: int, orientation: Qt.Orientation, role: int = Qt.ItemDataRole.DisplayRole) -> Any:
        if orientation == Qt.Orientation.Horizontal and role == Qt.ItemDataRole.DisplayRole:
            return self.COLUMNS[section]
        return None

    def data(self, index: QModelIndex, role: int = Qt.ItemDataRole.DisplayRole) -> Any:
        if not index.isValid():
            return None
        d = self.defects[index.row()]
        c = index.column()
        if role == self.LENS_ROLE:
            return (d.m, d.n)
        if role == Qt.ItemDataRole.DisplayRole:
            return (f"U({d.m},{d.n})", d.error_type, _fmt(d.magnitude), d.unit,
                    "" if d.direction_deg is None else f"{d.direction_deg:.0f}", f"{d.score:.1f}",
                    "within" if d.within_tolerance else "OUT", self.source_of(d))[c]
        if role == self.SORT_ROLE:
            return ((d.m, d.n), d.error_type, _finite_or(d.magnitude, -math.inf), d.unit,
                    _finite_or(d.direction_deg, -math.inf), _finite_or(d.score, -math.inf), int(d.within_tolerance),
                    self.source_of(d))[c]
        if role == Qt.ItemDataRole.ForegroundRole and c == 7 and "pinholes" in self.source_of(d):
            return QBrush(QColor("#6639ba"))
        if role == Qt.ItemDataRole.ToolTipRole and c == 7:
            src = self.source_of(d)
            z = (d.indexes or {}).get(TF_SOURCE_KEY)
            return self.SOURCE_TIPS.get(src, src) + (f" (z = {z:.1f})" if z is not None and math.isfinite(z) else "")
        if role == Qt.ItemDataRole.DecorationRole and c == 1:
            return qcolor(error_colour(d.error_type))
        if role == Qt.ItemDataRole.ForegroundRole and c == 6 and not d.within_tolerance:
            return QBrush(QColor("#cf222e"))
        if role == Qt.ItemDataRole.FontRole and c == 6 and not d.within_tolerance:
            f = QFont()
            f.setBold(True)
            return f
        if role == Qt.ItemDataRole.TextAlignmentRole and c in (2, 4, 5):
            return int(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
        if role == Qt.ItemDataRole.ToolTipRole:
            alts = "; ".join(f"{t} {_fmt(v)} {u}" for t, v, u, _a in (d.alternatives or ()))
            return f"U({d.m},{d.n}) {d.error_type}" + (f"\nalso fits: {alts}" if alts else "")
        return None

    def source_of(self, d: Any) -> str:
        """'white', 'white + pinholes', 'pinholes' or 'white (not covered)' (see
        gui.inspection_worker.defect_sources)."""
        src = self.sources.get((d.m, d.n))
        if src is None:
            src = "pinholes" if TF_SOURCE_KEY in (d.indexes or {}) else "white"
        return src

    def row_of(self, m: int, n: int) -> int:
        for i, d in enumerate(self.defects):
            if (d.m, d.n) == (m, n):
                return i
        return -1


class DefectSortProxy(QSortFilterProxyModel):
    """Sorts on the model's SORT_ROLE values (tuples and numbers compare as such)."""

    def lessThan(self, left: QModelIndex, right: QModelIndex) -> bool:
        a = left.data(DefectTableModel.SORT_ROLE)
        b = right.data(DefectTableModel.SORT_ROLE)
        try:
            return a < b
        except TypeError:
            return str(a) < str(b)


def _finite_or(v: Any, default: float) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return default
    return f if math.isfinite(f) else default


def _fmt(v: Any, digits: int = 3) -> str:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return ""
    if not math.isfinite(f):
        return "—"
    return f"{f:.{digits}g}" if abs(f) >= 1e-3 or f == 0 else f"{f:.2e}"


# ======================================================================================= lens detail


def measured_text(measured: Any, m: int, n: int) -> str:
    """One line of lens U(m,n)'s measured quantities (mlaqc.inspection.measure) with their 1-sigma."""
    if measured is None:
        return "measured: —"
    v = {k: float(a[m - 1, n - 1]) for k, a in measured.values.items()}
    centre = (f"centre shift ({_fmt(v['centre_dx_um'])}, {_fmt(v['centre_dy_um'])}) ± {_fmt(v['centre_sigma_um'], 2)} µm"
              if math.isfinite(v["centre_dx_um"]) else "centre not measured")
    if not math.isfinite(v["focal_rel"]):
        return f"{centre} · focal length not measured"
    sign = "sign known" if v["focal_sign_resolved"] == 1 else "sign not known"
    alt = f", or {100 * v['focal_alt_rel']:+.2f} %" if math.isfinite(v["focal_alt_rel"]) else ""
    return (f"{centre} · focal Δf/f {100 * v['focal_rel']:+.2f} ± {100 * v['focal_sigma_rel']:.2f} %{alt} "
            f"({_fmt(v['focal_um'])} µm, {sign})")


def throughfocus_text(tf: Any, m: int, n: int) -> str:
    """One line of lens U(m,n)'s through-focus reading (mlaqc.inspection.throughfocus_results.ThroughFocusResult):
    focal error with its sign and 1-sigma, the radius error it equals, covered or not, the optical-centre
    shift from the spot positions."""
    i, j = m - 1, n - 1

    def at(name: str) -> float:
        return float(np.asarray(getattr(tf, name))[i, j])

    dx, dy, cs = at("centre_dx_um"), at("centre_dy_um"), at("centre_sigma_um")
    centre = (f"optical centre ({_fmt(dx)}, {_fmt(dy)}) ± {_fmt(cs, 2)} µm" if math.isfinite(dx) and math.isfinite(dy)
              else "optical centre not measured")
    f, sig, r = at("focal_rel"), at("focal_sigma_rel"), at("radius_rel")
    if not (bool(np.asarray(tf.covered)[i, j]) and math.isfinite(f)):
        return f"not covered (no +u / −u pair lit this lens fully) · {centre}"
    return (f"focal Δf/f {100 * f:+.2f} ± {100 * sig:.2f} % · radius-equivalent {100 * r:+.2f} % · covered · "
            f"{centre}")


class LensDetail(QWidget):
    """The selected lens: its sub-image beside the reference (and their difference), and its indexes."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(4, 4, 4, 4)
        self.title = QLabel("No lens selected — click a lens on the image or a row of the table.")
        self.title.setWordWrap(True)
        self.title.setTextFormat(Qt.TextFormat.RichText)
        lay.addWidget(self.title)
        self.throughfocus = QLabel("")  # the pinhole frames' reading of the lens, under the white frame's
        self.throughfocus.setWordWrap(True)
        self.throughfocus.setTextFormat(Qt.TextFormat.RichText)
        self.throughfocus.setToolTip("through-focus reading: from the +u / −u pinhole pairs, against the "
                                     "array's typical lens")
        self.throughfocus.hide()
        lay.addWidget(self.throughfocus)
        self.glw = pg.GraphicsLayoutWidget()
        self.glw.setBackground("#1e1e1e")
        self.glw.setMinimumHeight(150)
        self.images: list[pg.ImageItem] = []
        self.captions: list[pg.LabelItem] = []
        for col, caption in enumerate(("lens", "reference", "difference")):
            label = self.glw.addLabel(caption, row=0, col=col, color="#dddddd", size="9pt")
            vb = self.glw.addViewBox(row=1, col=col, lockAspect=True, invertY=True, enableMouse=False, enableMenu=False)
            item = pg.ImageItem()
            vb.addItem(item)
            self.images.append(item)
            self.captions.append(label)
        lay.addWidget(self.glw, 2)
        self.table = QTableWidget(0, 4)
        self.table.setHorizontalHeaderLabels(["index", "lens", "median", "unit"])
        self.table.verticalHeader().hide()
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.Stretch)
        self.table.setEditTriggers(QTableWidget.EditTrigger.NoEditTriggers)
        self.table.setFont(MONO)
        lay.addWidget(self.table, 3)
        self.lens: tuple[int, int] | None = None

    def clear(self) -> None:
        self.lens = None
        self.title.setText("No lens selected — click a lens on the image or a row of the table.")
        for item in self.images:
            item.clear()
        self.table.setRowCount(0)
        self.throughfocus.setText("")
        self.throughfocus.hide()

    def show_lens(self, view: Any, m: int, n: int) -> None:
        r = view.result
        self.lens = (m, n)
        defect = next((d for d in r.defects if (d.m, d.n) == (m, n)), None)
        sub = np.asarray(r.subimages[m - 1, n - 1], np.float32)
        ref = np.asarray(view.reference_of(m, n), np.float32)
        both = np.concatenate([sub[np.isfinite(sub)], ref[np.isfinite(ref)]])
        lo, hi = (float(both.min()), float(both.max())) if both.size else (0.0, 1.0)
        if not hi > lo:
            hi = lo + 1.0
        self.images[0].setImage(np.nan_to_num(sub, nan=lo), levels=(lo, hi), autoLevels=False)
        self.images[1].setImage(np.nan_to_num(ref, nan=lo), levels=(lo, hi), autoLevels=False)
        if sub.shape == ref.shape:
            ok = np.isfinite(sub) & np.isfinite(ref)
            k = float(sub[ok].sum() / ref[ok].sum()) if ok.any() and ref[ok].sum() > 0 else 1.0
            diff = np.where(ok, sub - k * ref, 0.0)  # against the reference scaled to the lens' flux
            span = float(np.abs(diff).max()) or 1.0
            self.images[2].setImage(diff, levels=(-span, span), autoLevels=False,
                                    lut=pg.colormap.get("CET-D1").getLookupTable(nPts=256))
        else:
            self.images[2].clear()
        for item in self.images:
            item.getViewBox().autoRange(padding=0.02)
        x, y = view.centre(m, n)
        where = f"centre ({x:.2f}, {y:.2f}) px" if math.isfinite(x) else "centre unknown"
        if defect is None:
            state = "<span style='color:#1a7f37'><b>not flagged</b></span>"
        else:
            col = hex_colour(error_colour(defect.error_type))
            tol = ("<span style='color:#1a7f37'>within tolerance</span>" if defect.within_tolerance
                   else "<span style='color:#cf222e'><b>OUT of tolerance</b></span>")
            direction = "" if defect.direction_deg is None else f" @ {defect.direction_deg:.0f}°"
            state = (f"<span style='background:{col}'>&nbsp;&nbsp;&nbsp;</span> <b>{defect.error_type}</b> "
                     f"{_fmt(defect.magnitude)} {defect.unit}{direction} · {tol} · score {_fmt(defect.score, 3)}")
        tf = getattr(r, "through_focus", None)
        white = measured_text(getattr(r, "measurements", None), m, n)
        self.title.setText(f"<span style='font-size:14pt'><b>U({m},{n})</b></span>&nbsp;&nbsp;row {m}, column {n} · "
                           f"{where}<br>{state}<br>" + (white if tf is None else f"<b>white frame</b>: {white}"))
        if tf is None:
            self.throughfocus.setText("")
            self.throughfocus.hide()
        else:
            self.throughfocus.setText(f"<b>pinhole frames</b>: {throughfocus_text(tf, m, n)}")
            self.throughfocus.show()
        values = r.metrics.at(m, n)
        self.table.setRowCount(len(METRICS))
        for i, (name, (unit, meaning)) in enumerate(METRICS.items()):
            cells = (name, _fmt(values.get(name), 4), _fmt(view.medians.get(name), 4), unit)
            for j, text in enumerate(cells):
                item = QTableWidgetItem(text)
                item.setToolTip(meaning)
                if j in (1, 2):
                    item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
                self.table.setItem(i, j, item)
        self.table.resizeRowsToContents()


# ========================================================================================= wafer map


class WaferMap(pg.PlotWidget):
    """Scan positions at their stage coordinates, coloured by status; the live stage position as a cross."""

    positionClicked = Signal(int)

    STATUS = {"pending": "#d0d7de", "current": "#0969da", "captured": "#54aeff", "PASS": hex_colour(VERDICT_COLOURS["PASS"]),
              "FAIL": hex_colour(VERDICT_COLOURS["FAIL"]), "ERROR": "#bf8700", "failed": "#bf8700"}

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent, background="#ffffff")
        self.setAspectLocked(True)
        self.invertY(True)
        self.setLabel("bottom", "x", units="mm")
        self.setLabel("left", "y", units="mm")
        self.showGrid(x=True, y=True, alpha=0.25)
        self.setMenuEnabled(False)
        self.scatter = pg.ScatterPlotItem(pxMode=True, symbol="s", size=24, hoverable=True, tip=self._tip)
        self.addItem(self.scatter)
        self.marker = pg.ScatterPlotItem(pxMode=True, symbol="+", size=20, pen=pg.mkPen("#ffffff", width=1.5),
                                         brush=pg.mkBrush("#24292f"))  # the stage now: dark cross, white rim
        self.marker.setZValue(5)
        self.addItem(self.marker)
        self.positions: list[tuple[float, float, str]] = []
        self.status: list[str] = []
        self.info: list[dict] = []
        self.scatter.sigClicked.connect(self._clicked)

    def set_plan(self, positions: list[tuple[float, float, str]]) -> None:
        self.positions = list(positions)
        self.status = ["pending"] * len(positions)
        self.info = [{} for _ in positions]
        self._redraw()
        self.autoRange(padding=0.25)

    def set_status(self, index: int, status: str, info: dict | None = None) -> None:
        if 0 <= index < len(self.status):
            self.status[index] = status
            if info is not None:
                self.info[index] = info
            self._redraw()

    def set_stage_position(self, pos: tuple[float, float] | None) -> None:
        if pos is None:
            self.marker.setData(x=[], y=[])
        else:
            self.marker.setData(x=[pos[0]], y=[pos[1]])

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for s in self.status:
            out[s] = out.get(s, 0) + 1
        return out

    def _redraw(self) -> None:
        if not self.positions:
            self.scatter.setData([])
            return
        spots = []
        for i, ((x, y, _label), s) in enumerate(zip(self.positions, self.status)):
            colour = self.STATUS.get(s, "#d0d7de")
            pen = pg.mkPen("#0969da", width=3) if s == "current" else pg.mkPen("#57606a", width=1)
            spots.append({"pos": (x, y), "brush": pg.mkBrush(colour), "pen": pen, "data": i})
        self.scatter.setData(spots)

    def _tip(self, x: float, y: float, data: Any) -> str:
        i = int(data)
        label = self.positions[i][2] if 0 <= i < len(self.positions) else ""
        info = self.info[i] if 0 <= i < len(self.info) else {}
        extra = ""
        if info.get("verdict") in ("PASS", "FAIL"):
            extra = f"\n{info['verdict']}: {info.get('flagged', 0)} flagged, {info.get('out_of_tolerance', 0)} out of tol."
        elif info.get("error"):
            extra = f"\n{info['error']}"
        return f"#{i + 1} {label}  ({x:g}, {y:g}) mm\n{self.status[i] if i < len(self.status) else ''}{extra}"

    def _clicked(self, item: Any, points: Any, ev: Any = None) -> None:
        if len(points):
            self.positionClicked.emit(int(points[0].data()))
