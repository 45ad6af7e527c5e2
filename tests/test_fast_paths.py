"""The faster formulations of issue #11 give exactly what the plain ones gave: lazy reference images, the
grid's JSON (rounding, reading), report.json's encoding, lenses.csv without the csv module, the tone map,
and the command line importing only the named command's module."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import pickle

import numpy as np
import pytest

from mlaqc.cli import _parser_for
from mlaqc.errors import InputError
from mlaqc.inspection.grid import FORMAT, VERSION, Grid, _rounded_column
from mlaqc.inspection.metrics import reference_images
from mlaqc.inspection.results import LazyReferences
from mlaqc.models.reference import reference_model
from mlaqc.optics.config import default_config
from mlaqc.report.document import _ENCODER, _dumps, _jsonable, dumps_utf8, lenses_csv
from mlaqc.report.view import View
from test_report import make_result


def test_lazy_references_are_the_eager_ones_lens_by_lens_and_whole():
    model = reference_model(default_config())
    rng = np.random.default_rng(5)
    cx, cy = rng.uniform(9.6, 10.4, (4, 5)), rng.uniform(9.6, 10.4, (4, 5))
    eager = reference_images(model, cx, cy, 21, 21)
    lazy = LazyReferences(lambda x, y: reference_images(model, x, y, 21, 21), cx, cy, (21, 21))
    assert lazy.shape == eager.shape and lazy.ndim == 4
    for m, n in ((0, 0), (2, 3), (-1, -1)):
        assert np.array_equal(lazy[m, n], eager[m, n])
    with pytest.raises(IndexError):
        lazy[4, 0]
    assert np.array_equal(np.asarray(lazy), eager) and np.array_equal(lazy[1], eager[1])
    again = pickle.loads(pickle.dumps(lazy))
    assert isinstance(again, np.ndarray) and np.array_equal(again, eager)


def test_rounding_to_six_decimals_is_pythons_round():
    rng = np.random.default_rng(0)
    values = [rng.normal(0, s, 20000) for s in (1e-7, 1e-3, 1.0, 1e3, 1e6, 1e12, 1e300)]
    k = rng.integers(-10**9, 10**9, 5000)
    ties = (k + 0.5) / 1e6
    values += [ties + d * np.spacing(ties) for d in range(-4, 5)]
    values += [np.arange(-4096, 4096) / 8192.0, np.float32(rng.normal(0, 50, 5000)),
               np.array([0.0, -0.0, np.nan, np.inf, -np.inf, 5e-7, -5e-7, 2.5e-6, 2.0**52, 1e308, 5e-324])]
    for a in values:
        want = [round(v, 6) if math.isfinite(v) else None for v in np.asarray(a, float).tolist()]
        got = _rounded_column(a)
        assert [repr(v) for v in got] == [repr(v) for v in want]


def _grid_dict(rows=7, cols=9, seed=1) -> dict:
    rng = np.random.default_rng(seed)
    lenses = []
    for m in range(1, rows + 1):
        for n in range(1, cols + 1):
            missing = (m * n) % 11 == 0
            lenses.append({"m": m, "n": n, "measured_x_px": None if missing else float(rng.normal(100, 50)),
                           "measured_y_px": None if missing else float(rng.normal(100, 50)),
                           "grid_x_px": float(rng.normal(100, 50)), "grid_y_px": float(rng.normal(100, 50)),
                           "residual_px": None if missing else float(rng.uniform(0, 1)), "flux": float(rng.uniform(1, 9)),
                           "radius_px": 8 if n == 2 else float(rng.uniform(8, 9)), "missing": missing, "clipped": n == cols})
    return {"format": FORMAT, "version": VERSION, "image": {"height_px": 200, "width_px": 220},
            "shape": {"rows": rows, "cols": cols}, "pitch_px": {"x": 20.0, "y": 20.0}, "rotation_deg": 0.1,
            "shear_deg": 0.0, "origin_px": {"x": 10.0, "y": 10.0},
            "model": {"homography": [[20.0, 0, 10], [0, 20.0, 10], [0, 0, 1]], "radial_k": 0.0,
                      "radial_centre_px": {"x": 100.0, "y": 100.0}, "radial_scale_px": 100.0, "edge_width_px": 0.8},
            "summary": {"rms_residual_px": 0.02}, "lenses": lenses}


def test_grid_json_reads_every_lens_and_writes_it_back_as_before():
    data = _grid_dict()
    data["lenses"].reverse()  # any order
    grid = Grid.from_json_dict(data)
    for e in data["lenses"]:
        m, n = e["m"] - 1, e["n"] - 1
        for key in ("measured_x_px", "grid_x_px", "residual_px", "flux", "radius_px"):
            assert repr(float(getattr(grid, key)[m, n])) == repr(float("nan") if e[key] is None else float(e[key]))
        assert grid.missing[m, n] == e["missing"] and grid.clipped[m, n] == e["clipped"]
    fx = lambda v: None if not np.isfinite(v) else round(float(v), 6)  # noqa: E731 - the per-lens original
    want = [{"m": m + 1, "n": n + 1, **{k: fx(getattr(grid, k)[m, n]) for k in
                                         ("measured_x_px", "measured_y_px", "grid_x_px", "grid_y_px", "residual_px",
                                          "flux", "radius_px")},
             "missing": bool(grid.missing[m, n]), "clipped": bool(grid.clipped[m, n])}
            for m in range(grid.rows) for n in range(grid.cols)]
    assert json.dumps(grid.to_json_dict()["lenses"]) == json.dumps(want)


@pytest.mark.parametrize("change, message", [
    (lambda L: L[3].__setitem__("m", 0), "lenses[3] needs integer m"),
    (lambda L: L[3].__setitem__("n", 2.0), "lenses[3] needs integer m"),
    (lambda L: L[4].update(m=L[5]["m"], n=L[5]["n"]), "is listed twice"),
    (lambda L: L[4].__setitem__("flux", "bright"), "field 'flux' must be a number or null"),
    (lambda L: L[4].__setitem__("flux", math.inf), "field 'flux' must be a number or null"),
    (lambda L: L[4].__setitem__("flux", True), "field 'flux' must be a number or null"),
    (lambda L: L[4].__setitem__("clipped", 0), "field 'clipped' must be true or false"),
    (lambda L: L.__setitem__(2, [1, 2]), "lenses[2] must be an object"),
    (lambda L: L[4].__setitem__("grid_x_px", None), "has no grid (predicted) centre"),
    (lambda L: L[4].update(measured_x_px=None, missing=False), "is not marked missing but has no measured centre"),
])
def test_a_bad_lens_entry_is_named_as_before(change, message):
    data = _grid_dict()
    change(data["lenses"])
    with pytest.raises(InputError) as err:
        Grid.from_json_dict(data, source="g")
    assert message in str(err.value)


def test_grid_entries_the_lens_by_lens_reading_accepts_are_still_read():
    data = _grid_dict()
    data["lenses"][0]["m"] = True  # a bool is an int to isinstance: U(1, 1) as before
    data["lenses"][1]["flux"] = 7  # an integer number
    del data["lenses"][2]["clipped"]  # missing flags default to false
    grid = Grid.from_json_dict(data)
    assert grid.flux[0, 1] == 7.0 and not grid.clipped[0, 2]


def _dumps_oracle(obj, level=0) -> str:
    """report.json's layout as the record-at-a-time encoder wrote it."""
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        pad = "  " * (level + 1)
        items = ",\n".join(f"{pad}{json.dumps(k, ensure_ascii=False)}: {_dumps_oracle(v, level + 1)}"
                           for k, v in obj.items())
        return "{\n" + items + "\n" + "  " * level + "}" + ("\n" if level == 0 else "")
    if isinstance(obj, list):
        if all(not isinstance(x, (dict, list)) for x in obj):
            return _ENCODER.encode(obj)
        if all(isinstance(x, dict) and all(not isinstance(y, (dict, list)) for y in x.values()) for x in obj):
            one_line = [_ENCODER.encode(x) for x in obj]
            if max(map(len, one_line)) <= 400:
                pad = "  " * (level + 1)
                return "[\n" + ",\n".join(pad + x for x in one_line) + "\n" + "  " * level + "]"
        pad = "  " * (level + 1)
        return "[\n" + ",\n".join(pad + _dumps_oracle(x, level + 1) for x in obj) + "\n" + "  " * level + "]"
    return _ENCODER.encode(obj)


def test_report_json_encoding_is_the_record_at_a_time_one():
    rng = np.random.default_rng(2)
    records = [{"m": i, "x%": float(v), "ok": bool(v > 0), "none": None, "n\u00e9": -0.0 if i == 3 else i * 0.5}
               for i, v in enumerate(rng.normal(0, 1e3, 50))]
    doc = {
        "records": records,
        "ragged": [{"a": 1}, {"b": 2.5, "a": 3}],
        "with text": [{"t": "a, b", "v": 1.0}, {"t": "], [", "v": 2.0}],
        "rows": [[float(v) for v in rng.normal(0, 1, 7)] for _ in range(5)] + [[], [None, True, 3]],
        "one row": [[1.5, 2.5]], "empty rows": [[]], "empty": [], "nested": [[[1]], [2]],
        "long": [{"k": "x" * 500}], "scalars": [1, 2.5, None, "s"],
    }
    plain = _jsonable(doc)
    assert _jsonable(json.loads(json.dumps(doc))) == plain
    assert _dumps(plain) == _dumps_oracle(plain)
    assert dumps_utf8(plain) == _dumps_oracle(plain).encode("utf-8")  # (the report's bytes, piece by piece)
    nan_rows = {"rows": [[1.0, math.nan]]}
    with pytest.raises(ValueError):
        _dumps(nan_rows)
    assert _jsonable({"r": [{"a": math.nan, "b": 1.0}]}) == {"r": [{"a": None, "b": 1.0}]}


def _csv_module(text: str) -> str:
    """`text` read and written again by the csv module (its quoting, its line ends)."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(csv.reader(io.StringIO(text)))
    return buf.getvalue()


@pytest.mark.parametrize("error_type", ["radius", "odd, \"quoted\" type"])
def test_lenses_csv_is_what_the_csv_module_writes(error_type):
    base = make_result()
    result = dataclasses.replace(base, error_type=np.where(base.flagged, error_type, "").astype(object))
    text = lenses_csv(result)
    assert text == _csv_module(text)
    assert sum(1 for row in csv.reader(io.StringIO(text)) if error_type in row) == int(result.flagged.sum())


def test_tone_map_clips_and_blacks_out_as_before():
    result = make_result()
    img = result.image
    img[0, :5] = [np.nan, np.inf, -np.inf, 1e30, -1e30]
    v = View(result)
    sample = img[np.isfinite(img)]
    lo, hi = np.percentile(sample, [0.5, 99.5])
    want = np.nan_to_num((img - np.float32(lo)) * np.float32(255.0 / (hi - lo)), nan=0.0, posinf=255.0, neginf=0.0)
    want = np.clip(want + 0.5, 0, 255).astype(np.uint8)
    assert np.array_equal(v.tone_mapped(), want)


def test_command_line_imports_the_named_command_alone():
    parser = _parser_for(["inspect", "x.dng", "--out", "o"])
    choices = parser._subparsers._group_actions[0].choices
    assert list(choices) == ["inspect"]
    for argv in ([], ["--version"], ["no-such-command"]):
        full = _parser_for(argv)._subparsers._group_actions[0].choices
        assert {"simulate", "inspect", "calibrate", "errormap", "models", "demo"} <= set(full)


def test_focus_fit_split_over_lens_ranges_is_the_whole_array_call():
    """measure's compiled chi-square and scan run on lens ranges on the cores: each lens alone, so the
    split gives bit for bit what one call over all lenses gives."""
    from mlaqc.inspection import measure as ms

    rng = np.random.default_rng(4)
    n, gd, f = 5000, 8 * 20 + 1, 7
    dense_m = np.linspace(-0.1, 0.1, gd)
    ug = np.outer(dense_m, rng.normal(size=f)) + 0.3 * np.outer(dense_m ** 2, rng.normal(size=f))
    uv = ug[rng.integers(0, gd, n)] + rng.normal(scale=0.2, size=(n, f))
    chi2 = np.empty((n, (gd - 1) // ms.COARSE + 1))
    ms.coarse_chi2(uv, ug, ms.COARSE, chi2)
    whole = [np.empty(n), np.empty(n), np.empty(n), np.empty(n, np.bool_)]
    step = float(np.median(np.diff(dense_m[:: ms.COARSE])))
    ms.focal_scan(chi2, dense_m, ug, uv, ms.COARSE, 1.0 / 1.5 ** 2, ms.SIGN_RESOLVED_CHI2, 3.0 * step, *whole)
    split_chi2 = np.empty_like(chi2)
    ms._on_cores(lambda a, b: ms.coarse_chi2(uv[a:b], ug, ms.COARSE, split_chi2[a:b]), n)
    assert np.array_equal(split_chi2, chi2)
    for got, want in zip(ms._focal((dense_m, ug, uv, chi2), 1.5), whole):
        assert np.array_equal(got, want, equal_nan=True)


@pytest.mark.parametrize("side", [1000, 2048])
def test_hot_pixel_plane_noise_reads_a_known_noise_on_either_sample(side):
    """The plane noise comes from a 1-in-9 sample, 1-in-16 from 4 Mpx on: both read a Gaussian noise of
    known sigma on a smooth scene (the ring mean of a plane cancels it) within 2 %."""
    from mlaqc.inspection.raw_levels import _plane_noise

    rng = np.random.default_rng(side)
    yy, xx = np.mgrid[:side, :side]
    x = (0.5 + 0.2 * np.sin(xx / 300.0) * np.cos(yy / 250.0) + rng.normal(scale=0.01, size=(side, side)))
    assert _plane_noise(x.astype(np.float32), 0, 0, 1, side, side, False) == pytest.approx(0.01, rel=0.02)
