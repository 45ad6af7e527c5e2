"""Signature-table benchmark: how long the inverse model's table (every error type x magnitude, rendered
by the tracer on a 9 x 9-lens patch) takes to build for a camera, and to load once cached.

    python bench/signatures.py         # about a minute on 2 cores
"""

from __future__ import annotations

import sys
import time

from mlaqc.models.signatures import KINDS, PATCH, build_signatures, signature_table
from mlaqc.optics.config import default_config


def main() -> int:
    cfg = default_config()
    build_signatures(cfg, kinds=KINDS[:1], rays_per_pixel=1)  # compile the tracer first
    renders = 1 + sum(len(k.magnitudes) for k in KINDS)
    t = time.perf_counter()
    table = build_signatures(cfg)
    build = time.perf_counter() - t
    t = time.perf_counter()
    cached = signature_table(cfg)  # the shipped/cached table for the same optics
    load = time.perf_counter() - t
    drift = {k: abs(table.features[k] - cached.features[k]).max() / abs(cached.features[k]).max() for k in table.features}
    print(f"signature table, Table 1 optics: {len(KINDS)} error types, {renders} renders of a {PATCH}x{PATCH}-lens "
          f"patch at 400 rays/pixel, plus the patch's reference model")
    print(f"  build:                {build:8.2f} s")
    print(f"  load (package/cache): {load * 1e3:8.2f} ms   (key {cached.key}; cached in $MLAQC_CACHE or ~/.cache/mlaqc "
          f"after the first build for new optics)")
    print("  fresh build vs the loaded table, largest difference / largest feature, per type: "
          + ", ".join(f"{k} {v:.2f}" for k, v in drift.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
