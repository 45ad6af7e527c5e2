"""Numba's live-variable analysis on bitsets: the ray tracer's kernels compile about a third faster.

`numba.core.analysis.compute_live_map` finds the variables live at each block's entry in two fix points
over Python sets: which definitions reach a block, then liveness pushed backwards. Its first pass unions
each block's whole reaching set into every successor's, and Numba runs the analysis again after each of
its IR rewrites: on the tracer's inlined kernels (about a thousand blocks, thousands of variables, the
analysis run about 1,500 times per variant) that pass alone was 18 s of a variant's compile.

`bitset_liveness()` replaces it, while the tracer compiles, with the same two fix points over Python
integers used as bitsets (one bit per variable): the same iteration over the same blocks in the same
order, so the same least fixed point, returned as the same sets (tests/test_numba_passes.py compares
the two on real kernels' IR and on every analysis of a compile; every analysis of all twelve tracer
variants' compiles gave the same map, and the compiled kernels are byte-identical). Only where Numba's
function has the shape this module was written against (Numba 0.68, checked once against its source);
elsewhere it does nothing and compiles take their old time.
"""

from __future__ import annotations

import inspect
from collections import defaultdict
from typing import Any

from mlaqc.numba_patch import NumbaPatch

# lines of numba.core.analysis.compute_live_map this replacement reproduces (Numba 0.68: earlier ones iterate
# the blocks in another order, and are left alone)
_EXPECTED = ("def def_reach(dct):", "dct[offset] |= used_or_defined", "dct[out_blk] |= dct[offset]",
             "reachable = live_vars & def_reach_map[inc_blk]", "dct[inc_blk] |= reachable - var_def_map[inc_blk]",
             "live_map[offset] = set(var_use_map[offset])", "topo_order = cfg.topo_order()")


def compute_live_map(cfg: Any, blocks: Any, var_use_map: Any, var_def_map: Any) -> dict:
    """The variables live at the entry of each block, as numba.core.analysis.compute_live_map computes
    them (the same dict of sets), with the sets held as integer bitsets while the fix points run."""
    names: dict[str, int] = {}

    def bits(variables) -> int:
        out = 0
        for v in variables:
            i = names.get(v)
            if i is None:
                i = names[v] = len(names)
            out |= 1 << i
        return out

    topo = list(cfg.topo_order())
    succ = {o: [b for b, _ in cfg.successors(o)] for o in topo}
    pred = {o: [b for b, _ in cfg.predecessors(o)] for o in topo}
    use = defaultdict(int, {o: bits(s) for o, s in var_use_map.items()})
    define = defaultdict(int, {o: bits(s) for o, s in var_def_map.items()})

    reach: defaultdict[Any, int] = defaultdict(int)
    while True:  # definitions reaching each block's entry (forward, topological order)
        before = dict(reach)
        for o in topo:
            reach[o] |= define[o] | use[o]
            for b in succ[o]:
                reach[b] |= reach[o]
        if dict(reach) == before:
            break

    live = {o: bits(var_use_map[o]) for o in blocks.keys()}
    while True:  # liveness pushed backwards (reverse topological order)
        before = dict(live)
        for o in reversed(topo):
            for p in pred[o]:
                live[p] |= (live[o] & reach[p]) & ~define[p]
        if live == before:
            break
    order = list(names)
    return {o: _names(x, order) for o, x in live.items()}


def _names(x: int, order: list[str]) -> set[str]:
    """The variable names of bitset `x`."""
    out = set()
    while x:
        low = x & -x
        out.add(order[low.bit_length() - 1])
        x ^= low
    return out


def _find():
    """(numba.core.analysis, numba.core.ir_utils) where compute_live_map is the one this module reproduces."""
    from numba.core import analysis, ir_utils

    source = inspect.getsource(analysis.compute_live_map)
    if all(line in source for line in _EXPECTED) and ir_utils.compute_live_map is analysis.compute_live_map:
        return analysis, ir_utils
    return None


def _install(found) -> tuple:
    displaced = tuple(module.compute_live_map for module in found)
    for module in found:
        module.compute_live_map = compute_live_map
    return displaced


def _restore(found, displaced) -> None:
    for module, before in zip(found, displaced):
        if module.compute_live_map is compute_live_map:  # (not if another patch has since replaced it)
            module.compute_live_map = before


_PATCH = NumbaPatch(_find, _install, _restore)
_numba_modules = _PATCH.found


def bitset_liveness():
    """While inside, Numba's live-variable analysis runs on bitsets (process-wide while any thread is
    inside: nested and concurrent uses are counted)."""
    return _PATCH.applied()


def active() -> bool:
    """True while the bitset analysis is in place (tests)."""
    found = _numba_modules()
    return found is not None and found[0].compute_live_map is compute_live_map
