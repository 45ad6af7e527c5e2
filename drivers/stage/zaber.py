"""Zaber ASCII XY stage: two axes, as device 1 axes 1 and 2 or as devices 1 and 2, on one serial port.

Same layering as GRBL: zaber_codec (messages), transport (port), this state machine.
- Every command carries a message id (1-99, rolling) and only the reply with that device, axis and id
  answers it; anything else (stale replies, replies to stop(), alerts, info, noise) is logged and skipped.
- connect: a status query per device, then 'warnings' per axis. The stage counts as homed at connect
  when no axis reports WR/WH (a Zaber axis keeps its reference while powered).
- home: 'warnings clear', 'home' on each axis, poll until both are IDLE.
- move: 'move abs <microsteps>' on X then Y, poll until both are IDLE, then check 'get pos' == target.
- stop (any thread): '/<device> 0 stop' to each device, written without the command lock; the command
  thread then polls until both axes are IDLE.
- RJ replies -> DeviceError with the reason; F* fault flags -> StageAlarm (stage unhomed);
  WR/WH during motion -> StageAlarm; other flags are logged.
Positions convert with `microstep_um` (µm per microstep): steps = round(mm * 1000 / microstep_um).
Auxiliary axes (`aux`: {"z": AxisAddress(1, 3), ...}, URL ``aux=z:1.3,a:2.1,b:2.2``) are further axes on
the same chain: homed with X and Y, moved by `move_aux` ('move abs' on each, poll, check 'get pos').
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from dataclasses import dataclass
from typing import Mapping, Sequence

from mlaqc.errors import DeviceError, InputError

from . import zaber_codec as zc
from .base import Expired, Limits, NotHomedError, Stage, StageAlarm, StopRequested, _Closeable, format_aux
from .transport import Transport

log = logging.getLogger(__name__)

UNREFERENCED = ("WR", "WH")


@dataclass(frozen=True)
class AxisAddress:
    """Where one stage axis lives on the Zaber chain."""

    device: int
    axis: int

    def __str__(self) -> str:
        return f"device {self.device} axis {self.axis}"


def parse_axes(text: str) -> tuple[AxisAddress, AxisAddress]:
    """'1.1,1.2' (one device, two axes) or '1,2' (two devices, axis 1) -> (x, y) addresses; InputError if bad."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2:
        raise InputError(f"Zaber axes {text!r} must name two axes, e.g. '1.1,1.2' or '1,2'")
    addresses = []
    for part in parts:
        device, _, axis = part.partition(".")
        if not device.isdigit() or (axis and not axis.isdigit()):
            raise InputError(f"Zaber axis {part!r} in {text!r} is not 'device' or 'device.axis'")
        addr = AxisAddress(int(device), int(axis or 1))
        if not (1 <= addr.device <= 99 and 1 <= addr.axis <= 9):
            raise InputError(f"Zaber axis {part!r} in {text!r} is out of range (device 1-99, axis 1-9)")
        addresses.append(addr)
    if addresses[0] == addresses[1]:
        raise InputError(f"Zaber axes {text!r} name the same axis twice")
    return addresses[0], addresses[1]


def parse_aux_axes(text: str, xy: tuple[AxisAddress, AxisAddress] = ()) -> dict[str, AxisAddress]:
    """'z:1.3,a:2.1,b:2.2' -> {"z": AxisAddress(1, 3), ...}; InputError if malformed or reusing an axis."""
    from .base import AUX_AXES

    out: dict[str, AxisAddress] = {}
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        name, sep, where = part.partition(":")
        name = name.strip().lower()
        if not sep or name not in AUX_AXES:
            raise InputError(f"Zaber auxiliary axis {part!r} in {text!r} must be NAME:DEVICE.AXIS with NAME one of "
                             f"{', '.join(AUX_AXES)}, e.g. 'z:1.3'")
        if name in out:
            raise InputError(f"Zaber auxiliary axes {text!r} name axis {name!r} twice")
        device, _, axis = where.strip().partition(".")
        if not device.isdigit() or (axis and not axis.isdigit()):
            raise InputError(f"Zaber auxiliary axis {part!r} in {text!r} is not 'NAME:device' or 'NAME:device.axis'")
        addr = AxisAddress(int(device), int(axis or 1))
        if not (1 <= addr.device <= 99 and 1 <= addr.axis <= 9):
            raise InputError(f"Zaber auxiliary axis {part!r} in {text!r} is out of range (device 1-99, axis 1-9)")
        if addr in xy or addr in out.values():
            raise InputError(f"Zaber auxiliary axis {part!r} in {text!r} reuses {addr}")
        out[name] = addr
    return out


class ZaberStage(Stage):
    """An XY stage made of two Zaber ASCII axes on `port` (any pyserial URL or device path)."""

    protocol = "Zaber"

    def __init__(self, port: str, *, url: str | None = None, baud: int = 115200, limits: Limits = Limits(),
                 axes: tuple[AxisAddress, AxisAddress] = (AxisAddress(1, 1), AxisAddress(1, 2)),
                 microstep_um: float = 0.1, connect_timeout_s: float = 2.0, poll_s: float = 0.05,
                 stop_timeout_s: float = 2.0, checksum: bool = False, name: str | None = None,
                 owned: Sequence[_Closeable] = (), aux: Mapping[str, AxisAddress] | None = None,
                 aux_limits: Mapping[str, tuple[float, float]] | None = None) -> None:
        aux = dict(aux or {})
        if aux_limits is None:
            aux_limits = {name: (0.0, 100.0) for name in aux}
        if set(aux) != set(aux_limits):
            raise InputError(f"Zaber auxiliary axes {sorted(aux)} and their limits {sorted(aux_limits)} differ")
        super().__init__(url=url or port, limits=limits, name=name, poll_s=poll_s,
                         stop_timeout_s=stop_timeout_s, owned=owned, aux_limits=aux_limits)
        if not microstep_um > 0:
            raise InputError(f"Zaber microstep_um {microstep_um!r} must be positive")
        self.port = port
        self.axes = axes
        self.aux = {name: aux[name] for name in self.aux_axes}
        self._every_axis = (*axes, *self.aux.values())
        self.microstep_um = microstep_um
        self.connect_timeout_s = connect_timeout_s
        self.checksum = checksum
        self.garbage_lines = 0
        self._transport = Transport(port, baud=baud, owner=self.name)
        self._ids = itertools.cycle(range(1, 100))
        self._ids_lock = threading.Lock()

    @property
    def devices(self) -> list[int]:
        """Distinct device numbers used by the axes (X, Y and any auxiliary ones)."""
        return sorted({a.device for a in self._every_axis})

    # ------------------------------------------------------------ units

    def to_steps(self, mm: float) -> int:
        """mm -> microsteps."""
        return round(mm * 1000.0 / self.microstep_um)

    def to_mm(self, steps: float) -> float:
        """microsteps -> mm."""
        return steps * self.microstep_um / 1000.0

    # ------------------------------------------------------------ lifecycle hooks

    def _open_locked(self) -> None:
        """Open the port, check every device answers, read whether the axes have a reference."""
        deadline = time.monotonic() + self.connect_timeout_s
        self._transport.open()
        self._transport.discard_input()
        for device in self.devices:
            self._command(AxisAddress(device, 0), "", deadline)
        self._homed = not any(self._unreferenced(addr, deadline) for addr in self._every_axis)
        self._position_locked(deadline)
        if self.aux:
            self._aux_position_locked(deadline)

    def _close_port(self) -> None:
        """Close the port."""
        self._transport.close()

    # ------------------------------------------------------------ exchanges

    def _next_id(self) -> int:
        """Next message id (1-99, rolling), thread-safe."""
        with self._ids_lock:
            return next(self._ids)

    def _command(self, addr: AxisAddress, text: str, deadline: float, *, check: bool = True) -> zc.Reply:
        """Send one command and return its reply; RJ -> DeviceError, F* flag -> StageAlarm (if `check`)."""
        message_id = self._next_id()
        self._transport.write(zc.encode_command(addr.device, addr.axis, text, message_id=message_id,
                                                checksum=self.checksum))
        reply = self._await_reply(addr, message_id, deadline, f"reply from {addr} to {text or 'a status query'!r}")
        if reply.rejected:
            reason = reply.data or "?"
            raise self._fail(DeviceError, f"rejected {text!r} on {addr} with {reason} ({zc.rejection_text(reason)})")
        if check:
            self._check_flag(addr, reply.warning)
        return reply

    def _await_reply(self, addr: AxisAddress, message_id: int, deadline: float, waiting_for: str) -> zc.Reply:
        """Read until the reply with this device, axis and id; skip and log everything else."""
        while True:
            line = self._transport.read_line(deadline)
            if line is None:
                raise Expired(waiting_for)
            msg = zc.parse_message(line)
            if isinstance(msg, zc.Reply) and (msg.device, msg.axis, msg.message_id) == (addr.device, addr.axis, message_id):
                return msg
            self._skip(msg)

    def _skip(self, msg: zc.Message | None) -> None:
        """Log a message nobody waits for."""
        if isinstance(msg, zc.Garbage):
            self.garbage_lines += 1
            log.warning("%s: ignoring garbage line %r", self.name, msg.raw)
        elif msg is not None:
            log.debug("%s: skipping %s", self.name, msg)

    def _drain(self) -> None:
        """Skip whatever arrived while no command was running."""
        while (line := self._transport.read_line(time.monotonic())) is not None:
            self._skip(zc.parse_message(line))

    def _check_flag(self, addr: AxisAddress, flag: str) -> None:
        """Faults raise StageAlarm (and unhome); losing the reference while homed too; others are logged."""
        if flag == zc.NO_WARNING:
            return
        if flag.startswith("F"):
            self._homed = False
            raise self._fail(StageAlarm, f"reported fault {flag} ({zc.warning_text(flag)}) on {addr} and is no longer homed")
        if flag in UNREFERENCED:
            if self._homed:
                self._homed = False
                raise self._fail(StageAlarm, f"reported {flag} ({zc.warning_text(flag)}) on {addr} and is no longer homed")
            return
        if flag.startswith("W"):
            log.warning("%s: %s reports %s (%s)", self.name, addr, flag, zc.warning_text(flag))

    def _unreferenced(self, addr: AxisAddress, deadline: float) -> bool:
        """True if the axis reports WR or WH in its warning list."""
        reply = self._command(addr, "warnings", deadline, check=False)
        return any(flag in UNREFERENCED for flag in reply.values[1:])

    # ------------------------------------------------------------ commands

    def _home_locked(self, deadline: float, gen: int) -> None:
        """Clear warnings, 'home' every axis, wait until all are IDLE."""
        self._drain()
        for addr in self._every_axis:
            self._command(addr, "warnings clear", deadline, check=False)
        if self._stopped(gen):
            raise StopRequested()
        for addr in self._every_axis:
            self._command(addr, "home", deadline)
        self._await_idle(deadline, gen, "IDLE after homing")
        if any(self._unreferenced(addr, deadline) for addr in self._every_axis):
            raise self._fail(DeviceError, "still has no reference position after homing")
        self._homed = True
        self._position_locked(deadline)
        if self.aux:
            self._aux_position_locked(deadline)

    def _move_locked(self, x_mm: float, y_mm: float, deadline: float, gen: int) -> None:
        """'move abs' on both axes, wait for IDLE, check the position read back is the target."""
        self._drain()
        if not self._homed:
            raise self._fail(NotHomedError, "is no longer homed; call home() first")
        target = (self.to_steps(x_mm), self.to_steps(y_mm))
        try:
            for addr, steps in zip(self.axes, target):
                if self._stopped(gen):
                    break  # stop() arrived between the axis commands: do not start the next axis
                self._command(addr, f"move abs {steps}", deadline)
        except DeviceError:
            self._halt_now()
            raise
        self._await_idle(deadline, gen, "IDLE at the target")
        steps_now = tuple(self._get_pos(addr, deadline) for addr in self.axes)
        self._set_position(self.to_mm(steps_now[0]), self.to_mm(steps_now[1]))
        if steps_now != target:
            raise self._fail(DeviceError, f"stopped at ({self.to_mm(steps_now[0]):.4f}, {self.to_mm(steps_now[1]):.4f}) mm instead of the target")

    def _move_aux_locked(self, targets: dict[str, float], deadline: float, gen: int) -> None:
        """'move abs' on each auxiliary axis, wait for IDLE, check the positions read back are the targets."""
        self._drain()
        if not self._homed:
            raise self._fail(NotHomedError, "is no longer homed; call home() first")
        steps = {name: self.to_steps(v) for name, v in targets.items()}
        try:
            for name, target in steps.items():
                if self._stopped(gen):
                    break
                self._command(self.aux[name], f"move abs {target}", deadline)
        except DeviceError:
            self._halt_now()
            raise
        self._await_idle(deadline, gen, "IDLE at the target")
        now = {name: self._get_pos(self.aux[name], deadline) for name in steps}
        self._set_aux({name: self.to_mm(v) for name, v in now.items()})
        if now != steps:
            raise self._fail(DeviceError, f"stopped at {format_aux({n: self.to_mm(v) for n, v in now.items()})} "
                                          "instead of the target")

    def _aux_position_locked(self, deadline: float) -> dict[str, float]:
        """Every auxiliary axis' position in mm."""
        self._drain()
        aux = {name: self.to_mm(self._get_pos(addr, deadline)) for name, addr in self.aux.items()}
        self._set_aux(aux)
        return aux

    def _await_idle(self, deadline: float, gen: int, waiting_for: str) -> None:
        """Poll every axis until IDLE; stop() -> settle and StopRequested; Expired at the deadline."""
        while True:
            if self._stopped(gen):
                self._settle_locked(time.monotonic() + self.stop_timeout_s)
                raise StopRequested()
            if not any(self._command(addr, "", deadline).busy for addr in self._every_axis):
                return
            self._pause(deadline)
            if time.monotonic() >= deadline:
                raise Expired(waiting_for)

    def _get_pos(self, addr: AxisAddress, deadline: float) -> int:
        """'get pos' on one axis, in microsteps."""
        reply = self._command(addr, "get pos", deadline)
        try:
            return int(reply.values[0])
        except (IndexError, ValueError):
            raise self._fail(DeviceError, f"answered 'get pos' on {addr} with {reply.data!r}, not a position") from None

    def _position_locked(self, deadline: float) -> tuple[float, float]:
        """Both axes' positions in mm."""
        self._drain()
        x_mm, y_mm = (self.to_mm(self._get_pos(addr, deadline)) for addr in self.axes)
        self._set_position(x_mm, y_mm)
        return (x_mm, y_mm)

    def _busy_locked(self, deadline: float) -> bool:
        """True if any axis reports BUSY."""
        self._drain()
        return any(self._command(addr, "", deadline).busy for addr in self._every_axis)

    # ------------------------------------------------------------ stopping

    def _halt_now(self) -> None:
        """'/<device> 0 stop' to each device (no message id: its reply is skipped as unsolicited)."""
        for device in self.devices:
            self._transport.write(zc.encode_command(device, 0, "stop", checksum=self.checksum))

    def _settle_locked(self, deadline: float) -> None:
        """Stop again (an axis may have started after the first stop) and poll until every axis is IDLE."""
        self._halt_now()
        while any(self._command(addr, "", deadline).busy for addr in self._every_axis):
            time.sleep(max(0.0, min(self.poll_s, deadline - time.monotonic())))
            if time.monotonic() >= deadline:
                raise Expired("IDLE after a stop")

    def _hard_stop(self) -> None:
        """Send stop again and forget the reference (the stop was not confirmed)."""
        self._homed = False
        try:
            self._halt_now()
        except DeviceError as exc:
            log.warning("%s: stop failed: %s", self.name, exc)
