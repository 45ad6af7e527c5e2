"""cos(2*pi*u), sin(2*pi*u) for uniform draws u, to about 1 ulp, with no library call or branch.

Both engines sample pupil angles with it, so their rays are identical, and the compiled loop vectorizes
(libm's cos/sin would not). Reduction: v = 4u, q = round(v), r = v - q in [-1/2, 1/2] (exact), alpha = r*pi/2;
Taylor series of sin/cos on |alpha| <= pi/4 (truncation < 1e-16), then an exact quarter-turn by q mod 4.
"""

from __future__ import annotations

import math

import numpy as np

_S = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(9))  # sin: alpha^1 .. alpha^17
_C = tuple((-1.0) ** k / math.factorial(2 * k) for k in range(10))  # cos: alpha^0 .. alpha^18
S0, S1, S2, S3, S4, S5, S6, S7, S8 = _S
C0, C1, C2, C3, C4, C5, C6, C7, C8, C9 = _C
HALF_PI = 0.5 * math.pi


def poly_sin(a, a2):
    """sin(a) for |a| <= pi/4 by Horner in a^2 (works on floats and arrays alike)."""
    return a * (S0 + a2 * (S1 + a2 * (S2 + a2 * (S3 + a2 * (S4 + a2 * (S5 + a2 * (S6 + a2 * (S7 + a2 * S8))))))))


def poly_cos(a2):
    """cos(a) for |a| <= pi/4 from a^2."""
    return C0 + a2 * (C1 + a2 * (C2 + a2 * (C3 + a2 * (C4 + a2 * (C5 + a2 * (C6 + a2 * (C7 + a2 * (C8 + a2 * C9))))))))


def cos_sin_2pi(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos 2*pi*u, sin 2*pi*u) for an array of u in [0, 1)."""
    v = 4.0 * u
    q = np.floor(v + 0.5)
    a = (v - q) * HALF_PI
    a2 = a * a
    c, s = poly_cos(a2), poly_sin(a, a2)
    iq = q.astype(np.int64) & 3
    swap = (iq & 1) == 1
    sign_c = np.where((iq == 1) | (iq == 2), -1.0, 1.0)
    sign_s = np.where(iq >= 2, -1.0, 1.0)
    return sign_c * np.where(swap, s, c), sign_s * np.where(swap, c, s)


# Counter-based uniform draws: draw d of ray i in a batch with key k is SplitMix64's output for the state
# k + (4*i + d + 1) * GAMMA, so any ray can be drawn on its own (threads, blocks, both engines agree).
GAMMA = np.uint64(0x9E3779B97F4A7C15)
MIX1 = np.uint64(0xBF58476D1CE4E5B9)
MIX2 = np.uint64(0x94D049BB133111EB)
TO_UNIT = 2.0 ** -53


def counter_uniforms(key: int, n: int, dims: int, first: int = 0) -> np.ndarray:
    """(dims, n) float64 draws in [0, 1) for rays first..first+n-1 of the batch with `key`."""
    i = np.arange(first, first + n, dtype=np.uint64)
    out = np.empty((dims, n))
    with np.errstate(over="ignore"):
        for d in range(dims):
            z = np.uint64(key) + (np.uint64(4) * i + np.uint64(d + 1)) * GAMMA
            z = (z ^ (z >> np.uint64(30))) * MIX1
            z = (z ^ (z >> np.uint64(27))) * MIX2
            z = z ^ (z >> np.uint64(31))
            out[d] = (z >> np.uint64(11)).astype(np.float64) * TO_UNIT
    return out
