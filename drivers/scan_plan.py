"""The scan plan: its TOML tables (format: see drivers.scan) validated into positions and capture settings."""

from __future__ import annotations

import hashlib
import json
import math
import os
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from drivers.capture import MAX_AVERAGE, file_suffix
from mlaqc.errors import InputError
from mlaqc.optics.config import CameraConfig, load_config
from mlaqc.optics.throughfocus import (F_NUMBER, FOCUS_OFFSET_MM, SPACING_LENSES, Carrier, ThroughFocus,
                                      coverage_offsets)

MAX_POSITIONS = 1_000_000
MAX_FRAMES_PER_POSITION = 100
HOME_CHOICES = ("auto", "always", "never")
SCAN_KEYS = {"settle_s", "frames_per_position", "average", "retries", "retry_delay_s", "move_timeout_s",
             "capture_timeout_s", "home", "format", "exposure_us", "gain"}
RASTER_KEYS = {"origin_mm", "step_mm", "count", "serpentine", "fast_axis"}
POSITION_KEYS = {"x_mm", "y_mm", "label"}
THROUGH_FOCUS_KEYS = {"focus_offsets_mm", "f_number", "spacing_lenses", "offsets", "exposure_us", "settle_s", "average",
                      "iris", "white_frames", "config", "z_white_mm", "a_centre_mm", "b_window_mm", "field_pitch_mm"}
IRIS_CHOICES = ("camera", "manual")
MAX_FOCUS_OFFSETS = 20
MAX_THROUGH_FOCUS_FRAMES = 1000


@dataclass(frozen=True)
class PlanPosition:
    """One stop of the scan: its 0-based index in plan order, target (mm) and label."""

    index: int
    x_mm: float
    y_mm: float
    label: str

    def file_names(self, frames: int, suffix: str) -> list[str]:
        """Raw file names of this position's frames."""
        base = f"pos_{self.index + 1:05d}"
        if frames == 1:
            return [base + suffix]
        return [f"{base}_f{k}{suffix}" for k in range(1, frames + 1)]


@dataclass(frozen=True)
class ThroughFocusPlan:
    """The plan's [through_focus] table, validated; `frames(cfg)` expands it for a camera."""

    focus_offsets_mm: tuple[float, ...] = (FOCUS_OFFSET_MM, -FOCUS_OFFSET_MM)  # the shipped protocol
    f_number: float = F_NUMBER  # (mlaqc.optics.throughfocus; the Carrier's defaults match)
    spacing_lenses: int = SPACING_LENSES
    offsets: str | tuple[tuple[int, int], ...] = "cover"
    exposure_us: float | None = None
    settle_s: float | None = None
    average: int | None = None
    iris: str = "camera"
    white_frames: bool = True
    config: str | None = None  # resolved path of a camera config, None = the camera's own or Table 1
    carrier: Carrier = field(default_factory=Carrier)

    def frames(self, cfg: CameraConfig) -> list[ThroughFocus]:
        """The frames of one position: each focus offset (outer) at each lattice offset (inner)."""
        offsets = self.offsets
        if offsets == "cover":
            covers = [coverage_offsets(cfg, ThroughFocus(u, self.f_number, self.spacing_lenses))
                      for u in self.focus_offsets_mm]
            if any(not c for c in covers):
                raise InputError(f"through_focus.offsets = 'cover' has no answer: at f/{self.f_number:g} the smallest "
                                 "lit disc cannot hold a whole lens; use larger focus offsets or a smaller f-number")
            offsets = tuple(max(covers, key=len))  # the smallest disc needs the finest set
        return [ThroughFocus(u, self.f_number, self.spacing_lenses, tuple(o)) for u in self.focus_offsets_mm
                for o in offsets]


@dataclass(frozen=True)
class ScanPlan:
    """A validated scan plan: positions in order plus how to capture at each."""

    positions: tuple[PlanPosition, ...]
    settle_s: float = 0.05
    frames_per_position: int = 1
    average: int = 1
    retries: int = 3
    retry_delay_s: float = 0.5
    move_timeout_s: float = 30.0
    capture_timeout_s: float = 5.0
    home: str = "auto"
    file_format: str = "tiff"
    exposure_us: float | None = None
    gain: float | None = None
    kind: str = "list"
    source: str = "plan"
    through_focus: ThroughFocusPlan | None = None

    @property
    def suffix(self) -> str:
        return file_suffix(self.file_format)

    def to_dict(self) -> dict[str, Any]:
        """JSON form (for the manifest header)."""
        d = asdict(self)
        d["positions"] = [[p.x_mm, p.y_mm, p.label] for p in self.positions]
        return d

    @property
    def digest(self) -> str:
        """sha256 over what ends up on disk: positions, labels, frames, averaging and file format.

        Timing, retries and settings that do not change which files exist may differ between a scan
        and its resumption."""
        key = {"positions": [[p.x_mm, p.y_mm, p.label] for p in self.positions],
               "frames_per_position": self.frames_per_position, "average": self.average,
               "format": self.file_format}
        if self.through_focus is not None:  # (absent from older plans' digests)
            tf = asdict(self.through_focus)
            key["through_focus"] = {k: tf[k] for k in ("focus_offsets_mm", "f_number", "spacing_lenses", "offsets",
                                                       "average", "white_frames", "carrier")}
        return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()


class _Checker:
    """Typed access to one plan table; InputError naming the key."""

    def __init__(self, source: str, section: str, table: Any, allowed: set[str]) -> None:
        self.source, self.section = source, section
        if not isinstance(table, dict):
            raise self.error(section, "must be a table")
        unknown = sorted(set(table) - allowed)
        if unknown:
            raise InputError(f"scan plan {source!r}: unknown key '{section}.{unknown[0]}'; expected some of "
                             f"{', '.join(sorted(allowed))}")
        self.table = table

    def error(self, key: str, what: str, value: Any = None) -> InputError:
        got = "" if value is None else f", got {value!r}"
        return InputError(f"scan plan {self.source!r}: key '{key}' {what}{got}")

    def key(self, name: str) -> str:
        return f"{self.section}.{name}" if self.section else name

    def number(self, name: str, default: float | None, *, minimum: float = 0.0, strict: bool = False) -> float | None:
        if name not in self.table:
            return default
        value = self.table[name]
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not ok or value < minimum or (strict and value <= minimum):
            bound = f"greater than {minimum:g}" if strict else f"at least {minimum:g}"
            raise self.error(self.key(name), f"must be a number {bound}", value)
        return float(value)

    def integer(self, name: str, default: int, minimum: int, maximum: int) -> int:
        if name not in self.table:
            return default
        value = self.table[name]
        if isinstance(value, bool) or not isinstance(value, int) or not minimum <= value <= maximum:
            raise self.error(self.key(name), f"must be a whole number from {minimum} to {maximum}", value)
        return value

    def choice(self, name: str, default: str, choices: tuple[str, ...]) -> str:
        if name not in self.table:
            return default
        value = self.table[name]
        if value not in choices:
            raise self.error(self.key(name), f"must be one of {', '.join(repr(c) for c in choices)}", value)
        return value

    def boolean(self, name: str, default: bool) -> bool:
        if name not in self.table:
            return default
        value = self.table[name]
        if not isinstance(value, bool):
            raise self.error(self.key(name), "must be true or false", value)
        return value

    def pair(self, name: str, *, integer: bool = False, required: bool = True) -> tuple[Any, Any]:
        if name not in self.table:
            if required:
                raise self.error(self.key(name), "is missing")
            return None  # type: ignore[return-value]
        value = self.table[name]
        kind = int if integer else (int, float)
        ok = (isinstance(value, list) and len(value) == 2
              and all(isinstance(v, kind) and not isinstance(v, bool) for v in value)
              and all(math.isfinite(v) for v in value))
        if not ok:
            what = "two whole numbers [x, y]" if integer else "two numbers [x, y] in mm"
            raise self.error(self.key(name), f"must be a list of {what}", value)
        return value[0], value[1]


def load_plan(path: str | os.PathLike[str]) -> ScanPlan:
    """Read and validate a scan plan TOML; InputError naming the file and key at fault."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_bytes().decode("utf-8"))
    except FileNotFoundError:
        raise InputError(f"scan plan {str(p)!r} does not exist") from None
    except IsADirectoryError:
        raise InputError(f"scan plan {str(p)!r} is a folder, not a TOML file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"scan plan {str(p)!r} cannot be read ({exc.__class__.__name__})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"scan plan {str(p)!r} is not valid TOML: {exc}") from None
    return plan_from_dict(data, str(p), base_dir=p.parent)


def plan_from_dict(data: dict[str, Any], source: str = "plan", base_dir: str | os.PathLike[str] | None = None) -> ScanPlan:
    """Build a validated ScanPlan from the TOML tables (`base_dir`: where relative paths in it start)."""
    _Checker(source, "", data, {"scan", "raster", "positions", "through_focus"})  # unknown top-level keys
    s = _Checker(source, "scan", data.get("scan", {}), SCAN_KEYS)
    if ("raster" in data) == ("positions" in data):
        raise InputError(f"scan plan {source!r} needs exactly one of a [raster] table or a [[positions]] list")
    if "raster" in data:
        positions, kind = _raster(source, data["raster"]), "raster"
    else:
        positions, kind = _position_list(source, data["positions"]), "list"
    frames = s.integer("frames_per_position", 1, 1, MAX_FRAMES_PER_POSITION)
    file_format = s.choice("format", "tiff", ("tiff", "dng"))
    return ScanPlan(
        positions=tuple(positions),
        settle_s=s.number("settle_s", 0.05, minimum=0.0),
        frames_per_position=frames,
        average=s.integer("average", 1, 1, MAX_AVERAGE),
        retries=s.integer("retries", 3, 0, 100),
        retry_delay_s=s.number("retry_delay_s", 0.5, minimum=0.0),
        move_timeout_s=s.number("move_timeout_s", 30.0, minimum=0.0, strict=True),
        capture_timeout_s=s.number("capture_timeout_s", 5.0, minimum=0.0, strict=True),
        home=s.choice("home", "auto", HOME_CHOICES),
        file_format=file_format,
        exposure_us=s.number("exposure_us", None, minimum=0.0, strict=True),
        gain=s.number("gain", None, minimum=0.0, strict=True),
        kind=kind,
        source=source,
        through_focus=(_through_focus(source, data["through_focus"], base_dir,
                                      s.number("exposure_us", None, minimum=0.0, strict=True))
                       if "through_focus" in data else None),
    )


def _through_focus(source: str, table: Any, base_dir: str | os.PathLike[str] | None,
                   scan_exposure: float | None) -> ThroughFocusPlan:
    """The [through_focus] table; InputError naming the key."""
    c = _Checker(source, "through_focus", table, THROUGH_FOCUS_KEYS)
    d = ThroughFocusPlan()
    offs = table.get("focus_offsets_mm", list(d.focus_offsets_mm))
    if (not isinstance(offs, list) or not 1 <= len(offs) <= MAX_FOCUS_OFFSETS
            or not all(isinstance(u, (int, float)) and not isinstance(u, bool) and math.isfinite(u) and abs(u) >= 0.5
                       for u in offs)
            or len({float(u) for u in offs}) != len(offs)):
        raise c.error("through_focus.focus_offsets_mm", f"must be a list of 1 to {MAX_FOCUS_OFFSETS} distinct distances "
                      "in mm, each at least 0.5 from zero (+ behind the MLA, - in front)", offs)
    f_number = c.number("f_number", d.f_number, minimum=1.0)
    spacing = c.integer("spacing_lenses", d.spacing_lenses, 2, 1000)
    offsets: str | tuple[tuple[int, int], ...] = d.offsets
    if "offsets" in table:
        raw = table["offsets"]
        if raw == "cover":
            offsets = "cover"
        else:
            ok = (isinstance(raw, list) and raw
                  and all(isinstance(o, list) and len(o) == 2
                          and all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v < spacing for v in o)
                          for o in raw))
            if not ok or len({tuple(o) for o in raw}) != len(raw):
                raise c.error("through_focus.offsets", f"must be \"cover\" or a non-empty list of distinct [x, y] whole "
                              f"lens pitches from 0 to {spacing - 1} (below spacing_lenses)", raw)
            offsets = tuple((int(o[0]), int(o[1])) for o in raw)
    iris = c.choice("iris", d.iris, IRIS_CHOICES)
    white = c.boolean("white_frames", d.white_frames)
    if iris == "manual" and white:
        raise c.error("through_focus.iris", "is 'manual' (the lens stays at f/N for the whole scan), so the white frames "
                      "would be stopped down too; set through_focus.white_frames = false and scan the white frames "
                      "with their own plan", iris)
    config = None
    if "config" in table:
        raw_cfg = table["config"]
        if not isinstance(raw_cfg, str) or not raw_cfg.strip():
            raise c.error("through_focus.config", "must be the path of a camera config TOML", raw_cfg)
        path = Path(raw_cfg)
        if not path.is_absolute() and base_dir is not None:
            path = Path(base_dir) / path
        try:
            load_config(path)
        except InputError as exc:
            raise c.error("through_focus.config", f"names an unusable camera config ({exc})") from None
        config = str(path)
    dc = d.carrier
    try:
        carrier = Carrier(focus_offsets_mm=tuple(float(u) for u in offs), spacing_lenses=spacing,
                          z_white_mm=c.number("z_white_mm", dc.z_white_mm, minimum=-math.inf),
                          a_centre_mm=c.number("a_centre_mm", dc.a_centre_mm, minimum=-math.inf),
                          b_window_mm=c.number("b_window_mm", dc.b_window_mm, minimum=-math.inf),
                          field_pitch_mm=c.number("field_pitch_mm", dc.field_pitch_mm, minimum=0.0, strict=True))
    except InputError as exc:
        raise InputError(f"scan plan {source!r}: [through_focus]: {exc}") from None
    plan = ThroughFocusPlan(
        focus_offsets_mm=tuple(float(u) for u in offs), f_number=f_number, spacing_lenses=spacing, offsets=offsets,
        exposure_us=c.number("exposure_us", None, minimum=0.0, strict=True),
        settle_s=c.number("settle_s", None, minimum=0.0),
        average=c.integer("average", None, 1, MAX_AVERAGE) if "average" in table else None,
        iris=iris, white_frames=white, config=config, carrier=carrier)
    if plan.exposure_us is not None and white and scan_exposure is None:
        raise c.error("through_focus.exposure_us", "needs scan.exposure_us too, so that the white frames get their own "
                      "exposure back after the through-focus frames", plan.exposure_us)
    if isinstance(offsets, tuple) and len(offsets) * len(offs) > MAX_THROUGH_FOCUS_FRAMES:
        raise c.error("through_focus.offsets", f"makes more than {MAX_THROUGH_FOCUS_FRAMES} frames per position",
                      table["offsets"])
    return plan


def _raster(source: str, table: Any) -> list[PlanPosition]:
    r = _Checker(source, "raster", table, RASTER_KEYS)
    ox, oy = r.pair("origin_mm")
    sx, sy = r.pair("step_mm")
    nx, ny = r.pair("count", integer=True)
    if nx < 1 or ny < 1 or nx * ny > MAX_POSITIONS:
        raise r.error("raster.count", f"must be at least [1, 1] and at most {MAX_POSITIONS} positions in all",
                      table["count"])
    if (nx > 1 and sx == 0) or (ny > 1 and sy == 0):
        raise r.error("raster.step_mm", "must be non-zero along an axis with more than one position", table["step_mm"])
    serpentine = r.boolean("serpentine", True)
    fast = r.choice("fast_axis", "x", ("x", "y"))
    n_fast, n_slow = (nx, ny) if fast == "x" else (ny, nx)
    positions = []
    for slow in range(n_slow):
        order = range(n_fast)
        if serpentine and slow % 2:
            order = reversed(order)
        for fast_i in order:
            i, j = (fast_i, slow) if fast == "x" else (slow, fast_i)
            x, y = ox + i * sx, oy + j * sy
            positions.append(PlanPosition(len(positions), round(x, 9), round(y, 9), f"r{j + 1:03d}c{i + 1:03d}"))
    return positions


def _position_list(source: str, items: Any) -> list[PlanPosition]:
    if not isinstance(items, list) or not items:
        raise InputError(f"scan plan {source!r}: key 'positions' must be a non-empty list of "
                         "[[positions]] tables with x_mm and y_mm")
    if len(items) > MAX_POSITIONS:
        raise InputError(f"scan plan {source!r}: key 'positions' has more than {MAX_POSITIONS} entries")
    positions, labels = [], set()
    for k, item in enumerate(items):
        c = _Checker(source, f"positions[{k}]", item, POSITION_KEYS)
        for name in ("x_mm", "y_mm"):
            if name not in item:
                raise c.error(c.key(name), "is missing")
        x = c.number("x_mm", None, minimum=-math.inf)
        y = c.number("y_mm", None, minimum=-math.inf)
        label = item.get("label", f"p{k + 1:05d}")
        if not isinstance(label, str) or not label.strip() or len(label) > 100:
            raise c.error(c.key("label"), "must be a non-empty string of at most 100 characters", label)
        if label in labels:
            raise c.error(c.key("label"), "repeats an earlier label", label)
        labels.add(label)
        positions.append(PlanPosition(k, float(x), float(y), label))
    return positions
