"""The scan folder on disk: its manifest (read, appended, verified against the frames) and file helpers."""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.capture import load_sidecar, sha256_file
from mlaqc.errors import InputError

MANIFEST_NAME = "manifest.jsonl"
MANIFEST_FORMAT = "mlaqc-scan-manifest"


def _digest(obj: Any) -> str:
    """sha256 of an object's canonical JSON."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()


def _now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _fsync_dir(path: Path) -> None:
    """Make renames and new names in `path` durable."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@dataclass
class ManifestData:
    """A manifest as read: header, position records in file order, and whether the last line was torn."""

    header: dict[str, Any]
    records: list[dict[str, Any]]
    torn: bool = False


def read_manifest(path: str | os.PathLike[str]) -> ManifestData:
    """Parse a manifest; a torn (unterminated or unparsable) last line is reported, not fatal."""
    p = Path(path)
    try:
        blob = p.read_bytes()
    except FileNotFoundError:
        raise InputError(f"scan manifest {str(p)!r} does not exist") from None
    except OSError as exc:
        raise InputError(f"scan manifest {str(p)!r} cannot be read ({exc.strerror or exc})") from None
    lines = blob.split(b"\n")
    torn = False
    if lines and lines[-1] == b"":
        lines.pop()
    elif lines:
        torn = True  # the last line has no newline: an append was cut short
    parsed = []
    for k, line in enumerate(lines):
        try:
            obj = json.loads(line)
            if not isinstance(obj, dict):
                raise ValueError("not an object")
        except (ValueError, UnicodeDecodeError):
            if k == len(lines) - 1:
                torn = True
                continue
            raise InputError(f"scan manifest {str(p)!r} is damaged at line {k + 1}; it cannot be resumed") from None
        parsed.append(obj)
    if torn and parsed and len(parsed) == len(lines):
        parsed.pop()  # an unterminated line that happens to parse is still an unfinished append
    if not parsed or parsed[0].get("type") != "header" or parsed[0].get("format") != MANIFEST_FORMAT:
        raise InputError(f"{str(p)!r} is not an mlaqc scan manifest (no header line)")
    records = []
    for k, obj in enumerate(parsed[1:], start=2):
        if obj.get("type") != "position" or not isinstance(obj.get("index"), int) or not isinstance(obj.get("files"), list):
            raise InputError(f"scan manifest {str(p)!r} has an unknown record at line {k}; it cannot be resumed")
        records.append(obj)
    return ManifestData(parsed[0], records, torn)


def _manifest_bytes(header: dict[str, Any], records: list[dict[str, Any]]) -> bytes:
    return "".join(json.dumps(r, separators=(",", ":"), allow_nan=False) + "\n" for r in [header, *records]).encode()


class _ManifestWriter:
    """Appends one fsync'd line per completed position."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fh = open(path, "ab")

    def append(self, record: dict[str, Any]) -> None:
        line = (json.dumps(record, separators=(",", ":"), allow_nan=False) + "\n").encode()
        self._fh.write(line)
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self) -> None:
        self._fh.close()


def verify_record(out_dir: Path, record: dict[str, Any]) -> str | None:
    """None if every file of a manifest record exists and matches its recorded checksum; else why not."""
    for item in record.get("files", []):
        why = _verify_item(out_dir, record, item)
        if why:
            return why
    return None


def _verify_item(out_dir: Path, record: dict[str, Any], item: dict[str, Any]) -> str | None:
    """None if one listed frame and its sidecar are on disk with the recorded checksum; else why not."""
    name = item.get("file")
    if not isinstance(name, str) or "/" in name or name.startswith("."):
        return f"record {record.get('index')} names a bad file {name!r}"
    path = out_dir / name
    if not path.is_file():
        return f"{name} is missing"
    if sha256_file(path) != item.get("sha256"):
        return f"{name} does not match its recorded checksum"
    try:
        side = load_sidecar(path)
    except InputError as exc:
        return str(exc)
    if side.get("sha256") != item.get("sha256"):
        return f"the sidecar of {name} does not match its recorded checksum"
    return None


def verify_scan(out_dir: str | os.PathLike[str]) -> list[str]:
    """Problems with a finished scan folder: missing, altered or duplicated frames, stray temporary files."""
    out = Path(out_dir)
    data = read_manifest(out / MANIFEST_NAME)
    problems = []
    if data.torn:
        problems.append("the manifest's last line is torn")
    seen: set[int] = set()
    for rec in data.records:
        if rec["index"] in seen:
            problems.append(f"position {rec['index'] + 1} is recorded twice")
        seen.add(rec["index"])
        why = verify_record(out, rec)
        if why:
            problems.append(f"position {rec['index'] + 1}: {why}")
        for item in rec.get("rejected", []):  # (a rejected frame is evidence: checked here, not needed to resume)
            why = _verify_item(out, rec, item)
            if why:
                problems.append(f"position {rec['index'] + 1}, rejected frame: {why}")
    total = len(data.header.get("plan", {}).get("positions", []))
    missing = total - len(seen)
    if missing:
        problems.append(f"{missing} of {total} positions have no record")
    problems += [f"stray temporary file {p.name}" for p in _temp_files(out)]
    return problems


def _rejected_path(path: Path) -> Path:
    """`pos_00001.tiff` -> the first free `pos_00001_rejectedK.tiff` (K = 1, 2, ...): never overwrite a frame."""
    k = 1
    while True:
        candidate = path.with_name(f"{path.stem}_rejected{k}{path.suffix}")
        if not candidate.exists():
            return candidate
        k += 1


def _temp_files(out: Path) -> list[Path]:
    """Leftovers of atomic writes cut short (mlaqc.atomic names them '.<name>.<random>.part<suffix>')."""
    return sorted(p for p in out.glob(".*.part*") if p.is_file())
