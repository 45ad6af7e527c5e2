"""Serve a simulated controller on a pseudo-terminal: drivers open `path` exactly like a real serial port.

One background thread owns the pty master: it feeds received bytes to the device, writes the device's
output when it is due (latency), and wakes for the device's timed events (end of a move, homing done,
a scheduled fault). `hang_up()` closes the pty like an unplugged cable; `close()` stops the thread and
closes every descriptor, so nothing leaks.
"""

from __future__ import annotations

import errno
import logging
import os
import pty
import select
import threading
import time
import tty
from typing import Protocol

log = logging.getLogger(__name__)

MAX_IDLE_WAIT_S = 0.05


class Served(Protocol):
    """What PtyServer needs from a simulated device."""

    def feed(self, data: bytes, now: float) -> None: ...
    def tick(self, now: float) -> None: ...
    def take_output(self, now: float) -> bytes: ...
    def next_event(self, now: float) -> float | None: ...
    def hangup_requested(self) -> bool: ...


class PtyServer:
    """A pty whose master side is served by a background thread; open `path` to talk to the device."""

    def __init__(self, device: Served, *, name: str = "sim") -> None:
        self.device = device
        self._master, self._slave = pty.openpty()
        tty.setraw(self._slave)  # no echo, no CR/LF translation, before any driver opens it
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._pending = bytearray()
        self._closing = threading.Event()
        self._fds_lock = threading.Lock()
        self.hung_up = threading.Event()
        self._thread = threading.Thread(target=self._serve, name=f"{name}-pty-server", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Make the server thread re-check the device now (after a fault was injected)."""
        try:
            os.write(self._wake_w, b"x")
        except (BlockingIOError, OSError):
            pass

    def close(self) -> None:
        """Stop the server thread and close every descriptor; safe to call twice."""
        self._closing.set()
        self.wake()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=5.0)
        with self._fds_lock:
            for attr in ("_master", "_slave", "_wake_r", "_wake_w"):
                fd = getattr(self, attr)
                if fd is not None:
                    _close_fd(fd)
                    setattr(self, attr, None)

    # ------------------------------------------------------------ server thread

    def _serve(self) -> None:
        """Main loop: device timers, due output, input; ends on close() or hang-up."""
        try:
            while not self._closing.is_set():
                now = time.monotonic()
                self.device.tick(now)
                if self.device.hangup_requested():
                    self._hang_up()
                    return
                self._pending.extend(self.device.take_output(now))
                self._flush()
                self._wait_and_read(self._wait_s(time.monotonic()))
        except Exception:  # a simulator bug must not hang the driver under test silently
            log.exception("simulator server crashed; hanging up")
            self._hang_up()

    def _wait_s(self, now: float) -> float:
        """How long select() may sleep: until the device's next event, at most MAX_IDLE_WAIT_S."""
        event = self.device.next_event(now)
        wait = MAX_IDLE_WAIT_S if event is None else min(MAX_IDLE_WAIT_S, event - now)
        return 0.001 if self._pending else max(0.0, wait)

    def _wait_and_read(self, timeout_s: float) -> None:
        """Wait for input (or a wake-up) and hand received bytes to the device."""
        ready, _, _ = select.select([self._master, self._wake_r], [], [], timeout_s)
        if self._wake_r in ready:
            os.read(self._wake_r, 4096)
        if self._master in ready:
            try:
                data = os.read(self._master, 4096)
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno != errno.EIO:
                    raise
                return
            if data:
                self.device.feed(data, time.monotonic())

    def _flush(self) -> None:
        """Write as much pending output as the pty accepts now."""
        while self._pending:
            try:
                written = os.write(self._master, self._pending)
            except BlockingIOError:
                return
            del self._pending[:written]

    def _hang_up(self) -> None:
        """Close the pty (both sides we hold): the driver's next read or write fails like an unplugged port."""
        with self._fds_lock:
            for attr in ("_master", "_slave"):
                fd = getattr(self, attr)
                if fd is not None:
                    _close_fd(fd)
                    setattr(self, attr, None)
        self.hung_up.set()


def _close_fd(fd: int) -> None:
    """Close a descriptor, ignoring 'already closed'."""
    try:
        os.close(fd)
    except OSError:
        pass
