"""The main window's layout: central image and verdict banner, docks, status bar, menus, and the widgets' signals."""

from __future__ import annotations

from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtCore import Qt
from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import (QAbstractItemView, QDockWidget, QHeaderView, QLabel, QMainWindow, QTableView,
                               QVBoxLayout, QWidget)

from gui.history import HistoryPanel
from gui.lightfield import LightFieldPanel
from gui.panels import CameraPanel, InspectionPanel, ScanPanel, StagePanel
from gui.widgets import (MONO, DefectSortProxy, DefectTableModel, ImagePanel, LensDetail, LogView, StatusDot,
                         VerdictBanner)


class WindowLayoutMixin:
    """Part of gui.app.MainWindow: builds its widgets and connects their signals to the window's methods."""

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
