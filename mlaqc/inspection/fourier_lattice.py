"""The sub-image lattice of a white image from its Fourier transform (`_fft_lattice`): pitch, rotation and
offset of the lattice, and the packing its spectrum shows; the calibration's first step
(mlaqc.inspection.calibrate), from which every lens' disc fit (mlaqc.inspection.disc_fit) starts. Kept on
its own as the one place the packings' Fourier peaks and the half-period choice live.

Lattice from the Fourier transform of the (Hann-windowed, for big frames 2x2- or 4x4-binned) white
image: the two fundamental peaks give pitch and rotation (refined to ~0.01 bin with a local DTFT),
their phases the lattice offset (the remaining half-period ambiguity is settled by where the cell
corners are dark). Square: the peaks at |k| = 1/p, 90 degrees apart. Hex: two of the six at
|k| = 2/(sqrt(3) p), 60 degrees apart; the real basis is then a1 along the rows (~x) and a2 at +60
degrees (down-right as displayed), both a pitch long ("axial" lattice coordinates (j, i)); the basis
is refined on the second shell (|k| = 2/p) where that is the stronger, or where the first shell's
three peaks do not close (b1 + b2 off the third: sub-images growing through its zero across the
field pull them all the same way); the cell offset is the half-period shift about which the frame
is six-fold symmetric. A spectrum plainly of the other packing than the config's (shells of equal
peaks 60 rather than 90 degrees apart, or the reverse) is refused by name.

`_bilinear` (the frame sampled between pixels, for the origin's choice) is here too; the calibration's
background check samples the cell corners with it. Pixel conventions as mlaqc.inspection.grid's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mlaqc.errors import InputError
from mlaqc.inspection import calibrate_kernels as kernels
from mlaqc.inspection.disc_fit import _workers  # the transform's threads: as many as the disc fit's
from mlaqc.inspection.fft import rfft2
from mlaqc.optics.lattice import SQRT3_2

# Thresholds (relative units unless stated).
PITCH_TOLERANCE = 0.10  # the found pitch may differ from the expected one by 10 %
MIN_PITCH_PX = 4.0


# -------------------------------------------------------------------------------------------- lattice


@dataclass(frozen=True)
class _Lattice:
    """The image's sub-image lattice: point (j, i) (lattice coordinates) lies at origin + basis @ (j, i).
    Square: a1 along n (~x), a2 along m (~y). Hex: a1 along the rows (~x), a2 at 60 degrees from it
    (down and to the right as displayed), both one pitch long ("axial" coordinates)."""

    basis: np.ndarray  # (2, 2): columns a1 and a2, px
    origin: np.ndarray  # (2,) a lattice point (sub-image centre) near the frame centre, px
    packing: str = "square"


def _hann(n: int) -> np.ndarray:
    return (0.5 - 0.5 * np.cos(2.0 * np.pi * (np.arange(n) + 0.5) / n)).astype(np.float32)


def _dtft(a: np.ndarray, kxs: np.ndarray, kys: np.ndarray) -> np.ndarray:
    """DTFT of `a` (coordinates about the frame centre) on the grid kys x kxs (cycles/px), real matmuls."""
    h, w = a.shape
    x = (np.arange(w) - 0.5 * (w - 1)).astype(np.float64)
    y = (np.arange(h) - 0.5 * (h - 1)).astype(np.float64)
    px = 2.0 * np.pi * np.outer(kxs, x)
    t = kernels.row_dots(a, np.concatenate([np.cos(px), -np.sin(px)]).astype(np.float32))  # (h, 2 nx)
    row = (t[:, : len(kxs)] + 1j * t[:, len(kxs):]).astype(np.complex128)
    ey = np.exp(-2j * np.pi * np.outer(kys, y))
    return ey @ row


def _refine_peak(a: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, complex]:
    """Sub-bin peak of |DTFT|^2 near k: quadratic fits of log power on shrinking 5x5 grids."""
    h, w = a.shape
    k = np.array(k, dtype=np.float64)
    off = np.arange(-2, 3, dtype=np.float64)
    gy, gx = np.meshgrid(off, off, indexing="ij")
    design = np.stack([np.ones(25), gx.ravel(), gy.ravel(), gx.ravel() ** 2, (gx * gy).ravel(), gy.ravel() ** 2], 1)
    for step in (0.3, 0.08, 0.02):
        f = _dtft(a, k[0] + off * step / w, k[1] + off * step / h)
        lp = np.log(np.abs(f) ** 2 + 1e-300).ravel()
        c = np.linalg.lstsq(design, lp, rcond=None)[0]
        hess = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
        try:
            d = np.linalg.solve(hess, -c[1:3])
        except np.linalg.LinAlgError:
            d = np.zeros(2)
        if not (hess[0, 0] < 0 and np.linalg.det(hess) > 0):
            d = np.array(np.unravel_index(np.argmax(lp), (5, 5))[::-1], float) - 2.0
        d = np.clip(d, -2.0, 2.0)
        k = k + d * step / np.array([w, h])
    return k, complex(_dtft(a, k[:1], k[1:])[0, 0])


def _fft_lattice(img: np.ndarray, expected_pitch_px: float | None, packing: str = "square") -> _Lattice:
    """Pitch, rotation and offset of the sub-image lattice of `packing` from the image's Fourier transform."""
    full_h, full_w = img.shape
    # large frames of coarse lattices: b x b binning keeps the fundamental periods (>= 5 binned px) and the
    # frame centre, and costs 1 / b^2 of the transform and of the peak refinement
    b = 1
    if expected_pitch_px is not None:
        while b < 4 and expected_pitch_px >= 10.0 * b and min(full_h, full_w) >= 1024 * b:
            b *= 2
    binned = b > 1
    if binned:
        src = img[: full_h // b * b, : full_w // b * b]
        acc = src[0::b, 0::b].copy()
        for i in range(b):
            for j in range(b):
                if i or j:
                    acc += src[i::b, j::b]  # strided adds: far faster than a reshaped mean
        src = acc * np.float32(1.0 / (b * b))
        expected_pitch_px = expected_pitch_px / b
    else:
        src = img
    h, w = src.shape
    a = (src - np.float32(src.mean())) * _hann(h)[:, None] * _hann(w)[None, :]
    spec = rfft2(a, workers=_workers() if a.size > 1 << 20 else 1)  # small: threads cost more
    power = spec.real ** 2 + spec.imag ** 2
    ky = np.fft.fftfreq(h).astype(np.float32)
    kx = np.fft.rfftfreq(w).astype(np.float32)
    kr = np.hypot(ky[:, None], kx[None, :])
    band = (kr >= 6.0 / min(h, w)) & (kr <= 1.0 / MIN_PITCH_PX)
    pb = np.where(band, power, 0.0)
    if not pb.any():
        raise InputError("the white image shows no periodic microlens structure")
    iy, ix = np.nonzero(pb >= 0.03 * pb.max())
    if iy.size > 20000:  # a noise-like spectrum: no clear peaks
        raise InputError("the white image shows no periodic microlens structure")
    pv = pb[iy, ix]
    nb = np.stack([pb[(iy + dy) % h, np.clip(ix + dx, 0, pb.shape[1] - 1)]
                   for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])
    is_peak = pv >= nb.max(axis=0)
    iy, ix, pv = iy[is_peak], ix[is_peak], pv[is_peak]
    floor = float(np.median(power[::4, ::4][band[::4, ::4]]))
    if pv.size == 0 or pv.max() <= 200.0 * max(floor, 1e-30):
        raise InputError("the white image shows no periodic microlens structure")
    strong = pv >= 0.03 * pv.max()
    iy, ix, pv = iy[strong], ix[strong], pv[strong]
    kvec = np.stack([kx[ix], ky[iy]], 1).astype(np.float64)
    kmag = np.hypot(kvec[:, 0], kvec[:, 1])
    order = np.argsort(kmag)
    kvec, kmag, pv = kvec[order], kmag[order], pv[order]
    if packing == "hex":
        return _hex_lattice(img, a, kvec, kmag, pv, b, expected_pitch_px)
    first = kvec[0]
    if expected_pitch_px is not None:
        near = np.abs(kmag * expected_pitch_px - 1.0) <= PITCH_TOLERANCE
        if not near.any():
            _refuse_mismatch(kvec, pv, "square")
            unit = float(b)
            raise InputError(f"the microlens pitch in the image ({unit / kmag[0]:.2f} px) is far from the expected "
                             f"{unit * expected_pitch_px:.2f} px; check the camera config and the image")
        first = kvec[np.argmax(near)]
    # its partner: the strongest peak roughly perpendicular with a similar length
    cosang = np.abs(kvec @ first) / (np.hypot(kvec[:, 0], kvec[:, 1]) * np.hypot(*first))
    ratio = np.hypot(kvec[:, 0], kvec[:, 1]) / np.hypot(*first)
    partner = (cosang < math.sin(math.radians(10))) & (np.abs(ratio - 1) < 0.1)
    if not partner.any():
        _refuse_mismatch(kvec, pv, "square")
        raise InputError("the white image shows no square microlens lattice (only one periodic direction found)")
    second = kvec[np.argmax(np.where(partner, pv, -1))]
    k1, f1 = _refine_peak(a, first)
    k2, f2 = _refine_peak(a, second)
    # order: k1 along x (n), k2 along y (m); signs so that the real-space axes point +x and +y
    if abs(k1[0]) < abs(k2[0]):
        k1, k2, f1, f2 = k2, k1, f2, f1
    kmat = np.array([k1, k2])  # rows: reciprocal vectors; basis = inverse
    basis = np.linalg.inv(kmat)  # columns a1, a2 with k_i . a_j = delta_ij
    phase = -np.angle([f1, f2]) / (2.0 * np.pi)
    if basis[0, 0] < 0:
        basis[:, 0] *= -1
        phase[0] *= -1
    if basis[1, 1] < 0:
        basis[:, 1] *= -1
        phase[1] *= -1
    if binned:  # back to frame pixels: x = b x_binned + (b - 1) / 2, the same centre for frame sizes of b n
        basis *= b
        expected_pitch_px *= b
        h, w = full_h // b * b, full_w // b * b
    pitch = np.hypot(basis[0], basis[1])
    if pitch.min() < MIN_PITCH_PX:
        raise InputError(f"the periodic structure in the image ({pitch.min():.2f} px) is too fine for microlenses")
    if expected_pitch_px is not None and np.any(np.abs(pitch / expected_pitch_px - 1) > PITCH_TOLERANCE):
        _refuse_mismatch(kvec, pv, "square")
        raise InputError(f"the microlens pitch in the image ({pitch[0]:.2f} x {pitch[1]:.2f} px) is far from the expected "
                         f"{expected_pitch_px:.2f} px; check the camera config and the image")
    centre = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    base = centre + basis @ phase
    origin = _resolve_half_period(img, basis, base)
    return _Lattice(basis, origin)


PACKING_WORDS = {"square": "square", "hex": "hexagonal"}


def _spectrum_packing(kvec: np.ndarray, pv: np.ndarray) -> str | None:
    """The packing the spectrum's peaks show, or None if unclear: a hexagonal lattice's shells of equal
    peaks lie 60 degrees apart, a square one's 90 degrees. Looked at round the lowest and the strongest
    peak (peaks of one shell have lengths within 3 %; directions are lines, k and -k alike)."""
    if kvec.shape[0] < 2:
        return None
    mag = np.hypot(kvec[:, 0], kvec[:, 1])
    votes = set()
    for ref in {0, int(np.argmax(pv))}:
        same = np.abs(mag / mag[ref] - 1.0) < 0.03
        same[ref] = False
        cos = np.abs(kvec[same] @ kvec[ref]) / (mag[same] * mag[ref])
        if np.any(cos < math.sin(math.radians(5.0))):
            votes.add("square")
        if np.any(np.abs(cos - 0.5) < 0.075):  # 60 or 120 degrees, within ~5
            votes.add("hex")
    return votes.pop() if len(votes) == 1 else None


def _refuse_mismatch(kvec: np.ndarray, pv: np.ndarray, packing: str) -> None:
    """InputError if the spectrum plainly shows the other packing than the config's."""
    seen = _spectrum_packing(kvec, pv)
    if seen is not None and seen != packing:
        raise InputError(f"the white image shows a {PACKING_WORDS[seen]} microlens lattice but the config says "
                         f"mla.packing = {packing!r}")


def _hex_lattice(img: np.ndarray, a: np.ndarray, kvec: np.ndarray, kmag: np.ndarray, pv: np.ndarray, b: int,
                 expected_pitch_px: float | None) -> _Lattice:
    """The hexagonal lattice from the (binned by b, windowed) frame `a`'s spectral peaks (sorted by |k|):
    two of the six fundamental peaks (|k| = 2 / (sqrt(3) p), 60 degrees apart) give the lattice and its
    offset; the basis is then a1 along the rows (the lattice vector nearest +x), a2 at +60 degrees."""
    full_h, full_w = img.shape
    _refuse_mismatch(kvec, pv, "hex")
    first, shell = kvec[0], 1
    if expected_pitch_px is not None:  # binned px here
        near = np.abs(kmag * expected_pitch_px * SQRT3_2 - 1.0) <= PITCH_TOLERANCE
        # discs whose transform has a zero at the first shell (a defocused array's) leave only the second
        # shell (|k| = 2 / p) among the strong peaks
        near2 = np.abs(kmag * expected_pitch_px * 0.5 - 1.0) <= PITCH_TOLERANCE
        if not near.any() and not near2.any():
            raise InputError(f"the microlens pitch in the image ({b / (kmag[0] * SQRT3_2):.2f} px) is far from the "
                             f"expected {b * expected_pitch_px:.2f} px; check the camera config and the image")
        first, shell = (kvec[np.argmax(near)], 1) if near.any() else (kvec[np.argmax(near2)], 2)
    mag = np.hypot(kvec[:, 0], kvec[:, 1])
    cosang = np.abs(kvec @ first) / (mag * np.hypot(*first))
    partner = (np.abs(cosang - 0.5) < 0.15) & (np.abs(mag / np.hypot(*first) - 1) < 0.1)
    if not partner.any():
        raise InputError("the white image shows no hexagonal microlens lattice (only one periodic direction found)")
    second = kvec[np.argmax(np.where(partner, pv, -1))]
    if shell == 1:
        k1, f1 = _refine_peak(a, first)
        k2, f2 = _refine_peak(a, second)
    else:  # second-shell peaks q1, q2 60 degrees apart: first-shell (2 q1 - q2) / 3 and (q1 + q2) / 3
        q1, _ = _refine_peak(a, first)
        q2, _ = _refine_peak(a, second)
        k1, k2 = (2.0 * q1 - q2) / 3.0, (q1 + q2) / 3.0
        f1, f2 = (complex(_dtft(a, k[:1], k[1:])[0, 0]) for k in (k1, k2))
    prime = np.linalg.inv(np.array([k1, k2])) * b  # columns: a lattice basis (k_i . a_j = delta_ij), frame px
    phase = -np.angle([f1, f2]) / (2.0 * np.pi)
    h, w = (full_h // b * b, full_w // b * b) if b > 1 else (full_h, full_w)
    centre = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    base = centre + prime @ phase
    basis = _second_shell_basis(a, _hex_basis(prime) / b, min(abs(f1), abs(f2))) * b
    pitch = np.hypot(basis[0], basis[1])
    if pitch.min() < MIN_PITCH_PX:
        raise InputError(f"the periodic structure in the image ({pitch.min():.2f} px) is too fine for microlenses")
    if expected_pitch_px is not None and np.any(np.abs(pitch / (b * expected_pitch_px) - 1) > PITCH_TOLERANCE):
        raise InputError(f"the microlens pitch in the image ({pitch[0]:.2f} x {pitch[1]:.2f} px) is far from the expected "
                         f"{b * expected_pitch_px:.2f} px; check the camera config and the image")
    candidates = [base + basis @ np.array([sx, sy]) for sx in (0.0, 0.5) for sy in (0.0, 0.5)]
    candidates += _second_shell_origins(a, basis / b, centre, b)
    origin = _six_fold_origin(img, basis, candidates)
    return _Lattice(basis, origin, "hex")


def _second_shell_origins(a: np.ndarray, basis: np.ndarray, centre: np.ndarray, b: int) -> list[np.ndarray]:
    """Lattice origins (frame px) the second shell's phases allow (`basis`: binned px). Where the
    sub-image radius crosses the first shell's zero within the frame (a tilted, defocused array: its
    sub-images grow across the field) the first-shell phases mix both signs and say nothing; the second
    shell's, P1 = 2 f1 + f2 and P2 = f1 + 2 f2 (f: the origin in lattice units), fix f up to thirds of a
    period and the transform's common sign: 9 candidates, sorted out by their six-fold symmetry."""
    k1, k2 = np.linalg.inv(basis)
    phases = [-np.angle(_dtft(a, q[:1], q[1:])[0, 0]) / (2.0 * np.pi) for q in (2.0 * k1 + k2, k1 + 2.0 * k2)]
    out = []
    for sign in (0.0, 0.5):
        for n1 in range(3):
            p1, p2 = phases[0] + sign + n1, phases[1] + sign
            f = np.array([(2.0 * p1 - p2) / 3.0, (2.0 * p2 - p1) / 3.0])
            out.append(centre + (basis * b) @ f)
    return out


# the second shell's peaks are looked for this far (FFT bins) round where the first shell
# puts them: a first shell pulled by a bin puts them up to three bins off (2 b1 + b2 carries its pull thrice)
SHELL_SEARCH_BINS = 4
# a shell's third peak lies at the sum (first shell) or difference (second) of the other two, to noise (~1e-4
# of |k|); a shell pulled off by a zero of the discs' transform crossing the field misses it by the pull
CLOSURE_TOLERANCE = 2e-3


def _second_shell_basis(a: np.ndarray, basis: np.ndarray, first_level: float) -> np.ndarray:
    """The hex basis (binned px) refined on the second shell of peaks (|k| = 2 / p: 2 b1 + b2 and b1 + 2 b2,
    b_i the reciprocal basis) where that shell is the better: the stronger (`first_level`: the weaker
    first-shell peak's |DTFT|), or the only one of the two whose three peaks close (`_shell_closure`).
    Discs of about half the pitch, as an f-number-matched camera makes, have their first-shell peaks next
    to a zero of the disc's transform (2 pi |k| R ~ 3.7 against 3.83): weak, good to a few 1e-4 of the pitch
    only; the second shell is then about twice as strong and twice as far out (discs of ~0.3 p have it at
    the zero instead). A tilted, defocused array whose sub-images grow through that zero across the frame
    has the first shell's peaks, sums over the field of both signs, all pulled off by the same few 1e-3
    cycles/px (1.4 % of |k| on the Table 1 hex array with the sensor 15 µm back and a 0.3 degree tilt):
    not a lattice (b1 + b2 misses the third peak by the pull), so its second-shell guesses are looked for
    SHELL_SEARCH_BINS round. Kept if both refined peaks lie within 10 % of where the first shell puts them
    (no other peak of the spectrum is that close)."""
    b1, b2 = np.linalg.inv(basis)
    guess = (2.0 * b1 + b2, b1 + 2.0 * b2)
    (q1, g1), (q2, g2) = (_refine_peak(a, _coarse_peak(a, q)) for q in guess)
    if max(float(np.hypot(*(q - g)) / np.hypot(*g)) for q, g in zip((q1, q2), guess)) > 0.1:
        return basis
    second = np.linalg.inv(np.array([(2.0 * q1 - q2) / 3.0, (2.0 * q2 - q1) / 3.0]))
    if min(abs(g1), abs(g2)) > first_level:
        return second
    if _shell_closure(a, b1, b2, 1.0) > CLOSURE_TOLERANCE >= _shell_closure(a, q1, q2, -1.0):
        return second
    return basis


def _coarse_peak(a: np.ndarray, k: np.ndarray) -> np.ndarray:
    """The largest |DTFT| of `a` within SHELL_SEARCH_BINS bins of k, on the bin grid (within half a bin of
    the peak, where `_refine_peak`, which reaches 0.8 bin, can start; a finer grid makes the products wide
    enough for multi-threaded BLAS, which stalls for 0.1 s at a time on a busy machine)."""
    h, w = a.shape
    off = np.arange(-SHELL_SEARCH_BINS, SHELL_SEARCH_BINS + 0.5, 1.0)
    f = np.abs(_dtft(a, k[0] + off / w, k[1] + off / h))
    iy, ix = np.unravel_index(int(np.argmax(f)), f.shape)
    return np.array([k[0] + off[ix] / w, k[1] + off[iy] / h])


def _shell_closure(a: np.ndarray, k1: np.ndarray, k2: np.ndarray, sign: float) -> float:
    """How far (in |k1|) the three peaks of a shell refined near k1, k2 and k1 + sign k2 miss closing
    (k3 = k1 + sign k2): ~1e-4 on a lattice, the pull where the shell is pulled off."""
    q1, q2, q3 = (_refine_peak(a, _coarse_peak(a, k))[0] for k in (k1, k2, k1 + sign * k2))
    return float(np.hypot(*(q1 + sign * q2 - q3)) / np.hypot(*k1))


def _hex_basis(prime: np.ndarray) -> np.ndarray:
    """The canonical basis of the hexagonal lattice spanned by `prime`'s columns: a1 the shortest lattice
    vector nearest +x, a2 the one nearest a1 turned 60 degrees towards +y (down as displayed)."""
    p1, p2 = prime[:, 0], prime[:, 1]
    vecs = np.array([p1, p2, p1 + p2, p1 - p2, -p1, -p2, -p1 - p2, p2 - p1])
    length = np.hypot(vecs[:, 0], vecs[:, 1])
    short = vecs[np.argsort(length, kind="stable")[:6]]
    a1 = short[np.argmax(short[:, 0] / np.hypot(short[:, 0], short[:, 1]))]
    c, s = 0.5, SQRT3_2
    turned = np.array([c * a1[0] - s * a1[1], s * a1[0] + c * a1[1]])
    a2 = short[np.argmax(short @ turned)]
    return np.stack([a1, a2], axis=1)


# cell corners in lattice coordinates: the square's 4, the hexagon's 6 (centroids of the lattice triangles)
_CORNERS = {"square": [(cx, cy) for cx in (-0.5, 0.5) for cy in (-0.5, 0.5)],
            "hex": [(1 / 3, 1 / 3), (-1 / 3, 2 / 3), (-2 / 3, 1 / 3), (-1 / 3, -1 / 3), (1 / 3, -2 / 3), (2 / 3, -1 / 3)]}


def _resolve_half_period(img: np.ndarray, basis: np.ndarray, base: np.ndarray, packing: str = "square") -> np.ndarray:
    """The Fourier phase fixes the lattice up to half a period per axis (the sign of the sub-image's
    transform); pick the shift whose points are bright with dark cell corners around them (hex: the
    shift about whose points the frame has the lattice's six-fold symmetry, `_six_fold_origin`)."""
    if packing == "hex":
        return _six_fold_origin(img, basis, [base + basis @ np.array([sx, sy]) for sx in (0.0, 0.5) for sy in (0.0, 0.5)])
    h, w = img.shape
    jj, ii = np.meshgrid(np.arange(-6, 7), np.arange(-6, 7))
    best, score_best = base, -np.inf
    for sx in (0.0, 0.5):
        for sy in (0.0, 0.5):
            o = base + basis @ np.array([sx, sy])
            pts = o[:, None] + basis @ np.stack([jj.ravel(), ii.ravel()])
            corners = [pts + basis @ np.array([cx, cy])[:, None] for cx, cy in _CORNERS[packing]]
            inside = lambda p: (p[0] > 1) & (p[0] < w - 2) & (p[1] > 1) & (p[1] < h - 2)  # noqa: E731
            ok = inside(pts) & np.all([inside(c) for c in corners], axis=0)
            if not ok.any():
                continue
            sample = lambda p: _bilinear(img, p[0][ok], p[1][ok])  # noqa: E731
            score = float(np.mean(sample(pts)) - np.mean([sample(c) for c in corners]))
            if score > score_best:
                best, score_best = o, score
    return best


def _six_fold_origin(img: np.ndarray, basis: np.ndarray, candidates: list[np.ndarray]) -> np.ndarray:
    """Of the candidate origins of a hex lattice (the four half-period shifts, and the second shell's
    `_second_shell_origins`), the one whose points are centres of six-fold symmetry: on rings round a sub-image centre the frame repeats every 60 degrees, round the other three
    (midpoints between two neighbours) only every 180. Brightness tests fail here: discs larger than half
    the pitch light their overlaps twice and, beyond ~0.56 p, the cell corners too. Measured on the
    analytic model for radii 0.15 - 0.65 p, noise-free and at 15 % noise. Rings at 0.2, 0.3 and 0.4 p,
    12 samples each, round 21 x 21 lattice points near the frame centre."""
    h, w = img.shape
    jj, ii = np.meshgrid(np.arange(-10, 11), np.arange(-10, 11))
    pitch = float(np.hypot(*basis[:, 0]))
    angle = math.atan2(basis[1, 0], basis[0, 0]) + np.radians(np.arange(12) * 30.0)
    best, score_best = candidates[0], np.inf
    for o in candidates:
        pts = o[:, None] + basis @ np.stack([jj.ravel(), ii.ravel()])
        score = 0.0
        for rho in (0.2 * pitch, 0.3 * pitch, 0.4 * pitch):
            rx = pts[0][:, None] + rho * np.cos(angle)[None, :]
            ry = pts[1][:, None] + rho * np.sin(angle)[None, :]
            ok = np.all((rx > 1) & (rx < w - 2) & (ry > 1) & (ry < h - 2), axis=1)
            if not ok.any():
                continue
            f = _bilinear(img, rx[ok], ry[ok])
            score += float(np.mean(np.abs(f - np.roll(f, -2, axis=1))) / (np.mean(np.abs(f)) + 1e-12))
        if score < score_best:
            best, score_best = o, score
    return best


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """img interpolated bilinearly at points (x, y) inside the frame (map_coordinates' order=1, in NumPy)."""
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    fx, fy = x - x0, y - y0
    top = img[y0, x0] * (1.0 - fx) + img[y0, x0 + 1] * fx
    bottom = img[y0 + 1, x0] * (1.0 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1.0 - fy) + bottom * fy
