"""Real V4L2 cameras through linuxpy, for full-bit-depth monochrome and raw Bayer capture.

Three layers (DESIGN §7): the pure codec in `formats.py`; `LinuxpyAdapter` in `v4l2_adapter.py`, the only
code that calls linuxpy (one small method per ioctl, so tests replace it with a fake), beside the kernel
constants; and `V4L2Camera`, here, which owns the state machine: format and controls read back, a select()
deadline on every frame wait, error-flagged and short buffers discarded, sequence gaps counted, disconnects
turned into DeviceError, and `reopen()` that finds a re-plugged camera again through its stable
/dev/v4l/by-id link.

URL: ``v4l2:///dev/video0?format=Y16&width=2048&height=2048&exposure_us=5000&gain=1``; see `URL_PARAMS` in
`v4l2_params.py` (format, width, height, exposure_us, gain, roi=x,y,w,h, buffers, settle_frames,
exposure_unit_us, and the iris: f_number, iris_unit, iris_table, iris_timeout_s).

Frame stamps: `device_timestamp_s` is the driver's buffer timestamp (CLOCK_MONOTONIC on most drivers,
comparable with time.monotonic()); `host_timestamp_s` is time.time() at dequeue; exposure (µs) and gain
(device units) are read back from the device for every frame. Y16 frames report 16 bits even when the
sensor fills fewer (the kernel format does not say).

Iris (`set_f_number(N)`, `f_number`: the main lens' f-number, as the scan runner's through-focus frames
with ``[through_focus] iris = "camera"`` need it). What was relied on:
- The V4L2 spec (Documentation/userspace-api/media/v4l/ext-ctrls-camera.rst) defines
  V4L2_CID_IRIS_ABSOLUTE with "the unit is undefined. Larger values open the iris wider" and
  V4L2_CID_IRIS_RELATIVE as write-only, "positive values open the iris one step further, negative values
  close it"; include/uapi/linux/v4l2-controls.h gives their ids, V4L2_CID_CAMERA_CLASS_BASE + 17 and + 18
  (0x009A0911, 0x009A0912; linuxpy's ControlID.IRIS_ABSOLUTE / IRIS_RELATIVE agree).
- UVC 1.5, 4.2.2.1.9 Iris (Absolute) Control: wIris "in units of fstop * 100", and no SET while the
  auto-exposure mode is Auto or Shutter Priority; 4.2.2.1.10 Iris (Relative): 1 opens one step, 0xFF
  closes one, 0 goes to the default, the step size is the device's own.
- uvcvideo (drivers/media/usb/uvc/uvc_ctrl.c, `uvc_ctrl_mappings`) maps CT_IRIS_ABSOLUTE_CONTROL to
  V4L2_CID_IRIS_ABSOLUTE as an unsigned 16-bit value with no conversion, so on a UVC camera the V4L2
  value is the f-number × 100 and larger values *close* the iris, against the V4L2 wording; it clamps a
  written value to the control's GET_MIN/GET_MAX range snapped to GET_RES. Its CT_IRIS_RELATIVE_CONTROL
  has only SET_CUR, so V4L2 reports it write-only with the range 0..0, and `uvc_ctrl_set` clamps every
  step written to it to 0 ("default"): a UVC iris can be driven only through the absolute control.

The mapping is therefore explicit (`IrisMap`, in `v4l2_iris.py`): by default the UVC unit (N = value × 0.01);
``iris_unit=U`` in the URL for another linear unit (N = value × U, e.g. 0.1 for f-number × 10); or
``iris_table=V:N,V:N,...`` for any other driver: measured (value, f-number) points, interpolated in stops
(log N) between them, no request outside the table. A request is checked against the control's min/max and
snapped to its step; one that lands more than 1 % from the f-number asked for is refused naming the nearest
settings. The value is then read back (polled up to ``iris_timeout_s``, default 2 s, for a motorized iris) and
the f-number it maps to returned; auto exposure (Auto or Shutter Priority, where UVC refuses iris writes) is
switched to manual first. A camera with only V4L2_CID_IRIS_RELATIVE needs ``iris_table`` with values that count
steps closed from fully open: the driver first opens fully (+1 written as many times as the table's largest
count plus two, assuming steps past the stop do nothing), then closes step by step and counts; the control
cannot be read, so the f-number returned is the counted one (`settings()["iris"]` says so).
"""

from __future__ import annotations

import errno
import logging
import math
import os
import select
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.camera import register_camera_scheme
from drivers.camera.base import DEFAULT_TIMEOUT_S, Camera, Frame, SequenceTracker, check_timeout_s
from drivers.camera.formats import FORMATS, PixelFormat, format_by_code, fourcc_text, lookup_format
from drivers.camera.v4l2_adapter import (
    BUF_FLAG_ERROR,
    CID_ANALOGUE_GAIN,
    CID_AUTOGAIN,
    CID_EXPOSURE,
    CID_EXPOSURE_ABSOLUTE,
    CID_EXPOSURE_AUTO,
    CID_GAIN,
    CID_IRIS_ABSOLUTE,
    CID_IRIS_RELATIVE,
    EXPOSURE_ABSOLUTE_UNIT_US,
    EXPOSURE_AUTO,
    EXPOSURE_MANUAL,
    EXPOSURE_SHUTTER_PRIORITY,
    ControlInfo,
    LinuxpyAdapter,
    RawBuffer,
    RawFormat,
    V4L2Adapter,
)
from drivers.camera.v4l2_iris import (
    IRIS_HOME_EXTRA_STEPS,
    IRIS_POLL_S,
    IRIS_TIMEOUT_S,
    IRIS_TOLERANCE_REL,
    UVC_IRIS_UNIT,
    IrisMap,
)
from drivers.camera.v4l2_params import (
    URL_PARAMS,
    _check_number,
    _check_roi,
    _float_param,
    _int_param,
    _iris_table_param,
    _roi_param,
)
from drivers.url import DeviceURL, parse_device_url
from mlaqc.errors import DeviceError, InputError, MlaqcError

log = logging.getLogger(__name__)

BY_ID_DIR = Path("/dev/v4l/by-id")
DISCONNECT_ERRNOS = frozenset({errno.ENODEV, errno.EIO, errno.ENXIO, errno.ESHUTDOWN})
UNSUPPORTED_ERRNOS = frozenset({errno.EINVAL, errno.ENOTTY, errno.ENODATA, errno.EOPNOTSUPP})
REOPEN_POLL_S = 0.05
SPURIOUS_WAKE_S = 0.001


@dataclass
class _Desired:
    """Settings the user asked for; re-applied after every (re)open."""

    pixel_format: PixelFormat | None = None
    width: int | None = None
    height: int | None = None
    roi: tuple[int, int, int, int] | None = None
    exposure_us: float | None = None
    gain: float | None = None
    f_number: float | None = None


class V4L2Camera(Camera):
    """A V4L2 capture device delivering raw frames; see the module docstring for the fault handling."""

    def __init__(self, path: str, *, url: str | None = None, pixel_format: str | None = None,
                 width: int | None = None, height: int | None = None, exposure_us: float | None = None,
                 gain: float | None = None, roi: tuple[int, int, int, int] | None = None, buffers: int = 4,
                 settle_frames: int = 1, exposure_unit_us: float | None = None, f_number: float | None = None,
                 iris_unit: float | None = None, iris_table: Sequence[tuple[int, float]] | None = None,
                 iris_timeout_s: float | None = None,
                 adapter_factory: Callable[[str], V4L2Adapter] = LinuxpyAdapter,
                 by_id_dir: str | os.PathLike[str] = BY_ID_DIR) -> None:
        super().__init__(url or f"v4l2://{path}")
        self._path = path
        if f_number is not None:
            _check_number("f_number", f_number, positive=True)
        if iris_unit is not None and iris_table:
            raise InputError("give the iris mapping as iris_unit or as iris_table, not both")
        self._iris = IrisMap(UVC_IRIS_UNIT if iris_unit is None else iris_unit, tuple(iris_table or ()))
        self._iris_timeout_s = IRIS_TIMEOUT_S if iris_timeout_s is None else check_timeout_s(iris_timeout_s)
        self._iris_steps: int | None = None  # relative iris: steps closed from fully open, None = not known
        self._desired = _Desired(lookup_format(pixel_format) if pixel_format else None, width, height, roi,
                                 exposure_us, gain, f_number)
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
            f_number=_float_param(text, "f_number", p("f_number"), positive=True),
            iris_unit=_float_param(text, "iris_unit", p("iris_unit"), positive=True),
            iris_table=_iris_table_param(text, p("iris_table")),
            iris_timeout_s=_float_param(text, "iris_timeout_s", p("iris_timeout_s"), positive=True),
        )
        if kwargs["iris_unit"] is not None and kwargs["iris_table"] is not None:
            raise InputError(f"camera URL {text!r} gives both iris_unit and iris_table; the iris mapping is one or "
                             "the other")
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
        if self._desired.f_number is not None:
            self.set_f_number(self._desired.f_number)
        self._sequence.reset()

    def _release(self) -> None:
        """Drop the adapter whatever state the device is in."""
        adapter, self._adapter = self._adapter, None
        self._streaming = False
        self._roi_active = False
        self._iris_steps = None  # a relative iris is found again from its open stop
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

    # ----------------------------------------------------------------- iris

    @property
    def f_number(self) -> float:
        """The main lens' f-number read back from the iris control (a relative one: as counted); NaN when the
        camera is closed, has no iris control, or its value is outside the iris table."""
        with self._lock:
            if self._adapter is None:
                return math.nan
            with self._device_op("reading the iris"):
                return self._read_f_number()

    def set_f_number(self, f_number: float) -> float:
        """Set the main lens' iris to f/N through the camera's iris control; return the f-number read back.

        InputError (one sentence) when the camera has no iris control or f/N is outside what it can set;
        DeviceError when the iris does not read back f/N within `iris_timeout_s`. See the module docstring."""
        _check_number("f_number", f_number, positive=True)
        with self._lock:
            self._require_open("setting the iris")
            with self._device_op("setting the iris"):
                back = self._apply_f_number(float(f_number))
            self._desired.f_number = float(f_number)
            self._start_settling()
            return back

    @property
    def has_iris(self) -> bool:
        """Whether the open camera has an iris control (absolute or relative) that `set_f_number` can drive."""
        with self._lock:
            return self._adapter is not None and self._iris_cid() is not None

    def _iris_cid(self) -> int | None:
        """V4L2_CID_IRIS_ABSOLUTE if present, else V4L2_CID_IRIS_RELATIVE, else None."""
        return next((cid for cid in (CID_IRIS_ABSOLUTE, CID_IRIS_RELATIVE) if cid in self._controls), None)

    def _apply_f_number(self, f_number: float) -> float:
        cid = self._iris_cid()
        if cid is None:
            raise InputError(f"camera {self.name} has no iris control (V4L2_CID_IRIS_ABSOLUTE or _RELATIVE), so it "
                             f"cannot set f/{f_number:.4g}; set the lens by hand (through_focus.iris = 'manual')")
        info = self._controls[cid]
        if cid == CID_IRIS_RELATIVE:
            return self._step_iris(f_number, info)
        raw = self._iris_setting(f_number, info)
        self._allow_iris()
        self._adapter.set_control(cid, raw)
        return self._await_iris(raw, f_number)

    def _iris_setting(self, f_number: float, info: ControlInfo) -> int:
        """The control value for f/N: in the control's range, on its step grid, within IRIS_TOLERANCE_REL."""
        iris = self._iris
        exact = iris.value(f_number)
        span = iris.f_range(info.minimum, info.maximum)
        if exact is None or span is None or not info.minimum - 0.5 <= exact <= info.maximum + 0.5:
            where = f"f/{span[0]:.3g}..f/{span[1]:.3g}" if span else "nothing the mapping covers"
            raise InputError(f"f/{f_number:.4g} is outside camera {self.name}'s iris range {where} (control "
                             f"{info.name!r} {info.minimum}..{info.maximum}, {iris.describe()})")
        step = max(info.step, 1)
        below = info.minimum + math.floor((exact - info.minimum) / step) * step
        candidates = [v for v in (below, below + step)
                      if info.minimum <= v <= info.maximum and math.isfinite(iris.f_number(v))]
        raw = min(candidates, key=lambda v: abs(iris.f_number(v) - f_number), default=round(exact))
        if not abs(iris.f_number(raw) - f_number) <= IRIS_TOLERANCE_REL * f_number:
            nearest = " and ".join(f"f/{iris.f_number(v):.3g}" for v in candidates)
            raise InputError(f"camera {self.name}'s iris cannot be set to f/{f_number:.4g}: its nearest settings are "
                             f"{nearest} (control {info.name!r} in steps of {step}, {iris.describe()})")
        return int(raw)

    def _allow_iris(self) -> None:
        """UVC refuses iris writes in auto exposure modes Auto and Shutter Priority: switch those to manual."""
        if CID_EXPOSURE_AUTO in self._controls and \
                self._adapter.get_control(CID_EXPOSURE_AUTO) in (EXPOSURE_AUTO, EXPOSURE_SHUTTER_PRIORITY):
            self._switch_off(CID_EXPOSURE_AUTO, EXPOSURE_MANUAL, "auto exposure")

    def _await_iris(self, raw: int, f_number: float) -> float:
        """Poll the absolute iris until it reads back f/N (a motorized iris takes time); its f-number."""
        deadline = time.monotonic() + self._iris_timeout_s
        while True:
            back = self._adapter.get_control(CID_IRIS_ABSOLUTE)
            got = self._iris.f_number(back)
            if back == raw or abs(got - f_number) <= IRIS_TOLERANCE_REL * f_number:
                return got
            if time.monotonic() >= deadline:
                reads = f"f/{got:.3g}" if math.isfinite(got) else f"{back}, outside the iris table"
                raise DeviceError(f"camera {self.name}'s iris did not reach f/{f_number:.4g} within "
                                  f"{self._iris_timeout_s:g} s (it reads {reads})")
            time.sleep(min(IRIS_POLL_S, max(0.0, deadline - time.monotonic())))

    def _step_iris(self, f_number: float, info: ControlInfo) -> float:
        """A relative-only iris: open to the stop once, then close or open step by step, counting."""
        iris = self._iris
        if not iris.table:
            raise InputError(f"camera {self.name} has only a relative iris control, whose step size the driver does "
                             "not say; give the f-number after each step as iris_table=0:2.8,1:4,... (steps closed "
                             "from fully open) in the camera URL")
        if iris.table[0][0] < 0:
            raise InputError(f"camera {self.name} has only a relative iris control, so iris_table's values count steps "
                             f"closed from fully open and cannot be negative ({iris.describe()})")
        if info.minimum > -1 or info.maximum < 1:
            raise InputError(f"camera {self.name}'s relative iris control accepts only {info.minimum}..{info.maximum}, "
                             "not the +1/-1 steps that move it (uvcvideo reports 0..0 and turns every step into 0), "
                             "so its iris cannot be driven from here")
        exact = iris.value(f_number)
        steps = None if exact is None else round(exact)
        if steps is None or steps < 0 or not abs(iris.f_number(steps) - f_number) <= IRIS_TOLERANCE_REL * f_number:
            lo, hi = iris.f_range(0, iris.table[-1][0]) or (math.nan, math.nan)
            lower, upper = (0, 0) if exact is None else (math.floor(exact), math.ceil(exact))
            why = (f"outside its iris table f/{lo:.3g}..f/{hi:.3g}" if exact is None or steps < 0 else
                   f"between its steps f/{iris.f_number(lower):.3g} and f/{iris.f_number(upper):.3g}")
            raise InputError(f"camera {self.name}'s relative iris cannot be set to f/{f_number:.4g}: it is {why} "
                             f"({iris.describe()})")
        self._allow_iris()
        at, self._iris_steps = self._iris_steps, None  # unknown until every step is written
        if at is None:
            for _ in range(iris.table[-1][0] + IRIS_HOME_EXTRA_STEPS):
                self._adapter.set_control(CID_IRIS_RELATIVE, 1)
            at = 0
        while at != steps:
            self._adapter.set_control(CID_IRIS_RELATIVE, -1 if steps > at else 1)
            at += 1 if steps > at else -1
        self._iris_steps = steps
        return iris.f_number(steps)

    def _read_f_number(self) -> float:
        """The iris' f-number as read back (relative: as counted), NaN if there is none or it is unknown."""
        cid = self._iris_cid()
        if cid is None:
            return math.nan
        if cid == CID_IRIS_RELATIVE:
            known = self._iris_steps is not None and self._iris.table
            return self._iris.f_number(self._iris_steps) if known else math.nan
        return self._iris.f_number(self._adapter.get_control(cid))

    def _iris_settings(self) -> dict[str, Any] | None:
        """What a sidecar should say about the iris control and its mapping; None without one."""
        cid = self._iris_cid()
        if cid is None:
            return None
        info = self._controls[cid]
        if cid == CID_IRIS_ABSOLUTE:
            span = self._iris.f_range(info.minimum, info.maximum)
        else:  # steps closed from fully open, as far as the table goes
            span = self._iris.f_range(0, self._iris.table[-1][0]) if self._iris.table else None
        return {"control": "absolute" if cid == CID_IRIS_ABSOLUTE else "relative",
                "control_range": [info.minimum, info.maximum, info.step], "mapping": self._iris.describe(),
                "f_number_range": list(span) if span else None,
                "read_back": "counted steps" if cid == CID_IRIS_RELATIVE else "control value"}

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
                    "f_number": self._read_f_number(), "iris": self._iris_settings(),
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
            if self._iris_cid() is not None:
                extra["f_number"] = self._read_f_number()
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


register_camera_scheme("v4l2", V4L2Camera.from_url, replace=True)
