"""Headless capture: frames (or averages of frames) from any Camera to raw files with provenance sidecars.

Files. Each saved frame is one raw file written atomically with `mlaqc.inspection.raw_write.write_raw` (TIFF or DNG,
bits/CFA/black/white level in the file's own mlaqc record, plus a compact `acquisition` record in its
metadata) and one sidecar ``<raw name>.meta.json`` beside it (e.g. ``frame_000001.tiff.meta.json``),
also written atomically, after the raw file. The sidecar is separate because it holds the raw file's
sha256, which the raw file cannot hold itself. A raw file without its sidecar is an incomplete capture
(a crash between the two writes); the scan runner re-captures such frames.

Sidecar (format ``mlaqc-frame``, version 1): ``file``, ``sha256``, ``bytes``, ``dark``, ``device``
(URL), ``camera`` (name), ``pixel_format``, ``bits``, ``cfa``, ``width``, ``height``, ``black_level``,
``white_level``, ``exposure_us`` and ``gain`` (read back with the frame), ``sequence`` (first frame),
``sequences`` (every frame averaged), ``sequence_gap`` (frames lost, summed), ``device_timestamp_s``,
``device_timestamps_s``, ``host_timestamp_s`` (Unix time), ``host_time`` (ISO 8601 UTC), ``average``
(``frames``, ``method`` 'mean, rounded half to even', ``significant_bits``), ``stage_position_mm``
(read back, or null), ``warnings`` (black / saturated / not-dark / sequence gap), ``device_extra``
(the driver's diagnostics, e.g. the mock's ground truth), ``context`` (caller's extra record, e.g. the
scan position) and ``versions``.

Averages: K frames are summed in float64, divided by K and rounded half to even into uint16, so the file
keeps the camera's bit depth (`significant_bits`); the averaging gain in SNR is in the values' fraction
only to the extent rounding keeps it.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import platform
import re
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.camera.base import DEFAULT_TIMEOUT_S, Camera, Frame
from mlaqc import __version__
from mlaqc.atomic import write_bytes_atomic
from mlaqc.errors import DeviceError, InputError
from mlaqc.inspection.raw_levels import check_exposure
from mlaqc.inspection.raw_write import write_raw
from mlaqc.inspection.rawio import RawFrame

log = logging.getLogger(__name__)

SIDECAR_FORMAT = "mlaqc-frame"
SIDECAR_SUFFIX = ".meta.json"
FILE_FORMATS = {"tiff": ".tiff", "dng": ".dng"}
MAX_AVERAGE = 10_000
MAX_FRAMES = 1_000_000
_PREFIX_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


@dataclass(frozen=True)
class Grab:
    """One saved image's pixels (a frame or the average of several) and the frames' provenance."""

    data: np.ndarray  # (H, W) uint16
    frames: tuple[Frame, ...]  # the frames averaged; their pixel arrays are not kept beyond the first
    camera: str = ""  # the camera's name

    @property
    def first(self) -> Frame:
        return self.frames[0]

    @property
    def last(self) -> Frame:
        return self.frames[-1]

    @property
    def sequence_gap(self) -> int:
        """Frames lost before or between the averaged frames (driver-reported gaps plus jumps in between)."""
        gap = sum(int(f.extra.get("sequence_gap") or 0) for f in self.frames[:1])
        for prev, cur in zip(self.frames, self.frames[1:]):
            gap += max(0, cur.sequence - prev.sequence - 1)
        return gap

    @property
    def black_level(self) -> int:
        return int(self.first.extra.get("black_level", 0))

    @property
    def white_level(self) -> int:
        white = self.first.extra.get("white_level")
        return int(white) if white is not None else self.first.max_value


@dataclass(frozen=True)
class SavedFrame:
    """A raw file and its sidecar as written."""

    path: Path
    sidecar: Path
    sha256: str
    record: dict[str, Any]

    @property
    def warnings(self) -> list[str]:
        return list(self.record.get("warnings", []))


def sidecar_path(raw_path: str | os.PathLike[str]) -> Path:
    """The sidecar of a raw file: ``<name>.meta.json``."""
    p = Path(raw_path)
    return p.with_name(p.name + SIDECAR_SUFFIX)


def sha256_file(path: str | os.PathLike[str]) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def versions() -> dict[str, str]:
    """Software versions for sidecars."""
    return {"mlaqc": __version__, "numpy": np.__version__, "python": platform.python_version(),
            "platform": platform.platform(terse=True)}


def file_suffix(file_format: str) -> str:
    """'.tiff' or '.dng' for a --format value; InputError otherwise."""
    suffix = FILE_FORMATS.get(str(file_format).lower())
    if suffix is None:
        raise InputError(f"file format {file_format!r} is not one of {', '.join(FILE_FORMATS)}")
    return suffix


# --------------------------------------------------------------------------------------------- grabbing


def grab(camera: Camera, average: int = 1, timeout_s: float = DEFAULT_TIMEOUT_S) -> Grab:
    """Capture one frame, or `average` frames averaged into one image (float mean, rounded to uint16)."""
    check_count("average", average, MAX_AVERAGE)
    first = camera.capture(timeout_s)
    if average == 1:
        return Grab(first.data, (first,), camera.name)
    total = first.data.astype(np.float64)
    frames = [first]
    for _ in range(average - 1):
        frame = camera.capture(timeout_s)
        if frame.data.shape != first.data.shape or frame.bits != first.bits:
            raise DeviceError(f"camera {camera.name} changed its frame size or bit depth while averaging "
                              f"({first.data.shape}, {first.bits} bits -> {frame.data.shape}, {frame.bits} bits)")
        total += frame.data
        frames.append(_without_pixels(frame))
    mean = np.rint(total / average)
    data = np.clip(mean, 0, first.max_value).astype(np.uint16)
    return Grab(data, (first, *frames[1:]), camera.name)


def _without_pixels(frame: Frame) -> Frame:
    """The same frame's provenance with a 1x1 placeholder instead of its pixels (averaging keeps memory flat)."""
    return Frame(np.zeros((1, 1), np.uint16), frame.bits, frame.pixel_format, frame.cfa, frame.sequence,
                 frame.device_timestamp_s, frame.host_timestamp_s, frame.exposure_us, frame.gain, frame.device,
                 dict(frame.extra))


def exposure_problem(g: Grab) -> str | None:
    """Why a grabbed image cannot be inspected (black or saturated: the inspection's own check), else None."""
    # Every 3rd pixel each way: the statistics are the same, 9x cheaper; an odd stride keeps every CFA site.
    sample = g.data[::3, ::3] if g.data.size > 90_000 else g.data
    raw = RawFrame(sample, max(8, g.first.bits), g.first.cfa, g.black_level, max(g.white_level, g.black_level + 1))
    try:
        check_exposure(raw)
    except InputError as exc:
        return str(exc).replace("Frame (in memory) ", "frame ")
    return None


def frame_warnings(g: Grab, *, dark: bool = False) -> list[str]:
    """Plain-language problems with a grabbed image: black (unless dark), not dark (if dark), saturated, gaps."""
    warnings = []
    problem = exposure_problem(g)
    if problem is not None and not (dark and " is black" in problem):
        warnings.append(problem)
    elif problem is None and dark:
        warnings.append("dark frame is not dark: light rises above the black level; cover the lens or "
                        "switch the light off")
    if g.sequence_gap:
        warnings.append(f"{g.sequence_gap} frame(s) were lost (sequence-number gap) while capturing")
    return warnings


# --------------------------------------------------------------------------------------------- saving


def save_frame(path: str | os.PathLike[str], g: Grab, *, dark: bool = False,
               position_mm: tuple[float, float] | None = None, context: dict[str, Any] | None = None,
               warnings: list[str] | None = None) -> SavedFrame:
    """Write the raw file, then its sidecar, both atomically; return what was written.

    The raw file's own metadata carries the acquisition facts too (no checksum); the sidecar adds the
    sha256 of the raw file as written."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FILE_FORMATS.values():
        raise InputError(f"Cannot write frame {path}: use one of {', '.join(FILE_FORMATS.values())}")
    warnings = frame_warnings(g, dark=dark) if warnings is None else warnings
    record = _record(path, g, dark, position_mm, context, warnings)
    acquisition = {k: record[k] for k in ("device", "camera", "pixel_format", "sequence", "sequences",
                                          "device_timestamp_s", "host_timestamp_s", "host_time", "exposure_us",
                                          "gain", "dark", "average", "stage_position_mm")}
    first = g.first
    write_raw(path, g.data, bits=max(8, first.bits), cfa=first.cfa, black_level=g.black_level,
              white_level=min(g.white_level, (1 << max(8, first.bits)) - 1),
              metadata={"acquisition": jsonable(acquisition)})
    digest = sha256_file(path)
    record["sha256"] = digest
    record["bytes"] = path.stat().st_size
    side = sidecar_path(path)
    try:
        write_bytes_atomic(side, (json.dumps(jsonable(record), indent=2, allow_nan=False) + "\n").encode("utf-8"))
    except OSError as exc:
        raise InputError(f"Cannot write sidecar {side}: {exc.strerror or exc}.") from None
    return SavedFrame(path, side, digest, record)


def _record(path: Path, g: Grab, dark: bool, position_mm: tuple[float, float] | None,
            context: dict[str, Any] | None, warnings: list[str]) -> dict[str, Any]:
    """The sidecar record (sha256 filled in after the write)."""
    first, frames = g.first, g.frames
    host = first.host_timestamp_s
    return {
        "format": SIDECAR_FORMAT,
        "version": 1,
        "file": path.name,
        "sha256": None,
        "bytes": None,
        "dark": bool(dark),
        "device": first.device,
        "camera": g.camera or first.device,
        "pixel_format": first.pixel_format,
        "bits": first.bits,
        "cfa": first.cfa,
        "width": int(g.data.shape[1]),
        "height": int(g.data.shape[0]),
        "black_level": g.black_level,
        "white_level": g.white_level,
        "exposure_us": first.exposure_us,
        "gain": first.gain,
        "sequence": first.sequence,
        "sequences": [f.sequence for f in frames],
        "sequence_gap": g.sequence_gap,
        "device_timestamp_s": first.device_timestamp_s,
        "device_timestamps_s": [f.device_timestamp_s for f in frames],
        "host_timestamp_s": host,
        "host_time": _dt.datetime.fromtimestamp(host, _dt.timezone.utc).isoformat(timespec="microseconds"),
        "average": {"frames": len(frames), "method": "mean, rounded half to even", "significant_bits": first.bits},
        "stage_position_mm": None if position_mm is None else [float(position_mm[0]), float(position_mm[1])],
        "warnings": list(warnings),
        "device_extra": first.extra,
        "context": context or {},
        "versions": versions(),
    }


def jsonable(value: Any) -> Any:
    """Plain JSON types (NaN/inf become null, numpy scalars become Python numbers)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        number = float(value)
        return number if np.isfinite(number) else None
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if value is None or isinstance(value, (str, int, bool)):
        return value
    return str(value)


def load_sidecar(raw_path: str | os.PathLike[str]) -> dict[str, Any]:
    """The sidecar record of a raw file; InputError if absent or not a frame sidecar."""
    side = sidecar_path(raw_path)
    try:
        record = json.loads(side.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"frame {raw_path} has no sidecar {side.name}") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"sidecar {side} is not readable JSON ({exc.__class__.__name__})") from None
    if not isinstance(record, dict) or record.get("format") != SIDECAR_FORMAT:
        raise InputError(f"{side} is not an mlaqc frame sidecar")
    return record


def verify_frame(raw_path: str | os.PathLike[str], sha256: str | None = None) -> str | None:
    """None if the raw file exists, has its sidecar and matches its checksum (and `sha256` if given); else why not."""
    path = Path(raw_path)
    if not path.is_file():
        return f"{path.name} is missing"
    try:
        record = load_sidecar(path)
    except InputError as exc:
        return str(exc)
    actual = sha256_file(path)
    if record.get("sha256") != actual:
        return f"{path.name} does not match the checksum in its sidecar"
    if sha256 is not None and sha256 != actual:
        return f"{path.name} does not match the checksum recorded for it"
    return None


# --------------------------------------------------------------------------------------------- capture job


def check_count(name: str, value: Any, maximum: int) -> int:
    """A whole number in 1..maximum, or InputError naming the option."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= maximum:
        raise InputError(f"{name} must be a whole number from 1 to {maximum}, got {value!r}")
    return int(value)


def check_out_dir(out_dir: str | os.PathLike[str]) -> Path:
    """An output folder that exists and is writable, or whose parent does (it is created at the first write)."""
    out = Path(out_dir)
    if out.exists():
        if not out.is_dir():
            raise InputError(f"output folder {str(out)!r} exists and is not a folder")
        if not os.access(out, os.W_OK | os.X_OK):
            raise InputError(f"output folder {str(out)!r} is not writable")
        return out
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"output folder {str(out)!r} cannot be created: its parent {str(parent)!r} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"output folder {str(out)!r} cannot be created: {str(parent)!r} is not writable")
    return out


def make_out_dir(out: Path) -> None:
    """Create the output folder (its parent was checked) if needed."""
    try:
        out.mkdir(exist_ok=True)
    except OSError as exc:
        raise InputError(f"output folder {str(out)!r} cannot be created ({exc.strerror or exc})") from None


def frame_names(out: Path, prefix: str, count: int, suffix: str) -> list[Path]:
    """``<prefix>_000001<suffix>`` ...; InputError if any of them (or its sidecar) already exists."""
    if not _PREFIX_RE.match(prefix):
        raise InputError(f"file prefix {prefix!r} must be 1-64 letters, digits, '_', '-' or '.', starting with a "
                         "letter or digit")
    paths = [out / f"{prefix}_{i:06d}{suffix}" for i in range(1, count + 1)]
    if out.is_dir():
        taken = [p for p in paths if p.exists() or sidecar_path(p).exists()]
        if taken:
            raise InputError(f"output folder {str(out)!r} already holds {taken[0].name}; choose another folder or "
                             "--prefix so no frame is overwritten")
    return paths


def apply_settings(camera: Camera, exposure_us: float | None, gain: float | None) -> dict[str, float]:
    """Set exposure and gain if given; return what the camera read back."""
    back: dict[str, float] = {}
    if exposure_us is not None:
        back["exposure_us"] = camera.set_exposure_us(exposure_us)
    if gain is not None:
        back["gain"] = camera.set_gain(gain)
    return back


def capture(camera: Camera, out_dir: str | os.PathLike[str], *, frames: int = 1, average: int = 1, dark: bool = False,
            exposure_us: float | None = None, gain: float | None = None, file_format: str = "tiff",
            prefix: str | None = None, timeout_s: float = DEFAULT_TIMEOUT_S,
            position_mm: tuple[float, float] | None = None, progress: Callable[[int, int], None] | None = None,
            on_warning: Callable[[str], None] | None = None) -> list[SavedFrame]:
    """Capture `frames` images (each the average of `average` frames) from an open camera into `out_dir`.

    Files are ``<prefix>_NNNNNN.tiff|dng`` plus ``.meta.json`` sidecars; `prefix` defaults to 'dark' for
    dark frames, else 'frame'. Everything is checked before the first frame is taken (no file is written
    for bad options, a bad folder or a name clash); the folder is created at the first write."""
    check_count("frames", frames, MAX_FRAMES)
    check_count("average", average, MAX_AVERAGE)
    suffix = file_suffix(file_format)
    out = check_out_dir(out_dir)
    names = frame_names(out, prefix or ("dark" if dark else "frame"), frames, suffix)
    apply_settings(camera, exposure_us, gain)
    saved: list[SavedFrame] = []
    for i, path in enumerate(names):
        g = grab(camera, average, timeout_s)
        if i == 0:
            make_out_dir(out)
        item = save_frame(path, g, dark=dark, position_mm=position_mm,
                          context={"capture": {"index": i + 1, "of": frames}})
        for text in item.warnings:
            (on_warning or log.warning)(f"{path.name}: {text}")
        saved.append(item)
        if progress is not None:
            progress(i + 1, frames)
    return saved


def format_choices() -> Sequence[str]:
    return tuple(FILE_FORMATS)


def print_warning(text: str) -> None:
    """Default warning sink of the CLI: one line on stderr."""
    print(f"warning: {text}", file=sys.stderr)
