"""Through-focus frames as stored (`SpotFrame`, `prepare_spots`) and every lens' spot window in them: cut, first guess, moments."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mlaqc.inspection import throughfocus_kernels as kern
from mlaqc.inspection.raw_levels import normalized
from mlaqc.inspection.rawio import RawFrame

WINDOW_SIGMAS = 4.0  # moment window half-width, in the spot's per-axis rms
MIN_WINDOW_PX = 2.0  # never narrower: a spot smaller than a pixel still has the pixel's own width
SATURATED = 0.999  # a prepared (normalized) pixel at or above this is at the white level
RING_PX = 2  # the sub-image window's outer ring this wide gives the background
NOISE_WINDOWS = 128  # the frame's read noise is the robust spread of about this many windows' rings


@dataclass(frozen=True)
class SpotFrame:
    """A through-focus frame as `measure_through_focus` reads it: the counts as stored and the scale that
    normalizes them, (data - black) / span. A pinhole frame lights a few per cent of the sensor, so only
    the windows the analysis cuts are normalized (the same float32 operations as `raw_levels.normalized`, so
    the same values), never the whole frame: 32 frames of the shipped protocol are then read at 8 MB
    each as stored instead of 16 MB of float32 written and read again."""

    data: np.ndarray  # (H, W): integer counts, or an already normalized float32 frame (black 0, span 1)
    black: float = 0.0
    span: float = 1.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape  # type: ignore[return-value]

    @classmethod
    def of(cls, img: SpotFrame | np.ndarray) -> SpotFrame:
        """`img` itself, or an array taken as an already normalized frame."""
        return img if isinstance(img, SpotFrame) else cls(np.asarray(img))

    @property
    def counts(self) -> bool:
        """True for integer data: normalized by construction, no NaN (float data may hold anything)."""
        return self.data.dtype.kind in "iu"

    def image(self) -> np.ndarray:
        """The whole frame normalized (float32), as the analysis' windows see it: for display."""
        out = self.data.astype(np.float32)  # a copy, then in place
        out -= np.float32(self.black)
        out /= np.float32(self.span)
        return out


def prepare_spots(frame: RawFrame) -> SpotFrame:
    """A through-focus frame for `measure_through_focus`: black-subtracted and normalized (CFA sites
    balanced), without the hot-pixel pass of `pipeline.prepare` (which takes a focused spot's peak pixel
    for a hot pixel and cuts it). A monochrome integer frame stays as stored (`SpotFrame`); a CFA frame's
    site gains need the whole frame, so it is normalized whole."""
    if frame.cfa is None and frame.data.dtype.kind in "iu":
        return SpotFrame(frame.data, float(frame.black_level), float(frame.white_level - frame.black_level))
    return SpotFrame(normalized(frame).astype(np.float32, copy=False))


@dataclass(frozen=True)
class Spots:
    """One frame's windows around L lenses; window pixel coordinates are relative to the centre pixel."""

    cells: np.ndarray  # (L, n, n) background-subtracted
    ix: np.ndarray  # (L,) frame column of the window's centre pixel
    iy: np.ndarray
    background: np.ndarray  # (L,)
    bg_sigma: float  # the frame's unlit-pixel noise (normalized units)
    saturated: np.ndarray  # (L,) bool


def spots(img: SpotFrame | np.ndarray, x_px: np.ndarray, y_px: np.ndarray, half: int) -> Spots:
    """Cut every lens' window (centred on the pixel nearest (x, y), inside the frame), normalized,
    subtract its background (the median of its outer ring) and note saturation. Compiled:
    mlaqc.inspection.throughfocus_kernels.spot_windows_kernel."""
    frame = SpotFrame.of(img)
    ix = np.rint(x_px).astype(np.int64)
    iy = np.rint(y_px).astype(np.int64)
    n, L = 2 * half + 1, len(ix)
    if half <= RING_PX:
        raise ValueError(f"a spot window of half-width {half} px has no pixels inside its {RING_PX}-px ring")
    height, width = frame.shape
    if L and (min(ix.min(), iy.min()) < half or ix.max() + half >= width or iy.max() + half >= height):
        raise ValueError("a spot window reaches past the frame's edge")  # the kernel reads without bounds checks
    cells, bg, sat = np.empty((L, n, n)), np.empty(L, np.float32), np.empty(L, bool)
    kern.spot_windows_kernel(frame.data, iy - half, ix - half, frame.black, frame.span, RING_PX, SATURATED,
                             cells, bg, sat)
    # the frame's unlit-pixel noise: the rings of about NOISE_WINDOWS windows spread over the frame
    ring = np.ones((n, n), bool)
    ring[RING_PX:n - RING_PX, RING_PX:n - RING_PX] = False
    resid = cells[::max(1, L // NOISE_WINDOWS)][:, ring]
    bg_sigma = 1.4826 * float(np.median(np.abs(resid))) if resid.size else 0.0
    return Spots(cells, ix, iy, bg, bg_sigma, sat)


def moments(sp: Spots, cx: np.ndarray, cy: np.ndarray, w: np.ndarray, e_per_unit: float, refine: int = 2,
            variance: bool = True):
    """Centroid (window coordinates), second moment x + y (px^2), its variance and the flux of every
    spot in a window of half-width `w` around (cx, cy); the window follows the centroid `refine` times
    and shrinks so that it stays inside the ring. Pixels at the window's edge weigh by the share of
    them inside it (a row weight times a column weight). The variance is the delta method's
    (d m2 / d v_ij = w_ij (r2_ij - m2) / flux) over the pixels' shot and read noise, plus the ring
    median's. Returns (mx, my, m2, m2_var, flux, w); m2_var is None unless `variance`.
    Compiled: mlaqc.inspection.throughfocus_kernels."""
    L = len(sp.cells)

    def per_lens(v) -> np.ndarray:  # (L,) contiguous float64: one compiled specialization
        return np.ascontiguousarray(np.broadcast_to(np.asarray(v, np.float64), (L,)))

    out = np.empty((L, 6))
    kern.moments_kernel(np.ascontiguousarray(sp.cells, dtype=np.float64), per_lens(sp.background), per_lens(cx),
                        per_lens(cy), per_lens(w), int(refine), float(e_per_unit), float(sp.bg_sigma), RING_PX,
                        bool(variance), out)
    m2_var = out[:, kern.M2_VAR] if variance else None
    return out[:, kern.MX], out[:, kern.MY], out[:, kern.M2], m2_var, out[:, kern.FLUX], out[:, kern.WIDTH]


def _first_guess(sp: Spots) -> tuple[np.ndarray, np.ndarray]:
    """The brightest 3 x 3 sum inside the ring of every window (window coordinates)."""
    out = np.empty((len(sp.cells), 2))
    kern.first_guess_kernel(np.ascontiguousarray(sp.cells, dtype=np.float64), RING_PX, out)
    return out[:, 0], out[:, 1]


def _spot_window(sp: Spots, e_per_unit: float):
    """Each spot's centroid and a window of WINDOW_SIGMAS of its per-axis rms (at least MIN_WINDOW_PX)."""
    cx, cy = _first_guess(sp)
    w = np.full(len(cx), 3.0)
    for _ in range(2):
        cx, cy, m2, _, _, _ = moments(sp, cx, cy, w, e_per_unit, refine=1, variance=False)
        sig = np.sqrt(np.clip(0.5 * np.where(np.isfinite(m2), m2, 1.0), 0.0, None))
        w = np.maximum(WINDOW_SIGMAS * sig, MIN_WINDOW_PX)
    return cx, cy, w


__all__ = ["prepare_spots"]
