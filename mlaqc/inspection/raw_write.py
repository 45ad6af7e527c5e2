"""Writing raw frames bit-exactly (DNG, TIFF, PNG, NPY), with their acquisition record: in the DNG's real
tags and ImageDescription, in a TIFF's ImageDescription, or in a sidecar `<name>.json` for PNG and NPY
(mlaqc.inspection.rawio reads all of them back). Every file is written atomically.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc.atomic import atomic_path
from mlaqc.errors import InputError
from mlaqc.inspection.rawio import (CFA_PATTERNS, DNG_MAX_SIDE, DNG_MIN_SIDE, RECORD_KEY, RESERVED_METADATA_KEYS,
                                    TIFF_SUFFIXES, WRITE_SUFFIXES, sidecar_path)

_CFA_CODE = {"R": 0, "G": 1, "B": 2}  # TIFF/EP CFAPattern colour codes


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
    with atomic_path(sidecar_path(path)) as tmp_json, atomic_path(path) as tmp:
        tmp_json.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
        if suffix == ".png":
            tmp.write_bytes(payload)
        else:
            with open(tmp, "wb") as fh:
                np.save(fh, data, allow_pickle=False)
