"""Rendering on Dask (issue #13): a 10^9-ray Table 1 white render locally and on 1 and 2 local worker
processes, the same image bit for bit, and what a bigger cluster would take.

    python bench/dask_render.py                  # 10^9 rays (about 2 minutes on 2 idle cores)
    python bench/dask_render.py --rays 2e8       # quicker
    python bench/dask_render.py --scheduler tcp://host:8786   # also on a real cluster

The issue's bar: Dask on the same machine (2 workers) within 15 % of the local run. The cluster figure
per worker (M rays/s of one single-threaded worker) is what a node count multiplies; the client's share
(adding each chunk's partial image into the frame) is measured too, since it does not shrink with nodes.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mlaqc.cluster import connect
from mlaqc.optics.config import default_config
from mlaqc.optics.distributed import render_on_cluster
from mlaqc.optics.errormap import random_defects
from mlaqc.optics.render import Renderer, add_chunk
from mlaqc.optics.scene import WhiteScene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rays", type=float, default=1e9)
    ap.add_argument("--scheduler", help="a running Dask scheduler to measure as well")
    args = ap.parse_args()
    rays = int(args.rays)
    cfg = default_config()
    r = Renderer(cfg, random_defects(102, 102, 200, seed=3))
    r.render(WhiteScene(), rays=100_000, seed=0)  # compile
    t = time.perf_counter()
    local = r.render(WhiteScene(), rays=rays, seed=1)
    t_local = time.perf_counter() - t
    print(f"local, {rays:.0e} rays: {t_local:.1f} s ({rays / t_local / 1e6:.1f} M rays/s)", flush=True)
    plan = r.plan(WhiteScene(), rays, None, 1)
    chunks = [r.trace_chunk(WhiteScene(), c, plan.keys) for c in plan.chunks()[:8]]
    image = np.zeros_like(local.photons)
    t = time.perf_counter()
    for part in chunks:
        add_chunk(image, part)
    per_chunk = (time.perf_counter() - t) / len(chunks)
    print(f"client's sum: {1e3 * per_chunk:.2f} ms per chunk x {len(plan.chunks())} chunks "
          f"({per_chunk * len(plan.chunks()):.2f} s in all)")
    addresses = ["local:1", "local:2"] + ([args.scheduler] if args.scheduler else [])
    for address in addresses:
        with connect(address) as client:
            workers = len(client.nthreads())
            render_on_cluster(client, r, WhiteScene(), rays=1_000_000, seed=0)  # workers compile / warm up
            t = time.perf_counter()
            remote = render_on_cluster(client, r, WhiteScene(), rays=rays, seed=1)
            dt = time.perf_counter() - t
        same = np.array_equal(remote.photons, local.photons)
        per_worker = rays / dt / 1e6 / workers
        print(f"{address}: {workers} workers, {dt:.1f} s ({rays / dt / 1e6:.1f} M rays/s, {per_worker:.1f} per worker), "
              f"{dt / t_local:.2f} x the local time; image {'bit-identical' if same else 'DIFFERENT'}", flush=True)
    print(f"\na node of 2 cores gives about {2 * per_worker:.0f} M rays/s; 16 such nodes about {32 * per_worker:.0f} M rays/s "
          f"if the client keeps up: it adds one chunk in {1e3 * per_chunk:.1f} ms, i.e. up to "
          f"{plan.total / len(plan.chunks()) / per_chunk / 1e6:.0f} M rays/s")


if __name__ == "__main__":
    main()
