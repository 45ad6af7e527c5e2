"""The scan-plan editor: the plan's TOML in a text box, checked by the scan runner's own parser."""

from __future__ import annotations

import tomllib
from pathlib import Path

from PySide6.QtGui import QFontDatabase
from PySide6.QtWidgets import (QDialog, QDialogButtonBox, QFileDialog, QLabel, QPlainTextEdit, QPushButton,
                               QVBoxLayout, QWidget)

from gui.widgets import ErrorLabel
from mlaqc.atomic import write_bytes_atomic
from mlaqc.errors import InputError

TEMPLATE = Path(__file__).resolve().parent.parent / "fixtures" / "scan_plan_raster.toml"


def parse_plan_text(text: str, source: str = "edited plan"):
    """A validated ScanPlan from TOML text; InputError with one sentence otherwise."""
    from drivers.scan_plan import plan_from_dict

    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"the {source} is not valid TOML: {exc}") from None
    return plan_from_dict(data, source)


class PlanEditor(QDialog):
    """Edit a plan's TOML; OK only once the text is a valid plan. `plan` holds the result."""

    def __init__(self, text: str, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Scan plan")
        self.resize(640, 560)
        self.plan = None
        lay = QVBoxLayout(self)
        lay.addWidget(QLabel("A [raster] table or a [[positions]] list, and an optional [scan] table "
                             "(see fixtures/scan_plan_raster.toml)."))
        self.text = QPlainTextEdit(text)
        self.text.setFont(QFontDatabase.systemFont(QFontDatabase.SystemFont.FixedFont))
        lay.addWidget(self.text, 1)
        self.error = ErrorLabel()
        lay.addWidget(self.error)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel)
        save = QPushButton("Save as…")
        buttons.addButton(save, QDialogButtonBox.ButtonRole.ActionRole)
        lay.addWidget(buttons)
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        save.clicked.connect(self.save_as)

    def check(self) -> bool:
        """Parse the text; show the error sentence if it is not a plan."""
        try:
            self.plan = parse_plan_text(self.text.toPlainText())
        except InputError as exc:
            self.error.show_error(str(exc))
            return False
        self.error.clear_error()
        return True

    def accept(self) -> None:  # noqa: D102 - Qt override: only a valid plan closes the dialog
        if self.check():
            super().accept()

    def save_as(self) -> None:
        """Write the text as a .toml file (atomically), once it is a valid plan."""
        if not self.check():
            return
        path, _ = QFileDialog.getSaveFileName(self, "Save scan plan", "scan_plan.toml", "Scan plan (*.toml)")
        if path:
            write_bytes_atomic(path, self.text.toPlainText().encode("utf-8"))
