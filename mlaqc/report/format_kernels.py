"""Compiled (Numba) printf-style formatting of whole tables: lenses.csv's 40 columns of 10,404 lenses.

Why: Python's %-operator spent about 100 ns a value (40 ms a report) and the row joins as much again. The
kernel writes every cell straight into one byte buffer, each value exactly as Python's "%.{p}f", "%.{p}g"
and "%d" write it: digits correctly rounded from the binary value. A value whose scaled digits lie within
4e-9 of a rounding tie (an exact tie such as 0.0625 at "%.3f", or one the float product cannot decide) is
left to Python: the kernel lists those cells, the caller formats them and gives them back. Checked against
Python's own formatting on millions of values (tests/test_format_kernels.py).
"""

from __future__ import annotations

import math

import numpy as np

from mlaqc.compiled import kernel

_jit = kernel(cache=True, nogil=True, error_model="numpy")

INT, FIXED, GENERAL, TEXT, JSON_GENERAL, JSON_ROUND = 0, 1, 2, 3, 4, 5  # column codes (JSON_GENERAL: repr(float(
# "%.Ng" % x)); JSON_ROUND: repr(round(x, N)), N <= 6; both null for NaN and infinities)
CELL_MAX = 32  # bytes a number cell can take ("-1.23456789012345e-300" and the like)
_TIE = 4e-9  # closer than this to a rounding tie (in units of the last digit kept): left to Python
_P10 = np.array([10.0 ** k for k in range(23)])  # exact powers of ten


@_jit
def _scaled(ax, k):
    """ax * 10**k within a few ulps (exact powers up to 1e22, at most two roundings beyond)."""
    if k >= 0:
        if k <= 22:
            return ax * _P10[k]
        return (ax * _P10[22]) * 10.0 ** (k - 22)
    if k >= -22:
        return ax / _P10[-k]
    return (ax / _P10[22]) / 10.0 ** (-k - 22)


@_jit
def _put_uint(out, pos, v):
    """The decimal digits of v >= 0 at out[pos:]; the new position."""
    if v == 0:
        out[pos] = 48
        return pos + 1
    n = 0
    t = v
    while t > 0:
        n += 1
        t //= 10
    for i in range(n - 1, -1, -1):
        out[pos + i] = 48 + v % 10
        v //= 10
    return pos + n


@_jit
def _round_scaled(s):
    """(s rounded to an integer, ok): not ok when s is within _TIE of a tie."""
    fl = math.floor(s)
    frac = s - fl
    tol = max(_TIE, s * 4e-16)
    if abs(frac - 0.5) <= tol:
        return np.int64(0), False
    return np.int64(fl) + (1 if frac > 0.5 else 0), True


@_jit
def _signed_decimals(out, pos, x, decimals, limit):
    """|x| * 10**decimals rounded to an integer m, and x's sign written at out[pos:] (a minus on negative
    zero too, as Python writes it); (m, new position, ok): not ok for |x| >= limit or a near-tie."""
    ax = abs(x)
    if ax >= limit:
        return np.int64(0), pos, False
    m, ok = _round_scaled(_scaled(ax, decimals))
    if not ok:
        return m, pos, False
    if math.copysign(1.0, x) < 0:
        out[pos] = 45
        pos += 1
    return m, pos, True


@_jit
def _put_exponent(out, pos, e):
    """"e+XX" / "e-XX" (at least two digits) at out[pos:]; the new position."""
    out[pos] = 101
    out[pos + 1] = 45 if e < 0 else 43
    pos += 2
    ae = -e if e < 0 else e
    if ae < 10:
        out[pos] = 48
        pos += 1
    return _put_uint(out, pos, ae)


@_jit
def _put_fixed(out, pos, x, prec):
    """"%.{prec}f" % x at out[pos:]; (new position, ok)."""
    m, pos, ok = _signed_decimals(out, pos, x, prec, 1e15 / _P10[prec])
    if not ok:
        return pos, False
    p10 = np.int64(_P10[prec])
    pos = _put_uint(out, pos, m // p10)
    if prec > 0:
        out[pos] = 46
        pos += 1
        frac = m % p10
        for i in range(prec - 1, -1, -1):
            out[pos + i] = 48 + frac % 10
            frac //= 10
        pos += prec
    return pos, True


@_jit
def _put_general(out, pos, x, prec, digits, as_json):
    """"%.{prec}g" % x at out[pos:] (1 <= prec <= 15), or with `as_json` repr(float("%.{prec}g" % x)) (what
    JSON writes for that rounded value: positional up to 1e16, a ".0" on whole numbers); (new position, ok).
    `digits`: scratch of prec."""
    neg = math.copysign(1.0, x) < 0
    ax = abs(x)
    if neg:
        out[pos] = 45
        pos += 1
    if ax == 0.0:
        out[pos] = 48
        if as_json:
            out[pos + 1] = 46
            out[pos + 2] = 48
            return pos + 3, True
        return pos + 1, True
    e = np.int64(math.floor(math.log10(ax)))
    if e > 300 or e < -300:
        return pos, False
    s = _scaled(ax, prec - 1 - e)
    lo = _P10[prec - 1]
    if s < lo:  # log10 rounded up at a power of ten
        e -= 1
        s = _scaled(ax, prec - 1 - e)
    elif s >= lo * 10.0:
        e += 1
        s = _scaled(ax, prec - 1 - e)
    m, ok = _round_scaled(s)
    if not ok:
        return pos, False
    if m >= np.int64(lo * 10.0):  # 9.9999995 -> 10.000000
        m //= 10
        e += 1
    for i in range(prec - 1, -1, -1):
        digits[i] = m % 10
        m //= 10
    nd = prec
    while nd > 1 and digits[nd - 1] == 0:
        nd -= 1
    if e < -4 or e >= (16 if as_json else prec):  # d.ddde+XX
        out[pos] = 48 + digits[0]
        pos += 1
        if nd > 1:
            out[pos] = 46
            pos += 1
            for i in range(1, nd):
                out[pos] = 48 + digits[i]
                pos += 1
        return _put_exponent(out, pos, e), True
    if e >= 0:
        for i in range(e + 1):
            out[pos] = 48 + (digits[i] if i < nd and i < prec else 0)
            pos += 1
        if nd > e + 1:
            out[pos] = 46
            pos += 1
            for i in range(e + 1, nd):
                out[pos] = 48 + digits[i]
                pos += 1
        elif as_json:
            out[pos] = 46
            out[pos + 1] = 48
            pos += 2
        return pos, True
    out[pos] = 48
    out[pos + 1] = 46
    pos += 2
    for i in range(-e - 1):
        out[pos] = 48
        pos += 1
    for i in range(nd):
        out[pos] = 48 + digits[i]
        pos += 1
    return pos, True


@_jit
def _put_round(out, pos, x, n_dec):
    """repr(round(x, n_dec)) at out[pos:] (n_dec <= 6, |x| < 1e9: the shortest repr of that double is the
    decimal itself, trailing zeros dropped, ".0" on whole numbers, d.de-XX below 1e-4); (position, ok)."""
    m, pos, ok = _signed_decimals(out, pos, x, n_dec, 1e9)
    if not ok:
        return pos, False
    p10 = np.int64(_P10[n_dec])
    if n_dec >= 4 and 0 < m < np.int64(_P10[n_dec - 4]):  # below 1e-4: d.ddde-XX
        nd = 0
        t = m
        while t > 0:
            nd += 1
            t //= 10
        e = nd - 1 - n_dec  # the value is m / 10**n_dec = d.ddd x 10**e
        while m % 10 == 0:
            m //= 10
        start = pos
        pos = _put_uint(out, pos, m)
        if pos - start > 1:  # the point after the first digit
            for q in range(pos, start + 1, -1):
                out[q] = out[q - 1]
            out[start + 1] = 46
            pos += 1
        return _put_exponent(out, pos, e), True
    pos = _put_uint(out, pos, m // p10)
    out[pos] = 46
    pos += 1
    frac = m % p10
    if frac == 0:
        out[pos] = 48
        return pos + 1, True
    keep = n_dec
    while frac % 10 == 0:
        frac //= 10
        keep -= 1
    for i in range(keep - 1, -1, -1):
        out[pos + i] = 48 + frac % 10
        frac //= 10
    return pos + keep, True


@_jit
def _put_entry(out, pos, table, ends, j):
    """Entry j of a table of byte strings ending at `ends` at out[pos:]; the new position."""
    a = ends[j - 1] if j > 0 else 0
    for q in range(a, ends[j]):
        out[pos] = table[q]
        pos += 1
    return pos


@_jit.aot("f8[:, ::1], i8[::1], i8[::1], u1[::1], i8[::1], i8[::1], u1[::1], i8[::1], i8, i8, u1[::1], i8[::1]")
def format_table(values, codes, precs, table, table_ends, given, given_table, given_ends, col_sep, row_sep, out,
                 undecided):
    """Every cell of values (rows, columns), row by row, cells joined by col_sep, rows ended by row_sep
    (bytes; col_sep < 0: none), column k written as codes[k]: INT "%d", FIXED "%.{precs[k]}f", GENERAL
    "%.{precs[k]}g" (NaN and infinities empty), JSON_GENERAL that value as JSON writes it, JSON_ROUND
    round(value, precs[k]) as JSON writes it (both null for NaN and infinities), TEXT entry int(value) of
    `table` (its entries end at table_ends; < 0: empty).
    Cells whose flat index is in the sorted `given` are written as the matching entry of `given_table`.
    Returns the bytes written; or, when some values lie too close to a rounding tie to decide here,
    -1 - their count, their flat indices in `undecided` (as many as fit), and nothing usable in `out`.
    `out` needs rows * (sum of the cell widths + columns) bytes (CELL_MAX per number)."""
    rows, cols = values.shape
    digits = np.empty(16, np.int64)
    pos = 0
    n_undecided = 0
    g = 0
    for i in range(rows):
        for k in range(cols):
            if k and col_sep >= 0:
                out[pos] = col_sep
                pos += 1
            x = values[i, k]
            code = codes[k]
            flat = i * cols + k
            if g < given.size and given[g] == flat:
                pos = _put_entry(out, pos, given_table, given_ends, g)
                g += 1
            elif code == TEXT:
                j = np.int64(x)
                if j >= 0:
                    pos = _put_entry(out, pos, table, table_ends, j)
            elif code == INT:
                if not abs(x) < 9.2e18:  # past int64, or not a number: Python says what it is
                    if n_undecided < undecided.size:
                        undecided[n_undecided] = flat
                    n_undecided += 1
                    continue
                v = np.int64(x)
                if v < 0:
                    out[pos] = 45
                    pos += 1
                    v = -v
                pos = _put_uint(out, pos, v)
            elif not math.isfinite(x):
                if code == JSON_GENERAL or code == JSON_ROUND:  # null
                    out[pos], out[pos + 1], out[pos + 2], out[pos + 3] = 110, 117, 108, 108
                    pos += 4
            else:
                start = pos
                if code == FIXED:
                    pos, ok = _put_fixed(out, pos, x, precs[k])
                elif code == JSON_ROUND:
                    pos, ok = _put_round(out, pos, x, precs[k])
                else:
                    pos, ok = _put_general(out, pos, x, precs[k], digits, code == JSON_GENERAL)
                if not ok:
                    if n_undecided < undecided.size:
                        undecided[n_undecided] = flat
                    n_undecided += 1
                    pos = start
        out[pos] = row_sep
        pos += 1
    return pos if n_undecided == 0 else -1 - n_undecided
