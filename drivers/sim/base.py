"""Shared parts of the protocol simulators: timed output with latency, fault injection, motion, serving.

A simulator is a protocol state machine (`feed` bytes in, `_emit` bytes out, `tick` for timed events)
driven by a PtyServer thread. Every public method is thread-safe (one re-entrant lock), so a test can
inject faults while a driver talks to the simulator.

Fault injection, common to every simulator:
- `set_latency(latency_s)`: every later output is delayed (slow replies);
- `drop_replies(count=None)`: the next `count` replies are never sent; None = the link goes silent
  (no reply at all, status reports and unsolicited messages included) until `clear_faults()`;
- `garble_replies(count=1)`: a line of noise precedes each of the next `count` replies (tolerable);
- `corrupt_replies(count=1)`: the next `count` replies are replaced by noise (a lost reply);
- `send_garbage(data)`: noise on the line right now;
- `disconnect()` now, or `disconnect_mid_move(at_fraction)` during the next move: the pty hangs up;
- `clear_faults()`: disarm all of the above (latency back to its initial value).
Protocol simulators add their own (error replies, alarms/faults mid-move).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

from .pty_server import PtyServer

log = logging.getLogger(__name__)

NOISE = b"\xfe\x01~#%garbled\x80\xff"


@dataclass
class Motion:
    """Straight-line motion at constant speed from `start` to `target` beginning at monotonic time `t0`."""

    start: tuple[float, ...]
    target: tuple[float, ...]
    t0: float
    speed: float

    @property
    def distance(self) -> float:
        """Path length in the units of start/target."""
        return math.dist(self.start, self.target)

    @property
    def duration_s(self) -> float:
        """How long the move takes."""
        return self.distance / self.speed if self.speed > 0 else 0.0

    @property
    def t_end(self) -> float:
        """Monotonic time at which the move ends."""
        return self.t0 + self.duration_s

    def fraction(self, now: float) -> float:
        """Share of the path covered at `now` (0..1)."""
        duration = self.duration_s
        return 1.0 if duration <= 0 else min(1.0, max(0.0, (now - self.t0) / duration))

    def position(self, now: float) -> tuple[float, ...]:
        """Interpolated position at `now`."""
        f = self.fraction(now)
        return tuple(s + (t - s) * f for s, t in zip(self.start, self.target))

    def time_at(self, fraction: float) -> float:
        """Monotonic time at which `fraction` of the path is covered."""
        return self.t0 + self.duration_s * min(1.0, max(0.0, fraction))


@dataclass
class MidMoveFault:
    """A fault armed for the next move: `kind` happens when `at_fraction` of the path is covered."""

    kind: str
    at_fraction: float
    code: object = None
    due: float | None = None
    owner: object = None


class SimDevice:
    """Base of the protocol simulators: output queue, fault switches, pty serving, waiting helpers."""

    name = "sim"

    def __init__(self, *, latency_s: float = 0.0) -> None:
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._initial_latency_s = latency_s
        self.latency_s = latency_s
        self._outbox: deque[tuple[float, bytes]] = deque()
        self._last_due = 0.0
        self.received_lines: list[str] = []
        self.received_bytes = bytearray()
        self._drop_all = False
        self._drop_count = 0
        self._garble_count = 0
        self._corrupt_count = 0
        self._hangup = False
        self._armed: list[MidMoveFault] = []
        self._active: list[MidMoveFault] = []
        self._server: PtyServer | None = None

    # ------------------------------------------------------------ serving

    def start(self) -> "SimDevice":
        """Serve this simulator on a new pty; its slave path is `self.path`."""
        with self._lock:
            if self._server is None:
                self._power_up(time.monotonic())
                self._server = PtyServer(self, name=self.name)
        return self

    @property
    def path(self) -> str:
        """The pty slave device to open as a serial port."""
        if self._server is None:
            raise RuntimeError(f"{self.name} simulator is not started")
        return self._server.path

    @property
    def hung_up(self) -> bool:
        """True once the simulated cable was pulled."""
        return self._server is not None and self._server.hung_up.is_set()

    def close(self) -> None:
        """Stop serving and close the pty; safe to call twice."""
        server, self._server = self._server, None
        if server is not None:
            server.close()

    def __enter__(self) -> "SimDevice":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _wake(self) -> None:
        """Let the server re-evaluate timers now (called after a change from another thread)."""
        server = self._server
        if server is not None:
            server.wake()

    # ------------------------------------------------------------ fault injection

    def set_latency(self, latency_s: float) -> None:
        """Delay every later output by `latency_s` (slow replies)."""
        with self._lock:
            self.latency_s = latency_s

    def drop_replies(self, count: int | None = None) -> None:
        """Never send the next `count` replies; None = total silence until clear_faults()."""
        with self._lock:
            if count is None:
                self._drop_all = True
            else:
                self._drop_count = count

    def garble_replies(self, count: int = 1) -> None:
        """Precede each of the next `count` replies with a line of noise."""
        with self._lock:
            self._garble_count = count

    def corrupt_replies(self, count: int = 1) -> None:
        """Replace the next `count` replies with noise."""
        with self._lock:
            self._corrupt_count = count

    def send_garbage(self, data: bytes = NOISE + b"\r\n") -> None:
        """Put noise on the line now."""
        with self._lock:
            self._queue(data, time.monotonic())
        self._wake()

    def disconnect(self) -> None:
        """Pull the cable now: the pty hangs up."""
        with self._lock:
            self._hangup = True
        self._wake()

    def disconnect_mid_move(self, at_fraction: float = 0.5) -> None:
        """Pull the cable when the next move has covered `at_fraction` of its path."""
        self._arm(MidMoveFault("disconnect", at_fraction))

    def clear_faults(self) -> None:
        """Disarm every fault; latency back to its initial value."""
        with self._lock:
            self.latency_s = self._initial_latency_s
            self._drop_all = False
            self._drop_count = self._garble_count = self._corrupt_count = 0
            self._armed.clear()
            self._active.clear()
            self._clear_protocol_faults()

    def _arm(self, fault: MidMoveFault) -> None:
        """Arm a fault for the next move."""
        if not 0.0 <= fault.at_fraction <= 1.0:
            raise ValueError(f"at_fraction {fault.at_fraction} is not within 0..1")
        with self._lock:
            self._armed.append(fault)

    def _clear_protocol_faults(self) -> None:
        """Subclasses disarm their own faults here."""

    # ------------------------------------------------------------ observation

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float = 2.0) -> bool:
        """Block until `predicate()` (evaluated under the lock) is true or `timeout_s` passes."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while not predicate():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._changed.wait(min(remaining, 0.05))
            return True

    def _notify(self) -> None:
        """Wake wait_for() callers (state changed); lock must be held."""
        self._changed.notify_all()

    # ------------------------------------------------------------ output

    def _emit(self, data: bytes, now: float, *, reply: bool = True) -> None:
        """Queue output, applying the drop/garble/corrupt switches; `reply` = answers a command."""
        if self._drop_all:
            return
        if reply and self._drop_count > 0:
            self._drop_count -= 1
            return
        if reply and self._garble_count > 0:
            self._garble_count -= 1
            self._queue(NOISE + b"\r\n", now)
        if reply and self._corrupt_count > 0:
            self._corrupt_count -= 1
            data = NOISE + b"\r\n"
        self._queue(data, now)

    def _queue(self, data: bytes, now: float) -> None:
        """Append to the outbox, due after the latency, never before earlier output."""
        due = max(now + self.latency_s, self._last_due)
        self._last_due = due
        self._outbox.append((due, data))

    # ------------------------------------------------------------ server interface

    def take_output(self, now: float) -> bytes:
        """Everything in the outbox that is due by `now`."""
        with self._lock:
            out = bytearray()
            while self._outbox and self._outbox[0][0] <= now:
                out.extend(self._outbox.popleft()[1])
            return bytes(out)

    def next_event(self, now: float) -> float | None:
        """Monotonic time of the next output or timed event, if any."""
        with self._lock:
            times = [t for t in (self._next_timer(now),) if t is not None]
            if self._outbox:
                times.append(self._outbox[0][0])
            times.extend(f.due for f in self._active if f.due is not None)
            return min(times) if times else None

    def hangup_requested(self) -> bool:
        """True when the simulated cable should be pulled."""
        with self._lock:
            return self._hangup

    def feed(self, data: bytes, now: float) -> None:
        """Bytes from the driver."""
        with self._lock:
            self.received_bytes.extend(data)
            self._advance(now)
            self._on_bytes(data, now)
            self._notify()

    def tick(self, now: float) -> None:
        """Advance timed behaviour to `now`."""
        with self._lock:
            self._advance(now)
            self._notify()

    def _activate_faults(self, motion: Motion, owner: object = None) -> None:
        """Bind the armed mid-move faults to a move that just started (`owner`: e.g. the axis)."""
        for fault in self._armed:
            fault.due = motion.time_at(fault.at_fraction)
            fault.owner = owner
            self._active.append(fault)
        self._armed.clear()

    def _due_faults(self, now: float) -> list[MidMoveFault]:
        """Take the active faults whose time has come, earliest first."""
        due = sorted((f for f in self._active if f.due is not None and f.due <= now), key=lambda f: f.due or 0.0)
        for fault in due:
            self._active.remove(fault)
        return due

    # ------------------------------------------------------------ protocol hooks

    def _power_up(self, now: float) -> None:
        """Output at power-up (a banner)."""

    def _on_bytes(self, data: bytes, now: float) -> None:
        """Handle received bytes."""
        raise NotImplementedError

    def _advance(self, now: float) -> None:
        """Bring motion and timed events up to `now`."""
        raise NotImplementedError

    def _next_timer(self, now: float) -> float | None:
        """Monotonic time of the next protocol event (end of move, homing done)."""
        return None
