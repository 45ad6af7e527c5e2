"""The tracer's faster Numba passes give exactly Numba's own results: the live-variable analysis on bitsets
(mlaqc.numba_liveness) and the SSA reconstruction that skips blocks not naming a variable (mlaqc.numba_ssa),
on the frontend IR of the tracer's kernels and on every run Numba makes while compiling a kernel with
inlined helpers, loops and branches; call typing remembered within a compile (mlaqc.numba_typing_memo)
and each inlined function's IR built once (mlaqc.numba_callee_ir) give the same machine code; each is in
place only inside its context."""

import copy
import re

import numpy as np
import pytest

numba = pytest.importorskip("numba")

from numba.core import analysis, ir_utils  # noqa: E402
from numba.core.analysis import compute_cfg_from_blocks, compute_use_defs  # noqa: E402
from numba.core.compiler import run_frontend  # noqa: E402

from numba.core import ssa  # noqa: E402

from numba.core.types import functions as numba_functions  # noqa: E402

from mlaqc import numba_callee_ir, numba_liveness, numba_ssa, numba_typing_memo  # noqa: E402
from mlaqc.optics import kernel_geometry, kernel_jit, raytrace_kernels  # noqa: E402

ORIGINAL = analysis.compute_live_map
ORIGINAL_SSA = ssa._run_ssa
ORIGINAL_CALL_TYPE = numba_functions.BaseFunction.get_call_type
# each module reads Numba's source once, on first use: before any test here patches what it reads
numba_liveness._numba_modules(), numba_ssa._ssa_module(), numba_typing_memo._function_base()
numba_callee_ir._inline_worker()
KERNELS = ["kernel", "kernel_sag", "pass_front_refract", "bin_hits"]


def _both(blocks):
    cfg = compute_cfg_from_blocks(blocks)
    usedefs = compute_use_defs(blocks)
    return (ORIGINAL(cfg, blocks, usedefs.usemap, usedefs.defmap),
            numba_liveness.compute_live_map(cfg, blocks, usedefs.usemap, usedefs.defmap))


@pytest.mark.parametrize("name", KERNELS)
def test_the_tracer_kernels_frontend_ir_gives_numbas_live_map(name):
    func_ir = run_frontend(getattr(raytrace_kernels, name).py_func)
    theirs, ours = _both(func_ir.blocks)
    assert len(func_ir.blocks) > 3
    assert ours == theirs
    assert any(theirs.values())  # a map with live variables, not an empty one compared with another


def test_every_analysis_of_a_compile_with_inlining_and_loops_matches(monkeypatch):
    """Each live map Numba asks for while compiling (after each of its rewrites), computed both ways."""
    calls = []

    def checked(cfg, blocks, use, defs):
        want = ORIGINAL(cfg, blocks, use, defs)
        assert numba_liveness.compute_live_map(cfg, blocks, use, defs) == want
        calls.append(len(blocks))
        return want

    monkeypatch.setattr(analysis, "compute_live_map", checked)
    monkeypatch.setattr(ir_utils, "compute_live_map", checked)

    walk = _small_kernel()
    assert walk(np.linspace(-2, 2, 9), 3) == pytest.approx(walk.py_func(np.linspace(-2, 2, 9), 3))
    assert len(calls) > 3 and max(calls) > 5


def test_in_place_only_inside_the_context():
    assert not numba_liveness.active()
    with numba_liveness.bitset_liveness():
        assert numba_liveness.active()
        with numba_liveness.bitset_liveness():  # nested: still in place when the inner one ends
            pass
        assert numba_liveness.active() and ir_utils.compute_live_map is numba_liveness.compute_live_map
    assert not numba_liveness.active()
    assert analysis.compute_live_map is ORIGINAL and ir_utils.compute_live_map is ORIGINAL


def _small_kernel():
    """A fresh (uncompiled) kernel with an inlined helper, nested loops, branches and a break."""

    @numba.njit(inline="always")
    def clamp(x, lo, hi):
        return lo if x < lo else (hi if x > hi else x)

    @numba.njit
    def walk(a, k):
        total, i, j = 0.0, 0, 0
        while i < a.size:
            v = clamp(a[i], -1.0, 1.0)
            if v > 0:
                for j in range(k):
                    total += v * j
                    if total > 1e9:
                        break
            else:
                total -= clamp(v * v, 0.0, 0.5)
            i += 1
        return total + j

    return walk


def _dump(blocks) -> list:
    return [(label, [str(stmt) for stmt in block.body]) for label, block in blocks.items()]


def _ssa_both(blocks):
    """Numba's SSA reconstruction and the block-skipping one, each on its own copy of `blocks`."""
    theirs = ORIGINAL_SSA(copy.deepcopy(blocks))
    with numba_ssa.ssa_skipping_blocks():
        ours = ssa._run_ssa(copy.deepcopy(blocks))
    return theirs, ours


@pytest.mark.parametrize("name", KERNELS[:3])  # (bin_hits assigns no variable twice)
def test_the_tracer_kernels_frontend_ir_gives_numbas_ssa(name):
    blocks = run_frontend(getattr(raytrace_kernels, name).py_func).blocks
    theirs, ours = _ssa_both(blocks)
    assert _dump(ours) == _dump(theirs)
    violators = ssa._find_defs_violators(blocks, compute_cfg_from_blocks(blocks))
    named = [numba_ssa._named(b) for b in blocks.values()]
    # the comparison means something: variables to repair, and blocks that one of them never names
    assert violators and any(v not in n for v in violators for n in named)


def test_every_ssa_reconstruction_of_a_compile_matches(monkeypatch):
    calls = []

    def checked(blocks):
        theirs, ours = _ssa_both(blocks)
        assert _dump(ours) == _dump(theirs)
        calls.append(len(blocks))
        return ORIGINAL_SSA(blocks)

    monkeypatch.setattr(ssa, "_run_ssa", checked)
    walk = _small_kernel()
    assert walk(np.linspace(-2, 2, 9), 3) == pytest.approx(walk.py_func(np.linspace(-2, 2, 9), 3))
    assert len(calls) >= 2 and max(calls) > 5  # (the inlined helper: reconstructed on its own, then in place)


def test_ssa_skipping_only_inside_the_context():
    rewrite = ssa._run_block_rewrite
    assert not numba_ssa.active()
    with numba_ssa.ssa_skipping_blocks():
        assert numba_ssa.active()
        with numba_ssa.ssa_skipping_blocks():
            pass
        assert numba_ssa.active() and ssa._run_block_rewrite is numba_ssa._run_block_rewrite
    assert not numba_ssa.active() and ssa._run_ssa is ORIGINAL_SSA and ssa._run_block_rewrite is rewrite


def test_the_installed_numba_is_the_one_the_passes_were_written_against():
    """An upgrade that turns the faster passes off (compiles back to their old time) is said here."""
    assert numba_liveness._numba_modules() is not None, f"numba {numba.__version__}: compute_live_map changed"
    assert numba_ssa._ssa_module() is not None, f"numba {numba.__version__}: the SSA reconstruction changed"
    assert numba_typing_memo._function_base() is not None, f"numba {numba.__version__}: call typing changed"
    assert numba_callee_ir._inline_worker() is not None, f"numba {numba.__version__}: the inliner changed"


def test_each_context_restores_what_it_displaced(monkeypatch):
    """A patch of someone else's (here a test's own) is put back, not Numba's original."""
    def theirs_live(*args):
        return ORIGINAL(*args)

    def theirs_ssa(blocks):
        return ORIGINAL_SSA(blocks)

    def theirs_call_type(self, context, args, kws):
        return ORIGINAL_CALL_TYPE(self, context, args, kws)

    monkeypatch.setattr(analysis, "compute_live_map", theirs_live)
    monkeypatch.setattr(ssa, "_run_ssa", theirs_ssa)
    monkeypatch.setattr(numba_functions.BaseFunction, "get_call_type", theirs_call_type)
    with numba_liveness.bitset_liveness(), numba_ssa.ssa_skipping_blocks(), numba_typing_memo.remembered_call_types():
        assert analysis.compute_live_map is numba_liveness.compute_live_map and ssa._run_ssa is numba_ssa._run_ssa
        assert numba_functions.BaseFunction.get_call_type.__wrapped__ is theirs_call_type
    assert analysis.compute_live_map is theirs_live and ssa._run_ssa is theirs_ssa
    assert numba_functions.BaseFunction.get_call_type is theirs_call_type


def test_a_block_rewrite_outside_a_reconstruction_is_numbas_own():
    """Without the names a reconstruction found first (a rewrite called on its own), every block is walked."""
    blocks = run_frontend(raytrace_kernels.pass_front_refract.py_func).blocks
    violators = ssa._find_defs_violators(blocks, compute_cfg_from_blocks(blocks))
    name = next(iter(violators))
    want = _dump(ssa._fresh_vars(copy.deepcopy(blocks), name)[0])
    with numba_ssa.ssa_skipping_blocks():
        got = _dump(ssa._fresh_vars(copy.deepcopy(blocks), name)[0])
    assert got == want


def _machine_code(dispatcher) -> list[str]:
    """The compiled function's assembly, without what differs between two compiles of the same code: the
    version numbers Numba puts in mangled names, and the sizes of the strings that quote them."""
    asm = re.sub(r"B\d+v\d+B", "BvB", next(iter(dispatcher.inspect_asm().values())))
    return [line for line in asm.splitlines() if not re.match(r'\s*\.size\s+"\.const\.', line)]


def _surface_hit_compiled(remember: bool, counter: list) -> tuple:
    """A tracer function (inlined helpers, a None lattice, a rotation table) compiled afresh, with Numba's
    call typing counted; (its result, its machine code)."""
    flags = {k: v for k, v in kernel_jit.FLAGS.items() if k != "cache"}
    fresh = numba.njit(**flags)(kernel_geometry.surface_hit.py_func)
    args = (0.1, 0.2, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.5, 2.0, 0.0, 0.0, np.eye(3)[None].copy(), 0, 0.0, 0.0,
            10.0, 4.0, 4.0, None)
    if remember:
        with numba_typing_memo.remembered_call_types():
            out = fresh(*args)
    else:
        out = fresh(*args)
    return out, _machine_code(fresh), len(counter)


def test_remembered_call_types_compile_the_same_machine_code(monkeypatch):
    """The same code both ways, with far fewer questions put to Numba's templates."""
    asked = []

    def counted(self, context, args, kws):
        asked.append(self)
        return ORIGINAL_CALL_TYPE(self, context, args, kws)

    monkeypatch.setattr(numba_functions.BaseFunction, "get_call_type", counted)
    plain = _surface_hit_compiled(False, asked)
    del asked[:]
    remembered = _surface_hit_compiled(True, asked)
    assert remembered[0] == plain[0] and len(plain[1]) > 500
    assert remembered[1] == plain[1]
    assert remembered[2] < plain[2] / 2, (remembered[2], plain[2])
    assert numba_functions.BaseFunction.get_call_type is counted  # the test's own patch put back


def test_a_remembered_answer_records_its_implementation_again():
    """Lowering reads the implementation key last recorded for a signature's argument types; a remembered
    answer records it as asking the templates would."""
    from numba.core import types
    from numba.core.registry import cpu_target

    add = cpu_target.typing_context.resolve_value_type(__import__("operator").add)
    args = (types.float64, types.float64)
    with numba_typing_memo.remembered_call_types():
        assert numba_typing_memo.active()
        first = add.get_call_type(cpu_target.typing_context, args, {})
        key = add._impl_keys[first.args]
        add._impl_keys[first.args] = "another key"
        assert add.get_call_type(cpu_target.typing_context, args, {}) is first
        assert add._impl_keys[first.args] == key
        memo = numba_functions.BaseFunction.get_call_type.memo
        assert len(memo) == 1
    assert not numba_typing_memo.active() and numba_functions.BaseFunction.get_call_type is ORIGINAL_CALL_TYPE
    with numba_typing_memo.remembered_call_types():  # a fresh memo each time it is put in place
        assert numba_functions.BaseFunction.get_call_type.memo == {}


def test_an_overload_called_under_other_flags_is_typed_under_them():
    """An @overload's implementation is compiled with its caller's flags: one function that divides by zero
    under NumPy's error model (inf) and one under Python's (ZeroDivisionError), both compiled while the memo
    is in place, each behave as their own flags say."""
    from numba.extending import overload

    def divide(x, y):
        return x / y

    @overload(divide)
    def _divide(x, y):
        return lambda x, y: x / y

    @numba.njit(error_model="numpy")
    def numpy_model(x, y):
        return divide(x, y)

    @numba.njit
    def python_model(x, y):
        return divide(x, y)

    with numba_typing_memo.remembered_call_types():
        assert numpy_model(1.0, 0.0) == np.inf
        with pytest.raises(ZeroDivisionError):
            python_model(1.0, 0.0)


def _nested_inlining_kernel():
    """A fresh kernel inlining one helper at four sites, the helper inlining another at two."""

    @numba.njit(inline="always")
    def square(x):
        return x * x

    @numba.njit(inline="always")
    def norm2(x, y):
        return square(x) + square(y)

    @numba.njit(error_model="numpy")
    def kernel(a):
        total = 0.0
        for i in range(a.size - 1):
            if a[i] > 0:
                total += norm2(a[i], a[i + 1]) / norm2(a[i + 1], 1.0)
            else:
                total -= norm2(a[i], 2.0) + norm2(1.0, a[i])
        return total

    return kernel


def test_each_inlined_functions_ir_built_once_compiles_the_same_code(monkeypatch):
    """The same results and machine code both ways, with the helpers' pipelines run once each instead of
    once per site; the caller's flags come out the same (SSA off while it inlines)."""
    from numba.core.inline_closurecall import InlineWorker

    runs = []
    original = InlineWorker.run_untyped_passes

    def counted(self, func, enable_ssa=False):
        runs.append(func.__name__)
        return original(self, func, enable_ssa)

    monkeypatch.setattr(InlineWorker, "run_untyped_passes", counted)
    a = np.linspace(-2, 3, 11)
    plain = _nested_inlining_kernel()
    want = plain(a)
    plain_runs, runs[:] = list(runs), []
    remembered = _nested_inlining_kernel()
    with numba_callee_ir.remembered_callee_irs():
        assert numba_callee_ir.active()
        got = remembered(a)
    assert not numba_callee_ir.active()
    assert got == want == pytest.approx(plain.py_func(a))
    assert _machine_code(remembered) == _machine_code(plain)
    assert plain_runs.count("norm2") == 4 and runs.count("norm2") == 1, (plain_runs, runs)
