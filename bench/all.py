"""Every performance figure of the README in one run: tracer, inspection, calibration accuracy,
scaling, signature table — each script in turn, its output as it comes.

    python bench/all.py            # about 10 minutes on 2 cores (first run renders and caches frames)
    python bench/all.py --quick    # the shorter variants where a script has one
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
SCRIPTS = (("trace.py", True), ("inspection.py", False), ("calibrate.py", False), ("scaling.py", False),
           ("signatures.py", False), ("robustness.py", True))


def main() -> int:
    quick = "--quick" in sys.argv[1:]
    failed = []
    for name, has_quick in SCRIPTS:
        print(f"\n=== bench/{name} ===", flush=True)
        t = time.perf_counter()
        code = subprocess.call([sys.executable, str(HERE / name), *(["--quick"] if quick and has_quick else [])])
        print(f"--- {name}: exit {code}, {time.perf_counter() - t:.0f} s", flush=True)
        if code:
            failed.append(name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
