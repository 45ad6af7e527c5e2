"""Dock panels: camera, stage, inspection and scan controls. Pure widgets: they emit requests as signals
and show what the main window tells them; no device or file I/O happens here."""

from __future__ import annotations

import math
from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QFont
from PySide6.QtWidgets import (QCheckBox, QComboBox, QDoubleSpinBox, QFormLayout, QGridLayout, QGroupBox,
                               QHBoxLayout, QLabel, QLineEdit, QProgressBar, QPushButton, QSizePolicy, QToolButton,
                               QVBoxLayout, QWidget)

from gui.widgets import MONO, ErrorLabel, StatusDot, WaferMap

FORMAT_CHOICES = ("Y16", "Y12", "Y10", "GREY", "RGGB", "RG16")


def _button(text: str, tip: str = "", primary: bool = False) -> QPushButton:
    b = QPushButton(text)
    if tip:
        b.setToolTip(tip)
    if primary:
        b.setStyleSheet("QPushButton { font-weight: bold; padding: 5px 12px; background: #1f883d; color: white;"
                        " border-radius: 4px; } QPushButton:disabled { background: #94d3a2; }")
    return b


def _fit_text(button: QPushButton, other_text: str = "") -> None:
    """Never let a layout squeeze `button` below its text (or `other_text`, which it also shows)."""
    width = button.sizeHint().width()
    if other_text:
        shown = button.text()
        button.setText(other_text)
        width = max(width, button.sizeHint().width())
        button.setText(shown)
    button.setMinimumWidth(width)


def _clear_button(tip: str) -> QPushButton:
    """The narrow "✕" that drops one input of the inspection."""
    b = _button("✕", tip)
    b.setMaximumWidth(28)
    return b


def _readback() -> QLabel:
    label = QLabel("—")
    label.setFont(MONO)
    label.setStyleSheet("color: #57606a")
    label.setToolTip("value read back from the device")
    return label


class ConnectionRow(QWidget):
    """URL field, Connect/Reconnect and Disconnect buttons, and the state dot."""

    connectRequested = Signal(str)
    disconnectRequested = Signal()

    def __init__(self, url: str, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        lay = QGridLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.url = QLineEdit(url)
        self.url.setFont(MONO)
        self.url.setToolTip("device URL (see `mlaqc capture --help`)")
        self.connect_button = QPushButton("Connect")
        self.disconnect_button = QPushButton("Disconnect")
        self.dot = StatusDot()
        lay.addWidget(self.url, 0, 0, 1, 3)
        lay.addWidget(self.dot, 1, 0)
        lay.addWidget(self.connect_button, 1, 1)
        lay.addWidget(self.disconnect_button, 1, 2)
        lay.setColumnStretch(0, 1)
        self.connect_button.clicked.connect(lambda: self.connectRequested.emit(self.url.text().strip()))
        self.disconnect_button.clicked.connect(self.disconnectRequested)
        self.set_state("disconnected")

    def set_state(self, state: str, detail: str = "") -> None:
        words = {"connected": "connected", "connecting": "connecting…", "disconnected": "disconnected",
                 "error": "error"}
        self.dot.set_state(state, words.get(state, state))
        self.dot.setToolTip(detail)
        self.connect_button.setText("Reconnect" if state in ("connected", "error") else "Connect")
        self.connect_button.setEnabled(state != "connecting")
        self.disconnect_button.setEnabled(state in ("connected", "error"))


class CameraPanel(QWidget):
    """Camera: connection, exposure/gain/format with read-back, live view, capture."""

    exposureRequested = Signal(float)
    gainRequested = Signal(float)
    formatRequested = Signal(str)
    liveToggled = Signal(bool)
    captureRequested = Signal()
    saveRequested = Signal()

    def __init__(self, url: str, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        lay = QVBoxLayout(self)
        self.connection = ConnectionRow(url)
        lay.addWidget(self.connection)
        self.name = QLabel("")
        self.name.setWordWrap(True)
        self.name.setStyleSheet("color: #57606a")
        lay.addWidget(self.name)

        form = QFormLayout()
        self.exposure = QDoubleSpinBox()
        self.exposure.setRange(1.0, 10_000_000.0)
        self.exposure.setDecimals(0)
        self.exposure.setSuffix(" µs")
        self.exposure.setKeyboardTracking(False)
        self.exposure_rb = _readback()
        self.gain = QDoubleSpinBox()
        self.gain.setRange(0.0, 64.0)
        self.gain.setDecimals(2)
        self.gain.setSingleStep(0.1)
        self.gain.setKeyboardTracking(False)
        self.gain_rb = _readback()
        self.format = QComboBox()
        self.format.setEditable(True)
        self.format.addItems(FORMAT_CHOICES)
        self.format_rb = _readback()
        for label, w, rb in (("Exposure", self.exposure, self.exposure_rb), ("Gain", self.gain, self.gain_rb),
                             ("Format", self.format, self.format_rb)):
            row = QHBoxLayout()
            row.addWidget(w, 1)
            row.addWidget(rb)
            form.addRow(label, row)
        lay.addLayout(form)

        buttons = QHBoxLayout()
        self.live = QPushButton("▶ Live")
        self.live.setCheckable(True)
        self.live.setToolTip("start/stop live view")
        self.capture = _button("Capture frame", "grab one frame (shown and kept for inspection)", primary=True)
        self.save = QPushButton("Save…")
        self.save.setToolTip("save the last captured frame as TIFF/DNG with its provenance sidecar")
        buttons.addWidget(self.live)
        buttons.addWidget(self.capture, 1)
        buttons.addWidget(self.save)
        lay.addLayout(buttons)
        self.fps = QLabel("")
        self.fps.setFont(MONO)
        lay.addWidget(self.fps)
        self.error = ErrorLabel()
        lay.addWidget(self.error)
        lay.addStretch(1)

        self.exposure.editingFinished.connect(lambda: self.exposureRequested.emit(self.exposure.value()))
        self.gain.editingFinished.connect(lambda: self.gainRequested.emit(self.gain.value()))
        self.format.activated.connect(lambda _i: self.formatRequested.emit(self.format.currentText().strip()))
        self.live.toggled.connect(self._live_clicked)
        self.capture.clicked.connect(self.captureRequested)
        self.save.clicked.connect(self.saveRequested)
        self._locked = False
        self._state = "disconnected"
        self._update_enabled()

    def _live_clicked(self, on: bool) -> None:
        self.liveToggled.emit(on)

    def set_state(self, state: str, detail: str = "") -> None:
        self._state = state
        self.connection.set_state(state, detail)
        if state == "connected":
            self.name.setText(detail)
            self.error.clear_error()
        elif state == "error":
            self.error.show_error(detail)
        if state != "connected":
            self.set_live(False)
        self._update_enabled()

    def set_settings(self, s: dict[str, Any]) -> None:
        exp, gain, fmt = s.get("exposure_us"), s.get("gain"), s.get("pixel_format")
        if isinstance(exp, (int, float)) and math.isfinite(exp):
            self.exposure_rb.setText(f"{exp:,.0f} µs")
            if not self.exposure.hasFocus():
                self.exposure.blockSignals(True)
                self.exposure.setValue(exp)
                self.exposure.blockSignals(False)
        if isinstance(gain, (int, float)) and math.isfinite(gain):
            self.gain_rb.setText(f"{gain:.2f}")
            if not self.gain.hasFocus():
                self.gain.blockSignals(True)
                self.gain.setValue(gain)
                self.gain.blockSignals(False)
        if fmt:
            bits = s.get("bits")
            self.format_rb.setText(f"{fmt} {bits} bit" if bits else str(fmt))
            if self.format.findText(fmt) < 0:
                self.format.addItem(fmt)
            self.format.setCurrentText(fmt)
        w, h = s.get("width"), s.get("height")
        if w and h:
            self.name.setText(f"{s.get('name', '')} · {w}×{h} px")

    def set_live(self, on: bool) -> None:
        self.live.blockSignals(True)
        self.live.setChecked(on)
        self.live.blockSignals(False)
        self.live.setText("■ Stop live" if on else "▶ Live")
        if not on:
            self.fps.setText("")

    def set_locked(self, locked: bool) -> None:
        """While a scan borrows the camera."""
        self._locked = locked
        self._update_enabled()

    def _update_enabled(self) -> None:
        ok = self._state == "connected" and not self._locked
        for w in (self.exposure, self.gain, self.format, self.live, self.capture):
            w.setEnabled(ok)
        self.connection.setEnabled(not self._locked)


class StagePanel(QWidget):
    """Stage: connection, live position, limits, jog with step size, home, go-to, and STOP (always enabled)."""

    homeRequested = Signal()
    jogRequested = Signal(float, float)
    gotoRequested = Signal(float, float)
    stopRequested = Signal()

    STEPS_MM = ("0.001", "0.01", "0.1", "0.5", "1", "5", "10")

    def __init__(self, url: str, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        lay = QVBoxLayout(self)
        self.connection = ConnectionRow(url)
        lay.addWidget(self.connection)

        self.stop = QPushButton("STOP")
        self.stop.setMinimumHeight(46)
        f = QFont()
        f.setPointSize(15)
        f.setBold(True)
        self.stop.setFont(f)
        self.stop.setStyleSheet("QPushButton { background: #cf222e; color: white; border-radius: 6px; }"
                                " QPushButton:pressed { background: #a40e26; }")
        self.stop.setToolTip("halt the stage now (also aborts a running scan's move); always available")

        pos_box = QGroupBox("Position")
        pl = QGridLayout(pos_box)
        big = QFont(MONO)
        big.setPointSize(13)
        self.x_label = QLabel("x —")
        self.y_label = QLabel("y —")
        for w in (self.x_label, self.y_label):
            w.setFont(big)
        self.homed = QLabel("not homed")
        self.busy = QLabel("")
        self.busy.setStyleSheet("color: #0969da")
        self.limits = QLabel("limits —")
        self.limits.setStyleSheet("color: #57606a")
        self.limits.setWordWrap(True)
        pl.addWidget(self.x_label, 0, 0)
        pl.addWidget(self.y_label, 0, 1)
        pl.addWidget(self.homed, 1, 0)
        pl.addWidget(self.busy, 1, 1)
        pl.addWidget(self.limits, 2, 0, 1, 2)
        lay.addWidget(pos_box)

        jog_box = QGroupBox("Jog")
        jl = QGridLayout(jog_box)
        self.step = QComboBox()
        self.step.addItems(self.STEPS_MM)
        self.step.setCurrentText("1")
        self.step.setEditable(True)
        self.jog_buttons = {}
        for key, text, r, c in (("-y", "▲ −Y", 0, 1), ("-x", "◀ −X", 1, 0), ("+x", "+X ▶", 1, 2), ("+y", "▼ +Y", 2, 1)):
            b = QToolButton()
            b.setText(text)
            b.setMinimumWidth(56)
            jl.addWidget(b, r, c)
            self.jog_buttons[key] = b
            b.clicked.connect(lambda _=False, k=key: self._jog(k))
        step_row = QHBoxLayout()
        step_row.addWidget(QLabel("step"))
        step_row.addWidget(self.step)
        step_row.addWidget(QLabel("mm"))
        w = QWidget()
        w.setLayout(step_row)
        jl.addWidget(w, 1, 1)
        self.home = QPushButton("Home")
        jl.addWidget(self.home, 0, 2)
        lay.addWidget(jog_box)

        goto_box = QGroupBox("Go to")
        gl = QHBoxLayout(goto_box)
        self.goto_x = QDoubleSpinBox()
        self.goto_y = QDoubleSpinBox()
        for sb, v in ((self.goto_x, 10.0), (self.goto_y, 10.0)):
            sb.setRange(-1000.0, 1000.0)
            sb.setDecimals(3)
            sb.setSuffix(" mm")
            sb.setValue(v)
        self.goto = QPushButton("Go")
        gl.addWidget(QLabel("x"))
        gl.addWidget(self.goto_x, 1)
        gl.addWidget(QLabel("y"))
        gl.addWidget(self.goto_y, 1)
        gl.addWidget(self.goto)
        lay.addWidget(goto_box)
        lay.addWidget(self.stop)
        self.error = ErrorLabel()
        lay.addWidget(self.error)
        lay.addStretch(1)

        self.home.clicked.connect(self.homeRequested)
        self.goto.clicked.connect(lambda: self.gotoRequested.emit(self.goto_x.value(), self.goto_y.value()))
        self.stop.clicked.connect(self.stopRequested)
        self._state = "disconnected"
        self._busy = False
        self._locked = False
        self._update_enabled()

    def _jog(self, key: str) -> None:
        try:
            step = float(self.step.currentText())
        except ValueError:
            self.error.show_error(f"Jog step {self.step.currentText()!r} is not a number of mm.")
            return
        sign = -1.0 if key[0] == "-" else 1.0
        dx, dy = (sign * step, 0.0) if key[1] == "x" else (0.0, sign * step)
        self.jogRequested.emit(dx, dy)

    def set_state(self, state: str, detail: str = "") -> None:
        self._state = state
        self.connection.set_state(state, detail)
        if state == "connected":
            self.error.clear_error()
        elif state == "error":
            self.error.show_error(detail)
        self._update_enabled()

    def set_info(self, info: dict[str, Any]) -> None:
        x0, x1, y0, y1 = info["limits"]
        self.limits.setText(f"limits x {x0:g}…{x1:g} mm, y {y0:g}…{y1:g} mm")
        for sb, lo, hi in ((self.goto_x, x0, x1), (self.goto_y, y0, y1)):
            sb.setRange(lo, hi)

    def set_position(self, state: dict[str, Any]) -> None:
        pos = state.get("pos")
        if pos is None:
            self.x_label.setText("x —")
            self.y_label.setText("y —")
        else:
            self.x_label.setText(f"x {pos[0]:8.3f} mm")
            self.y_label.setText(f"y {pos[1]:8.3f} mm")
        homed = state.get("homed")
        self.homed.setText("<span style='color:#1a7f37'>homed</span>" if homed
                           else "<span style='color:#9a6700'>not homed</span>")

    def set_busy(self, busy: bool, what: str = "") -> None:
        self._busy = busy
        self.busy.setText(what if busy else "")
        self._update_enabled()

    def set_locked(self, locked: bool) -> None:
        self._locked = locked
        self._update_enabled()

    def _update_enabled(self) -> None:
        ok = self._state == "connected" and not self._busy and not self._locked
        for w in (*self.jog_buttons.values(), self.home, self.goto, self.goto_x, self.goto_y, self.step):
            w.setEnabled(ok)
        self.connection.setEnabled(not self._locked and not self._busy)
        self.stop.setEnabled(True)  # always


class InspectionPanel(QWidget):
    """Inspection inputs (raw, white, through-focus frames, last frame, config), run/cancel with progress,
    export."""

    openRawRequested = Signal()
    openWhiteRequested = Signal()
    clearWhiteRequested = Signal()
    openThroughFocusRequested = Signal()
    clearThroughFocusRequested = Signal()
    openDarksRequested = Signal()
    clearDarksRequested = Signal()
    useFrameRequested = Signal()
    configRequested = Signal()
    runRequested = Signal()
    cancelRequested = Signal()
    exportRequested = Signal()

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        lay = QVBoxLayout(self)
        form = QFormLayout()
        self.source = QLabel("—")
        self.source.setWordWrap(True)
        self.white = QLabel("none (the image calibrates itself)")
        self.white.setWordWrap(True)
        self.throughfocus = QLabel("none")
        self.throughfocus.setWordWrap(True)
        self.throughfocus.setToolTip("pinhole frames of the same array imaged ±u behind / in front of the MLA: "
                                     "they read every covered lens' focal error with its sign")
        self.darks = QLabel("none")
        self.darks.setWordWrap(True)
        self.config = QLabel("—")
        self.config.setWordWrap(True)
        for w in (self.source, self.white, self.throughfocus, self.darks, self.config):
            w.setStyleSheet("color: #24292f")
            w.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
        form.addRow("Image", self.source)
        form.addRow("White", self.white)
        form.addRow("Through-focus", self.throughfocus)
        form.addRow("Darks", self.darks)
        form.addRow("Config", self.config)
        lay.addLayout(form)
        row = QHBoxLayout()
        self.open_raw = QPushButton("Open raw…")
        self.open_white = QPushButton("White…")
        self.clear_white = _clear_button("calibrate on the image itself")
        self.use_frame = QPushButton("Last frame")
        self.use_frame.setToolTip("inspect the last captured frame")
        self.open_config = QPushButton("Config…")
        for w in (self.open_raw, self.open_white, self.clear_white, self.use_frame, self.open_config):
            row.addWidget(w)
        lay.addLayout(row)
        tf_row = QHBoxLayout()
        self.open_tf = _button("Through-focus frames…", "choose the +u / −u pinhole frames of the same array (several "
                               "files at once); each needs its .sim.json or .meta.json record")
        self.clear_tf = _clear_button("inspect without through-focus frames")
        self.open_darks = _button("Dark frames…", "dark frames (lens covered, the frames' exposure and gain): their "
                                  "master dark is subtracted first and its hot and dead pixels replaced")
        self.clear_darks = _clear_button("inspect without dark frames")
        tf_row.addWidget(self.open_tf)
        tf_row.addWidget(self.clear_tf)
        tf_row.addWidget(self.open_darks)
        tf_row.addWidget(self.clear_darks)
        tf_row.addStretch(1)
        lay.addLayout(tf_row)
        row2 = QHBoxLayout()
        self.run = _button("Inspect", "calibrate the grid, measure every lens, flag defects", primary=True)
        self.cancel = QPushButton("Cancel")
        self.export = QPushButton("Export report…")
        self.export.setToolTip("write report.json, lenses.csv, defect maps and report.html")
        row2.addWidget(self.run, 1)
        row2.addWidget(self.cancel)
        row2.addWidget(self.export)
        lay.addLayout(row2)
        self.progress = QProgressBar()
        self.progress.setRange(0, 100)
        self.progress.setValue(0)
        self.progress.setFormat("%p%")
        self.status = QLabel("")
        self.status.setWordWrap(True)
        self.status.setFixedHeight(4 * self.status.fontMetrics().lineSpacing() + 4)  # no relayout per update
        self.status.setAlignment(Qt.AlignmentFlag.AlignLeft | Qt.AlignmentFlag.AlignTop)
        self.status.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Fixed)
        lay.addWidget(self.progress)
        lay.addWidget(self.status)
        self.error = ErrorLabel()
        lay.addWidget(self.error)

        self.open_raw.clicked.connect(self.openRawRequested)
        self.open_white.clicked.connect(self.openWhiteRequested)
        self.clear_white.clicked.connect(self.clearWhiteRequested)
        self.open_tf.clicked.connect(self.openThroughFocusRequested)
        self.clear_tf.clicked.connect(self.clearThroughFocusRequested)
        self.open_darks.clicked.connect(self.openDarksRequested)
        self.clear_darks.clicked.connect(self.clearDarksRequested)
        self.use_frame.clicked.connect(self.useFrameRequested)
        self.open_config.clicked.connect(self.configRequested)
        self.run.clicked.connect(self.runRequested)
        self.cancel.clicked.connect(self.cancelRequested)
        self.export.clicked.connect(self.exportRequested)
        self.set_running(False)
        self.export.setEnabled(False)

    def set_running(self, running: bool) -> None:
        self.run.setEnabled(not running)
        self.cancel.setEnabled(running)
        for w in (self.open_raw, self.open_white, self.clear_white, self.open_tf, self.clear_tf, self.open_darks,
                  self.clear_darks, self.use_frame, self.open_config):
            w.setEnabled(not running)


class ScanPanel(QWidget):
    """Scan plan, output folder, run/pause/abort/resume, progress and the wafer map."""

    loadPlanRequested = Signal()
    editPlanRequested = Signal()
    chooseOutRequested = Signal()
    runRequested = Signal()
    pauseToggled = Signal(bool)
    abortRequested = Signal()
    resumeRequested = Signal()

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        outer = QHBoxLayout(self)
        left = QVBoxLayout()
        form = QFormLayout()
        self.plan = QLabel("no plan loaded")
        self.plan.setWordWrap(True)
        self.plan.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
        self.out = QLineEdit()
        self.out.setFont(MONO)
        self.out.setPlaceholderText("output folder (new or empty)")
        form.addRow("Plan", self.plan)
        out_row = QHBoxLayout()
        out_row.addWidget(self.out, 1)
        self.choose_out = QToolButton()  # a tool button: as narrow as its "…", never clipped
        self.choose_out.setText("…")
        self.choose_out.setToolTip("choose the output folder")
        out_row.addWidget(self.choose_out)
        form.addRow("Output", out_row)
        left.addLayout(form)
        self.inspect = QCheckBox("Inspect each position (verdict on the wafer map)")
        self.inspect.setChecked(True)
        left.addWidget(self.inspect)
        row = QGridLayout()
        self.load = QPushButton("Load plan…")
        self.edit = QPushButton("Edit plan…")
        self.run = _button("Run scan", primary=True)
        self.pause = QPushButton("Pause")
        self.pause.setCheckable(True)
        self.abort = QPushButton("Abort")
        self.abort.setStyleSheet("QPushButton:enabled { color: #cf222e; font-weight: bold; }")
        self.resume = QPushButton("Resume")
        self.resume.setToolTip("continue the last aborted or failed scan in the same folder")
        # two rows (plan and start; then the running scan's controls): six buttons in one row did not fit
        # the column at the default window size and Qt squeezed them below their text ("un sca")
        for k, w in enumerate((self.load, self.edit, self.run, self.pause, self.abort, self.resume)):
            _fit_text(w, "Continue" if w is self.pause else "")
            row.addWidget(w, k // 3, k % 3)
        left.addLayout(row)
        self.progress = QProgressBar()
        self.progress.setFormat("no plan")
        self.progress.setRange(0, 1)
        self.progress.setValue(0)
        left.addWidget(self.progress)
        self.status = QLabel("")
        self.status.setWordWrap(True)
        left.addWidget(self.status)
        self.error = ErrorLabel()
        left.addWidget(self.error)
        left.addStretch(1)
        lw = QWidget()
        lw.setLayout(left)
        lw.setMinimumWidth(max(340, lw.minimumSizeHint().width()))
        lw.setMaximumWidth(max(460, lw.minimumSizeHint().width()))  # a large font widens the column, never clips
        outer.addWidget(lw)
        self.wafer = WaferMap()
        self.wafer.setMinimumHeight(160)
        outer.addWidget(self.wafer, 1)

        self.load.clicked.connect(self.loadPlanRequested)
        self.edit.clicked.connect(self.editPlanRequested)
        self.choose_out.clicked.connect(self.chooseOutRequested)
        self.run.clicked.connect(self.runRequested)
        self.pause.toggled.connect(self._pause_clicked)
        self.abort.clicked.connect(self.abortRequested)
        self.resume.clicked.connect(self.resumeRequested)
        self.set_running(False, can_resume=False, has_plan=False)

    def _pause_clicked(self, on: bool) -> None:
        self.pause.setText("Continue" if on else "Pause")
        self.pauseToggled.emit(on)

    def set_running(self, running: bool, *, can_resume: bool, has_plan: bool) -> None:
        self.run.setEnabled(not running and has_plan)
        self.load.setEnabled(not running)
        self.out.setEnabled(not running)
        self.choose_out.setEnabled(not running)
        self.inspect.setEnabled(not running)
        self.pause.setEnabled(running)
        self.abort.setEnabled(running)
        self.resume.setEnabled(not running and can_resume)
        if not running:
            self.pause.blockSignals(True)
            self.pause.setChecked(False)
            self.pause.setText("Pause")
            self.pause.blockSignals(False)
