"""Report set: report.json, lenses.csv, defect maps, self-contained sortable HTML; atomic writes; load_report."""

from __future__ import annotations

import base64
import csv
import json
import math
import re
import shutil
import subprocess
import types
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest

from mlaqc import __version__
from mlaqc.errors import InputError
from mlaqc.inspection.results import METRICS, Defect, InspectionResult, LensMetrics
from mlaqc.inspection.measure import MEASUREMENTS
from mlaqc.inspection.throughfocus_results import TF_MEASUREMENTS
from mlaqc.report import ERROR_COLOURS, REPORT_FILES
from mlaqc.report import html as report_html
from mlaqc.report import load_report
from mlaqc.report import maps as report_maps
from mlaqc.report import png as report_png
from mlaqc.report import write as report_write
from mlaqc.report import write_report

ROWS, COLS, PITCH = 12, 15, 20
HOSTILE = "/data/<script>x</script>.dng"


def _defects() -> list[Defect]:
    """One of each kind; none in the top-right quadrant, so the legend goes there."""
    return [
        Defect(3, 4, "pitch", 2.5, "µm", 30.0, 9.1, False, {"offset_um": 2.5, "offset_x_px": 0.43}),
        Defect(5, 6, "decenter", 0.8, "µm", 200.0, 4.2, True, {"skew_x": 0.3}),
        Defect(9, 3, "radius", -1.5, "%", None, 5.0, False, {"size_px": 4.9}),
        Defect(10, 12, "missing", math.nan, "", None, math.inf, False, {}),
        Defect(12, 15, "unknown", 0.1, "1", None, 3.3, True, {"ncc": 0.91}),
        Defect(11, 10, "tilt", 0.2, "deg", 90.0, 3.9, True, {"ellipticity": 0.12}),
        Defect(7, 2, "position", 1.1, "µm", 45.0, 6.5, True, {"offset_um": 1.1},
               alternatives=(("pitch", 1.1, "µm", 45.0), ("decenter", 2.9, "µm", 45.0))),
    ]


def make_result(rows: int = ROWS, cols: int = COLS, pitch: int = PITCH, *, defects: list[Defect] | None = None,
                source: str = "/data/frame_0001.dng", verdict: str | None = None, per_lens_reference: bool = False,
                pitch_px_only: bool = False, seed: int = 0) -> InspectionResult:
    """A synthetic inspection: bright discs on a square grid, the missing lens dark, random metrics."""
    rng = np.random.default_rng(seed)
    defects = _defects() if defects is None else defects
    shape = (rows, cols)
    # (0, 0) = centre of the top-left pixel: cell n spans x in [(n-1)p - 0.5, np - 0.5)
    gx = np.broadcast_to((np.arange(cols) + 0.5) * pitch - 0.5, shape).copy()
    gy = np.broadcast_to(((np.arange(rows) + 0.5) * pitch - 0.5)[:, None], shape).copy()
    missing = np.zeros(shape, bool)
    for d in defects:
        if d.error_type == "missing":
            missing[d.m - 1, d.n - 1] = True
    mx = gx + rng.uniform(-0.2, 0.2, shape)
    my = gy + rng.uniform(-0.2, 0.2, shape)
    mx[missing] = np.nan
    my[missing] = np.nan
    yy, xx = np.mgrid[0:rows * pitch, 0:cols * pitch].astype(np.float32)
    u = (xx + 0.5) % pitch - pitch / 2
    v = (yy + 0.5) % pitch - pitch / 2
    image = np.where(u * u + v * v < (0.4 * pitch) ** 2, 0.8, 0.05).astype(np.float32)
    image += rng.normal(0, 0.01, image.shape).astype(np.float32)
    for m, n in zip(*np.nonzero(missing)):
        image[m * pitch:(m + 1) * pitch, n * pitch:(n + 1) * pitch] = 0.02
    subimages = image.reshape(rows, pitch, cols, pitch).transpose(0, 2, 1, 3).copy()
    ref = np.where(u[:pitch, :pitch] ** 2 + v[:pitch, :pitch] ** 2 < (0.4 * pitch) ** 2, 0.8, 0.05)
    reference = ref.astype(np.float32)
    if per_lens_reference:
        reference = np.broadcast_to(reference, (rows, cols, pitch, pitch)).copy()
    values = {k: rng.normal(1.0, 0.05, shape) for k in METRICS}
    for arr in values.values():
        arr[missing] = np.nan
    values["ssim"][1, 1] = np.nan
    flagged = np.zeros(shape, bool)
    error_type = np.full(shape, "", dtype=object)
    for d in defects:
        flagged[d.m - 1, d.n - 1] = True
        error_type[d.m - 1, d.n - 1] = d.error_type
    residual = np.hypot(mx - gx, my - gy)
    grid = types.SimpleNamespace(
        rows=rows, cols=cols, rotation_deg=0.05,
        measured_x_px=mx, measured_y_px=my, grid_x_px=gx, grid_y_px=gy, residual_px=residual, missing=missing,
        to_json_dict=lambda: {"rows": rows, "cols": cols, "pitch_px": float(pitch), "rotation_deg": 0.05,
                              "measured_x_px": mx, "residual_px": residual, "missing": missing})
    if pitch_px_only:
        grid.pitch_px = float(pitch)
    else:
        grid.pitch_x_px = grid.pitch_y_px = float(pitch)
    if verdict is None:
        verdict = "FAIL" if any(not d.within_tolerance for d in defects) else "PASS"
    return InspectionResult(
        verdict=verdict, grid=grid, metrics=LensMetrics(values), defects=tuple(defects), flagged=flagged,
        error_type=error_type.astype(str), image=image, subimages=subimages, reference=reference, source=source,
        tolerances={"pitch_um": 1.0, "decenter_um": 1.0, "radius_rel": 0.01}, timings_s={"calibrate": 0.12},
        notes=("synthetic test frame",))


def _strict_json(path: Path) -> dict:
    def no_nan(const):
        raise AssertionError(f"{const} in JSON")
    return json.loads(path.read_text(encoding="utf-8"), parse_constant=no_nan)


def _read_png(path: Path) -> np.ndarray:
    bgr = cv2.imdecode(np.frombuffer(path.read_bytes(), np.uint8), cv2.IMREAD_COLOR)
    assert bgr is not None
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("rep") / "inspection"  # does not exist yet: write_report creates it
    result = make_result()
    paths = write_report(result, out, config_dict={"mla": {"pitch_um": 100.0}, "note": "<b>cfg</b>"})
    return result, out, paths


def test_every_file_is_written_and_nothing_else(written):
    _, out, paths = written
    assert set(paths) == set(REPORT_FILES)
    assert {p.name for p in paths.values()} == set(REPORT_FILES.values())
    assert all(p.parent == out and p.stat().st_size > 0 for p in paths.values())
    assert sorted(p.name for p in out.iterdir()) == sorted(REPORT_FILES.values())  # no temp files left


def test_report_json_lists_exactly_the_defects_in_u_m_n(written):
    result, out, paths = written
    data = _strict_json(paths["json"])
    assert data["format"] == "mlaqc-report" and data["format_version"] == 1
    assert data["mlaqc_version"] == __version__
    assert data["verdict"] == "FAIL" and data["source"] == result.source
    got = {(d["row"], d["col"], d["error_type"]) for d in data["defects"]}
    assert got == {(d.m, d.n, d.error_type) for d in result.defects}
    assert len(data["defects"]) == len(result.defects)
    pitch = next(d for d in data["defects"] if d["error_type"] == "pitch")
    expected = {"row": 3, "col": 4, "error_type": "pitch", "magnitude": 2.5, "unit": "µm",
                "direction_deg": 30.0, "score": 9.1, "within_tolerance": False,
                "indexes": {"offset_um": 2.5, "offset_x_px": 0.43}}
    assert {k: pitch[k] for k in expected} == expected
    assert data["defects"] == [d.to_json_dict() for d in result.defects]  # Defect.to_json_dict, NaN -> null
    miss = next(d for d in data["defects"] if d["error_type"] == "missing")
    assert (miss["row"], miss["col"], miss["magnitude"], miss["score"]) == (10, 12, None, None)
    s = data["summary"]
    assert (s["rows"], s["cols"], s["lens_count"], s["found"], s["missing"]) == (12, 15, 180, 179, 1)
    assert (s["flagged"], s["out_of_tolerance"]) == (7, 3)
    assert s["by_error_type"] == {"pitch": 1, "decenter": 1, "position": 1, "radius": 1, "tilt": 1, "missing": 1,
                                  "unknown": 1}
    g = data["grid_summary"]
    assert g["pitch_px"] == 20.0 and g["rotation_deg"] == 0.05
    assert (g["origin_x_px"], g["origin_y_px"]) == (9.5, 9.5)
    res = result.grid.residual_px[~result.grid.missing]
    assert g["rms_residual_px"] == pytest.approx(float(np.sqrt(np.mean(res ** 2))))
    assert data["grid"]["measured_x_px"][9][11] is None  # the missing lens' NaN became null
    assert data["grid"]["missing"][9][11] is True
    assert data["tolerances"]["pitch_um"] == 1.0 and data["timings_s"] == {"calibrate": 0.12}
    assert data["notes"] == ["synthetic test frame"] and data["config"]["mla"]["pitch_um"] == 100.0
    assert list(data["metrics"]) == list(METRICS)
    assert load_report(paths["json"]) == data
    assert load_report(out) == data  # the folder works too


def test_lenses_csv_rows_columns_and_u_m_n_indexing(written):
    result, _, paths = written
    with open(paths["csv"], newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    header, body = rows[0], rows[1:]
    assert header == ["row", "col", "x_px", "y_px", "grid_x_px", "grid_y_px", "flagged", "error_type",
                      *METRICS, *MEASUREMENTS, *TF_MEASUREMENTS]
    assert len(body) == ROWS * COLS
    assert all(r[-len(TF_MEASUREMENTS):] == [""] * len(TF_MEASUREMENTS) for r in body)  # no pinhole frames: empty
    assert [(int(r[0]), int(r[1])) for r in body[:3]] == [(1, 1), (1, 2), (1, 3)]  # m then n
    assert (int(body[-1][0]), int(body[-1][1])) == (ROWS, COLS)
    g = result.grid
    by_u = {(int(r[0]), int(r[1])): dict(zip(header, r)) for r in body}
    lens = by_u[(3, 4)]  # U(3,4) = array element [2, 3]
    assert float(lens["x_px"]) == pytest.approx(g.measured_x_px[2, 3], abs=1e-3)
    assert float(lens["y_px"]) == pytest.approx(g.measured_y_px[2, 3], abs=1e-3)
    assert float(lens["grid_x_px"]) == pytest.approx(69.5) and float(lens["grid_y_px"]) == pytest.approx(49.5)
    assert float(lens["x_px"]) == pytest.approx(69.5, abs=0.3)  # x is the column (n = 4), not swapped with y
    assert (lens["flagged"], lens["error_type"]) == ("1", "pitch")
    for k in METRICS:
        assert float(lens[k]) == pytest.approx(result.metrics[k][2, 3], rel=1e-5)
    other = by_u[(4, 3)]
    assert (other["flagged"], other["error_type"]) == ("0", "")
    assert float(other["flux"]) == pytest.approx(result.metrics["flux"][3, 2], rel=1e-5)
    gone = by_u[(10, 12)]
    assert gone["x_px"] == gone["y_px"] == "" and gone["error_type"] == "missing"
    assert all(gone[k] == "" for k in METRICS) and float(gone["grid_x_px"]) == pytest.approx(229.5)
    assert by_u[(2, 2)]["ssim"] == "" and by_u[(2, 2)]["flux"] != ""
    assert "nan" not in paths["csv"].read_text().lower()
    assert all(lens[k] == "" for k in MEASUREMENTS)  # a result without measurements: empty, never made up


def _ring(rgb: np.ndarray, cx: float, cy: float, r: float, width: float = 1.0) -> np.ndarray:
    """The pixels of `rgb` within `width` of a circle."""
    yy, xx = np.mgrid[0:rgb.shape[0], 0:rgb.shape[1]]
    d = np.hypot(xx - cx, yy - cy)
    return rgb[np.abs(d - r) <= width]


def _ring_coverage(rgb: np.ndarray, cx: int, cy: int, r: float, colour: np.ndarray) -> float:
    """Fraction of 72 points on the circle with `colour` within one pixel."""
    hits = total = 0
    for a in np.linspace(0, 2 * np.pi, 72, endpoint=False):
        x, y = round(cx + r * np.cos(a)), round(cy + r * np.sin(a))
        if 1 <= x < rgb.shape[1] - 1 and 1 <= y < rgb.shape[0] - 1:  # rings may be clipped at the border
            total += 1
            hits += bool(np.all(rgb[y - 1:y + 2, x - 1:x + 2] == colour, axis=-1).any())
    return hits / total


def test_defect_map_rings_have_the_type_colour(written):
    result, _, paths = written
    rgb = _read_png(paths["defect_map"])
    assert rgb.shape == (*result.image.shape, 3)
    assert report_maps.legend_corner(result) == "tr"
    r = round(0.5 * PITCH)
    counts = []
    for d in result.defects:
        cx, cy = result.grid.grid_x_px[d.m - 1, d.n - 1], result.grid.grid_y_px[d.m - 1, d.n - 1]
        if d.error_type != "missing":
            cx, cy = result.grid.measured_x_px[d.m - 1, d.n - 1], result.grid.measured_y_px[d.m - 1, d.n - 1]
        cx, cy = round(cx), round(cy)
        colour = np.array(ERROR_COLOURS[d.error_type])
        assert _ring_coverage(rgb, round(cx), round(cy), r, colour) > 0.95, d
        counts.append((d, int(np.all(_ring(rgb, round(cx), round(cy), r, 2.5) == colour, axis=1).sum())))
        for x, y in ((cx + r, cy), (cx - r, cy), (cx, cy + r), (cx, cy - r)):
            if 0 <= x < rgb.shape[1] and 0 <= y < rgb.shape[0]:
                assert tuple(rgb[round(y), round(x)]) == ERROR_COLOURS[d.error_type], d
    gone = next(d for d in result.defects if d.error_type == "missing")
    assert tuple(rgb[round(result.grid.grid_y_px[9, 11]), round(result.grid.grid_x_px[9, 11])]) \
        == ERROR_COLOURS["missing"]  # the cross through the centre
    thick = [c for d, c in counts if not d.within_tolerance and d is not gone]
    thin = [c for d, c in counts if d.within_tolerance]
    assert min(thick) > 1.5 * max(thin)
    # far from every flagged lens and from the legend: still the grey image, no palette colour
    for m, n in ((1, 1), (4, 1), (12, 1), (12, 6)):
        cell = rgb[(m - 1) * PITCH:m * PITCH, (n - 1) * PITCH:n * PITCH].astype(int)
        assert np.all(cell[..., 0] == cell[..., 1]) and np.all(cell[..., 1] == cell[..., 2]), (m, n)
    # bright disc centre vs dark gap: the tone map spans the range
    assert rgb[9, 9, 0] > 200 and rgb[0, 0, 0] < 40
    small = _read_png(paths["defect_map_small"])
    assert small.shape == rgb.shape  # already under 1024 px


def test_small_map_is_at_most_1024_px(tmp_path):
    result = make_result(rows=30, cols=60, defects=[Defect(15, 30, "radius", 2.0, "%", None, 6.0, False, {})])
    paths = write_report(result, tmp_path / "r")
    full, small = _read_png(paths["defect_map"]), _read_png(paths["defect_map_small"])
    assert full.shape == (600, 1200, 3) and small.shape == (512, 1024, 3)
    cx, cy = result.grid.measured_x_px[14, 29] * 1024 / 1200, result.grid.measured_y_px[14, 29] * 1024 / 1200
    r = round(0.5 * PITCH * 1024 / 1200)
    assert _ring_coverage(small, round(cx), round(cy), r, np.array(ERROR_COLOURS["radius"])) > 0.95


class _Html(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags: list[tuple[str, dict]] = []
        self.stack: list[str] = []
        self.defect_rows = 0
        self.ths: list[dict] = []
        self.cells: list[list[str]] = []
        self._in_defects = False
        self.scripts = 0

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append((tag, a))
        if tag == "table" and a.get("id") == "defects":
            self._in_defects = True
        if self._in_defects and tag == "th":
            self.ths.append(a)
        if self._in_defects and tag == "tr" and "tbody" in self.stack:
            self.defect_rows += 1
            self.cells.append([])
        if tag == "script":
            self.scripts += 1
        self.stack.append(tag)

    def handle_endtag(self, tag):
        if tag == "table":
            self._in_defects = False
        while self.stack and self.stack.pop() != tag:
            pass

    def handle_data(self, data):
        if self._in_defects and self.stack and self.stack[-1] in ("td", "a") and self.cells:
            self.cells[-1].append(data)


def test_html_is_self_contained_sortable_and_complete(written):
    result, _, paths = written
    text = paths["html"].read_text(encoding="utf-8")
    p = _Html()
    p.feed(text)
    assert p.defect_rows == len(result.defects)
    assert len(p.ths) == 6 and all(th.get("data-type") in ("num", "str") for th in p.ths)
    assert p.scripts == 1 and "addEventListener('click'" in text and 'class="sortable"' in text
    imgs = [a for t, a in p.tags if t == "img"]
    assert len(imgs) == 1 + 2 * len(result.defects)  # the map, then lens + reference per flagged lens
    for a in imgs:
        assert a["src"].startswith("data:image/png;base64,")
        assert base64.b64decode(a["src"].split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    small = paths["defect_map_small"].read_bytes()
    assert imgs[0]["src"] == "data:image/png;base64," + base64.b64encode(small).decode()
    for t, a in p.tags:  # nothing fetched from elsewhere; links only to the sibling files and anchors
        for attr in ("src", "href"):
            if attr in a:
                assert not re.match(r"^(https?:)?//", a[attr]), a
    assert "<link" not in text and "@import" not in text
    assert '<div class="banner FAIL"' in text and ">FAIL<" in text
    u_cells = sorted(c[0] for c in p.cells)
    assert u_cells == sorted(f"U({d.m},{d.n})" for d in result.defects)
    assert "2.5 µm" in text and "&lt;b&gt;cfg&lt;/b&gt;" in text  # config shown, escaped
    assert 'id="U3-4"' in text and 'href="#U3-4"' in text
    assert "also fits: pitch 1.1 µm @ 45°; decenter 2.9 µm @ 45°" in text
    assert 'data-sort="Infinity">∞</td>' in text  # the missing lens' score


def test_html_escapes_a_hostile_source_name(tmp_path):
    result = make_result(source=HOSTILE, defects=[Defect(2, 2, "<img src=x onerror=alert(1)>", 1.0,
                                                         "<u>", None, 3.0, True, {"<i>": 1.0})])
    paths = write_report(result, tmp_path / "r")
    text = paths["html"].read_text(encoding="utf-8")
    assert "<script>x</script>" not in text and "&lt;script&gt;x&lt;/script&gt;.dng" in text
    assert "<img src=x" not in text and "<u>" not in text and "<i>" not in text
    assert text.count("<script>") == 1
    assert _strict_json(paths["json"])["source"] == HOSTILE
    assert '<div class="banner PASS"' in text


def test_pass_without_defects_per_lens_reference_and_pitch_px_grid(tmp_path):
    result = make_result(defects=[], per_lens_reference=True, pitch_px_only=True)
    paths = write_report(result, tmp_path / "r")
    data = load_report(paths["json"])
    assert data["verdict"] == "PASS" and data["defects"] == [] and data["summary"]["flagged"] == 0
    assert data["grid_summary"]["pitch_x_px"] == data["grid_summary"]["pitch_y_px"] == 20.0
    assert "No lens was flagged" in paths["html"].read_text(encoding="utf-8")
    one = make_result(defects=[Defect(4, 5, "radius", 1.0, "%", None, 4.0, False, {})], per_lens_reference=True)
    text = write_report(one, tmp_path / "r1")["html"].read_text(encoding="utf-8")
    assert text.count('<figure><img alt="reference U(4,5)"') == 1


def test_gallery_is_capped(tmp_path, monkeypatch):
    monkeypatch.setattr(report_html, "GALLERY_MAX", 5)
    defects = [Defect(m, n, "pitch", 1.0 + m, "µm", 0.0, float(m + n), True, {})
               for m in range(1, 4) for n in range(1, 5)]
    text = write_report(make_result(defects=defects), tmp_path / "r")["html"].read_text(encoding="utf-8")
    p = _Html()
    p.feed(text)
    assert p.defect_rows == 12 and text.count('<div class="lens"') == 5
    assert "Showing the 5 most severe of 12" in text
    assert 'id="U3-4"' in text  # the highest score is in the gallery


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_out_dir_problems_are_one_sentence_input_errors(tmp_path):
    result = make_result()
    a_file = tmp_path / "taken"
    a_file.write_text("keep me")
    with pytest.raises(InputError, match="not a folder"):
        write_report(result, a_file)
    assert a_file.read_text() == "keep me"
    with pytest.raises(InputError, match="does not exist"):
        write_report(result, tmp_path / "no" / "such")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_encoder_failure_half_way_leaves_old_files_and_no_partial_ones(tmp_path, monkeypatch):
    result = make_result()
    out = tmp_path / "r"
    write_report(result, out)
    before = _snapshot(out)
    real, calls = report_png.PendingPng._compress, []

    def flaky(self, a, b, final):  # one band of one image (the maps' bands on the pool, the gallery's here)
        calls.append((a, b))
        if len(calls) == 3:
            raise RuntimeError("encoder exploded")
        return real(self, a, b, final)

    monkeypatch.setattr(report_png.PendingPng, "_compress", flaky)
    changed = make_result(source="/data/other.dng")
    with pytest.raises(RuntimeError, match="exploded"):
        write_report(changed, out)
    assert _snapshot(out) == before
    calls.clear()
    with pytest.raises(RuntimeError):
        write_report(changed, tmp_path / "fresh")
    assert not (tmp_path / "fresh").exists()


def test_disk_full_while_writing_leaves_old_files_and_no_temp_files(tmp_path, monkeypatch):
    result = make_result()
    out = tmp_path / "r"
    write_report(result, out)
    before = _snapshot(out)
    real, calls = report_write._write_bytes, []

    def full_disk(path, data):
        calls.append(path)
        if len(calls) == 3:
            real(path, data[: len(data) // 2])
            raise OSError(28, "No space left on device")
        real(path, data)

    monkeypatch.setattr(report_write, "_write_bytes", full_disk)
    with pytest.raises(InputError, match="No space left on device"):
        write_report(make_result(source="/data/other.dng"), out)
    assert _snapshot(out) == before  # no half-written file, no temp file, nothing replaced
    assert len(calls) == 3
    calls.clear()
    with pytest.raises(InputError):
        write_report(result, tmp_path / "fresh")
    assert not (tmp_path / "fresh").exists()


def test_inconsistent_result_is_refused(tmp_path):
    result = make_result()
    flagged = result.flagged.copy()
    flagged[0, 0] = True  # flagged but no defect listed
    bad = InspectionResult(**{**result.__dict__, "flagged": flagged})
    with pytest.raises(InputError, match="flagged"):
        write_report(bad, tmp_path / "r")
    outside = InspectionResult(**{**result.__dict__, "defects": result.defects + (
        Defect(13, 1, "pitch", 1.0, "µm", 0.0, 3.0, True, {}),)})
    with pytest.raises(InputError, match=r"U\(13,1\) is outside"):
        write_report(outside, tmp_path / "r")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("content, match", [
    (None, "does not exist"),
    (b"\x89PNG not json", "not valid JSON|cannot read"),
    (b"{\"format\": ", "not valid JSON"),
    (b"[1, 2]", "not a JSON object"),
    (b"{\"format\": \"something-else\"}", "format"),
    (b"{\"format\": \"mlaqc-report\", \"format_version\": 99}", "format_version"),
])
def test_load_report_rejects_garbage(tmp_path, content, match):
    path = tmp_path / "report.json"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=match) as info:
        load_report(path)
    msg = str(info.value)
    assert "\n" not in msg and msg.endswith(".")


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(verdict="MAYBE"), "verdict"),
    (lambda d: d["defects"][0].update(row=0), "outside"),
    (lambda d: d["defects"][0].update(col=16), "outside"),
    (lambda d: d["defects"][0].update(magnitude="big"), "non-numeric magnitude"),
    (lambda d: d["defects"][0].pop("within_tolerance"), "within_tolerance"),
    (lambda d: d.pop("summary"), "summary"),
    (lambda d: d["summary"].update(flagged=2), "counts 2 flagged"),
    (lambda d: d.update(defects={}), "not a list"),
])
def test_load_report_rejects_damaged_reports(written, tmp_path, edit, match):
    data = json.loads(written[2]["json"].read_text(encoding="utf-8"))
    edit(data)
    path = tmp_path / "report.json"
    path.write_text(json.dumps(data), encoding="utf-8")
    with pytest.raises(InputError, match=match):
        load_report(path)


def test_load_report_rejects_nan(written, tmp_path):
    text = written[2]["json"].read_text(encoding="utf-8").replace('"magnitude": 2.5', '"magnitude": NaN')
    path = tmp_path / "report.json"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(InputError, match="NaN"):
        load_report(path)


_NODE_SORT_CHECK = r"""
const rows = JSON.parse(process.argv[2]);
function el(attrs) {
  return { a: Object.assign({}, attrs), l: {},
    getAttribute(k) { return k in this.a ? this.a[k] : null; }, hasAttribute(k) { return k in this.a; },
    setAttribute(k, v) { this.a[k] = String(v); }, removeAttribute(k) { delete this.a[k]; },
    addEventListener(e, f) { this.l[e] = f; } };
}
const types = ['num', 'str', 'num', 'num', 'num', 'str'];
const ths = types.map(t => el({'data-type': t}));
const body = { rows: rows.map(r => ({ cells: r.map(c => Object.assign(el(c.sort === null ? {} : {'data-sort': c.sort}),
                                                                     { textContent: c.text })) })),
               appendChild(r) { this.rows.splice(this.rows.indexOf(r), 1); this.rows.push(r); } };
const table = { tHead: { rows: [{ cells: ths }] }, tBodies: [body] };
global.document = { querySelectorAll: () => [table] };
eval(process.argv[1]);
const col = (i) => body.rows.map(r => r.cells[0].textContent);
const out = {};
ths[4].l.click(); out.score_asc = col(); ths[4].l.click(); out.score_desc = col();
ths[1].l.click(); out.type_asc = col(); ths[0].l.click(); out.u_asc = col();
ths[2].l.click(); out.mag_asc = col(); ths[2].l.click(); out.mag_desc = col();
console.log(JSON.stringify(out));
"""


@pytest.mark.skipif(shutil.which("node") is None, reason="node.js not installed")
def test_table_sort_script_sorts_every_column(written):
    """Run the report's own sort script under node against a minimal DOM of the defect table."""
    result, _, paths = written
    text = paths["html"].read_text(encoding="utf-8")
    js = re.search(r"<script>(.*)</script>", text, re.S).group(1)
    tbody = re.search(r'<table class="sortable" id="defects">.*?<tbody>(.*?)</tbody>', text, re.S).group(1)
    rows = []
    for tr in re.findall(r"<tr[^>]*>(.*?)</tr>", tbody, re.S):
        cells = re.findall(r"<td([^>]*)>(.*?)</td>", tr, re.S)
        rows.append([{"sort": (re.search(r'data-sort="([^"]*)"', a) or [None, None])[1],
                      "text": re.sub(r"<[^>]+>", "", c)} for a, c in cells])
    done = subprocess.run(["node", "-e", _NODE_SORT_CHECK, js, json.dumps(rows)], capture_output=True, text=True,
                          timeout=30)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    ds = list(result.defects)
    u = lambda d: f"U({d.m},{d.n})"  # noqa: E731
    assert any(math.isinf(d.score) for d in ds)  # the missing lens: sorts as the largest score
    assert out["score_asc"] == [u(d) for d in sorted(ds, key=lambda d: d.score)]
    assert out["score_desc"] == [u(d) for d in sorted(ds, key=lambda d: -d.score)]
    assert out["type_asc"] == [u(d) for d in sorted(ds, key=lambda d: d.error_type)]
    assert out["u_asc"] == [u(d) for d in sorted(ds, key=lambda d: (d.m, d.n))]  # numeric: U(3,4) < U(10,12)
    mag = [d for d in ds if math.isfinite(d.magnitude)]
    blank = [u(d) for d in ds if math.isnan(d.magnitude)]
    assert out["mag_asc"] == [u(d) for d in sorted(mag, key=lambda d: d.magnitude)] + blank  # blanks last
    assert out["mag_desc"] == [u(d) for d in sorted(mag, key=lambda d: -d.magnitude)] + blank  # either way


def test_the_detection_limit_is_reported_in_json_and_html(tmp_path):
    from dataclasses import replace

    limit = {"pitch_um": 0.55, "decenter_um": 2.0, "radius_rel_pos": 0.112, "radius_rel_neg": None,
             "detect_sigma": 6.0}
    result = replace(make_result(), detection_limit=limit, below_reportable=3, not_inspected=7)
    write_report(result, tmp_path / "r")
    data = load_report(tmp_path / "r")
    assert data["detection_limit"] == limit
    assert data["summary"]["not_inspected"] == 7 and data["summary"]["below_reportable"] == 3
    page = (tmp_path / "r" / "report.html").read_text()
    para = page[page.index('id="detection-limit"'):].split("</p>")[0]
    assert "pitch 0.55 µm" in para and "decenter 2 µm" in para and "+11.2 %" in para
    assert "not detectable" in para  # the radius' negative side has no limit in this frame


def test_report_json_says_which_lens_boundary_model_was_used(tmp_path):
    """Issue #22: the report says whether the frame was inspected with sag-intersection (physical, the
    default) or grid (idealised) lens boundaries; null for a result that does not say."""
    from dataclasses import replace

    from mlaqc.inspection.results import detection_limit_text

    write_report(replace(make_result(), lens_boundaries="sag-intersection"), tmp_path / "s")
    assert load_report(tmp_path / "s")["lens_boundaries"] == "sag-intersection"
    write_report(make_result(), tmp_path / "n")
    assert load_report(tmp_path / "n")["lens_boundaries"] is None
    split = {"pitch_vs_decenter": {"pitch_um": 0.6, "decenter_um": 1.2}}
    assert "(sag-intersection lens boundaries)" in detection_limit_text(split)
    assert "grid lens boundaries" in detection_limit_text({"pitch_vs_decenter": None})
