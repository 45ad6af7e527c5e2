"""GRBL 1.1 XY stage: the device state machine on top of grbl_codec (messages) and transport (port).

Behaviour:
- connect: flush stale input, soft-reset (0x18), wait for the banner, read the state with '?'.
  The stage is not homed after connect (GRBL cannot tell whether it was homed before).
- home: soft-reset first if the controller is in alarm or hold, then '$H'; GRBL answers 'ok' when
  homing has finished.
- move: one 'G90 G53 G0 X.. Y..' line (machine coordinates), wait for 'ok', then poll '?' until the
  report says Idle at the target. A stale feed hold is cleared by a soft reset before moving.
- stop (any thread): '!' (feed hold: decelerate, position kept), or 0x18 while homing (the only way to
  abort homing). The command thread then waits for 'Hold:0' and soft-resets to flush the planner:
  GRBL keeps its position after a reset from a completed hold, so the stage stays homed.
- timeout: the same halt, and a soft reset if the hold is not confirmed (then the stage is unhomed).
- ALARM:N -> StageAlarm with GRBL's text, stage unhomed; error:N -> DeviceError with GRBL's text;
  garbage lines are logged and counted (`garbage_lines`) and otherwise ignored.
- auxiliary axes (`aux_limits` keys, URL ``aux=z`` or ``aux=z,a,b``): Z is GRBL 1.1's third axis; A
  and B are the fourth and fifth axes of 5-axis GRBL ports (grblHAL), reported as the 4th and 5th MPos
  values. `move_aux` sends one 'G90 G53 G0 Z.. A.. B..' line and polls like an XY move.
"""

from __future__ import annotations

import logging
import time
from typing import Mapping, Sequence

from mlaqc.errors import DeviceError

from . import grbl_codec as gc
from .base import Expired, Limits, NotHomedError, Stage, StageAlarm, StopRequested, _Closeable
from .transport import Transport

log = logging.getLogger(__name__)

TARGET_TOLERANCE_MM = 0.0015  # GRBL reports 3 decimals
AXIS_INDEX = {"z": 2, "a": 3, "b": 4}  # auxiliary axis -> index in MPos/WPos reports


class GrblStage(Stage):
    """An XY stage driven by a GRBL 1.1 controller on `port` (any pyserial URL or device path)."""

    protocol = "GRBL"

    def __init__(self, port: str, *, url: str | None = None, baud: int = 115200, limits: Limits = Limits(),
                 feed_mm_min: float | None = None, connect_timeout_s: float = 3.0, poll_s: float = 0.1,
                 stop_timeout_s: float = 2.0, name: str | None = None, owned: Sequence[_Closeable] = (),
                 aux_limits: Mapping[str, tuple[float, float]] | None = None) -> None:
        super().__init__(url=url or port, limits=limits, name=name, poll_s=poll_s,
                         stop_timeout_s=stop_timeout_s, owned=owned, aux_limits=aux_limits)
        self.port = port
        self.feed_mm_min = feed_mm_min
        self.connect_timeout_s = connect_timeout_s
        self.garbage_lines = 0
        self.last_status: gc.Status | None = None
        self.last_alarm: gc.Alarm | None = None
        self._transport = Transport(port, baud=baud, owner=self.name)
        self._wco_mm: tuple[float, ...] | None = None
        self._homing = False
        self._awaiting_banner = False
        self._unexpected_resets = 0
        self._needs_reset = False

    # ------------------------------------------------------------ lifecycle hooks

    def _open_locked(self) -> None:
        """Open, soft-reset, wait for the banner and read the state."""
        deadline = time.monotonic() + self.connect_timeout_s
        self._transport.open()
        self._transport.discard_input()
        self._soft_reset(deadline)
        self._query_status(deadline)

    def _close_port(self) -> None:
        """Close the port."""
        self._transport.close()

    # ------------------------------------------------------------ reading

    def _next_or_none(self, deadline: float) -> gc.Message | None:
        """The next meaningful message, or None at the deadline; logs noise, caches status, notes alarms."""
        while True:
            line = self._transport.read_line(deadline)
            if line is None:
                return None
            msg = gc.parse_line(line)
            if msg is None or self._absorb(msg):
                continue
            return msg

    def _absorb(self, msg: gc.Message) -> bool:
        """Side effects of a message; True if callers never need to see it (garbage, feedback, settings)."""
        if isinstance(msg, gc.Garbage):
            self.garbage_lines += 1
            log.warning("%s: ignoring garbage line %r", self.name, msg.raw)
            return True
        if isinstance(msg, (gc.Feedback, gc.Setting)):
            log.info("%s: %s", self.name, msg)
            return True
        if isinstance(msg, gc.Status):
            self._note_status(msg)
        elif isinstance(msg, gc.Alarm):
            log.error("%s: ALARM:%d (%s)", self.name, msg.code, msg.text)
            self.last_alarm = msg
            self._homed = False
        elif isinstance(msg, gc.Banner) and not self._awaiting_banner and self._doing != "connecting":
            log.error("%s: controller restarted unexpectedly (banner %s)", self.name, msg.version)
            self._unexpected_resets += 1
            self._homed = False
        return False

    def _next(self, deadline: float, waiting_for: str) -> gc.Message:
        """The next meaningful message; Expired(waiting_for) at the deadline."""
        msg = self._next_or_none(deadline)
        if msg is None:
            raise Expired(waiting_for)
        return msg

    def _drain(self) -> None:
        """Handle whatever arrived while no command was running (late reports, alarms, a reset)."""
        while (msg := self._next_or_none(time.monotonic())) is not None:
            log.debug("%s: stale %s", self.name, msg)

    def _note_status(self, status: gc.Status) -> None:
        """Cache a status report, its work offset and its machine position."""
        self.last_status = status
        if status.wco_mm is not None:
            self._wco_mm = status.wco_mm
        pos = status.machine_position(self._wco_mm)
        if pos is not None and len(pos) >= 2:
            self._set_position(pos[0], pos[1])
            aux = {name: pos[AXIS_INDEX[name]] for name in self.aux_axes if AXIS_INDEX[name] < len(pos)}
            if aux:
                self._set_aux(aux)

    # ------------------------------------------------------------ exchanges

    def _alarm_error(self, alarm: gc.Alarm) -> DeviceError:
        """StageAlarm for ALARM:N with GRBL's text."""
        return self._fail(StageAlarm, f"raised ALARM:{alarm.code} ({alarm.text}) and is no longer homed")

    def _send_line(self, data: bytes, deadline: float, waiting_for: str) -> None:
        """Send one command line and wait for its 'ok'; error:N, ALARM:N, a reset -> DeviceError."""
        self._transport.write(data)
        while True:
            msg = self._next(deadline, waiting_for)
            if isinstance(msg, gc.Ok):
                return
            if isinstance(msg, gc.Error):
                raise self._fail(DeviceError, f"answered error:{msg.code} ({msg.text}) to {data.decode().strip()!r}")
            if isinstance(msg, gc.Alarm):
                raise self._alarm_error(msg)
            if isinstance(msg, gc.Banner):
                raise self._fail(DeviceError, "restarted unexpectedly")

    def _query_status(self, deadline: float) -> gc.Status:
        """Send '?' and return the next status report; ALARM:N -> StageAlarm."""
        self._transport.write(gc.STATUS_QUERY)
        while True:
            msg = self._next(deadline, "status report")
            if isinstance(msg, gc.Status):
                return msg
            if isinstance(msg, gc.Alarm):
                raise self._alarm_error(msg)
            log.debug("%s: skipping %s while waiting for a status report", self.name, msg)

    def _await_banner(self, deadline: float) -> None:
        """Read until the reset banner (alarms are noted, not raised: a reset may cause ALARM:3/6)."""
        self._awaiting_banner = True
        try:
            while not isinstance(self._next(deadline, "startup banner after a reset"), gc.Banner):
                pass
        finally:
            self._awaiting_banner = False

    def _soft_reset(self, deadline: float) -> None:
        """Soft-reset (0x18) and wait for the banner: flushes the planner, clears holds and alarms' lockout."""
        self._transport.write(gc.SOFT_RESET)
        self._await_banner(deadline)
        self._needs_reset = False

    # ------------------------------------------------------------ commands

    def _ready(self, deadline: float) -> gc.Status:
        """Bring the controller to Idle before a move: clear a stale hold; refuse alarm and busy states."""
        self._drain()
        if self._needs_reset:
            self._soft_reset(deadline)
        status = self._query_status(deadline)
        if status.state == "Hold":
            self._settle_locked(deadline)
            status = self._query_status(deadline)
        if status.state == "Alarm":
            self._homed = False
            raise self._fail(NotHomedError, "is in alarm lock and no longer homed; call home() first")
        if status.state != "Idle":
            raise self._fail(DeviceError, f"is in state {status.state}, not Idle")
        if not self._homed:
            raise self._fail(NotHomedError, "is no longer homed; call home() first")
        return status

    def _home_locked(self, deadline: float, gen: int) -> None:
        """Reset out of alarm/hold if needed, send '$H' and wait for its 'ok' (stop() aborts with 0x18)."""
        self._drain()
        status = self._query_status(deadline)
        if self._needs_reset or status.state in ("Alarm", "Hold", "Door", "Sleep"):
            self._soft_reset(deadline)
        elif status.state in ("Run", "Jog", "Home"):
            raise self._fail(DeviceError, f"is busy (state {status.state})")
        self._homing = True
        try:
            if self._stopped(gen):
                raise StopRequested()
            self._transport.write(gc.encode_home())
            self._await_homing(deadline, gen)
        finally:
            self._homing = False
        self._homed = True
        self._query_status(deadline)

    def _await_homing(self, deadline: float, gen: int) -> None:
        """Wait for '$H' to answer 'ok'; on stop() wait for the reset it caused and raise StopRequested."""
        while True:
            if self._stopped(gen):
                self._await_banner(time.monotonic() + self.stop_timeout_s)
                raise StopRequested()
            msg = self._next_or_none(min(deadline, time.monotonic() + self.poll_s))
            if msg is None:
                if time.monotonic() >= deadline:
                    raise Expired("'ok' for the homing cycle")
            elif isinstance(msg, gc.Ok):
                return
            elif isinstance(msg, gc.Error):
                raise self._fail(DeviceError, f"answered error:{msg.code} ({msg.text}) to '$H'")
            elif isinstance(msg, gc.Alarm) and not self._stopped(gen):
                raise self._alarm_error(msg)

    def _move_locked(self, x_mm: float, y_mm: float, deadline: float, gen: int) -> None:
        """Send the move, wait for 'ok', then poll '?' until Idle at the target."""
        self._move_axes_locked({0: x_mm, 1: y_mm}, gc.encode_move(x_mm, y_mm, feed_mm_min=self.feed_mm_min),
                               deadline, gen)

    def _move_aux_locked(self, targets: dict[str, float], deadline: float, gen: int) -> None:
        """Move the auxiliary axes with one G53 line, then poll like an XY move."""
        line = gc.encode_move_axes({name.upper(): v for name, v in targets.items()}, feed_mm_min=self.feed_mm_min)
        self._move_axes_locked({AXIS_INDEX[name]: v for name, v in targets.items()}, line, deadline, gen)

    def _move_axes_locked(self, target_mm: dict[int, float], line: bytes, deadline: float, gen: int) -> None:
        """Send a move line, wait for 'ok', then poll '?' until Idle with every axis (by report index) at its target."""
        self._ready(deadline)
        if self._stopped(gen):  # stop() arrived during the readiness check: clear its hold, send nothing
            self._settle_locked(time.monotonic() + self.stop_timeout_s)
            raise StopRequested()
        resets = self._unexpected_resets
        self._send_line(line, deadline, "'ok' for the move command")
        target = {i: round(v, 3) for i, v in target_mm.items()}
        while True:
            if self._stopped(gen):
                self._settle_locked(time.monotonic() + self.stop_timeout_s)
                raise StopRequested()
            status = self._query_status(deadline)
            if self._unexpected_resets != resets:
                raise self._fail(DeviceError, "restarted unexpectedly")
            if status.state == "Alarm":
                raise self._fail(StageAlarm, "entered alarm state and is no longer homed")
            if status.state == "Idle" and self._at(status, target):
                return
            self._pause(deadline)
            if time.monotonic() >= deadline:
                raise Expired("Idle status at the target")

    def _at(self, status: gc.Status, target: dict[int, float]) -> bool:
        """True if the report's machine position is the target (axis index -> mm, within GRBL's 3-decimal rounding)."""
        pos = status.machine_position(self._wco_mm)
        if pos is None:
            return False
        if any(i >= len(pos) for i in target):
            raise self._fail(DeviceError, f"reports only {len(pos)} axes, not the {gc.AXIS_LETTERS[max(target)]} axis it "
                                          "was asked to move (check the URL's aux= against the controller)")
        return all(abs(pos[i] - t) <= TARGET_TOLERANCE_MM for i, t in target.items())

    def _position_locked(self, deadline: float) -> tuple[float, float]:
        """Machine position from a fresh status report (waits for a WCO if GRBL reports WPos only)."""
        self._drain()
        while True:
            pos = self._query_status(deadline).machine_position(self._wco_mm)
            if pos is not None:
                return (pos[0], pos[1])
            self._pause(deadline)

    def _aux_position_locked(self, deadline: float) -> dict[str, float]:
        """Auxiliary-axis machine positions from a fresh status report."""
        self._drain()
        while True:
            pos = self._query_status(deadline).machine_position(self._wco_mm)
            if pos is not None:
                break
            self._pause(deadline)
        missing = [name.upper() for name in self.aux_axes if AXIS_INDEX[name] >= len(pos)]
        if missing:
            raise self._fail(DeviceError, f"reports only {len(pos)} axes, so it has no {', '.join(missing)} axis "
                                          "(check the URL's aux= against the controller)")
        return {name: pos[AXIS_INDEX[name]] for name in self.aux_axes}

    def _busy_locked(self, deadline: float) -> bool:
        """True if GRBL reports motion (Run, Jog, Home or a hold still decelerating)."""
        self._drain()
        status = self._query_status(deadline)
        return status.state in ("Run", "Jog", "Home") or (status.state == "Hold" and status.substate == 1)

    # ------------------------------------------------------------ stopping

    def _halt_now(self) -> None:
        """'!' (feed hold, keeps position), or 0x18 while homing; thread-safe single-byte write."""
        self._transport.write(gc.SOFT_RESET if self._homing else gc.FEED_HOLD)

    def _settle_locked(self, deadline: float) -> None:
        """Wait for the hold to complete ('Hold:0'), then soft-reset to flush what was still planned."""
        while True:
            status = self._query_status(deadline)
            if status.state == "Hold" and status.substate in (0, None):
                self._soft_reset(deadline)
                return
            if status.state in ("Idle", "Alarm", "Sleep", "Door", "Check"):
                return
            if status.state in ("Home", "Jog"):
                self._soft_reset(deadline)
                return
            if status.state == "Run":
                self._transport.write(gc.FEED_HOLD)
            time.sleep(max(0.0, min(self.poll_s, deadline - time.monotonic())))

    def _hard_stop(self) -> None:
        """Soft-reset without waiting (the hold was not confirmed): position is unknown, re-home needed."""
        self._homed = False
        self._needs_reset = True
        try:
            self._transport.write(gc.SOFT_RESET)
        except DeviceError as exc:
            log.warning("%s: soft reset failed: %s", self.name, exc)

    # ------------------------------------------------------------ extras

    def unlock(self, timeout_s: float = 5.0) -> None:
        """'$X': clear an alarm lock without homing (the stage stays unhomed: moves remain refused)."""
        def run(deadline: float) -> None:
            """Reset if needed, then '$X'."""
            self._drain()
            if self._needs_reset:
                self._soft_reset(deadline)
            self._send_line(gc.encode_unlock(), deadline, "'ok' for '$X'")

        self._run("unlocking", timeout_s, run)
