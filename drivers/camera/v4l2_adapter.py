"""The V4L2 kernel boundary: UAPI constants, raw format, buffer and control records, V4L2Adapter, LinuxpyAdapter."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

# Kernel UAPI constants (stable ABI), spelled out so everything but LinuxpyAdapter runs without linuxpy.
BUF_FLAG_ERROR = 0x00000040
CID_EXPOSURE = 0x00980911  # user class, driver units
CID_AUTOGAIN = 0x00980912
CID_GAIN = 0x00980913  # user class, driver units
CID_EXPOSURE_AUTO = 0x009A0901  # menu: 0 auto, 1 manual, 2 shutter priority, 3 aperture priority
CID_EXPOSURE_ABSOLUTE = 0x009A0902  # units of 100 µs
CID_ANALOGUE_GAIN = 0x009E0903  # image-source class, driver units
CID_IRIS_ABSOLUTE = 0x009A0911  # camera class, driver units (uvcvideo: f-number x 100)
CID_IRIS_RELATIVE = 0x009A0912  # camera class, write-only: +1 opens, -1 closes one step
EXPOSURE_AUTO = 0
EXPOSURE_MANUAL = 1
EXPOSURE_SHUTTER_PRIORITY = 2
EXPOSURE_ABSOLUTE_UNIT_US = 100.0


@dataclass(frozen=True)
class RawFormat:
    """The capture format as the driver reports it (VIDIOC_G_FMT)."""

    width: int
    height: int
    code: int
    bytes_per_line: int
    size_bytes: int


@dataclass(frozen=True)
class RawBuffer:
    """One dequeued buffer, already copied out of the driver's memory and requeued."""

    data: bytes
    sequence: int
    timestamp_s: float
    flags: int
    bytes_used: int


@dataclass(frozen=True)
class ControlInfo:
    """One V4L2 control's id, name and integer range."""

    cid: int
    name: str
    minimum: int
    maximum: int
    step: int
    default: int


class V4L2Adapter(Protocol):
    """The ioctl-level operations V4L2Camera needs; raise OSError exactly as the kernel reports it."""

    path: str

    def open(self) -> None: ...
    def close(self) -> None: ...
    def fileno(self) -> int: ...
    def identify(self) -> dict[str, str]: ...
    def pixel_format_codes(self) -> list[int]: ...
    def get_format(self) -> RawFormat: ...
    def set_format(self, width: int, height: int, code: int) -> RawFormat: ...
    def controls(self) -> dict[int, ControlInfo]: ...
    def get_control(self, cid: int) -> int: ...
    def set_control(self, cid: int, value: int) -> None: ...
    def set_crop(self, left: int, top: int, width: int, height: int) -> None: ...
    def get_crop(self) -> tuple[int, int, int, int]: ...
    def start(self, buffer_count: int) -> int: ...
    def stop(self) -> None: ...
    def dequeue(self) -> RawBuffer | None: ...


class LinuxpyAdapter:
    """V4L2Adapter over linuxpy: non-blocking fd, MMAP buffers, plain G/S_CTRL; nothing else touches linuxpy."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._dev: Any = None
        self._maps: list[Any] = []

    def open(self) -> None:
        """Open the node non-blocking (DQBUF then returns EAGAIN instead of hanging)."""
        from linuxpy.video import device as lv

        self._lv = lv
        self._capture = lv.BufferType.VIDEO_CAPTURE
        self._mmap = lv.Memory.MMAP
        dev = lv.Device(self.path, blocking=False)
        dev.open()
        self._dev = dev

    def close(self) -> None:
        """Release buffers and the fd, ignoring errors from a device that is already gone."""
        if self._dev is None:
            return
        try:
            self.stop()
        except OSError:
            pass
        self._dev.close()
        self._dev = None

    def fileno(self) -> int:
        return self._dev.fileno()

    def identify(self) -> dict[str, str]:
        caps = self._lv.read_capabilities(self._dev)
        return {"driver": caps.driver.decode(), "card": caps.card.decode(), "bus_info": caps.bus_info.decode()}

    def pixel_format_codes(self) -> list[int]:
        desc = self._lv.raw.v4l2_fmtdesc()
        desc.type = self._capture
        return [int(d.pixelformat) for d in self._lv.iter_read(self._dev, self._lv.IOC.ENUM_FMT, desc)]

    def get_format(self) -> RawFormat:
        pix = self._lv.get_raw_format(self._dev, self._capture).fmt.pix
        return RawFormat(pix.width, pix.height, pix.pixelformat, pix.bytesperline, pix.sizeimage)

    def set_format(self, width: int, height: int, code: int) -> RawFormat:
        self._lv.set_format(self._dev, self._capture, width, height, pixel_format=code)
        return self.get_format()

    def controls(self) -> dict[int, ControlInfo]:
        found = {}
        for c in self._lv.iter_read_controls(self._dev):
            disabled = c.flags & self._lv.ControlFlag.DISABLED
            if c.type != self._lv.ControlType.CTRL_CLASS and not disabled:
                found[c.id] = ControlInfo(c.id, c.name.decode(), c.minimum, c.maximum, c.step, c.default_value)
        return found

    def get_control(self, cid: int) -> int:
        return int(self._lv.get_control(self._dev, cid))

    def set_control(self, cid: int, value: int) -> None:
        self._lv.set_control(self._dev, cid, int(value))

    def set_crop(self, left: int, top: int, width: int, height: int) -> None:
        rect = self._lv.Rect(left, top, width, height)
        self._lv.set_selection(self._dev, self._capture, self._lv.SelectionTarget.CROP, rect)

    def get_crop(self) -> tuple[int, int, int, int]:
        r = self._lv.get_selection(self._dev, self._capture, self._lv.SelectionTarget.CROP)
        return (r.left, r.top, r.width, r.height)

    def start(self, buffer_count: int) -> int:
        """Request, map and queue MMAP buffers, then STREAMON; return the count the driver granted."""
        lv, dev = self._lv, self._dev
        granted = lv.request_buffers(dev, self._capture, self._mmap, buffer_count).count
        for index in range(granted):
            buff = lv.query_buffer(dev, self._capture, self._mmap, index)
            self._maps.append(lv.mmap_from_buffer(dev, buff))
            lv.enqueue_buffer(dev, self._capture, self._mmap, 0, index)
        lv.stream_on(dev, self._capture)
        return granted

    def stop(self) -> None:
        """STREAMOFF, unmap and free the buffers."""
        if not self._maps:
            return
        maps, self._maps = self._maps, []
        try:
            self._lv.stream_off(self._dev, self._capture)
        finally:
            for m in maps:
                m.close()
            self._lv.free_buffers(self._dev, self._capture, self._mmap)

    def dequeue(self) -> RawBuffer | None:
        """DQBUF one filled buffer, copy it out and QBUF it back; None if none is ready (EAGAIN)."""
        try:
            buff = self._lv.dequeue_buffer(self._dev, self._capture, self._mmap)
        except BlockingIOError:
            return None
        data = self._maps[buff.index][: buff.bytesused]
        stamp = buff.timestamp.secs + buff.timestamp.usecs * 1e-6
        raw = RawBuffer(data, int(buff.sequence), stamp, int(buff.flags), int(buff.bytesused))
        self._lv.enqueue_buffer_raw(self._dev, buff)
        return raw
