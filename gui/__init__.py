"""PySide6 desktop QC app (`mlaqc gui`). Imports `mlaqc` and `drivers`; nothing imports `gui`.

Modules: `commands` (the CLI entry; no Qt import until the command runs), `app` (the main window's
signals, state and closing, and `run`), assembled from the `window_*` mixins (layout, workers, devices,
inputs, results, reports, scans), `workers` (one thread per device and per kind of long job; see its docstring for the threading
model), `inspection_worker` and `scan_worker` (the inspection's and the scan's), `panels` and `widgets` (pure
widgets), `qt` (Qt import point with a guard against a PySide6 6.12
reference-count bug on Python 3.11), `screenshot` (regenerates docs/screenshot.png offscreen).
"""
