"""The user's mlaqc cache: what is built once and kept (models, the ahead-of-time kernels' fallback
place, the tracer's background compile's log and lock), in $MLAQC_CACHE or ~/.cache/mlaqc."""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """$MLAQC_CACHE or ~/.cache/mlaqc (read each time: tests and users point it elsewhere)."""
    return Path(os.environ.get("MLAQC_CACHE", Path.home() / ".cache" / "mlaqc"))
