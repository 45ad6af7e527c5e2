"""XY stages: `open_stage(url)` returns a connected Stage for a device URL.

URLs (parameters are optional unless marked):
- ``serial:///dev/ttyUSB0?protocol=grbl&baud=115200``: a real controller; `protocol` (required) is
  grbl or zaber. The path may be any device node, e.g. a pty.
- ``sim+grbl://?speed_mm_s=50&latency_ms=2``: a GRBL simulator on a new pty, driven by the real driver.
- ``sim+zaber://?axes=1.1,1.2&microstep_um=0.1``: a Zaber ASCII simulator on a new pty.
- ``mock://``: the GRBL simulator with fast motion, for demos and tests of other code.

Parameters, all protocols: x_min_mm, x_max_mm, y_min_mm, y_max_mm (soft limits, default 0..200),
poll_s (status polling interval), stop_timeout_s, connect_timeout_s; ``aux``: the auxiliary axes of the
target carrier (see drivers.stage.base: z = focus, a and b = lateral), GRBL ``aux=z`` or ``aux=z,a,b``
(Z is GRBL 1.1's third axis, A and B the 4th and 5th of grblHAL), Zaber ``aux=z:1.3,a:2.1,b:2.2``
(NAME:DEVICE.AXIS on the same chain), with soft limits z_min_mm, z_max_mm, a_min_mm, ... (default
0..100 mm each; only for axes named in aux). GRBL: feed_mm_min (use G1 at this
feed instead of G0 rapids). Zaber: axes ('1.1,1.2' = device 1 axes 1 and 2, '1,2' = devices 1 and 2),
microstep_um (µm per microstep), checksum (0/1). Simulators: speed_mm_s, latency_ms, and decel_ms
(GRBL). Anything else, or an unknown scheme or protocol, is an InputError naming it.

A stage opened on a simulator owns it (closing the stage closes it) and exposes it as `stage.sim` for
fault injection; see drivers.sim.
"""

from __future__ import annotations

import math
from typing import Callable

from mlaqc.errors import InputError

from drivers.url import DeviceURL, parse_device_url

from .base import AUX_AXES, DEFAULT_AUX_LIMITS_MM, Limits, NotHomedError, Stage, StageAlarm, StageStopped, StageTimeout
from .grbl import GrblStage
from .zaber import AxisAddress, ZaberStage, parse_aux_axes, parse_axes

__all__ = ["AxisAddress", "GrblStage", "Limits", "NotHomedError", "Stage", "StageAlarm", "StageStopped",
           "StageTimeout", "ZaberStage", "open_stage"]

COMMON = {"x_min_mm", "x_max_mm", "y_min_mm", "y_max_mm", "poll_s", "stop_timeout_s", "connect_timeout_s", "aux",
          *(f"{a}_{end}_mm" for a in AUX_AXES for end in ("min", "max"))}
GRBL = {"feed_mm_min"}
ZABER = {"axes", "microstep_um", "checksum"}
SIM = {"speed_mm_s", "latency_ms"}
MOCK_DEFAULTS = {"speed_mm_s": "2000", "poll_s": "0.005"}


class _Params:
    """Typed access to a device URL's query parameters, with InputError naming the bad one."""

    def __init__(self, url: str, parsed: DeviceURL, allowed: set[str]) -> None:
        self.url = url
        self.params = parsed.params
        unknown = sorted(set(self.params) - allowed)
        if unknown:
            raise InputError(f"stage URL {url!r} has unknown parameter {unknown[0]!r}; allowed: {', '.join(sorted(allowed))}")

    def number(self, name: str, default: float, *, positive: bool = False) -> float:
        """A float parameter."""
        text = self.params.get(name)
        if text is None:
            return default
        try:
            value = float(text)
        except ValueError:
            raise InputError(f"stage URL {self.url!r}: parameter {name}={text!r} is not a number") from None
        bad_sign = (positive and value <= 0) or (value < 0 and name.endswith(("_s", "_ms")))
        if not math.isfinite(value) or bad_sign:
            raise InputError(f"stage URL {self.url!r}: parameter {name}={text!r} is out of range")
        return value

    def optional(self, name: str) -> float | None:
        """A positive float parameter that may be absent."""
        return self.number(name, 0.0, positive=True) if name in self.params else None

    def text(self, name: str, default: str) -> str:
        """A string parameter."""
        return self.params.get(name, default)

    def flag(self, name: str) -> bool:
        """A 0/1 parameter."""
        text = self.params.get(name, "0")
        if text not in ("0", "1"):
            raise InputError(f"stage URL {self.url!r}: parameter {name}={text!r} must be 0 or 1")
        return text == "1"

    def limits(self) -> Limits:
        """Soft limits from x_min_mm .. y_max_mm."""
        d = Limits()
        return Limits(self.number("x_min_mm", d.x_min_mm), self.number("x_max_mm", d.x_max_mm),
                      self.number("y_min_mm", d.y_min_mm), self.number("y_max_mm", d.y_max_mm))

    def aux_names(self, names: list[str]) -> None:
        """Refuse limits of auxiliary axes the URL does not name in aux=."""
        for a in AUX_AXES:
            for end in ("min", "max"):
                key = f"{a}_{end}_mm"
                if key in self.params and a not in names:
                    raise InputError(f"stage URL {self.url!r}: parameter {key} needs axis {a!r} in aux=, e.g. aux={a}")

    def aux_limits(self, names: list[str]) -> dict[str, tuple[float, float]]:
        """Soft limits of the named auxiliary axes from {axis}_min_mm / {axis}_max_mm."""
        self.aux_names(names)
        lo, hi = DEFAULT_AUX_LIMITS_MM
        out = {}
        for a in names:
            bounds = (self.number(f"{a}_min_mm", lo), self.number(f"{a}_max_mm", hi))
            if not bounds[0] < bounds[1]:
                raise InputError(f"stage URL {self.url!r}: {a}_min_mm must be below {a}_max_mm")
            out[a] = bounds
        return out

    def grbl_aux(self) -> list[str]:
        """aux=z or aux=z,a,b for a GRBL controller (Z is the third axis, A and B the 4th and 5th)."""
        text = self.text("aux", "")
        names = [n.strip().lower() for n in text.split(",") if n.strip()]
        if any(n not in AUX_AXES for n in names) or len(set(names)) != len(names):
            raise InputError(f"stage URL {self.url!r}: aux={text!r} must list distinct axes from {', '.join(AUX_AXES)}, "
                             "e.g. aux=z or aux=z,a,b")
        if ("a" in names or "b" in names) and "z" not in names:
            raise InputError(f"stage URL {self.url!r}: aux={text!r}: a GRBL controller numbers A and B after Z, so "
                             "aux must include z")
        return [a for a in AUX_AXES if a in names]

    def common(self, default_poll_s: float, aux: list[str] = ()) -> dict[str, object]:
        """Driver keyword arguments shared by every protocol."""
        return {"limits": self.limits(), "poll_s": self.number("poll_s", default_poll_s, positive=True),
                "stop_timeout_s": self.number("stop_timeout_s", 2.0, positive=True),
                "aux_limits": self.aux_limits(list(aux))}


def open_stage(url: str) -> Stage:
    """Open and connect the stage named by `url` (see the module docstring); InputError for a bad URL."""
    parsed = parse_device_url(url)
    opener = _OPENERS.get(parsed.scheme)
    if opener is None:
        raise InputError(f"stage URL {url!r} has unknown scheme {parsed.scheme!r}; expected serial://, sim+grbl://, sim+zaber:// or mock://")
    stage = opener(url, parsed)
    try:
        stage.connect()
    except BaseException:
        stage.close()
        raise
    return stage


def _open_serial(url: str, parsed: DeviceURL) -> Stage:
    """serial:///dev/...?protocol=grbl|zaber."""
    protocol = parsed.param("protocol")
    if protocol not in ("grbl", "zaber"):
        raise InputError(f"stage URL {url!r} needs protocol=grbl or protocol=zaber, not {protocol!r}")
    if not parsed.path:
        raise InputError(f"stage URL {url!r} names no serial port, e.g. serial:///dev/ttyUSB0?protocol={protocol}")
    extra = GRBL if protocol == "grbl" else ZABER
    p = _Params(url, parsed, COMMON | extra | {"protocol", "baud"})
    baud = int(p.number("baud", 115200, positive=True))
    connect_s = p.number("connect_timeout_s", 3.0, positive=True)
    if protocol == "grbl":
        return GrblStage(parsed.path, url=url, baud=baud, feed_mm_min=p.optional("feed_mm_min"),
                         connect_timeout_s=connect_s, **p.common(0.1, p.grbl_aux()))  # type: ignore[arg-type]
    axes = parse_axes(p.text("axes", "1.1,1.2"))
    aux = _zaber_aux(url, p, axes)
    return ZaberStage(parsed.path, url=url, baud=baud, axes=axes, aux=aux,
                      microstep_um=p.number("microstep_um", 0.1, positive=True), checksum=p.flag("checksum"),
                      connect_timeout_s=connect_s, **p.common(0.05, list(aux)))  # type: ignore[arg-type]


def _zaber_aux(url: str, p: _Params, axes: tuple[AxisAddress, AxisAddress]) -> dict[str, AxisAddress]:
    """aux=z:1.3,... for a Zaber chain, InputError naming the URL."""
    try:
        return parse_aux_axes(p.text("aux", ""), axes)
    except InputError as exc:
        raise InputError(f"stage URL {url!r}: {exc}") from None


def _open_sim_grbl(url: str, parsed: DeviceURL, defaults: dict[str, str] | None = None) -> Stage:
    """sim+grbl://?... (and mock://): a GrblSim on a pty plus the real GRBL driver."""
    from drivers.sim import GrblSim

    if defaults:
        parsed = DeviceURL(parsed.scheme, parsed.path, {**defaults, **parsed.params})
    p = _Params(url, parsed, COMMON | GRBL | SIM | {"decel_ms"})
    limits = p.limits()
    aux = p.grbl_aux()
    common = p.common(0.01, aux)
    aux_limits: dict = common["aux_limits"]  # type: ignore[assignment]
    sim = GrblSim(speed_mm_s=p.number("speed_mm_s", 50.0, positive=True),
                  latency_s=p.number("latency_ms", 0.0) / 1000.0, decel_s=p.number("decel_ms", 5.0) / 1000.0,
                  travel_mm=(limits.x_max_mm, limits.y_max_mm),
                  axes="XYZAB" if {"a", "b"} & set(aux) else "XYZ",
                  aux_travel_mm=tuple(aux_limits.get(a, DEFAULT_AUX_LIMITS_MM)[1] for a in AUX_AXES))
    kwargs = dict(url=url, feed_mm_min=p.optional("feed_mm_min"),
                  connect_timeout_s=p.number("connect_timeout_s", 2.0, positive=True), **common)
    return _with_sim(sim, lambda path: GrblStage(path, owned=[sim], **kwargs))  # type: ignore[arg-type]


def _open_sim_zaber(url: str, parsed: DeviceURL) -> Stage:
    """sim+zaber://?...: a ZaberSim on a pty plus the real Zaber driver."""
    from drivers.sim import ZaberSim

    p = _Params(url, parsed, COMMON | ZABER | SIM)
    limits = p.limits()
    axes = parse_axes(p.text("axes", "1.1,1.2"))
    aux = _zaber_aux(url, p, axes)
    common = p.common(0.01, list(aux))
    aux_limits: dict = common["aux_limits"]  # type: ignore[assignment]
    microstep_um = p.number("microstep_um", 0.1, positive=True)
    sim = ZaberSim(axes=[(a.device, a.axis) for a in (*axes, *aux.values())], microstep_um=microstep_um,
                   speed_mm_s=p.number("speed_mm_s", 50.0, positive=True),
                   latency_s=p.number("latency_ms", 0.0) / 1000.0,
                   travel_mm=(limits.x_max_mm, limits.y_max_mm, *(aux_limits[a][1] for a in aux)))
    kwargs = dict(url=url, axes=axes, aux=aux, microstep_um=microstep_um, checksum=p.flag("checksum"),
                  connect_timeout_s=p.number("connect_timeout_s", 2.0, positive=True), **common)
    return _with_sim(sim, lambda path: ZaberStage(path, owned=[sim], **kwargs))  # type: ignore[arg-type]


def _with_sim(sim: object, make: Callable[[str], Stage]) -> Stage:
    """Start `sim`, build the stage on its pty and attach the simulator as `stage.sim`."""
    sim.start()  # type: ignore[attr-defined]
    try:
        stage = make(sim.path)  # type: ignore[attr-defined]
    except BaseException:
        sim.close()  # type: ignore[attr-defined]
        raise
    stage.sim = sim  # type: ignore[attr-defined]
    return stage


_OPENERS: dict[str, Callable[[str, DeviceURL], Stage]] = {
    "serial": _open_serial,
    "sim+grbl": _open_sim_grbl,
    "sim+zaber": _open_sim_zaber,
    "mock": lambda url, parsed: _open_sim_grbl(url, parsed, MOCK_DEFAULTS),
}
