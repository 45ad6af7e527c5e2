"""mlaqc: microlens-array QC — plenoptic camera model, raw capture, per-lens defect identification."""

import os as _os

# One BLAS thread unless the user says otherwise (read when NumPy loads, so only if mlaqc is imported
# first): mlaqc's matrix products are small (10^4 x 20), gain nothing from BLAS threads, and OpenBLAS'
# idle threads spin after each product, taking the cores from mlaqc's own kernel pools (measured: the
# indexes of the next frame 47 -> 70 ms on average on 2 cores).
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
