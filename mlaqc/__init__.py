"""mlaqc: microlens-array QC — plenoptic camera model, raw capture, per-lens defect identification."""

__version__ = "0.1.0"
