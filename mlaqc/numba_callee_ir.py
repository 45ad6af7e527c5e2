"""Numba's inliner builds each inlined function's IR once: the ray tracer's variants compile ~15 % faster.

Numba inlines an `inline="always"` function (numba.core.inline_closurecall.InlineWorker.inline_function)
by running the whole untyped pipeline over the callee's bytecode, which inlines the callee's own callees
the same way, and then copying the IR it got before splicing the copy in. The tracer's passes call the
same helpers at many sites, so the same pipelines ran about 175 times per variant, nested.

`remembered_callee_irs()` keeps, while the tracer compiles, the IR that pipeline made for each (function,
contexts, pipeline, flags, declared locals), and gives it to the next site that inlines the same function
under the same settings, with a function identity of its own (the inlined variables are named after it, as
after a fresh run). The inliner only ever copies that IR (its first step), so the copies are what a fresh
run would have given, apart from the numbers of the labels and identities Numba makes up, which come from
process-wide counters; the pipeline's side effect on the caller's flags (SSA off) is made again on each
reuse. (The inliner's shared-scope copy, numba_inliner, then starts a fresh memo for each site: inline_ir
copies its copy at once, so the last scope it saw is never the remembered IR's.) The compiled kernels'
frames are bit-identical with and without it (bench/trace.py --images check), and tests/test_numba_passes.py
checks a small compile's results and machine code. Only where Numba's inliner has the shape this module was
written against (Numba 0.68, checked once against its source); elsewhere it does nothing.
"""

from __future__ import annotations

import copy
import inspect

from mlaqc.numba_patch import wrapping

# lines of InlineWorker.inline_function and .inline_ir this memo relies on: the callee's IR comes from
# run_untyped_passes, and inline_ir copies it before it changes anything
_EXPECTED_CALLER = ("callee_ir = self.run_untyped_passes(function)",
                    "return self.inline_ir(caller_ir, block, i, callee_ir, freevars,")
_EXPECTED_COPY = ("# Always copy the callee IR, it gets mutated", "callee_ir = copy_ir(callee_ir)",
                  "callee_ir_original = copy_ir(callee_ir)")
_EXPECTED_PASSES = ("state.flags = self.flags", "state.flags.enable_ssa = enable_ssa")


def _remembering(original_inline_function):
    """InlineWorker.inline_function with the callee's untyped IR built once per key (a memo of its own)."""
    memo: dict = {}

    def inline_function(self, caller_ir, block, i, function, arg_typs=None):
        self.flags.enable_ssa = False  # what run_untyped_passes(function) does to the caller's flags
        try:
            key = (function, self.typingctx, self.targetctx, self.pipeline, self.flags.copy(),
                   tuple(sorted(self.locals.items())) if self.locals else ())
            callee_ir = memo.get(key)
        except TypeError:  # something unhashable: built afresh, as Numba does
            return original_inline_function(self, caller_ir, block, i, function, arg_typs=arg_typs)
        if callee_ir is None:
            callee_ir = memo[key] = self.run_untyped_passes(function)
        else:  # a function identity of its own, as a fresh run gives: the site's variables are named after it
            callee_ir = copy.copy(callee_ir)
            callee_ir.func_id = callee_ir.func_id.derive()
        return self.inline_ir(caller_ir, block, i, callee_ir, function.__code__.co_freevars, arg_typs=arg_typs)

    inline_function.__wrapped__ = original_inline_function
    inline_function.memo = memo
    return inline_function


def _find():
    """numba.core.inline_closurecall.InlineWorker where it inlines as this module expects."""
    from numba.core.inline_closurecall import InlineWorker

    caller = inspect.getsource(InlineWorker.inline_function)
    copies = inspect.getsource(InlineWorker.inline_ir)
    passes = inspect.getsource(InlineWorker.run_untyped_passes)
    if (all(line in caller for line in _EXPECTED_CALLER) and all(line in copies for line in _EXPECTED_COPY)
            and all(line in passes for line in _EXPECTED_PASSES)):
        return InlineWorker
    return None


_PATCH = wrapping(_find, "inline_function", _remembering)
_inline_worker = _PATCH.found


def remembered_callee_irs():
    """While inside, each inlined function's untyped IR is built once per settings (process-wide while any
    thread is inside: nested and concurrent uses are counted)."""
    return _PATCH.applied()


def active() -> bool:
    """True while the memo is in place (tests)."""
    worker = _inline_worker()
    return worker is not None and getattr(worker.inline_function, "__module__", None) == __name__
