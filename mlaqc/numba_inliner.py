"""Numba's IR inliner without its quadratic copy: the ray tracer's kernels compile 2-3x faster.

Numba inlines an `inline="always"` function by copying its IR block by block, one `copy.deepcopy` per
block (numba.core.inline_closurecall.InlineWorker.inline_ir). Every variable of every block points at the
function's one Scope, which holds all its variables, so each block's copy copies the whole scope again:
inlining a function of B blocks and V variables makes about B x V object copies. The tracer's passes
inline into functions of hundreds of blocks and thousands of variables, and those copies were 60 % of a
kernel variant's compile (the square grid's: 38 s, 16 s without them, on this project's 2-core host).

`shared_scope_copies()` gives the blocks of one IR one memo, so they share one copy of their scope, as the
original blocks share the original. The copy is the same IR (Numba relabels and renames it the same way
afterwards), so the compiled code is unchanged: the tracer's frames are bit-identical either way
(bench/trace.py --images check, tests/test_tracer_variants.py). It is active only while the tracer
compiles, and only where Numba's inliner still copies blocks with `copy.deepcopy` (checked once against
its source); elsewhere it does nothing and compiles take their old time.
"""

from __future__ import annotations

import contextlib
import copy
import inspect
import threading
from typing import Any, Iterator

_LOCK = threading.Lock()
_STATE: dict[str, Any] = {"users": 0, "module": None, "checked": False}


class _SharedScopeCopy:
    """Stands in for the `copy` module inside numba.core.inline_closurecall: a deep copy of a Block shares
    its memo with the copies of the other blocks of the same scope made just before it."""

    def __init__(self, block_type: type) -> None:
        self._block_type = block_type
        self._last: tuple[Any, dict] = (None, {})

    def deepcopy(self, x: Any, memo: dict | None = None) -> Any:
        if memo is None and type(x) is self._block_type:
            scope, shared = self._last
            if scope is not x.scope:  # the first block of another IR: a fresh memo (it keeps `scope` alive)
                shared = {}
                self._last = (x.scope, shared)
            return copy.deepcopy(x, shared)
        return copy.deepcopy(x, memo)

    def forget(self) -> None:
        """Drop the last IR's memo (and the objects it keeps alive)."""
        self._last = (None, {})

    def __getattr__(self, name: str) -> Any:
        return getattr(copy, name)


def _inliner_module():
    """numba.core.inline_closurecall where its inliner copies blocks as this module expects, else None."""
    if not _STATE["checked"]:
        _STATE["checked"] = True
        try:
            from numba.core import inline_closurecall, ir

            source = inspect.getsource(inline_closurecall.InlineWorker.inline_ir)
            if inline_closurecall.copy is copy and "copy.deepcopy(the_ir.blocks[block_label])" in source:
                _STATE["module"] = (inline_closurecall, ir.Block)
        except Exception:  # noqa: BLE001 - another Numba: compile as it does
            _STATE["module"] = None
    return _STATE["module"]


@contextlib.contextmanager
def shared_scope_copies() -> Iterator[None]:
    """While inside, Numba's inliner copies each IR's scope once (process-wide while any thread is inside:
    nested and concurrent uses are counted)."""
    with _LOCK:
        found = _inliner_module()
        if found is not None:
            if _STATE["users"] == 0:
                found[0].copy = _SharedScopeCopy(found[1])
            _STATE["users"] += 1
    try:
        yield
    finally:
        if found is not None:
            with _LOCK:
                _STATE["users"] -= 1
                if _STATE["users"] == 0:
                    found[0].copy.forget()
                    found[0].copy = copy


def active() -> bool:
    """True while the faster copy is in place (tests)."""
    found = _inliner_module()
    return found is not None and isinstance(found[0].copy, _SharedScopeCopy)
