"""Install-time steps pyproject.toml cannot declare: the inspection kernels compiled ahead of time.

`mlaqc._kernels` is built by numba.pycc from the kernels' own sources (mlaqc/compiled_build.py), for this
machine's CPU, so the first `mlaqc inspect` after `pip install` compiles nothing. A build that fails (no C
compiler, no Numba in the build environment) only warns: the package then compiles the kernels with
Numba's JIT on first use, as before. An editable install also byte-compiles the sources, which
PYTHONDONTWRITEBYTECODE would otherwise have every run recompile, and compiles the ray tracer's variants
for the shipped fixtures into Numba's cache beside them (mlaqc.optics.tracer_variants.INSTALL_VARIANTS), so
that `mlaqc demo` and every fixture never wait for a compile; the other seven variants compile in the
background of the first command that traces (mlaqc.optics.tracer_background). MLAQC_AOT=0 skips both.
"""

from __future__ import annotations

import compileall
import os
import shutil
import subprocess
import sys
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

HERE = Path(__file__).resolve().parent


class BuildKernels(build_ext):
    """Build `mlaqc._kernels` with numba.pycc instead of a C compiler run over sources."""

    def run(self) -> None:
        self._built: list[Path] = []
        # an editable install also compiles the fixtures' tracer variants: started now, one process per core,
        # so that they share the machine with the kernels' build rather than wait for it
        self._tracer = self._start_tracer() if getattr(self, "editable_mode", False) else None
        super().run()

    def build_extension(self, ext: Extension) -> None:
        target = Path(self.get_ext_fullpath(ext.name))
        if os.environ.get("MLAQC_AOT", "1") == "0":
            print("mlaqc: MLAQC_AOT=0, kernels left to Numba's JIT", file=sys.stderr)
            return
        sys.path.insert(0, str(HERE))
        try:
            from mlaqc.compiled_build import build_extension

            build_extension(target, log=lambda text: print(text, file=sys.stderr))
            self._built.append(target)
        except Exception as exc:  # noqa: BLE001 - any failure leaves the JIT path, which always works
            print(f"mlaqc: WARNING: the kernels were not compiled ahead of time ({type(exc).__name__}: {exc}); "
                  "Numba compiles them on first use instead (`mlaqc kernels` retries)", file=sys.stderr)
        finally:
            sys.path.remove(str(HERE))

    def copy_extensions_to_source(self) -> None:
        """Editable install: the built extension and its stamp into the package folder, sources byte-compiled."""
        for built in self._built:
            for name in (built.name, "_kernels.stamp"):
                src = built.parent / name
                dst = HERE / "mlaqc" / name
                part = dst.with_name(dst.name + ".part")
                shutil.copyfile(src, part)
                os.chmod(part, 0o755 if name == built.name else 0o644)
                os.replace(part, dst)
        for package in ("mlaqc", "drivers", "gui"):
            compileall.compile_dir(str(HERE / package), quiet=1)
        if os.environ.get("MLAQC_AOT", "1") != "0":
            self._compile_tracer()

    def _start_tracer(self) -> subprocess.Popen | None:
        """The shipped fixtures' tracer variants compiled into Numba's cache in the source tree (where the
        editable install runs it), one process per core: the demo and the fixtures never wait; the other
        variants compile in the background of the first command that traces (mlaqc.optics.tracer_background),
        or with `mlaqc kernels`."""
        if os.environ.get("MLAQC_AOT", "1") == "0":
            return None
        code = (f"import sys; sys.path.insert(0, {str(HERE)!r})\n"
                "from mlaqc.optics.tracer_variants import INSTALL_VARIANTS, compile_all\n"
                "compile_all(INSTALL_VARIANTS, log=lambda text: print(text, flush=True))\n")
        try:
            return subprocess.Popen([sys.executable, "-c", code], cwd=str(HERE), stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True,
                                    env={**os.environ, "MLAQC_BACKGROUND_COMPILE": "0"})
        except OSError as exc:
            print(f"mlaqc: WARNING: the ray tracer was not compiled at install ({exc}); `mlaqc kernels` compiles it",
                  file=sys.stderr)
            return None

    def _compile_tracer(self) -> None:
        """Wait for the tracer's compile (started with the build, or now) and say how it went."""
        proc = getattr(self, "_tracer", None) or self._start_tracer()
        if proc is None:
            return
        print("mlaqc: compiling the ray tracer's variants for the shipped fixtures into Numba's cache ...",
              file=sys.stderr)
        out, _ = proc.communicate()
        print(out.rstrip(), file=sys.stderr)
        if proc.returncode != 0 or "FAILED" in out:
            print("mlaqc: WARNING: the ray tracer was not compiled at install (compiled on first use instead; "
                  "`mlaqc kernels` compiles it)", file=sys.stderr)

    def get_outputs(self) -> list[str]:
        built = getattr(self, "_built", [])
        return [str(p) for p in built] + [str(p.parent / "_kernels.stamp") for p in built]

    def get_output_mapping(self) -> dict[str, str]:
        return {str(p): str(HERE / "mlaqc" / p.name) for p in getattr(self, "_built", [])}


setup(ext_modules=[Extension("mlaqc._kernels", sources=[])], cmdclass={"build_ext": BuildKernels})
