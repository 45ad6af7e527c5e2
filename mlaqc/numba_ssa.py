"""Numba's SSA reconstruction without its visits to blocks that never name the variable: the ray tracer's
kernels compile about a fifth faster.

`numba.core.ssa._run_ssa` repairs each variable assigned more than once (a "violator") in two passes over
every statement of every block: fresh names for its assignments, then each use re-pointed at the
definition that reaches it. A block that neither assigns nor uses the variable comes out of both passes
unchanged (each statement is handed to a handler that returns it as it was, touching no state), but is
still walked: violators x statements handler calls, about 7 million per tracer variant (a fifth of its
compile). `ssa_skipping_blocks()` walks only the blocks whose statements name the violator (found once
per reconstruction from the statements' variables) and copies the others' statement lists, as the
original's rewrite does.

The IR that comes out is the same as long as no two statements share a mutable part (a repair copies a
statement shallowly and re-points its variables in place, which would then reach the other statement), and
as long as the names a repair makes are new ones: both hold for the IR Numba's own passes build.
tests/test_numba_passes.py compares the two on the tracer kernels' IR and on every reconstruction of a
compile; every reconstruction of all twelve tracer variants' compiles gave the same IR, and the compiled
kernels are byte-identical. Only where Numba's functions have the shape this module was written against
(Numba 0.68, checked once against their source); elsewhere it does nothing and compiles take their old
time.
"""

from __future__ import annotations

import inspect
import threading
from typing import Any

from mlaqc.numba_patch import NumbaPatch

_LOCAL = threading.local()
_STATE: dict[str, Any] = {"original": None, "rewrite": None, "module": None}  # Numba's, once recognised
# what this replacement relies on in numba.core.ssa (Numba 0.68): the passes, and the handlers' leaving a
# statement that does not name the variable as it was
_EXPECTED = {
    "_run_ssa": ("violators = _find_defs_violators(blocks, cfg)", "blocks, defmap = _fresh_vars(blocks, varname)",
                 "blocks = _fix_ssa_vars(blocks, varname, defmap, cfg, df_plus,"),
    "_run_block_rewrite": ("newblk = ir.Block(scope=blk.scope, loc=blk.loc)",
                           "for stmt in _run_ssa_block_pass(states, blk, handler):", "newblk.body = newbody"),
    "_fresh_vars": ("states['varname'] = varname", "_run_block_rewrite(blocks, states, _FreshVarHandler())"),
    "_fix_ssa_vars": ("states['varname'] = varname", "_run_block_rewrite(blocks, states, _FixSSAVars("),
    "_run_ssa_block_pass": ("ret = handler.on_assign(states, stmt)", "ret = handler.on_other(states, stmt)"),
    "_FreshVarHandler": ("if assign.target.name == states['varname']:", "return assign", "return stmt"),
    "_FixSSAVars": ("if phivar in varnames:", "return self._find_def(states, stmt)", "return assign",
                    "return stmt"),
}


def _run_ssa(blocks):
    """numba.core.ssa._run_ssa, with the names each block's statements mention found first."""
    outer = getattr(_LOCAL, "mentions", None)
    _LOCAL.mentions = {label: _named(block) for label, block in blocks.items()}
    try:
        return _STATE["original"](blocks)
    finally:
        _LOCAL.mentions = outer


def _named(block: Any) -> set[str]:
    """Every variable name a block's statements assign or use."""
    return {v.name for stmt in block.body for v in stmt.list_vars()}


def _run_block_rewrite(blocks, states, handler):
    """numba.core.ssa._run_block_rewrite over the blocks that name `states['varname']`; the others' statements
    are copied into new blocks untouched, as the handlers would return them."""
    ssa = _STATE["module"]
    mentions = getattr(_LOCAL, "mentions", None)
    varname = states.get("varname")
    if mentions is None or varname is None:
        return _STATE["rewrite"](blocks, states, handler)
    newblocks = {}
    for label, blk in blocks.items():
        named = mentions.get(label)
        if named is not None and varname not in named:
            newblk = ssa.ir.Block(scope=blk.scope, loc=blk.loc)
            newblk.body = list(blk.body)
            newblocks[label] = newblk
        else:
            newblocks.update(_STATE["rewrite"]({label: blk}, states, handler))
    return newblocks


def _find():
    """numba.core.ssa where its functions are the ones this module relies on (their originals kept)."""
    from numba.core import ssa

    if all(all(line in inspect.getsource(getattr(ssa, name)) for line in lines) for name, lines in _EXPECTED.items()):
        _STATE.update(module=ssa, original=ssa._run_ssa, rewrite=ssa._run_block_rewrite)
        return ssa
    return None


def _install(ssa) -> tuple:
    displaced = (ssa._run_ssa, ssa._run_block_rewrite)
    ssa._run_ssa, ssa._run_block_rewrite = _run_ssa, _run_block_rewrite
    return displaced


def _restore(ssa, displaced) -> None:
    if ssa._run_ssa is _run_ssa:  # (not if another patch has since replaced it)
        ssa._run_ssa, ssa._run_block_rewrite = displaced


_PATCH = NumbaPatch(_find, _install, _restore)
_ssa_module = _PATCH.found


def ssa_skipping_blocks():
    """While inside, Numba's SSA reconstruction visits only the blocks that name each violator
    (process-wide while any thread is inside: nested and concurrent uses are counted)."""
    return _PATCH.applied()


def active() -> bool:
    """True while the block-skipping reconstruction is in place (tests)."""
    ssa = _ssa_module()
    return ssa is not None and ssa._run_ssa is _run_ssa
