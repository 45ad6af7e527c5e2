"""Compiled table formatting (mlaqc.report.numtext): Python's %-formatting to the byte, ties and all."""

import json

import numpy as np
import pytest

from mlaqc.report.numtext import _python_cell, _python_rows, format_column, format_rows


def _values(seed: int = 0, n: int = 20_000) -> np.ndarray:
    """Values a report meets and the hard ones: every magnitude, both signs, exact binary ties at every
    precision, rounding carries (9.9999995), powers of ten, zeros, non-finite and huge values."""
    rng = np.random.default_rng(seed)
    special = np.array([0.0, -0.0, 0.5, 1.5, 2.5, -2.5, 0.0625, 0.03125, 9.9999995, 99999.5, 999999.5, 123456.5,
                        1e-5, 1e-4, 9.99995e-5, 1e5, 1e6, 1e15, 1e16, 1e22, 1e300, 5e-324, 1.2345e-5, 12345678.9,
                        np.nan, np.inf, -np.inf, 0.1, 0.2, 0.3, 1 / 3, 2 / 3, -1e-7, 4.35, 2.675, 1.005])
    return np.concatenate([
        special, rng.normal(0, 1, n), rng.normal(0, 1e4, n), 10 ** rng.uniform(-12, 12, n) * rng.choice([-1, 1], n),
        np.round(rng.normal(0, 100, n), 3), rng.integers(-10 ** 6, 10 ** 6, n) / 8.0,  # exact ties
        rng.integers(-10 ** 6, 10 ** 6, n) / 1024.0])


@pytest.mark.parametrize("fmt", ["%.6g", "%.5g", "%.3g", "%.1g", "%.15g", "%.3f", "%.0f", "%.6f", "%.5j", "%.6j",
                                 "%.6r", "%.4r", "%.0r"])
def test_every_value_is_written_as_python_writes_it(fmt):
    values = _values()
    want = [_python_cell(x, fmt, ()) for x in values]
    if fmt.endswith("r"):  # the reference itself: what JSON writes for round(x, N)
        assert want == [json.dumps(round(float(x), int(fmt[2:-1]))) if np.isfinite(x) else "null" for x in values]
    if fmt.startswith("%.5"):  # the reference itself, against the formatting it stands for
        want_direct = [(fmt.replace("j", "g") % x if np.isfinite(x) else "") if fmt.endswith("g") else
                       (json.dumps(float(f"{x:.5g}")) if np.isfinite(x) else "null") for x in values]
        assert want == want_direct
    assert format_column(values, fmt) == want


def test_a_table_with_text_ints_and_ties_is_the_python_table():
    rng = np.random.default_rng(4)
    n = 3000
    values = np.column_stack([np.arange(1, n + 1), rng.normal(0, 10, n), np.where(rng.random(n) < 0.3, rng.integers(0, 3, n), -1),
                              rng.integers(-4000, 4000, n) / 8.0, rng.normal(0, 1, n)])
    formats, texts = ["%d", "%.3f", "%s", "%.6g", "%.5j"], ["position", "radius", "unknown"]
    for parallel in (True, False):
        assert format_rows(values, formats, texts, parallel=parallel) == _python_rows(values, formats, texts, ",", "\n")
    assert format_rows(values[:0], formats, texts) == ""


def test_tie_laden_data_still_comes_out_right():
    """Every value an exact tie at "%.3f" (more than the kernel hands back): Python formats the table."""
    values = (np.arange(10_000) + 0.5)[:, None] / 1000.0  # x.xxx5: ties in binary only where exact
    assert format_rows(values, ["%.3f"]) == "".join("%.3f\n" % x for x in values[:, 0])


def test_edge_tables():
    """No columns (only row ends), ints past int64 (Python's digits), a NaN for %d (Python's error)."""
    assert format_rows(np.zeros((5, 0)), []) == "\n" * 5
    assert format_rows(np.zeros((300_000, 0)), []) == "\n" * 300_000  # (the buffer once held no row ends)
    big = np.array([[1e20], [-2.0 ** 63], [2.0 ** 62]])
    assert format_rows(big, ["%d"]) == "".join("%d\n" % int(x) for x in big[:, 0])
    with pytest.raises(ValueError):
        format_rows(np.array([[np.nan]]), ["%d"])
    for seps in ({"col_sep": ", "}, {"row_sep": ""}, {"col_sep": "\u00e9"}):
        with pytest.raises(ValueError):
            format_rows(np.zeros((1, 2)), ["%d", "%d"], **seps)


def test_bad_formats_are_refused():
    for fmt in ("%e", "%.16g", "%f5", "%.3s"):
        with pytest.raises(ValueError):
            format_rows(np.zeros((2, 1)), [fmt])
    with pytest.raises(ValueError):
        format_rows(np.zeros((2, 2)), ["%d"])
    with pytest.raises(ValueError):  # a text index past the table (the kernel would read past it)
        format_rows(np.array([[0.0], [2.0]]), ["%s"], ["a", "b"])
    with pytest.raises(ValueError):
        format_rows(np.array([[0.5]]), ["%s"], ["a"])


def test_a_grids_records_are_the_json_encoders_lines():
    """A grid's lens records (floats rounded to 6 decimals, ints, booleans, nulls) through the compiled
    formatter: the lines the JSON encoder writes record by record."""
    from calib_images import synthetic_white
    from mlaqc.inspection.calibrate import calibrate
    from mlaqc.report.document import _flat_records, _jsonable

    img, _, _ = synthetic_white(noise=0.01, seed=3)
    grid = calibrate(img, expected_pitch_px=20.05, expected_shape=(18, 19))
    grid.measured_x_px[0, 3], grid.missing[0, 3] = np.nan, True  # as a lens not found
    lenses = grid.to_json_dict()["lenses"]
    assert lenses[3]["measured_x_px"] is None and lenses[3]["missing"] is True
    fast = _jsonable(lenses)
    assert fast.record_decimals == 6
    assert _flat_records(fast) == [json.dumps(x, ensure_ascii=False) for x in lenses]


def test_lenses_csv_is_the_csv_module_s_text():
    """lenses.csv through the compiled path and through the csv module (the quoting path): the same text."""
    from mlaqc.report.document import _quoted_csv, lenses_csv
    from mlaqc.report.view import View
    from test_report import make_result

    view = View(make_result())
    assert lenses_csv(view) == _quoted_csv(view)
