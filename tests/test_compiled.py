"""The kernels compiled ahead of time: the same results as Numba's JIT bit for bit, used only while current,
never called with other types, and a JIT compile said once and kept out of the stage timings."""

import copy
import io
import os
import subprocess
import sys
import threading
import time
from contextlib import redirect_stderr
from pathlib import Path

import numpy as np
import pytest

from mlaqc import compiled

ROOT = Path(__file__).resolve().parent.parent
SMALL = ROOT / "fixtures" / "small_camera.toml"
CURRENT, WHY = compiled.aot_status()
needs_aot = pytest.mark.skipif(not CURRENT and os.environ.get("MLAQC_REQUIRE_AOT") != "1",
                               reason=f"no current ahead-of-time build ({WHY}); `mlaqc kernels` makes one")


def test_ci_has_the_ahead_of_time_kernels():
    """CI sets MLAQC_REQUIRE_AOT=1: an install whose kernel build failed is a red run, not a slow one."""
    if os.environ.get("MLAQC_REQUIRE_AOT") != "1":
        pytest.skip("MLAQC_REQUIRE_AOT is not set (a development checkout may be ahead of its build)")
    assert CURRENT, WHY


def test_signature_parsing():
    assert compiled.split_signature("f4[:, ::1], i8, b1[::1], f8[:, :, ::1]") == ["f4[:, ::1]", "i8", "b1[::1]",
                                                                                    "f8[:, :, ::1]"]
    assert compiled._arg_key("f4[:, ::1]") == ("a", "f", 2, True)
    assert compiled._arg_key("u2[:, :]") == ("a", "H", 2, False)
    assert compiled._arg_key("i8") == ("s", "i", "l")
    assert compiled._arg_key("b1") == ("s", "b", "?")
    with pytest.raises(ValueError):
        compiled._arg_key("c16[:]")


def test_argument_types_must_match_exactly():
    keys = tuple(compiled._arg_key(a) for a in compiled.split_signature("f4[:, ::1], i8, f8, b1"))
    img = np.zeros((4, 5), np.float32)
    assert compiled._matches(keys, (img, 3, 2.5, True))
    assert compiled._matches(keys, (img, np.int64(3), np.float64(2.5), np.bool_(False)))
    assert not compiled._matches(keys, (img.astype(np.float64), 3, 2.5, True))  # dtype
    assert not compiled._matches(keys, (img[:, ::2], 3, 2.5, True))  # not C-contiguous
    assert not compiled._matches(keys, (img[None], 3, 2.5, True))  # ndim
    assert not compiled._matches(keys, (img, 3.0, 2.5, True))  # float for an int
    assert not compiled._matches(keys, (img, True, 2.5, True))  # bool for an int
    assert not compiled._matches(keys, (img, 3, 2.5, 1))  # int for a bool
    assert not compiled._matches(keys, (img, 3, 2.5))  # count
    assert not compiled._matches(keys, (img.astype(">f4"), 3, 2.5, True))  # byte order


def test_other_types_go_to_the_jit_and_give_its_answer():
    """A declared kernel called with float64 where float32 is declared runs Numba's JIT (an AOT function
    would read the bytes as float32): the same sample as the float32 call."""
    from mlaqc.inspection.rawio_kernels import ring_residual_sample

    rng = np.random.default_rng(3)
    x = rng.normal(100.0, 5.0, (40, 50)).astype(np.float32)
    want = np.empty((14, 17), np.float32)
    got = np.empty((14, 17), np.float32)
    ring_residual_sample(x, 0, 0, 1, 3, want)
    ring_residual_sample(x.astype(np.float64), 0, 0, 1, 3, got)
    assert np.array_equal(got, want)


def _inspect_small_capturing_calls(tmp_path):
    """Every declared kernel's first call (its arguments, copied) while a small camera's frame is loaded
    and inspected."""
    from mlaqc.inspection.pipeline import inspect_image, load_frame
    from mlaqc.optics.config import load_config
    from mlaqc.optics.errormap import random_defects
    from mlaqc.optics.simulate import simulate, write_simulation

    cfg = load_config(SMALL)
    raw = tmp_path / "frame.tiff"
    write_simulation(raw, simulate(cfg, None, random_defects(24, 24, 3, seed=5), rays_per_pixel=4, seed=5), cfg)
    calls = {}
    original = compiled.Kernel.__call__

    def record(self, *args):
        calls.setdefault(self, copy.deepcopy(args))
        return original(self, *args)

    compiled.Kernel.__call__ = record
    try:
        inspect_image(load_frame(raw, cfg), cfg)
    finally:
        compiled.Kernel.__call__ = original
    return {k: v for k, v in calls.items() if k.signatures}


@needs_aot
def test_ahead_of_time_kernels_match_the_jit_bit_for_bit(tmp_path):
    """Every declared kernel an inspection calls, on the inspection's own arguments: the extension's code and
    Numba's JIT write the same bytes into every output array."""
    calls = _inspect_small_capturing_calls(tmp_path)
    assert len(calls) >= 8, [k.__name__ for k in calls]
    for k, args in calls.items():
        aot_args, jit_args = copy.deepcopy(args), copy.deepcopy(args)
        aot = [fn for keys, fn in k._bind() if compiled._matches(keys, aot_args)]
        assert aot, f"{k.__name__}: no compiled variant for the inspection's own argument types"
        r_aot = aot[0](*aot_args)
        r_jit = k.dispatcher(*jit_args)
        for a, b in zip(aot_args, jit_args):
            if isinstance(a, np.ndarray):
                assert np.array_equal(a, b, equal_nan=True), k.__name__
        assert _same(r_aot, r_jit), k.__name__


def _same(a, b) -> bool:
    """Equal to the bit (NaN equal to NaN), through tuples of arrays and scalars."""
    if isinstance(a, tuple):
        return isinstance(b, tuple) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=np.asarray(a).dtype.kind in "fc")


def test_a_stale_build_is_never_loaded(tmp_path, monkeypatch):
    """A stamp that is not the current sources' (an edited kernel, another CPU) leaves the extension unused."""
    suffix = compiled.importlib.machinery.EXTENSION_SUFFIXES[0]
    fake = tmp_path / f"_kernels{suffix}"
    fake.write_bytes(b"not a shared object")  # would crash the import if it were ever loaded
    (tmp_path / "_kernels.stamp").write_text("0123456789abcdef0123\n")
    monkeypatch.setattr(compiled, "extension_paths", lambda: [fake])
    monkeypatch.setattr(compiled, "_STATE", {**compiled._STATE, "loaded": False, "module": None})
    assert compiled.extension() is None
    assert "out of date" in compiled.aot_status()[1]


def test_a_build_that_does_not_load_leaves_the_jit(tmp_path, monkeypatch):
    """A damaged (or foreign) extension with a current stamp file: no crash, the JIT does the work."""
    suffix = compiled.importlib.machinery.EXTENSION_SUFFIXES[0]
    broken = tmp_path / f"_kernels{suffix}"
    broken.write_bytes(b"\x7fELF truncated")
    (tmp_path / "_kernels.stamp").write_text(compiled.current_stamp() + "\n")
    monkeypatch.setattr(compiled, "extension_paths", lambda: [broken])
    monkeypatch.setattr(compiled, "_STATE", {**compiled._STATE, "loaded": False, "module": None})
    assert compiled.extension() is None
    assert "does not load" in compiled.aot_status()[1]


def test_mlaqc_aot_0_turns_the_extension_off(monkeypatch):
    monkeypatch.setenv("MLAQC_AOT", "0")
    monkeypatch.setattr(compiled, "_STATE", {**compiled._STATE, "loaded": False, "module": None})
    assert compiled.aot_status() == (False, "MLAQC_AOT=0")


def test_stamp_follows_the_kernel_sources():
    stamp = compiled.current_stamp()
    assert len(stamp) == 20 and stamp == compiled.current_stamp()
    assert "flags" in compiled.cpu_identity() or sys.platform != "linux"


def test_net_clock_leaves_out_compile_time(monkeypatch):
    monkeypatch.setitem(compiled._STATE, "compile_s", 0.0)
    a = compiled.net_clock()
    compiled._STATE["compile_s"] += 5.0  # a 5 s compile happened
    assert compiled.net_clock() - a < 0.0


def test_a_long_compile_is_said_once():
    """compile_notice: nothing for a quick call; one line for a slow one, however many threads wait."""
    err = io.StringIO()
    with redirect_stderr(err):
        with compiled.compile_notice("a quick thing", after_s=5.0):
            pass
        said = threading.Event()

        def slow():
            with compiled.compile_notice("the test kernel", after_s=0.01):
                deadline = time.monotonic() + 10
                while "the test kernel" not in err.getvalue() and time.monotonic() < deadline:
                    time.sleep(0.005)
                said.set()

        threads = [threading.Thread(target=slow) for _ in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert said.is_set()
    assert err.getvalue().count("compiling the test kernel once") == 1
    assert "a quick thing" not in err.getvalue()


def _imports_after(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300,
                         env={**os.environ, "QT_QPA_PLATFORM": "offscreen"})
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_help_imports_no_command_module_and_lists_every_command():
    code = ("import sys, contextlib, io; from mlaqc.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()) as f:\n"
            "    try: main(['--help'])\n"
            "    except SystemExit: pass\n"
            "print(all(n in f.getvalue() for n in ('simulate', 'inspect', 'kernels', 'scan', 'gui')), "
            "'numpy' in sys.modules, any(m.startswith('mlaqc.commands.') for m in sys.modules))")
    assert _imports_after(code) == ["True", "False", "False"]


def test_the_command_table_says_what_each_module_registers():
    """`mlaqc --help` shows the table's lines without importing the modules: they must be the modules' own."""
    from mlaqc.cli import COMMANDS, build_parser

    registered = {a.dest: a.help for a in build_parser()._subparsers._group_actions[0]._choices_actions}
    assert registered == {name: line for name, (_, line) in COMMANDS.items()}


@needs_aot
def test_inspecting_imports_neither_numba_nor_scipy_fft(tmp_path):
    """With the kernels compiled ahead of time an inspection never loads Numba (0.4 s with its cache) nor
    the scipy.fft package (0.12 s)."""
    from mlaqc.optics.config import load_config
    from mlaqc.optics.simulate import simulate, write_simulation

    raw = tmp_path / "f.tiff"
    cfg = load_config(SMALL)
    write_simulation(raw, simulate(cfg, None, None, rays_per_pixel=4, seed=2), cfg)
    code = ("import sys; from mlaqc.cli import main\n"
            f"main(['inspect', {str(raw)!r}, '-c', {str(SMALL)!r}, '--out', {str(tmp_path / 'r')!r}, '-q'])\n"
            "print('numba' in sys.modules, 'scipy.fft' in sys.modules, 'scipy.ndimage' in sys.modules)")
    assert _imports_after(code)[-3:] == ["False", "False", "False"]
    assert (tmp_path / "r" / "report.json").is_file()
