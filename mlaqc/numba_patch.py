"""What the tracer's Numba patches share (numba_inliner, numba_liveness, numba_ssa, numba_typing_memo,
numba_callee_ir): Numba's source read once to decide whether a patch applies, and the patch in place
process-wide while any thread is inside it (Numba compiles under one lock, so every compile meanwhile gets
it; results are Numba's own either way)."""

from __future__ import annotations

import contextlib
import threading
from typing import Any, Callable, Iterator


class NumbaPatch:
    """`find()` returns what to patch where Numba has the shape the patch reproduces (None, or an exception:
    this Numba is left alone); `install(found)` puts the patch in and returns what it displaced, which
    `restore(found, displaced)` puts back when the last user leaves."""

    def __init__(self, find: Callable[[], Any], install: Callable[[Any], Any],
                 restore: Callable[[Any, Any], None]) -> None:
        self._find, self._install, self._restore = find, install, restore
        self._lock = threading.Lock()
        self._users = 0
        self._checked = False
        self._found: Any = None
        self._displaced: Any = None

    def found(self) -> Any:
        """What `find()` returned, asked once per process."""
        if not self._checked:
            try:
                self._found = self._find()
            except Exception:  # noqa: BLE001 - another Numba: compile as it does
                self._found = None
            self._checked = True
        return self._found

    @contextlib.contextmanager
    def applied(self) -> Iterator[None]:
        """The patch in place while inside (nested and concurrent uses are counted)."""
        with self._lock:
            found = self.found()
            if found is not None:
                if self._users == 0:
                    self._displaced = self._install(found)
                self._users += 1
        try:
            yield
        finally:
            if found is not None:
                with self._lock:
                    self._users -= 1
                    if self._users == 0:
                        self._restore(found, self._displaced)


def wrapping(find: Callable[[], Any], name: str, wrap: Callable[[Any], Any]) -> NumbaPatch:
    """A NumbaPatch that replaces attribute `name` of what `find()` returns with `wrap(original)` (a
    function whose `__wrapped__` is the original), and puts the original back unless another patch has
    since replaced the wrapper (that patch then keeps it beneath until it is taken out itself)."""

    def install(owner: Any) -> Any:
        displaced = getattr(owner, name)
        setattr(owner, name, wrap(displaced))
        return displaced

    def restore(owner: Any, displaced: Any) -> None:
        if getattr(getattr(owner, name), "__wrapped__", None) is displaced:
            setattr(owner, name, displaced)

    return NumbaPatch(find, install, restore)
