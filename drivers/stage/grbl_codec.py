"""GRBL 1.1 serial protocol codec: bytes <-> messages, no I/O, shared by the driver and the simulator.

Host -> controller: G-code lines ending in '\\n', '$' system commands ('$H' home, '$X' unlock) and
single real-time bytes ('?' status, '!' feed hold, '~' resume, 0x18 soft reset) that GRBL picks out of
the stream wherever they appear. Controller -> host: 'ok', 'error:N', unsolicited 'ALARM:N',
'[MSG:...]' and other '[KEY:...]' feedback, '$N=value' settings, status reports '<Idle|MPos:...|FS:...>'
and the reset banner "Grbl 1.1h ['$' for help]". Everything else is garbage (line noise), kept raw.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Union

# ---------------------------------------------------------------- real-time bytes (host -> controller)

STATUS_QUERY = b"?"
FEED_HOLD = b"!"
CYCLE_START = b"~"
SOFT_RESET = b"\x18"
REALTIME_BYTES = frozenset({ord("?"), ord("!"), ord("~"), 0x18})

AXIS_LETTERS = ("X", "Y", "Z", "A", "B", "C")  # report order of MPos/WPos values
LINE_MAX_CHARS = 80  # GRBL's serial line buffer (LINE_BUFFER_SIZE) on the ATmega328p
VERSION = "1.1h"

# ---------------------------------------------------------------- GRBL 1.1 message tables

ERROR_TEXT: dict[int, tuple[str, str]] = {
    1: ("Expected command letter", "G-code words consist of a letter and a value. Letter was not found."),
    2: ("Bad number format", "Missing the expected G-code word value or numeric value format is not valid."),
    3: ("Invalid statement", "Grbl '$' system command was not recognized or supported."),
    4: ("Value < 0", "Negative value received for an expected positive value."),
    5: ("Setting disabled", "Homing cycle failure. Homing is not enabled via settings."),
    6: ("Value < 3 usec", "Minimum step pulse time must be greater than 3usec."),
    7: ("EEPROM read fail. Using defaults", "An EEPROM read failed. Auto-restoring affected EEPROM to default values."),
    8: ("Not idle", "Grbl '$' command cannot be used unless Grbl is IDLE. Ensures smooth operation during a job."),
    9: ("G-code lock", "G-code commands are locked out during alarm or jog state."),
    10: ("Homing not enabled", "Soft limits cannot be enabled without homing also enabled."),
    11: ("Line overflow", "Max characters per line exceeded. Received command line was not executed."),
    12: ("Step rate > 30kHz", "Grbl '$' setting value cause the step rate to exceed the maximum supported."),
    13: ("Check Door", "Safety door detected as opened and door state initiated."),
    14: ("Line length exceeded", "Build info or startup line exceeded EEPROM line length limit. Line not stored."),
    15: ("Travel exceeded", "Jog target exceeds machine travel. Jog command has been ignored."),
    16: ("Invalid jog command", "Jog command has no '=' or contains prohibited g-code."),
    17: ("Setting disabled", "Laser mode requires PWM output."),
    20: ("Unsupported command", "Unsupported or invalid g-code command found in block."),
    21: ("Modal group violation", "More than one g-code command from same modal group found in block."),
    22: ("Undefined feed rate", "Feed rate has not yet been set or is undefined."),
    23: ("Invalid gcode ID:23", "G-code command in block requires an integer value."),
    24: ("Invalid gcode ID:24", "More than one g-code command that requires axis words found in block."),
    25: ("Invalid gcode ID:25", "Repeated g-code word found in block."),
    26: ("Invalid gcode ID:26", "No axis words found in block for g-code command or current modal state which requires them."),
    27: ("Invalid gcode ID:27", "Line number value is invalid."),
    28: ("Invalid gcode ID:28", "G-code command is missing a required value word."),
    29: ("Invalid gcode ID:29", "G59.x work coordinate systems are not supported."),
    30: ("Invalid gcode ID:30", "G53 only allowed with G0 and G1 motion modes."),
    31: ("Invalid gcode ID:31", "Axis words found in block when no command or current modal state uses them."),
    32: ("Invalid gcode ID:32", "G2 and G3 arcs require at least one in-plane axis word."),
    33: ("Invalid gcode ID:33", "Motion command target is invalid."),
    34: ("Invalid gcode ID:34", "Arc radius value is invalid."),
    35: ("Invalid gcode ID:35", "G2 and G3 arcs require at least one in-plane offset word."),
    36: ("Invalid gcode ID:36", "Unused value words found in block."),
    37: ("Invalid gcode ID:37", "G43.1 dynamic tool length offset is not assigned to configured tool length axis."),
    38: ("Invalid gcode ID:38", "Tool number greater than max supported value."),
}

ALARM_TEXT: dict[int, tuple[str, str]] = {
    1: ("Hard limit", "Hard limit has been triggered. Machine position is likely lost due to sudden halt. Re-homing is highly recommended."),
    2: ("Soft limit", "G-code motion target exceeds machine travel. Machine position retained. Alarm may be safely unlocked."),
    3: ("Abort during cycle", "Reset while in motion. Machine position is likely lost due to sudden halt. Re-homing is highly recommended."),
    4: ("Probe fail", "Probe is not in the expected initial state before starting probe cycle."),
    5: ("Probe fail", "Probe did not contact the workpiece within the programmed travel for G38.2 and G38.4."),
    6: ("Homing fail", "The active homing cycle was reset."),
    7: ("Homing fail", "Safety door was opened during homing cycle."),
    8: ("Homing fail", "Pull off travel failed to clear limit switch. Try increasing pull-off setting or check wiring."),
    9: ("Homing fail", "Could not find limit switch within search distances. Try increasing max travel, decreasing pull-off distance, or check wiring."),
}

CRITICAL_ALARMS = frozenset({1, 2})  # GRBL locks out everything but '?' and reset after these
POSITION_LOST_ALARMS = frozenset({1, 3, 6, 7, 8, 9})  # machine position can no longer be trusted
STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")


def error_text(code: int) -> str:
    """GRBL's short message and description for error:N, e.g. 'Unsupported command: Unsupported ... block'."""
    short, desc = ERROR_TEXT.get(code, ("Unknown error", "Not in the GRBL 1.1 error table."))
    return f"{short}: {desc.rstrip('.')}"


def alarm_text(code: int) -> str:
    """GRBL's short message and description for ALARM:N."""
    short, desc = ALARM_TEXT.get(code, ("Unknown alarm", "Not in the GRBL 1.1 alarm table."))
    return f"{short}: {desc.rstrip('.')}"


# ---------------------------------------------------------------- controller -> host messages


@dataclass(frozen=True)
class Ok:
    """'ok': the last line was parsed and executed (or queued, for motion)."""


@dataclass(frozen=True)
class Error:
    """'error:N': the last line was rejected; `text` is GRBL's message for N."""

    code: int

    @property
    def text(self) -> str:
        """GRBL's message for this code."""
        return error_text(self.code)


@dataclass(frozen=True)
class Alarm:
    """'ALARM:N': unsolicited; motion stopped and G-code is locked out until unlock, home or reset."""

    code: int

    @property
    def text(self) -> str:
        """GRBL's message for this code."""
        return alarm_text(self.code)

    @property
    def position_lost(self) -> bool:
        """True when GRBL says the machine position is likely lost (re-home)."""
        return self.code in POSITION_LOST_ALARMS


@dataclass(frozen=True)
class Banner:
    """The reset banner "Grbl 1.1h ['$' for help]": the controller just (re)started."""

    version: str = VERSION


@dataclass(frozen=True)
class Feedback:
    """A bracketed push message '[KEY:text]', e.g. kind 'MSG' for '[MSG:Caution: Unlocked]'."""

    kind: str
    text: str


@dataclass(frozen=True)
class Setting:
    """One '$N=value' line of a '$$' settings dump."""

    number: int
    value: str


@dataclass(frozen=True)
class Status:
    """A real-time status report '<State|MPos:x,y,z|FS:f,s|...>'; positions in mm, feed in mm/min."""

    state: str
    substate: int | None = None
    mpos_mm: tuple[float, ...] | None = None
    wpos_mm: tuple[float, ...] | None = None
    wco_mm: tuple[float, ...] | None = None
    feed_mm_min: float | None = None
    spindle_rpm: float | None = None
    buffer: tuple[int, int] | None = None
    line_number: int | None = None
    pins: str | None = None
    overrides: tuple[int, ...] | None = None
    extra: tuple[tuple[str, str], ...] = field(default=())

    @property
    def idle(self) -> bool:
        """True when the controller is idle (nothing moving, nothing queued to run)."""
        return self.state == "Idle"

    def machine_position(self, wco_mm: tuple[float, ...] | None) -> tuple[float, ...] | None:
        """Machine position: MPos, or WPos + WCO (this report's WCO, else `wco_mm`); None if unknown."""
        if self.mpos_mm is not None:
            return self.mpos_mm
        offset = self.wco_mm if self.wco_mm is not None else wco_mm
        if self.wpos_mm is None or offset is None:
            return None
        return tuple(w + o for w, o in zip(self.wpos_mm, offset))


@dataclass(frozen=True)
class Garbage:
    """A line that is none of the above (noise, a corrupted reply, another firmware's chatter)."""

    raw: bytes


Message = Union[Ok, Error, Alarm, Banner, Feedback, Setting, Status, Garbage]

_BANNER_RE = re.compile(r"^Grbl\w*\s+(\S+)\s+\[.*help\]$")
_STATUS_RE = re.compile(r"^<([A-Za-z]+)(?::(\d+))?((?:\|[^|<>]*)*)>$")
_FEEDBACK_RE = re.compile(r"^\[([A-Za-z0-9]+):(.*)\]$")
_SETTING_RE = re.compile(r"^\$(\d+)=(\S*)$")


def parse_line(line: bytes | str) -> Message | None:
    """Decode one controller line (with or without its line ending); None for a blank line."""
    raw = line.encode("latin-1", "replace") if isinstance(line, str) else bytes(line)
    text = raw.decode("ascii", "replace").strip()
    if not text:
        return None
    try:
        parsed = _parse_text(text)
    except ValueError:
        parsed = None
    return parsed if parsed is not None else Garbage(raw.rstrip(b"\r\n"))


def _parse_text(text: str) -> Message | None:
    """Parse a stripped line; None (or ValueError) when it matches no GRBL message form."""
    if text == "ok":
        return Ok()
    if text.startswith("error:"):
        return Error(int(text[6:]))
    if text.startswith("ALARM:"):
        return Alarm(int(text[6:]))
    if text.startswith("<"):
        return parse_status(text)
    match = _FEEDBACK_RE.match(text)
    if match:
        return Feedback(match.group(1), match.group(2))
    match = _BANNER_RE.match(text)
    if match:
        return Banner(match.group(1))
    match = _SETTING_RE.match(text)
    if match:
        return Setting(int(match.group(1)), match.group(2))
    return None


def _floats(text: str) -> tuple[float, ...]:
    """'1.000,-2.5,0' -> (1.0, -2.5, 0.0); ValueError on anything non-finite or malformed."""
    values = tuple(float(v) for v in text.split(","))
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"non-finite value in {text!r}")
    return values


def parse_status(text: str) -> Status | None:
    """Parse a GRBL 1.1 status report '<Run|MPos:1,2,3|FS:500,0>'; None if it is not one."""
    match = _STATUS_RE.match(text.strip())
    if not match or match.group(1) not in STATES:
        return None
    fields: dict[str, object] = {"state": match.group(1)}
    if match.group(2) is not None:
        fields["substate"] = int(match.group(2))
    extra = []
    for item in filter(None, match.group(3).split("|")):
        key, _, value = item.partition(":")
        if not _status_field(key, value, fields):
            extra.append((key, value))
    return Status(extra=tuple(extra), **fields)  # type: ignore[arg-type]


def _status_field(key: str, value: str, fields: dict[str, object]) -> bool:
    """Store one known status field in `fields`; False for fields kept raw in `extra`."""
    if key in ("MPos", "WPos", "WCO"):
        fields[{"MPos": "mpos_mm", "WPos": "wpos_mm", "WCO": "wco_mm"}[key]] = _floats(value)
    elif key == "FS":
        feed, speed = _floats(value)
        fields["feed_mm_min"], fields["spindle_rpm"] = feed, speed
    elif key == "F":
        fields["feed_mm_min"] = _floats(value)[0]
    elif key == "Bf":
        blocks, chars = (int(v) for v in value.split(","))
        fields["buffer"] = (blocks, chars)
    elif key == "Ln":
        fields["line_number"] = int(value)
    elif key == "Pn":
        fields["pins"] = value
    elif key == "Ov":
        fields["overrides"] = tuple(int(v) for v in value.split(","))
    else:
        return False
    return True


# ---------------------------------------------------------------- controller-side encoders (simulator)


def _num(value: float) -> str:
    """GRBL's 3-decimal mm formatting, never '-0.000'."""
    text = f"{value:.3f}"
    return "0.000" if text == "-0.000" else text


def _vec(values: tuple[float, ...]) -> str:
    """'1.000,2.000,0.000'."""
    return ",".join(_num(v) for v in values)


def encode_ok() -> bytes:
    """'ok\\r\\n'."""
    return b"ok\r\n"


def encode_error(code: int) -> bytes:
    """'error:N\\r\\n'."""
    return f"error:{code}\r\n".encode()


def encode_alarm(code: int) -> bytes:
    """'ALARM:N\\r\\n'."""
    return f"ALARM:{code}\r\n".encode()


def encode_banner(version: str = VERSION) -> bytes:
    """The reset banner, preceded by the blank line GRBL prints first."""
    return f"\r\nGrbl {version} ['$' for help]\r\n".encode()


def encode_feedback(kind: str, text: str) -> bytes:
    """'[KIND:text]\\r\\n', e.g. encode_feedback('MSG', 'Caution: Unlocked')."""
    return f"[{kind}:{text}]\r\n".encode()


def encode_setting(number: int, value: str) -> bytes:
    """'$N=value\\r\\n'."""
    return f"${number}={value}\r\n".encode()


def encode_status(status: Status) -> bytes:
    """Format a Status the way GRBL 1.1 prints it, fields in GRBL's order."""
    parts = [status.state + (f":{status.substate}" if status.substate is not None else "")]
    if status.mpos_mm is not None:
        parts.append("MPos:" + _vec(status.mpos_mm))
    if status.wpos_mm is not None:
        parts.append("WPos:" + _vec(status.wpos_mm))
    if status.buffer is not None:
        parts.append(f"Bf:{status.buffer[0]},{status.buffer[1]}")
    if status.line_number is not None:
        parts.append(f"Ln:{status.line_number}")
    if status.feed_mm_min is not None:
        feed = f"{status.feed_mm_min:g}"
        parts.append(f"FS:{feed},{status.spindle_rpm:g}" if status.spindle_rpm is not None else f"F:{feed}")
    if status.pins:
        parts.append(f"Pn:{status.pins}")
    if status.wco_mm is not None:
        parts.append("WCO:" + _vec(status.wco_mm))
    if status.overrides is not None:
        parts.append("Ov:" + ",".join(str(v) for v in status.overrides))
    parts.extend(f"{k}:{v}" for k, v in status.extra)
    return ("<" + "|".join(parts) + ">\r\n").encode()


# ---------------------------------------------------------------- host-side encoders (driver)


def encode_line(text: str) -> bytes:
    """One command line, '\\n'-terminated; refuses real-time bytes, newlines and over-long lines."""
    if any(ord(c) in REALTIME_BYTES or c in "\r\n" for c in text):
        raise ValueError(f"GRBL command line {text!r} contains a real-time byte or a line break")
    if len(text) > LINE_MAX_CHARS:
        raise ValueError(f"GRBL command line {text!r} is longer than {LINE_MAX_CHARS} characters")
    return text.encode("ascii") + b"\n"


def encode_move(x_mm: float, y_mm: float, *, feed_mm_min: float | None = None) -> bytes:
    """Absolute move in machine coordinates: 'G90 G53 G0 X.. Y..' (rapid) or 'G90 G53 G1 X.. Y.. F..'."""
    if not (math.isfinite(x_mm) and math.isfinite(y_mm)):
        raise ValueError(f"move target ({x_mm}, {y_mm}) is not finite")
    if feed_mm_min is None:
        return encode_line(f"G90 G53 G0 X{_num(x_mm)} Y{_num(y_mm)}")
    return encode_line(f"G90 G53 G1 X{_num(x_mm)} Y{_num(y_mm)} F{feed_mm_min:g}")


def encode_move_axes(targets: dict[str, float], *, feed_mm_min: float | None = None) -> bytes:
    """Absolute move of any axes in machine coordinates, e.g. {'Z': 40.0, 'A': 1.5} ->
    'G90 G53 G0 Z40 A1.5' (GRBL 1.1 has X, Y, Z; grblHAL and other GRBL ports add A, B, C)."""
    if not targets:
        raise ValueError("a move needs at least one axis")
    words = []
    for letter, value in targets.items():
        if letter not in AXIS_LETTERS:
            raise ValueError(f"{letter!r} is not a GRBL axis letter ({', '.join(AXIS_LETTERS)})")
        if not math.isfinite(value):
            raise ValueError(f"move target {letter}={value} is not finite")
        words.append(f"{letter}{_num(value)}")
    mode = "G0" if feed_mm_min is None else "G1"
    feed = "" if feed_mm_min is None else f" F{feed_mm_min:g}"
    return encode_line(f"G90 G53 {mode} {' '.join(words)}{feed}")


def encode_home() -> bytes:
    """'$H': run the homing cycle; 'ok' comes when homing has finished."""
    return encode_line("$H")


def encode_unlock() -> bytes:
    """'$X': kill the alarm lock without homing."""
    return encode_line("$X")


# ---------------------------------------------------------------- host -> controller parsing (simulator)


class GcodeError(ValueError):
    """A command line GRBL would reject; `code` is the error:N it answers with."""

    def __init__(self, code: int) -> None:
        super().__init__(f"error:{code} ({error_text(code)})")
        self.code = code


@dataclass(frozen=True)
class Block:
    """One parsed G-code block: its (letter, value) words in order."""

    words: tuple[tuple[str, float], ...]

    def values(self, letter: str) -> list[float]:
        """Every value of `letter` in the block."""
        return [v for k, v in self.words if k == letter]

    def get(self, letter: str) -> float | None:
        """The value of a word that appears at most once, or None."""
        found = self.values(letter)
        return found[0] if found else None


_WORD_RE = re.compile(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))")


def parse_block(text: str) -> Block:
    """Parse a G-code line into words; raise GcodeError with GRBL's code on a malformed line."""
    if len(text) > LINE_MAX_CHARS:
        raise GcodeError(11)
    body = re.sub(r"\([^)]*\)", "", text.split(";", 1)[0]).upper()
    body = "".join(body.split())
    words: list[tuple[str, float]] = []
    pos = 0
    while pos < len(body):
        if not body[pos].isalpha():
            raise GcodeError(1)
        match = _WORD_RE.match(body, pos)
        if not match:
            raise GcodeError(2)
        words.append((match.group(1), float(match.group(2))))
        pos = match.end()
    return Block(tuple(words))


def is_realtime(byte: int) -> bool:
    """True for the single bytes GRBL acts on immediately, wherever they appear in the stream."""
    return byte in REALTIME_BYTES
