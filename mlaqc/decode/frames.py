"""Frames for decoding: a raw read, its levels settled and normalised like an inspection's, hot pixels
replaced, and demosaiced where the sensor has a colour filter array (RGB out, one channel per colour)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from mlaqc.errors import InputError
from mlaqc.inspection.raw_levels import Levels, normalized, resolve_levels, suppress_hot_pixels
from mlaqc.inspection.rawio import load_raw

# OpenCV names a Bayer conversion by the 2x2 block one pixel down and right of the pattern's origin
_OPENCV_BAYER = {"RGGB": "COLOR_BayerBG2RGB", "BGGR": "COLOR_BayerRG2RGB", "GRBG": "COLOR_BayerGB2RGB",
                 "GBRG": "COLOR_BayerGR2RGB"}


def load_decode_frame(path: str, cfg: Any, levels: Levels | None = None) -> np.ndarray:
    """The frame at `path` as float32 (H, W) (monochrome) or (H, W, 3) RGB, black 0 and white 1. InputError
    for an unreadable file, a frame of another size, or a frame with no light or NaNs."""
    s = cfg.sensor
    frame = resolve_levels(load_raw(path), levels, Levels(s.bit_depth, s.black_level_dn))
    want = (s.height_px, s.width_px)
    if frame.shape != want:
        raise InputError(f"{path} is {frame.shape[1]}x{frame.shape[0]} px but the camera's sensor is "
                         f"{want[1]}x{want[0]} px (sensor.width_px/height_px)")
    img = normalized(frame)
    if not np.all(np.isfinite(img)):
        raise InputError(f"{path} holds values that are not numbers (NaN or infinite)")
    if float(np.percentile(img, 99.9)) <= 0.0:
        raise InputError(f"{path} is black: no pixel received light above the black level")
    img, _ = suppress_hot_pixels(img, frame.cfa)
    return demosaiced(img, frame.cfa)


def demosaiced(img: np.ndarray, cfa: str | None) -> np.ndarray:
    """Monochrome frames as they are; a Bayer frame (the four sites already on one scale, `normalized`)
    interpolated to RGB bilinearly (OpenCV), each colour from its own sites only."""
    if cfa is None:
        return img
    import cv2

    top = max(float(img.max()), 1e-12)
    counts = np.clip(img / top * 65535.0, 0, 65535).astype(np.uint16)
    rgb = cv2.cvtColor(counts, getattr(cv2, _OPENCV_BAYER[cfa]))
    return rgb.astype(np.float32) * np.float32(top / 65535.0)


def averaged(paths: Sequence[str], cfg: Any, levels: Levels | None = None) -> np.ndarray:
    """Several frames of one state (white frames, usually) averaged into one."""
    total = None
    for p in paths:
        img = load_decode_frame(p, cfg, levels)
        total = img if total is None else total + img
    return total / len(paths)
