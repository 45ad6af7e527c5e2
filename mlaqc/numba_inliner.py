"""Numba's IR inliner without its quadratic copy: the ray tracer's kernels compile 2-3x faster.

Numba inlines an `inline="always"` function by copying its IR block by block, one `copy.deepcopy` per
block (numba.core.inline_closurecall.InlineWorker.inline_ir). Every variable of every block points at the
function's one Scope, which holds all its variables, so each block's copy copies the whole scope again:
inlining a function of B blocks and V variables makes about B x V object copies. The tracer's passes
inline into functions of hundreds of blocks and thousands of variables, and those copies were 60 % of a
kernel variant's compile (the square grid's: 38 s, 16 s without them, on this project's 2-core host).

`shared_scope_copies()` gives the blocks of one IR one memo, so they share one copy of their scope, as the
original blocks share the original. It also copies them with `ir_deepcopy`, which makes copy.deepcopy's copy
without its generic reduce-and-reconstruct protocol for the lists, dicts, tuples and plain objects that make
up most of an IR (a variant's copies 3.2 -> 1.9 s; tests/test_tracer_variants.py compares the two object for
object on the tracer's kernels). The copy is the same IR (Numba relabels and renames it the same way
afterwards), so the compiled code is unchanged: the tracer's frames are bit-identical either way
(bench/trace.py --images check, tests/test_tracer_variants.py). It is active only while the tracer compiles,
and only where Numba's inliner still copies blocks with `copy.deepcopy` (checked once against its source);
elsewhere it does nothing and compiles take their old time.
"""

from __future__ import annotations

import copy
import copyreg
import inspect
from typing import Any

from mlaqc.numba_patch import NumbaPatch


_NIL = object()
# the types copy.deepcopy returns as they are
_ATOMIC = frozenset(t for t, f in copy._deepcopy_dispatch.items() if f is copy._deepcopy_atomic)
_PLAIN: dict[type, bool] = {}


def _is_plain(cls: type) -> bool:
    """True when copy.deepcopy copies instances of `cls` by its generic path: `cls.__new__(cls)` given a deep
    copy of the old one's __dict__ (no __deepcopy__, __reduce__, __getstate__, __setstate__,
    __getnewargs__ or slots of its own, no copyreg entry, no built-in base but object)."""
    plain = _PLAIN.get(cls)
    if plain is None:
        plain = _PLAIN[cls] = (
            cls.__reduce_ex__ is object.__reduce_ex__ and cls.__reduce__ is object.__reduce__
            and getattr(cls, "__deepcopy__", None) is None and getattr(cls, "__getstate__", None) is object.__getstate__
            and not hasattr(cls, "__setstate__") and cls not in copyreg.dispatch_table
            and not hasattr(cls, "__getnewargs__") and not hasattr(cls, "__getnewargs_ex__")
            and all(k is object or k.__module__ != "builtins" for k in cls.__mro__)
            and cls not in copy._deepcopy_dispatch and not issubclass(cls, (type, list, dict, tuple, set))
            and not any(vars(k).get("__slots__") for k in cls.__mro__))
    return plain


def ir_deepcopy(x: Any, memo: dict) -> Any:
    """copy.deepcopy(x, memo), the same copy with the same memo entries for the copied objects, with
    lists, dicts, tuples and plain objects (the IR's statements, expressions, locations) copied here
    without copy's generic reduce-and-reconstruct protocol; everything else goes to copy.deepcopy."""
    cls = type(x)
    if cls in _ATOMIC:
        return x
    d = id(x)
    y = memo.get(d, _NIL)
    if y is not _NIL:
        return y
    if cls is list:
        y = memo[d] = []
        y.extend(ir_deepcopy(v, memo) for v in x)
    elif cls is dict:
        y = memo[d] = {}
        for k, v in x.items():
            y[ir_deepcopy(k, memo)] = ir_deepcopy(v, memo)
    elif cls is tuple:
        items = [ir_deepcopy(v, memo) for v in x]
        y = memo.get(d, _NIL)
        if y is not _NIL:  # (the tuple was reached again through its own items)
            return y
        y = x if all(a is b for a, b in zip(items, x)) else tuple(items)
    elif _is_plain(cls):
        y = memo[d] = cls.__new__(cls)
        state = getattr(x, "__dict__", None)
        if state:
            y.__dict__.update({k: ir_deepcopy(v, memo) for k, v in state.items()})
    else:
        return copy.deepcopy(x, memo)
    if y is not x:
        memo[d] = y
        copy._keep_alive(x, memo)
    return y


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
            return ir_deepcopy(x, shared)
        return copy.deepcopy(x, memo)

    def forget(self) -> None:
        """Drop the last IR's memo (and the objects it keeps alive)."""
        self._last = (None, {})

    def __getattr__(self, name: str) -> Any:
        return getattr(copy, name)


def _find():
    """(numba.core.inline_closurecall, ir.Block) where its inliner copies blocks as this module expects."""
    from numba.core import inline_closurecall, ir

    source = inspect.getsource(inline_closurecall.InlineWorker.inline_ir)
    if inline_closurecall.copy is copy and "copy.deepcopy(the_ir.blocks[block_label])" in source:
        return inline_closurecall, ir.Block
    return None


def _install(found) -> None:
    found[0].copy = _SharedScopeCopy(found[1])


def _restore(found, _displaced) -> None:
    found[0].copy.forget()
    found[0].copy = copy


_PATCH = NumbaPatch(_find, _install, _restore)
_inliner_module = _PATCH.found


def shared_scope_copies():
    """While inside, Numba's inliner copies each IR's scope once (process-wide while any thread is inside:
    nested and concurrent uses are counted)."""
    return _PATCH.applied()


def active() -> bool:
    """True while the faster copy is in place (tests)."""
    found = _inliner_module()
    return found is not None and isinstance(found[0].copy, _SharedScopeCopy)
