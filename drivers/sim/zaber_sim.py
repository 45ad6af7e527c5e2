"""A simulated chain of Zaber ASCII devices (via zaber_codec) on a pty.

What it models: devices and axes addressed as '/device axis [id] command'; replies '@dd a [id] OK|RJ
BUSY|IDLE flag data' echoing the message id; 'home' (axis moves to 0 at `speed_mm_s`, WR cleared when
done), 'move abs|rel N', 'move min|max' at `speed_mm_s` (BUSY while moving, position interpolated),
'stop'/'estop' (NI set on an interrupted move), 'get pos|limit.min|limit.max|maxspeed|system.axiscount',
'warnings [clear]', empty command = status. Controller-side limits: targets outside 0..limit.max are
rejected with BADDATA; axes without a reference (WR) reject absolute moves with BADCOMMAND (a choice of
this simulator); an unknown device is silent, an unknown axis BADAXIS, an unknown command BADCOMMAND.

Zaber-specific fault injection (see drivers.sim.base for the common ones):
- `fail_next(reason="BADDATA", match="")`: the next command whose text starts with `match` is
  rejected with `reason`;
- `fault_mid_move(flag="FS", at_fraction=0.5)`: the axis that starts the next move stops there and
  reports the fault flag (FS = stalled and stopped) until 'warnings clear'.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

from drivers.stage import zaber_codec as zc

from .base import MidMoveFault, Motion, SimDevice


@dataclass
class SimAxis:
    """One simulated axis: position in microsteps, motion, reference and warning flags."""

    device: int
    number: int
    limit_max: int
    speed_steps_s: float
    pos: float
    referenced: bool = False
    homing: bool = False
    motion: Motion | None = None
    flags: set[str] = field(default_factory=set)

    def position(self, now: float) -> float:
        """Position in microsteps at `now`."""
        return self.motion.position(now)[0] if self.motion is not None else self.pos

    def halt(self, now: float) -> None:
        """Stop where the axis is now."""
        self.pos = self.position(now)
        self.motion = None
        self.homing = False

    def flag(self) -> str:
        """The most important warning flag, or '--'."""
        if not self.flags:
            return zc.NO_WARNING
        return max(sorted(self.flags), key=zc.warning_rank)


class ZaberSim(SimDevice):
    """Simulated Zaber devices; `axes` lists (device, axis) pairs, e.g. ((1, 1), (1, 2)) or ((1, 1), (2, 1))."""

    name = "zaber-sim"

    def __init__(self, *, axes: Sequence[tuple[int, int]] = ((1, 1), (1, 2)), microstep_um: float = 0.1,
                 speed_mm_s: float = 50.0, travel_mm: float | Sequence[float] = 200.0, start_mm: float | None = None,
                 latency_s: float = 0.0, referenced: bool = False) -> None:
        super().__init__(latency_s=latency_s)
        self.order = [(int(d), int(a)) for d, a in axes]
        travels = [float(travel_mm)] * len(self.order) if isinstance(travel_mm, (int, float)) else list(travel_mm)
        if speed_mm_s <= 0 or microstep_um <= 0 or len(travels) != len(self.order) or min(travels) <= 0:
            raise ValueError("speed_mm_s, microstep_um and travel_mm must be positive (one travel per axis)")
        self.microstep_um = microstep_um
        steps_per_mm = 1000.0 / microstep_um
        travel_of = dict(zip(self.order, travels))
        self.devices: dict[int, list[SimAxis]] = {}
        for device in sorted({d for d, _ in self.order}):
            count = max(a for d, a in self.order if d == device)
            self.devices[device] = []
            for n in range(1, count + 1):
                travel = travel_of.get((device, n), max(travels))
                start = travel / 2 if start_mm is None else start_mm
                self.devices[device].append(SimAxis(
                    device, n, round(travel * steps_per_mm), speed_mm_s * steps_per_mm, start * steps_per_mm,
                    referenced=referenced, flags=set() if referenced else {"WR"}))
        self._fail_next: tuple[str, str] | None = None
        self._line = bytearray()

    # ------------------------------------------------------------ observation (thread-safe)

    def axis(self, device: int, number: int) -> SimAxis:
        """The simulated axis object (read it under `with sim.locked()` or via the helpers)."""
        return self.devices[device][number - 1]

    @property
    def position_mm(self) -> tuple[float, ...]:
        """Positions (mm) of the axes in the order given to the constructor."""
        with self._lock:
            now = time.monotonic()
            self._advance(now)
            return tuple(self.axis(d, a).position(now) * self.microstep_um / 1000.0 for d, a in self.order)

    @property
    def busy(self) -> bool:
        """True while any axis moves."""
        with self._lock:
            self._advance(time.monotonic())
            return self._any_busy()

    def flags(self, device: int, number: int) -> set[str]:
        """Current warning flags of one axis."""
        with self._lock:
            return set(self.axis(device, number).flags)

    def wait_busy(self, timeout_s: float = 2.0) -> bool:
        """Block until some axis is moving."""
        return self.wait_for(self._any_busy, timeout_s)

    def _any_busy(self) -> bool:
        """True while any axis moves (lock held)."""
        return any(ax.motion is not None for axes in self.devices.values() for ax in axes)

    # ------------------------------------------------------------ Zaber-specific faults

    def fail_next(self, reason: str = "BADDATA", match: str = "") -> None:
        """Reject the next command whose text starts with `match` with `reason`."""
        with self._lock:
            self._fail_next = (reason, match)

    def fault_mid_move(self, flag: str = "FS", at_fraction: float = 0.5) -> None:
        """The axis starting the next move stops at `at_fraction` of it and reports `flag`."""
        self._arm(MidMoveFault("fault", at_fraction, flag))

    def _clear_protocol_faults(self) -> None:
        """Disarm fail_next."""
        self._fail_next = None

    # ------------------------------------------------------------ time

    def _all_axes(self) -> list[SimAxis]:
        """Every axis of every device."""
        return [ax for axes in self.devices.values() for ax in axes]

    def _next_timer(self, now: float) -> float | None:
        """End of the next axis motion."""
        ends = [ax.motion.t_end for ax in self._all_axes() if ax.motion is not None]
        return min(ends) if ends else None

    def _advance(self, now: float) -> None:
        """Apply due faults and finished motions."""
        for fault in self._due_faults(now):
            self._apply_fault(fault)
        for ax in self._all_axes():
            if ax.motion is not None and now >= ax.motion.t_end:
                ax.pos = ax.motion.target[0]
                ax.motion = None
                if ax.homing:
                    ax.homing, ax.referenced = False, True
                    ax.flags -= {"WR", "WH"}
                self._notify()

    def _apply_fault(self, fault: MidMoveFault) -> None:
        """Stall the axis (flag) or pull the cable."""
        if fault.kind == "disconnect":
            for ax in self._all_axes():
                ax.halt(fault.due or time.monotonic())
            self._hangup = True
            return
        axis = fault.owner
        if isinstance(axis, SimAxis):
            axis.halt(fault.due or time.monotonic())
            axis.flags.add(str(fault.code))
            self._notify()

    # ------------------------------------------------------------ input

    def _on_bytes(self, data: bytes, now: float) -> None:
        """Build lines; each complete line is one command."""
        for byte in data:
            if byte in (0x0A, 0x0D):
                if self._line:
                    self._on_line(self._line.decode("ascii", "replace"), now)
                self._line.clear()
            elif len(self._line) < 512:
                self._line.append(byte)

    def _on_line(self, text: str, now: float) -> None:
        """Execute one command on every addressed device and queue the replies."""
        self.received_lines.append(text)
        try:
            cmd = zc.parse_command(text)
        except zc.ZaberSyntaxError:
            return  # devices ignore lines that are not commands or fail their checksum
        devices = sorted(self.devices) if cmd.device == 0 else [cmd.device] if cmd.device in self.devices else []
        for device in devices:
            self._emit(zc.encode_reply(self._execute(device, cmd, now)), now)

    def _execute(self, device: int, cmd: zc.Command, now: float) -> zc.Reply:
        """Run one command on one device and build its reply."""
        axes = self.devices[device]
        if cmd.axis > len(axes):
            return self._reply(device, cmd, axes, "RJ", "BADAXIS")
        targets = axes if cmd.axis == 0 else [axes[cmd.axis - 1]]
        if self._fail_next is not None and cmd.text.startswith(self._fail_next[1]):
            reason, self._fail_next = self._fail_next[0], None
            return self._reply(device, cmd, targets, "RJ", reason)
        try:
            data = self._run(cmd.text.split(), targets, cmd.axis == 0, now)
        except _Reject as rej:
            return self._reply(device, cmd, targets, "RJ", rej.reason)
        return self._reply(device, cmd, targets, "OK", data)

    def _reply(self, device: int, cmd: zc.Command, targets: list[SimAxis], flag: str, data: str) -> zc.Reply:
        """Reply with the targets' busy status and most important warning."""
        busy = any(ax.motion is not None for ax in targets)
        warning = max((ax.flag() for ax in targets), key=zc.warning_rank, default=zc.NO_WARNING)
        return zc.Reply(device, cmd.axis, cmd.message_id, flag, "BUSY" if busy else "IDLE", warning, data)

    # ------------------------------------------------------------ commands

    def _run(self, words: list[str], targets: list[SimAxis], device_level: bool, now: float) -> str:
        """Execute command words on the target axes; return the reply data or raise _Reject."""
        if not words:
            return "0"
        head = words[0]
        if head == "home" and len(words) == 1:
            for ax in targets:
                self._start(ax, 0.0, now, homing=True)
            return "0"
        if head == "move":
            return self._move(words[1:], targets, now)
        if head in ("stop", "estop") and len(words) == 1:
            for ax in targets:
                if ax.motion is not None:
                    ax.flags.add("NI")
                ax.halt(now)
            self._notify()
            return "0"
        if head == "get" and len(words) == 2:
            return self._get(words[1], targets, device_level, now)
        if head == "warnings":
            return self._warnings(words[1:], targets)
        raise _Reject("BADCOMMAND")

    def _move(self, args: list[str], targets: list[SimAxis], now: float) -> str:
        """'move abs|rel N' or 'move min|max'."""
        for ax in targets:
            goal = self._goal(args, ax, now)
            if not ax.referenced:
                raise _Reject("BADCOMMAND")
            if not 0 <= goal <= ax.limit_max:
                raise _Reject("BADDATA")
        for ax in targets:
            self._start(ax, self._goal(args, ax, now), now)
        return "0"

    def _goal(self, args: list[str], ax: SimAxis, now: float) -> float:
        """Target microsteps of a move command, or _Reject('BADDATA'/'BADCOMMAND')."""
        if args in (["min"], ["max"]):
            return 0.0 if args[0] == "min" else float(ax.limit_max)
        if len(args) != 2 or args[0] not in ("abs", "rel"):
            raise _Reject("BADCOMMAND")
        try:
            value = int(args[1])
        except ValueError:
            raise _Reject("BADDATA") from None
        return float(value) if args[0] == "abs" else round(ax.position(now)) + value

    def _start(self, ax: SimAxis, goal: float, now: float, *, homing: bool = False) -> None:
        """Start (or redirect) an axis towards `goal`."""
        if ax.motion is not None:
            ax.flags.add("NI")
        ax.pos = ax.position(now)
        ax.homing = homing
        if homing:
            ax.referenced = False
        ax.motion = Motion((ax.pos,), (goal,), now, ax.speed_steps_s)
        self._activate_faults(ax.motion, ax)
        self._notify()

    def _get(self, setting: str, targets: list[SimAxis], device_level: bool, now: float) -> str:
        """'get pos', 'get limit.max', ... (space-separated per axis for device-level queries)."""
        if setting == "system.axiscount" and device_level:
            return str(len(targets))
        values = {"pos": lambda ax: round(ax.position(now)), "limit.max": lambda ax: ax.limit_max,
                  "limit.min": lambda ax: 0, "maxspeed": lambda ax: round(ax.speed_steps_s * 1.6384)}
        if setting not in values:
            raise _Reject("BADCOMMAND")
        return " ".join(str(values[setting](ax)) for ax in targets)

    def _warnings(self, args: list[str], targets: list[SimAxis]) -> str:
        """'warnings' lists the flags ('NN F1 F2'); 'warnings clear' lists then clears them."""
        if args not in ([], ["clear"]):
            raise _Reject("BADCOMMAND")
        flags = sorted({f for ax in targets for f in ax.flags})
        data = " ".join([f"{len(flags):02d}"] + flags)
        if args:
            for ax in targets:
                ax.flags = {"WR"} if not ax.referenced else set()
        return data


class _Reject(Exception):
    """Internal: reject the command with `reason`."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason
