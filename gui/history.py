"""The history panel: the arrays of a lot as the results database has them (mlaqc.resultsdb) — each array's
latest verdict, flags, station and time, the lot's yield and its repeating defects. A pure widget: it asks
for a lot (`refreshRequested`) and shows what the main window hands back (`show_history`), read in the io
worker (`IoWorker.readHistory`), so a slow or shared database never blocks the window."""

from __future__ import annotations

from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtCore import Signal
from PySide6.QtGui import QColor
from PySide6.QtWidgets import (QHBoxLayout, QHeaderView, QLabel, QLineEdit, QPushButton, QTableWidget,
                               QTableWidgetItem, QVBoxLayout, QWidget)

from gui.widgets import ErrorLabel

COLUMNS = ("wafer", "array", "verdict", "flagged", "out of tol.", "inspected", "station", "report")  # lot.ARRAY_COLUMNS
VERDICT_COLOURS = {"PASS": "#1a7f37", "FAIL": "#cf222e"}


def read_history(lot: str | None) -> dict[str, Any]:
    """What the panel shows of `lot` (None: every lot), read from the default results database; runs in a
    worker thread. DatabaseError propagates (one sentence)."""
    from mlaqc.resultsdb import lot as views
    from mlaqc.resultsdb.store import open_database

    lot = lot or None
    with open_database(create=False) as db:
        return {"lot": lot, "where": db.where, "rows": [list(r) for r in views.arrays(db, lot)],
                "yield": views.yield_table(db, lot),
                "repeats": [d.sentence() for d in views.repeating_defects(db, lot)]}


class HistoryPanel(QWidget):
    """A lot's arrays and what they read; asks for them with `refreshRequested(lot)`."""

    refreshRequested = Signal(str)

    def __init__(self) -> None:
        super().__init__()
        self.lot = QLineEdit()
        self.lot.setPlaceholderText("lot (empty: every lot)")
        self.refresh = QPushButton("Show")
        self.refresh.setToolTip("read the lot's arrays from the results database")
        self.summary = QLabel("The results database's arrays of a lot appear here.")
        self.summary.setWordWrap(True)
        self.error = ErrorLabel()
        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.verticalHeader().hide()
        self.table.setEditTriggers(QTableWidget.EditTrigger.NoEditTriggers)
        self.table.setSortingEnabled(True)
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        self.table.horizontalHeader().setStretchLastSection(True)
        top = QHBoxLayout()
        top.addWidget(self.lot, 1)
        top.addWidget(self.refresh)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(4, 4, 4, 4)
        lay.addLayout(top)
        lay.addWidget(self.summary)
        lay.addWidget(self.error)
        lay.addWidget(self.table, 1)
        self.refresh.clicked.connect(self._ask)
        self.lot.returnPressed.connect(self._ask)

    def _ask(self) -> None:
        self.refresh.setEnabled(False)
        self.error.clear_error()
        self.refreshRequested.emit(self.lot.text().strip())

    def show_history(self, data: dict[str, Any]) -> None:
        """Fill the table and the summary from `read_history`'s dict."""
        self.refresh.setEnabled(True)
        rows = data["rows"]
        self.table.setSortingEnabled(False)
        self.table.setRowCount(len(rows))
        for r, row in enumerate(rows):
            for c, value in enumerate(row):
                item = QTableWidgetItem()
                item.setData(0, value if isinstance(value, (int, float)) else ("" if value is None else str(value)))
                if c == 2 and value in VERDICT_COLOURS:
                    item.setForeground(QColor(VERDICT_COLOURS[value]))
                self.table.setItem(r, c, item)
        self.table.setSortingEnabled(True)
        passed = sum(y["passed"] for y in data["yield"])
        total = sum(y["arrays"] for y in data["yield"])
        head = (f"{data['lot'] or 'every lot'}: {total} arrays, {passed} pass"
                + (f" ({passed / total:.1%})" if total else "") + f" — {data['where']}")
        self.summary.setText("\n".join([head, *data["repeats"]]))

    def show_error(self, text: str) -> None:
        self.refresh.setEnabled(True)
        self.error.show_error(text)
