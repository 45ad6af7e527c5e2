"""A fake V4L2 camera at the adapter boundary: planted frames, controls, crop and faults, no kernel needed.

`FakeV4L2Bus` is an `adapter_factory` for `V4L2Camera`; it maps device nodes (real files, so by-id symlinks
and vanishing nodes work) to `FakeV4L2Device`s. Readiness is signalled through a real pipe, so the driver's
select() deadlines run exactly as on a device fd. Frames in `pending` are "exposed" one at a time when the
driver finds no buffer ready (like a sensor finishing the next frame); `plant_ready` puts a frame in a
filled buffer at once (a stale frame, or one arriving late from another thread).

Iris controls (none by default; add `uvc_iris_control()` or `relative_iris_control()` to `controls`) behave
as uvcvideo exposes a UVC camera's: the absolute value is the f-number x 100, writes are ignored while auto
exposure is Auto or Shutter Priority (UVC refuses them), and `iris_lag_reads` makes a motorized iris read
its old value back that many times after a write (None: it never gets there, a jammed iris). The relative
control is write-only (G_CTRL fails with EACCES): +k opens k steps, -k closes k, 0 goes to the power-on
position; `iris_step` is where the blades are, in steps closed from fully open (0 .. `iris_travel`).
"""

from __future__ import annotations

import errno
import os
import threading
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.camera.formats import format_by_code, lookup_format
from drivers.camera.v4l2_adapter import (
    BUF_FLAG_ERROR,
    CID_AUTOGAIN,
    CID_EXPOSURE_ABSOLUTE,
    CID_EXPOSURE_AUTO,
    CID_GAIN,
    CID_IRIS_ABSOLUTE,
    CID_IRIS_RELATIVE,
    EXPOSURE_MANUAL,
    ControlInfo,
    RawBuffer,
    RawFormat,
)

DISCONNECT = "disconnect"
EXPOSURE_APERTURE_PRIORITY = 3
# control -> (its auto-mode control, the auto-mode values in which writes to it take effect)
AUTO_CONTROLS = {CID_EXPOSURE_ABSOLUTE: (CID_EXPOSURE_AUTO, {EXPOSURE_MANUAL}), CID_GAIN: (CID_AUTOGAIN, {0}),
                 CID_IRIS_ABSOLUTE: (CID_EXPOSURE_AUTO, {EXPOSURE_MANUAL, EXPOSURE_APERTURE_PRIORITY}),
                 CID_IRIS_RELATIVE: (CID_EXPOSURE_AUTO, {EXPOSURE_MANUAL, EXPOSURE_APERTURE_PRIORITY})}


@dataclass(frozen=True)
class PlantedFrame:
    """A buffer the fake driver will deliver: bytes exactly as V4L2 hands them over, plus metadata."""

    data: bytes
    sequence: int
    flags: int = 0
    bytes_used: int | None = None
    timestamp_s: float | None = None


def default_controls() -> dict[int, ControlInfo]:
    """A UVC-like control set: exposure auto menu, absolute exposure (100 µs units), autogain, gain."""
    return {
        CID_EXPOSURE_AUTO: ControlInfo(CID_EXPOSURE_AUTO, "Auto Exposure", 0, 3, 1, 3),
        CID_EXPOSURE_ABSOLUTE: ControlInfo(CID_EXPOSURE_ABSOLUTE, "Exposure Time, Absolute", 1, 10000, 1, 100),
        CID_AUTOGAIN: ControlInfo(CID_AUTOGAIN, "Gain, Automatic", 0, 1, 1, 1),
        CID_GAIN: ControlInfo(CID_GAIN, "Gain", 0, 100, 1, 10),
    }


def uvc_iris_control(minimum: int = 200, maximum: int = 1600, step: int = 10,
                     default: int = 200) -> dict[int, ControlInfo]:
    """A UVC lens' absolute iris as uvcvideo reports it: f/2 .. f/16 as f-number x 100, in steps of 0.1."""
    return {CID_IRIS_ABSOLUTE: ControlInfo(CID_IRIS_ABSOLUTE, "Iris, Absolute", minimum, maximum, step, default)}


def relative_iris_control(minimum: int = -1, maximum: int = 1) -> dict[int, ControlInfo]:
    """A relative (step) iris control; uvcvideo reports its range as 0..0 (no GET_MIN/GET_MAX)."""
    return {CID_IRIS_RELATIVE: ControlInfo(CID_IRIS_RELATIVE, "Iris, Relative", minimum, maximum, 1, 0)}


class FakeV4L2Device:
    """What the kernel knows about one camera: formats, controls, crop, and frames the sensor will produce."""

    def __init__(self, node: str | os.PathLike[str], *, formats: Iterable[str] = ("Y16",), width: int = 8,
                 height: int = 6, stride_pad: int = 0, controls: dict[int, ControlInfo] | None = None,
                 crop_supported: bool = True, crop_align: int = 2, max_buffers: int = 4,
                 card: str = "Fake Camera", extra_codes: Iterable[int] = (), iris_lag_reads: int | None = 0,
                 iris_travel: int = 8, iris_default_step: int = 3) -> None:
        self.node = str(node)
        self.offered = [lookup_format(name).code for name in formats] + list(extra_codes)
        self.sensor_size = (width, height)
        self.stride_pad = stride_pad
        self.controls = dict(default_controls() if controls is None else controls)
        self.values = {cid: info.default for cid, info in self.controls.items()}
        self.iris_lag_reads = iris_lag_reads
        self.iris_target: tuple[int, int | None] | None = None  # (value written, reads before it shows): moving
        self.iris_travel, self.iris_default_step = iris_travel, iris_default_step
        self.iris_step = iris_default_step
        self.crop_supported, self.crop_align = crop_supported, crop_align
        self.crop = (0, 0, width, height)
        self.max_buffers = max_buffers
        self.ident = {"driver": "fake", "card": card, "bus_info": "usb-0000:00:14.0-1"}
        self.pending: deque[PlantedFrame | str] = deque()
        self.ready: deque[RawBuffer] = deque()
        self.calls: list[tuple] = []
        self.gone = False
        self.streaming = False
        self.adapters: set[FakeV4L2Adapter] = set()
        self.lock = threading.Lock()
        self.format = self._make_format(width, height, self.offered[0])
        Path(self.node).touch()

    def _make_format(self, width: int, height: int, code: int) -> RawFormat:
        """The format a driver reports for this size and code, with the device's row padding."""
        fmt = format_by_code(code)
        row = fmt.min_bytes_per_line(width) if fmt else 2 * width
        stride = row + self.stride_pad
        return RawFormat(width, height, code, stride, stride * height)

    # -- planting frames and faults (test side)

    def plant(self, data: bytes, sequence: int, flags: int = 0, bytes_used: int | None = None) -> None:
        """Queue a frame the sensor will produce when the driver next waits."""
        self.pending.append(PlantedFrame(bytes(data), sequence, flags, bytes_used))

    def plant_image(self, image: np.ndarray, sequence: int, flags: int = 0) -> None:
        """Queue an image encoded in the current format, row padding included."""
        fmt = format_by_code(self.format.code)
        self.plant(fmt.pack(image, self.format.bytes_per_line), sequence, flags)

    def plant_error(self, sequence: int) -> None:
        """Queue a buffer the driver marks with V4L2_BUF_FLAG_ERROR (garbage contents)."""
        self.plant(bytes(self.format.size_bytes), sequence, BUF_FLAG_ERROR)

    def plant_disconnect(self) -> None:
        """Queue an unplug: the node vanishes and every later call fails with ENODEV."""
        self.pending.append(DISCONNECT)

    def plant_ready(self, frame: PlantedFrame) -> None:
        """Put a frame in a filled buffer now (stale frame, or a late one from another thread)."""
        with self.lock:
            self.ready.append(_to_raw(frame))
        self._notify()

    def unplug(self) -> None:
        """The USB cable is pulled: node removed, fds readable (POLLERR) and failing with ENODEV."""
        self.gone = True
        self.streaming = False
        Path(self.node).unlink(missing_ok=True)
        self._notify()

    def replug(self, node: str | os.PathLike[str]) -> None:
        """The camera comes back, possibly at another node, with its power-on state."""
        self.node, self.gone = str(node), False
        self.values = {cid: info.default for cid, info in self.controls.items()}
        self.iris_target, self.iris_step = None, self.iris_default_step
        self.ready.clear()
        Path(self.node).touch()

    def _notify(self) -> None:
        for adapter in list(self.adapters):
            adapter.sync_signal()

    def produce(self) -> bool:
        """The sensor finishes the next pending frame; False if there is none. Raises nothing."""
        if not self.pending:
            return False
        item = self.pending.popleft()
        if item == DISCONNECT:
            self.unplug()
        else:
            with self.lock:
                self.ready.append(_to_raw(item))
            self._notify()
        return True


def _to_raw(frame: PlantedFrame) -> RawBuffer:
    """A planted frame as the adapter returns it after DQBUF."""
    used = len(frame.data) if frame.bytes_used is None else frame.bytes_used
    stamp = time.monotonic() if frame.timestamp_s is None else frame.timestamp_s
    return RawBuffer(frame.data[:used], frame.sequence, stamp, frame.flags, used)


class FakeV4L2Bus:
    """An adapter factory mapping device nodes to fake devices, as udev does for real ones."""

    def __init__(self, *devices: FakeV4L2Device) -> None:
        self.devices = list(devices)
        self.opened: list[FakeV4L2Adapter] = []

    def __call__(self, path: str) -> FakeV4L2Adapter:
        adapter = FakeV4L2Adapter(path, self)
        self.opened.append(adapter)
        return adapter

    def device_at(self, path: str) -> FakeV4L2Device | None:
        """The device whose node `path` resolves to, if any."""
        real = os.path.realpath(path)
        return next((d for d in self.devices if os.path.realpath(d.node) == real), None)


class FakeV4L2Adapter:
    """The V4L2Adapter protocol over a FakeV4L2Device, raising OSError as the kernel would."""

    def __init__(self, path: str, bus: FakeV4L2Bus) -> None:
        self.path = path
        self._bus = bus
        self.dev: FakeV4L2Device | None = None
        self._pipe: tuple[int, int] | None = None
        self._signalled = False
        self._signal_lock = threading.Lock()

    def open(self) -> None:
        dev = self._bus.device_at(self.path) if os.path.exists(self.path) else None
        if dev is None:
            raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), self.path)
        if dev.gone:
            raise OSError(errno.ENODEV, os.strerror(errno.ENODEV), self.path)
        self.dev, self._pipe = dev, os.pipe()
        dev.adapters.add(self)
        self.sync_signal()

    def close(self) -> None:
        if self.dev is None:
            return
        if self.dev.streaming and not self.dev.gone:
            self.dev.streaming = False
        self.dev.adapters.discard(self)
        with self._signal_lock:
            for fd in self._pipe:
                os.close(fd)
            self.dev, self._pipe = None, None

    def fileno(self) -> int:
        if self._pipe is None:
            raise ValueError("I/O operation on closed device")
        return self._pipe[0]

    def sync_signal(self) -> None:
        """Make the fd readable exactly when a buffer is ready or the device is gone."""
        with self._signal_lock:
            if self._pipe is None or self.dev is None:
                return
            want = bool(self.dev.ready) or self.dev.gone
            if want and not self._signalled:
                os.write(self._pipe[1], b"!")
            elif not want and self._signalled:
                os.read(self._pipe[0], 1)
            self._signalled = want

    def _alive(self, call: str, *args: object) -> FakeV4L2Device:
        """The device, after logging the call; ENODEV once unplugged."""
        dev = self.dev
        if dev is None:
            raise OSError(errno.EBADF, os.strerror(errno.EBADF))
        dev.calls.append((call, *args))
        if dev.gone:
            raise OSError(errno.ENODEV, os.strerror(errno.ENODEV))
        return dev

    def identify(self) -> dict[str, str]:
        return dict(self._alive("identify").ident)

    def pixel_format_codes(self) -> list[int]:
        return list(self._alive("enum_fmt").offered)

    def get_format(self) -> RawFormat:
        return self._alive("g_fmt").format

    def set_format(self, width: int, height: int, code: int) -> RawFormat:
        dev = self._alive("s_fmt", width, height, code)
        if dev.streaming:
            raise OSError(errno.EBUSY, os.strerror(errno.EBUSY))
        code = code if code in dev.offered else dev.offered[0]
        width, height = min(width, dev.sensor_size[0]), min(height, dev.sensor_size[1])
        dev.format = dev._make_format(width, height, code)
        return dev.format

    def controls(self) -> dict[int, ControlInfo]:
        return dict(self._alive("query_ctrls").controls)

    def get_control(self, cid: int) -> int:
        dev = self._alive("g_ctrl", cid)
        if cid not in dev.controls:
            raise OSError(errno.EINVAL, os.strerror(errno.EINVAL))
        if cid == CID_IRIS_RELATIVE:  # write-only
            raise OSError(errno.EACCES, os.strerror(errno.EACCES))
        if cid == CID_IRIS_ABSOLUTE and dev.iris_target is not None:
            target, left = dev.iris_target
            if left == 0:
                dev.values[cid], dev.iris_target = target, None
            elif left is not None:
                dev.iris_target = (target, left - 1)
        return dev.values[cid]

    def set_control(self, cid: int, value: int) -> None:
        """S_CTRL: range-checked; writes to a control whose auto mode is on are ignored, as on many cameras."""
        dev = self._alive("s_ctrl", cid, value)
        info = dev.controls.get(cid)
        if info is None:
            raise OSError(errno.EINVAL, os.strerror(errno.EINVAL))
        if not info.minimum <= value <= info.maximum:
            raise OSError(errno.ERANGE, os.strerror(errno.ERANGE))
        auto = AUTO_CONTROLS.get(cid)
        if auto and auto[0] in dev.values and dev.values[auto[0]] not in auto[1]:
            return
        if cid == CID_IRIS_RELATIVE:
            step = dev.iris_default_step if value == 0 else dev.iris_step - int(value)  # + opens
            dev.iris_step = min(max(step, 0), dev.iris_travel)
        elif cid == CID_IRIS_ABSOLUTE and dev.iris_lag_reads != 0:
            dev.iris_target = (int(value), dev.iris_lag_reads)
        else:
            dev.values[cid] = int(value)

    def set_crop(self, left: int, top: int, width: int, height: int) -> None:
        dev = self._alive("s_selection", left, top, width, height)
        if not dev.crop_supported:
            raise OSError(errno.ENOTTY, os.strerror(errno.ENOTTY))
        a = dev.crop_align
        sw, sh = dev.sensor_size
        left, width = left // a * a, max(a, width // a * a)
        dev.crop = (min(left, sw - a), min(top, sh - 1), min(width, sw - left), min(height, sh - top))

    def get_crop(self) -> tuple[int, int, int, int]:
        dev = self._alive("g_selection")
        if not dev.crop_supported:
            raise OSError(errno.ENOTTY, os.strerror(errno.ENOTTY))
        return dev.crop

    def start(self, buffer_count: int) -> int:
        dev = self._alive("streamon", buffer_count)
        if dev.streaming:
            raise OSError(errno.EBUSY, os.strerror(errno.EBUSY))
        dev.streaming = True
        return min(buffer_count, dev.max_buffers)

    def stop(self) -> None:
        dev = self._alive("streamoff")
        dev.streaming = False
        with dev.lock:
            dev.ready.clear()
        self.sync_signal()

    def dequeue(self) -> RawBuffer | None:
        """DQBUF on a non-blocking fd: a ready buffer, else None (EAGAIN) after the sensor starts the next one."""
        dev = self._alive("dqbuf")
        if not dev.streaming:
            raise OSError(errno.EINVAL, os.strerror(errno.EINVAL))
        with dev.lock:
            raw = dev.ready.popleft() if dev.ready else None
        if raw is not None:
            self.sync_signal()
            return raw
        dev.produce()
        return None


__all__ = ["DISCONNECT", "FakeV4L2Adapter", "FakeV4L2Bus", "FakeV4L2Device", "PlantedFrame", "default_controls",
           "relative_iris_control", "uvc_iris_control"]
