"""Tables of numbers as text, exactly as Python's %-formatting writes them, at compiled speed.

`format_rows` writes a (rows, columns) array with a printf format per column through one compiled pass
(mlaqc.report.format_kernels); the few values the kernel leaves undecided (within a hair of a rounding tie)
are formatted by Python and handed back to it, so the text is Python's to the byte.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from mlaqc.parallel import cores, thread_map
from mlaqc.report.format_kernels import CELL_MAX, FIXED, GENERAL, INT, JSON_GENERAL, JSON_ROUND, TEXT, format_table

_FORMAT = re.compile(r"^%(?:\.(\d+))?([dfgsjr])$")  # %.Nj: repr(float("%.Ng" % x)); %.Nr: repr(round(x, N))
BLOCK_CELLS = 100_000  # cells per pool task at least
_MAX_UNDECIDED = 4096  # beyond this many near-ties (data made of exact binary ties) Python formats all
_EMPTY_U8, _EMPTY_I8 = np.zeros(0, np.uint8), np.zeros(0, np.int64)


def format_rows(values: np.ndarray, formats: Sequence[str], texts: Sequence[str] = (), *, col_sep: str = ",",
                row_sep: str = "\n", parallel: bool = True) -> str:
    """`format_rows_utf8`'s text as a string."""
    return format_rows_utf8(values, formats, texts, col_sep=col_sep, row_sep=row_sep, parallel=parallel).decode("utf-8")


def format_rows_utf8(values: np.ndarray, formats: Sequence[str], texts: Sequence[str] = (), *, col_sep: str = ",",
                     row_sep: str = "\n", parallel: bool = True) -> bytes:
    """`values` (rows, columns) as UTF-8 text: column k in printf format formats[k] ("%d", "%.3f", "%.6g"; NaN and
    infinities empty) or "%s" (the value indexes `texts`; negative: empty); cells joined by col_sep, every
    row ended by row_sep (one ASCII character each). With `parallel`, large tables are cut into row blocks
    written on the process' pool at once (the kernel releases the GIL); without, here (when the pool is
    busy with other work, as the report's PNGs)."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise ValueError(f"format_rows takes a (rows, columns) array, not shape {values.shape}")
    if len(col_sep) > 1 or len(row_sep) != 1 or not (col_sep + row_sep).isascii():
        raise ValueError("format_rows separates cells by at most one and rows by one ASCII character")
    codes, _ = _parse(formats, values.shape[1])
    index = values[:, codes == TEXT]
    if index.size and not (np.all(index == np.floor(index)) and index.max() < len(texts)):
        raise ValueError(f"a %s column holds values that are not indexes of the {len(texts)} texts")
    blocks = max(1, min(cores(), values.size // BLOCK_CELLS)) if parallel else 1
    edges = np.linspace(0, values.shape[0], blocks + 1).astype(int)
    parts = [values[a:b] for a, b in zip(edges[:-1], edges[1:])]
    return b"".join(thread_map(lambda part: _format_block(part, formats, texts, col_sep, row_sep), parts))


def _format_block(values: np.ndarray, formats: Sequence[str], texts: Sequence[str], col_sep: str,
                  row_sep: str) -> bytes:
    """format_rows_utf8 of one block of rows, in this thread."""
    values = np.ascontiguousarray(values)
    rows, cols = values.shape
    codes, precs = _parse(formats, cols)
    table = [t.encode("utf-8") for t in texts]
    table_bytes = np.frombuffer(b"".join(table), np.uint8) if table else _EMPTY_U8
    table_ends = np.cumsum([len(t) for t in table], dtype=np.int64) if table else _EMPTY_I8
    widths = np.where(codes == TEXT, max((len(t) for t in table), default=0), CELL_MAX)
    given, given_text = _EMPTY_I8, []
    while True:
        extra = sum(len(t) for t in given_text)
        out = np.empty(rows * int(widths.sum() + cols + 1) + extra, np.uint8)  # cells, separators, row ends
        undecided = np.empty(_MAX_UNDECIDED, np.int64)
        given_bytes = np.frombuffer(b"".join(given_text), np.uint8) if given_text else _EMPTY_U8
        given_ends = np.cumsum([len(t) for t in given_text], dtype=np.int64) if given_text else _EMPTY_I8
        n = format_table(values, codes, precs, table_bytes, table_ends, given, given_bytes, given_ends,
                         ord(col_sep) if col_sep else -1, ord(row_sep), out, undecided)
        if n >= 0:
            return out[:n].tobytes()
        if -1 - n > _MAX_UNDECIDED or given.size:
            return _python_rows(values, formats, texts, col_sep, row_sep).encode("utf-8")
        given = np.sort(undecided[: -1 - n])
        given_text = [_python_cell(values.flat[c], formats[c % cols], texts).encode("ascii") for c in given.tolist()]


def format_column(values: np.ndarray, fmt: str, *, parallel: bool = True) -> list[str]:
    """Each value of `values` (any shape, flattened) in printf format `fmt`, non-finite ones empty."""
    a = np.asarray(values, dtype=np.float64).reshape(-1, 1)
    return format_rows(a, [fmt], row_sep="\0", parallel=parallel).split("\0")[:-1]


def _parse(formats: Sequence[str], cols: int) -> tuple[np.ndarray, np.ndarray]:
    if len(formats) != cols:
        raise ValueError(f"{len(formats)} formats for {cols} columns")
    codes, precs = [], []
    for fmt in formats:
        m = _FORMAT.match(fmt)
        if (m is None or (m.group(2) in "fgjr") != (m.group(1) is not None) or (m.group(1) and int(m.group(1)) > 15)
                or (m.group(2) == "r" and int(m.group(1)) > 6)):
            raise ValueError(f"unsupported column format {fmt!r} (%d, %.Nf, %.Ng or %.Nj with N <= 15, %.Nr with "
                             "N <= 6, or %s)")
        codes.append({"d": INT, "f": FIXED, "g": GENERAL, "s": TEXT, "j": JSON_GENERAL, "r": JSON_ROUND}[m.group(2)])
        precs.append(max(int(m.group(1) or 0), 1) if m.group(2) in "gj" else int(m.group(1) or 0))
    return np.array(codes, np.int64), np.array(precs, np.int64)


def _python_rows(values: np.ndarray, formats: Sequence[str], texts: Sequence[str], col_sep: str,
                 row_sep: str) -> str:
    """The same text by Python's own formatting (the reference, and the path for tie-laden data)."""
    return "".join(col_sep.join(_python_cell(x, f, texts) for x, f in zip(row, formats)) + row_sep
                   for row in values.tolist())


def _python_cell(x: float, fmt: str, texts: Sequence[str]) -> str:
    """One cell as Python writes it."""
    if fmt.endswith("j"):
        return repr(float((fmt[:-1] + "g") % x)) if np.isfinite(x) else "null"
    if fmt.endswith("r"):
        return repr(round(float(x), int(fmt[2:-1]))) if np.isfinite(x) else "null"
    if fmt == "%s":
        return texts[int(x)] if x >= 0 else ""
    if fmt == "%d":
        return "%d" % int(x)
    return fmt % x if np.isfinite(x) else ""
