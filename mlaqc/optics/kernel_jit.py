"""How the compiled tracer's modules are compiled: Numba's flags, the decorators, and the cache's stamp.

Every module of the tracer's kernels (kernel_geometry, kernel_sampling, raytrace_kernels) imports its
decorators from here, so the first of them to be imported stamps Numba's cache of all of them with what
they are compiled from (kernel_sources), before any is decorated. Without Numba the decorators return the
plain Python functions.
"""

from __future__ import annotations

from mlaqc.optics import kernel_sources

try:
    from numba import njit
except ImportError:  # pragma: no cover - exercised only where numba is missing
    njit = None

AVAILABLE = njit is not None
# the message of Numba's pedantic SSA warning that inlined selects trip (silenced below; tests check it matches)
SSA_SCOPE_WARNING = r".*variable '.*' is not in scope"


def _identity(fn):
    return fn


# fastmath is limited to FMA contraction (a * b + c in one rounding): about 5 % faster, results within an
# ulp or two of the uncontracted NumPy reference. The other fast-math flags would break the NaN (miss)
# and +-0 handling the kernel relies on.
FLAGS = dict(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
if AVAILABLE:
    import warnings

    from numba.core.errors import NumbaIRAssumptionWarning

    # Numba's cache stamped by every source the kernels are compiled from, not each file alone
    kernel_sources.register(kernel_sources.TRACER_SOURCES)
    # Inlining cell_edge's selects into the sag-intersection passes trips a pedantic SSA check of Numba's
    # (the variables are in scope: the kernels agree with the NumPy reference ray by ray); it is not the
    # user's to see at compile time. Numba prefixes the message with a terminal colour code (the filter matches
    # from the message's start: without the leading .* the warnings reached the user on every first compile).
    warnings.filterwarnings("ignore", SSA_SCOPE_WARNING, NumbaIRAssumptionWarning)
jit = njit(**FLAGS) if AVAILABLE else _identity
jit_inline = njit(inline="always", **FLAGS) if AVAILABLE else _identity
