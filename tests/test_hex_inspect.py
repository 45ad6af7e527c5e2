"""Inspection after calibration on a hexagonal lattice (issue #22): a lens' neighbours are the lattice's
six, each along its own direction (echo suppression, the pitch/decenter contrast), the hex edge columns'
two populations, the signature patch and the reference's cells, and bad input. Checked against
geometry worked out here by hand (positions from the convention's own formula, distances), not against
the code's output."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mlaqc.errors import InputError
from mlaqc.inspection.baselines import local_deviations
from mlaqc.inspection.identify import spill
from mlaqc.models.position_split import contrast_sigma, neighbour_contrast
from mlaqc.models.reference import _lattice_cell_sums
from mlaqc.models.signatures import nominal_windows, patch_centre, patch_config, patch_errors, signature_key
from mlaqc.optics.config import load_config

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
HEX = load_config(FIXTURES / "hex_small_camera.toml")
SQUARE = load_config(FIXTURES / "small_camera.toml")
S3 = math.sqrt(3.0) / 2.0


def centre_uv(r, c):
    """U(r+1, c+1)'s centre in pitches from U(1,1), by the convention's formula (README, lattice note)."""
    return c + 0.5 * (np.asarray(r) % 2), np.asarray(r) * S3


def hex_neighbours(r: int, c: int, rows: int, cols: int) -> list[tuple[int, int]]:
    """The lenses one pitch from (r, c), found by distance (not by index steps)."""
    u0, v0 = centre_uv(r, c)
    out = []
    for rr in range(max(r - 1, 0), min(r + 2, rows)):
        for cc in range(max(c - 2, 0), min(c + 3, cols)):
            u, v = centre_uv(rr, cc)
            if (rr, cc) != (r, c) and abs(math.hypot(u - u0, v - v0) - 1.0) < 1e-9:
                out.append((rr, cc))
    return out


# --- the pitch/decenter contrast: the 6 neighbours' tilts towards the lens -----------------------------

@pytest.mark.parametrize("r", [4, 5])  # both row parities
def test_hex_contrast_sums_the_six_neighbours_tilts_towards_the_lens(r):
    rows, cols, c = 10, 10, 4
    ax, ay = np.zeros((rows, cols)), np.zeros((rows, cols))
    u0, v0 = centre_uv(r, c)
    nbrs = hex_neighbours(r, c, rows, cols)
    assert len(nbrs) == 6
    for k, (rr, cc) in enumerate(nbrs):  # each tilted towards the lens by 0.1 k
        u, v = centre_uv(rr, cc)
        ax[rr, cc], ay[rr, cc] = 0.1 * (k + 1) * (u0 - u), 0.1 * (k + 1) * (v0 - v)
    got = neighbour_contrast(ax, ay, "hex")
    assert got[r, c] == pytest.approx(0.1 * sum(range(1, 7)))
    # tilts across the line to the lens add nothing
    tx, ty = -ay, ax
    assert neighbour_contrast(tx, ty, "hex")[r, c] == pytest.approx(0.0, abs=1e-12)


def test_hex_contrast_of_a_uniform_tilt_is_zero_and_border_lenses_have_none():
    """The six unit vectors sum to zero: a tilt the whole field shares (vignetting) is no contrast."""
    rng = np.random.default_rng(1)
    ax, ay = np.full((12, 11), 0.37), np.full((12, 11), -0.21)
    c = neighbour_contrast(ax, ay, "hex")
    assert np.allclose(c[1:-1, 1:-1], 0.0, atol=1e-12)
    assert np.isnan(c[0]).all() and np.isnan(c[-1]).all() and np.isnan(c[:, 0]).all() and np.isnan(c[:, -1]).all()
    assert np.isfinite(contrast_sigma(rng.normal(size=(12, 11)), rng.normal(size=(12, 11)), "hex"))


def test_square_contrast_is_unchanged():
    rng = np.random.default_rng(2)
    ax, ay = rng.normal(size=(7, 8)), rng.normal(size=(7, 8))
    c = neighbour_contrast(ax, ay)
    assert c[3, 4] == pytest.approx(ax[3, 3] - ax[3, 5] + ay[2, 4] - ay[4, 4])


# --- echo suppression over the six neighbours ----------------------------------------------------------

@pytest.mark.parametrize("r", [4, 5])
def test_a_weak_flag_beside_a_strong_one_is_its_echo_on_all_six_sides_and_not_two_away(r):
    rows, cols, c = 10, 10, 4
    score = np.zeros((rows, cols))
    flagged = np.zeros((rows, cols), bool)
    score[r, c], flagged[r, c] = 20.0, True
    nbrs = hex_neighbours(r, c, rows, cols)
    for rr, cc in nbrs:
        score[rr, cc], flagged[rr, cc] = 10.0, True  # under 0.65 x 20
    far = (r, c + 2)  # two pitches away in the row
    score[far], flagged[far] = 10.0, True
    echo = spill(score, flagged, packing="hex")
    assert all(echo[p] for p in nbrs)
    assert not echo[far] and not echo[r, c]
    # a lens one row down whose index column equals the strong lens' but is not its neighbour on this
    # parity (the square 3 x 3 would call it one)
    not_nbr = (r + 1, c - 1) if r % 2 else (r + 1, c + 1)
    assert not_nbr not in nbrs
    score2, flagged2 = np.zeros((rows, cols)), np.zeros((rows, cols), bool)
    score2[r, c], flagged2[r, c] = 20.0, True
    score2[not_nbr], flagged2[not_nbr] = 10.0, True
    assert not spill(score2, flagged2, packing="hex")[not_nbr]


@pytest.mark.parametrize("r", [4, 5])
def test_a_facing_echo_is_told_by_its_tilt_along_the_true_neighbour_direction(r):
    """A neighbour at 0.9 x the strong lens' score is its echo only if its tilt lies along the line to it:
    the hex lines lie at 0, 60, 120 degrees (half a pitch across for the rows above and below)."""
    rows, cols, c = 10, 10, 4
    u0, v0 = centre_uv(r, c)
    for rr, cc in hex_neighbours(r, c, rows, cols):
        u, v = centre_uv(rr, cc)
        score = np.zeros((rows, cols))
        flagged = np.zeros((rows, cols), bool)
        score[r, c], flagged[r, c] = 20.0, True
        score[rr, cc], flagged[rr, cc] = 18.0, True
        for along, expect in (((u0 - u, v0 - v), True), ((-(v0 - v), u0 - u), False)):
            ax, ay = np.zeros((rows, cols)), np.zeros((rows, cols))
            ax[rr, cc], ay[rr, cc] = along
            echo = spill(score, flagged, asym=(ax, ay), packing="hex")
            assert echo[rr, cc] == expect, ((rr, cc), along)


def test_square_spill_still_sees_eight_neighbours():
    score = np.zeros((7, 7))
    flagged = np.zeros((7, 7), bool)
    score[3, 3], flagged[3, 3] = 20.0, True
    for dm in (-1, 0, 1):
        for dn in (-1, 0, 1):
            if dm or dn:
                score[3 + dm, 3 + dn], flagged[3 + dm, 3 + dn] = 10.0, True
    echo = spill(score, flagged)
    assert echo.sum() == 8 and not echo[3, 3]


def test_a_lens_moved_beyond_what_spilled_light_does_is_never_an_echo():
    """Beside a neighbour scoring 10x, a lens whose centre moved 0.8 px is its own defect when echoes move
    under 0.5 px; one that moved 0.2 px is still the echo."""
    score = np.zeros((5, 5))
    flagged = np.zeros((5, 5), bool)
    score[2, 2], score[2, 3], score[3, 2] = 100.0, 10.0, 10.0
    flagged[2, 2] = flagged[2, 3] = flagged[3, 2] = True
    ox, oy = np.zeros((5, 5)), np.zeros((5, 5))
    ox[2, 3], oy[3, 2] = 0.8, 0.2
    echo = spill(score, flagged, offset=(ox, oy), moved_px=0.5)
    assert not echo[2, 3] and echo[3, 2] and not echo[2, 2]


# --- local baselines on the hex lattice ----------------------------------------------------------------

def test_a_linear_trend_leaves_at_most_a_quarter_pitch_of_its_slope_inside():
    """The 5 x 5 offset window is not point-symmetric on hex; on a linear trend its median is off by
    at most 0.33 pitch times the slope (0.326 worked out over every direction in half degrees)."""
    rows, cols = 30, 26
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    u, v = centre_uv(r, c)
    for deg in range(0, 180, 7):
        a = math.radians(deg)
        ramp = 0.01 * (math.cos(a) * u + math.sin(a) * v)  # 1 % per pitch
        dev = local_deviations([ramp], [""], packing="hex")[0]
        # (lenses 3 or more in: nearer the edge the outermost lenses are left out of the window, on
        # either lattice, and its median moves with what is left)
        assert np.abs(dev[3:-3, 3:-3]).max() <= 0.33 * 0.01, deg
        assert np.abs(dev[3:-3, 3:-3]).max() < 1e-12 or deg % 30, deg  # exact along the lattice's lines


def test_hex_edge_columns_compare_the_lenses_sticking_out_with_each_other():
    """On hex the first column's lenses of odd rows m (0-based even) stick out and miss 3 neighbours,
    the others miss 1: given a bias of their own, each is judged against its own kind."""
    rows, cols = 28, 24
    rng = np.random.default_rng(5)
    vals = 1e-4 * rng.standard_normal((rows, cols))
    vals[0::2, 0] += 0.05  # the unshifted rows' first lenses stick out on the left
    vals[1::2, -1] += 0.05  # the shifted rows' last lenses stick out on the right
    dev = local_deviations([vals], [""], packing="hex")[0]
    assert np.abs(dev[1:-1, [0, -1]]).max() < 1e-3
    # a square array's edge line mixes them (what the hex path avoids)
    sq = local_deviations([vals], [""])[0]
    assert np.abs(sq[1:-1, [0, -1]]).max() > 0.02


def test_square_local_deviation_is_unchanged_by_the_packing_argument():
    rng = np.random.default_rng(6)
    vals = rng.standard_normal((20, 20))
    assert np.array_equal(local_deviations([vals], ["x"])[0], local_deviations([vals], ["x"], packing="square")[0])


# --- the signature patch and the reference's cells -----------------------------------------------------

def test_hex_patch_holds_the_centre_lens_two_rings_and_fits_its_sensor():
    patch = patch_config(HEX)
    rows, cols = patch.mla.count_h, patch.mla.count_w
    assert patch.mla.packing == "hex" and cols == 9 and rows == 11
    r, c = patch_centre(patch)
    u0, v0 = centre_uv(r, c)
    # every lattice site within 4 pitches of the centre lens is a lens of the patch
    for rr in range(r - 6, r + 7):
        for cc in range(c - 6, c + 7):
            u, v = centre_uv(rr, cc)
            if math.hypot(u - u0, v - v0) <= 4.0 + 1e-9:
                assert 0 <= rr < rows and 0 <= cc < cols, (rr, cc)
    # the sensor holds every cell with 8 px to spare, and no more than a few px beyond
    p = HEX.layout.subimage_pitch_px
    need_w, need_h = (cols + 0.5) * p, ((rows - 1) * S3 + 2 / math.sqrt(3)) * p
    assert need_w + 16 <= patch.sensor.width_px <= need_w + 18
    assert need_h + 16 <= patch.sensor.height_px <= need_h + 18
    assert patch_config(SQUARE).sensor.width_px == patch_config(SQUARE).sensor.height_px == 198  # as before


def test_hex_nominal_windows_sit_on_the_conventions_centres():
    patch = patch_config(HEX)
    h, w = patch.sensor.height_px, patch.sensor.width_px
    img = np.zeros((h, w), np.float32)
    rows, cols = patch.mla.count_h, patch.mla.count_w
    p = HEX.layout.subimage_pitch_px
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    u, v = centre_uv(r, c)
    x = (w - 1) / 2 + (u - (cols - 0.5) / 2) * p  # the bounding box of the centres is centred
    y = (h - 1) / 2 + (v - (rows - 1) * S3 / 2) * p
    _, cx, cy = nominal_windows(img, patch)
    # window origin + centre in window = frame position
    win_x0 = np.floor(x - 10 + 0.5)
    win_y0 = np.floor(y - 10 + 0.5)
    assert np.allclose(cx + win_x0, x) and np.allclose(cy + win_y0, y)


def test_hex_patch_errors_sit_on_the_centre_lens_of_a_hex_map():
    maps = patch_errors(packing="hex")
    assert all(m.packing == "hex" and m.shape == (11, 9) for m in maps)
    assert not maps[0].defective().any()
    assert all(np.argwhere(m.defective()).tolist() == [[5, 4]] for m in maps[1:])


def test_hex_models_have_their_own_keys():
    assert signature_key(HEX) != signature_key(SQUARE)
    from mlaqc.models.reference import config_key

    assert config_key(HEX) != config_key(SQUARE)


def test_hex_cell_sums_of_an_even_field_are_the_cells_area():
    """Each pixel goes to the hexagon it lies in: on a uniform frame an inner lens collects its cell's
    area, pitch^2 sqrt(3)/2 px^2, to within one column of pixels along its outline (its height, 2 p /
    sqrt(3)); on average over the cells to the pixels' sampling alone."""
    img = np.ones((HEX.sensor.height_px, HEX.sensor.width_px))
    sums, (y, x), inner = _lattice_cell_sums(img, HEX)
    p = HEX.layout.subimage_pitch_px
    area = p * p * S3
    assert sums.shape == (28, 24) and inner.sum() == 26 * 22
    assert np.all(np.abs(sums[inner] - area) < 2 * p / math.sqrt(3))
    assert abs(sums[inner].mean() / area - 1) < 2e-3
    assert np.abs(x).max() <= 0.5 and np.abs(y).max() <= 0.5  # scaled by the array's outline


# --- bad input ----------------------------------------------------------------------------------------

def test_a_grid_on_another_lattice_is_refused_in_one_sentence():
    from types import SimpleNamespace

    from mlaqc.inspection.pipeline import inspect_image

    img = np.zeros((HEX.sensor.height_px, HEX.sensor.width_px), np.float32)
    grid = SimpleNamespace(packing="square")
    with pytest.raises(InputError, match="square lattice but the camera's MLA is hex"):
        inspect_image(img, HEX, grid=grid, model=object(), table=object())


def test_inspect_with_a_grid_file_of_another_lattice_exits_2_writing_nothing(tmp_path, capsys):
    """A square array's grid.json given to a hex camera of the same lens count: one sentence, exit 2."""
    from mlaqc.cli import main
    from mlaqc.inspection.calibrate import calibrate_for
    from mlaqc.optics.render import Renderer
    from mlaqc.optics.scene import WhiteScene

    img = Renderer(SQUARE).render(WhiteScene(), rays_per_pixel=10, seed=1).photons
    calibrate_for((img / img.max()).astype(np.float32), SQUARE).save(tmp_path / "grid.json")
    hex24 = tmp_path / "hex24.toml"
    hex24.write_text('[mla]\npacking = "hex"\ncount_w = 24\ncount_h = 24\n[sensor]\nwidth_px = 496\nheight_px = 496\n')
    raw = tmp_path / "white.npy"
    np.save(raw, (3000 * img / img.max()).astype(np.uint16))
    out = tmp_path / "rep"
    capsys.readouterr()  # (a first render's one-time compile note is not the command's)
    code = main(["inspect", str(raw), "-c", str(hex24), "-g", str(tmp_path / "grid.json"), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and err.count("\n") == 1
    assert "square lattice but the camera's MLA is hex" in err
    assert not out.exists() or not any(out.iterdir())


# --- the whole chain on a ray-traced hex frame -----------------------------------------------------------

SEEDED = {(10, 8): ("pitch", 3.0, 0.0), (15, 15): ("decenter", 10.0, 60.0), (20, 6): ("radius", -0.15, 0.0),
          (7, 18): ("radius", 0.15, 0.0), (23, 21): ("pitch", 3.0, 120.0)}


def traced_hex_result(seeded: dict, rays_per_pixel: float, seed: int):
    """The inspection of a ray-traced small hex camera frame with `seeded` {(m, n): (kind, size, direction)}."""
    from mlaqc.inspection.pipeline import inspect_image, prepare
    from mlaqc.inspection.rawio import RawFrame
    from mlaqc.optics.errormap import ErrorMap, lens_error_fields
    from mlaqc.optics.sensor import white_level
    from mlaqc.optics.simulate import simulate

    em = ErrorMap.zeros(HEX.mla.count_h, HEX.mla.count_w, "hex")
    for (m, n), (kind, mag, d) in seeded.items():
        em = em.with_lens(m, n, **lens_error_fields(kind, mag, d))
    sim = simulate(HEX, None, em, rays_per_pixel=rays_per_pixel, seed=seed)
    s = HEX.sensor
    frame = RawFrame(sim.raw, s.bit_depth, None, s.black_level_dn, white_level(s), {}, "hex")
    return inspect_image(prepare(frame), HEX)


@pytest.fixture(scope="module")
def hex_result():
    return traced_hex_result(SEEDED, 50, 11)


def test_a_hex_frame_finds_the_seeded_lenses_by_their_u_m_n_and_nothing_else(hex_result):
    found = {(d.m, d.n): d for d in hex_result.defects}
    assert set(found) == set(SEEDED)
    assert hex_result.grid.packing == "hex" and hex_result.lattice.hex
    for key, (kind, mag, _) in SEEDED.items():
        d = found[key]
        ok = d.error_type == kind or (d.error_type == "position" and kind in ("pitch", "decenter"))
        assert ok, (key, d.error_type)
        read = {a[0]: a[1] for a in d.alternatives}[kind] if d.error_type == "position" else d.magnitude
        assert abs(read - mag) <= 0.35 * abs(mag), (key, read)
        if d.direction_deg is not None:  # (within 25 deg: the registration's gain is lower along y on hex)
            assert abs((d.direction_deg - SEEDED[key][2] + 180.0) % 360.0 - 180.0) < 25.0, (key, d.direction_deg)
    assert hex_result.lattice_facts()["packing"] == "hex"
    assert hex_result.lattice_facts()["convention"].startswith("U(m,n)")


def test_a_hex_frame_measures_every_lens_and_states_what_it_detects(hex_result):
    meas = hex_result.measurements
    assert meas["centre_dx_um"].shape == (28, 24)
    healthy = np.ones((28, 24), bool)
    for m, n in SEEDED:
        healthy[m - 1, n - 1] = False
    # a 3 µm pitch error moves its lens' optical centre by 3 µm; healthy lenses scatter far less
    dx, dy = meas["centre_dx_um"], meas["centre_dy_um"]
    assert math.hypot(dx[9, 7], dy[9, 7]) == pytest.approx(3.0, rel=0.35)
    assert np.nanmedian(np.hypot(dx, dy)[healthy]) < 0.5
    assert hex_result.detection_limit["pitch_um"] is not None


def test_a_perfect_hex_array_reads_no_placement_error():
    """The projection fit's design centres are the hex lattice's: a perfect array's frame reads no shift
    or rotation, and its centres fit to the calibration's own noise (the square formula would leave
    every other row half a pitch off)."""
    from mlaqc.inspection.calibrate import calibrate_for
    from mlaqc.inspection.projection import fit_projection, pupil_distance_mm
    from mlaqc.optics.render import Renderer
    from mlaqc.optics.scene import WhiteScene

    img = Renderer(HEX).render(WhiteScene(), rays_per_pixel=30, seed=2).photons
    grid = calibrate_for((img / img.max()).astype(np.float32), HEX)
    params, cov, used, rms = fit_projection(grid, HEX, pupil_distance_mm(HEX))
    sigma = np.sqrt(np.diag(cov))
    assert used == 28 * 24 and rms < 0.05
    assert abs(params[1]) < 4 * sigma[1] + 1e-3  # rotation, deg
    assert abs(params[4]) < 0.05 and abs(params[5]) < 0.05  # shifts, µm
    assert abs(params[0]) < 4 * sigma[0] + 1.0  # sensor distance, µm


def test_circular_apertures_cannot_tell_pitch_from_decenter():
    """Each circle is centred on its own front vertex: no boundary is shared, no neighbour sees either."""
    import dataclasses

    from mlaqc.models.position_split import position_split

    circ = dataclasses.replace(HEX, mla=dataclasses.replace(HEX.mla, aperture="circle", aperture_diameter_um=90.0))
    assert position_split(circ) is None


def test_a_hex_frame_inspected_with_a_square_config_exits_2_writing_nothing(tmp_path, capsys):
    """The calibration finds the frame's lattice is not the config's: one sentence naming both, exit 2."""
    from mlaqc.cli import main
    from mlaqc.optics.errormap import ErrorMap
    from mlaqc.optics.simulate import simulate, write_simulation

    raw = tmp_path / "hex.dng"
    write_simulation(raw, simulate(HEX, None, ErrorMap.zeros(28, 24, "hex"), rays_per_pixel=20, seed=3), HEX)
    out = tmp_path / "rep"
    capsys.readouterr()
    code = main(["inspect", str(raw), "-c", str(FIXTURES / "small_camera.toml"), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and err.count("\n") == 1, err
    assert "hexagonal microlens lattice" in err and "'square'" in err
    assert not out.exists() or not any(out.iterdir())


def test_hex_edge_classes_are_the_steps_off_the_array():
    """`edge_classes` (min of the row and column distances to the edge) is, on hex too, the number of
    neighbour steps from a lens to the nearest site off the array, less one (breadth-first search over
    the lattice's own neighbours, clipped at 2)."""
    from mlaqc.inspection.lens_classes import edge_classes
    from mlaqc.optics.lattice import Lattice

    rows, cols = 13, 11
    nbr = Lattice("hex", rows, cols).neighbours()
    dist = np.full(rows * cols, -1)
    frontier = np.flatnonzero((nbr < 0).any(axis=1))  # one step from a site off the array
    dist[frontier] = 0
    d = 0
    while frontier.size:
        d += 1
        nxt = np.unique(nbr[frontier][nbr[frontier] >= 0])
        frontier = nxt[dist[nxt] < 0]
        dist[frontier] = d
    assert np.array_equal(np.minimum(dist, 2).reshape(rows, cols), edge_classes((rows, cols)))
