"""The camera interface every driver implements: `Frame` (one raw image plus its provenance) and `Camera`.

Drivers return raw sensor data only (monochrome or Bayer mosaic, uint16, values in 0 .. 2**bits - 1);
demosaicing, calibration and everything after belong to `mlaqc`.
"""

from __future__ import annotations

import abc
import math
import numbers
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mlaqc.errors import InputError

CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
DEFAULT_TIMEOUT_S = 5.0


@dataclass(frozen=True, eq=False)
class Frame:
    """One raw frame with everything a sidecar needs: sequence, both timestamps, exposure/gain read back.

    `data` is 2-D uint16 (H, W); `bits` its significant bits; `cfa` None for monochrome or the Bayer
    pattern of the top-left 2x2 cell; `gain` is in device units; `extra` holds driver diagnostics such as
    `sequence_gap` (frames lost just before this one) and `error_frames_discarded`.
    """

    data: np.ndarray
    bits: int
    pixel_format: str
    cfa: str | None
    sequence: int
    device_timestamp_s: float
    host_timestamp_s: float
    exposure_us: float
    gain: float
    device: str
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Reject malformed frames at construction so no stage downstream has to guess."""
        if not isinstance(self.data, np.ndarray) or self.data.ndim != 2 or self.data.dtype != np.uint16:
            kind = getattr(self.data, "dtype", type(self.data))
            raise ValueError(f"Frame.data must be a 2-D uint16 array, got {kind} with shape "
                             f"{getattr(self.data, 'shape', None)}")
        if not 1 <= self.bits <= 16:
            raise ValueError(f"Frame.bits must be 1..16, got {self.bits}")
        if self.cfa is not None and self.cfa not in CFA_PATTERNS:
            raise ValueError(f"Frame.cfa must be None or one of {CFA_PATTERNS}, got {self.cfa!r}")

    @property
    def height(self) -> int:
        """Rows in pixels."""
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        """Columns in pixels."""
        return int(self.data.shape[1])

    @property
    def max_value(self) -> int:
        """Largest value a pixel can hold at this bit depth (the saturation level)."""
        return (1 << self.bits) - 1


class SequenceTracker:
    """Counts frames lost between consecutive device sequence numbers (wrap-around aware)."""

    def __init__(self, modulus: int = 1 << 32) -> None:
        self.modulus = modulus
        self.last: int | None = None
        self.lost_total = 0
        self.gap_events = 0

    def reset(self) -> None:
        """Forget the baseline, e.g. after a stream restart or when lost frames are expected."""
        self.last = None

    def update(self, sequence: int) -> int | None:
        """Record `sequence`; return frames lost since the previous one, or None if it went backwards."""
        last, self.last = self.last, sequence
        if last is None:
            return 0
        gap = (sequence - last - 1) % self.modulus
        if gap >= self.modulus // 2:
            return None
        if gap:
            self.lost_total += gap
            self.gap_events += 1
        return gap


def check_timeout_s(timeout_s: float) -> float:
    """Validate a wait deadline: a positive finite number of seconds."""
    if isinstance(timeout_s, bool) or not isinstance(timeout_s, numbers.Real) or not math.isfinite(timeout_s) \
            or timeout_s <= 0:
        raise InputError(f"timeout_s must be a positive number of seconds, got {timeout_s!r}")
    return float(timeout_s)


class Camera(abc.ABC):
    """A raw-frame camera; a context manager that opens on enter and closes on exit.

    `open()` is idempotent and returns the camera. Setters switch the matching auto mode off and return
    the value read back from the device. Every wait takes `timeout_s` and raises DeviceError past it.
    """

    def __init__(self, url: str) -> None:
        self._url = url

    @property
    def url(self) -> str:
        """The device URL this camera was made from."""
        return self._url

    @property
    def name(self) -> str:
        """Human-readable device name for messages and sidecars (defaults to the URL)."""
        return self._url

    @property
    @abc.abstractmethod
    def is_open(self) -> bool:
        """True while the device is open."""

    @property
    @abc.abstractmethod
    def bit_depth(self) -> int:
        """Significant bits per pixel of the current pixel format."""

    @abc.abstractmethod
    def open(self) -> Camera:
        """Open the device and apply the configured settings; no-op if already open."""

    @abc.abstractmethod
    def close(self) -> None:
        """Stop streaming and release the device; safe to call twice."""

    def reopen(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> Camera:
        """Close and open again (drivers override to find a re-plugged device)."""
        check_timeout_s(timeout_s)
        self.close()
        return self.open()

    @abc.abstractmethod
    def settings(self) -> dict[str, Any]:
        """Current settings as read back from the device."""

    @abc.abstractmethod
    def set_exposure_us(self, exposure_us: float) -> float:
        """Switch auto exposure off, set the exposure; return the exposure read back in µs."""

    @abc.abstractmethod
    def set_gain(self, gain: float) -> float:
        """Switch auto gain off, set the gain (device units); return the gain read back."""

    @abc.abstractmethod
    def set_format(self, pixel_format: str) -> str:
        """Select a raw pixel format by name ('Y16', 'Y10', 'RGGB', ...); return the format read back."""

    def set_roi(self, x: int, y: int, width: int, height: int) -> tuple[int, int, int, int]:
        """Restrict readout to a region of interest; return (x, y, width, height) read back."""
        raise InputError(f"camera {self.name} does not support a region of interest")

    @abc.abstractmethod
    def capture(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> Frame:
        """Return the next frame completed after this call, waiting at most `timeout_s`."""

    def stream(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> Iterator[Frame]:
        """Yield frames for live view, each waited for at most `timeout_s`; stop by closing the iterator."""
        check_timeout_s(timeout_s)
        while True:
            yield self.capture(timeout_s)

    def __enter__(self) -> Camera:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "open" if self.is_open else "closed"
        return f"<{type(self).__name__} {self.url} {state}>"
