"""The tracer compiled once (#40): twelve variants cover every camera, a global rotation and a texture are
run-time switches that compile nothing of their own, `mlaqc kernels --check` says what is compiled, and
the inliner's faster copy makes the same IR."""

import collections
import copy
import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mlaqc import numba_inliner
from mlaqc.optics import kernel_layout, kernel_sampling, raytrace_kernels
from mlaqc.optics.config import config_from_dict, load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import TextureScene, WhiteScene
from mlaqc.optics.tracer_variants import VARIANTS, Variant, is_ready

ROOT = Path(__file__).resolve().parent.parent
FIXTURES = ROOT / "fixtures"
pytestmark = pytest.mark.skipif(not raytrace_kernels.AVAILABLE, reason="needs numba")


def _signature(renderer: Renderer, texture=None) -> tuple:
    """The kernel and Numba argument types one batch of this renderer calls (what selects a compiled variant)."""
    trace, args = renderer.fast.call(kernel_layout.IMAGE_SIDE, 0, 8, texture=texture)
    return trace.__name__, tuple(trace.typeof_pyval(a) for a in args)


def test_the_twelve_variants_are_twelve_distinct_kernels():
    signatures = {_signature(v.renderer()) for v in VARIANTS}
    assert len(VARIANTS) == 12 and len(signatures) == 12


@pytest.mark.parametrize("variant", VARIANTS[:6], ids=lambda v: v.name)
def test_a_global_rotation_and_a_texture_use_the_variants_own_kernel(variant: Variant):
    """Neither a rotated MLA nor a textured scene selects other code (each was a compile of its own)."""
    cfg, errors = variant.camera()
    base = Renderer(cfg, errors, engine="numba")
    rotated = Renderer(cfg, errors.with_globals(mla_rotation_deg=0.4, mla_tilt_x_deg=0.1), engine="numba")
    assert rotated.camera.rotated
    assert _signature(rotated) == _signature(base)
    assert _signature(base, texture=np.full((5, 7), 0.3)) == _signature(base)


def test_every_fixture_camera_falls_into_one_of_the_variants():
    known = {_signature(v.renderer()) for v in VARIANTS}
    for path in sorted(FIXTURES.glob("*.toml")):
        if path.name.startswith("scan_plan"):
            continue
        cfg = load_config(path)
        small = dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, count_w=3, count_h=3),
                                    sensor=dataclasses.replace(cfg.sensor, width_px=64, height_px=64))
        for tilt in (0.0, 0.5):
            errors = ErrorMap.zeros(3, 3, cfg.mla.packing).with_lens(2, 2, tilt_y_deg=tilt)
            try:
                r = Renderer(small, errors, engine="numba")
            except Exception as exc:  # noqa: BLE001 - a camera the tracer does not model (an ideal main lens)
                assert "main lens" in str(exc) or "thick" in str(exc), (path.name, exc)
                break
            assert _signature(r) in known, path.name


def test_the_texture_switch_weighs_every_ray_by_its_texel():
    """A uniform texture of 0.5 gives exactly half the frame of one of 1.0 (the same rays; 0.5 is exact in
    binary), and a texture dark on one half darkens one half of the frame only (the main lens inverts the
    image): the switch is read.
    Off, it changes nothing (the white scene's frames equal the NumPy engine's, test_raytrace_kernels)."""
    cfg = config_from_dict({"mla": {"count_w": 4, "count_h": 4, "boundaries": "grid"},
                            "sensor": {"width_px": 80, "height_px": 80}})
    r = Renderer(cfg, ErrorMap.zeros(4, 4).with_lens(2, 3, radius_front_rel=0.03), engine="numba")
    frames = {value: r.render(TextureScene(np.full((6, 6), value)), rays=60_000, seed=4, threads=1).photons
              for value in (0.5, 1.0)}
    assert frames[1.0].sum() > 0
    np.testing.assert_array_equal(frames[0.5], 0.5 * frames[1.0])
    half = np.ones((6, 6))
    half[:, :3] = 0.0
    dark = r.render(TextureScene(half), rays=60_000, seed=4, threads=1).photons
    lit = frames[1.0]
    kept = sorted((dark[:, 45:].sum() / lit[:, 45:].sum(), dark[:, :35].sum() / lit[:, :35].sum()))
    assert kept[0] < 0.3 and kept[1] > 0.7, kept


def test_shared_scope_copies_make_the_same_ir_with_one_scope():
    """The faster copy gives the blocks of one IR one copy of their scope (as the original has), and the
    same statements as Numba's own block-by-block copy."""
    from numba.core import inline_closurecall, ir
    from numba.core.compiler import run_frontend

    func_ir = run_frontend(raytrace_kernels.pass_front_refract.py_func)
    assert len(func_ir.blocks) > 5
    plain = {label: inline_closurecall.copy.deepcopy(block) for label, block in func_ir.blocks.items()}
    with numba_inliner.shared_scope_copies():
        assert numba_inliner.active()
        shared = {label: inline_closurecall.copy.deepcopy(block) for label, block in func_ir.blocks.items()}
    assert not numba_inliner.active() and inline_closurecall.copy is copy
    assert len({id(b.scope) for b in plain.values()}) == len(plain)  # Numba's: a scope per block
    assert len({id(b.scope) for b in shared.values()}) == 1
    assert next(iter(shared.values())).scope is not next(iter(func_ir.blocks.values())).scope
    for label in func_ir.blocks:
        assert [str(s) for s in shared[label].body] == [str(s) for s in plain[label].body]
        assert isinstance(shared[label], ir.Block)


def _isomorphic(a, b, seen: dict, originals: set, path: str = "ir") -> None:
    """Two copies of one object graph: the same types and atoms, the same sharing (one object in one copy
    wherever there is one in the other), no original among the copied objects; objects both hold (module
    globals, constants Numba does not copy) are the same object."""
    if a is b:
        assert id(a) not in seen, path
        return
    assert type(a) is type(b), (path, type(a), type(b))
    assert id(a) not in originals and id(b) not in originals, ("an original in a copy", path)
    if id(a) in seen or id(b) in seen.values():
        assert seen.get(id(a)) == id(b), ("shared differently", path)
        return
    seen[id(a)] = id(b)
    if isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (u, v) in enumerate(zip(a, b)):
            _isomorphic(u, v, seen, originals, f"{path}[{i}]")
    elif isinstance(a, dict):
        assert list(a) == list(b), path
        for k in a:
            _isomorphic(a[k], b[k], seen, originals, f"{path}[{k!r}]")
    elif hasattr(a, "__dict__"):
        _isomorphic(vars(a), vars(b), seen, originals, f"{path}.{type(a).__name__}")
    else:
        assert a == b, (path, a, b)


def _ir_objects(x, out: set) -> set:
    """ids of the IR's own objects (its blocks, statements, expressions, scope, containers)."""
    if id(x) in out or isinstance(x, (str, int, float, bool, type(None))):
        return out
    if isinstance(x, (list, tuple, dict)) or type(x).__module__ == "numba.core.ir":
        out.add(id(x))
        items = x.values() if isinstance(x, dict) else x if isinstance(x, (list, tuple)) else vars(x).values()
        for v in items:
            _ir_objects(v, out)
    return out


@pytest.mark.parametrize("name", ["kernel", "kernel_sag", "scan_candidates", "bin_hits", "sampling.stage1_forward"])
def test_the_inliners_copy_is_copy_deepcopys_object_for_object(name):
    """numba_inliner.ir_deepcopy copies a whole IR, block by block through one memo as the inliner does,
    into the same object graph as copy.deepcopy: types, values, which objects are shared, nothing original."""
    from numba.core.compiler import run_frontend

    module, _, name = name.rpartition(".")
    blocks = run_frontend(getattr(kernel_sampling if module else raytrace_kernels, name).py_func).blocks
    theirs_memo, ours_memo = {}, {}
    theirs = {label: copy.deepcopy(block, theirs_memo) for label, block in blocks.items()}
    ours = {label: numba_inliner.ir_deepcopy(block, ours_memo) for label, block in blocks.items()}
    _isomorphic(theirs, ours, {}, _ir_objects(blocks, set()))
    assert len(ours_memo) > 100


def test_the_fast_copy_leaves_objects_with_a_copy_protocol_of_their_own_to_copy():
    """A class with its own __deepcopy__, __reduce__ or __getstate__, slots, or a dict subclass, is copied
    by copy.deepcopy itself."""

    class Own:
        def __deepcopy__(self, memo):
            return "own"

    class State:
        def __getstate__(self):
            return {"x": 1}

    class Slots:
        __slots__ = ("a",)

    class Plain:
        def __init__(self):
            self.items = [1, [2]]

    class Text(str):
        pass

    class Made:
        def __new__(cls, a):
            return super().__new__(cls)

        def __getnewargs__(self):
            return (1,)

    assert numba_inliner.ir_deepcopy([Own()], {}) == ["own"]
    assert not any(numba_inliner._is_plain(c) for c in (State, Slots, Text, Made, collections.defaultdict,
                                                       collections.OrderedDict))
    assert numba_inliner.ir_deepcopy([Text("ab")], {}) == ["ab"]
    assert isinstance(numba_inliner.ir_deepcopy(Made(1), {}), Made)
    p = Plain()
    q = numba_inliner.ir_deepcopy((p, p), {})
    assert q[0] is q[1] and q[0] is not p and q[0].items == [1, [2]] and q[0].items[1] is not p.items[1]


def test_kernels_check_names_the_variants_an_empty_cache_lacks(tmp_path):
    """`mlaqc kernels --check` with a Numba cache that holds nothing: exit 1, every variant named; it
    compiles nothing (a check that compiled would take minutes)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), MLAQC_AOT="0")
    out = subprocess.run([sys.executable, "-m", "mlaqc", "kernels", "--check"], env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 1, out.stderr
    line = next(t for t in out.stdout.splitlines() if t.startswith("tracer:"))
    assert line.startswith("tracer: 0 of 12 variants compiled; not: ")
    assert all(v.name in line for v in VARIANTS)
    assert not (tmp_path / "numba").exists() or not any((tmp_path / "numba").rglob("*.nbc"))


def test_a_variant_compiled_in_this_process_is_ready():
    variant = VARIANTS[2]  # hex sag-intersection
    variant.renderer().render(WhiteScene(), rays=2_000, seed=0, threads=1)
    assert is_ready(variant)
