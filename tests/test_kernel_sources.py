"""Numba's cache of a kernel module is stale when any source it is compiled from changes
(mlaqc.optics.kernel_sources): two throw-away modules, a kernel that inlines a helper from the other,
compiled in fresh processes as a user's commands would be."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from mlaqc.optics import kernel_sources, tracer_background

pytest.importorskip("numba")

KERNEL = textwrap.dedent("""
    from pathlib import Path
    from numba import njit
    from mlaqc.optics import kernel_sources
    {register}
    import helper_mod
    g = njit(inline="always", cache=True)(helper_mod.f)

    @njit(cache=True)
    def k(x):
        return g(x) * 2.0
""")
REGISTER = 'kernel_sources.register((Path(__file__), "helper_mod"))'
# the tracer's layout: the first kernel file imported registers every kernel file, a helper file's own
# functions are jitted there, and the kernel inlines them from it
JIT_MOD = textwrap.dedent("""
    from pathlib import Path
    from numba import njit
    from mlaqc.optics import kernel_sources
    HERE = Path(__file__).resolve().parent
    kernel_sources.register((HERE / "kernel_mod.py", HERE / "helper_mod.py"))
    inline = njit(inline="always", cache=True)
""")
HELPER_FILE = "from jit_mod import inline\n\n@inline\ndef f(x):\n    return x + {}\n"
KERNEL_OF_FILES = textwrap.dedent("""
    from numba import njit
    from jit_mod import inline
    from helper_mod import f

    @njit(cache=True)
    def k(x):
        return f(x) * 2.0
""")


def run(folder: Path, path: Path | None = None) -> tuple[str, bool]:
    """k(1.0) in a fresh process, and whether it came from Numba's cache; `path`: the folder the modules
    are imported from (another name for `folder`, say)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CACHE")}
    env["NUMBA_DEBUG_CACHE"] = "1"
    if path is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(path), env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, "-c", "import kernel_mod; print('k =', kernel_mod.k(1.0))"],
                         cwd=folder if path is None else folder.parent, env=env, capture_output=True, text=True,
                         check=True).stdout
    value = next(line for line in out.splitlines() if line.startswith("k = "))[4:]
    return value, "data loaded from" in out


@pytest.mark.parametrize("registered", [True, False])
def test_an_edited_helper_module_recompiles_the_kernel(tmp_path, registered):
    """Numba alone serves the old machine code after the helper's module changes; registered, the
    kernel is compiled again."""
    (tmp_path / "helper_mod.py").write_text("def f(x):\n    return x + 1.0\n")
    (tmp_path / "kernel_mod.py").write_text(KERNEL.format(register=REGISTER if registered else ""))
    assert run(tmp_path) == ("4.0", False)
    assert run(tmp_path) == ("4.0", True)  # the second process loads it from the cache
    (tmp_path / "helper_mod.py").write_text("def f(x):\n    return x + 100.0\n")
    assert run(tmp_path) == (("202.0", False) if registered else ("4.0", True))


@pytest.mark.parametrize("linked", [False, True])
def test_a_split_off_helper_file_recompiles_the_kernel_that_inlines_it(tmp_path, linked):
    """As the tracer is laid out (kernel_jit registers kernel_geometry, kernel_sampling and
    raytrace_kernels): an edit to a jitted helper's own file recompiles the kernel in another file; also
    where the package is imported through a symlink (Numba then names the files by the link's path,
    while the registration resolved it)."""
    folder = tmp_path / "real"
    folder.mkdir()
    link = None
    if linked:
        link = tmp_path / "link"
        link.symlink_to(folder, target_is_directory=True)
    (folder / "jit_mod.py").write_text(JIT_MOD)
    (folder / "helper_mod.py").write_text(HELPER_FILE.format("1.0"))
    (folder / "kernel_mod.py").write_text(KERNEL_OF_FILES)
    assert run(folder, link) == ("4.0", False)
    assert run(folder, link) == ("4.0", True)
    (folder / "helper_mod.py").write_text(HELPER_FILE.format("100.0"))
    assert run(folder, link) == ("202.0", False)


def test_the_tracer_is_stamped_by_everything_it_takes_from_other_modules():
    """Every name a kernel file imports from an mlaqc module is in the stamp, as a kernel file, a whole
    module or by name; every module that jits tracer code is a kernel file; the background job's stamp
    covers the same."""
    import ast

    srcs = kernel_sources.TRACER_SOURCES
    files = {p.stem for p in kernel_sources.KERNEL_FILES}
    whole = {s.rsplit(".", 1)[1] for s in srcs if isinstance(s, str)} | files
    named = {(m.rsplit(".", 1)[1], n) for m, n in (s for s in srcs if isinstance(s, tuple))}
    assert files == {"kernel_jit", "kernel_geometry", "kernel_sampling", "raytrace_kernels"}
    assert all(p in srcs and p.exists() for p in kernel_sources.KERNEL_FILES)
    for path in kernel_sources.KERNEL_FILES:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module == "mlaqc.optics":
                assert {a.name for a in node.names} - {"kernel_sources"} <= whole
            elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mlaqc."):
                module = node.module.rsplit(".", 1)[1]
                assert module in whole or all((module, a.name) in named for a in node.names), node.module
    jitting = {p.stem for p in Path(kernel_sources.__file__).parent.glob("*.py")
               if "from mlaqc.optics.kernel_jit import" in p.read_text()}
    assert jitting <= files
    assert set(srcs) <= set(tracer_background.SOURCES)


def test_registering_again_keeps_one_locator_in_front():
    """A second registration (a module reloaded) replaces the first locator, and Numba's own stay."""
    from numba.core import caching

    before = [c for c in caching.CacheImpl._locator_classes if not hasattr(c, "_mlaqc_sources_locator")]
    kernel_sources.register(kernel_sources.TRACER_SOURCES)
    kernel_sources.register(kernel_sources.TRACER_SOURCES)
    now = caching.CacheImpl._locator_classes
    assert hasattr(now[0], "_mlaqc_sources_locator") and now[1:] == before


def test_the_stamp_follows_a_borrowed_function_and_constant(monkeypatch):
    from mlaqc.optics import scene

    before = kernel_sources.digest(kernel_sources.TRACER_SOURCES)
    monkeypatch.setattr(scene, "FOUR_OVER_PI", scene.FOUR_OVER_PI * (1 + 1e-15))
    assert kernel_sources.digest(kernel_sources.TRACER_SOURCES) != before


def test_the_stamp_is_the_loaded_code_not_the_file(tmp_path, monkeypatch):
    """A module edited on disk after this process imported it: the stamp stays that of the code loaded,
    so what this process compiles is not saved as the new file's."""
    (tmp_path / "loaded_mod.py").write_text("def f(x):\n    return x + 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import loaded_mod  # noqa: F401

    before = kernel_sources.digest(("loaded_mod",))
    (tmp_path / "loaded_mod.py").write_text("def f(x):\n    return x + 2.0\n")
    assert kernel_sources.digest(("loaded_mod",)) == before


def test_a_module_of_jitted_helpers_is_stamped_by_their_code(tmp_path, monkeypatch):
    """A module whose helpers are Numba dispatchers (as one split off raytrace_kernels would be): its stamp
    follows their Python code."""
    import importlib

    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    path = tmp_path / "jit_helpers_mod.py"
    digests = []
    for body in ("x + 1.0", "x + 200.0"):
        path.write_text(f"from numba import njit\n\n\n@njit(inline='always')\ndef f(x):\n    return {body}\n")
        module = (importlib.reload(sys.modules["jit_helpers_mod"]) if digests
                  else importlib.import_module("jit_helpers_mod"))
        assert hasattr(module.f, "py_func")
        digests.append(kernel_sources.digest(("jit_helpers_mod",)))
    assert digests[0] != digests[1]
