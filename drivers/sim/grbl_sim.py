"""A simulated GRBL 1.1 XY controller that speaks the real serial protocol (via grbl_codec) on a pty.

What it models: power-up/reset banner and homing lock (Alarm until '$H' or '$X'); '$H' homing that
takes time (state Home, 'ok' when done, machine position 0,0); G0/G1/G53/G90/G91/G21/G4 motion queued
with 'ok' at once and executed at `speed_mm_s` (state Run, position interpolated, then Idle); '?' status
reports with MPos (or WPos) and FS, WCO every 10th report; '!' feed hold (Hold:1 for `decel_s`, then
Hold:0), '~' resume, 0x18 soft reset (ALARM:3 if moving, ALARM:6 if homing: position lost; from Idle or
Hold:0 the position is kept); controller-side soft limits (ALARM:2, locked until reset); G-code in
alarm -> error:9; malformed lines -> GRBL's error codes. `axes` is "XYZ" (GRBL 1.1, the default) or
"XYZAB" (a 5-axis port such as grblHAL: A and B words, five MPos values); every axis homes to 0 and has
controller soft limits 0..travel (`travel_mm` for X and Y, `aux_travel_mm` for Z, A, B).

GRBL-specific fault injection (see drivers.sim.base for the common ones):
- `fail_next(code=20, match="")`: the next command line (starting with `match`) gets 'error:code';
- `alarm_mid_move(code=1, at_fraction=0.5)`: during the next move, halt and push 'ALARM:code'
  (1 and 2 also lock the controller until a soft reset, as GRBL does).

Use: `with GrblSim(speed_mm_s=500) as sim: GrblStage(sim.path)`; or `open_stage('sim+grbl://...')`.
"""

from __future__ import annotations

import time
from collections import deque

from drivers.stage import grbl_codec as gc

from .base import MidMoveFault, Motion, SimDevice

SUPPORTED_G = {0, 1, 4, 17, 20, 21, 53, 54, 90, 91, 94}
SUPPORTED_M = {0, 2, 3, 4, 5, 7, 8, 9, 30}
IGNORED_WORDS = set("NSTP")
WCO_EVERY = 10


class GrblSim(SimDevice):
    """Simulated GRBL 1.1 controller with an XYZ (or XYZAB) machine of `travel_mm` (machine coords 0..travel)."""

    name = "grbl-sim"

    def __init__(self, *, speed_mm_s: float = 50.0, homing_speed_mm_s: float | None = None,
                 travel_mm: tuple[float, float] = (200.0, 200.0), start_mm: tuple[float, float] | None = None,
                 latency_s: float = 0.0, decel_s: float = 0.005, soft_limits: bool = True,
                 homing_lock: bool = True, report_wpos: bool = False,
                 wco_mm: tuple[float, ...] = (0.0, 0.0, 0.0), axes: str = "XYZ",
                 aux_travel_mm: float | tuple[float, ...] = 100.0) -> None:
        super().__init__(latency_s=latency_s)
        if speed_mm_s <= 0:
            raise ValueError(f"speed_mm_s {speed_mm_s} must be positive")
        if axes not in ("XYZ", "XYZA", "XYZAB"):
            raise ValueError(f"axes {axes!r} must be XYZ, XYZA or XYZAB")
        self.axes = axes
        n_aux = len(axes) - 2
        aux = (float(aux_travel_mm),) * n_aux if isinstance(aux_travel_mm, (int, float)) else tuple(aux_travel_mm)
        if len(aux) < n_aux or min(aux[:n_aux]) <= 0:
            raise ValueError(f"aux_travel_mm {aux_travel_mm!r} needs a positive travel for each of {axes[2:]}")
        self.aux_travel_mm = aux[:n_aux]
        self.speed_mm_s = speed_mm_s
        self.homing_speed_mm_s = homing_speed_mm_s or speed_mm_s
        self.travel_mm = travel_mm
        self.decel_s = decel_s
        self.soft_limits = soft_limits
        self.homing_lock = homing_lock
        self.report_wpos = report_wpos
        self.wco_mm = tuple(wco_mm) + (0.0,) * (len(axes) - len(wco_mm))
        start = start_mm if start_mm is not None else (travel_mm[0] / 2, travel_mm[1] / 2)
        self._pos: tuple[float, ...] = (start[0], start[1]) + (0.0,) * n_aux
        self._state = "Idle"
        self._hold_sub = 0
        self._hold_until = 0.0
        self._critical = False
        self._homed = False
        self._home_done_at: float | None = None
        self._motion: Motion | None = None
        self._planner: deque[tuple[tuple[float, ...], float]] = deque()
        self._resume: tuple[tuple[float, ...], float] | None = None
        self._line = bytearray()
        self._overflow = False
        self._absolute = True
        self._rapid = True
        self._feed_mm_min: float | None = None
        self._reports = 0
        self._fail_next: tuple[int, str] | None = None
        self.realtime_log: list[bytes] = []
        self.alarms_sent: list[int] = []

    # ------------------------------------------------------------ observation (thread-safe)

    @property
    def state(self) -> str:
        """GRBL state as reported, e.g. 'Idle', 'Run', 'Hold:0', 'Alarm'."""
        with self._lock:
            self._advance(time.monotonic())
            return self._state_text()

    @property
    def position_mm(self) -> tuple[float, float]:
        """True machine position (x, y) now."""
        with self._lock:
            self._advance(time.monotonic())
            pos = self._current(time.monotonic())
            return (pos[0], pos[1])

    @property
    def axes_mm(self) -> tuple[float, ...]:
        """True machine position of every axis (X, Y, Z[, A, B]) now."""
        with self._lock:
            self._advance(time.monotonic())
            return tuple(self._current(time.monotonic()))

    @property
    def homed(self) -> bool:
        """True once a homing cycle completed (until a position-losing alarm)."""
        with self._lock:
            return self._homed

    def wait_state(self, state: str, timeout_s: float = 2.0) -> bool:
        """Block until the reported state starts with `state` (e.g. 'Run', 'Hold:0')."""
        return self.wait_for(lambda: self._state_text().startswith(state), timeout_s)

    # ------------------------------------------------------------ GRBL-specific faults

    def fail_next(self, code: int = 20, match: str = "") -> None:
        """Answer the next command line starting with `match` with 'error:code' instead of running it."""
        with self._lock:
            self._fail_next = (code, match.upper())

    def alarm_mid_move(self, code: int = 1, at_fraction: float = 0.5) -> None:
        """During the next move, at `at_fraction` of its path: halt and push 'ALARM:code'."""
        self._arm(MidMoveFault("alarm", at_fraction, code))

    def _clear_protocol_faults(self) -> None:
        """Disarm fail_next."""
        self._fail_next = None

    # ------------------------------------------------------------ time

    def _power_up(self, now: float) -> None:
        """Banner at power-up; Alarm (homing lock) if configured."""
        if self.homing_lock:
            self._set_state("Alarm")
        self._emit(gc.encode_banner(), now, reply=False)
        if self.homing_lock:
            self._emit(gc.encode_feedback("MSG", "'$H'|'$X' to unlock"), now, reply=False)

    def _next_timer(self, now: float) -> float | None:
        """End of the move, end of homing, end of deceleration."""
        times = []
        if self._motion is not None:
            times.append(self._motion.t_end)
        if self._home_done_at is not None:
            times.append(self._home_done_at)
        if self._state == "Hold" and self._hold_sub == 1:
            times.append(self._hold_until)
        return min(times) if times else None

    def _advance(self, now: float) -> None:
        """Apply everything that happened up to `now`: faults, move ends, homing end, hold complete."""
        for fault in self._due_faults(now):
            self._apply_fault(fault)
        if self._home_done_at is not None and now >= self._home_done_at:
            self._finish_homing(now)
        while self._motion is not None and now >= self._motion.t_end:
            t_end = self._motion.t_end
            self._pos = self._motion.target  # type: ignore[assignment]
            self._motion = None
            self._start_next(t_end)
        if self._state == "Hold" and self._hold_sub == 1 and now >= self._hold_until:
            self._hold_sub = 0
            self._notify()

    def _apply_fault(self, fault: MidMoveFault) -> None:
        """A mid-move fault fires: freeze the axes, then alarm or hang up."""
        assert fault.due is not None
        if self._motion is not None:
            self._pos = self._motion.position(fault.due)  # type: ignore[assignment]
        self._motion = None
        self._planner.clear()
        if fault.kind == "disconnect":
            self._hangup = True
            return
        code = int(fault.code)  # type: ignore[arg-type]
        self._raise_alarm(code, fault.due)

    def _raise_alarm(self, code: int, now: float) -> None:
        """Push ALARM:code and enter Alarm (critical alarms lock out everything until reset)."""
        self._set_state("Alarm")
        if code in gc.POSITION_LOST_ALARMS:
            self._homed = False
        self.alarms_sent.append(code)
        self._emit(gc.encode_alarm(code), now, reply=False)
        if code in gc.CRITICAL_ALARMS:
            self._critical = True
            self._emit(gc.encode_feedback("MSG", "Reset to continue"), now, reply=False)

    def _finish_homing(self, now: float) -> None:
        """Homing cycle completed: machine origin, Idle, 'ok' for the '$H'."""
        self._home_done_at = None
        self._pos = (0.0,) * len(self.axes)
        self._homed = True
        self._set_state("Idle")
        self._emit(gc.encode_ok(), now)

    def _current(self, now: float) -> tuple[float, ...]:
        """Position now (interpolated while moving)."""
        if self._motion is not None:
            return self._motion.position(now)  # type: ignore[return-value]
        return self._pos

    def _set_state(self, state: str, sub: int = 0) -> None:
        """Change state and wake waiters."""
        self._state, self._hold_sub = state, sub
        self._notify()

    def _state_text(self) -> str:
        """'Hold:0' style state name."""
        return f"Hold:{self._hold_sub}" if self._state == "Hold" else self._state

    # ------------------------------------------------------------ input

    def _on_bytes(self, data: bytes, now: float) -> None:
        """Real-time bytes act at once; everything else builds lines."""
        for byte in data:
            if gc.is_realtime(byte):
                self.realtime_log.append(bytes([byte]))
                self._realtime(byte, now)
            elif byte in (0x0A, 0x0D):
                self._end_line(now)
            elif len(self._line) >= gc.LINE_MAX_CHARS:
                self._overflow = True
            else:
                self._line.append(byte)

    def _end_line(self, now: float) -> None:
        """A complete line arrived."""
        text = self._line.decode("ascii", "replace").strip()
        overflow, self._overflow = self._overflow, False
        self._line.clear()
        self.received_lines.append(text)
        if self._critical:
            return  # GRBL blocks everything but '?' and reset after a critical alarm
        if overflow:
            self._emit(gc.encode_error(11), now)
        elif self._fail_next is not None and text.upper().startswith(self._fail_next[1]):
            code, self._fail_next = self._fail_next[0], None
            self._emit(gc.encode_error(code), now)
        elif not text:
            self._emit(gc.encode_ok(), now)
        elif text.startswith("$"):
            self._system_command(text, now)
        else:
            self._gcode(text, now)

    # ------------------------------------------------------------ real-time commands

    def _realtime(self, byte: int, now: float) -> None:
        """'?' report, '!' hold, '~' resume, 0x18 reset."""
        if byte == ord("?"):
            self._emit(self._status_report(now), now)
        elif byte == ord("!"):
            self._feed_hold(now)
        elif byte == ord("~"):
            self._cycle_start(now)
        else:
            self._soft_reset(now)

    def _status_report(self, now: float) -> bytes:
        """'<State|MPos:...|FS:...>' (WPos instead of MPos if configured; WCO every 10th report)."""
        pos = self._current(now)
        speed = self._motion.speed * 60.0 if self._motion is not None and self._state == "Run" else 0.0
        with_wco = self._reports % WCO_EVERY == 0
        self._reports += 1
        wpos = tuple(p - o for p, o in zip(pos, self.wco_mm))
        status = gc.Status(self._state, self._hold_sub if self._state == "Hold" else None,
                           mpos_mm=None if self.report_wpos else pos, wpos_mm=wpos if self.report_wpos else None,
                           wco_mm=self.wco_mm if with_wco else None, feed_mm_min=round(speed), spindle_rpm=0.0)
        return gc.encode_status(status)

    def _feed_hold(self, now: float) -> None:
        """'!': decelerate to a hold (Hold:1 then Hold:0); in Idle it is an immediate Hold:0."""
        if self._state == "Run" and self._motion is not None:
            self._pos = self._motion.position(now)  # type: ignore[assignment]
            self._resume = (self._motion.target, self._motion.speed)  # type: ignore[assignment]
            self._motion = None
            self._active.clear()
            self._hold_until = now + self.decel_s
            self._set_state("Hold", 1 if self.decel_s > 0 else 0)
        elif self._state == "Idle":
            self._set_state("Hold", 0)

    def _cycle_start(self, now: float) -> None:
        """'~': resume from a completed hold."""
        if self._state != "Hold" or self._hold_sub != 0:
            return
        if self._resume is not None:
            self._planner.appendleft(self._resume)
            self._resume = None
        self._set_state("Idle")
        self._start_next(now)

    def _soft_reset(self, now: float) -> None:
        """0x18: abort everything; ALARM:3/6 if it interrupted motion/homing; banner."""
        alarm = None
        if self._state == "Home":
            alarm = 6
        elif self._state == "Run" or (self._state == "Hold" and self._hold_sub == 1):
            alarm = 3
        self._pos = self._current(now)
        self._motion, self._resume, self._home_done_at = None, None, None
        self._planner.clear()
        self._active.clear()
        self._line.clear()
        self._critical = False
        if alarm is not None:
            self._raise_alarm(alarm, now)
        self._set_state("Alarm" if self._state == "Alarm" else "Idle")
        self._emit(gc.encode_banner(), now, reply=False)
        if self._state == "Alarm":
            self._emit(gc.encode_feedback("MSG", "'$H'|'$X' to unlock"), now, reply=False)

    # ------------------------------------------------------------ line commands

    def _system_command(self, text: str, now: float) -> None:
        """'$H', '$X', '$I', '$G', '$$'."""
        command = text.upper()
        if command == "$H":
            self._start_homing(now)
        elif command == "$X":
            if self._state == "Alarm":
                self._set_state("Idle")
                self._emit(gc.encode_feedback("MSG", "Caution: Unlocked"), now)
            self._emit(gc.encode_ok(), now)
        elif command == "$I":
            self._emit(gc.encode_feedback("VER", f"{gc.VERSION}.20190825:") + gc.encode_feedback("OPT", "V,15,128")
                       + gc.encode_ok(), now)
        elif command == "$G":
            mode = f"G{0 if self._rapid else 1} G54 G17 G21 G{90 if self._absolute else 91} G94 M5 M9 T0"
            self._emit(gc.encode_feedback("GC", f"{mode} F{self._feed_mm_min or 0:g} S0") + gc.encode_ok(), now)
        elif command == "$$":
            settings = [(22, "1"), (110, f"{self.speed_mm_s * 60:g}"), (111, f"{self.speed_mm_s * 60:g}"),
                        (130, f"{self.travel_mm[0]:g}"), (131, f"{self.travel_mm[1]:g}")]
            settings += [(132 + k, f"{t:g}") for k, t in enumerate(self.aux_travel_mm)]
            self._emit(b"".join(gc.encode_setting(n, v) for n, v in settings) + gc.encode_ok(), now)
        else:
            self._emit(gc.encode_error(3), now)

    def _start_homing(self, now: float) -> None:
        """'$H' from Idle or Alarm: state Home for the time it takes to reach the origin."""
        if self._state not in ("Idle", "Alarm"):
            self._emit(gc.encode_error(8), now)
            return
        distance = max(abs(v) for v in self._pos)
        self._home_done_at = now + max(0.005, distance / self.homing_speed_mm_s)
        self._set_state("Home")

    def _gcode(self, text: str, now: float) -> None:
        """One G-code block: modal updates and at most one linear move."""
        if self._state == "Alarm":
            self._emit(gc.encode_error(9), now)
            return
        try:
            target, speed = self._interpret(gc.parse_block(text))
        except gc.GcodeError as exc:
            self._emit(gc.encode_error(exc.code), now)
            return
        if target is None:
            self._emit(gc.encode_ok(), now)
            return
        if self.soft_limits and not self._within_travel(target):
            self._raise_alarm(2, now)  # GRBL: soft-limit alarm, no 'ok', locked until reset
            return
        self._planner.append((target, speed))
        self._emit(gc.encode_ok(), now)
        if self._state == "Idle":
            self._start_next(now)

    def _interpret(self, block: gc.Block) -> tuple[tuple[float, ...] | None, float]:
        """Target (machine mm) and speed (mm/s) of a block, after applying its modal words."""
        g_words = [int(v) if v == int(v) else v for v in block.values("G")]
        for letter, _ in block.words:
            if letter not in "GMF" + self.axes and letter not in IGNORED_WORDS:
                raise gc.GcodeError(20)
        if any(g not in SUPPORTED_G for g in g_words) or any(m not in SUPPORTED_M for m in block.values("M")):
            raise gc.GcodeError(20)
        motion = [g for g in g_words if g in (0, 1)]
        if len(motion) > 1 or len([g for g in g_words if g in (90, 91)]) > 1:
            raise gc.GcodeError(21)
        if block.get("F") is not None:
            self._feed_mm_min = block.get("F")
        if 90 in g_words or 91 in g_words:
            self._absolute = 90 in g_words
        if motion:
            self._rapid = motion[0] == 0
        axes = {a: block.get(a) for a in self.axes}
        if all(v is None for v in axes.values()):
            if 53 in g_words:
                raise gc.GcodeError(26)
            return None, 0.0
        if 53 in g_words and not motion:
            raise gc.GcodeError(30)
        if not self._rapid and not self._feed_mm_min:
            raise gc.GcodeError(22)
        return self._target(axes, machine=53 in g_words), self._speed()

    def _target(self, axes: dict[str, float | None], *, machine: bool) -> tuple[float, ...]:
        """Machine target from axis words: G53 machine coords, G90 work coords (+WCO) or G91 increments."""
        base = self._planner[-1][0] if self._planner else self._current(time.monotonic())
        target = []
        for i, letter in enumerate(self.axes):
            value = axes[letter]
            if value is None:
                target.append(base[i])
            elif machine:
                target.append(value)
            elif self._absolute:
                target.append(value + self.wco_mm[i])
            else:
                target.append(base[i] + value)
        return tuple(target)

    def _speed(self) -> float:
        """mm/s of the current motion mode."""
        if self._rapid or not self._feed_mm_min:
            return self.speed_mm_s
        return min(self.speed_mm_s, self._feed_mm_min / 60.0)

    def _within_travel(self, target: tuple[float, ...]) -> bool:
        """Controller-side soft limits: 0..travel on every axis."""
        eps = 1e-9
        travel = (*self.travel_mm[:2], *self.aux_travel_mm)
        return all(-eps <= target[i] <= travel[i] + eps for i in range(len(target)))

    def _start_next(self, now: float) -> None:
        """Start the next queued move, or go Idle."""
        if self._state not in ("Idle", "Run"):
            return
        if not self._planner:
            if self._state == "Run":
                self._set_state("Idle")
            return
        target, speed = self._planner.popleft()
        self._motion = Motion(self._pos, target, now, speed)
        self._activate_faults(self._motion)
        self._set_state("Run")
