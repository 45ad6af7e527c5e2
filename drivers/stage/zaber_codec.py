"""Zaber ASCII protocol codec: bytes <-> messages, no I/O, shared by the driver and the simulator.

Command (host -> device): '/' [device [axis [message_id]]] [command words] [':' checksum] '\\n',
e.g. '/1 1 12 move abs 1000'. Device 0 (or none) addresses every device, axis 0 the whole device.
Reply: '@01 1 12 OK BUSY -- 0' = device, axis, optional message id, OK|RJ, BUSY|IDLE, the most
important warning flag ('--' for none), data (a value, several values, or a rejection reason).
Info '#01 0 text' and alert '!01 1 IDLE --' messages complete the set. Optional checksum: the LRC of the
bytes between the leading character and ':', as two upper-case hex digits.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Union

WARNINGS: dict[str, str] = {
    "FD": "Driver Disabled: the driver has disabled itself due to overheating or over-current",
    "FQ": "Encoder Error: the encoder-measured position may be unreliable",
    "FS": "Stalled and Stopped: stalling was detected and the axis has stopped itself",
    "FT": "Excessive Twist: the lockstep group has exceeded the allowable twist and stopped",
    "FB": "Stream Bounds Error: a streamed or sinusoidal motion was terminated by an axis limit",
    "FP": "Interpolated Path Deviation: streamed or sinusoidal motion deviated from its path",
    "FE": "Limit Error: the target limit sensor cannot be reached or is faulty",
    "WH": "Device Not Homed: the device has a position reference but has not been homed",
    "WL": "Unexpected Limit Trigger: a movement was interrupted by an unexpected limit sensor",
    "WV": "Voltage Out of Range: the supply voltage is outside the recommended range",
    "WT": "Controller Temperature High: the controller is near its maximum temperature",
    "WM": "Displaced When Stationary: the axis was moved by an external force while stationary",
    "WR": "No Reference Position: the axis has no reference position and must be homed",
    "NC": "Manual Control: axis is busy due to manual control via the knob or joystick",
    "NI": "Command Interrupted: a movement was interrupted by a new command or by stop",
    "ND": "Stream Discontinuity: a stream moved slower than requested due to a missing command",
    "NU": "Setting Update Pending: a setting is pending an update or a reset is pending",
    "NJ": "Joystick Calibrating: the joystick is calibrating",
}

REJECTIONS: dict[str, str] = {
    "AGAIN": "the command cannot be processed right now; send it again",
    "BADAXIS": "the axis number is larger than the number of axes on the device",
    "BADCOMMAND": "the command or setting is not valid or not allowed now",
    "BADDATA": "the data in the command is invalid or out of range",
    "BADMESSAGEID": "the message id is not 0-99",
    "DEVICEONLY": "an axis number was given to a device-only command",
    "FULL": "the device has run out of permanent storage",
    "LOCKSTEP": "the axis is part of a lockstep group and cannot move alone",
    "NOACCESS": "the command or setting needs a higher access level",
    "PARKED": "the device is parked and cannot move",
    "STATUSBUSY": "the device is busy and cannot be made idle",
}

NO_WARNING = "--"


def warning_text(flag: str) -> str:
    """Zaber's meaning of a two-letter warning flag."""
    return WARNINGS.get(flag, "unknown warning flag")


def rejection_text(reason: str) -> str:
    """Zaber's meaning of a rejection reason (RJ data)."""
    return REJECTIONS.get(reason, "unknown rejection reason")


def warning_rank(flag: str) -> int:
    """Importance of a flag: faults (F) 3, warnings (W) 2, notes (N) 1, none 0."""
    return {"F": 3, "W": 2, "N": 1}.get(flag[:1], 0) if flag != NO_WARNING else 0


def lrc(payload: bytes) -> int:
    """Zaber checksum: two's complement of the byte sum, modulo 256."""
    return (-sum(payload)) & 0xFF


# ---------------------------------------------------------------- commands


@dataclass(frozen=True)
class Command:
    """One host command; `text` is the command words ('' = status query)."""

    device: int = 0
    axis: int = 0
    message_id: int | None = None
    text: str = ""


def encode_command(device: int, axis: int, text: str, *, message_id: int | None = None,
                   checksum: bool = False) -> bytes:
    """'/1 1 12 move abs 1000\\n' (message id and ':XX' checksum optional)."""
    if not (0 <= device <= 254 and 0 <= axis <= 9):
        raise ValueError(f"Zaber address {device} {axis} out of range")
    if message_id is not None and not 0 <= message_id <= 99:
        raise ValueError(f"Zaber message id {message_id} is not 0-99")
    if any(c in text for c in "\r\n/:@#!"):
        raise ValueError(f"Zaber command {text!r} contains a reserved character")
    words = [str(device), str(axis)] + ([f"{message_id:02d}"] if message_id is not None else []) + ([text] if text else [])
    body = " ".join(words)
    suffix = f":{lrc(body.encode()):02X}" if checksum else ""
    return f"/{body}{suffix}\n".encode("ascii")


class ZaberSyntaxError(ValueError):
    """A command line the device cannot parse (or whose checksum is wrong)."""


_CHECKSUM_RE = re.compile(r"^(.*):([0-9A-Fa-f]{2})$")


def _strip_checksum(body: str) -> str:
    """Verify and remove a trailing ':XX' checksum, if present."""
    match = _CHECKSUM_RE.match(body)
    if not match:
        return body
    if (sum(match.group(1).encode()) + int(match.group(2), 16)) & 0xFF:
        raise ZaberSyntaxError(f"bad checksum in {body!r}")
    return match.group(1)


def parse_command(line: bytes | str) -> Command:
    """Parse '/1 1 12 move abs 1000' (device, axis, id optional); ZaberSyntaxError if not a command."""
    text = (line.decode("ascii", "replace") if isinstance(line, bytes) else line).strip()
    if not text.startswith("/"):
        raise ZaberSyntaxError(f"not a Zaber command: {text!r}")
    tokens = _strip_checksum(text[1:]).split()
    numbers: list[int] = []
    while tokens and tokens[0].isdigit() and len(numbers) < 3:
        numbers.append(int(tokens.pop(0)))
    device = numbers[0] if numbers else 0
    axis = numbers[1] if len(numbers) > 1 else 0
    message_id = numbers[2] if len(numbers) > 2 else None
    return Command(device, axis, message_id, " ".join(tokens))


# ---------------------------------------------------------------- device messages


@dataclass(frozen=True)
class Reply:
    """'@01 1 12 OK BUSY -- 0': the device's answer to one command."""

    device: int
    axis: int
    message_id: int | None
    flag: str
    status: str
    warning: str
    data: str

    @property
    def rejected(self) -> bool:
        """True for 'RJ' (the command was not executed)."""
        return self.flag == "RJ"

    @property
    def busy(self) -> bool:
        """True while the addressed axis (or any axis, for axis 0) is moving."""
        return self.status == "BUSY"

    @property
    def values(self) -> list[str]:
        """The data field split into words."""
        return self.data.split()


@dataclass(frozen=True)
class Alert:
    """'!01 1 IDLE --': unsolicited, e.g. motion finished (only when comm.alert is on)."""

    device: int
    axis: int
    status: str
    warning: str
    data: str = ""


@dataclass(frozen=True)
class Info:
    """'#01 0 text': extra lines after some replies (help, stream info)."""

    device: int
    axis: int
    message_id: int | None
    text: str


@dataclass(frozen=True)
class Garbage:
    """A line that is no Zaber message (noise, a corrupted or checksum-failed reply)."""

    raw: bytes


Message = Union[Reply, Alert, Info, Garbage]

_REPLY_RE = re.compile(r"^@(\d{2,3}) (\d)(?: (\d{1,2}))? (OK|RJ) (BUSY|IDLE) (--|[A-Z]{2})(?: (.*))?$")
_ALERT_RE = re.compile(r"^!(\d{2,3}) (\d) (BUSY|IDLE) (--|[A-Z]{2})(?: (.*))?$")
_INFO_RE = re.compile(r"^#(\d{2,3}) (\d)(?: (\d{1,2}))?(?: (.*))?$")


def parse_message(line: bytes | str) -> Message | None:
    """Decode one device line (line ending optional); None for a blank line."""
    raw = line.encode("latin-1", "replace") if isinstance(line, str) else bytes(line)
    text = raw.decode("ascii", "replace").strip()
    if not text:
        return None
    try:
        body = text[:1] + _strip_checksum(text[1:])
    except ZaberSyntaxError:
        return Garbage(raw.rstrip(b"\r\n"))
    match = _REPLY_RE.match(body)
    if match:
        d, a, mid, flag, status, warning, data = match.groups()
        return Reply(int(d), int(a), int(mid) if mid else None, flag, status, warning, data or "")
    match = _ALERT_RE.match(body)
    if match:
        d, a, status, warning, data = match.groups()
        return Alert(int(d), int(a), status, warning, data or "")
    match = _INFO_RE.match(body)
    if match:
        d, a, mid, info = match.groups()
        return Info(int(d), int(a), int(mid) if mid else None, info or "")
    return Garbage(raw.rstrip(b"\r\n"))


def _finish(lead: str, body: str, checksum: bool) -> bytes:
    """Lead character + body (+ checksum) + CRLF."""
    suffix = f":{lrc(body.encode()):02X}" if checksum else ""
    return f"{lead}{body}{suffix}\r\n".encode("ascii")


def encode_reply(reply: Reply, *, checksum: bool = False) -> bytes:
    """Format a Reply as the device sends it."""
    mid = f" {reply.message_id:02d}" if reply.message_id is not None else ""
    body = f"{reply.device:02d} {reply.axis}{mid} {reply.flag} {reply.status} {reply.warning} {reply.data}".rstrip()
    return _finish("@", body, checksum)


def encode_alert(alert: Alert, *, checksum: bool = False) -> bytes:
    """Format an Alert."""
    body = f"{alert.device:02d} {alert.axis} {alert.status} {alert.warning} {alert.data}".rstrip()
    return _finish("!", body, checksum)


def encode_info(info: Info, *, checksum: bool = False) -> bytes:
    """Format an Info line."""
    mid = f" {info.message_id:02d}" if info.message_id is not None else ""
    return _finish("#", f"{info.device:02d} {info.axis}{mid} {info.text}".rstrip(), checksum)
