"""Dark frames and frame stacks: a master dark subtracted before everything else, and several frames of
one state averaged into one.

Master dark (`build_master_dark`): N dark frames (lens covered or light off, the frames' exposure, gain,
size and bit depth) combined per pixel, by their median (default) or by a sigma-clipped mean (each
pixel's samples further than CLIP_SIGMA read-noise sigmas from its median are dropped, the rest
averaged: a cosmic-ray hit or a flicker in one frame is rejected, and with many frames the result is
less noisy than the median). The dark's read noise is measured from the frames themselves (the robust
spread of the differences of consecutive frames, over √2; from one frame, of its vertical second
difference), and the master's own noise from it (σ/√N for the mean, the median's larger factor for it).

Bad pixels: a pixel whose master-dark level stands more than BAD_SIGMA sigmas above (hot) or below
(dead) the median of its eight vertical neighbours in the same column (same-colour sites for a CFA),
sigma being the robust spread of that residual over the frame. A column's own offset and a smooth glow
cancel in that residual, so only the pixel's own deviation counts. This map is used instead of guessing
bad pixels from the white frame (`raw_levels.suppress_hot_pixels`, which still runs on frames without a
dark): a hot pixel is restored by the subtraction, unless the frame clipped it at the white level; those
and the dead pixels are replaced from their same-channel neighbours (`repair_mask`, `replace_bad_pixels`).

A "dark" that is lit is refused, each dark frame on its own (one lit frame would hide under a median):
its median above the black level by more than LIT_SIGMA read-noise sigmas and LIT_FRACTION of the range
(where the file says its black level), or the microlenses' sub-image lattice in it (the power at the
lattice's diagonal frequency, in a central crop with column/row offsets and smooth glow taken out, over
the spectrum's median: noise gives about 1, a frame with light through the MLA 10^4 and more).

Frames (`load_frames`): one raw, or several of one state (a stack), each loaded with its levels
settled as a single raw is (`raw_levels.resolve_levels`), checked against the first (size, bit depth,
exposure, gain) and against the master dark, checked for exposure, averaged in float32 counts, the
master dark subtracted (the frame's nominal black level added back, so levels and checks keep their
meaning), checked again for a black frame, normalized, and the bad pixels replaced. A stack of K
frames has 1/√K of one frame's pixel noise; inspection measures its noise on the frame it is given,
so the detection limit is the stack's, and the report says so (`noise_info`, `detection_limit["noise"]`).

Exposure and gain come from the frame's `<file>.meta.json` sidecar (`mlaqc capture`, `mlaqc scan`), else
the `acquisition` record in the raw file's own metadata, else a TIFF/DNG ExposureTime tag; a check is
made only where both sides say them. Every mismatch is one sentence (InputError, exit status 2).
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc.errors import InputError
from mlaqc.inspection.raw_levels import (Levels, check_exposure, levels_note, normalized, resolve_levels,
                                         suppress_hot_pixels)
from mlaqc.inspection.rawio import RawFrame, load_raw

METHODS = ("median", "mean")  # "mean": the sigma-clipped mean
CLIP_SIGMA = 3.0  # the clipped mean drops samples this many read-noise sigmas from the pixel's median
BAD_SIGMA = 8.0  # a hot / dead pixel stands this many sigmas above / below its column neighbours
LIT_SIGMA = 6.0  # a dark frame's median may sit this many read-noise sigmas above black ...
LIT_FRACTION = 0.02  # ... and this fraction of the range, before it is called lit
PATTERN_RATIO = 1000.0  # lattice power over the spectrum's median above which a dark shows sub-images
EXPOSURE_REL = 0.01  # exposures (and gains) further apart than this fraction do not match
META_SUFFIX = ".meta.json"
KNOWN_LEVELS = ("file", "option", "config")  # levels a frame states (not guessed from its data)
_NEIGHBOURS = 4  # vertical neighbours each side the bad-pixel residual is taken against
_SORT8 = ((0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (1, 2), (5, 6), (0, 4), (3, 7), (1, 5),
          (2, 6), (1, 4), (3, 6), (2, 4), (3, 5), (3, 4))


# --------------------------------------------------------------------------------------------- facts


@dataclass(frozen=True)
class FrameFacts:
    """What must match between a dark and its frames (None: the file does not say)."""

    name: str
    shape: tuple[int, int] | None
    bits: int | None
    cfa: str | None
    normalized: bool
    exposure_us: float | None
    gain: float | None

    @classmethod
    def of(cls, frame: RawFrame, path: str | os.PathLike | None = None, *, exposure_us: float | None = None,
           gain: float | None = None) -> FrameFacts:
        """The facts of a loaded frame: its shape and levels, exposure and gain from its sidecar or record."""
        meta = read_meta(path) if path is not None else {}
        acq = frame.metadata.get("acquisition") if isinstance(frame.metadata, dict) else None
        acq = acq if isinstance(acq, dict) else {}
        tags = frame.metadata.get("tags") if isinstance(frame.metadata, dict) else None
        exposure = _first_number(exposure_us, meta.get("exposure_us"), acq.get("exposure_us"), _tag_exposure_us(tags))
        gain = _first_number(gain, meta.get("gain"), acq.get("gain"))
        bits = meta.get("bits") if isinstance(meta.get("bits"), int) else None
        if bits is None and frame.levels_from in KNOWN_LEVELS:
            bits = frame.bits
        name = Path(path).name if path is not None else (frame.source or "(in memory)")
        return cls(name, tuple(frame.data.shape), bits, frame.cfa, frame.levels_from == "normalized", exposure, gain)

    @classmethod
    def from_meta(cls, path: str | os.PathLike) -> FrameFacts | None:
        """The facts a frame's `.meta.json` sidecar alone gives (None without one): no pixel is read."""
        meta = read_meta(path)
        if not meta:
            return None
        w, h = meta.get("width"), meta.get("height")
        shape = (int(h), int(w)) if isinstance(w, int) and isinstance(h, int) else None
        bits = meta.get("bits") if isinstance(meta.get("bits"), int) else None
        cfa = meta.get("cfa") if isinstance(meta.get("cfa"), str) else None
        return cls(Path(path).name, shape, bits, cfa, False, _first_number(meta.get("exposure_us")),
                   _first_number(meta.get("gain")))


def read_meta(path: str | os.PathLike) -> dict:
    """The `<file>.meta.json` sidecar beside a raw file (`mlaqc capture`/`scan`), {} when there is none."""
    side = Path(str(path) + META_SUFFIX)
    if not side.is_file():
        return {}
    try:
        obj = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"sidecar {str(side)!r} is not valid JSON ({type(exc).__name__})") from None
    return obj if isinstance(obj, dict) else {}


def _first_number(*values: Any) -> float | None:
    for v in values:
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v)):
            return float(v)
    return None


def _tag_exposure_us(tags: Any) -> float | None:
    """A TIFF/DNG ExposureTime tag (seconds, or a rational as two numbers) in µs."""
    if not isinstance(tags, dict) or "ExposureTime" not in tags:
        return None
    v = tags["ExposureTime"]
    if isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v) and v[1]:
        v = v[0] / v[1]
    return 1e6 * float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def compare(a: FrameFacts, b: FrameFacts, what_a: str, what_b: str) -> None:
    """InputError, one sentence, where two frames that must match do not (what the files say)."""
    def fail(thing: str, va: str, vb: str) -> None:
        raise InputError(f"the {what_a} {a.name} {thing} {va} but the {what_b} {b.name} {vb}: "
                         f"{_MATCH[what_a == what_b]}")

    if a.shape is not None and b.shape is not None and a.shape != b.shape:
        fail("is", f"{a.shape[1]}x{a.shape[0]} px", f"is {b.shape[1]}x{b.shape[0]} px")
    if a.normalized != b.normalized:
        fail("holds", "normalized values" if a.normalized else "raw counts",
             "holds " + ("normalized values" if b.normalized else "raw counts"))
    if a.bits is not None and b.bits is not None and a.bits != b.bits:
        fail("has", f"{a.bits}-bit counts", f"has {b.bits}-bit counts")
    if a.cfa != b.cfa and not (a.normalized or b.normalized):
        fail("has", f"CFA pattern {a.cfa or 'none (mono)'}", f"has {b.cfa or 'none (mono)'}")
    if _differ(a.exposure_us, b.exposure_us):
        fail("was exposed", f"{a.exposure_us:g} µs", f"{b.exposure_us:g} µs")
    if _differ(a.gain, b.gain):
        fail("was taken at gain", f"{a.gain:g}", f"at {b.gain:g}")


_MATCH = {False: "a dark must be taken with its frames' camera mode, size, bit depth, exposure and gain",
          True: "frames averaged into one must share size, bit depth, exposure and gain"}


def _differ(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return False
    return abs(a - b) > EXPOSURE_REL * max(abs(a), abs(b)) and abs(a - b) > 1e-9


# --------------------------------------------------------------------------------------- master dark


@dataclass(frozen=True, eq=False)
class MasterDark:
    """A master dark: per-pixel dark level (counts, black level included), its bad pixels and noise."""

    level: np.ndarray  # float32 (H, W)
    hot: np.ndarray  # bool (H, W)
    dead: np.ndarray  # bool (H, W)
    bad: np.ndarray  # hot | dead
    frames: int
    method: str  # 'median' or 'mean' (sigma-clipped)
    read_noise_dn: float  # one dark frame's temporal noise per pixel, counts (robust)
    noise_dn: float  # the master's own noise per pixel, counts
    facts: FrameFacts  # of the dark frames (they all agree)
    black_level: int
    white_level: int
    sources: tuple[str, ...]
    seconds: float = 0.0  # time to build it

    @property
    def shape(self) -> tuple[int, int]:
        return self.level.shape  # type: ignore[return-value]

    def check(self, facts: FrameFacts, what: str = "frame") -> None:
        """InputError when the frame does not match the darks (size, levels, exposure, gain)."""
        compare(self.facts, facts, "dark frame", what)

    def summary(self) -> dict:
        """JSON-ready facts for the report (`detection_limit["noise"]["dark"]`)."""
        return {"frames": self.frames, "method": self.method, "read_noise_dn": round(self.read_noise_dn, 4),
                "master_noise_dn": round(self.noise_dn, 4), "hot_pixels": int(self.hot.sum()),
                "dead_pixels": int(self.dead.sum()), "exposure_us": self.facts.exposure_us,
                "gain": self.facts.gain, "files": [Path(s).name for s in self.sources]}


def build_master_dark(paths: Sequence[str | os.PathLike], *, levels: Levels | None = None,
                      sensor: Levels | None = None, method: str = "median", pitch_px: float | None = None,
                      expected_shape: tuple[int, int] | None = None) -> MasterDark:
    """The master dark of the dark frames at `paths` (see the module's docstring); `levels` / `sensor`
    settle their levels as a raw's are; `pitch_px`, the sub-image pitch, lets the lit check look for the
    lattice; `expected_shape` (rows, cols), the camera's sensor."""
    t0 = time.perf_counter()
    paths = [str(p) for p in paths]
    if not paths:
        raise InputError("--dark needs at least one dark frame")
    if method not in METHODS:
        raise InputError(f"the master dark method {method!r} is not one of {', '.join(METHODS)}")
    frames, facts = [], []
    for p in paths:
        frame = resolve_levels(load_raw(p), levels, sensor)
        f = FrameFacts.of(frame, p)
        if facts:
            compare(facts[0], f, "dark frame", "dark frame")
        frames.append(frame)
        facts.append(f)
    first = frames[0]
    if expected_shape is not None and first.shape != tuple(expected_shape):
        raise InputError(f"the dark frame {facts[0].name} is {first.shape[1]}x{first.shape[0]} px but the camera's "
                         f"sensor is {expected_shape[1]}x{expected_shape[0]} px: a dark must be taken with the "
                         "frames' camera mode")
    stack = np.stack([np.asarray(f.data, dtype=np.float32) for f in frames])
    sigma = read_noise(stack)
    for frame, f in zip(frames, facts):
        check_not_lit(frame, f.name, sigma, pitch_px)
    level, noise = combine(stack, method, sigma)
    del stack
    hot, dead = bad_pixels(level, first.cfa, noise, integer=first.data.dtype.kind == "u")
    return MasterDark(level, hot, dead, hot | dead, len(frames), method if len(frames) > 2 else "mean", sigma, noise,
                      facts[0], first.black_level, first.white_level, tuple(paths), round(time.perf_counter() - t0, 4))


def read_noise(stack: np.ndarray) -> float:
    """One frame's temporal read noise (counts), robust: from the differences of consecutive frames
    (over √2), or for a single frame from its vertical second difference (over √1.5); floored at the
    quantization noise of integer counts (1/√12)."""
    n, h = stack.shape[:2]
    rows = slice(None, None, max(1, h // 512))  # about 512 rows are plenty
    if n >= 2:
        d = np.concatenate([(stack[k + 1, rows] - stack[k, rows]).ravel() for k in range(min(n - 1, 8))])
        scale = math.sqrt(2.0)
    else:
        x = stack[0]
        d = (x[1:-1] - 0.5 * (x[:-2] + x[2:]))[rows].ravel()
        scale = math.sqrt(1.5)
    d = d[np.isfinite(d)]
    if not d.size:
        return 0.0
    return max(_robust_std(d) / scale, 1 / math.sqrt(12.0))


def _robust_std(d: np.ndarray) -> float:
    """The standard deviation of the values within 4 robust sigmas of their median (the MAD alone is
    quantized on integer counts: 5 % high at 3 counts of noise)."""
    med = float(np.median(d))
    s0 = 1.4826 * float(np.median(np.abs(d - med)))
    if s0 <= 0:
        return 0.0
    return float(d[np.abs(d - med) <= 4.0 * s0].std())


def combine(stack: np.ndarray, method: str, sigma: float) -> tuple[np.ndarray, float]:
    """(master level float32, its noise per pixel) of a (N, H, W) stack of dark frames."""
    n = stack.shape[0]
    if n == 1:
        return stack[0].copy(), sigma
    if n == 2 or method == "median":
        level = _median(stack) if n > 2 else stack.mean(axis=0)
        return level, sigma * (median_factor(n) if n > 2 else 1.0) / math.sqrt(n)
    med = _median(stack)
    keep = np.abs(stack - med) <= np.float32(CLIP_SIGMA * sigma)
    count = keep.sum(axis=0)
    total = np.where(keep, stack, np.float32(0)).sum(axis=0)
    level = np.where(count > 0, total / np.maximum(count, 1), med).astype(np.float32)
    return level, sigma * clipped_factor(n) / math.sqrt(n)


def _median(stack: np.ndarray) -> np.ndarray:
    """np.median over axis 0 (float32), element-wise for three or four frames (a fifth of its time)."""
    n = stack.shape[0]
    if n == 3:
        a, b, c = stack
        return np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))
    if n == 4:
        total = stack.sum(axis=0)
        total -= stack.max(axis=0)
        total -= stack.min(axis=0)
        total *= np.float32(0.5)
        return total
    return np.median(stack, axis=0).astype(np.float32, copy=False)


@lru_cache(maxsize=64)
def median_factor(n: int) -> float:
    """The noise of the median of n normal samples over that of their mean (1.0 for n <= 2, → √(π/2))."""
    if n <= 2:
        return 1.0
    z = np.random.default_rng(12345).standard_normal((40_000, n))
    return float(np.median(z, axis=1).std() * math.sqrt(n))


@lru_cache(maxsize=64)
def clipped_factor(n: int) -> float:
    """The same for the sigma-clipped mean (`combine`): barely above 1."""
    z = np.random.default_rng(12345).standard_normal((40_000, n))
    med = np.median(z, axis=1, keepdims=True)
    keep = np.abs(z - med) <= CLIP_SIGMA
    return float(((z * keep).sum(axis=1) / keep.sum(axis=1)).std() * math.sqrt(n))


def bad_pixels(level: np.ndarray, cfa: str | None, noise_dn: float, *, integer: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(hot, dead) masks of a master dark: the level against the median of its _NEIGHBOURS vertical
    neighbours each side (same CFA row parity), beyond BAD_SIGMA robust sigmas of that residual. Then once
    more where a first-pass hot pixel was in the window, against neighbours with it taken out (two hot
    pixels near each other in a column, on a steep glow, would otherwise make their neighbours look dead)."""
    step = 1 if cfa is None else 2
    h = level.shape[0]
    pad = _NEIGHBOURS * step
    if h <= 2 * (pad + 16 * step):
        return np.zeros(level.shape, bool), np.zeros(level.shape, bool)
    ref = _column_reference_parallel(level, step)
    res = level - ref
    sigma = _robust_std(res[:: max(1, h // 512)].ravel())
    sigma = max(sigma, noise_dn, (1 / math.sqrt(12.0)) if integer else 0.0, 1e-9)
    cut = np.float32(BAD_SIGMA * sigma)
    hot, dead = res > cut, res < -cut
    del res
    inner = hot.copy()
    inner[:pad] = inner[h - pad:] = False  # (the edge rows' references are extrapolated, never used as neighbours)
    hy, hx = np.nonzero(inner)
    if not hy.size:
        return hot, dead
    clean = level.copy()
    clean[hy, hx] = ref[hy, hx]
    offs = np.array([k * step for k in range(-_NEIGHBOURS, _NEIGHBOURS + 1) if k])
    cy, cx = (hy[:, None] + offs[None, :]).ravel(), np.repeat(hx, offs.size)
    keep = (cy >= pad) & (cy < h - pad)
    y, x = np.divmod(np.unique(cy[keep].astype(np.int64) * level.shape[1] + cx[keep]), level.shape[1])
    r2 = level[y, x] - np.median(clean[y[:, None] + offs[None, :], x[:, None]], axis=1)
    hot[y, x], dead[y, x] = r2 > cut, r2 < -cut
    slab = pad + 16 * step  # the edge rows again: their extrapolation from the cleaned references
    for rows, part in ((slice(0, pad), slice(0, slab)), (slice(h - pad, h), slice(h - slab, h))):
        r = _column_reference(clean[part], step)
        r = r[rows] if rows.start == 0 else r[-pad:]
        edge = level[rows] - r
        hot[rows], dead[rows] = edge > cut, edge < -cut
    return hot, dead


def _column_reference_parallel(level: np.ndarray, step: int) -> np.ndarray:
    """`_column_reference` in column blocks on the thread pool (columns are independent; NumPy's
    element-wise passes release the GIL): the same array, in about 1/cores of the time."""
    from mlaqc.parallel import cores, thread_map

    edges = np.linspace(0, level.shape[1], max(1, min(cores(), level.shape[1] // 64)) + 1).astype(int)
    if len(edges) <= 2:
        return _column_reference(level, step)
    blocks = thread_map(lambda ab: _column_reference(level[:, ab[0]:ab[1]], step), list(zip(edges[:-1], edges[1:])))
    return np.concatenate(blocks, axis=1)


def _column_reference(level: np.ndarray, step: int) -> np.ndarray:
    """Per pixel, the median of its _NEIGHBOURS vertical neighbours each side (every `step`-th row); in
    the first and last rows, where a reflected window would see a slope as a V (a glow at the edge as a
    hot or dead row), the least-squares line through the next eight rows' references, extrapolated."""
    h = level.shape[0]
    pad = _NEIGHBOURS * step
    padded = np.pad(level, ((pad, pad), (0, 0)), mode="reflect")
    a = [padded[pad + k * step:pad + k * step + h] for k in (-4, -3, -2, -1, 1, 2, 3, 4)]
    for i, j in _SORT8:  # Batcher's sorting network: 19 element-wise min/max, twice np.median's speed
        a[i], a[j] = np.minimum(a[i], a[j]), np.maximum(a[i], a[j])
    ref = np.float32(0.5) * (a[3] + a[4])  # the median of the eight
    del a, padded
    t = np.arange(_NEIGHBOURS, _NEIGHBOURS + 8)  # the fitted rows, in steps from y
    weights = (1 / t.size - t.mean() * (t - t.mean()) / ((t - t.mean()) ** 2).sum()).astype(np.float32)
    for y in (*range(pad), *range(h - pad, h)):
        rows = y + (1 if y < pad else -1) * step * t
        ref[y] = np.tensordot(weights, ref[rows], axes=1)  # the line's value at y
    return ref


def check_not_lit(frame: RawFrame, name: str, sigma: float, pitch_px: float | None) -> None:
    """InputError when a dark frame is lit: its median well above black, or the sub-image lattice in it."""
    data = frame.data
    sample = data[::3, ::3] if min(data.shape) >= 300 else data
    span = float(frame.white_level - frame.black_level)
    if frame.levels_from in KNOWN_LEVELS or frame.levels_from == "normalized":
        excess = float(np.median(sample)) - frame.black_level
        if excess > max(LIT_SIGMA * sigma, LIT_FRACTION * span):
            raise InputError(f"the dark frame {name} is lit: its median is {excess:.4g} counts above the black level "
                             f"{frame.black_level} ({excess / max(sigma, 1e-12):.0f} times its noise); cover the lens or "
                             "switch the light off and capture the darks again")
    if pitch_px:
        ratio = lattice_ratio(data, pitch_px)
        if ratio > PATTERN_RATIO:
            raise InputError(f"the dark frame {name} is lit: it shows the microlenses' sub-images (their lattice "
                             f"stands {ratio:.3g} times above the noise); cover the lens or switch the light off and "
                             "capture the darks again")


def lattice_ratio(data: np.ndarray, pitch_px: float, size: int = 256) -> float:
    """The power at the sub-image lattice's diagonal frequency (1/pitch, 1/pitch) of a central crop, over
    the spectrum's median; column and row offsets, smooth glow and outliers taken out first. About 1 on
    a dark frame, 10^4 and more where light reaches the sensor through the MLA."""
    from scipy.ndimage import uniform_filter1d

    n = min(size, *data.shape) // 2 * 2
    if n < 4 * pitch_px:
        return 0.0
    h, w = data.shape
    crop = np.asarray(data[(h - n) // 2:(h - n) // 2 + n, (w - n) // 2:(w - n) // 2 + n], dtype=np.float64)
    crop = crop - np.median(crop, axis=0, keepdims=True)
    crop -= np.median(crop, axis=1, keepdims=True)
    width = 2 * int(round(pitch_px)) + 1  # twice a box of two pitches: at the lattice frequency it passes all
    smooth = crop
    for axis in (0, 1, 0, 1):
        smooth = uniform_filter1d(smooth, width, axis=axis, mode="reflect")
    crop -= smooth
    mad = 1.4826 * float(np.median(np.abs(crop)))
    if mad > 0:
        np.clip(crop, -8 * mad, 8 * mad, out=crop)
    win = np.hanning(n)
    power = np.abs(np.fft.fft2(crop * win[:, None] * win[None, :])) ** 2
    f = n / pitch_px
    peak = 0.0
    for sy, sx in ((1, 1), (1, -1)):
        cy, cx = int(round(sy * f)), int(round(sx * f))
        ys = np.arange(cy - 3, cy + 4) % n
        xs = np.arange(cx - 3, cx + 4) % n
        peak = max(peak, float(power[np.ix_(ys, xs)].max()))
    keep = np.ones((n, n), bool)
    keep[:3], keep[-2:], keep[:, :3], keep[:, -2:] = False, False, False, False  # the axes (offsets, glow)
    floor = float(np.median(power[keep]))
    return peak / floor if floor > 0 else (math.inf if peak > 0 else 0.0)


_CACHE: dict[tuple, MasterDark] = {}


def master_dark_cached(paths: Sequence[str | os.PathLike], **kw: Any) -> MasterDark:
    """`build_master_dark`, kept for the same files (path, size, mtime) and options: the app inspects
    frame after frame with one set of darks and builds their master once."""
    key = (tuple((os.path.abspath(p), *_stat(p)) for p in paths), tuple(sorted(kw.items())))
    hit = _CACHE.get(key)
    if hit is None:
        hit = build_master_dark(paths, **kw)
        if len(_CACHE) >= 2:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = hit
    return hit


def _stat(path: str | os.PathLike) -> tuple[int, int]:
    try:
        st = os.stat(path)
    except OSError:
        return (0, 0)
    return (st.st_size, st.st_mtime_ns)


# --------------------------------------------------------------------------------------------- frames


def replace_bad_pixels(img: np.ndarray, bad: np.ndarray, cfa: str | None) -> np.ndarray:
    """Replace the `bad` pixels of `img` in place by the median of their 8 same-channel neighbours that
    are not bad (the 16 of the next ring where none is); returns img. (On the independent analytic
    frames' sharp sub-image rims the median of 8 errs least: 0.040 of white RMS, against 0.045 for the
    mean of the 4 nearest, 0.049 for the mean of the least-different opposite pair, 0.051 for a
    quadratic fitted to the 5 x 5 window.)"""
    ys, xs = np.nonzero(bad)
    if not ys.size:
        return img
    step = 1 if cfa is None else 2
    h, w = img.shape
    vals = np.full((ys.size, 24), np.nan, dtype=np.float32)
    k = 0
    for r in (1, 2):
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                if max(abs(dy), abs(dx)) != r:
                    continue
                yy, xx = ys + dy * step, xs + dx * step
                ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
                yy, xx = np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)
                ok &= ~bad[yy, xx]
                vals[:, k] = np.where(ok, img[yy, xx], np.nan)
                k += 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: handled below
        near = np.nanmedian(vals[:, :8], axis=1)
        wide = np.nanmedian(vals, axis=1)
    rep = np.where(np.isfinite(near), near, wide)
    ok = np.isfinite(rep)
    img[ys[ok], xs[ok]] = rep[ok].astype(img.dtype)
    return img


def repair_mask(frames: Sequence[RawFrame], dark: MasterDark) -> np.ndarray:
    """The pixels the subtraction cannot restore: every dead pixel, and the hot pixels at the white
    level in any frame (clipped: their signal is lost). A hot pixel below it is restored by the
    subtraction to within its noise (0.2 DN/e: 25 DN for 3,000 DN of dark), where an interpolation from
    its neighbours errs by 4 % of white on a sub-image's rim."""
    out = dark.dead.copy()
    hy, hx = np.nonzero(dark.hot)
    if hy.size:
        sat = np.zeros(hy.size, bool)
        for f in frames:
            sat |= np.asarray(f.data[hy, hx]) >= f.white_level
        out[hy[sat], hx[sat]] = True
    return out


def correct(frames: Sequence[RawFrame], dark: MasterDark | None = None) -> np.ndarray:
    """The prepared float32 image of one frame or a stack of one state: averaged, master dark
    subtracted, checked for a black frame, normalized, bad pixels replaced (the dark's map) or hot
    pixels suppressed (no dark). The frames were checked (sizes, facts, exposure) by the caller."""
    first = frames[0]
    if len(frames) == 1 and dark is None:
        acc = normalized(first)
        return suppress_hot_pixels(acc, first.cfa, inplace=True)[0].astype(np.float32, copy=False)
    acc = np.asarray(first.data, dtype=np.float32).copy()
    for f in frames[1:]:
        acc += f.data
    if len(frames) > 1:
        acc *= np.float32(1.0 / len(frames))
    if dark is not None:
        acc -= dark.level
        acc += np.float32(first.black_level)
    frame = RawFrame(acc, first.bits, first.cfa, first.black_level, first.white_level, first.metadata, first.source,
                     first.levels_from)
    if dark is not None:
        check_exposure(frame)  # a frame that was only its dark is black now
    img = normalized(frame)
    if dark is not None:
        replace_bad_pixels(img, repair_mask(frames, dark), first.cfa)
    else:
        suppress_hot_pixels(img, first.cfa, inplace=True)
    return img.astype(np.float32, copy=False)


def load_frames(paths: str | os.PathLike | Sequence[str | os.PathLike], cfg: Any, levels: Levels | None = None,
                notes: list[str] | None = None, dark: MasterDark | None = None) -> tuple[np.ndarray, dict]:
    """Load one raw or a stack of raws of one state (the config's sensor size), settle their levels,
    check them against each other and the master dark, check exposure, and prepare the image
    (`correct`). Returns (image, noise info: `noise_info`); `notes` gets the sentences for the report."""
    s = cfg.sensor
    sensor = Levels(s.bit_depth, s.black_level_dn)
    paths = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    frames, facts = [], []
    for p in paths:
        frame = resolve_levels(load_raw(p, expected_shape=(s.height_px, s.width_px)), levels, sensor)
        f = FrameFacts.of(frame, p)
        if dark is not None:
            dark.check(f)
        if facts:
            compare(facts[0], f, "frame", "frame")
            frame = RawFrame(frame.data, frames[0].bits, frames[0].cfa, frames[0].black_level, frames[0].white_level,
                             frame.metadata, frame.source, frames[0].levels_from)  # one scale for the whole stack
        check_exposure(frame)
        frames.append(frame)
        facts.append(f)
    if notes is not None and frames[0].levels_from != "file":
        notes.append(levels_note(frames[0]))
    img = correct(frames, dark)
    info = noise_info(len(frames), dark)
    if notes is not None:
        notes.extend(noise_notes(info, [Path(p).name for p in paths]))
    return img, info


def noise_info(frames: int, dark: MasterDark | None) -> dict:
    """What the stack and the dark did to the frame's noise: `frames_averaged`, `noise_scale` (1/√K of
    one frame's pixel noise), `dark` (the master's summary, or None) and `dark_pixel_noise_dn` (an unlit
    pixel's noise after the subtraction: the stack's read noise and the master's, in quadrature)."""
    out: dict = {"frames_averaged": int(frames), "noise_scale": round(1.0 / math.sqrt(frames), 4),
                 "dark": dark.summary() if dark is not None else None}
    if dark is not None:
        out["dark_pixel_noise_dn"] = round(math.sqrt(dark.read_noise_dn ** 2 / frames + dark.noise_dn ** 2), 4)
    return out


def noise_notes(info: dict, names: Sequence[str] = ()) -> list[str]:
    """The report's sentences on the stack and the dark."""
    out = []
    k = info["frames_averaged"]
    if k > 1:
        listed = f" ({', '.join(names)})" if names and len(names) <= 8 else ""
        out.append(f"Averaged from {k} frames of one state{listed}: the pixel noise is 1/√{k} = "
                   f"{info['noise_scale']:.2f} of one frame's, and the detection limit is this average's.")
    d = info.get("dark")
    if d:
        how = "median" if d["method"] == "median" else "sigma-clipped mean"
        out.append(f"Dark-subtracted: a master dark, the {how} of {d['frames']} frame{'s' * (d['frames'] != 1)} "
                   f"(read noise {d['read_noise_dn']:.3g} counts per frame, the master's own {d['master_noise_dn']:.3g}; "
                   f"an unlit pixel's noise after subtraction {info['dark_pixel_noise_dn']:.3g} counts); its "
                   f"{d['hot_pixels']} hot and {d['dead_pixels']} dead pixels are this frame's bad pixels, not guessed "
                   "from it (hot ones restored by the subtraction unless clipped, those and the dead replaced from "
                   "their neighbours).")
    return out


def with_noise(result: Any, info: dict | None) -> Any:
    """`result` with `info` as its detection limit's `noise` entry, where a stack or a dark was used
    (the dict is mutable, as timings_s; the result is frozen)."""
    if info and (info.get("frames_averaged", 1) > 1 or info.get("dark")):
        result.detection_limit["noise"] = info
    return result


def prepare_check(raws: Sequence[str | os.PathLike], dark: MasterDark | None) -> None:
    """Check every raw's `.meta.json` sidecar against the master dark before anything is inspected or
    written (frames without one are checked as they are loaded)."""
    if dark is None:
        return
    for raw in raws:
        facts = FrameFacts.from_meta(raw)
        if facts is not None:
            dark.check(FrameFacts(facts.name, facts.shape, facts.bits, facts.cfa if facts.cfa else dark.facts.cfa,
                                  dark.facts.normalized, facts.exposure_us, facts.gain))


def scan_dark_frames(folder: str | os.PathLike) -> list[str]:
    """A scan folder's dark frames: the raws beside it (or in its `darks`/`dark` subfolder) whose
    `.meta.json` sidecar says `"dark": true` (`mlaqc capture --dark --out SCAN`), in name order; the scan's
    own `pos_*` frames are not read (it runs for every position of a scan that inspects as it goes)."""
    folder = Path(folder)
    out = []
    for where in (folder, folder / "darks", folder / "dark"):
        if not where.is_dir():
            continue
        for side in sorted(where.glob("*" + META_SUFFIX)):
            if side.name.startswith("pos_"):  # the scan's own frames (drivers.scan): never dark, and many
                continue
            try:
                rec = json.loads(side.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, ValueError):
                continue
            if isinstance(rec, dict) and rec.get("dark") is True:
                raw = where / (rec.get("file") if isinstance(rec.get("file"), str) else side.name[:-len(META_SUFFIX)])
                if raw.is_file():
                    out.append(str(raw))
    return out


__all__ = ["FrameFacts", "MasterDark", "build_master_dark", "correct", "load_frames", "master_dark_cached",
           "noise_info", "noise_notes", "prepare_check", "replace_bad_pixels", "scan_dark_frames", "with_noise"]
