"""The report set of one inspection: report.json and lenses.csv (document), the defect map (maps),
report.html (html), written together atomically (write)."""

from mlaqc.lazy import lazy_exports

_EXPORTS = {
    "write_report": "write", "render_report": "write", "write_report_files": "write",
    "build_report_dict": "document", "lenses_csv": "document",
    "load_report": "document", "REPORT_FILES": "document", "render_defect_map": "maps",
    "ERROR_COLOURS": "maps", "VERDICT_COLOURS": "maps", "error_colour": "maps",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
