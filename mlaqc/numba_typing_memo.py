"""Numba's call typing remembered while the ray tracer compiles: a variant's type inference about 2x faster.

`types.BaseFunction.get_call_type` finds the signature of a call to a function typed by templates
(operator.mul, getitem, bool, the ufuncs, the number classes ...) by trying every template registered for
it, in order, each with and without literal arguments. The tracer's inlined kernels make about 21,000 such
calls per variant but only about 1,100 distinct (function, argument types) pairs: 6-7 s of a variant's
27 s compile went to asking the same templates the same question.

`remembered_call_types()` keeps, while the tracer compiles, the signature each (function, typing context,
target, compile flags, argument types, keyword types) resolved to, and answers the next call with the same
key from it. (The flags are in the key because an `@overload`'s implementation is compiled with its caller's
flags, its error model for one; the target because it orders the templates.) The templates are asked exactly
as before for a key's first call, so the answer is Numba's own; each later call with that key records the
winning template's implementation key again, as asking the templates would (lowering reads the last one
recorded for the signature's argument types, which another key can share). A call that fails or raises is
not remembered and fails again the same way. This holds while a template's answer depends on nothing but
that key, which is so for every template the tracer's kernels use: their machine code comes out the same
with and without it (tests/test_numba_passes.py). Each time it is put in place it starts from an empty memo.
Only where Numba's method has the shape this module was written against (Numba 0.68, checked once against
its source); elsewhere it does nothing. A patch of someone else's put on top of it while it is in place
keeps it beneath (it is then taken out only when that patch is).
"""

from __future__ import annotations

import inspect

from mlaqc.numba_patch import wrapping

# lines of numba.core.types.functions.BaseFunction.get_call_type this memo relies on (the first answer is
# returned as soon as a template gives one, and recorded for lowering by the signature's args)
_EXPECTED = ("def get_call_type(self, context, args, kws):", "for temp_cls in order:",
             "self._impl_keys[sig.args] = temp.get_impl_key(sig)", "return sig", "failures.raise_error()")


def _remembering(original):
    """get_call_type answered from a memo of its own for a key seen before, from `original` (and
    remembered) else."""
    from numba.core.target_extension import get_local_target
    from numba.core.targetconfig import ConfigStack

    memo: dict = {}

    def get_call_type(self, context, args, kws):
        try:
            key = (self, context, get_local_target(context), ConfigStack.top_or_none(), tuple(args),
                   tuple(sorted(kws.items())) if kws else ())
            hit = memo.get(key)
        except TypeError:  # an unhashable argument type: asked as before
            return original(self, context, args, kws)
        if hit is not None:  # the winning template's implementation key recorded again, as its apply does
            sig, impl_key = hit
            self._impl_keys[sig.args] = impl_key
            return sig
        sig = original(self, context, args, kws)
        if sig is not None:
            memo[key] = (sig, self._impl_keys[sig.args])
        return sig

    get_call_type.__wrapped__ = original
    get_call_type.memo = memo
    return get_call_type


def _find():
    """numba.core.types.functions.BaseFunction where get_call_type is the one this memo was written against."""
    from numba.core.types import functions

    source = inspect.getsource(functions.BaseFunction.get_call_type)
    if all(line in source for line in _EXPECTED) and "get_call_type" not in vars(functions.Function):
        return functions.BaseFunction
    return None


_PATCH = wrapping(_find, "get_call_type", _remembering)
_function_base = _PATCH.found


def remembered_call_types():
    """While inside, a call's signature is worked out once per (function, context, target, flags, argument
    types) (process-wide while any thread is inside: nested and concurrent uses are counted)."""
    return _PATCH.applied()


def active() -> bool:
    """True while the memo is in place (tests)."""
    base = _function_base()
    return base is not None and getattr(base.get_call_type, "__module__", None) == __name__
