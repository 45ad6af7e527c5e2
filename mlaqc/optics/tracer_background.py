"""The ray tracer's variants compiled in the background of the first command that traces.

`pip install -e .` compiles the variants the shipped fixtures use (tracer_variants.INSTALL_VARIANTS) and
leaves the rest so that the install stays short; the first command that makes a Numba renderer starts
one process at the idle priority (`python -m mlaqc.optics.tracer_compile_job`) that waits for that command
to end (a minute at most), then compiles any variant not in Numba's cache (the fixtures' first, where an
install could not compile them), and says so on screen. A stamp records that
every variant is compiled for these sources, this Numba and this Python, so later commands check a file,
not the cache. A command that needs a variant before the background has reached it compiles it itself, as
on first use before (said on screen). MLAQC_BACKGROUND_COMPILE=0 never starts one (the tests, the
background job itself, `mlaqc kernels`, the install).
"""

from __future__ import annotations

import hashlib
import os
import platform
import subprocess
import sys
import threading
from pathlib import Path
from typing import TextIO

from mlaqc.optics.kernel_sources import TRACER_SOURCES, digest
from mlaqc.user_cache import cache_dir

ENV_SWITCH = "MLAQC_BACKGROUND_COMPILE"
HERE = Path(__file__).resolve().parent
# what the compiled variants depend on: the kernels' sources (Numba's cache is stamped with them too,
# kernel_sources) and the variants' list
SOURCES = (*TRACER_SOURCES, HERE / "tracer_variants.py")
_STARTED = threading.Event()


def stamp_path() -> Path:
    """Beside Numba's cache of the kernel (the package's __pycache__) when writable, else the user's cache."""
    folder = HERE / "__pycache__"
    if (folder.is_dir() and os.access(folder, os.W_OK)) or (not folder.exists() and os.access(HERE, os.W_OK)):
        return folder / "tracer_variants.ready"
    return cache_dir() / "tracer_variants.ready"


def log_path() -> Path:
    return cache_dir() / "tracer-compile.log"


def lock_path() -> Path:
    return cache_dir() / "tracer-compile.lock"


def sources_key() -> str:
    """What the compiled variants depend on: the kernel's sources, Numba's and Python's versions, the machine."""
    from importlib.metadata import PackageNotFoundError, version

    h = hashlib.sha1()
    h.update(digest(SOURCES).encode())
    try:
        numba = version("numba")
    except PackageNotFoundError:
        numba = "none"
    h.update(f"{numba} {sys.version} {platform.machine()}".encode())
    return h.hexdigest()


def all_compiled() -> bool:
    """True when the stamp says every variant is compiled for the current sources."""
    try:
        return stamp_path().read_text().strip() == sources_key()
    except OSError:
        return False


def mark_all_compiled() -> None:
    """Write the stamp (atomically; a read-only place is left unstamped)."""
    from mlaqc.atomic import write_bytes_atomic

    path = stamp_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(path, (sources_key() + "\n").encode())
    except OSError:
        pass


def forget() -> None:
    """Remove the stamp (the cache is being rebuilt)."""
    stamp_path().unlink(missing_ok=True)


def running() -> bool:
    """Whether a background compile holds its lock now."""
    import fcntl

    path = lock_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(fh, fcntl.LOCK_UN)
    return False


def start_if_needed(stream: TextIO | None = None) -> bool:
    """Once per process: start the background compile unless every variant is compiled, one is running, or
    it is switched off; say so on `stream` (stderr). True when one was started."""
    if _STARTED.is_set() or os.environ.get(ENV_SWITCH, "1") == "0":
        return False
    _STARTED.set()
    try:
        if all_compiled() or running():
            return False
        log = log_path()
        with open(log, "ab") as out:
            subprocess.Popen([sys.executable, "-m", "mlaqc.optics.tracer_compile_job", str(os.getpid())],
                             stdin=subprocess.DEVNULL,
                             stdout=out, stderr=subprocess.STDOUT, start_new_session=True, close_fds=True,
                             env={**os.environ, ENV_SWITCH: "0"})
    except OSError:
        return False  # no cache folder, no process: each variant compiles on its first use, as before
    print(f"mlaqc: compiling the ray tracer's other variants in the background, at idle priority (a few minutes; "
          f"log {log}; `mlaqc kernels --check` says which are ready)", file=stream or sys.stderr, flush=True)
    return True
