"""Real V4L2 cameras through linuxpy, for full-bit-depth monochrome and raw Bayer capture.

Three layers (DESIGN §7): the pure codec in `formats.py`; `LinuxpyAdapter`, the only code that calls
linuxpy (one small method per ioctl, so tests replace it with a fake); and `V4L2Camera`, which owns the
state machine: format and controls read back, a select() deadline on every frame wait, error-flagged and
short buffers discarded, sequence gaps counted, disconnects turned into DeviceError, and `reopen()`
that finds a re-plugged camera again through its stable /dev/v4l/by-id link.

URL: ``v4l2:///dev/video0?format=Y16&width=2048&height=2048&exposure_us=5000&gain=1``; see `URL_PARAMS`
(format, width, height, exposure_us, gain, roi=x,y,w,h, buffers, settle_frames, exposure_unit_us).

Frame stamps: `device_timestamp_s` is the driver's buffer timestamp (CLOCK_MONOTONIC on most drivers,
comparable with time.monotonic()); `host_timestamp_s` is time.time() at dequeue; exposure (µs) and gain
(device units) are read back from the device for every frame. Y16 frames report 16 bits even when the
sensor fills fewer (the kernel format does not say).
"""

from __future__ import annotations

import errno
import logging
import math
import numbers
import operator
import os
import select
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from drivers.camera import register_camera_scheme
from drivers.camera.base import DEFAULT_TIMEOUT_S, Camera, Frame, SequenceTracker, check_timeout_s
from drivers.camera.formats import FORMATS, PixelFormat, format_by_code, fourcc_text, lookup_format
from drivers.url import DeviceURL, parse_device_url
from mlaqc.errors import DeviceError, InputError, MlaqcError

log = logging.getLogger(__name__)

# Kernel UAPI constants (stable ABI), spelled out so everything but LinuxpyAdapter runs without linuxpy.
BUF_FLAG_ERROR = 0x00000040
CID_EXPOSURE = 0x00980911  # user class, driver units
CID_AUTOGAIN = 0x00980912
CID_GAIN = 0x00980913  # user class, driver units
CID_EXPOSURE_AUTO = 0x009A0901  # menu: 0 auto, 1 manual, 2 shutter priority, 3 aperture priority
CID_EXPOSURE_ABSOLUTE = 0x009A0902  # units of 100 µs
CID_ANALOGUE_GAIN = 0x009E0903  # image-source class, driver units
EXPOSURE_MANUAL = 1
EXPOSURE_ABSOLUTE_UNIT_US = 100.0

BY_ID_DIR = Path("/dev/v4l/by-id")
DISCONNECT_ERRNOS = frozenset({errno.ENODEV, errno.EIO, errno.ENXIO, errno.ESHUTDOWN})
UNSUPPORTED_ERRNOS = frozenset({errno.EINVAL, errno.ENOTTY, errno.ENODATA, errno.EOPNOTSUPP})
URL_PARAMS = ("format", "width", "height", "exposure_us", "gain", "roi", "buffers", "settle_frames", "exposure_unit_us")
REOPEN_POLL_S = 0.05
SPURIOUS_WAKE_S = 0.001


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


@dataclass
class _Desired:
    """Settings the user asked for; re-applied after every (re)open."""

    pixel_format: PixelFormat | None = None
    width: int | None = None
    height: int | None = None
    roi: tuple[int, int, int, int] | None = None
    exposure_us: float | None = None
    gain: float | None = None


class V4L2Camera(Camera):
    """A V4L2 capture device delivering raw frames; see the module docstring for the fault handling."""

    def __init__(self, path: str, *, url: str | None = None, pixel_format: str | None = None,
                 width: int | None = None, height: int | None = None, exposure_us: float | None = None,
                 gain: float | None = None, roi: tuple[int, int, int, int] | None = None, buffers: int = 4,
                 settle_frames: int = 1, exposure_unit_us: float | None = None,
                 adapter_factory: Callable[[str], V4L2Adapter] = LinuxpyAdapter,
                 by_id_dir: str | os.PathLike[str] = BY_ID_DIR) -> None:
        super().__init__(url or f"v4l2://{path}")
        self._path = path
        self._desired = _Desired(lookup_format(pixel_format) if pixel_format else None, width, height, roi,
                                 exposure_us, gain)
        self._buffers_wanted = buffers
        self._settle_frames = settle_frames
        self._exposure_unit_override_us = exposure_unit_us
        self._adapter_factory = adapter_factory
        self._by_id_dir = Path(by_id_dir)
        self._lock = threading.RLock()
        self._adapter: V4L2Adapter | None = None
        self._open_path = path
        self._by_id_path: str | None = path if Path(path).parent == self._by_id_dir else None
        self._ident: dict[str, str] = {}
        self._controls: dict[int, ControlInfo] = {}
        self._fmt: PixelFormat | None = None
        self._raw_fmt: RawFormat | None = None
        self._streaming = False
        self._buffer_count = 0
        self._settle_left = 0
        self._roi_active = False
        self._disconnected = False
        self._sequence = SequenceTracker()
        self.error_frames = 0
        self.timeouts = 0

    # ----------------------------------------------------------------- construction from a URL

    @classmethod
    def from_url(cls, url: DeviceURL | str, **options: Any) -> V4L2Camera:
        """Build an unopened camera from a ``v4l2://`` URL; InputError naming any bad parameter.

        `options` are constructor keywords (adapter_factory, by_id_dir, ...) and override URL parameters."""
        parsed = parse_device_url(url) if isinstance(url, str) else url
        text = str(url)
        unknown = sorted(set(parsed.params) - set(URL_PARAMS))
        if unknown:
            raise InputError(f"unknown parameter {unknown[0]!r} in camera URL {text!r}; "
                             f"known: {', '.join(URL_PARAMS)}")
        if not parsed.path.startswith("/"):
            raise InputError(f"camera URL {text!r} needs an absolute device path, e.g. 'v4l2:///dev/video0'")
        p = parsed.param
        kwargs = dict(
            pixel_format=p("format"),
            width=_int_param(text, "width", p("width"), 1),
            height=_int_param(text, "height", p("height"), 1),
            exposure_us=_float_param(text, "exposure_us", p("exposure_us"), positive=True),
            gain=_float_param(text, "gain", p("gain")),
            roi=_roi_param(text, p("roi")),
            buffers=_int_param(text, "buffers", p("buffers"), 2, 32) or 4,
            settle_frames=_int_param(text, "settle_frames", p("settle_frames"), 0, 100),
            exposure_unit_us=_float_param(text, "exposure_unit_us", p("exposure_unit_us"), positive=True),
        )
        if kwargs["settle_frames"] is None:
            kwargs["settle_frames"] = 1
        return cls(parsed.path, url=text, **{**kwargs, **options})

    # ----------------------------------------------------------------- identity and state

    @property
    def name(self) -> str:
        """'<card name> at <device path>' once opened, else the device path."""
        card = self._ident.get("card")
        return f"'{card}' at {self._path}" if card else self._path

    @property
    def is_open(self) -> bool:
        return self._adapter is not None

    @property
    def bit_depth(self) -> int:
        if self._fmt is None:
            raise DeviceError(f"camera {self.name} has no pixel format yet; open it first")
        return self._fmt.bits

    @property
    def dropped_frames(self) -> int:
        """Frames lost (sequence gaps) since the camera was created."""
        return self._sequence.lost_total

    # ----------------------------------------------------------------- open / close / reopen

    def open(self) -> V4L2Camera:
        """Open the node, read its identity and controls, and apply format, ROI, exposure and gain."""
        with self._lock:
            if self._adapter is not None:
                return self
            adapter = self._adapter_factory(self._open_path)
            with self._device_op("opening the device", adapter_path=self._open_path):
                adapter.open()
            self._adapter = adapter
            try:
                self._configure()
            except BaseException:
                self._release()
                raise
            self._disconnected = False
            return self

    def close(self) -> None:
        """Stop streaming and close the fd; errors from a vanished device are ignored."""
        with self._lock:
            self._release()

    def reopen(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> V4L2Camera:
        """Close, wait (up to `timeout_s`) for the camera's by-id link to reappear, open and re-apply settings."""
        check_timeout_s(timeout_s)
        deadline = time.monotonic() + timeout_s
        with self._lock:
            self._release()
            self._open_path = self._by_id_path or self._path
            while True:
                try:
                    if os.path.exists(self._open_path):
                        return self.open()
                except DeviceError:
                    if time.monotonic() >= deadline:
                        raise
                if time.monotonic() >= deadline:
                    raise DeviceError(f"camera {self.name} did not reappear at {self._open_path} within "
                                      f"{timeout_s:g} s while reopening it; check the cable and power")
                time.sleep(min(REOPEN_POLL_S, max(0.0, deadline - time.monotonic())))

    def _configure(self) -> None:
        """Read identity and controls, locate the by-id link, then apply the desired settings."""
        adapter = self._require_open("opening the device")
        with self._device_op("reading its capabilities"):
            self._ident = adapter.identify()
            self._controls = adapter.controls()
        self._remember_by_id()
        self._apply_format()
        if self._desired.roi is not None:
            self._apply_roi(*self._desired.roi)
        if self._desired.exposure_us is not None:
            self.set_exposure_us(self._desired.exposure_us)
        if self._desired.gain is not None:
            self.set_gain(self._desired.gain)
        self._sequence.reset()

    def _release(self) -> None:
        """Drop the adapter whatever state the device is in."""
        adapter, self._adapter = self._adapter, None
        self._streaming = False
        self._roi_active = False
        if adapter is None:
            return
        try:
            adapter.close()
        except OSError as exc:
            log.debug("closing %s: %s", self._path, exc)

    def _remember_by_id(self) -> None:
        """Find the /dev/v4l/by-id link that points at the opened node, to find it again after a re-plug."""
        if self._by_id_path is not None or not self._by_id_dir.is_dir():
            return
        node = os.path.realpath(self._open_path)
        for link in sorted(self._by_id_dir.iterdir()):
            if os.path.realpath(link) == node:
                self._by_id_path = str(link)
                return

    # ----------------------------------------------------------------- format and ROI

    def set_format(self, pixel_format: str) -> str:
        """Switch to a raw pixel format the camera offers, keeping the frame size; return the name read back."""
        fmt = lookup_format(pixel_format)
        with self._lock:
            self._require_open("setting the pixel format")
            previous, self._desired.pixel_format = self._desired.pixel_format, fmt
            try:
                self._apply_format()
            except InputError:
                self._desired.pixel_format = previous
                raise
            return self._fmt.name

    def set_roi(self, x: int, y: int, width: int, height: int) -> tuple[int, int, int, int]:
        """Crop the sensor readout (VIDIOC_S_SELECTION) and size the format to it; return the ROI read back."""
        roi = _check_roi(f"ROI for camera {self.name}", (x, y, width, height))
        with self._lock:
            self._require_open("setting the region of interest")
            back = self._apply_roi(*roi)
            self._desired.roi = roi
            return back

    def _apply_format(self) -> None:
        """Set the desired (or best available) raw format and size; InputError if the camera cannot."""
        adapter = self._require_open("setting the pixel format")
        with self._device_op("setting the pixel format"):
            self._stop_streaming()
            current = adapter.get_format()
            offered = adapter.pixel_format_codes()
            fmt = self._desired.pixel_format or format_by_code(current.code) or _best_format(offered)
            if fmt is None:
                raise InputError(f"camera {self.name} offers no raw monochrome or Bayer format "
                                 f"(it offers {', '.join(map(fourcc_text, offered)) or 'nothing'})")
            if fmt.code not in offered:
                usable = [f.name for f in FORMATS if f.code in offered]
                raise InputError(f"camera {self.name} does not offer pixel format {fmt.name}; "
                                 f"it offers {', '.join(usable) or 'no raw format'}")
            if self._roi_active:
                width, height = current.width, current.height
            else:
                width = self._desired.width or current.width
                height = self._desired.height or current.height
            raw = adapter.set_format(width, height, fmt.code)
        self._accept_format(raw, fmt, width, height)

    def _accept_format(self, raw: RawFormat, fmt: PixelFormat, width: int, height: int) -> None:
        """Check the format the driver granted against the request and store it."""
        if raw.code != fmt.code:
            raise InputError(f"camera {self.name} refused pixel format {fmt.name} and chose "
                             f"{fourcc_text(raw.code)} instead")
        sized = not self._roi_active and (self._desired.width is not None or self._desired.height is not None)
        if sized and (raw.width, raw.height) != (width, height):
            raise InputError(f"camera {self.name} cannot deliver {width}x{height} in {fmt.name}; "
                             f"the nearest it offers is {raw.width}x{raw.height}")
        if raw.bytes_per_line and raw.bytes_per_line < fmt.min_bytes_per_line(raw.width):
            raise DeviceError(f"camera {self.name} reports {raw.bytes_per_line} bytes per line, fewer than "
                              f"{fmt.name} needs for {raw.width} pixels")
        self._fmt, self._raw_fmt = fmt, raw

    def _apply_roi(self, x: int, y: int, width: int, height: int) -> tuple[int, int, int, int]:
        """Crop, then set the format to the crop size; return the crop read back."""
        adapter = self._require_open("setting the region of interest")
        with self._device_op("setting the region of interest"):
            self._stop_streaming()
            try:
                adapter.set_crop(x, y, width, height)
            except OSError as exc:
                if exc.errno not in UNSUPPORTED_ERRNOS:
                    raise
                raise InputError(f"camera {self.name} does not support a region of interest "
                                 f"({os.strerror(exc.errno)})") from None
            back = tuple(adapter.get_crop())
            raw = adapter.set_format(back[2], back[3], self._fmt.code)
        if back != (x, y, width, height):
            log.warning("camera %s adjusted the ROI %s to %s", self.name, (x, y, width, height), back)
        if (raw.width, raw.height) != back[2:]:
            log.warning("camera %s delivers %dx%d for a %dx%d ROI", self.name, raw.width, raw.height, *back[2:])
        self._roi_active = True
        self._accept_format(raw, self._fmt, raw.width, raw.height)
        return back

    # ----------------------------------------------------------------- controls

    def set_exposure_us(self, exposure_us: float) -> float:
        """Switch auto exposure off, set the exposure time; return it as read back in µs."""
        _check_number("exposure_us", exposure_us, positive=True)
        with self._lock:
            self._require_open("setting the exposure")
            cid, unit_us = self._exposure_control()
            with self._device_op("setting the exposure"):
                self._switch_off(CID_EXPOSURE_AUTO, EXPOSURE_MANUAL, "auto exposure")
                self._set_in_range(cid, exposure_us / unit_us, "exposure", "µs", unit_us)
                back_us = self._adapter.get_control(cid) * unit_us
            self._desired.exposure_us = float(exposure_us)
            self._start_settling()
            return back_us

    def set_gain(self, gain: float) -> float:
        """Switch auto gain off, set the gain in device units; return it as read back."""
        _check_number("gain", gain)
        with self._lock:
            self._require_open("setting the gain")
            cid = self._gain_control()
            if cid is None:
                raise InputError(f"camera {self.name} has no gain control")
            with self._device_op("setting the gain"):
                self._switch_off(CID_AUTOGAIN, 0, "auto gain")
                self._set_in_range(cid, gain, "gain", "", 1.0)
                back = float(self._adapter.get_control(cid))
            self._desired.gain = float(gain)
            self._start_settling()
            return back

    def _start_settling(self) -> None:
        """While streaming, the frame in flight mixes old and new settings: drop `settle_frames` frames."""
        if self._streaming:
            self._settle_left = self._settle_frames

    def _exposure_control(self) -> tuple[int, float]:
        """The exposure control id and its unit in µs; InputError if the unit is unknown."""
        if CID_EXPOSURE_ABSOLUTE in self._controls:
            return CID_EXPOSURE_ABSOLUTE, EXPOSURE_ABSOLUTE_UNIT_US
        if CID_EXPOSURE in self._controls:
            if self._exposure_unit_override_us is None:
                raise InputError(f"camera {self.name} has only a driver-unit exposure control; give its unit "
                                 f"as exposure_unit_us=... in the camera URL")
            return CID_EXPOSURE, self._exposure_unit_override_us
        raise InputError(f"camera {self.name} has no exposure control")

    def _gain_control(self) -> int | None:
        """V4L2_CID_GAIN if present, else V4L2_CID_ANALOGUE_GAIN, else None."""
        return next((cid for cid in (CID_GAIN, CID_ANALOGUE_GAIN) if cid in self._controls), None)

    def _switch_off(self, cid: int, value: int, what: str) -> None:
        """Set an auto-mode control to its manual value and verify it stuck."""
        if cid not in self._controls:
            return
        self._adapter.set_control(cid, value)
        if self._adapter.get_control(cid) != value:
            raise DeviceError(f"camera {self.name} did not switch {what} off")

    def _set_in_range(self, cid: int, value: float, what: str, unit: str, scale: float) -> None:
        """Write a control value snapped to its step; InputError if it is outside the control's range."""
        info = self._controls[cid]
        raw = int(round(value))
        if not info.minimum <= raw <= info.maximum:
            raise InputError(f"{what} {value * scale:g}{unit and ' ' + unit} is outside camera {self.name}'s "
                             f"range {info.minimum * scale:g}..{info.maximum * scale:g}{unit and ' ' + unit}")
        step = max(info.step, 1)
        raw = min(info.maximum, info.minimum + round((raw - info.minimum) / step) * step)
        self._adapter.set_control(cid, raw)

    def _read_exposure_us(self) -> float:
        """Exposure read back in µs, NaN if the camera has none or its unit is unknown."""
        try:
            cid, unit_us = self._exposure_control()
        except InputError:
            return math.nan
        return self._adapter.get_control(cid) * unit_us

    def _read_gain(self) -> float:
        """Gain read back in device units, NaN if the camera has none."""
        cid = self._gain_control()
        return math.nan if cid is None else float(self._adapter.get_control(cid))

    def _read_auto(self, cid: int, manual: int) -> bool | None:
        """Whether an auto mode is on, None if the camera has no such control."""
        return None if cid not in self._controls else self._adapter.get_control(cid) != manual

    def settings(self) -> dict[str, Any]:
        """Everything a sidecar needs about the camera, read back from the device."""
        with self._lock:
            adapter = self._require_open("reading its settings")
            with self._device_op("reading its settings"):
                raw = adapter.get_format()
                return {
                    "url": self.url, "name": self.name, "device_node": os.path.realpath(self._open_path),
                    "by_id_path": self._by_id_path, **self._ident,
                    "pixel_format": self._fmt.name, "bits": self._fmt.bits, "cfa": self._fmt.cfa,
                    "width": raw.width, "height": raw.height, "bytes_per_line": raw.bytes_per_line,
                    "roi": self._read_roi(),
                    "exposure_us": self._read_exposure_us(),
                    "exposure_auto": self._read_auto(CID_EXPOSURE_AUTO, EXPOSURE_MANUAL),
                    "gain": self._read_gain(), "gain_auto": self._read_auto(CID_AUTOGAIN, 0),
                    "buffers": self._buffer_count or self._buffers_wanted, "settle_frames": self._settle_frames,
                    "streaming": self._streaming, "dropped_frames": self.dropped_frames,
                    "error_frames": self.error_frames, "timeouts": self.timeouts,
                }

    def _read_roi(self) -> tuple[int, int, int, int] | None:
        """The crop rectangle, None if the driver has no selection API."""
        try:
            return tuple(self._adapter.get_crop())
        except OSError as exc:
            if exc.errno in UNSUPPORTED_ERRNOS:
                return None
            raise

    # ----------------------------------------------------------------- frames

    def capture(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> Frame:
        """Return the first good frame completed after this call; DeviceError if none within `timeout_s`."""
        timeout_s = check_timeout_s(timeout_s)
        deadline = time.monotonic() + timeout_s
        with self._lock:
            self._require_open("capturing a frame")
            with self._device_op("capturing a frame"):
                self._ensure_streaming()
                self._flush()
                return self._next_frame(deadline, timeout_s, "capturing a frame")

    def stream(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> Iterator[Frame]:
        """Yield every frame in order for live view; each waited for at most `timeout_s`."""
        timeout_s = check_timeout_s(timeout_s)
        while True:
            with self._lock:
                self._require_open("streaming frames")
                with self._device_op("streaming frames"):
                    self._ensure_streaming()
                    frame = self._next_frame(time.monotonic() + timeout_s, timeout_s, "streaming frames")
            yield frame

    def _ensure_streaming(self) -> None:
        """Queue buffers and STREAMON if not already streaming."""
        if not self._streaming:
            self._buffer_count = self._adapter.start(self._buffers_wanted)
            self._streaming = True
            self._sequence.reset()

    def _stop_streaming(self) -> None:
        """STREAMOFF and free buffers (required before changing format or crop)."""
        self._settle_left = 0
        if self._streaming:
            self._streaming = False
            self._adapter.stop()

    def _flush(self) -> None:
        """Drop frames completed before the call. If every buffer was full, the driver may have dropped
        frames for lack of buffers while nobody was reading, so the gap baseline is reset."""
        drained = 0
        while drained < 4 * self._buffer_count:
            raw = self._adapter.dequeue()
            if raw is None:
                break
            drained += 1
            self._sequence.update(raw.sequence)
        if drained >= self._buffer_count:
            self._sequence.reset()

    def _next_frame(self, deadline: float, timeout_s: float, doing: str) -> Frame:
        """Wait for buffers until a good one arrives: discard error-flagged, short and settling frames."""
        errors = gap = settled = 0
        while True:
            raw = self._wait_buffer(deadline, timeout_s, doing, errors)
            host_s = time.time()
            lost = self._sequence.update(raw.sequence)
            gap += lost or 0
            if lost:
                log.warning("camera %s lost %d frame(s) before sequence %d", self.name, lost, raw.sequence)
            if raw.flags & BUF_FLAG_ERROR or min(raw.bytes_used, len(raw.data)) < self._needed_bytes():
                errors += 1
                self.error_frames += 1
                log.warning("camera %s: discarded bad frame %d (flags 0x%x, %d bytes)", self.name,
                            raw.sequence, raw.flags, raw.bytes_used)
                continue
            if self._settle_left > 0:
                self._settle_left -= 1
                settled += 1
                continue
            extra = {"sequence_gap": gap, "dropped_frames_total": self.dropped_frames,
                     "error_frames_discarded": errors, "settle_frames_discarded": settled,
                     "sequence_reset": lost is None, "buffer_flags": raw.flags,
                     "bytes_per_line": self._raw_fmt.bytes_per_line}
            return self._make_frame(raw, host_s, extra)

    def _needed_bytes(self) -> int:
        """Bytes a complete image needs in the current format."""
        raw = self._raw_fmt
        return self._fmt.min_image_bytes(raw.width, raw.height, raw.bytes_per_line)

    def _wait_buffer(self, deadline: float, timeout_s: float, doing: str, errors: int) -> RawBuffer:
        """Dequeue the next filled buffer, select()ing on the fd until the deadline."""
        fd = self._adapter.fileno()
        woke = False
        while True:
            raw = self._adapter.dequeue()
            if raw is not None:
                return raw
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise self._timeout_error(timeout_s, doing, errors)
            if woke:  # readable yet EAGAIN: do not spin at full speed
                time.sleep(min(SPURIOUS_WAKE_S, remaining))
            readable, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
            woke = bool(readable)

    def _timeout_error(self, timeout_s: float, doing: str, errors: int) -> DeviceError:
        """A timeout, or a disconnect if the device node has vanished meanwhile."""
        if not os.path.exists(self._open_path):
            return self._disconnected_error(doing, "its device node vanished")
        self.timeouts += 1
        why = f" ({errors} error-flagged or short frames discarded)" if errors else ""
        return DeviceError(f"camera {self.name} timed out after {timeout_s:g} s waiting for a frame "
                           f"while {doing}{why}")

    def _make_frame(self, raw: RawBuffer, host_s: float, extra: dict[str, Any]) -> Frame:
        """Decode the buffer and stamp it with the settings read back now."""
        fmt, rf = self._fmt, self._raw_fmt
        data = fmt.unpack(raw.data, rf.width, rf.height, rf.bytes_per_line)
        return Frame(data=data, bits=fmt.bits, pixel_format=fmt.name, cfa=fmt.cfa, sequence=raw.sequence,
                     device_timestamp_s=raw.timestamp_s, host_timestamp_s=host_s,
                     exposure_us=self._read_exposure_us(), gain=self._read_gain(), device=self.url, extra=extra)

    # ----------------------------------------------------------------- errors

    def _require_open(self, doing: str) -> V4L2Adapter:
        """The adapter, or DeviceError saying why there is none."""
        if self._adapter is not None:
            return self._adapter
        if self._disconnected:
            raise DeviceError(f"camera {self.name} is disconnected; reconnect it and call reopen() before {doing}")
        raise DeviceError(f"camera {self.name} is not open; open it before {doing}")

    @contextmanager
    def _device_op(self, doing: str, adapter_path: str | None = None) -> Iterator[None]:
        """Turn OSError from the device into one-sentence DeviceErrors naming the camera and the action."""
        try:
            yield
        except MlaqcError:
            raise
        except OSError as exc:
            raise self._os_error(exc, doing, adapter_path) from exc

    def _os_error(self, exc: OSError, doing: str, adapter_path: str | None) -> DeviceError:
        """Classify an OSError: disconnect, missing node, busy, permission, not V4L2, or other."""
        code = exc.errno
        path = adapter_path or self._open_path
        if code in DISCONNECT_ERRNOS or (adapter_path is None and not os.path.exists(path)):
            return self._disconnected_error(doing, errno.errorcode.get(code, str(exc)))
        where = "" if path == self._path else f" at {path}"
        opening = adapter_path is not None
        if code == errno.ENOENT and opening:
            return DeviceError(f"camera {self.name} was not found{where} while {doing}; is it plugged in?")
        if code == errno.EACCES and opening:
            return DeviceError(f"camera {self.name} refused access{where}; add the user to the 'video' group")
        if code == errno.EBUSY:
            return DeviceError(f"camera {self.name} is busy while {doing}; another program may be using it")
        if code == errno.ENOTTY:
            return DeviceError(f"camera {self.name} failed while {doing}: {path} is not a V4L2 video device")
        return DeviceError(f"camera {self.name} failed while {doing}: {exc.strerror or exc}")

    def _disconnected_error(self, doing: str, why: str) -> DeviceError:
        """Mark the camera disconnected, release the fd and say so."""
        self._release()
        self._disconnected = True
        return DeviceError(f"camera {self.name} was disconnected while {doing} ({why}); "
                           f"reconnect it and call reopen()")


# --------------------------------------------------------------------- helpers


def _best_format(offered: list[int]) -> PixelFormat | None:
    """The deepest raw format on offer, preferring unpacked and monochrome ones."""
    usable = [f for f in FORMATS if f.code in offered]
    return max(usable, key=lambda f: (f.bits, not f.packed, f.cfa is None), default=None)


def _check_number(name: str, value: float, positive: bool = False) -> float:
    """A finite number (positive if asked); InputError otherwise."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) \
            or (positive and value <= 0):
        raise InputError(f"{name} must be a {'positive ' if positive else ''}finite number, got {value!r}")
    return float(value)


def _check_roi(what: str, roi: tuple[Any, ...]) -> tuple[int, int, int, int]:
    """(x, y, w, h) with x, y >= 0 and w, h > 0, all integers; InputError otherwise."""
    try:
        values = tuple(operator.index(v) for v in roi)
    except TypeError:
        values = ()
    if len(values) != 4 or min(values[:2]) < 0 or min(values[2:]) <= 0:
        raise InputError(f"{what} must be four integers x, y >= 0 and width, height > 0, got {tuple(roi)!r}")
    return values  # type: ignore[return-value]


def _int_param(url: str, name: str, text: str | None, lo: int, hi: int | None = None) -> int | None:
    """An integer URL parameter within [lo, hi], or None if absent."""
    if text is None:
        return None
    try:
        value = int(text)
    except ValueError:
        raise InputError(f"parameter {name}={text!r} in camera URL {url!r} is not an integer") from None
    if value < lo or (hi is not None and value > hi):
        bound = f"between {lo} and {hi}" if hi is not None else f"at least {lo}"
        raise InputError(f"parameter {name}={value} in camera URL {url!r} must be {bound}")
    return value


def _float_param(url: str, name: str, text: str | None, positive: bool = False) -> float | None:
    """A finite (optionally positive) float URL parameter, or None if absent."""
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"parameter {name}={text!r} in camera URL {url!r} is not a number") from None
    if not math.isfinite(value) or (positive and value <= 0):
        kind = "a positive number" if positive else "a finite number"
        raise InputError(f"parameter {name}={text!r} in camera URL {url!r} must be {kind}")
    return value


def _roi_param(url: str, text: str | None) -> tuple[int, int, int, int] | None:
    """The roi=x,y,w,h URL parameter, or None if absent."""
    if text is None:
        return None
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"parameter roi={text!r} in camera URL {url!r} must be x,y,width,height") from None
    return _check_roi(f"parameter roi in camera URL {url!r}", values)


register_camera_scheme("v4l2", V4L2Camera.from_url, replace=True)
