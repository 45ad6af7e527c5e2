"""Numba's on-disk cache of the tracer's kernel modules, made stale by anything the kernels are compiled from.

Numba stamps a cached function with its own file only. The tracer's kernels inline helpers and freeze
constants from other modules (their sine, their Sobol' generator, the pupil's sampling and lattice
constants), so after an edit to one of those alone, a `git pull` into an editable install say, Numba kept
loading the old machine code: silently wrong frames. `register(sources)` puts a cache locator in front of
Numba's own for the functions of the files among `sources`: the cache goes where Numba's own locators put
it, and its stamp is a digest of the sources as this process loaded them (a process that imported a
helper before a `git pull` stamps what it compiles with the old helper's code, not the new file's).
Importing this module does not import Numba (tracer_background reads TRACER_SOURCES to check its own
stamp)."""

from __future__ import annotations

import hashlib
import importlib
import os
import types
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
# what the ray tracer's kernels are compiled from: the files of its kernel modules (files: the first of them
# to be imported registers them all, kernel_jit), the three modules it takes its layout and most of its
# helpers from (every function and constant they define), and the four names it borrows from three others,
# whose edits elsewhere (the NumPy tracer, the scenes, the lattice) leave the kernels as they are
KERNEL_FILES: tuple = tuple(HERE / f"{name}.py" for name in
                            ("kernel_jit", "kernel_geometry", "kernel_sampling", "raytrace_kernels"))
TRACER_SOURCES: tuple = (*KERNEL_FILES, "mlaqc.optics.kernel_layout", "mlaqc.optics.lowdisc",
                         "mlaqc.optics.unitcircle", ("mlaqc.optics.scene", "aperture_point"),
                         ("mlaqc.optics.scene", "FOUR_OVER_PI"), ("mlaqc.optics.raytrace", "INV_ROW_PAIR_HEX"),
                         ("mlaqc.optics.lattice", "SQRT3_2"))

_DIGESTS: dict[str, str] = {}  # a kernel module's file -> the digest of what it is compiled from
_MARK = "_mlaqc_sources_locator"  # set on the locator class (a module reload makes a second one)


def register(sources: tuple) -> None:
    """Stamp the Numba cache of the functions of every file among `sources` with `digest(sources)`, taken
    now; call while the first of those files is imported, before any of their cached functions is decorated."""
    from numba.core import config

    stamp = digest(sources)
    for src in sources:
        if isinstance(src, Path):
            _DIGESTS[os.path.realpath(src)] = stamp
    if config.CACHE_LOCATOR_CLASSES:  # Numba then ignores its locator list, and so this stamp
        warnings.warn("NUMBA_CACHE_LOCATOR_CLASSES is set: the ray tracer's cache is stamped by Numba alone, "
                      "and can serve old code after an edit to a module its kernels inline from", stacklevel=2)
    impl = _cache_impl()
    others = [c for c in impl._locator_classes if not getattr(c, _MARK, False)]
    impl._locator_classes = [_locator_class(), *others]


def digest(sources: tuple) -> str:
    """SHA-1 over the sources: a file's name and bytes (a missing one counts as such); a module's
    functions' code and constants as loaded; a (module, name) pair's function code or constant."""
    h = hashlib.sha1()
    for src in sources:
        if isinstance(src, tuple):
            module, name = src
            _feed(h, f"{module}.{name}", getattr(importlib.import_module(module), name))
        elif isinstance(src, str):
            mod = importlib.import_module(src)
            for name in sorted(vars(mod)):
                value = vars(mod)[name]
                if not isinstance(value, types.FunctionType) or value.__module__ == src:
                    _feed(h, f"{src}.{name}", value)
        else:
            path = Path(src)
            _feed(h, path.name, path.read_bytes() if path.exists() else b"<missing>")
    return h.hexdigest()


def _feed(h, label: str, value) -> None:
    """One labelled item into the hash, length-prefixed: a function's compiled code, an array's dtype,
    shape and bytes, bytes as they are, a number or string by repr; anything else (modules, classes) not.
    A Numba dispatcher counts as the Python function it compiles."""
    value = getattr(value, "py_func", value)
    if isinstance(value, types.FunctionType):
        data = _code_bytes(value.__code__)
    elif isinstance(value, np.ndarray):
        data = f"{value.dtype.str}{value.shape}".encode() + np.ascontiguousarray(value).tobytes()
    elif isinstance(value, bytes):
        data = value
    elif isinstance(value, (int, float, complex, str, tuple)):
        data = repr(value).encode()
    else:
        return
    for part in (label.encode(), data):
        h.update(len(part).to_bytes(8, "little"))
        h.update(part)


def _code_bytes(code: types.CodeType) -> bytes:
    """A function's compiled code as bytes: its bytecode, names and constants, nested code alike (not
    `marshal`, whose output follows reference counts and so differs between processes)."""
    parts = [code.co_code, repr((code.co_names, code.co_varnames, code.co_freevars, code.co_cellvars,
                                 code.co_argcount, code.co_kwonlyargcount, code.co_flags)).encode()]
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            parts.append(_code_bytes(const))
        elif isinstance(const, frozenset):  # `x in {...}`: its order follows the string hash seed
            parts.append(repr(sorted(repr(c) for c in const)).encode())
        else:
            parts.append(repr(const).encode())
    return b"\0".join(len(p).to_bytes(8, "little") + p for p in parts)


def _cache_impl():
    """Numba's cache implementation class (named `_CacheImpl` before 0.59)."""
    from numba.core import caching

    return getattr(caching, "CacheImpl", None) or caching._CacheImpl


def _locator_class():
    """The locator: Numba's own for the function (the cache path and file name it would use), stamped
    with the registered digest instead of the file."""
    from numba.core import caching

    class SourcesLocator(caching._CacheLocator):
        def __init__(self, inner, stamp: str) -> None:
            self._inner = inner
            self._stamp = stamp

        def __getattr__(self, name):  # Numba reads the inner locator's _py_file, _lineno, ...
            if name == "_inner":  # not set yet (a copy being made): no recursion
                raise AttributeError(name)
            return getattr(self._inner, name)

        def ensure_cache_path(self) -> None:
            self._inner.ensure_cache_path()

        def get_cache_path(self) -> str:
            return self._inner.get_cache_path()

        def get_source_stamp(self):
            return ("mlaqc-sources", self._stamp)

        def get_disambiguator(self) -> str:
            return self._inner.get_disambiguator()

        @classmethod
        def from_function(cls, py_func, py_file):
            stamp = _DIGESTS.get(os.path.realpath(py_file))  # the same file through a symlink too
            if stamp is None:
                return None
            for other in _cache_impl()._locator_classes:
                if not getattr(other, _MARK, False):
                    inner = other.from_function(py_func, py_file)
                    if inner is not None:
                        return cls(inner, stamp)
            return None

    setattr(SourcesLocator, _MARK, True)
    return SourcesLocator
