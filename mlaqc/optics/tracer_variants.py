"""The ray tracer's compiled variants: which there are, compiling them all once, and whether each is ready.

The Numba kernel is specialised where a measurement showed it pays (raytrace_kernels): the lens boundary
model (grid, sag-intersection, circle apertures), the lattice (square, hex) and per-lens tilts (the tilted
kernel is 2.4-2.8x slower per ray on an untilted array). A textured scene and a global MLA rotation are
run-time switches inside each. That makes twelve variants, which every camera the config can describe
falls into. `pip install -e .` compiles the five the shipped fixtures use into Numba's cache (setup.py),
the first command that traces starts the other seven in the background (tracer_background); `mlaqc
kernels` compiles them all in the foreground, and `mlaqc kernels --check` says which are ready.
"""

from __future__ import annotations

import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Callable

from mlaqc.parallel import cores


@dataclass(frozen=True)
class Variant:
    """One compiled kernel: lens boundaries ('grid', 'sag-intersection' or 'circle' apertures), lattice
    ('square' or 'hex'), and whether any lens is tilted."""

    lenses: str
    packing: str
    tilted: bool

    @property
    def name(self) -> str:
        return f"{self.packing} {self.lenses}{', tilted lenses' if self.tilted else ''}"

    def camera(self):
        """(config, error map) of a 2 x 2-lens camera of this variant."""
        from mlaqc.optics.config import config_from_dict
        from mlaqc.optics.errormap import ErrorMap

        mla = {"count_w": 2, "count_h": 2, "packing": self.packing,
               "boundaries": "grid" if self.lenses == "circle" else self.lenses}
        if self.lenses == "circle":
            mla.update(aperture="circle", aperture_diameter_um=90.0)
        cfg = config_from_dict({"mla": mla, "sensor": {"width_px": 48, "height_px": 48}})
        errors = ErrorMap.zeros(2, 2, self.packing)
        return cfg, (errors.with_lens(1, 1, tilt_x_deg=0.5) if self.tilted else errors)

    def renderer(self):
        """A numba Renderer of that camera (a few rays compile or load its kernel)."""
        from mlaqc.optics.render import Renderer

        return Renderer(*self.camera(), engine="numba")


VARIANTS = tuple(Variant(lenses, packing, tilted) for lenses in ("sag-intersection", "grid", "circle")
                 for packing in ("square", "hex") for tilted in (False, True))
#: compiled by `pip install -e .`: the variants of the shipped fixtures (Table 1 and the demo, hex, circle and
#: hex-circle apertures, a tilted error map), longest compile first; the rest in the background
INSTALL_VARIANTS = (Variant("sag-intersection", "hex", False), Variant("sag-intersection", "square", False),
                    Variant("sag-intersection", "square", True), Variant("circle", "hex", False),
                    Variant("circle", "square", False))


def compile_variant(variant: Variant) -> tuple[float, str]:
    """Compile (or load from Numba's cache) one variant's kernel: (seconds, error or '')."""
    from mlaqc.compiled import announced
    from mlaqc.optics.scene import WhiteScene

    announced("the ray tracer")  # the caller says what is compiled, variant by variant
    start = time.perf_counter()
    try:
        variant.renderer().render(WhiteScene(), rays=2_000, seed=0, threads=1)
    except Exception as exc:  # noqa: BLE001 - reported by the caller; the variant then compiles on first use
        return time.perf_counter() - start, f"{type(exc).__name__}: {exc}"
    return time.perf_counter() - start, ""


def is_ready(variant: Variant) -> bool:
    """True when this process has the variant's kernel or Numba's cache holds it for this machine (loads it,
    never compiles)."""
    from mlaqc.optics.kernel_layout import IMAGE_SIDE

    trace, args = variant.renderer().fast.call(IMAGE_SIDE, 0, 8)
    signature = tuple(trace.typeof_pyval(a) for a in args)
    if signature in trace.overloads:
        return True
    try:
        return trace._cache.load_overload(signature, trace.targetctx) is not None
    except Exception:  # noqa: BLE001 - no usable cache (read-only, foreign, damaged): not ready
        return False


def compile_all(variants: tuple[Variant, ...] = VARIANTS, processes: int | None = None,
                log: Callable[[str], None] = print) -> list[tuple[Variant, float, str]]:
    """Compile every variant into Numba's cache, `processes` at a time (default: one per core), each in a
    fresh interpreter; logs a line per variant and returns (variant, seconds, error or '')."""
    workers = max(1, min(processes or cores(), len(variants)))
    out = []
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        for variant, (seconds, error) in zip(variants, pool.map(compile_variant, variants)):
            log(f"  {variant.name}: {'FAILED ' + error if error else f'{seconds:.0f} s'}")
            out.append((variant, seconds, error))
    return out
