"""The XY-stage interface every driver implements, and the locking/deadline machinery they share.

Contract (what the scan runner and the GUI may rely on):
- One command in flight at a time: every public call takes the command lock, with the call's own deadline.
- `move_to`/`move_by`/`home` block until the motion has finished, the deadline passes (then a stop is
  sent and StageTimeout raised), the device faults (StageAlarm, DeviceError) or `stop()` is called
  (StageStopped).
- Targets outside `limits` raise InputError and moves before `home()` raise NotHomedError, both before
  a single byte is sent. Nothing is ever clipped.
- `stop()` may be called from any thread at any time: it sends the protocol's out-of-band halt at once,
  without waiting for the command lock, and cancels the move in flight and moves queued on the lock.
- A lost connection raises DeviceError naming the device and what it was doing; the stage is then
  disconnected and unhomed until `connect()` and `home()` again.

Auxiliary axes: a controller may drive more than the MLA's X and Y. `aux_axes` names them, from
AUX_AXES: ``z`` (the target carrier's focus axis, along the optical axis) and ``a``, ``b`` (the
carrier's two lateral axes), each with its own soft limits in `aux_limits`. `move_aux({"z": 42.0})`,
`aux_position()` and `last_aux` work like `move_to`, `position()` and `last_position` (same lock,
deadlines, stop, limit and homing checks); a stage without the axis refuses with InputError before
sending anything. `home()` homes every axis.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Callable, Mapping, Protocol, Sequence, TypeVar

from mlaqc.errors import DeviceError, InputError

from .transport import PortError

log = logging.getLogger(__name__)

T = TypeVar("T")


AUX_AXES = ("z", "a", "b")  # auxiliary axes a stage may have, in the order controllers number them
DEFAULT_AUX_LIMITS_MM = (0.0, 100.0)


def check_aux_limits(aux_limits: Mapping[str, tuple[float, float]] | None) -> dict[str, tuple[float, float]]:
    """{axis: (min, max)} for known auxiliary axes with finite, non-empty ranges, else InputError."""
    out: dict[str, tuple[float, float]] = {}
    for name, bounds in (aux_limits or {}).items():
        if name not in AUX_AXES:
            raise InputError(f"stage axis {name!r} is not an auxiliary axis; expected some of {', '.join(AUX_AXES)}")
        try:
            lo, hi = (float(v) for v in bounds)
        except (TypeError, ValueError):
            raise InputError(f"stage {name.upper()} limits {bounds!r} must be two numbers (min, max) in mm") from None
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise InputError(f"stage {name.upper()} limits {lo:g}..{hi:g} mm must be finite and non-empty")
        out[name] = (lo, hi)
    return {name: out[name] for name in AUX_AXES if name in out}


def format_aux(values: Mapping[str, float]) -> str:
    """'Z=42.000 A=1.250 mm'."""
    return " ".join(f"{k.upper()}={v:.3f}" for k, v in values.items()) + " mm"


class StageStopped(DeviceError):
    """A move or homing cycle ended early because stop() was called."""


class StageTimeout(DeviceError):
    """The device did not answer or finish within the deadline (a stop was sent for motion commands)."""


class StageAlarm(DeviceError):
    """The controller raised an alarm or fault (GRBL ALARM:N, Zaber F* flag); the stage is no longer homed."""


class NotHomedError(DeviceError):
    """A move was asked for before the stage was homed; nothing was sent."""


class _Closeable(Protocol):
    def close(self) -> None: ...


class Expired(Exception):
    """Internal: a deadline passed while waiting for `waiting_for`."""

    def __init__(self, waiting_for: str) -> None:
        super().__init__(waiting_for)
        self.waiting_for = waiting_for


class StopRequested(Exception):
    """Internal: stop() was called while a command was running; the device has been settled."""


@dataclass(frozen=True)
class Limits:
    """Soft travel limits in mm (inclusive); moves outside are refused, never clipped."""

    x_min_mm: float = 0.0
    x_max_mm: float = 200.0
    y_min_mm: float = 0.0
    y_max_mm: float = 200.0

    def __post_init__(self) -> None:
        values = (self.x_min_mm, self.x_max_mm, self.y_min_mm, self.y_max_mm)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise InputError(f"stage limits {values} must be finite numbers in mm")
        if self.x_min_mm >= self.x_max_mm or self.y_min_mm >= self.y_max_mm:
            raise InputError(f"stage limits x {self.x_min_mm}..{self.x_max_mm} mm, y {self.y_min_mm}..{self.y_max_mm} mm are empty")

    def contains(self, x_mm: float, y_mm: float) -> bool:
        """True if (x_mm, y_mm) is inside the limits."""
        return self.x_min_mm <= x_mm <= self.x_max_mm and self.y_min_mm <= y_mm <= self.y_max_mm

    def __str__(self) -> str:
        return f"x {self.x_min_mm:g}..{self.x_max_mm:g} mm, y {self.y_min_mm:g}..{self.y_max_mm:g} mm"


def _check_number(name: str, value: float) -> float:
    """`value` as a float, or InputError if it is not a finite number."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"stage {name} {value!r} is not a number") from None
    if not math.isfinite(number):
        raise InputError(f"stage {name} {value!r} is not a finite number")
    return number


def _check_timeout(timeout_s: float) -> float:
    """A positive finite timeout, or InputError."""
    timeout = _check_number("timeout_s", timeout_s)
    if timeout <= 0:
        raise InputError(f"stage timeout_s {timeout_s!r} must be positive")
    return timeout


class Stage(ABC):
    """An XY stage behind one serial controller; use as a context manager or call connect()/close()."""

    protocol = "?"
    sim: object | None = None  # the simulator behind a sim+.../mock:// stage (fault injection), else None

    def __init__(self, *, url: str, limits: Limits, name: str | None = None, poll_s: float = 0.05,
                 stop_timeout_s: float = 2.0, owned: Sequence[_Closeable] = (),
                 aux_limits: Mapping[str, tuple[float, float]] | None = None) -> None:
        self.url = url
        self.name = name or f"{self.protocol} stage {url}"
        self.limits = limits
        self.aux_limits = check_aux_limits(aux_limits)
        self.poll_s = poll_s
        self.stop_timeout_s = stop_timeout_s
        self._owned = list(owned)
        self._lock = threading.Lock()
        self._gen_lock = threading.Lock()
        self._stop_gen = 0
        self._wake = threading.Event()
        self._homed = False
        self._connected = False
        self._doing = "idle"
        self._last_position: tuple[float, float] | None = None
        self._last_aux: dict[str, float] | None = None

    # ------------------------------------------------------------ lifecycle

    def __enter__(self) -> "Stage":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url!r} connected={self._connected} homed={self._homed}>"

    @property
    def is_connected(self) -> bool:
        """True between a successful connect() and close() or a lost connection."""
        return self._connected

    @property
    def homed(self) -> bool:
        """True once home() succeeded, until an alarm, a reset or a lost connection."""
        return self._homed

    @property
    def last_position(self) -> tuple[float, float] | None:
        """The most recent position the device reported (mm), without asking it: for live displays."""
        return self._last_position

    @property
    def aux_axes(self) -> tuple[str, ...]:
        """The auxiliary axes this stage drives (see AUX_AXES), () for a plain XY stage."""
        return tuple(self.aux_limits)

    @property
    def last_aux(self) -> dict[str, float] | None:
        """The most recent auxiliary-axis positions the device reported (mm), without asking it; None if none."""
        aux = self._last_aux
        return None if aux is None else dict(aux)

    def connect(self) -> None:
        """Open the port and synchronise with the controller; a no-op when already connected."""
        with self._lock:
            if self._connected:
                return
            self._doing = "connecting"
            self._homed = False
            try:
                self._open_locked()
            except PortError as exc:
                self._close_port()
                raise DeviceError(f"{self.name} lost its connection while connecting ({exc.detail}).") from None
            except Expired as exc:
                self._close_port()
                raise StageTimeout(f"{self.name} did not answer while connecting ({exc.waiting_for}).") from None
            except BaseException:
                self._close_port()
                raise
            self._connected = True
            self._doing = "idle"

    def close(self) -> None:
        """Stop any motion in flight, close the port and shut down owned resources (a simulator)."""
        acquired = self._lock.acquire(timeout=0.05)
        if not acquired and self._connected:
            try:
                self.stop()
            except DeviceError as exc:
                log.warning("%s: stop on close failed: %s", self.name, exc)
            acquired = self._lock.acquire(timeout=self.stop_timeout_s + 1.0)
        try:
            self._connected = False
            self._homed = False
            self._close_port()
        finally:
            if acquired:
                self._lock.release()
            for resource in self._owned:
                resource.close()

    # ------------------------------------------------------------ public commands

    def home(self, timeout_s: float = 60.0) -> None:
        """Run the homing cycle and block until it finishes; afterwards moves are allowed."""
        timeout = _check_timeout(timeout_s)
        gen = self._stop_gen
        self._run("homing", timeout, lambda deadline: self._home_locked(deadline, gen), gen=gen, stop_on_timeout=True)

    def move_to(self, x_mm: float, y_mm: float, timeout_s: float = 30.0) -> None:
        """Move to absolute (x_mm, y_mm) and block until there; refused outside the limits or before homing."""
        x, y = _check_number("x_mm", x_mm), _check_number("y_mm", y_mm)
        timeout = _check_timeout(timeout_s)
        gen = self._stop_gen
        self._check_move(x, y)
        doing = f"moving to ({x:.3f}, {y:.3f}) mm"
        self._run(doing, timeout, lambda deadline: self._move_locked(x, y, deadline, gen), gen=gen, stop_on_timeout=True)

    def move_by(self, dx_mm: float, dy_mm: float, timeout_s: float = 30.0) -> None:
        """Move by (dx_mm, dy_mm) from the position read back now; same checks as move_to on the target."""
        dx, dy = _check_number("dx_mm", dx_mm), _check_number("dy_mm", dy_mm)
        timeout = _check_timeout(timeout_s)
        gen = self._stop_gen
        self._check_homed(f"a move by ({dx:.3f}, {dy:.3f}) mm")

        def step(deadline: float) -> None:
            """Read the position, check the target, move (all under one lock hold)."""
            x0, y0 = self._position_locked(deadline)
            x, y = x0 + dx, y0 + dy
            self._check_move(x, y)
            self._doing = f"moving by ({dx:.3f}, {dy:.3f}) mm to ({x:.3f}, {y:.3f}) mm"
            self._move_locked(x, y, deadline, gen)

        self._run(f"moving by ({dx:.3f}, {dy:.3f}) mm", timeout, step, gen=gen, stop_on_timeout=True)

    def move_aux(self, targets: Mapping[str, float], timeout_s: float = 30.0) -> None:
        """Move auxiliary axes to absolute positions, e.g. {"z": 42.0, "a": 10.1}, and block until there;
        refused (before anything is sent) for an axis the stage lacks, outside its limits or before homing."""
        clean = self._check_aux_move(targets)
        timeout = _check_timeout(timeout_s)
        gen = self._stop_gen
        doing = f"moving {format_aux(clean)}"
        self._run(doing, timeout, lambda deadline: self._move_aux_locked(clean, deadline, gen), gen=gen,
                  stop_on_timeout=True)

    def aux_position(self, timeout_s: float = 5.0) -> dict[str, float]:
        """Auxiliary-axis positions read back from the device now ({} for a plain XY stage)."""
        timeout = _check_timeout(timeout_s)
        if not self.aux_axes:
            return {}
        return self._run("reading its auxiliary axes", timeout, self._aux_position_locked)

    def position(self, timeout_s: float = 5.0) -> tuple[float, float]:
        """(x_mm, y_mm) read back from the device now (waits for a command in flight to finish)."""
        timeout = _check_timeout(timeout_s)
        return self._run("reading its position", timeout, self._position_locked)

    def is_busy(self, timeout_s: float = 5.0) -> bool:
        """True if a command is in flight or the device reports motion."""
        if self._lock.locked():
            return True
        timeout = _check_timeout(timeout_s)
        return self._run("reading its state", timeout, self._busy_locked)

    def stop(self) -> None:
        """Halt motion now from any thread: out-of-band halt, cancel the running and queued moves."""
        with self._gen_lock:
            self._stop_gen += 1
        self._wake.set()
        if not self._connected:
            return
        try:
            self._halt_now()
        except PortError as exc:
            raise DeviceError(f"{self.name} could not be sent a stop ({exc.detail}); it may still be moving.") from None
        if self._lock.acquire(blocking=False):
            try:
                self._settle_quietly()
            finally:
                self._lock.release()

    # ------------------------------------------------------------ shared machinery

    def _check_move(self, x_mm: float, y_mm: float) -> None:
        """Refuse (before sending anything) a target outside the limits or a move before homing."""
        if not self.limits.contains(x_mm, y_mm):
            raise InputError(f"{self.name} refused a move to ({x_mm:.3f}, {y_mm:.3f}) mm: it is outside the soft limits ({self.limits})")
        self._check_homed(f"a move to ({x_mm:.3f}, {y_mm:.3f}) mm")

    def _check_aux_move(self, targets: Mapping[str, float]) -> dict[str, float]:
        """Targets in AUX_AXES order, checked against the stage's axes, limits and homing."""
        if not isinstance(targets, Mapping) or not targets:
            raise InputError(f"{self.name}: an auxiliary move needs at least one axis target, e.g. {{'z': 40.0}}")
        clean: dict[str, float] = {}
        for name in targets:
            if name not in self.aux_limits:
                have = ", ".join(a.upper() for a in self.aux_axes) or "none"
                raise InputError(f"{self.name} has no {str(name).upper()} axis (its auxiliary axes: {have}); "
                                 "name them in the stage URL, e.g. aux=z,a,b")
        for name in AUX_AXES:
            if name in targets:
                value = _check_number(f"{name}_mm", targets[name])
                lo, hi = self.aux_limits[name]
                if not lo <= value <= hi:
                    raise InputError(f"{self.name} refused a move to {name.upper()}={value:.3f} mm: it is outside the "
                                     f"soft limits ({name} {lo:g}..{hi:g} mm)")
                clean[name] = value
        self._check_homed(f"a move to {format_aux(clean)}")
        return clean

    def _check_homed(self, what: str) -> None:
        """Refuse `what` (a move) with NotHomedError unless the stage is homed."""
        if not self._homed:
            raise NotHomedError(f"{self.name} refused {what} because it is not homed; call home() first.")

    def _stopped(self, gen: int) -> bool:
        """True if stop() was called since the command that captured `gen` was issued."""
        return self._stop_gen != gen

    def _pause(self, deadline: float) -> None:
        """Wait one poll interval (less if the deadline is nearer); stop() wakes it at once."""
        self._wake.wait(max(0.0, min(self.poll_s, deadline - time.monotonic())))

    def _run(self, doing: str, timeout_s: float, fn: Callable[[float], T], *, gen: int | None = None,
             stop_on_timeout: bool = False) -> T:
        """Run `fn(deadline)` holding the command lock; turn internal outcomes into one-sentence errors.

        `gen` is the stop generation a motion command was issued under (None for queries)."""
        deadline = time.monotonic() + timeout_s
        if not self._lock.acquire(timeout=timeout_s):
            raise StageTimeout(f"{self.name} stayed busy with another command for {timeout_s:g} s, so it could not start {doing}.")
        try:
            self._doing = doing
            if not self._connected:
                raise DeviceError(f"{self.name} is not connected, so it cannot start {doing}; call connect() first.")
            if gen is not None and self._stopped(gen):  # stop() cancels motion queued on the lock, not queries
                raise StageStopped(f"{self.name} was stopped before it started {doing}.")
            self._wake.clear()
            return fn(deadline)
        except StopRequested:
            raise StageStopped(f"{self.name} was stopped while {self._doing}.") from None
        except Expired as exc:
            if stop_on_timeout:
                self._stop_after_timeout()
            sent = "; a stop was sent" if stop_on_timeout else ""
            raise StageTimeout(f"{self.name} did not finish {self._doing} within {timeout_s:g} s (no {exc.waiting_for}){sent}.") from None
        except PortError as exc:
            self._lost(exc)
            raise DeviceError(f"{self.name} lost its connection while {self._doing} ({exc.detail}).") from None
        finally:
            self._doing = "idle"
            self._lock.release()

    def _fail(self, cls: type[DeviceError], what: str) -> DeviceError:
        """A one-sentence error: '<name> <what> while <doing>.'."""
        return cls(f"{self.name} {what} while {self._doing}.")

    def _stop_after_timeout(self) -> None:
        """Best-effort halt after a deadline passed (the lock is held); never raises."""
        try:
            self._halt_now()
            self._settle_locked(time.monotonic() + self.stop_timeout_s)
        except (PortError, Expired, DeviceError) as exc:
            log.warning("%s: halting after a timeout did not complete cleanly: %s", self.name, exc)
            self._hard_stop()
        except StopRequested:
            pass

    def _settle_quietly(self) -> None:
        """After stop() with no command running: settle the device, logging (not raising) problems."""
        try:
            self._settle_locked(time.monotonic() + self.stop_timeout_s)
        except PortError as exc:
            self._lost(exc)
            log.warning("%s: connection lost while stopping: %s", self.name, exc.detail)
        except (Expired, DeviceError) as exc:
            log.warning("%s: stop sent but not confirmed: %s", self.name, exc)

    def _lost(self, exc: PortError) -> None:
        """Mark the stage disconnected and unhomed after a port failure."""
        log.error("%s: %s", self.name, exc)
        self._connected = False
        self._homed = False
        self._close_port()

    def _set_position(self, x_mm: float, y_mm: float) -> None:
        """Remember the latest reported position for `last_position`."""
        self._last_position = (x_mm, y_mm)

    def _set_aux(self, values: Mapping[str, float]) -> None:
        """Remember the latest reported auxiliary positions for `last_aux` (merged with earlier ones)."""
        merged = dict(self._last_aux or {})
        merged.update(values)
        self._last_aux = merged

    # ------------------------------------------------------------ protocol hooks

    @abstractmethod
    def _open_locked(self) -> None:
        """Open the port and bring the controller to a known state (may raise PortError, Expired)."""

    @abstractmethod
    def _close_port(self) -> None:
        """Close the port; must not raise."""

    @abstractmethod
    def _home_locked(self, deadline: float, gen: int) -> None:
        """Home all axes by `deadline`; set self._homed."""

    @abstractmethod
    def _move_locked(self, x_mm: float, y_mm: float, deadline: float, gen: int) -> None:
        """Move to (x_mm, y_mm) by `deadline`; raise StopRequested after settling if stop() was called."""

    @abstractmethod
    def _position_locked(self, deadline: float) -> tuple[float, float]:
        """Ask the device for its position in mm."""

    def _move_aux_locked(self, targets: dict[str, float], deadline: float, gen: int) -> None:
        """Move auxiliary axes by `deadline` (drivers with auxiliary axes override this)."""
        raise self._fail(DeviceError, "cannot drive auxiliary axes")

    def _aux_position_locked(self, deadline: float) -> dict[str, float]:
        """Ask the device for its auxiliary-axis positions (drivers with auxiliary axes override this)."""
        raise self._fail(DeviceError, "cannot read auxiliary axes")

    @abstractmethod
    def _busy_locked(self, deadline: float) -> bool:
        """Ask the device whether it is moving."""

    @abstractmethod
    def _halt_now(self) -> None:
        """Send the protocol's immediate halt without the command lock (thread-safe writes only)."""

    @abstractmethod
    def _settle_locked(self, deadline: float) -> None:
        """After a halt: wait until motion has ended and leave the controller ready for new commands."""

    @abstractmethod
    def _hard_stop(self) -> None:
        """Last resort when a halt could not be confirmed (e.g. GRBL soft reset); never raises."""
