"""PySide6 desktop QC app. Imports `mlaqc` and `drivers`."""
