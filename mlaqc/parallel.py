"""The process' worker threads: one pool of a thread per core, shared by every stage that splits its work
over the cores (compiled kernels and NumPy release the GIL, so do file reads).

One pool, kept for the process: starting threads anew for every frame cost a few milliseconds, and
separate pools per stage put more threads than cores on the machine when stages overlap. Per process
id, so a forked child (Dask, multiprocessing) starts its own. Work submitted from one of the pool's own
threads runs in that thread: a pool whose threads all wait on work queued behind them would deadlock.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

THREAD_PREFIX = "mlaqc-pool"
_LOCK = threading.Lock()
_POOLS: dict[int, ThreadPoolExecutor] = {}


def cores() -> int:
    """The number of cores this process may use."""
    return os.cpu_count() or 1


def pool() -> ThreadPoolExecutor:
    """The process' pool: a thread per core, created on first use."""
    pid = os.getpid()
    with _LOCK:
        p = _POOLS.get(pid)
        if p is None:
            p = _POOLS[pid] = ThreadPoolExecutor(cores(), thread_name_prefix=THREAD_PREFIX)
    return p


def in_pool() -> bool:
    """True in one of the pool's own threads."""
    return threading.current_thread().name.startswith(THREAD_PREFIX)


def thread_map(fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """[fn(item) for item in items], on the pool when there are several items and cores; results in
    order, the first item's exception raised first (as a loop would)."""
    items = list(items)
    if len(items) <= 1 or cores() == 1 or in_pool():
        return [fn(item) for item in items]
    return list(pool().map(fn, items))


def run_parts(fn: Callable[[Any], Any], parts: list, workers: int) -> None:
    """fn(part) for every part, at most `workers` at a time: on the process' pool when `workers` asks for
    every core, on a pool of its own when fewer, in this thread when one."""
    if workers <= 1 or len(parts) <= 1 or in_pool():
        for part in parts:
            fn(part)
    elif workers >= cores():
        thread_map(fn, parts)
    else:
        with ThreadPoolExecutor(workers) as own:
            list(own.map(fn, parts))
