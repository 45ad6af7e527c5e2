"""Reports of hex-packed arrays: the defect map's rings are the lens' hexagonal cell at U(m,n)'s lattice
position, the lens maps tile hexagonal cells, lenses.csv carries the design centres and round-trips,
report.json and report.html state the packing and its convention.

Every expected position here is worked out from the convention itself (even rows m = 2, 4, ... shifted
half a pitch right, rows pitch*sqrt(3)/2 apart), not from mlaqc.optics.lattice."""

from __future__ import annotations

import csv
import io
import json
import math

import cv2
import numpy as np
import pytest

from mlaqc.errors import InputError
from mlaqc.inspection.calibrate import Grid
from mlaqc.inspection.measure import MEASUREMENTS
from mlaqc.inspection.results import METRICS, Defect, InspectionResult, LensMetrics
from mlaqc.inspection.throughfocus_results import TF_MEASUREMENTS
from mlaqc.optics.lattice import Lattice
from mlaqc.report import ERROR_COLOURS
from mlaqc.report.document import CSV_COLUMNS, HEX_CSV_COLUMNS
from mlaqc.report.lensmaps import HEX_LENS_PX, diverging, hex_cells, render_lens_maps
from mlaqc.report import maps as report_maps
from mlaqc.report.maps import render_defect_map
from mlaqc.report.write import render_report

ROWS, COLS, PITCH = 10, 12, 30.0
ROT_DEG = 3.0  # the lattice is rotated on the image: the hexagons must turn with it
ORIGIN = (40.0, 45.0)  # U(1,1)'s centre, px
S3 = math.sqrt(3.0)


def design_uv(m, n):
    """Design centre of U(m,n) in pitches from U(1,1)'s: the convention, written out."""
    m, n = np.asarray(m), np.asarray(n)
    return (n - 1) + 0.5 * (m % 2 == 0), (m - 1) * S3 / 2


def centre_px(m, n, pitch=PITCH, rot_deg=ROT_DEG, origin=ORIGIN):
    """Pixel centre of U(m,n) on the synthetic frame: the lattice rotated counterclockwise as displayed."""
    u, v = design_uv(m, n)
    a = math.radians(rot_deg)
    x = origin[0] + pitch * (u * math.cos(a) + v * math.sin(a))
    y = origin[1] + pitch * (-u * math.sin(a) + v * math.cos(a))
    return x, y


def direction_px(angle_deg: float, rot_deg: float = ROT_DEG) -> np.ndarray:
    """Unit vector on the image at `angle_deg` counterclockwise (as displayed) from the lattice's row axis."""
    a = math.radians(angle_deg + rot_deg)
    return np.array([math.cos(a), -math.sin(a)])


def make_hex_result(defects: list[Defect] | None = None, rows: int = ROWS, cols: int = COLS, pitch: float = PITCH,
                    rot_deg: float = ROT_DEG, with_measurements: bool = False) -> InspectionResult:
    """A synthetic inspection of a hex array: bright discs at the convention's centres on a dark frame, a
    real Grid (packing 'hex') whose measured and predicted centres are those centres."""
    defects = [] if defects is None else defects
    shape = (rows, cols)
    m, n = np.meshgrid(np.arange(1, rows + 1), np.arange(1, cols + 1), indexing="ij")
    gx, gy = centre_px(m, n, pitch, rot_deg)
    h = math.ceil(gy.max() + ORIGIN[1])
    w = math.ceil(gx.max() + ORIGIN[0])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    image = np.full((h, w), 0.05, np.float32)
    for x0, y0 in zip(gx.ravel(), gy.ravel()):
        image[(xx - x0) ** 2 + (yy - y0) ** 2 < (0.4 * pitch) ** 2] = 0.8
    side = int(pitch)
    subimages = np.zeros((rows, cols, side, side), np.float32)
    for r in range(rows):
        for c in range(cols):
            y0, x0 = int(gy[r, c]) - side // 2, int(gx[r, c]) - side // 2
            subimages[r, c] = image[y0:y0 + side, x0:x0 + side]
    missing = np.zeros(shape, bool)
    flagged = np.zeros(shape, bool)
    error_type = np.full(shape, "", dtype=object)
    for d in defects:
        flagged[d.m - 1, d.n - 1] = True
        error_type[d.m - 1, d.n - 1] = d.error_type
        missing[d.m - 1, d.n - 1] |= d.error_type == "missing"
    mx, my = np.where(missing, np.nan, gx), np.where(missing, np.nan, gy)
    grid = Grid(rows=rows, cols=cols, pitch_px=(pitch, pitch * S3 / 2), rotation_deg=rot_deg, shear_deg=0.0,
                origin_px=(float(gx[0, 0]), float(gy[0, 0])), homography=np.eye(3), radial_k=0.0,
                radial_centre_px=(w / 2, h / 2), radial_scale_px=float(w), edge_width_px=0.5, image_shape=(h, w),
                measured_x_px=mx, measured_y_px=my, grid_x_px=gx, grid_y_px=gy, residual_px=np.hypot(mx - gx, my - gy),
                flux=np.where(missing, np.nan, 1.0), radius_px=np.where(missing, np.nan, 0.4 * pitch),
                missing=missing, clipped=np.zeros(shape, bool), rms_residual_px=0.0, packing="hex")
    rng = np.random.default_rng(1)
    values = {k: np.where(missing, np.nan, rng.normal(1.0, 0.05, shape)) for k in METRICS}
    measurements = None
    if with_measurements:
        from mlaqc.inspection.measure import LensMeasurements

        measurements = LensMeasurements({k: rng.normal(0.0, 1.0, shape) for k in MEASUREMENTS}, 500.0)
    verdict = "FAIL" if any(not d.within_tolerance for d in defects) else "PASS"
    return InspectionResult(
        verdict=verdict, grid=grid, metrics=LensMetrics(values), defects=tuple(defects), flagged=flagged,
        error_type=error_type.astype(str), image=image, subimages=subimages, reference=subimages[0, 0].copy(),
        source="/data/hex.dng", tolerances={"pitch_um": 1.0}, timings_s={}, measurements=measurements)


def _is_grey(px: np.ndarray) -> bool:
    return int(px[0]) == int(px[1]) == int(px[2])


def _colour_near(rgb: np.ndarray, x: float, y: float, colour) -> bool:
    """`colour` within one pixel of (x, y)."""
    xi, yi = round(x), round(y)
    return bool(np.all(rgb[yi - 1:yi + 2, xi - 1:xi + 2] == np.array(colour), axis=-1).any())


# ------------------------------------------------------------------------------------------ defect map


def test_a_flagged_lens_ring_is_its_hexagon_at_the_lattice_position():
    # U(4,5): an even row, so shifted half a pitch right; thin ring (within tolerance)
    lens = Defect(4, 5, "decenter", 0.8, "µm", None, 4.2, True, {})
    rgb = render_defect_map(make_hex_result([lens]))
    colour = ERROR_COLOURS["decenter"]
    cx, cy = centre_px(4, 5)
    c = np.array([cx, cy])
    apothem, circumradius = 0.5 * PITCH, PITCH / S3
    for k in range(6):
        edge = direction_px(60.0 * k)  # flat sides face the row and the diagonal neighbours
        corner = direction_px(30.0 + 60.0 * k)  # pointy top: corners at 30, 90, ... degrees
        assert _colour_near(rgb, *(c + apothem * edge), colour), ("edge", k)
        assert _colour_near(rgb, *(c + circumradius * corner), colour), ("corner", k)
        # a circle of one pitch would pass here; the hexagon's corner lies 15 % further out
        assert _is_grey(rgb[round(cy + 0.47 * PITCH * corner[1]), round(cx + 0.47 * PITCH * corner[0])]), k
        # outside the ring (its halo ends 2 px beyond the outline): the image again
        out = c + (apothem + 5.0) * edge
        assert _is_grey(rgb[round(out[1]), round(out[0])]), ("outside", k)
    assert _is_grey(rgb[round(cy), round(cx)])  # the sub-image itself is left to be seen
    assert rgb[round(cy), round(cx), 0] > 200  # ... bright: the ring is centred on the lens
    # the same lens on the unshifted row's position would be half a pitch left: its corner is not ringed
    wrong = c - 0.5 * PITCH * direction_px(0.0) + circumradius * direction_px(90.0)
    assert not _colour_near(rgb, *wrong, colour)


def test_out_of_tolerance_hexagons_are_thicker_and_a_missing_lens_is_crossed():
    thin = Defect(3, 3, "pitch", 0.5, "µm", None, 4.0, True, {})
    thick = Defect(7, 8, "pitch", 3.0, "µm", None, 9.0, False, {})
    gone = Defect(6, 4, "missing", math.nan, "", None, math.inf, False, {})
    result = make_hex_result([thin, thick, gone])
    rgb = render_defect_map(result)
    colour = np.array(ERROR_COLOURS["pitch"])

    def width(m: int, n: int) -> int:
        """Coloured run along the ray through the middle of the lens' right-hand side."""
        c = np.array(centre_px(m, n))
        along = [c + t * direction_px(0.0) for t in np.arange(0.3, 0.75, 0.02) * PITCH]
        return sum(bool(np.all(rgb[round(p[1]), round(p[0])] == colour)) for p in along)

    assert width(7, 8) > 1.5 * width(3, 3) > 0
    x, y = centre_px(6, 4)
    assert tuple(rgb[round(y), round(x)]) == ERROR_COLOURS["missing"]  # the cross through its centre


def test_the_small_map_scales_the_hexagons_with_the_image():
    lens = Defect(5, 6, "pitch", 3.0, "µm", None, 9.0, False, {})
    result = make_hex_result([lens])
    h, w = result.image.shape
    rgb = render_defect_map(result, max_side=w // 2)
    k = (w // 2) / max(h, w)
    c = np.array(centre_px(5, 6)) * k
    for j in range(6):
        assert _colour_near(rgb, *(c + 0.5 * PITCH * k * direction_px(60.0 * j)), ERROR_COLOURS["pitch"]), j
    assert not _colour_near(rgb, *c, ERROR_COLOURS["pitch"])


def _ringed(rgb: np.ndarray, m: int, n: int, colour) -> bool:
    """The middle of each of U(m,n)'s six hexagon sides (inside the image) carries `colour`."""
    c = np.array(centre_px(m, n))
    sides = [c + 0.5 * PITCH * direction_px(60.0 * k) for k in range(6)]
    inside = [p for p in sides if 1 <= p[0] < rgb.shape[1] - 1 and 1 <= p[1] < rgb.shape[0] - 1]
    return len(inside) >= 3 and all(_colour_near(rgb, *p, colour) for p in inside)


def test_the_legend_goes_where_it_hides_no_ring_and_never_hides_one():
    colour = ERROR_COLOURS["radius"]
    lens = lambda m, n: Defect(m, n, "radius", 3.0, "%", None, 9.0, False, {})  # noqa: E731
    # top right holds the fewest flagged lenses, but its one sits in the corner; top left's two are
    # clear of a corner box: the legend goes top left
    spread = [(4, 6), (5, 6), (1, COLS), (ROWS, 1), (ROWS - 1, 2), (ROWS, COLS), (ROWS - 1, COLS - 1)]
    result = make_hex_result([lens(m, n) for m, n in spread])
    assert report_maps.legend_corner(result) == "tl"
    rgb = render_defect_map(result)
    assert all(_ringed(rgb, m, n, colour) for m, n in spread)
    # a flagged lens in every corner: the box covers one, and its ring is drawn over the box
    corners = [(1, 1), (1, COLS), (ROWS, 1), (ROWS, COLS)]
    result = make_hex_result([lens(m, n) for m, n in corners])
    rgb = render_defect_map(result)
    assert all(_ringed(rgb, m, n, colour) for m, n in corners)
    fail = np.all(rgb == np.array(report_maps.VERDICT_COLOURS["FAIL"]), axis=-1)
    assert fail.sum() > 20  # the legend is still drawn


# ------------------------------------------------------------------------------------------ lens maps


def _axial_class(m: np.ndarray, n: np.ndarray) -> np.ndarray:
    """A 3-colouring of the hex lattice (no two neighbours share a class): axial q - r mod 3, with the
    axial coordinates of the 'odd-r' offset layout (0-based odd rows shifted right)."""
    r, c = m - 1, n - 1
    q = c - (r - (r % 2)) // 2
    return (q - r) % 3


def test_lens_maps_tile_hexagons_each_lens_coloured_at_its_own_cell():
    rows, cols = 9, 11
    m, n = np.meshgrid(np.arange(1, rows + 1), np.arange(1, cols + 1), indexing="ij")
    cls = _axial_class(m, n)
    values = (cls - 1).astype(float)  # -1, 0, +1: blue, white, red
    meas = {k: np.zeros((rows, cols)) for k in ("centre_dy_um", "focal_rel", "centre_sigma_um", "focal_sigma_rel")}
    meas["centre_dx_um"] = values
    meas["centre_sigma_um"] = np.full((rows, cols), 0.01)
    img = render_lens_maps(meas, (rows, cols), "hex")
    px = HEX_LENS_PX
    body_w = math.ceil((cols + 0.5) * px)
    palette = diverging(np.array([-1.0, 0.0, 1.0]), 1.0)
    # U(m,n)'s centre from the bounding box's corner: half a pitch right, one circumradius down
    for mm, nn, k in zip(m.ravel(), n.ravel(), cls.ravel()):
        u, v = design_uv(mm, nn)
        x, y = (u + 0.5) * px, (v + 1 / S3) * px
        assert tuple(img[26 + int(y), int(x)]) == tuple(palette[k]), (mm, nn)
    body = img[26:26 + math.ceil(((rows - 1) * S3 / 2 + 2 / S3) * px), :body_w]
    # the array's inside (between the outer rows' and columns' centres) has no background pixel
    inner = body[int(1 / S3 * px) + 1:int(((rows - 1) * S3 / 2 + 1 / S3) * px) - 1, px + 1:int((cols - 0.5) * px) - 1]
    assert not np.any(np.all(inner == 255, axis=-1))
    # ... and the colours are the three classes' only
    assert {tuple(p) for p in inner.reshape(-1, 3)} <= {tuple(p) for p in palette}


def test_hex_cells_are_the_lenses_hexagons():
    rows, cols, px = 6, 7, 40
    labels, inside = hex_cells(Lattice("hex", rows, cols), px)
    r_img, c_img = np.mgrid[0:labels.shape[0], 0:labels.shape[1]]
    x, y = (c_img + 0.5) / px, (r_img + 0.5) / px  # pitches from the bounding box's corner
    area = px * px * S3 / 2
    for m in (2, 3, 5):  # inner lenses, both row parities
        for nn in (2, 4, 6):
            k = (m - 1) * cols + nn - 1
            mine = inside & (labels == k)
            u, v = design_uv(m, nn)
            cx, cy = u + 0.5, v + 1 / S3
            assert mine.sum() == pytest.approx(area, rel=0.03)  # a cell's area, sqrt(3)/2 pitch^2
            assert x[mine].mean() == pytest.approx(cx, abs=0.01) and y[mine].mean() == pytest.approx(cy, abs=0.01)
            # inside its hexagon: |d . e_k| <= 1/2 along the six edge normals (and the cells do not overlap:
            # every such pixel has this one label)
            dx, dy = x - cx, y - cy
            normals = [(math.cos(math.radians(a)), math.sin(math.radians(a))) for a in range(0, 360, 60)]
            proj = np.max([dx * a + dy * b for a, b in normals], axis=0)
            assert np.all(mine[proj < 0.49]) and not np.any(mine[proj > 0.51])
    assert not inside[0, 0] and not inside[labels.shape[0] // 2, -1]  # the ragged outline's notches


# ------------------------------------------------------------------------------------ csv, json, html


@pytest.fixture(scope="module")
def rendered():
    defects = [Defect(4, 5, "decenter", 0.8, "µm", 30.0, 4.2, True, {}),
               Defect(7, 8, "radius", -1.5, "%", None, 9.0, False, {})]
    result = make_hex_result(defects, with_measurements=True)
    return result, render_report(result, {"mla": {"pitch_um": 100.0, "packing": "hex"}})


def test_lenses_csv_has_design_centres_and_round_trips(rendered):
    result, files = rendered
    rows = list(csv.reader(io.StringIO(files["csv"].decode())))
    header, body = rows[0], rows[1:]
    assert header == [*CSV_COLUMNS, *HEX_CSV_COLUMNS]
    assert len(body) == ROWS * COLS
    by_u = {(int(r[0]), int(r[1])): dict(zip(header, r)) for r in body}
    lat = Lattice("hex", ROWS, COLS, 100.0)
    u_mid, v_mid = (COLS - 0.5) / 2, (ROWS - 1) * S3 / 4  # the bounding box of the centres
    for (m, n), lens in by_u.items():
        u, v = design_uv(m, n)
        assert float(lens["design_u"]) == pytest.approx(u, abs=1e-5)
        assert float(lens["design_v"]) == pytest.approx(v, abs=1e-5)
        x, y = float(lens["design_x_um"]), float(lens["design_y_um"])
        assert x == pytest.approx(100 * (u - u_mid), abs=1e-3) and y == pytest.approx(100 * (v - v_mid), abs=1e-3)
        r, c, ok = lat.nearest(x, y)  # the design centre lies in its own cell: back to U(m,n)
        assert bool(ok) and (int(r) + 1, int(c) + 1) == (m, n)
        assert float(lens["x_px"]) == pytest.approx(result.grid.measured_x_px[m - 1, n - 1], abs=1e-3)
    assert (by_u[(4, 5)]["flagged"], by_u[(4, 5)]["error_type"]) == ("1", "decenter")
    assert all(lens[k] == "" for lens in body for k in (header.index(t) for t in TF_MEASUREMENTS))


def test_csv_without_the_pitch_leaves_micrometres_empty():
    from mlaqc.report.document import lenses_csv

    text = lenses_csv(make_hex_result())
    rows = list(csv.DictReader(io.StringIO(text)))
    assert all(r["design_x_um"] == "" and r["design_y_um"] == "" for r in rows)
    assert float(rows[COLS]["design_u"]) == 0.5  # U(2,1): the first shifted row


def test_report_json_and_html_state_the_hex_convention(rendered):
    _, files = rendered
    data = json.loads(files["json"])
    lat = data["conventions"]["lattice"]
    assert (lat["packing"], lat["rows"], lat["cols"]) == ("hex", ROWS, COLS)
    assert lat["row_step_pitch"] == pytest.approx(S3 / 2)
    assert "even rows" in data["conventions"]["lens"] and "sqrt(3)/2" in data["conventions"]["lens"]
    assert data["grid_summary"]["pitch_px"] == pytest.approx(PITCH, rel=1e-9)  # along a row, not the row step
    html_text = files["html"].decode()
    assert 'id="lattice"' in html_text and "Lattice: hex" in html_text
    assert "hexagonal cell per lens" in html_text and "Hexagon (the lens' cell) colour" in html_text
    lens_png = cv2.imdecode(np.frombuffer(files["lens_maps"], np.uint8), cv2.IMREAD_COLOR)
    assert lens_png.shape[0] > 26 + (ROWS - 1) * S3 / 2 * HEX_LENS_PX


def test_a_square_grid_still_reports_square(rendered):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_report import make_result

    data = json.loads(render_report(make_result())["json"])
    assert data["conventions"]["lattice"]["packing"] == "square"
    assert data["conventions"]["lens"] == "U(m,n): row m from 1 at the top, column n from 1 at the left"


def test_an_unknown_packing_is_refused_in_one_sentence():
    result = make_hex_result()
    object.__setattr__(result.grid, "packing", "triangle")
    with pytest.raises(InputError, match="packing is 'triangle'"):
        render_report(result)


def test_html_states_circular_apertures_from_the_config():
    files = render_report(make_hex_result(), {"mla": {"pitch_um": 100.0, "packing": "hex", "aperture": "circle",
                                                      "aperture_diameter_um": 90.0, "gap": "opaque"}})
    assert "Lattice: hex</b>, circular lenses 90 µm across, opaque gaps" in files["html"].decode()
