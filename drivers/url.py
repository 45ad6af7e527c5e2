"""Device URLs: one string names a camera or a stage in configs and on the command line.

Examples: ``v4l2:///dev/v4l/by-id/usb-cam?format=Y16``, ``serial:///dev/ttyUSB0?protocol=grbl&baud=115200``,
``mock://``, ``sim+grbl://``, ``sim+zaber://?latency_ms=5``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from urllib.parse import parse_qsl, urlsplit

from mlaqc.errors import InputError


@dataclass(frozen=True)
class DeviceURL:
    """A parsed device URL: `scheme` (e.g. 'serial', 'sim+grbl'), `path` (device node or ''), `params`."""

    scheme: str
    path: str = ""
    params: dict[str, str] = field(default_factory=dict)

    @property
    def kind(self) -> str:
        """The scheme's first part: 'sim+grbl' -> 'sim'."""
        return self.scheme.split("+", 1)[0]

    @property
    def variant(self) -> str:
        """The scheme's second part, or '': 'sim+grbl' -> 'grbl'."""
        parts = self.scheme.split("+", 1)
        return parts[1] if len(parts) > 1 else ""

    def param(self, name: str, default: str | None = None) -> str | None:
        """The query parameter `name`, or `default`."""
        return self.params.get(name, default)

    def __str__(self) -> str:
        query = "&".join(f"{k}={v}" for k, v in self.params.items())
        return f"{self.scheme}://{self.path}" + (f"?{query}" if query else "")


def parse_device_url(text: str) -> DeviceURL:
    """Parse a device URL; raise InputError naming the URL if it has no scheme or a bad query."""
    if "://" not in text:
        raise InputError(f"device URL {text!r} has no scheme; expected e.g. 'mock://', 'sim+grbl://' or 'serial:///dev/ttyUSB0'")
    parts = urlsplit(text)
    if not parts.scheme:
        raise InputError(f"device URL {text!r} has no scheme")
    try:
        params = dict(parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query)))
    except ValueError:
        raise InputError(f"device URL {text!r} has a malformed query string {parts.query!r}") from None
    return DeviceURL(scheme=parts.scheme.lower(), path=(parts.netloc + parts.path), params=params)
