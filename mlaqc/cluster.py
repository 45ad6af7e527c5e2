"""Running a command's work on a Dask cluster: what every command with `--scheduler` shares.

    with connect(scheduler_address(args.scheduler)) as client:   # one sentence (DeviceError) if unreachable
        shared = share(client, spec, "inspect-spec")              # shipped once, recomputed if lost
        futures = {client.submit(work, shared, item, retries=TASK_RETRIES): item for item in items}
        for item, value in follow(futures, "inspecting"):          # a progress bar follows the cluster
            ...                                                     # the client alone writes results

- The address comes from `--scheduler ADDRESS`, else the environment variable `MLAQC_SCHEDULER`, else
  there is none and the command runs on this machine as it always did. `tcp://host:8786` (or `host:8786`)
  names a running scheduler; `local` starts a LocalCluster with one single-threaded worker process per
  core on this machine for the command's duration, `local:N` one with N workers.
- Exit status: a malformed address (`local:x`, an unknown scheme) is bad input, `InputError` (2); a
  scheduler that cannot be reached within `CONNECT_TIMEOUT_S`, answers but is no Dask scheduler, has no
  workers, is lost mid-run, or whose workers keep dying on a task is a failed service, `DeviceError`
  (3) — the status the CLI already gives a camera or stage that failed. Each is one sentence.
- Workers must be able to import `mlaqc` (the same version) and see the files a task names by path.
  Workers of `dask worker` set MALLOC_TRIM_THRESHOLD_ (see NO_MALLOC_TRIM); setting that key to null in
  the workers' Dask config saves about a tenth of the work.
- A worker lost mid-run costs nothing: the scheduler runs its tasks again elsewhere (up to Dask's
  `distributed.scheduler.allowed-failures` times, 3 by default); `TASK_RETRIES` also retries a task
  that raised. Tasks should return results rather than write files, so that a task run twice cannot
  write twice.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import gc
import logging
import os
import sys
import uuid
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any, TextIO, TypeVar

from mlaqc.errors import DeviceError, InputError
from mlaqc.progress import ProgressBar

if TYPE_CHECKING:  # importing distributed costs 0.5 s: only commands that get an address pay it
    from distributed import Client, Future

ENV_VAR = "MLAQC_SCHEDULER"
CONNECT_TIMEOUT_S = 10.0  # to reach the scheduler, and again for its first worker to be there
TASK_RETRIES = 2  # extra runs of a task that raised (a worker that died is handled by the scheduler)
# Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536, which turns off glibc's adaptive mmap
# threshold: every large array is then mapped afresh and faulted in page by page (0.12 s of system time
# per 2048^2 frame inspected and reported, a tenth of the work). `local:N` workers go without it.
NO_MALLOC_TRIM = "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"

T = TypeVar("T")


def add_scheduler_option(p: argparse.ArgumentParser) -> None:
    """Add `--scheduler ADDRESS` to a command's parser."""
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help=f"run the work on a Dask cluster: a scheduler address (tcp://host:8786), or 'local' / "
                        f"'local:N' for N worker processes on this machine (default: ${ENV_VAR}, else this "
                        f"machine without Dask)")


def scheduler_address(arg: str | None) -> str | None:
    """The scheduler to use: `arg` (the option), else $MLAQC_SCHEDULER, else None (run here, no Dask)."""
    for value in (arg, os.environ.get(ENV_VAR)):
        if value is not None and value.strip():
            return value.strip()
    return None


def local_workers(address: str) -> int | None:
    """N for `local:N` (the core count for `local`); None for any other address (InputError if malformed)."""
    if address != "local" and not address.startswith("local:"):
        return None
    n = address.partition(":")[2]
    if not n:
        return os.cpu_count() or 1
    if not n.isdigit() or int(n) < 1:
        raise InputError(f"scheduler address {address!r}: 'local:N' needs a worker count N of at least 1")
    return int(n)


@contextlib.contextmanager
def connect(address: str, *, timeout_s: float | None = None, quiet: bool = False,
            stream: TextIO | None = None) -> Iterator[Client]:
    """A `distributed.Client` on `address` (a scheduler, or `local`/`local:N`), closed on exit.

    Waits up to `timeout_s` (default CONNECT_TIMEOUT_S) for the scheduler and again for a worker; says
    on `stream` (stderr) where the work runs and the dashboard link unless `quiet`. A cluster that fails
    — here or later in the `with` body (lost connection, cancelled futures, workers dying on a task) —
    becomes one sentence as a DeviceError; a malformed address an InputError."""
    timeout = CONNECT_TIMEOUT_S if timeout_s is None else timeout_s
    stream = stream or sys.stderr
    try:
        import asyncio

        import dask
        from distributed import Client, KilledWorker, LocalCluster
        from distributed.comm.core import CommClosedError
    except ImportError as exc:
        raise InputError(f"running on a Dask cluster needs the 'distributed' package ({exc}); "
                         "install it with: python3 -m pip install 'dask[distributed]'") from None
    n_local = local_workers(address)
    with contextlib.ExitStack() as stack:
        # every failure below becomes one sentence: Dask's own log lines about it would only repeat it
        stack.enter_context(_quiet_logger("distributed"))
        if n_local is not None:
            try:
                with dask.config.set({NO_MALLOC_TRIM: None}):
                    target: Any = stack.enter_context(LocalCluster(
                        n_workers=n_local, threads_per_worker=1, processes=True, dashboard_address=":0",
                        silence_logs=logging.ERROR))
            except Exception as exc:
                raise DeviceError(f"cannot start a local Dask cluster ({n_local} worker processes; "
                                  f"{_reason(exc)})") from exc
        else:
            target = check_address(address)
        client = failure = None
        try:
            client = Client(target, timeout=timeout, set_as_default=False)
        except (OSError, TimeoutError):
            failure = DeviceError(f"cannot reach the Dask scheduler at {address} within {timeout:g} s "
                                  "(is it running, and is the address right?)")
        except Exception as exc:  # something answered, but not as a scheduler (garbage, another protocol)
            failure = DeviceError(f"the service at {address} did not answer as a Dask scheduler ({_reason(exc)})")
        if failure is not None:
            # the half-built Client sits in a reference cycle: finalized by some later collection, its
            # close() can run inside the next Dask start in this thread and hang it (the loop runner's
            # lock); finalize it now, outside the except block that still referenced it
            gc.collect()
            raise failure
        stack.enter_context(client)
        try:
            client.wait_for_workers(1, timeout=timeout)
        except (TimeoutError, OSError):
            raise DeviceError(f"the Dask scheduler at {address} has no workers (none joined within "
                              f"{timeout:g} s)") from None
        if not quiet:
            _say_where(client, address, stream)
        try:
            yield client
        except KilledWorker as exc:
            raise _killed(exc) from exc
        except (CommClosedError, concurrent.futures.CancelledError, asyncio.CancelledError) as exc:
            why = getattr(exc, "reason", None) or _reason(exc)  # FutureCancelledError: scheduler-connection-lost
            raise DeviceError(f"lost the Dask cluster at {address} mid-run ({why}); what was written so far is "
                              "complete") from exc


def check_address(address: str) -> str:
    """`address` if it is `local`, `local:N` or has a scheme Dask knows (tcp:// when it has none); else
    InputError. Cheap: call it before any work so that a typo is said at once."""
    if local_workers(address) is not None:
        return address
    from distributed.comm.addressing import parse_address
    from distributed.comm.registry import get_backend

    try:
        get_backend(parse_address(address)[0])
    except (ValueError, TypeError) as exc:
        raise InputError(f"scheduler address {address!r} is not a Dask address ({exc})") from None
    return address


def share(client: Client, obj: Any, name: str) -> Future:
    """A future holding `obj` that tasks take as an argument: sent once with the graph, fetched once per
    worker, and — unlike scattered data — computed again from the graph if the workers holding it die."""
    return client.submit(_same, obj, key=f"{name}-{uuid.uuid4().hex[:12]}", pure=False)


def _same(obj: T) -> T:
    return obj


def follow(futures: Mapping[Future, T], label: str, *, progress: bool | None = None,
           stream: TextIO | None = None) -> Iterator[tuple[T, Any]]:
    """Yield (tag, result) for each future of {future: tag} as it completes, with a ProgressBar of
    completed over all on `stream` (stderr; `progress` None: only on a terminal, False: never, True:
    always); each future is released once its result has been yielded.

    A task's own exception is raised as is; workers dying on a task over and over (Dask's KilledWorker)
    becomes a DeviceError. Print lines meanwhile with `echo`, which keeps them off the bar."""
    from distributed import KilledWorker, as_completed

    bar = ProgressBar(label, stream=stream or sys.stderr, enabled=progress)
    total, done = len(futures), 0
    if not total:
        return
    bar(0, total)
    try:
        first = next(iter(futures))
        for fut in as_completed(list(futures), loop=first.client.loop):
            try:
                value = fut.result()
            except KilledWorker as exc:
                raise _killed(exc) from exc
            done += 1
            yield futures[fut], value
            fut.release()
            bar(done, total)
    finally:
        bar.close()


def echo(line: str, stream: TextIO | None = None) -> None:
    """Print a line on stderr above the progress bar `follow` may be drawing there."""
    stream = stream or sys.stderr
    if stream.isatty():
        stream.write("\r\x1b[K")  # clear the bar's line; the bar redraws below on its next update
    print(line, file=stream, flush=True)


@contextlib.contextmanager
def _quiet_logger(name: str) -> Iterator[None]:
    """Only CRITICAL records from logger `name` and its children (Dask sets some children's levels) inside."""
    names = [n for n in list(logging.root.manager.loggerDict) if n == name or n.startswith(name + ".")]
    loggers = [logging.getLogger(n) for n in {name, *names}]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def _say_where(client: Client, address: str, stream: TextIO) -> None:
    threads = client.nthreads()
    info = client.scheduler_info()
    n, t = len(threads), sum(threads.values())
    where = f"Dask: {n} worker{'s' * (n != 1)} ({t} thread{'s' * (t != 1)}) at {info.get('address', address)}"
    if "dashboard" in info.get("services", {}):
        where += f", dashboard {client.dashboard_link}"
    print(where, file=stream, flush=True)


def unseen(host: str, path: str) -> DeviceError:
    """The error when a worker on `host` cannot see a file the client reads at `path` (absolute)."""
    return DeviceError(f"the Dask worker on {host} cannot see {path!r}: workers read raws by path, so they need "
                       "the same files at the same paths (a shared filesystem)")


def _killed(exc: BaseException) -> DeviceError:
    """One sentence for Dask's KilledWorker: every worker that ran a task died while running it."""
    task, tries = getattr(exc, "task", "?"), getattr(exc, "allowed_failures", None)
    times = f"{tries + 1} " if isinstance(tries, int) else ""
    return DeviceError(f"{times}Dask workers in turn died while running task {task!r}: it runs out of memory or "
                       "crashes them (their logs say which)")


def _reason(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    text = text if len(text) <= 160 else text[:157] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


