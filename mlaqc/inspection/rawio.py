"""Raw-image I/O: load single-channel raw frames (DNG, vendor raws, TIFF, PNG, NPY) bit-exactly; `raw_write`
writes them, `raw_levels` reads their levels and normalizes them.

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
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc.errors import InputError

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



def sidecar_path(path: Path) -> Path:
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
    side = sidecar_path(path)
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
