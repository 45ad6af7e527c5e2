"""scipy.fft.rfft2 without importing scipy.fft: the calibration's one transform, bit for bit scipy's.

Why: importing the scipy.fft package costs 0.12 s (its array-API layer and scipy.special) on every
`mlaqc inspect`, for a transform its pocketfft extension does in 2 ms. The extension is loaded on its own
and called with the arguments scipy.fft.rfft2 gives it (tests/test_fast_paths.py checks the result against
scipy.fft.rfft2 bit for bit); if that ever fails (another SciPy layout), scipy.fft itself is used.
"""

from __future__ import annotations

import glob
import importlib.util
import os

import numpy as np

_EXTENSION: list = []  # [module] once loaded, [None] when it cannot be


def rfft2(a: np.ndarray, workers: int = 1) -> np.ndarray:
    """scipy.fft.rfft2(a, workers=workers) of a 2-D float32 or float64 array."""
    ext = _pocketfft()
    if ext is not None and a.ndim == 2 and a.dtype in (np.float32, np.float64):
        try:
            return ext.r2c(a, (0, 1), True, 0, None, workers)  # forward, norm "backward", new output
        except (TypeError, ValueError, AttributeError):
            pass
    import scipy.fft

    return scipy.fft.rfft2(a, workers=workers)


def _pocketfft():
    """SciPy's pocketfft extension module, loaded alone (not registered as a module), or None."""
    if not _EXTENSION:
        module = None
        try:
            import scipy

            paths = glob.glob(os.path.join(scipy.__path__[0], "fft", "_pocketfft", "pypocketfft*"))
            spec = importlib.util.spec_from_file_location("mlaqc_scipy_fft.pypocketfft", paths[0]) if paths else None
            if spec is not None and spec.loader is not None:
                module = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(module)
        except Exception:  # noqa: BLE001 - any failure: scipy.fft is the way
            module = None
        _EXTENSION.append(module)
    return _EXTENSION[0]
