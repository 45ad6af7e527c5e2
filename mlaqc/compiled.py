"""Compiled kernels without a compile on the user's time, and without Numba's start-up on every run.

A kernel is a Numba function written as before, decorated with a `Flavour` (its Numba options). The ones a
command calls on its hot path also declare the argument types they are called with (`Flavour.aot`): at
install time `setup.py` compiles those ahead of time (numba.pycc, `mlaqc.compiled_build`) into one
extension module, `mlaqc/_kernels*.so`, for this machine's CPU and with each kernel's own Numba options,
so it runs the same machine code as the JIT would. A call whose arguments match a declared signature runs
that code (importing it takes a millisecond; `import numba` and loading its cache took 0.4 s). Anything
else (no extension built, a kernel source edited since, other argument types, kernels without a declared
signature) goes to Numba's JIT as before, with its on-disk cache; the first compile in a process says so
once on stderr, and the time it takes is kept apart (`compile_seconds`) so stage timings do not carry it.

The extension is used only while its stamp (the kernel sources, the Numba and llvmlite releases, NumPy's
major version and this CPU's flags) matches, and only if it loads: a stale or damaged one is never called,
and `mlaqc kernels` rebuilds it.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.machinery
import importlib.util
import os
import re
import sys
import threading
import time
import types
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mlaqc.user_cache import cache_dir

# the modules whose declared kernels are compiled ahead of time (their sources make the stamp)
AOT_MODULES = (
    "mlaqc.inspection.rawio_kernels",
    "mlaqc.inspection.calibrate_kernels",
    "mlaqc.inspection.metrics_kernels",
    "mlaqc.inspection.measure_kernels",
    "mlaqc.inspection.throughfocus_kernels",
    "mlaqc.report.format_kernels",
)
EXTENSION = "_kernels"  # mlaqc/_kernels<EXT_SUFFIX>, with its stamp in mlaqc/_kernels.stamp
PACKAGE_DIR = Path(__file__).resolve().parent

_LOCK = threading.RLock()


def _after_fork() -> None:
    """A forked child gets its own lock (one held by another thread at the fork would never be released)."""
    global _LOCK
    _LOCK = threading.RLock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork)
_STATE: dict[str, Any] = {"module": None, "loaded": False, "why": "", "compile_s": 0.0, "noticed": False,
                          "announced": set()}
_ALL: list["Kernel"] = []

# numpy dtype of each short type code used in declared signatures (Numba's own spelling)
_CODES = {"b1": np.bool_, "u1": np.uint8, "u2": np.uint16, "i4": np.int32, "i8": np.int64, "f4": np.float32,
          "f8": np.float64}
_ARG = re.compile(r"^\s*(\w+)\s*(?:\[([^\]]*)\])?\s*$")


def _arg_key(code: str) -> tuple:
    """The runtime key of one declared argument type: ('a', dtype char, ndim, C?) or ('s', kind)."""
    m = _ARG.match(code)
    if not m or m.group(1) not in _CODES:
        raise ValueError(f"unsupported kernel argument type {code!r}")
    dtype = np.dtype(_CODES[m.group(1)])
    if m.group(2) is None:
        return ("s", "b" if dtype.kind == "b" else ("i" if dtype.kind in "iu" else "f"), dtype.char)
    dims = [d.strip() for d in m.group(2).split(",")]
    return ("a", dtype.char, len(dims), dims[-1] == "::1")


def split_signature(signature: str) -> list[str]:
    """The argument types of a declared signature 'f4[:, ::1], i8, ...' (commas inside [] kept)."""
    parts, depth, cur = [], 0, ""
    for ch in signature:
        depth += (ch == "[") - (ch == "]")
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    return [p.strip() for p in parts + [cur] if p.strip()]


def _matches(keys: tuple, args: tuple) -> bool:
    """True when every argument has exactly the declared type (an AOT function does not check types)."""
    if len(keys) != len(args):
        return False
    for key, a in zip(keys, args):
        if key[0] == "a":
            if (type(a) is not np.ndarray and not isinstance(a, np.ndarray)) or a.dtype.char != key[1] \
                    or a.ndim != key[2] or (key[3] and not a.flags.c_contiguous) or not a.flags.aligned \
                    or not a.dtype.isnative:
                return False
        elif key[1] == "b":
            if not isinstance(a, (bool, np.bool_)):
                return False
        elif isinstance(a, (bool, np.bool_)):
            return False
        elif key[1] == "i":
            if not (type(a) is int or (isinstance(a, np.integer) and a.dtype.char == key[2])):
                return False
        elif not (type(a) is float or (isinstance(a, np.floating) and a.dtype.char == key[2])):
            return False
    return True


class Kernel:
    """One Numba kernel: the AOT code for a declared signature, else the JIT dispatcher (made on demand)."""

    def __init__(self, py_func: Callable, options: dict, signatures: tuple[str, ...]):
        self.py_func = py_func
        self.options = dict(options)
        self.signatures = signatures
        self.__name__ = py_func.__name__
        self.__qualname__ = py_func.__qualname__
        self.__module__ = py_func.__module__
        self.__doc__ = py_func.__doc__
        self.__wrapped__ = py_func
        self._keys = [tuple(_arg_key(a) for a in split_signature(s)) for s in signatures]
        self._aot: list[tuple[tuple, Callable]] | None = None if signatures else []
        self._dispatcher = None
        _ALL.append(self)

    @property
    def export_names(self) -> list[str]:
        """The extension's symbol for each declared signature."""
        short = self.__module__.rsplit(".", 1)[-1]
        return [f"{short}__{self.__name__}__{i}" for i in range(len(self.signatures))]

    def __call__(self, *args):
        aot = self._aot if self._aot is not None else self._bind()
        for keys, fn in aot:
            if _matches(keys, args):
                return fn(*args)
        return _timed_jit(self, args)

    def _bind(self) -> list:
        module = extension()
        found = [] if module is None else [(k, getattr(module, n)) for k, n in zip(self._keys, self.export_names)
                                           if hasattr(module, n)]
        self._aot = found
        return found

    @property
    def dispatcher(self):
        """The Numba JIT dispatcher (cache=True as declared), made with every kernel of its module."""
        if self._dispatcher is None:
            _jit_module(sys.modules[self.__module__])
        return self._dispatcher


class Flavour:
    """A set of Numba options: `@flavour` makes a JIT kernel, `@flavour.aot(sig, ...)` one compiled ahead."""

    def __init__(self, **options):
        self.options = options

    def __call__(self, fn: Callable) -> Kernel:
        return Kernel(fn, self.options, ())

    def aot(self, *signatures: str) -> Callable[[Callable], Kernel]:
        """Declare the argument types (Numba spelling, e.g. 'f4[:, ::1], i8') of the AOT-compiled variants."""
        return lambda fn: Kernel(fn, self.options, signatures)


def kernel(**options) -> Flavour:
    """A kernel flavour with these Numba options (`nogil`, `error_model`, `fastmath`, `inline`, ...)."""
    return Flavour(**options)


def _jit_module(module: types.ModuleType) -> None:
    """Make the JIT dispatcher of every kernel of `module`, each seeing the others as dispatchers."""
    from numba import njit

    with _LOCK:
        kernels = {k: v for k, v in vars(module).items() if isinstance(v, Kernel) and v.__module__ == module.__name__}
        if all(v._dispatcher is not None for v in kernels.values()):
            return
        jit_globals = dict(vars(module))
        made = {}
        for name, k in kernels.items():
            f = k.py_func
            fresh = types.FunctionType(f.__code__, jit_globals, f.__name__, f.__defaults__, f.__closure__)
            fresh.__qualname__, fresh.__doc__ = f.__qualname__, f.__doc__
            made[name] = jit_globals[name] = njit(**k.options)(fresh)
        for name, v in list(jit_globals.items()):  # kernels imported from other modules
            if isinstance(v, Kernel) and v.__module__ != module.__name__:
                jit_globals[name] = v.dispatcher
        for name, k in kernels.items():  # published only now: no compile can see a half-made module
            k._dispatcher = made[name]


def _timed_jit(k: Kernel, args: tuple):
    """Call the JIT dispatcher; a first call per signature (a compile, or a load from Numba's cache) is
    timed apart, and a compile is announced once."""
    d = k.dispatcher
    if _known(d, args):
        return d(*args)
    with _LOCK:  # one first call at a time: Numba compiles one at a time anyway, and the time adds up once
        start = time.perf_counter()
        if not _cached(d):
            _notice()
        out = d(*args)
        _STATE["compile_s"] += time.perf_counter() - start
    return out


def _known(d, args: tuple) -> bool:
    """True when the dispatcher already has code for these arguments (no compile or cache load ahead)."""
    try:
        return tuple(d.typeof_pyval(a) for a in args) in d.overloads
    except Exception:  # noqa: BLE001 - an untypable argument: let the dispatcher say so
        return False


def _cached(d) -> bool:
    """True when Numba's on-disk cache has some code of this kernel (a load, not a compile, is ahead)."""
    try:
        return bool(d._cache._cache_file._load_index())
    except Exception:  # noqa: BLE001 - no cache at all
        return False


def _notice() -> None:
    """One line on stderr, once per process, before the first compile."""
    with _LOCK:
        if _STATE["noticed"]:
            return
        _STATE["noticed"] = True
    why = aot_status()[1]
    print(f"mlaqc: compiling kernels once for this machine (about a minute; kept in Numba's cache) — {why}; "
          "`mlaqc kernels` compiles them all ahead of time", file=sys.stderr, flush=True)


@contextlib.contextmanager
def compile_notice(what: str, after_s: float = 1.5):
    """Around a JIT call that may compile (a tracer variant the install did not compile: 25-55 s on first
    use, on 2 cores): if it has not returned after `after_s`, say once per process on stderr that `what` is
    being compiled, and why it is slow only this once."""
    def say() -> None:
        with _LOCK:
            if what in _STATE["announced"]:
                return
            _STATE["announced"].add(what)
        print(f"mlaqc: compiling {what} once for this machine (under a minute; kept in Numba's cache for every "
              "later run; `mlaqc kernels` compiles all of it ahead) ...", file=sys.stderr, flush=True)

    timer = threading.Timer(after_s, say)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


def announced(what: str) -> None:
    """Treat `what` as announced: a process that compiles it on purpose (`mlaqc kernels`) says so itself."""
    with _LOCK:
        _STATE["announced"].add(what)


def compile_seconds() -> float:
    """Seconds this process spent compiling kernels (stage timings subtract it)."""
    return float(_STATE["compile_s"])


def net_clock() -> float:
    """time.perf_counter() less the time this process spent compiling (or first loading) JIT kernels: stage
    timings read on it do not carry a one-off compile."""
    return time.perf_counter() - _STATE["compile_s"]


def current_stamp() -> str:
    """What the extension must have been built from: the AOT kernel sources, this file and this CPU."""
    h = hashlib.sha256()
    for name in AOT_MODULES:
        h.update((PACKAGE_DIR.parent / (name.replace(".", "/") + ".py")).read_bytes())
    h.update(Path(__file__).read_bytes())
    h.update((PACKAGE_DIR / "compiled_build.py").read_bytes())
    h.update(_compiler_identity())
    h.update(cpu_identity().encode())
    return h.hexdigest()[:20]


def _compiler_identity() -> bytes:
    """The Numba and llvmlite releases (their _version.py, read without importing them: the JIT that the
    build must match) and NumPy's major version (its C ABI)."""
    parts = [f"numpy {np.__version__.split('.')[0]}".encode()]
    for name in ("numba", "llvmlite"):
        try:
            spec = importlib.util.find_spec(name)
            parts.append((Path(spec.origin).parent / "_version.py").read_bytes() if spec and spec.origin else b"")
        except (ImportError, OSError, ValueError):
            parts.append(b"")
    return b"\0".join(parts)


def cpu_identity() -> str:
    """This CPU's model and instruction-set flags (the extension is compiled for them)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        import platform

        return f"{platform.machine()} {platform.processor()}"
    fields = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key in ("model name", "flags", "Features", "CPU part") and key not in fields:
            fields[key] = " ".join(sorted(value.split()))
        if not line.strip() and fields:
            break
    return "|".join(f"{k}={v}" for k, v in sorted(fields.items()))


def extension_paths() -> list[Path]:
    """Where the extension may be: in the package (built at install), else in the user's cache."""
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    return [PACKAGE_DIR / f"{EXTENSION}{suffix}", cache_dir() / "kernels" / f"{EXTENSION}{suffix}"]


def extension():
    """The AOT extension module when one built from the current sources for this CPU exists, else None."""
    with _LOCK:
        if _STATE["loaded"]:
            return _STATE["module"]
        _STATE["loaded"] = True
        if os.environ.get("MLAQC_AOT", "1") == "0":
            _STATE["why"] = "MLAQC_AOT=0"
            return None
        stamp, why = current_stamp(), "no ahead-of-time build"
        for path in extension_paths():
            stamp_file = path.parent / f"{EXTENSION}.stamp"
            if not path.exists():
                continue
            if not stamp_file.exists() or stamp_file.read_text().strip() != stamp:
                why = f"the ahead-of-time build in {path.parent} is out of date"
                continue
            try:
                spec = importlib.util.spec_from_file_location(f"mlaqc.{EXTENSION}", path)
                module = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(module)
            except Exception as exc:  # noqa: BLE001 - a damaged or foreign build: the JIT does the work
                why = f"the ahead-of-time build {path} does not load ({type(exc).__name__}: {exc})"
                continue
            if not hasattr(module, f"stamp_{stamp}"):  # the stamp file and the code disagree
                why = f"the ahead-of-time build in {path.parent} is out of date"
                continue
            _STATE["module"], _STATE["why"] = module, f"ahead-of-time build {path}"
            return module
        _STATE["why"] = why
        return None


def aot_status() -> tuple[bool, str]:
    """(whether the AOT extension is in use, why or why not)."""
    module = extension()
    return module is not None, _STATE["why"]


def declared_kernels() -> list[Kernel]:
    """Every kernel of the AOT modules that declares signatures (imports those modules)."""
    for name in AOT_MODULES:
        importlib.import_module(name)
    return [k for k in _ALL if k.signatures and k.__module__ in AOT_MODULES]
