"""Transport: deadlines, atomic writes from many threads, one owner per port, port failures."""

import os
import pty
import threading
import time
import tty

import pytest

from drivers.stage.transport import MAX_LINE_BYTES, PortError, Transport
from mlaqc.errors import DeviceError

pytestmark = pytest.mark.timeout(20)


@pytest.fixture
def loop():
    transport = Transport("loop://", owner="test loop")
    transport.open()
    yield transport
    transport.close()


@pytest.fixture
def pty_pair():
    master, slave = pty.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    fds = {"master": master, "slave": slave}
    yield path, fds
    for fd in fds.values():
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass


def test_read_line_strips_endings_and_keeps_order(loop):
    loop.write(b"ok\r\nerror:9\n<Idle>\r\n")
    deadline = time.monotonic() + 1
    assert [loop.read_line(deadline) for _ in range(3)] == [b"ok", b"error:9", b"<Idle>"]


def test_read_line_returns_none_at_the_deadline(loop):
    start = time.monotonic()
    assert loop.read_line(start + 0.1) is None
    assert 0.09 <= time.monotonic() - start < 0.5


def test_partial_line_waits_for_the_rest(loop):
    loop.write(b"par")
    assert loop.read_line(time.monotonic() + 0.05) is None
    loop.write(b"tial\n")
    assert loop.read_line(time.monotonic() + 1) == b"partial"


def test_endless_noise_is_cut_into_bounded_lines(loop):
    loop.write(b"\xff" * (MAX_LINE_BYTES + 10) + b"\n")
    first = loop.read_line(time.monotonic() + 1)
    assert len(first) == MAX_LINE_BYTES
    assert loop.read_line(time.monotonic() + 1) == b"\xff" * 10


def test_discard_input_drops_stale_bytes(loop):
    loop.write(b"stale\n")  # loop:// is synchronous: the bytes are already queued
    loop.discard_input()
    assert loop.read_line(time.monotonic() + 0.05) is None


def test_concurrent_writers_never_interleave_lines(loop):
    lines_per_thread, threads = 200, 4

    def writer(tag: int) -> None:
        for i in range(lines_per_thread):
            loop.write(f"thread{tag} line{i:04d} {'x' * 40}\n".encode())

    workers = [threading.Thread(target=writer, args=(t,)) for t in range(threads)]
    for w in workers:
        w.start()
    received = []
    deadline = time.monotonic() + 10
    while len(received) < lines_per_thread * threads:
        line = loop.read_line(deadline)
        assert line is not None, "lines went missing"
        received.append(line.decode())
    for w in workers:
        w.join()
    assert all(line.endswith("x" * 40) and line.startswith("thread") for line in received)
    assert len(set(received)) == lines_per_thread * threads


def test_one_owner_per_port(pty_pair):
    path, _ = pty_pair
    first = Transport(path, owner="first stage")
    first.open()
    try:
        second = Transport(path, owner="second stage")
        with pytest.raises(DeviceError, match="already open by first stage"):
            second.open()
    finally:
        first.close()
    again = Transport(path, owner="second stage")
    again.open()
    again.close()


def test_unopenable_port_is_a_device_error():
    with pytest.raises(DeviceError, match="could not open serial port /nonexistent/tty"):
        Transport("/nonexistent/tty", owner="ghost").open()


def test_hang_up_raises_port_error(pty_pair):
    path, fds = pty_pair
    transport = Transport(path, owner="test")
    transport.open()
    try:
        os.write(fds["master"], b"hello\n")
        assert transport.read_line(time.monotonic() + 1) == b"hello"
        os.close(fds["master"])
        os.close(fds["slave"])
        fds["master"] = fds["slave"] = None
        with pytest.raises(PortError):
            transport.read_line(time.monotonic() + 1)
        assert not transport.is_open
        with pytest.raises(PortError):
            transport.write(b"x")
    finally:
        transport.close()


def test_use_after_close_is_a_port_error(loop):
    loop.close()
    with pytest.raises(PortError, match="not open"):
        loop.write(b"x")
