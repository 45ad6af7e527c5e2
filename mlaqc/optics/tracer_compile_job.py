"""The background compile itself (`python -m mlaqc.optics.tracer_compile_job PID`, started by
tracer_background.start_if_needed): after the command that started it, at the idle priority, compile every
tracer variant not in Numba's cache, then stamp them all compiled. Apart from tracer_background so that
the renderer, which starts it, does not import the variants, which make renderers.
"""

from __future__ import annotations

import os
import sys

from mlaqc.optics.tracer_background import ENV_SWITCH, lock_path, mark_all_compiled

# the job waits for the command that started it to end, this long at most (a hyperthread shared with a
# compile slowed the demo 2.5x even at idle priority)
WAIT_FOR_STARTER_S = 60.0


def _order(variant) -> tuple:
    """The shipped fixtures' variants first (sag-intersection and circle apertures, untilted; the install's,
    where it could not compile them), then the rest."""
    return (variant.lenses == "grid", variant.tilted and variant.packing == "hex", variant.tilted, variant.lenses)


def _lowest_priority() -> None:
    """CPU only when nothing else wants it (Linux's idle class; else nice 19), for this process and the
    compiling processes it starts (they inherit it): the command that started it runs at full speed."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        try:
            os.nice(19)
        except OSError:
            pass


def _after(pid: int | None, limit_s: float = WAIT_FOR_STARTER_S) -> None:
    """Wait until process `pid` (the command that started the job) has ended, at most `limit_s`: a short
    command (the demo, a simulate) runs with the machine to itself; a long one (the app) not for ever."""
    import time

    end = time.monotonic() + limit_s
    while pid and time.monotonic() < end:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        except PermissionError:
            pass
        time.sleep(0.2)


def main(argv: list[str] | None = None) -> int:
    """The background job: after the command that started it, compile every variant not in Numba's cache,
    one process per core at idle priority, then write the stamp; exits at once if another holds the lock."""
    import fcntl
    import time

    args = sys.argv[1:] if argv is None else argv

    os.environ[ENV_SWITCH] = "0"
    path = lock_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = open(path, "a")  # held until this process ends
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return 0
    _lowest_priority()
    _after(int(args[0]) if args and args[0].isdigit() else None)
    from mlaqc.optics.tracer_variants import VARIANTS, compile_all, is_ready

    start = time.strftime("%Y-%m-%d %H:%M:%S")
    missing = tuple(v for v in sorted(VARIANTS, key=_order) if not is_ready(v))
    print(f"{start} mlaqc {os.getpid()}: compiling {len(missing)} tracer variant(s)", flush=True)
    failed = [v for v, _, error in compile_all(missing, log=lambda text: print(text, flush=True)) if error]
    if not failed:
        mark_all_compiled()
    print(f"{time.strftime('%Y-%m-%d %H:%M:%S')} done" + (f"; failed: {len(failed)}" if failed else ""), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
