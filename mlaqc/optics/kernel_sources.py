"""Numba's on-disk cache of a kernel module, made stale by any source the kernels are compiled from.

Numba stamps a cached function with its own file's modification time and size only. A kernel inlines
helpers and freezes constants from other modules (raytrace_kernels takes its sine, its Sobol' generator,
the pupil's sampling and lattice constants from five), so after an edit to one of those alone, a
`git pull` into an editable install say, Numba kept loading the old machine code: silently wrong frames.
`register(kernels_file, sources)` puts a cache locator in front of Numba's own for that file's functions:
the cache goes where Numba's own locators put it, and its stamp is a digest of every source. Importing
this module does not import Numba (tracer_background reads TRACER_SOURCES to check its stamp).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

HERE = Path(__file__).resolve().parent
# what the ray tracer's kernels are compiled from: raytrace_kernels.py and the two modules it takes most
# of its helpers from, whole; and the single names it borrows from three others, whose edits elsewhere
# (the NumPy tracer, the scenes, the lattice) leave the kernels as they are
TRACER_SOURCES: tuple = (HERE / "raytrace_kernels.py", HERE / "lowdisc.py", HERE / "unitcircle.py",
                         ("mlaqc.optics.scene", "aperture_point"), ("mlaqc.optics.scene", "FOUR_OVER_PI"),
                         ("mlaqc.optics.raytrace", "INV_ROW_PAIR_HEX"), ("mlaqc.optics.lattice", "SQRT3_2"))

_SOURCES: dict[str, tuple] = {}  # a kernel module's file -> every source it is compiled from
_LOCATOR: list = []  # the locator class, made on the first registration (it subclasses Numba's)


def register(kernels_file: str, sources: tuple) -> None:
    """Stamp the Numba cache of `kernels_file`'s functions with a digest of `sources` (files, and
    (module, name) pairs: a function's source or a constant's repr); call before its first cached
    function is decorated."""
    _SOURCES[os.path.abspath(kernels_file)] = tuple(sources)
    locator = _locator_class()
    impl = _cache_impl()
    if locator not in impl._locator_classes:
        impl._locator_classes = [locator, *impl._locator_classes]


def digest(sources: tuple) -> str:
    """SHA-1 over the sources: each file's name and bytes (a missing one counts as such), each borrowed
    name's source (a function) or repr (a constant)."""
    import importlib
    import inspect

    h = hashlib.sha1()
    for src in sources:
        if isinstance(src, tuple):
            module, name = src
            obj = getattr(importlib.import_module(module), name)
            h.update(f"{module}.{name}".encode())
            h.update((inspect.getsource(obj) if callable(obj) else repr(obj)).encode())
        else:
            path = Path(src)
            h.update(path.name.encode())
            h.update(path.read_bytes() if path.exists() else b"<missing>")
    return h.hexdigest()


def _cache_impl():
    """Numba's cache implementation class (named `_CacheImpl` before 0.59)."""
    from numba.core import caching

    return getattr(caching, "CacheImpl", None) or caching._CacheImpl


def _locator_class():
    """The locator: Numba's own for the function (the cache path and file name it would use), stamped
    with the digest of the registered sources instead of the file's time and size."""
    if _LOCATOR:
        return _LOCATOR[0]
    from numba.core import caching

    class SourcesLocator(caching._CacheLocator):
        def __init__(self, inner, sources: tuple) -> None:
            self._inner = inner
            self._sources = sources

        def ensure_cache_path(self) -> None:
            self._inner.ensure_cache_path()

        def get_cache_path(self) -> str:
            return self._inner.get_cache_path()

        def get_source_stamp(self):
            return ("mlaqc-sources", digest(self._sources))

        def get_disambiguator(self) -> str:
            return self._inner.get_disambiguator()

        @classmethod
        def from_function(cls, py_func, py_file):
            sources = _SOURCES.get(os.path.abspath(py_file))
            if sources is None:
                return None
            for other in _cache_impl()._locator_classes:
                if other is not cls:
                    inner = other.from_function(py_func, py_file)
                    if inner is not None:
                        return cls(inner, sources)
            return None

    _LOCATOR.append(SourcesLocator)
    return SourcesLocator
