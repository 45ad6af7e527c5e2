"""Waiting in tests: poll a condition until a deadline, never a fixed sleep.

Simulators, servers and worker threads change their state on their own threads, often a moment after the
driver under test has already reacted (a pty hangs up before its simulator records it). A test that checks
such state waits for it with `wait_until`, which returns as soon as the condition holds, so it costs nothing
when the state is already there and fails only when it never comes.
"""

from __future__ import annotations

import time
from collections.abc import Callable

DEFAULT_TIMEOUT_S = 5.0
POLL_S = 0.005


def wait_until(condition: Callable[[], object], timeout_s: float = DEFAULT_TIMEOUT_S, poll_s: float = POLL_S) -> bool:
    """True as soon as `condition()` is truthy; False if it is still falsy at the deadline (checked once more then)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return bool(condition())
        time.sleep(min(poll_s, remaining))
    return True


def stays(condition: Callable[[], object], for_s: float, poll_s: float = POLL_S) -> bool:
    """True if `condition()` holds throughout the next `for_s` seconds; False as soon as it does not."""
    return not wait_until(lambda: not condition(), for_s, poll_s)
