"""Tracer benchmark: end-to-end rays/s (source -> main lens -> MLA with per-lens errors -> sensor) and
peak memory on the default camera, for each engine and thread count; then the issue's full-frame bar.

    python bench/trace.py            # all figures (about a minute on 2 idle cores)
    python bench/trace.py --quick    # fewer rays
    python bench/trace.py --huge     # also 10^9 rays in the memory table
    python bench/trace.py --boundaries   # only: sag-intersection vs grid lens boundaries, interleaved runs
    python bench/trace.py --arrays       # only: square grid / sag, hex grid / sag, hex circles, interleaved
    python bench/trace.py --kernels      # only: the same, the tracer's batches alone in short paired rounds
    python bench/trace.py --packing hex --aperture circle   # the main tables on another array
    python bench/trace.py --arrays --against /work/main     # --arrays for that tree's mlaqc and this one's,
                                                            # in child processes taking turns
    python bench/trace.py --kernels --quick --against OLD --rounds 6   # the same for --kernels
    python bench/trace.py --images save ref.npz   # seeded frames of every array kind (both samplers), then
    python bench/trace.py --images check ref.npz  # after a kernel change: are they bit-identical? (every
                                                  # array kind, and every variant of the tracer's kernel)

Wall-clock rates depend on what else runs on the machine; the CPU time per ray (single thread) does not
much, so it is printed too: compare that between revisions on a shared machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import time

from pathlib import Path

import numpy as np

from mlaqc.optics.config import CameraConfig, default_config, load_config
from mlaqc.optics.errormap import ErrorMap, random_defects
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene

DEFECTS = dict(types=("pitch", "decenter", "radius", "thickness"))


FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"


def camera(packing: str = "square", aperture: str = "cell", boundaries: str | None = None) -> tuple[CameraConfig, ErrorMap]:
    """The benchmark camera: Table 1, 200 defective lenses, Fresnel on; hex: fixtures/hex_camera.toml (102
    x 116 lenses on the same sensor); aperture 'circle': 90 µm circles, opaque gaps."""
    cfg = default_config() if packing == "square" else load_config(FIXTURES / "hex_camera.toml")
    mla = {"boundaries": boundaries} if boundaries else {}
    if aperture == "circle":
        mla.update(aperture="circle", aperture_diameter_um=90.0, gap="opaque")
    cfg = dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, **mla))
    return cfg, random_defects(cfg.mla.count_h, cfg.mla.count_w, 200, seed=3, packing=packing, **DEFECTS)


ARRAYS = {"square grid": ("square", "cell", "grid"), "square sag-intersection": ("square", "cell", "sag-intersection"),
          "hex grid": ("hex", "cell", "grid"), "hex sag-intersection": ("hex", "cell", "sag-intersection"),
          "hex circle 90 µm": ("hex", "circle", None), "square circle 90 µm": ("square", "circle", None)}


def compare_arrays(rays: int, repeats: int) -> dict:
    """rays/s (numba, one thread and all cores) of every array kind, against the square grid's (the issue's
    bars: hex and sag-intersection within 1.2x, i.e. >= 0.83x). The host's speed drifts by tens of per cent
    over seconds, so each round runs every array back to back (order alternating) and the ratio is taken
    within the round; the median over rounds and its interquartile range are printed (a ratio of medians
    over the whole run mixes fast and slow phases). Returns {threads: {array: (rays/s ratio, CPU ratio)}}."""
    renderers = warm_renderers()
    cores = os.cpu_count() or 1
    print(f"arrays, numba, {rays:,} rays a run, {repeats} rounds of every array back to back (paired ratios to the "
          "square grid in each round: median [interquartile range]); 200 defective lenses each")
    names = list(renderers)
    ratios = {}
    for threads in sorted({1, cores}):
        got = {b: [] for b in names}
        for k in range(repeats):
            for b in (names if k % 2 == 0 else names[::-1]):
                got[b].append(rate(renderers[b], rays, threads, seed=10 + k))
        ref = got["square grid"]
        ratios[threads] = {}
        for b in names:
            wall, q1, q3 = paired([g[0] / r[0] for g, r in zip(got[b], ref)])
            cpu = paired([r[2] / g[2] for g, r in zip(got[b], ref)])[0]
            ratios[threads][b] = (wall, cpu)
            print(f"  {b:24s} {threads} thread(s): {np_median([g[0] for g in got[b]]):6.2f} M rays/s, "
                  f"{np_median([g[2] for g in got[b]]):6.1f} CPU ns/ray, x{wall:.3f} rays/s "
                  f"[{q1:.2f}-{q3:.2f}] (x{cpu:.3f} by CPU) of square grid")
    return ratios


def compare_kernels(rays: int, rounds: int) -> dict[str, dict[str, tuple[float, float]]]:
    """The tracer's batches alone (no frame assembly), one thread: each round traces the next `rays` rays of
    every array's own job list back to back (order alternating) and takes each array's ratio to the
    square grid within the round, by wall clock and by this thread's CPU time (which a busy host's other
    work and stolen time do not add to). Rounds of a fraction of a second pair far more tightly than whole
    renders on a host whose speed drifts; median and interquartile range over the rounds. Returns
    {"1": {array: (wall ratio, CPU ratio)}}, as compare_arrays does."""
    scene = WhiteScene()
    renderers = warm_renderers()
    plans = {name: r.plan(scene, rays * rounds, None, 3) for name, r in renderers.items()}
    pos, ns, cpu = dict.fromkeys(renderers, 0), {name: [] for name in renderers}, {name: [] for name in renderers}
    names = list(renderers)
    for k in range(rounds):
        for name in (names if k % 2 == 0 else names[::-1]):
            r, plan, n = renderers[name], plans[name], 0
            t, c = time.perf_counter(), time.thread_time()
            while n < rays:
                job = plan.jobs[pos[name] % len(plan.jobs)]
                pos[name] += 1
                r._trace_job(scene, job, int(plan.keys[job.index]))
                n += job.n
            ns[name].append((time.perf_counter() - t) / n * 1e9)
            cpu[name].append((time.thread_time() - c) / n * 1e9)
    print(f"tracer batches alone, numba, 1 thread, {rounds} rounds of ~{rays:,} rays per array (paired ratios to the "
          "square grid in each round: median [interquartile range]; by wall clock, then by CPU time)")
    out = {}
    for name in names:
        med, q1, q3 = paired([a / b for a, b in zip(ns["square grid"], ns[name])])
        cmed, c1, c3 = paired([a / b for a, b in zip(cpu["square grid"], cpu[name])])
        print(f"  {name:24s} {np_median(ns[name]):6.1f} ns/ray, x{med:.3f} [{q1:.3f}-{q3:.3f}] rays/s of square grid; "
              f"CPU x{cmed:.3f} [{c1:.3f}-{c3:.3f}]")
        out[name] = (float(med), float(cmed))
    return {"1": out}


def warm_renderers() -> dict[str, Renderer]:
    """A numba Renderer of every array kind (ARRAYS), each compiled / warmed up by a small render."""
    renderers = {name: Renderer(*camera(*spec), engine="numba") for name, spec in ARRAYS.items()}
    for r in renderers.values():
        r.render(WhiteScene(), rays=200_000, seed=0)
    return renderers


def paired(ratios: list[float]) -> tuple[float, float, float]:
    """Median and interquartile range (first, third quartile) of per-round ratios."""
    v = sorted(ratios)
    return np_median(v), v[len(v) // 4], v[(3 * len(v)) // 4]


def compare_trees(other: str, quick: bool, what: str = "--arrays", rounds: int = 2) -> None:
    """`--arrays` (or `--kernels`) in child processes, the mlaqc of `other` (a checkout, e.g. main's) and
    this tree's taking turns (the host's speed drifts); each child's table, then the ratios to the square
    grid of both trees (medians over the rounds)."""
    here = str(Path(__file__).resolve().parent.parent)
    trees = {"other": str(Path(other).resolve()), "this": here}
    got = {t: [] for t in trees}
    for k in range(rounds):
        for t in (list(trees) if k % 2 == 0 else list(trees)[::-1]):
            env = dict(os.environ, PYTHONPATH=trees[t])
            cmd = [sys.executable, __file__, what, "--ratios-json"] + (["--quick"] if quick else [])
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout.splitlines()
            print(f"--- round {k + 1}, {t} ({trees[t]}) ---")
            print("\n".join(out[:-1]), flush=True)
            got[t].append(json.loads(out[-1]))
    print("\nrays/s relative to the square grid, median over rounds (CPU-time ratio in brackets):")
    for threads in got["this"][0]:
        for name in got["this"][0][threads]:
            cells = []
            for t in trees:
                wall = np_median([g[threads][name][0] for g in got[t]])
                cpu = np_median([g[threads][name][1] for g in got[t]])
                cells.append(f"{t} x{wall:.3f} (x{cpu:.3f})")
            print(f"  {threads} thread(s) {name:24s} " + ", ".join(cells))


def rate(renderer: Renderer, rays: int, threads: int | None, seed: int = 1) -> tuple[float, float, float]:
    """(M rays/s wall, seconds wall, CPU ns per ray) for one white render."""
    t, c = time.perf_counter(), time.process_time()
    renderer.render(WhiteScene(), rays=rays, seed=seed, threads=threads)
    dt, dc = time.perf_counter() - t, time.process_time() - c
    return rays / dt / 1e6, dt, dc / rays * 1e9


def compare_boundaries(rays: int, repeats: int) -> None:
    """The default camera's rays/s with sag-intersection and with grid lens boundaries (numba, one thread
    and all cores), runs interleaved so that the machine's load hits both alike; medians and their ratio."""
    cfg, errors = camera()
    models = ("sag-intersection", "grid")
    renderers = {b: Renderer(dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, boundaries=b)), errors,
                             engine="numba") for b in models}
    for r in renderers.values():
        r.render(WhiteScene(), rays=200_000, seed=0)  # compile / warm up
    cores = os.cpu_count() or 1
    print(f"lens boundaries, numba, {rays:,} rays a run, {repeats} interleaved runs each (median; CPU ns/ray "
          "single-threaded is the load-independent figure)")
    for threads in sorted({1, cores}):
        got = {b: [] for b in models}
        for k in range(repeats):
            for b in (models if k % 2 == 0 else models[::-1]):
                got[b].append(rate(renderers[b], rays, threads, seed=10 + k))
        med = {b: (float(np_median([g[0] for g in got[b]])), float(np_median([g[2] for g in got[b]]))) for b in models}
        for b in models:
            print(f"  {b:16s} {threads} thread(s): {med[b][0]:6.2f} M rays/s, {med[b][1]:6.1f} CPU ns/ray")
        print(f"  sag / grid: rays/s x{med['sag-intersection'][0] / med['grid'][0]:.2f}, "
              f"CPU per ray x{med['sag-intersection'][1] / med['grid'][1]:.2f}")


def reference_frames(rays: int = 400_000) -> dict[str, np.ndarray]:
    """Seeded frames (numba, one thread) of every array kind of ARRAYS, both samplers: what a kernel change
    must leave bit-identical (the shipped models were rendered with today's)."""
    out = {}
    for name, spec in ARRAYS.items():
        for sampler, seeds in (("sobol", (1, 7)), ("random", (3,))):
            r = Renderer(*camera(*spec), engine="numba", sampler=sampler)
            for seed in seeds:
                key = f"{name} {sampler} {seed}".replace(" ", "_").replace("µ", "u")
                out[key] = r.render(WhiteScene(), rays=rays, seed=seed, threads=1).photons
    return out


# every combination of the tracer's options the test suite used before #40 (each was a kernel of its own; a
# global rotation and a texture are run-time switches since): (per-lens tilts, a global MLA rotation, a
# textured scene, lens boundaries, array)
VARIANTS = (
    (False, False, False, "grid", "square"), (False, True, False, "grid", "square"),
    (False, False, True, "grid", "square"), (True, True, False, "grid", "square"),
    (True, True, True, "grid", "square"), (False, True, True, "grid", "square"), (True, False, False, "grid", "square"),
    (False, False, False, "sag-intersection", "square"), (True, True, False, "sag-intersection", "square"),
    (True, False, False, "sag-intersection", "square"), (False, False, False, "grid", "hex"),
    (False, False, False, "sag-intersection", "hex"), (True, True, False, "grid", "hex"),
    (True, True, False, "sag-intersection", "hex"), (False, False, False, "grid", "hex-circle"),
    (True, True, False, "grid", "hex-circle"), (True, True, False, "grid", "circle"),
)


def variant_camera(tilted: bool, rotated: bool, boundaries: str, mla: str):
    """A 6 x 6-lens camera of one tracer variant, with random defects (tilts among them where `tilted`)."""
    from mlaqc.optics.config import config_from_dict

    packing = "hex" if mla.startswith("hex") else "square"
    lenses = {"count_w": 6, "count_h": 6, "boundaries": boundaries, "packing": packing}
    if mla.endswith("circle"):
        lenses.update(aperture="circle", aperture_diameter_um=90.0)
    cfg = config_from_dict({"mla": lenses, "sensor": {"width_px": 160, "height_px": 160}})
    types = ("pitch", "decenter", "radius", "thickness") + (("tilt",) if tilted else ())
    errors = random_defects(6, 6, 4, seed=5, packing=packing, types=types)
    if tilted and not errors.has_tilt():
        errors = errors.with_lens(2, 3, tilt_x_deg=2.0)
    if rotated:
        errors = errors.with_globals(mla_rotation_deg=0.4)
    return cfg, errors


def variant_frames(rays: int = 200_000) -> dict[str, np.ndarray]:
    """Seeded frames (numba, one thread) of every tracer variant (VARIANTS), both samplers."""
    from mlaqc.optics.scene import TextureScene

    texture = TextureScene(np.random.default_rng(0).uniform(0.2, 1.0, (24, 24)))
    out = {}
    for tilted, rotated, textured, boundaries, mla in VARIANTS:
        cfg, errors = variant_camera(tilted, rotated, boundaries, mla)
        for sampler in ("sobol", "random"):
            r = Renderer(cfg, errors, engine="numba", sampler=sampler)
            key = f"variant {mla} {boundaries} tilt{int(tilted)} rot{int(rotated)} tex{int(textured)} {sampler}"
            out[key.replace(" ", "_")] = r.render(texture if textured else WhiteScene(), rays=rays, seed=2,
                                                  threads=1).photons
    return out


def images(mode: str, path: str) -> int:
    """--images save PATH: write the reference frames; --images check PATH: compare, frame by frame, bit
    for bit; exit status 1 if any differs."""
    frames = {**reference_frames(), **variant_frames()}
    if mode == "save":
        np.savez_compressed(path, **frames)
        print(f"saved {len(frames)} frames to {path}")
        return 0
    ref = np.load(path)
    bad = [k for k, v in frames.items() if k not in ref or not np.array_equal(ref[k], v)]
    for k in frames:
        print(f"  {'DIFFERS' if k in bad else 'same   '} {k}")
    print("all frames bit-identical" if not bad else f"{len(bad)} of {len(frames)} frames differ")
    return 1 if bad else 0


def np_median(values: list[float]) -> float:
    v = sorted(values)
    n = len(v)
    return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


def _status_mib(field: str) -> float:
    """A memory figure of this process from /proc/self/status (Linux), in MiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def memory_child(rays: int) -> None:
    """Run in a fresh process: one render of `rays` rays on all cores; print the resident set before it and
    its peak during it (the peak is reset after the warm-up, which loads LLVM and the compiled kernels)."""
    cfg, errors = camera()
    r = Renderer(cfg, errors)
    r.render(WhiteScene(), rays=1000, seed=0)
    base = _status_mib("VmRSS")
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # reset VmHWM, the peak resident set size
    except OSError:
        pass
    mrs, dt, _ = rate(r, rays, None)
    peak = _status_mib("VmHWM")
    print(json.dumps({"base": base, "peak": peak, "mrs": mrs, "seconds": dt}))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer rays everywhere")
    ap.add_argument("--huge", action="store_true", help="add 10^9 rays to the memory table")
    ap.add_argument("--memory-child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--ratios-json", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--against", metavar="TREE", help="with --arrays or --kernels: also that checkout's mlaqc, "
                    "taking turns")
    ap.add_argument("--rounds", type=int, help="with --against: child processes per tree (default 2)")
    ap.add_argument("--boundaries", action="store_true", help="only sag-intersection vs grid boundaries' rays/s")
    ap.add_argument("--arrays", action="store_true", help="only rays/s of square / hex, grid / sag, circles")
    ap.add_argument("--kernels", action="store_true", help="only the tracer's batches of every array kind, paired")
    ap.add_argument("--images", nargs=2, metavar=("save|check", "PATH"),
                    help="seeded frames of every array kind: save them, or check these are bit-identical")
    ap.add_argument("--packing", choices=("square", "hex"), default="square", help="the main tables' array packing")
    ap.add_argument("--aperture", choices=("cell", "circle"), default="cell", help="the main tables' lens aperture")
    args = ap.parse_args()
    if args.memory_child:
        memory_child(args.memory_child)
        return 0
    if args.images:
        if args.images[0] not in ("save", "check"):
            ap.error("--images takes 'save' or 'check' and a path")
        return images(*args.images)
    if args.boundaries:
        compare_boundaries(10_000_000 if args.quick else 40_000_000, 3 if args.quick else 5)
        return 0
    if (args.arrays or args.kernels) and args.against:
        compare_trees(args.against, args.quick, "--kernels" if args.kernels else "--arrays", args.rounds or 2)
        return 0
    if args.kernels:
        ratios = compare_kernels(500_000 if args.quick else 1_000_000, 20 if args.quick else 60)
        if args.ratios_json:
            print(json.dumps(ratios))
        return 0
    if args.arrays:
        ratios = compare_arrays(5_000_000 if args.quick else 20_000_000, 5 if args.quick else 11)
        if args.ratios_json:
            print(json.dumps(ratios))
        return 0
    cfg, errors = camera(args.packing, args.aperture)
    cores = os.cpu_count() or 1
    print(f"machine: {cores} cores, load average {os.getloadavg()[0]:.1f}; camera: Table 1 optics "
          f"({cfg.mla.count_w}x{cfg.mla.count_h} {cfg.mla.packing} lenses, aperture {cfg.mla.aperture}, 2048x2048 px), "
          f"200 defective lenses, Fresnel on, {cfg.mla.boundaries} lens boundaries")
    print(f"{'engine':8s} {'threads':>7s} {'rays':>12s} {'M rays/s':>9s} {'seconds':>8s} {'CPU ns/ray':>11s}")
    rays = 10_000_000 if args.quick else 40_000_000
    for engine in ("numba", "numpy"):
        r = Renderer(cfg, errors, engine=engine)
        r.render(WhiteScene(), rays=200_000, seed=0)  # compile / warm up
        n = rays if engine == "numba" else rays // 8
        for threads in sorted({1, cores}):
            mrs, dt, ns = rate(r, n, threads)
            print(f"{engine:8s} {threads:7d} {n:12,d} {mrs:9.2f} {dt:8.2f} {ns:11.1f}")

    print("\npeak memory vs rays (numba, all cores, each in a fresh process; the image itself is 32 MiB):")
    sizes = [10 ** 6, 10 ** 7] + ([] if args.quick else [10 ** 8]) + ([10 ** 9] if args.huge else [])
    for n in sizes:
        out = subprocess.run([sys.executable, __file__, "--memory-child", str(n)], capture_output=True, text=True,
                             check=True).stdout
        m = json.loads(out.strip().splitlines()[-1])
        print(f"  {n:>14,d} rays: peak RSS {m['peak']:6.0f} MiB = {m['peak'] - m['base']:5.0f} MiB above the loaded "
              f"process ({m['base']:.0f} MiB: interpreter, NumPy, LLVM, kernels); {m['mrs']:6.2f} M rays/s")

    r = Renderer(cfg, errors)
    rpp = 10 if args.quick else 100
    t = time.perf_counter()
    res = r.render(WhiteScene(), rays_per_pixel=rpp, seed=2)
    dt = time.perf_counter() - t
    print(f"\nfull 2048x2048 white image at {rpp} rays/pixel: {res.rays_traced:,} rays in {dt:.1f} s "
          f"({res.rays_traced / dt / 1e6:.2f} M rays/s), {100 * res.rays_landed / res.rays_traced:.1f} % landed")
    print(f"process max RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
