"""Line transport over one serial port: owns the port, writes whole lines atomically, reads lines by deadline.

The port is opened with `serial.serial_for_url`, so a real port ('/dev/ttyUSB0'), a pty slave path,
'loop://' or 'socket://host:port' all work. One Transport owns one port: a second open of the same port in
this process is refused, and real ports are opened with an exclusive lock. Every read takes an absolute
deadline (time.monotonic()); the port's own timeout is only a short slice so no call blocks past it.
Serial faults (unplugged cable, closed pty, EOF) surface as PortError.
"""

from __future__ import annotations

import logging
import os
import threading
import time

import serial

from mlaqc.errors import DeviceError

log = logging.getLogger(__name__)

MAX_LINE_BYTES = 1024  # a longer run of bytes without a newline is handed up as one (garbage) line


class PortError(DeviceError):
    """The serial port failed, closed or reached end of file; `detail` says how."""

    def __init__(self, port: str, detail: str) -> None:
        super().__init__(f"serial port {port} failed: {detail}.")
        self.port = port
        self.detail = detail


class Transport:
    """One serial port: atomic line writes (any thread), deadline-bounded line reads (one reader at a time)."""

    _owners: dict[str, str] = {}
    _owners_lock = threading.Lock()

    def __init__(self, port: str, *, baud: int = 115200, owner: str = "", read_slice_s: float = 0.01) -> None:
        self.port = port
        self.baud = baud
        self.owner = owner or port
        self.read_slice_s = read_slice_s
        self._serial: serial.SerialBase | None = None
        self._write_lock = threading.Lock()
        self._buffer = bytearray()
        self._key = _port_key(port)
        self._failed: str | None = None

    # ------------------------------------------------------------ lifecycle

    @property
    def is_open(self) -> bool:
        """True while the port is open and has not failed."""
        return self._serial is not None and self._failed is None

    def open(self) -> None:
        """Open the port (refused if this process already owns it); DeviceError if it cannot be opened."""
        self._claim()
        try:
            self._serial = serial.serial_for_url(self.port, do_not_open=True, baudrate=self.baud,
                                                 timeout=self.read_slice_s, write_timeout=2.0)
            if self._key.startswith("/"):
                self._serial.exclusive = True
            self._serial.open()
        except (serial.SerialException, OSError, ValueError) as exc:
            self._serial = None
            self._release()
            raise DeviceError(f"{self.owner} could not open serial port {self.port}: {exc}.") from None
        self._failed = None
        self._buffer.clear()

    def close(self) -> None:
        """Close the port and give up ownership; safe to call twice."""
        port, self._serial = self._serial, None
        if port is not None:
            try:
                port.close()
            except Exception as exc:  # closing a dead port must not mask the real error
                log.debug("closing %s: %s", self.port, exc)
        self._release()

    def _claim(self) -> None:
        """Register this process as the port's only owner."""
        if self._key.startswith("loop://"):
            return
        with Transport._owners_lock:
            holder = Transport._owners.get(self._key)
            if holder is not None:
                raise DeviceError(f"{self.owner} cannot open serial port {self.port}: it is already open by {holder}.")
            Transport._owners[self._key] = self.owner

    def _release(self) -> None:
        """Forget the ownership claim, if this transport holds it."""
        with Transport._owners_lock:
            if Transport._owners.get(self._key) == self.owner:
                del Transport._owners[self._key]

    # ------------------------------------------------------------ I/O

    def write(self, data: bytes) -> None:
        """Write `data` in one piece (no other write can interleave with it); PortError on failure."""
        port = self._require_open()
        with self._write_lock:
            try:
                port.write(data)
                port.flush()
            except Exception as exc:
                raise self._fail(f"write failed ({exc})") from None

    def read_line(self, deadline: float) -> bytes | None:
        """The next line without its line ending, or None when `deadline` (monotonic s) passes first."""
        while True:
            line = self._pop_line()
            if line is not None:
                return line
            if time.monotonic() >= deadline:
                return None
            self._fill()

    def discard_input(self) -> None:
        """Drop everything received but not yet read (stale replies, a power-up banner)."""
        port = self._require_open()
        self._buffer.clear()
        try:
            port.reset_input_buffer()
        except Exception as exc:
            raise self._fail(f"flushing input failed ({exc})") from None

    def _pop_line(self) -> bytes | None:
        """Take one complete line out of the buffer (or an over-long run of bytes), else None."""
        newline = self._buffer.find(b"\n", 0, MAX_LINE_BYTES)
        if newline < 0:
            if len(self._buffer) < MAX_LINE_BYTES:
                return None
            newline = MAX_LINE_BYTES - 1
        line = bytes(self._buffer[: newline + 1])
        del self._buffer[: newline + 1]
        return line.rstrip(b"\r\n")

    def _fill(self) -> None:
        """Read what is waiting (at most one read slice of blocking) into the buffer."""
        port = self._require_open()
        try:
            waiting = port.in_waiting
            chunk = port.read(max(1, min(waiting, 4096)))
        except Exception as exc:
            raise self._fail(f"read failed ({exc})") from None
        self._buffer.extend(chunk)

    def _require_open(self) -> serial.SerialBase:
        """The open port, or PortError if it is closed or has failed."""
        if self._failed is not None:
            raise PortError(self.port, self._failed)
        port = self._serial
        if port is None:
            raise PortError(self.port, "the port is not open")
        return port

    def _fail(self, detail: str) -> PortError:
        """Remember that the port is dead and build the error for it."""
        if self._serial is None:
            detail = "the port was closed"
        self._failed = detail
        return PortError(self.port, detail)


def _port_key(port: str) -> str:
    """The ownership key of a port: the real path of a device node, else the URL itself."""
    if "://" in port:
        return port
    try:
        return os.path.realpath(port)
    except OSError:
        return port
