"""The process' shared pool (mlaqc.parallel): results in order, the first exception first, work nested
inside the pool's own threads run where it is (no deadlock), one pool per process."""

from __future__ import annotations

import threading

import pytest

from mlaqc import parallel


def test_thread_map_keeps_order_and_uses_the_pool():
    names = set()

    def square(x: int) -> int:
        names.add(threading.current_thread().name)
        return x * x

    assert parallel.thread_map(square, range(50)) == [x * x for x in range(50)]
    if parallel.cores() > 1:
        assert all(n.startswith(parallel.THREAD_PREFIX) for n in names)
    assert parallel.thread_map(square, []) == []


def test_the_first_items_exception_is_raised():
    def fail(x: int) -> int:
        if x in (3, 7):
            raise ValueError(f"item {x}")
        return x

    with pytest.raises(ValueError, match="item 3"):
        parallel.thread_map(fail, range(10))


def test_nested_maps_inside_the_pool_do_not_deadlock():
    """More outer items than threads, each mapping inner items: every outer call runs its inner map in
    its own thread (a pool waiting on itself would hang here)."""
    outer = 4 * parallel.cores()
    done = threading.Event()
    result: list = []

    def inner_sum(k: int) -> int:
        return sum(parallel.thread_map(lambda j: j * k, range(8)))

    def run() -> None:
        result.extend(parallel.thread_map(inner_sum, range(outer)))
        done.set()

    threading.Thread(target=run, daemon=True).start()
    assert done.wait(30), "nested thread_map deadlocked"
    assert result == [28 * k for k in range(outer)]


def test_run_parts_runs_every_part_once_at_any_worker_count():
    for workers in (1, 2, parallel.cores(), parallel.cores() + 3):
        seen: list[int] = []
        lock = threading.Lock()

        def note(p: int) -> None:
            with lock:
                seen.append(p)

        parallel.run_parts(note, list(range(13)), workers)
        assert sorted(seen) == list(range(13)), workers


def test_one_pool_per_process():
    assert parallel.pool() is parallel.pool()
