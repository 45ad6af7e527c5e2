"""From a raw frame to per-lens defects: raw I/O, grid calibration, sub-images, image-quality indexes,
identification, and the pipeline that runs them (raw -> grid -> sub-images -> indexes -> defects)."""

from mlaqc.lazy import lazy_exports

_EXPORTS = {
    "inspect_image": "pipeline", "inspect_file": "pipeline", "load_frame": "pipeline",
    "load_raw": "rawio", "write_raw": "raw_write", "RawFrame": "rawio",
    "calibrate": "calibrate", "load_grid": "calibrate", "Grid": "calibrate",
    "identify": "identify", "InspectionResult": "results", "Defect": "results",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
