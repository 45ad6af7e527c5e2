"""The app on hex arrays (offscreen, pytest-qt): a click or hover near a hexagon's edge or corner names the
lens whose cell holds the point, the grid overlay, the defect rings and the selection are hexagonal
cells at the lattice positions, and the mock camera presents and scans a wafer of hex arrays.

Expected lenses and positions are worked out from the convention (even rows m = 2, 4, ... half a pitch
right, rows pitch*sqrt(3)/2 apart), not from mlaqc.optics.lattice."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")
pytest.importorskip("pytestqt")

sys.path.insert(0, str(Path(__file__).parent))

from PySide6.QtCore import QPointF  # noqa: E402
from test_hex_report import (  # noqa: E402
    COLS,
    PITCH,
    ROT_DEG,
    ROWS,
    S3,
    centre_px,
    design_uv,
    direction_px,
    make_hex_result,
)

from gui.app import MainWindow  # noqa: E402
from gui.inspection_worker import build_view  # noqa: E402
from mlaqc.inspection.results import Defect  # noqa: E402
from mlaqc.optics.config import load_config  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
HEX_SMALL = str(ROOT / "fixtures" / "hex_small_camera.toml")
DEFECTS = [Defect(4, 5, "decenter", 0.8, "µm", 30.0, 4.2, True, {}),
           Defect(7, 8, "radius", -1.5, "%", None, 9.0, False, {})]


def lens_of_uv(u: float, v: float) -> tuple[int, int]:
    """U(m,n) whose design centre is at lattice position (u, v) (pitches from U(1,1)'s)."""
    m = round(v / (S3 / 2)) + 1
    return m, round(u - 0.5 * (m % 2 == 0)) + 1


@pytest.fixture(scope="module")
def view():
    result = make_hex_result(DEFECTS)
    return build_view(result, load_config(HEX_SMALL), "/data/hex.dng", 0.1)


def test_clicks_near_hexagon_edges_and_corners_name_the_right_lens(view):
    checked = 0
    for m, n in ((4, 5), (5, 5), (2, 2), (5, 8), (6, 3)):  # both row parities
        c = np.array(centre_px(m, n))
        u, v = design_uv(m, n)
        for k in range(6):
            a = math.radians(60.0 * k)
            nb = lens_of_uv(u + math.cos(a), v - math.sin(a))  # the neighbour across this edge
            e = direction_px(60.0 * k)
            assert view.lens_at(*(c + (0.5 * PITCH - 0.6) * e)) == (m, n), (m, n, k)
            assert view.lens_at(*(c + (0.5 * PITCH + 0.6) * e)) == nb, (m, n, k)
            # just inside a corner, beyond the circle of one pitch
            assert view.lens_at(*(c + (PITCH / S3 - 1.0) * direction_px(30.0 + 60.0 * k))) == (m, n), (m, n, k)
            checked += 3
    assert checked == 90
    # the ragged outline: the notch left of U(2,1) (an even row) and just beyond U(1,1)'s left edge are
    # no lens (though a lens centre is less than 0.72 pitch away)
    assert view.lens_at(*(np.array(centre_px(2, 1)) - 0.8 * PITCH * direction_px(0.0))) is None
    assert view.lens_at(*(np.array(centre_px(1, 1)) + 0.55 * PITCH * direction_px(180.0))) is None
    assert view.lens_at(*(np.array(centre_px(1, 1)) + 0.45 * PITCH * direction_px(180.0))) == (1, 1)


def test_a_distorted_grid_still_gives_each_point_its_own_cell():
    """A grid whose centres drift from a perfect lattice (radial distortion, 1.5 px at the corners): the
    click is read in the frame of the lens' own predicted centre, so points 1 px inside an edge still
    belong to that lens."""
    import dataclasses

    result = make_hex_result()
    g = result.grid
    cx, cy = g.grid_x_px.mean(), g.grid_y_px.mean()
    r2 = ((g.grid_x_px - cx) ** 2 + (g.grid_y_px - cy) ** 2) / ((g.grid_x_px - cx) ** 2 + (g.grid_y_px - cy) ** 2).max()
    k = 1.5 / np.sqrt(((g.grid_x_px - cx) ** 2 + (g.grid_y_px - cy) ** 2).max())
    gx, gy = cx + (g.grid_x_px - cx) * (1 + k * r2), cy + (g.grid_y_px - cy) * (1 + k * r2)
    result = dataclasses.replace(result, grid=dataclasses.replace(g, grid_x_px=gx, grid_y_px=gy, measured_x_px=gx,
                                                                   measured_y_px=gy))
    v = build_view(result, load_config(HEX_SMALL), "x", 0.0)
    for m, n in ((1, 1), (1, COLS), (ROWS, 1), (ROWS, COLS), (5, 6)):
        c = np.array([gx[m - 1, n - 1], gy[m - 1, n - 1]])
        for kk in range(6):
            assert v.lens_at(*(c + (0.5 * PITCH - 1.0) * direction_px(60.0 * kk))) == (m, n), (m, n, kk)


def test_overlays_are_hexagonal_cells_at_the_lattice_positions(qtbot, view):
    w = MainWindow(config_path=HEX_SMALL, connect=False)
    qtbot.addWidget(w)
    w.show_inspection(view)
    w.image.grid_box.setChecked(True)
    assert "hex lenses" in w.inspection_panel.config.text()
    # the grid overlay: one closed hexagon per lens, its corners one circumradius from the lens' centre
    xs, ys = w.image.cells_item.getData()
    assert w.image.cells_item.isVisible() and np.isnan(xs).sum() == ROWS * COLS
    polys = np.column_stack([xs, ys]).reshape(ROWS * COLS, 8, 2)[:, :7]
    m, n = np.meshgrid(np.arange(1, ROWS + 1), np.arange(1, COLS + 1), indexing="ij")
    centres = np.stack(centre_px(m.ravel(), n.ravel()), axis=1)
    d = np.hypot(*(polys[:, :6] - centres[:, None, :]).transpose(2, 0, 1))
    assert np.allclose(d, PITCH / S3, atol=1e-6)
    assert np.allclose(polys[:, 6], polys[:, 0])  # closed
    # the selection (first defect row) is U(4,5)'s hexagon; its top corner points straight up the lattice
    w.select_lens(4, 5)
    assert w.image.select_hex.isVisible() and not w.image.select_item.isVisible()
    poly = w.image.select_hex.polygon()
    pts = np.array([[poly.at(i).x(), poly.at(i).y()] for i in range(poly.count())])
    c = np.array(centre_px(4, 5))
    top = c + PITCH / S3 * direction_px(90.0)
    assert np.min(np.hypot(*(pts - top).T)) < 1e-6
    # the defect rings are hexagons too: the symbol path is a unit cell turned with the grid
    path = w.image.ring_item.opts["symbol"]
    assert not isinstance(path, str)
    a = math.radians(ROT_DEG)
    assert path.contains(QPointF(0.45 * math.cos(a), -0.45 * math.sin(a)))  # inside an edge's middle
    assert not path.contains(QPointF(0.55 * math.cos(a), -0.55 * math.sin(a)))
    corner = (0.55 * math.cos(a + math.pi / 6), -0.55 * math.sin(a + math.pi / 6))  # a corner reaches 1/sqrt(3)
    assert path.contains(QPointF(*corner))
    # a click and a hover through the image's signals: the detail panel and the status bar name the lens
    p = c + (0.5 * PITCH - 0.7) * direction_px(120.0)
    w.image.clicked.emit(float(p[0]), float(p[1]))
    assert w.lens_detail.lens == (4, 5)
    q = c + (0.5 * PITCH + 0.7) * direction_px(120.0)  # across the upper-left edge: U(3,5)
    w.image.clicked.emit(float(q[0]), float(q[1]))
    assert w.lens_detail.lens == (3, 5)
    w.image.hovered.emit(float(p[0]), float(p[1]), None)
    assert "U(4,5)" in w.cursor_label.text()
    w.close()


def test_a_square_view_keeps_round_rings_and_no_cells(qtbot):
    import dataclasses

    result = make_hex_result(DEFECTS)
    result = dataclasses.replace(result, grid=dataclasses.replace(result.grid, packing="square"))
    v = build_view(result, load_config(str(ROOT / "fixtures" / "small_camera.toml")), "x", 0.0)
    assert v.packing == "square" and v.cells_x is None
    w = MainWindow(connect=False)
    qtbot.addWidget(w)
    w.show_inspection(v)
    w.image.grid_box.setChecked(True)
    assert w.image.ring_item.opts["symbol"] == "o"
    xs = w.image.cells_item.getData()[0]
    assert xs is None or len(xs) == 0
    w.select_lens(3, 4)
    assert w.image.select_item.isVisible() and not w.image.select_hex.isVisible()
    w.close()


# ------------------------------------------------------------------------------ mock hardware


def test_the_mock_wafer_holds_hex_arrays_of_the_hex_config():
    from drivers.camera.mock import MockCamera
    from drivers.wafer import Wafer, array_size_mm

    cfg = load_config(HEX_SMALL)
    p_mm = cfg.mla.pitch_um / 1000
    w_mm, h_mm = array_size_mm(cfg)
    assert w_mm == pytest.approx((24 + 0.5) * p_mm) and h_mm == pytest.approx((27 * S3 / 2 + 2 / S3) * p_mm)
    wafer = Wafer(cfg, cols=2, rows=1, defects=4, seed=3)
    arr = wafer.array(1, 2)
    assert arr.errors.packing == "hex" and arr.errors.shape == (28, 24)
    assert wafer.truth()["arrays"][1]["error_map"]["packing"] == "hex"
    assert wafer.layout()["mla_packing"] == "hex"
    with MockCamera.from_url("mock://?config=hex_small&wafer=2x1&rpp=0.5&defects=2") as cam:
        assert "hex" in cam.name and cam.cfg.mla.packing == "hex" and cam.cfg.mla.count_h == 28
        frame = cam.capture()
        assert frame.data.shape == (496, 496) and frame.extra["truth"]["error_map"]["packing"] == "hex"


def test_a_scan_over_a_hex_wafer_records_each_arrays_hex_truth(tmp_path):
    import json

    from drivers.scan import run_scan
    from drivers.scan_plan import load_plan

    plan = tmp_path / "plan.toml"
    plan.write_text('[scan]\nsettle_s = 0.0\n[[positions]]\nx_mm = 10.0\ny_mm = 10.0\nlabel = "W(1,1)"\n'
                    '[[positions]]\nx_mm = 15.0\ny_mm = 10.0\nlabel = "W(1,2)"\n')
    camera = "mock://?config=hex_small&wafer=2x1&defects=3&seed=4&rpp=0.5"
    run_scan(camera, "mock://", load_plan(plan), tmp_path / "scan")
    lines = [json.loads(x) for x in (tmp_path / "scan" / "manifest.jsonl").read_text().splitlines()]
    header, records = lines[0], [r for r in lines[1:] if r.get("type") != "header"]
    assert header["truth"]["mla_packing"] == "hex" and header["truth"]["mla_shape"] == [28, 24]
    assert [r["truth"]["array"] for r in records] == ["W(1,1)", "W(1,2)"]
    assert all(a["error_map"]["packing"] == "hex" for a in header["truth"]["arrays"])
    for rec in records:
        assert rec["truth"]["in_view"]
        assert (tmp_path / "scan" / rec["files"][0]["file"]).stat().st_size > 496 * 496


def test_circular_apertures_are_drawn_in_the_grid_overlay(qtbot):
    cfg = load_config(str(ROOT / "fixtures" / "hex_circle_camera.toml"))
    v = build_view(make_hex_result(DEFECTS), cfg, "x", 0.0)
    assert v.aperture_px == pytest.approx(0.9 * PITCH)  # 90 µm circles at a 100 µm pitch
    w = MainWindow(connect=False)
    qtbot.addWidget(w)
    w.show_inspection(v)
    w.image.grid_box.setChecked(True)
    xs, _ = w.image.apertures_item.getData()
    assert len(xs) == ROWS * COLS and w.image.apertures_item.isVisible()
    assert w.image.apertures_item.opts["size"] == pytest.approx(0.9 * PITCH)
    assert np.allclose(sorted(xs), sorted(np.ravel(centre_px(*np.meshgrid(np.arange(1, ROWS + 1),
                                                                         np.arange(1, COLS + 1), indexing="ij"))[0])))
    w.close()


def test_a_scan_with_inspection_finds_the_seeded_defects_of_each_hex_array(tmp_path):
    import json

    from drivers.scan import default_inspect_hook, run_scan
    from drivers.scan_plan import load_plan
    plan = tmp_path / "plan.toml"
    plan.write_text('[scan]\nsettle_s = 0.0\n[[positions]]\nx_mm = 10.0\ny_mm = 10.0\nlabel = "W(1,1)"\n'
                    '[[positions]]\nx_mm = 15.0\ny_mm = 10.0\nlabel = "W(1,2)"\n')
    camera = "mock://?config=hex_small&wafer=2x1&defects=3&defect_types=decenter&seed=4&rpp=40"
    run_scan(camera, "mock://", load_plan(plan), tmp_path / "scan", inspect=default_inspect_hook())
    lines = [json.loads(x) for x in (tmp_path / "scan" / "manifest.jsonl").read_text().splitlines()]
    header, records = lines[0], [r for r in lines[1:] if r.get("type") != "header"]
    for rec in records:
        raw = tmp_path / "scan" / rec["files"][0]["file"]
        report = json.loads(raw.with_name(raw.name + ".inspect.json").read_text())
        seeded = next({(lens["m"], lens["n"]) for lens in a["error_map"]["lenses"]}
                      for a in header["truth"]["arrays"] if a["name"] == rec["truth"]["array"])
        found = {(d["row"], d["col"]) for d in report["defects"] if d["error_type"] in ("decenter", "position")}
        assert len(seeded) == 3 and seeded <= found, (rec["label"], found, seeded)
        assert report["verdict"] == "FAIL"
