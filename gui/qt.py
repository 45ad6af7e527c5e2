"""Qt import point of the app, with a guard against PySide6 reference-count bugs on Python < 3.12.

PySide6 6.12.0 (the version installed here) drops references to singletons it never took:

- every call from C++ into a Python callable (a slot run by a C++ signal such as `QTimer.timeout`, a
  queued delivery, a virtual override such as `QGraphicsItem.paint`) lowers ``None``'s reference count
  by one, whatever the callable returns;
- every ``SignalInstance.emit()`` from Python lowers ``True``'s by one (it returns ``True`` unowned).

Measured with a plain `QTimer` and no other code: ``sys.getrefcount(None)`` falls by exactly one per
timeout. Python 3.12 made these singletons immortal, so there it is harmless, and the wheel (built for
the stable ABI) seems to assume that; on Python 3.11 the count reaches zero within seconds of live view
(pyqtgraph paints through Python overrides) and the interpreter aborts with "Fatal Python error:
none_dealloc: deallocating None".

`install_refcount_guard()` probes for the drain once and, only if it is present on a CPython that has
mortal singletons, adds 2**56 references to ``None``, ``True`` and ``False`` (as if that many holders
existed), which makes them effectively immortal as in 3.12: at a million lost references per second
that lasts for two thousand years, and 2**56 leaves room below the 2**63 limit for every real
reference. Nothing else changes. Every module of the app imports Qt through here, so the guard is in
place before the first callback. A PySide6 without the bug leaves the probe clean and nothing is done.
"""

from __future__ import annotations

import ctypes
import sys

from PySide6.QtCore import QObject, Signal

BIAS = 1 << 56
SINGLETONS = (None, True, False)

guard_active = False
_probed = False


def _refcounts() -> tuple[int, ...]:
    return tuple(sys.getrefcount(s) for s in SINGLETONS)


def refcount_drain(samples: int = 32) -> dict[str, int]:
    """References to None/True/False lost over `samples` C++-to-Python calls and `samples` emits."""

    class _Probe(QObject):
        sig = Signal()

    probe = _Probe()
    probe.objectNameChanged.connect(lambda _name: None)  # C++ signal -> Python callable
    probe.sig.connect(lambda: None)
    before = _refcounts()
    for i in range(samples):
        probe.setObjectName(f"probe{i}")
        probe.sig.emit()
    after = _refcounts()
    probe.deleteLater()
    return {repr(s): b - a for s, b, a in zip(SINGLETONS, before, after)}


def _mortal_singletons() -> bool:
    return sys.implementation.name == "cpython" and sys.version_info < (3, 12)


def install_refcount_guard() -> bool:
    """Make None/True/False effectively immortal if this PySide6 drains their counts; idempotent."""
    global guard_active, _probed
    if _probed:
        return guard_active
    _probed = True
    if not _mortal_singletons():
        return False
    lost = refcount_drain()
    if max(lost.values()) < 16:  # half the probe's calls: a real drain loses one per call
        return False
    for obj in SINGLETONS:
        ctypes.c_ssize_t.from_address(id(obj)).value += BIAS  # ob_refcnt is PyObject's first field
    guard_active = True
    return True


install_refcount_guard()
