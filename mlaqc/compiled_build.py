"""Build the ahead-of-time kernel extension (numba.pycc): run by setup.py at install and by `mlaqc kernels`.

Every kernel of `mlaqc.compiled.AOT_MODULES` that declares signatures is exported once per signature, with
its own Numba options (nogil releases the GIL, error_model, fastmath) and for this CPU's name and features,
as Numba's JIT would compile it: the same machine code, so the same results bit for bit
(tests/test_compiled.py). Needs Numba, NumPy and a C compiler; what it cannot build, the JIT does at run time.
"""

from __future__ import annotations

import importlib.machinery
import os
import shutil
import tempfile
import time
import warnings
from pathlib import Path


def build_extension(target: Path, *, log=print) -> Path:
    """Compile every declared kernel into the extension file `target` (plus its `.stamp`); return target."""
    from mlaqc import compiled

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba.pycc's pending-deprecation notice
        from numba.core import compiler as numba_compiler
        from numba.core.codegen import AOTCPUCodegen
        from numba.core.cpu import CPUTargetOptions
        from numba.pycc import CC
        import numba.pycc.compiler as pycc_compiler

    target = Path(target).resolve()
    stamp = compiled.current_stamp()  # once, before the minute of compiling: a source edited meanwhile is stale
    kernels = compiled.declared_kernels()
    start = time.perf_counter()
    options: dict[object, dict] = {}
    with tempfile.TemporaryDirectory(prefix="mlaqc-aot-") as tmp:
        cc = CC(compiled.EXTENSION)
        cc.output_dir = tmp
        cc.target_cpu = "host"
        cc.verbose = False
        for k in kernels:
            for name, signature in zip(k.export_names, k.signatures):
                fn = k.dispatcher.py_func  # over globals where its fellow kernels are JIT dispatchers
                options[fn] = k.options
                cc.export(name, _full_signature(k, signature))(fn)
        cc.export(f"stamp_{stamp}", "i8()")(lambda: 0)
        patches = _patch_numba(pycc_compiler, numba_compiler, CPUTargetOptions, AOTCPUCodegen, options)
        try:
            cc.compile()
        finally:
            for obj, name, old in patches:
                setattr(obj, name, old)
        built = Path(tmp) / cc.output_file
        target.parent.mkdir(parents=True, exist_ok=True)
        part = target.with_name(target.name + ".part")
        shutil.copyfile(built, part)
        os.chmod(part, 0o755)
        os.replace(part, target)
    (target.parent / f"{compiled.EXTENSION}.stamp").write_text(stamp + "\n")
    log(f"mlaqc: compiled {sum(len(k.signatures) for k in kernels)} kernel variants ahead of time into {target} "
        f"({time.perf_counter() - start:.0f} s)")
    return target


def default_target() -> Path:
    """The extension's file in the package folder."""
    from mlaqc import compiled

    return compiled.PACKAGE_DIR / f"{compiled.EXTENSION}{importlib.machinery.EXTENSION_SUFFIXES[0]}"


def _full_signature(k, signature: str):
    """The Numba signature ret(args) of a declared argument list; ret is what the JIT infers for them."""
    import numpy as np
    from numba import from_dtype, types as nb_types
    from numba.core.typing import signature as make_signature

    from mlaqc import compiled

    args = []
    for code in compiled.split_signature(signature):
        key = compiled._arg_key(code)
        if key[0] == "a":
            args.append(nb_types.Array(from_dtype(np.dtype(key[1])), key[2], "C" if key[3] else "A"))
        else:
            args.append(from_dtype(np.dtype(key[2])))
    k.dispatcher.compile(tuple(args))
    return make_signature(k.dispatcher.overloads[tuple(args)].signature.return_type, *args)


def _patch_numba(pycc_compiler, numba_compiler, target_options, aot_codegen, options: dict) -> list:
    """Patch pycc for the build: each export compiled with its kernel's own options, for this CPU's features."""
    patches = []

    def set_attr(obj, name, value):
        patches.append((obj, name, getattr(obj, name)))
        setattr(obj, name, value)

    compile_extra = pycc_compiler.compile_extra

    def compile_with_options(typingctx, targetctx, func, args, return_type, flags, locals, library):
        if func in options:
            own = numba_compiler.Flags()
            target_options.parse_as_flags(own, {k: v for k, v in options[func].items() if k != "cache"})
            for name in ("no_compile", "no_cpython_wrapper", "no_cfunc_wrapper", "nrt"):
                setattr(own, name, getattr(flags, name))
            flags = own
        return compile_extra(typingctx, targetctx, func, args, return_type, flags, locals, library)

    set_attr(pycc_compiler, "compile_extra", compile_with_options)
    set_attr(aot_codegen, "_customize_tm_features", lambda self: self._get_host_cpu_features())
    return patches
