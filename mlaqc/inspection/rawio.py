"""Raw-image I/O: load and write single-channel raw frames (DNG, vendor raws, TIFF, PNG, NPY) bit-exactly.

Everything that can go wrong with an input file becomes an `InputError` with one sentence naming the file.

Where the acquisition facts live (bit depth, CFA pattern, black/white level, user metadata):
- DNG: the real DNG tags (BlackLevel, WhiteLevel, CFAPattern...) are authoritative and read through
  rawpy/LibRaw; an mlaqc JSON record in ImageDescription adds `bits` and the user metadata.
- TIFF: the mlaqc JSON record in ImageDescription (foreign TIFFs: BitsPerSample, CFA/BlackLevel/WhiteLevel tags).
- PNG, NPY: these formats have nowhere to put it, so `write_raw` writes a sidecar `<name>.json`
  (e.g. `white.png.json`) holding the same record; `load_raw` reads it when present.
- A sidecar that is not an mlaqc record is kept verbatim as `metadata["sidecar"]`; TIFF/DNG tags of
  interest (Make, Model, ExposureTime...) land in `metadata["tags"]`. Both keys are reserved.

Monochrome DNGs are written as PhotometricInterpretation LinearRaw with one sample (the DNG-spec way;
LibRaw reads it as a flat, one-colour raw); CFA DNGs as PhotometricInterpretation CFA with a 2x2
CFAPattern. Both read back bit-exactly through rawpy (tests prove it for mono and all four Bayer
patterns). LibRaw refuses raws under 22 or over 64000 pixels a side, so `write_raw` refuses such DNGs.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import partial
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc.atomic import atomic_path
from mlaqc.errors import InputError
from mlaqc.parallel import thread_map

CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")

RAWPY_SUFFIXES = frozenset(
    ".dng .nef .nrw .cr2 .cr3 .crw .arw .srf .sr2 .raf .orf .rw2 .pef .ptx .srw .x3f .3fr .fff .iiq "
    ".mos .mef .mrw .kdc .dcr .erf .raw .rwl .gpr".split()
)
TIFF_SUFFIXES = frozenset({".tif", ".tiff"})
WRITE_SUFFIXES = (".dng", ".tif", ".tiff", ".png", ".npy")
RECORD_KEY = "mlaqc_raw"  # marks a JSON object (ImageDescription or sidecar) as an mlaqc raw record
RESERVED_METADATA_KEYS = frozenset({"tags", "sidecar"})
DNG_MIN_SIDE, DNG_MAX_SIDE = 22, 64000  # LibRaw 0.22 rejects raws outside this (measured), so write_raw does too

_TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_CFA_CODE = {"R": 0, "G": 1, "B": 2}  # TIFF/EP CFAPattern colour codes
_TAGS_OF_INTEREST = (
    "Make", "Model", "UniqueCameraModel", "Software", "DateTime", "Artist", "ImageDescription",
    "ExposureTime", "ISOSpeedRatings", "FNumber", "FocalLength", "DateTimeOriginal", "BodySerialNumber",
)


@dataclass(frozen=True, eq=False)
class RawFrame:
    """One raw frame as the sensor delivered it, plus the facts needed to interpret its counts."""

    data: np.ndarray  # 2-D uint16 raw counts (float32 only when an NPY file held floats: counts, or 0..1)
    bits: int  # significant bit depth (8..16)
    cfa: str | None  # one of CFA_PATTERNS, or None for monochrome
    black_level: int
    white_level: int  # saturation value in counts
    metadata: dict = field(default_factory=dict)
    source: str = ""
    # where bits, black and white level came from: 'file' (tags, record, sidecar), 'container' (only the
    # container's dtype: `resolve_levels` refines them), 'normalized' (float data within 0..1: black 0,
    # white 1), or what resolved them ('option', 'config', 'data')
    levels_from: str = "file"

    def __post_init__(self) -> None:
        """Reject frames no later stage could interpret."""
        if not isinstance(self.data, np.ndarray) or self.data.ndim != 2:
            raise InputError(f"Raw frame {self.source or '(in memory)'} must be a 2-D array.")
        if not 8 <= self.bits <= 16:
            raise InputError(f"Raw frame {self.source or '(in memory)'} has bit depth {self.bits}, outside 8..16.")
        if self.cfa is not None and self.cfa not in CFA_PATTERNS:
            raise InputError(f"Raw frame {self.source or '(in memory)'} has unknown CFA pattern {self.cfa!r}.")
        if not 0 <= self.black_level < self.white_level:
            raise InputError(
                f"Raw frame {self.source or '(in memory)'} has black level {self.black_level} "
                f"not below white level {self.white_level}."
            )

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the frame."""
        return self.data.shape  # type: ignore[return-value]


# --------------------------------------------------------------------------------------------- writing


def write_raw(
    path: str | os.PathLike[str],
    data: np.ndarray,
    *,
    bits: int | None = None,
    cfa: str | None = None,
    black_level: int = 0,
    white_level: int | None = None,
    metadata: dict | None = None,
) -> None:
    """Write a 2-D uint16/uint8 frame atomically, format by suffix, so `load_raw` gets back the same frame.

    `bits` defaults to the dtype's depth (16 for uint16, 8 for uint8); `white_level` to 2**bits - 1.
    PNG and NPY get a sidecar `<name>.json` with bits, CFA, levels and metadata.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in WRITE_SUFFIXES:
        raise InputError(
            f"Cannot write raw file {path}: suffix {suffix or '(none)'} is not one of {', '.join(WRITE_SUFFIXES)}."
        )
    record = _write_record(path, data, bits, cfa, black_level, white_level, metadata)
    if suffix == ".dng" and not (DNG_MIN_SIDE <= min(data.shape) and max(data.shape) <= DNG_MAX_SIDE):
        raise InputError(
            f"Cannot write raw file {path}: LibRaw only reads DNGs {DNG_MIN_SIDE}..{DNG_MAX_SIDE} pixels a side, "
            f"not {data.shape[0]}x{data.shape[1]}; use TIFF or NPY."
        )
    try:
        if suffix == ".dng":
            with atomic_path(path) as tmp:
                _write_dng(tmp, data, record)
        elif suffix in TIFF_SUFFIXES:
            with atomic_path(path) as tmp:
                _write_tiff(tmp, data, record)
        else:
            _write_with_sidecar(path, data, record, suffix)
    except OSError as exc:
        raise InputError(f"Cannot write raw file {path}: {exc.strerror or exc}.") from None


def _write_record(
    path: Path, data: Any, bits: int | None, cfa: str | None, black: int, white: int | None, metadata: dict | None
) -> dict:
    """Validate write_raw's arguments and return the JSON record that describes the frame."""
    where = f"Cannot write raw file {path}:"
    if not isinstance(data, np.ndarray) or data.dtype not in (np.uint16, np.uint8):
        kind = data.dtype if isinstance(data, np.ndarray) else type(data).__name__
        raise InputError(f"{where} data must be a uint16 or uint8 array, not {kind}.")
    if data.ndim != 2 or 0 in data.shape:
        raise InputError(f"{where} data must be a non-empty 2-D array, not shape {data.shape}.")
    dtype_bits = data.dtype.itemsize * 8
    bits = dtype_bits if bits is None else bits
    if not isinstance(bits, (int, np.integer)) or not 8 <= bits <= dtype_bits:
        raise InputError(f"{where} bits={bits!r} must be an integer in 8..{dtype_bits} for {data.dtype} data.")
    if cfa is not None and (not isinstance(cfa, str) or cfa.upper() not in CFA_PATTERNS):
        raise InputError(f"{where} cfa={cfa!r} must be None or one of {', '.join(CFA_PATTERNS)}.")
    full = (1 << int(bits)) - 1
    white = full if white is None else white
    for name, value in (("black_level", black), ("white_level", white)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool):
            raise InputError(f"{where} {name}={value!r} must be an integer.")
    if not 0 <= black < white <= full:
        raise InputError(f"{where} levels must satisfy 0 <= black_level ({black}) < white_level ({white}) <= {full}.")
    if int(data.max()) > full:
        raise InputError(f"{where} data reach {int(data.max())}, above the {bits}-bit maximum {full}.")
    metadata = {} if metadata is None else metadata
    if not isinstance(metadata, dict):
        raise InputError(f"{where} metadata must be a dict, not {type(metadata).__name__}.")
    clash = RESERVED_METADATA_KEYS.intersection(metadata)
    if clash:
        raise InputError(f"{where} metadata keys {sorted(clash)} are reserved for file tags and sidecars.")
    try:
        json.dumps(metadata, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where} metadata is not JSON-serialisable ({exc}).") from None
    return {
        RECORD_KEY: 1,
        "bits": int(bits),
        "cfa": None if cfa is None else cfa.upper(),
        "black_level": int(black),
        "white_level": int(white),
        "metadata": metadata,
    }


def _record_json(record: dict) -> str:
    """The record as compact ASCII JSON (TIFF ImageDescription must be 7-bit ASCII)."""
    return json.dumps(record, ensure_ascii=True, separators=(",", ":"))


def _write_dng(tmp: Path, data: np.ndarray, record: dict) -> None:
    """Write a DNG that LibRaw reads back bit-exactly: LinearRaw mono or 2x2 Bayer CFA."""
    import tifffile

    extratags: list[tuple] = [
        (50706, 1, 4, (1, 4, 0, 0), True),  # DNGVersion 1.4
        (50707, 1, 4, (1, 1, 0, 0), True),  # DNGBackwardVersion 1.1
        (50708, 2, 0, "mlaqc", True),  # UniqueCameraModel
        (50714, 4, 1, (record["black_level"],), True),  # BlackLevel
        (50717, 4, 1, (record["white_level"],), True),  # WhiteLevel
    ]
    cfa = record["cfa"]
    if cfa is not None:
        identity = (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)
        extratags += [
            (33421, 3, 2, (2, 2), True),  # CFARepeatPatternDim
            (33422, 1, 4, tuple(_CFA_CODE[c] for c in cfa), True),  # CFAPattern
            (50710, 1, 3, (0, 1, 2), True),  # CFAPlaneColor R, G, B
            (50711, 3, 1, (1,), True),  # CFALayout rectangular
            (50721, 10, 9, identity, True),  # ColorMatrix1 (identity: no colour science here)
            (50778, 3, 1, (21,), True),  # CalibrationIlluminant1 D65
            (50728, 5, 3, (1, 1, 1, 1, 1, 1), True),  # AsShotNeutral
        ]
    # tifffile refuses to write LinearRaw with one sample, so mono is written MinIsBlack and patched in place.
    photometric = 32803 if cfa is not None else "minisblack"
    tifffile.imwrite(
        tmp, data, photometric=photometric, description=_record_json(record), software="mlaqc",
        subfiletype=0, metadata=None, extratags=extratags,
    )
    if cfa is None:
        with tifffile.TiffFile(tmp, mode="r+b") as tif:
            tif.pages[0].tags["PhotometricInterpretation"].overwrite(34892)  # LinearRaw


def _write_tiff(tmp: Path, data: np.ndarray, record: dict) -> None:
    """Write a plain single-page TIFF (8 or 16 bit) with the record in ImageDescription."""
    import tifffile

    tifffile.imwrite(
        tmp, data, photometric="minisblack", description=_record_json(record), software="mlaqc", metadata=None
    )


def _write_with_sidecar(path: Path, data: np.ndarray, record: dict, suffix: str) -> None:
    """Write a PNG or NPY plus its sidecar record; neither is renamed into place unless both were written."""
    if suffix == ".png":
        import cv2

        ok, buf = cv2.imencode(".png", data)
        if not ok:
            raise InputError(f"Cannot write raw file {path}: OpenCV failed to encode it as PNG.")
        payload = buf.tobytes()
    with atomic_path(_sidecar_path(path)) as tmp_json, atomic_path(path) as tmp:
        tmp_json.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
        if suffix == ".png":
            tmp.write_bytes(payload)
        else:
            with open(tmp, "wb") as fh:
                np.save(fh, data, allow_pickle=False)


def _sidecar_path(path: Path) -> Path:
    """The sidecar JSON beside a raw file: `<name>.json`."""
    return path.with_name(path.name + ".json")


# --------------------------------------------------------------------------------------------- loading


def load_raw(path: str | os.PathLike[str], *, expected_shape: tuple[int, int] | None = None,
             mapped: bool = False) -> RawFrame:
    """Load a raw frame from DNG/vendor raw, TIFF, PNG or NPY; any problem is an InputError naming the file.

    `mapped`: an uncompressed TIFF's pixels are mapped from the file, not read: only the pages the caller
    touches are read (a pinhole frame's analysis reads a quarter of its rows). For callers that are done
    with the frame before the file could change: a frame written in place of it (os.replace, as every
    mlaqc writer does) leaves the mapping intact, a file cut short under it would not."""
    path = Path(path)
    name = str(path)
    _check_file(path)
    suffix = path.suffix.lower()
    loader = _loader_for(suffix)
    if loader is None:
        kinds = "DNG, a camera raw, TIFF, PNG or NPY"
        raise InputError(f"Raw file {name} has unsupported type {suffix or '(no suffix)'}; use {kinds}.")
    try:
        sidecar = _read_sidecar(path)
        frame = _load_tiff(path, sidecar, mapped=True) if mapped and loader is _load_tiff else loader(path, sidecar)
    except InputError:
        raise
    except MemoryError:
        raise InputError(f"Raw file {name} is too large to load into memory.") from None
    except Exception as exc:  # noqa: BLE001 - decoder internals must never leak past this point
        kind = "TIFF" if suffix in TIFF_SUFFIXES else suffix[1:].upper()
        raise InputError(f"Raw file {name} is corrupt or not a readable {kind} file ({_short(exc)}).") from None
    if expected_shape is not None and tuple(frame.data.shape) != tuple(expected_shape):
        (rows, cols), (want_rows, want_cols) = frame.data.shape, expected_shape
        raise InputError(
            f"Raw file {name} is {rows}x{cols} pixels (rows x cols) but {want_rows}x{want_cols} was expected."
        )
    return frame


def _loader_for(suffix: str) -> Any:
    """The loader function for a lower-case suffix, or None when the type is unsupported."""
    if suffix in RAWPY_SUFFIXES:
        return _load_rawpy
    if suffix in TIFF_SUFFIXES:
        return _load_tiff
    return {".png": _load_png, ".npy": _load_npy}.get(suffix)


def _short(exc: BaseException) -> str:
    """A decoder exception squeezed into a clause: its type and first line, no trailing period."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    if text.startswith("b'") or text.startswith('b"'):
        text = text[2:-1]
    text = text.rstrip(".")
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _check_file(path: Path) -> None:
    """Missing, not a regular file, unreadable or empty -> InputError."""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise InputError(f"Raw file {path} does not exist.") from None
    except OSError as exc:
        raise InputError(f"Raw file {path} cannot be accessed ({exc.strerror or exc}).") from None
    if path.is_dir():
        raise InputError(f"Raw file {path} is a directory, not a file.")
    if st.st_size == 0:
        raise InputError(f"Raw file {path} is empty (0 bytes).")
    if not os.access(path, os.R_OK):
        raise InputError(f"Raw file {path} is not readable (permission denied).")


def _read_sidecar(path: Path) -> dict | None:
    """The sidecar JSON object beside `path`, or None when there is none."""
    side = _sidecar_path(path)
    if not side.is_file():
        return None
    try:
        obj = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"Sidecar {side} of raw file {path} is not valid JSON ({_short(exc)}).") from None
    if not isinstance(obj, dict):
        raise InputError(f"Sidecar {side} of raw file {path} must hold a JSON object.")
    return obj


def _split_record(obj: dict | None, path: Path, origin: str) -> tuple[dict | None, dict]:
    """Split a JSON object into (validated mlaqc record or None, metadata contribution)."""
    if obj is None:
        return None, {}
    if RECORD_KEY not in obj:
        return None, {"sidecar": obj}
    rec = {k: obj.get(k) for k in ("bits", "cfa", "black_level", "white_level")}
    meta = obj.get("metadata") or {}
    ok = (
        isinstance(rec["bits"], int) and 8 <= rec["bits"] <= 16
        and (rec["cfa"] is None or rec["cfa"] in CFA_PATTERNS)
        and isinstance(rec["black_level"], int) and isinstance(rec["white_level"], int)
        and 0 <= rec["black_level"] < rec["white_level"]
        and isinstance(meta, dict)
    )
    if not ok:
        raise InputError(f"The mlaqc record in the {origin} of raw file {path} is inconsistent or damaged.")
    return rec, dict(meta)


@contextlib.contextmanager
def _quiet_tifffile() -> Iterator[None]:
    """Silence tifffile's logger while we probe files; its complaints become our InputError instead."""
    logger = logging.getLogger("tifffile")
    previous = logger.disabled
    logger.disabled = True
    try:
        yield
    finally:
        logger.disabled = previous


@contextlib.contextmanager
def _quiet_opencv() -> Iterator[None]:
    """Silence OpenCV's decoder log while decoding; a failed decode becomes our InputError instead."""
    import cv2

    log = cv2.utils.logging
    previous = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        log.setLogLevel(previous)


def _tiff_info(path: Path, *, check_truncation: bool = True) -> dict | None:
    """Tags of a TIFF-structured file's first IFD (EXIF merged in), or None when it is not TIFF-structured.

    With `check_truncation`, raises InputError when an IFD's image data runs past the end of the file:
    caught here, before LibRaw or tifffile would print to stderr or hand back zero-filled pixels.
    """
    import tifffile

    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic not in _TIFF_MAGIC:
        return None
    try:
        with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
            if check_truncation:
                _check_tiff_extent(tif, path)
            tags = {t.name: t.value for t in tif.pages[0].tags.values()}
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - tifffile's parse errors become one sentence
        raise InputError(f"Raw file {path} has a corrupt TIFF structure ({_short(exc)}).") from None
    exif = tags.pop("ExifTag", None)
    if isinstance(exif, dict):
        tags.update(exif)
    return tags


def _check_tiff_extent(tif: Any, path: Path, max_pages: int = 8) -> None:
    """InputError if the image data of the first IFDs (and their SubIFDs) extend past the end of the file."""
    size = path.stat().st_size
    pages = [tif.pages[i] for i in range(min(len(tif.pages), max_pages))]
    for page in list(pages):
        with contextlib.suppress(Exception):
            pages.extend(page.pages or ())
    for page in pages:
        ends = [int(o) + int(n) for o, n in zip(page.dataoffsets, page.databytecounts) if n]
        if ends and max(ends) > size:
            raise InputError(
                f"Raw file {path} is truncated: its image data need {max(ends)} bytes but the file has {size}."
            )


def _vendor_tags(path: Path, suffix: str) -> dict | None:
    """Best-effort TIFF tags of a DNG (truncation checked) or vendor raw (never blocks: LibRaw decides)."""
    if suffix == ".dng":
        return _tiff_info(path)
    try:
        return _tiff_info(path, check_truncation=False)
    except Exception:  # noqa: BLE001 - maker-specific TIFF oddities are LibRaw's business, not ours
        return None


def _description_record(tags: dict | None, path: Path) -> tuple[dict | None, dict, dict]:
    """From TIFF tags: (mlaqc record or None, user metadata, JSON-safe tags of interest)."""
    if tags is None:
        return None, {}, {}
    desc = tags.get("ImageDescription")
    record, meta = None, {}
    if isinstance(desc, str) and desc.lstrip().startswith("{"):
        with contextlib.suppress(ValueError):
            obj = json.loads(desc)
            if isinstance(obj, dict) and RECORD_KEY in obj:
                record, meta = _split_record(obj, path, "ImageDescription")
    interest = {
        k: _jsonable(tags[k]) for k in _TAGS_OF_INTEREST
        if k in tags and not (k == "ImageDescription" and record is not None)
        and not (k == "Software" and tags[k] == "mlaqc")
    }
    return record, meta, interest


def _jsonable(value: Any) -> Any:
    """Turn a TIFF tag value into something json.dumps accepts."""
    if isinstance(value, bytes):
        return value.decode("latin-1").rstrip("\x00")
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (tuple, list)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def _merge_metadata(path: Path, embedded_meta: dict, sidecar: dict | None, tags: dict) -> tuple[dict | None, dict]:
    """Combine embedded metadata, sidecar and tags into one dict; also return the sidecar's record."""
    side_record, side_meta = _split_record(sidecar, path, "sidecar")
    metadata = {**side_meta, **embedded_meta}
    if tags:
        metadata["tags"] = tags
    return side_record, metadata


def _load_rawpy(path: Path, sidecar: dict | None) -> RawFrame:
    """DNG and vendor raws through rawpy/LibRaw: visible raw counts, black/white level, Bayer pattern."""
    tags = _vendor_tags(path, path.suffix.lower())
    record, meta, interest = _description_record(tags, path)
    side_record, metadata = _merge_metadata(path, meta, sidecar, interest)
    own = _own_dng_data(path) if record is not None else None
    if own is not None:  # our own uncompressed DNG: the same counts LibRaw gives, 10x faster (tests check)
        return _frame_from_record(own, record["bits"], record, metadata, path)
    import rawpy  # (only here: our own DNGs need no LibRaw, nor its import)

    try:
        with rawpy.imread(str(path)) as raw:
            data = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            blacks = [int(b) for b in raw.black_level_per_channel]
            white = int(raw.white_level)
            cfa = _rawpy_cfa(raw, path)
    except rawpy.LibRawFileUnsupportedError:
        raise InputError(f"Raw file {path} is not a raw format LibRaw recognises (corrupt or unsupported).") from None
    except (rawpy.LibRawIOError, rawpy.LibRawDataError):
        raise InputError(f"Raw file {path} is truncated or its image data is corrupt.") from None
    except rawpy.LibRawError as exc:
        raise InputError(f"Raw file {path} cannot be decoded by LibRaw ({_short(exc)}).") from None
    if data.ndim != 2 or data.size == 0:
        raise InputError(f"Raw file {path} holds no 2-D raw image (shape {data.shape}).")
    if len(set(blacks)) > 1:
        metadata.setdefault("tags", {})["BlackLevelPerChannel"] = blacks
    black = int(round(float(np.mean(blacks))))
    white = max(white, black + 1)
    bits = (record or side_record or {}).get("bits") or min(16, max(8, white.bit_length()))
    return RawFrame(data, int(bits), cfa, black, white, metadata, str(path))


def _own_dng_data(path: Path) -> np.ndarray | None:
    """The counts of a DNG that `write_raw` wrote (one uncompressed 16-bit plane), read directly; None
    for anything else, which LibRaw then decodes."""
    import tifffile

    with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        if page.compression != 1 or page.samplesperpixel != 1 or page.ndim != 2 or page.dtype != np.uint16:
            return None
        data = page.asarray()
    return data if data.size else None


def _rawpy_cfa(raw: Any, path: Path) -> str | None:
    """The 2x2 Bayer pattern LibRaw reports, as e.g. "RGGB"; None for monochrome; InputError for others."""
    pattern = raw.raw_pattern
    if raw.num_colors == 1 or pattern is None or pattern.size <= 1:
        return None
    desc = raw.color_desc.decode("ascii", "replace")
    if pattern.shape != (2, 2):
        rows, cols = pattern.shape
        raise InputError(f"Raw file {path} uses a {rows}x{cols} CFA (e.g. X-Trans); only 2x2 Bayer is supported.")
    letters = "".join(desc[int(i)] if 0 <= int(i) < len(desc) else "?" for i in pattern.ravel())
    if letters not in CFA_PATTERNS:
        raise InputError(f"Raw file {path} has CFA pattern {letters}; only {', '.join(CFA_PATTERNS)} are supported.")
    return letters


def _load_tiff(path: Path, sidecar: dict | None, mapped: bool = False) -> RawFrame:
    """TIFF through tifffile: first page, 8- or 16-bit single channel; `mapped` as `load_raw` says."""
    import tifffile

    tags = _tiff_info(path)
    if tags is None:
        raise InputError(f"Raw file {path} is not a TIFF file (bad header).")
    record, meta, interest = _description_record(tags, path)
    side_record, metadata = _merge_metadata(path, meta, sidecar, interest)
    with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        if page.samplesperpixel != 1 or page.ndim != 2:
            raise InputError(
                f"Raw file {path} has shape {page.shape} ({page.samplesperpixel} samples per pixel); "
                "a raw frame must be a single-channel 2-D image."
            )
        data = _mapped_page(tif, page, path) if mapped else None
        if data is None:
            data = page.asarray()
    data = _integer_data(data, path)
    bits = 8 if data.dtype == np.uint8 else 16
    data = data.astype(np.uint16, copy=False)  # the page's array is ours: no 8 MB copy when already 16-bit
    if record or side_record:
        return _frame_from_record(data, bits, record or side_record, metadata, path)
    black = _int_tag(tags, "BlackLevel", 0, np.mean)
    white = max(_int_tag(tags, "WhiteLevel", (1 << bits) - 1, np.max), black + 1)
    tagged = "BlackLevel" in tags or "WhiteLevel" in tags
    return RawFrame(data, bits, _tiff_cfa(tags), black, white, metadata, str(path),
                    "file" if tagged else "container")


def _mapped_page(tif: Any, page: Any, path: Path) -> np.ndarray | None:
    """The page's pixels mapped read-only from the file (the extent was checked by `_tiff_info`), or None
    where they are not stored as one plain native-order block (compressed, in strips apart, big-endian)."""
    if page.dtype is None or not page.is_memmappable or not page.is_contiguous:
        return None
    dtype = np.dtype(tif.byteorder + page.dtype.char)
    if not dtype.isnative or dtype not in (np.uint8, np.uint16):
        return None
    return np.asarray(np.memmap(path, dtype=dtype, mode="r", offset=int(page.dataoffsets[0]), shape=page.shape))


def _int_tag(tags: dict, name: str, default: int, reduce: Any) -> int:
    """An integer level tag (reduced over channels), or `default` when absent or not plain integers."""
    values = np.atleast_1d(np.asarray(tags.get(name, default)))
    if values.dtype.kind not in "ui" or values.size == 0:
        return default
    return int(round(float(reduce(values))))


def _tiff_cfa(tags: dict) -> str | None:
    """A 2x2 Bayer pattern from TIFF/EP CFA tags of a foreign TIFF, else None."""
    dims, pattern = tags.get("CFARepeatPatternDim"), tags.get("CFAPattern")
    if dims is None or pattern is None or tuple(dims) != (2, 2):
        return None
    codes = bytes(pattern) if not isinstance(pattern, bytes) else pattern
    letters = "".join({0: "R", 1: "G", 2: "B"}.get(c, "?") for c in codes[:4])
    return letters if letters in CFA_PATTERNS else None


def _integer_data(data: np.ndarray, path: Path) -> np.ndarray:
    """Accept uint8/uint16 pixel data only; anything else is an unsupported dtype."""
    if data.dtype not in (np.uint8, np.uint16):
        raise InputError(f"Raw file {path} holds {data.dtype} pixels; only uint8 and uint16 raw counts are supported.")
    return data


def _load_png(path: Path, sidecar: dict | None) -> RawFrame:
    """PNG through OpenCV (IMREAD_UNCHANGED), after checking signature and chunk CRCs (truncation, corruption)."""
    import cv2

    blob = path.read_bytes()
    if not blob.startswith(_PNG_MAGIC) or blob[12:16] != b"IHDR":
        raise InputError(f"Raw file {path} is not a PNG file (bad signature or header).")
    _check_png_chunks(blob, path)
    with _quiet_opencv():
        data = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise InputError(f"Raw file {path} is a corrupt PNG that OpenCV cannot decode.")
    if data.ndim != 2:
        raise InputError(
            f"Raw file {path} is a {data.shape[2]}-channel (colour or alpha) PNG, not a single-channel 2-D raw frame."
        )
    data = _integer_data(data, path)
    record, metadata = _merge_metadata(path, {}, sidecar, {})
    return _frame_from_record(data.astype(np.uint16), 8 if data.dtype == np.uint8 else 16, record, metadata, path)


def _check_png_chunks(blob: bytes, path: Path) -> None:
    """Walk the PNG chunks and verify each CRC, so truncation and corruption are caught before libpng prints."""
    pos = len(_PNG_MAGIC)
    while pos + 12 <= len(blob):
        length = int.from_bytes(blob[pos : pos + 4], "big")
        kind = blob[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > len(blob):
            break
        if zlib.crc32(blob[pos + 4 : end - 4]) != int.from_bytes(blob[end - 4 : end], "big"):
            name = kind.decode("latin-1")
            raise InputError(f"Raw file {path} is a corrupt PNG (checksum error in its {name} chunk).")
        if kind == b"IEND":
            return
        pos = end
    raise InputError(f"Raw file {path} is truncated (its PNG chunks stop before the end chunk).")


def _load_npy(path: Path, sidecar: dict | None) -> RawFrame:
    """NPY through np.load(allow_pickle=False): 2-D uint8/uint16, or finite floats kept as float32."""
    with open(path, "rb") as fh:
        if fh.read(6) != b"\x93NUMPY":
            raise InputError(f"Raw file {path} is not a NumPy .npy file (bad header).")
    try:
        data = np.load(path, allow_pickle=False)
    except ValueError as exc:
        msg = str(exc)
        if "pickle" in msg or "Object arrays" in msg:
            raise InputError(f"Raw file {path} holds Python objects, not numeric pixel data.") from None
        raise InputError(f"Raw file {path} is truncated or corrupt ({_short(exc)}).") from None
    except EOFError:
        raise InputError(f"Raw file {path} is truncated (unexpected end of file).") from None
    if not isinstance(data, np.ndarray) or data.ndim != 2:
        shape = getattr(data, "shape", None)
        raise InputError(f"Raw file {path} holds an array of shape {shape}; a raw frame must be 2-D.")
    if 0 in data.shape:
        raise InputError(f"Raw file {path} holds an empty {data.shape} array.")
    record, metadata = _merge_metadata(path, {}, sidecar, {})
    if data.dtype.kind == "f":
        if not np.isfinite(data).all():
            bad = int(data.size - np.count_nonzero(np.isfinite(data)))
            raise InputError(f"Raw file {path} contains {bad} NaN or infinite values.")
        data = data.astype(np.float32)
        if record is None and _normalized_floats(data):
            # a frame already scaled to 0..1 (white 1.0, black 0), not counts: read as 16-bit counts it
            # would sit under 2e-5 of full scale and be refused as black
            return RawFrame(data, 16, None, 0, 1, metadata, str(path), "normalized")
        return _frame_from_record(data, 16, record, metadata, path)
    data = _integer_data(data, path)
    return _frame_from_record(data.astype(np.uint16), 8 if data.dtype == np.uint8 else 16, record, metadata, path)


def _normalized_floats(data: np.ndarray) -> bool:
    """A float frame whose values all lie within [0, 1] and are not all integers: a normalized frame (a
    frame of float counts, or one holding only 0 and 1, is not)."""
    lo, hi = float(data.min()), float(data.max())
    return 0.0 <= lo and hi <= 1.0 and not bool(np.all(data == np.round(data)))


def _frame_from_record(data: np.ndarray, bits: int, record: dict | None, metadata: dict, path: Path) -> RawFrame:
    """Frame whose acquisition facts come from the sidecar record, or from the dtype when there is none."""
    if record is None:
        return RawFrame(data, bits, None, 0, (1 << bits) - 1, metadata, str(path), "container")
    r = record
    return RawFrame(data, r["bits"], r["cfa"], r["black_level"], r["white_level"], metadata, str(path))


# --------------------------------------------------------------------------------------------- levels

STANDARD_BITS = (8, 10, 12, 14, 16)


@dataclass(frozen=True)
class Levels:
    """Bit depth and black level a user states for a frame (`--bit-depth`, `--black-level`); None: unknown."""

    bits: int | None = None
    black: int | None = None

    def __post_init__(self) -> None:
        if self.bits is not None and not 8 <= self.bits <= 16:
            raise InputError(f"The bit depth {self.bits} is outside 8..16.")
        if self.black is not None and not 0 <= self.black < (1 << (self.bits or 16)) - 1:
            raise InputError(f"The black level {self.black} does not fit {self.bits or 16}-bit counts.")


def resolve_levels(frame: RawFrame, stated: Levels | None = None, sensor: Levels | None = None) -> RawFrame:
    """The frame with its significant bits, black and white level settled, for any container.

    Order: what the user `stated` (always wins); then the file's own tags, record or sidecar; for a
    container without them (a 16-bit TIFF, PNG or NPY of 12-bit data), the camera config's `sensor` when
    the data agree with it (no count above its white level, its dark pixels not below its black level),
    else the data: the smallest standard depth that holds the brightest count, and the black level of
    the unlit pixels (`unlit_level`). The white level is then the top of that depth, so the black and
    saturation checks are relative to the real scale."""
    stated = stated or Levels()
    if frame.data.dtype.kind == "f" or (frame.levels_from != "container" and stated == Levels()):
        return frame
    top = int(frame.data.max())
    dark = unlit_level(frame.data)
    container_bits = frame.bits
    bits, black, source = frame.bits, frame.black_level, frame.levels_from
    if frame.levels_from == "container":
        sensor_ok = (sensor is not None and sensor.bits is not None and sensor.bits <= container_bits
                     and top <= (1 << sensor.bits) - 1 and (sensor.black or 0) <= dark + 2)
        if sensor_ok:
            bits, black, source = sensor.bits, sensor.black or 0, "config"
        else:
            bits = next(b for b in STANDARD_BITS if top <= (1 << b) - 1 and b <= max(container_bits, 8)) \
                if top <= (1 << container_bits) - 1 else container_bits
            black, source = int(round(min(dark, ((1 << bits) - 1) / 8))), "data"
    if stated.bits is not None:
        bits, source = stated.bits, "option"
        if top > (1 << bits) - 1:
            raise InputError(f"Frame {frame.source or '(in memory)'} has counts up to {top}, more than "
                             f"{bits} bits hold; check --bit-depth.")
    if stated.black is not None:
        black, source = stated.black, "option"
    white = (1 << bits) - 1 if (frame.levels_from == "container" or stated.bits is not None) else frame.white_level
    if not black < white:
        raise InputError(f"Frame {frame.source or '(in memory)'}: black level {black} is not below the white "
                         f"level {white}.")
    return RawFrame(frame.data, bits, frame.cfa, int(black), int(white), frame.metadata, frame.source, source)


def unlit_level(data: np.ndarray) -> float:
    """The counts of the pixels that see no light — in a white plenoptic frame, the gaps between the
    sub-images: the median of those within 2 % of the range above the 0.1th percentile, when that
    percentile is under half the 99th (else the frame has no unlit pixels and 0 is returned); but never
    more than three times their pixel noise above that darkest 0.1 %.

    Why the cap: where the gaps are lit too (stray light, the tails of a wide blur) no pixel shows the
    black, and the median of the gaps is their light (measured on an independent generator's frames: 888
    for a true black of 512 in 14 bits, 1599 for 0 in 16 bits). The darkest pixels still bound the black
    from above, as far as their noise lets them dip below it. The cap only ever lowers the estimate of a
    frame that has lit pixels, so it cannot make a lit frame look black; on a black frame (no pixel lit)
    the median already sits within the noise of the darkest pixels, so it does not move."""
    sample = data[::3, ::3] if min(data.shape) >= 300 else data
    dark, bright = (float(v) for v in np.percentile(sample, [0.1, 99.0]))
    if dark > 0.5 * bright:
        return 0.0
    cut = dark + 0.02 * (bright - dark)
    return min(float(np.median(sample[sample <= cut])), dark + 3.0 * _dark_noise(data, cut))


def _dark_noise(data: np.ndarray, cut: float) -> float:
    """Pixel-to-pixel noise of the pixels at or under `cut`: 1.4826 x the median absolute difference of
    neighbours (both at or under it) over sqrt 2, along rows and along columns, the smaller of the two
    (one direction runs along the dark gaps, where the light hardly changes); inf with too few pairs."""
    step = 8 if min(data.shape) >= 800 else 1  # every 8th row (column) of a big frame is plenty
    out = np.inf
    for a, b in ((data[::step, :-1], data[::step, 1:]), (data[:-1, ::step], data[1:, ::step])):
        both = (a <= cut) & (b <= cut)
        if np.count_nonzero(both) >= 50:
            d = a[both].astype(np.float64) - b[both].astype(np.float64)
            out = min(out, 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2.0))
    return out


def levels_note(frame: RawFrame) -> str:
    """One sentence saying which levels a frame was read with and where they came from."""
    if frame.levels_from == "normalized":
        return "Read as a normalized frame (its float values all lie within 0..1): black level 0, white level 1."
    origin = {"option": "as stated on the command line", "config": "from the camera config's [sensor]",
              "data": "estimated from the data (no level tags in the file)",
              "container": "from the container alone", "file": "from the file"}.get(frame.levels_from, "")
    return (f"Read as {frame.bits}-bit counts, black level {frame.black_level}, white level {frame.white_level}, "
            f"{origin}.")


# --------------------------------------------------------------------------------------------- checks


def check_exposure(
    frame: RawFrame, *, max_saturated_fraction: float = 0.05, min_signal_fraction: float = 0.01
) -> None:
    """InputError if a frame is black or saturated; separate from load_raw because dark frames are legitimate.

    Black: the 99.9th percentile above black level does not clear the noise — 6 sigma of the darker half of
    the frame (capped at 5 % of full scale) or `min_signal_fraction` of full scale, whichever is larger.
    Saturated: more than `max_saturated_fraction` of the pixels sit at or above the white level.
    """
    data = frame.data
    span = float(frame.white_level - frame.black_level)
    saturated = float(np.count_nonzero(data >= frame.white_level)) / data.size
    if saturated > max_saturated_fraction:
        raise InputError(
            f"Frame {frame.source or '(in memory)'} is saturated: {saturated:.1%} of pixels are at the white level "
            f"{frame.white_level} (limit {max_saturated_fraction:.1%}); reduce the exposure or the light."
        )
    sample = data[::3, ::3] if min(data.shape) >= 300 else data  # robust statistics need no more
    if sample.dtype.kind == "u":
        bright, median, sigma = _integer_sample_stats(sample, frame.black_level)
    else:
        excess = sample.astype(np.float32) - np.float32(frame.black_level)
        bright = float(np.percentile(excess, 99.9))
        median = float(np.median(excess))
        lower = excess[excess <= median]
        sigma = 1.4826 * float(np.median(median - lower)) if lower.size else 0.0
    # (at least one count: 1/65535 of the span for a normalized frame)
    threshold = max(min(6.0 * sigma, 0.05 * span), min_signal_fraction * span, min(1.0, span / 65535.0))
    if bright <= threshold:
        raise InputError(
            f"Frame {frame.source or '(in memory)'} is black: nothing rises above the black level "
            f"{frame.black_level} plus noise; check the light source, shutter and exposure."
        )


def _integer_sample_stats(sample: np.ndarray, black: int) -> tuple[float, float, float]:
    """(99.9th percentile, median, 1.4826 x median distance of the darker half below the median) of
    sample - black, read from the histogram of the integer counts: the same order statistics as
    np.percentile / np.median ('linear' interpolation), in about a millisecond instead of 15."""
    hist = np.bincount(sample.ravel())
    cum = np.cumsum(hist)
    n = int(cum[-1])

    def order(k: np.ndarray) -> np.ndarray:  # the k-th smallest counts (0-based)
        return np.searchsorted(cum, np.asarray(k) + 1, side="left").astype(np.float64)

    def quantile(q: float, m: int, offset: int = 0) -> float:  # numpy 'linear' quantile of the m smallest
        pos = q * (m - 1)
        lo = int(np.floor(pos))
        a, b = order([offset + lo, offset + min(lo + 1, m - 1)])
        return float(a + (b - a) * (pos - lo))

    bright = quantile(0.999, n) - black
    median = quantile(0.5, n) - black
    m_low = int(cum[int(np.floor(median + black))]) if median + black >= 0 else 0  # counts <= median
    sigma = 1.4826 * (median - (quantile(0.5, m_low) - black)) if m_low else 0.0
    return bright, median, sigma


# --------------------------------------------------------------------------------------------- processing


def cfa_planes(cfa: str | None) -> list[tuple[slice, slice]]:
    """Slices selecting each same-colour plane: four 2x2 sites for a CFA, the whole frame for mono."""
    if cfa is None:
        return [(slice(None), slice(None))]
    return [(slice(r, None, 2), slice(c, None, 2)) for r in (0, 1) for c in (0, 1)]


def normalized(frame: RawFrame) -> np.ndarray:
    """Float32 (data - black)/(white - black); CFA frames become a full-resolution luminance, no demosaic.

    For CFA frames each of the four 2x2 sites is multiplied by gain = G_level / own_level, where a
    site's level is the median of its brightest 10 % of pixels (its 95th percentile: robust to hot pixels
    and to the dark gaps between sub-images) and G_level is the mean of the two green sites' levels.
    A white/grey scene thus gives four matching channels on the green channel's scale (so red or blue
    can exceed 1.0 after gain). If any site's level is under 1 % of full scale (dark frame, missing
    colour) the gains are meaningless and the plain normalisation is returned.
    """
    span = np.float32(frame.white_level - frame.black_level)
    out = frame.data.astype(np.float32)  # then in place: the same float32 results, no temporaries
    out -= np.float32(frame.black_level)
    out /= span
    if frame.cfa is None:
        return out
    planes = cfa_planes(frame.cfa)
    levels = [float(np.percentile(out[sl], 95.0)) for sl in planes]
    if min(levels) < 0.01:
        return out
    sites = [frame.cfa[i] for i in range(4)]
    green = float(np.mean([lvl for lvl, s in zip(levels, sites) if s == "G"]))
    for sl, lvl in zip(planes, levels):
        out[sl] *= np.float32(green / lvl)
    return out


def suppress_hot_pixels(
    img: np.ndarray, cfa: str | None, *, nsigma: float = 6.0, inplace: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Replace isolated hot (and dead) pixels by their 3x3 same-channel median; return (cleaned, mask).

    Works per CFA site plane (or on the whole mono frame), one compiled pass per plane
    (mlaqc.inspection.rawio_kernels). A pixel is an outlier when it stands above the brightest (or below the darkest)
    of its 8 same-channel neighbours by more than `nsigma` * max(plane noise, local structure). Plane
    noise is the robust sigma (1.4826 * MAD) of the residual against the ring mean on a sparse sample
    (`_plane_noise`), at least 1 count for integer data. Local structure is the rms residual of the 8 neighbours about their
    own least-squares plane: zero on flat areas and gradients, large at sub-image edges, corners and
    gaps, so genuine structure is never "cleaned" (PlenoptiCam's cfa_outliers idea: judge a pixel
    against its same-channel window's spread). `inplace`: clean `img` itself (the caller owns it).
    Limits: two outliers adjacent in the same plane shield each other; at the frame border the mirrored
    window is less sensitive.
    """
    img = np.asarray(img)
    if img.ndim != 2:
        raise InputError(f"suppress_hot_pixels needs a 2-D image, not shape {img.shape}.")
    if cfa is not None and cfa not in CFA_PATTERNS:
        raise InputError(f"suppress_hot_pixels: cfa={cfa!r} must be None or one of {', '.join(CFA_PATTERNS)}.")
    from mlaqc.inspection.rawio_kernels import hot_pixel_rows  # lazily: capture and I/O alone need no Numba import

    x = np.ascontiguousarray(img, dtype=np.float32)  # float32 halves the memory traffic (no copy if already)
    mask = np.zeros(img.shape, dtype=bool)
    med = np.empty(img.shape, dtype=np.float32)  # written only at outliers
    step = 1 if cfa is None else 2
    integer = img.dtype.kind in "ui"
    planes = [(r0, c0, len(range(r0, img.shape[0], step)), len(range(c0, img.shape[1], step)))
              for r0, c0 in (((0, 0),) if cfa is None else ((0, 0), (0, 1), (1, 0), (1, 1)))]
    planes = [pl for pl in planes if min(pl[2], pl[3]) >= 3]
    # the planes' noise, then every plane's row ranges, each on the thread pool at once (the kernels
    # release the GIL; each plane writes only its own pixels of `mask` and `med`)
    noises = thread_map(lambda pl: _plane_noise(x, pl[0], pl[1], step, pl[2], pl[3], integer), planes)
    jobs, row_bads = [], []
    for (r0, c0, ph, _pw), noise in zip(planes, noises):
        if not np.isfinite(noise):
            continue  # NaN pixels: no threshold can be judged (as the filter formulation)
        row_bad = np.zeros(ph, dtype=np.int64)
        run = partial(hot_pixel_rows, x, r0, c0, step, float(noise), float(nsigma))
        edges = np.linspace(0, ph, 2 * (os.cpu_count() or 1) + 1).astype(int) if ph >= 64 else np.array([0, ph])
        jobs += [(run, int(a), int(b), row_bad) for a, b in pairwise(edges) if b > a]
        row_bads.append((r0, row_bad))
    thread_map(lambda job: job[0](job[1], job[2], mask, med, job[3]), jobs)
    bad_rows = [r0 + step * np.flatnonzero(row_bad) for r0, row_bad in row_bads]
    cleaned = img if inplace else img.copy()
    rows = np.unique(np.concatenate(bad_rows)) if bad_rows else np.zeros(0, np.int64)
    if rows.size:  # replace after detection, so every median saw the original neighbours
        i, j = np.nonzero(mask[rows])
        cleaned[rows[i], j] = med[rows[i], j].astype(img.dtype)
    return cleaned, mask


def _median(a: np.ndarray) -> np.floating:
    """np.median of a 1-D array by one np.partition (np.median's own path is ~10x slower here)."""
    if not np.isfinite(a).all():
        return np.median(a)
    k = a.size // 2
    if a.size % 2:
        return np.partition(a, k)[k]
    part = np.partition(a, (k - 1, k))
    return np.mean(part[k - 1 : k + 1])


def _plane_noise(x: np.ndarray, r0: int, c0: int, step: int, ph: int, pw: int, integer: bool) -> float:
    """Robust sigma of one plane's residual against its 8-neighbour ring mean (var = sigma^2 (1 + 1/8)),
    from a 1-in-9 sample (1-in-16 from 4 Mpx on: still 250,000 values, and the two medians are most of
    the cost); floored at 1 count (integer data) or 1e-6 of the plane's range."""
    from mlaqc.inspection.rawio_kernels import ring_residual_sample

    every = 4 if ph * pw >= 4_000_000 else 3
    sample = np.empty(((ph + every - 1) // every, (pw + every - 1) // every), dtype=np.float32)
    ring_residual_sample(x, r0, c0, step, every, sample)
    centre = _median(sample.ravel())
    noise = 1.4826 * float(_median(np.abs(sample - centre).ravel())) / np.sqrt(1.125)
    if integer:
        return max(noise, 1.0)
    plane = x[r0::step, c0::step]  # NumPy's vectorized min/max: a third of the compiled scalar loop's time
    return max(noise, 1e-6 * ((float(plane.max()) - float(plane.min())) or 1.0))
