"""Low-discrepancy draws: Sobol points, Owen-scrambled and digitally shifted, counter-based.

Plain Monte-Carlo (`unitcircle.counter_uniforms`) lands rays on a pixel with Poisson-like scatter. A
Sobol sequence in base 2 fills every dyadic box evenly, so the count of rays in a pixel's preimage (about a
box: a microlens cell times a patch of the exit aperture) is off by a few rays instead of sqrt(n).

- Points: Sobol directions of Joe & Kuo (new-joe-kuo-6.21201, dims 1-4), taken in Gray-code order
  (point j is the XOR of the directions of the set bits of j ^ (j >> 1)), so any point is computed on its own
  and consecutive ones by one XOR each; the first 2^m points are the same set as in natural order.
- Randomization: a nested uniform (Owen) scramble by hashing (Burley 2020, "Practical hash-based Owen
  scrambling", with Vegdahl's constants) seeded per render, then a random digital shift (XOR) per
  microlens cell (image-side scenes) or per batch (point and object-side scenes). Both keep the net
  property and make every estimate unbiased.
- Counter-based: a draw depends only on the key, the cell or batch, the point index and the dimension,
  so thread count, batch order and worker count give the same image.

The functions below are plain arithmetic on uint64 values (32-bit results, masked), so the same code runs
on NumPy arrays (the reference engine) and, compiled by Numba, on scalars (the fast engine); tests check
both against each other and the points against SciPy's unscrambled Sobol set.
"""

from __future__ import annotations

import numpy as np

from mlaqc.optics.unitcircle import GAMMA, MIX1, MIX2

DIMS = 4
MASK32 = np.uint64(0xFFFFFFFF)
TO_UNIT32 = 2.0 ** -32
# Joe & Kuo dims 2..4 (dim 1 is van der Corput): degree s, coefficients a, initial m_1..m_s.
_JOE_KUO = ((1, 0, (1,)), (2, 1, (1, 3)), (3, 1, (1, 3, 1)))
OWEN_SALT = np.uint64(0xA5A5_5A5A_C3C3_3C3C)
_K1, _K2, _K3 = np.uint64(0x3D20ADEA), np.uint64(0x05526C56), np.uint64(0x53A22864)
_ONE = np.uint64(1)


def _directions() -> np.ndarray:
    """(DIMS, 32) direction numbers v_{d,b} (bit b of the index), as uint64 holding 32 bits."""
    v = np.zeros((DIMS, 32), dtype=np.uint64)
    v[0] = [1 << (31 - b) for b in range(32)]
    for d, (s, a, m) in enumerate(_JOE_KUO, start=1):
        row = [m[b] << (31 - b) for b in range(s)]
        for b in range(s, 32):
            x = row[b - s] ^ (row[b - s] >> s)
            for k in range(1, s):
                if (a >> (s - 1 - k)) & 1:
                    x ^= row[b - k]
            row.append(x)
        v[d] = row
    return v


DIRECTIONS = _directions()


def sobol32(j, d, directions):
    """Unscrambled 32-bit coordinate d of Sobol point j (Gray-code order); j a uint64 scalar or array."""
    g = j ^ (j >> _ONE)
    x = g & np.uint64(0)
    for b in range(32):
        x = x ^ (directions[d, b] * ((g >> np.uint64(b)) & _ONE))
    return x


def reverse32(x):
    """The 32 low bits of x in reverse order."""
    x = ((x >> np.uint64(1)) & np.uint64(0x55555555)) | ((x & np.uint64(0x55555555)) << np.uint64(1))
    x = ((x >> np.uint64(2)) & np.uint64(0x33333333)) | ((x & np.uint64(0x33333333)) << np.uint64(2))
    x = ((x >> np.uint64(4)) & np.uint64(0x0F0F0F0F)) | ((x & np.uint64(0x0F0F0F0F)) << np.uint64(4))
    x = ((x >> np.uint64(8)) & np.uint64(0x00FF00FF)) | ((x & np.uint64(0x00FF00FF)) << np.uint64(8))
    return ((x >> np.uint64(16)) | (x << np.uint64(16))) & MASK32


def lk_hash(x, seed):
    """Laine-Karras style hash of 32-bit x: each output bit depends only on the input bits below it."""
    x = x ^ ((x * _K1) & MASK32)
    x = (x + seed) & MASK32
    x = (x * ((seed >> np.uint64(16)) | _ONE)) & MASK32
    x = x ^ ((x * _K2) & MASK32)
    return x ^ ((x * _K3) & MASK32)


def owen32(x, seed):
    """Nested uniform scramble of 32-bit x: the hash applied to the bit-reversed value, so each digit
    depends only on the digits before it. (The compiled twin composes the same three steps.)"""
    return reverse32(lk_hash(reverse32(x), seed))


def hash32(key, a, d):
    """32 random bits for (key, a, d): SplitMix64 as in counter_uniforms, top half."""
    z = key + (np.uint64(4) * a + np.uint64(d + 1)) * GAMMA
    z = (z ^ (z >> np.uint64(30))) * MIX1
    z = (z ^ (z >> np.uint64(27))) * MIX2
    return (z ^ (z >> np.uint64(31))) >> np.uint64(32)


def to_unit(x):
    """A 32-bit digit string as a float in (0, 1): the centre of its interval (never 0 or 1)."""
    return (x + 0.5) * TO_UNIT32


def owen_seeds(key: int) -> np.ndarray:
    """The DIMS scramble seeds of a render (or batch) key."""
    k = np.uint64(key) ^ OWEN_SALT
    with np.errstate(over="ignore"):
        return np.array([hash32(k, np.uint64(0), d) for d in range(DIMS)], dtype=np.uint64)


def cell_uniforms(key: int, j: np.ndarray, cell_id: np.ndarray) -> np.ndarray:
    """(DIMS, n) draws of points j in cells cell_id: scrambled per render, shifted per cell."""
    seeds = owen_seeds(key)
    j = np.asarray(j, dtype=np.uint64)
    cell_id = np.asarray(cell_id, dtype=np.uint64)
    out = np.empty((DIMS, len(j)))
    with np.errstate(over="ignore"):
        for d in range(DIMS):
            x = owen32(sobol32(j, d, DIRECTIONS), seeds[d]) ^ hash32(np.uint64(key), cell_id, d)
            out[d] = to_unit(x.astype(np.float64))
    return out


def batch_uniforms(key: int, n: int, dims: int, first: int = 0) -> np.ndarray:
    """(dims, n) draws for points first..first+n-1 of one batch (point and object-side scenes)."""
    return cell_uniforms(key, np.arange(first, first + n), np.zeros(n))[:dims]
