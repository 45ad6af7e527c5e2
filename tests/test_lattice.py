"""The lattice (mlaqc.optics.lattice): lens centres, the cell a point lies in, neighbours and the cell
outline for square and hex packing, against brute force and plane geometry; and the config, error-map and
model-key rules that come with the packing."""

import json
import math

import numpy as np
import pytest

from mlaqc.errors import InputError
from mlaqc.models.reference import config_key
from mlaqc.optics.config import config_from_dict, load_config
from mlaqc.optics.errormap import ErrorMap, error_map_from_dict, load_error_map, random_defects
from mlaqc.optics.lattice import SQRT3_2, Lattice, cell_vertices, hex_cell, neighbour_offsets

FIXTURES = "fixtures"


def test_square_centres_are_the_old_grid():
    lat = Lattice("square", 4, 6, 0.1)
    x, y = lat.centres()
    r, c = np.meshgrid(np.arange(4), np.arange(6), indexing="ij")
    assert np.allclose(x, (c + 0.5) * 0.1 - 0.5 * 6 * 0.1) and np.allclose(y, (r + 0.5) * 0.1 - 0.5 * 4 * 0.1)


def test_hex_convention_even_rows_shifted_half_a_pitch():
    lat = Lattice("hex", 4, 5, 2.0)
    x, y = lat.centres()
    assert np.allclose(x[1] - x[0], 1.0) and np.allclose(x[2], x[0]) and np.allclose(x[3], x[1])  # m = 2, 4 shifted
    assert np.allclose(np.diff(y[:, 0]), 2.0 * math.sqrt(3) / 2)
    assert abs(x.min() + x.max()) < 1e-12 and abs(y.min() + y.max()) < 1e-12  # centred on the array


@pytest.mark.parametrize("packing", ["square", "hex"])
def test_nearest_is_the_voronoi_cell(packing):
    lat = Lattice(packing, 7, 6, 1.3)
    rng = np.random.default_rng(1)
    px, py = rng.uniform(-6, 6, 20000), rng.uniform(-6, 6, 20000)
    rr, cc = np.meshgrid(np.arange(-2, 9), np.arange(-2, 8), indexing="ij")
    gx, gy = lat.position(rr.ravel(), cc.ravel())
    k = np.argmin((px[:, None] - gx) ** 2 + (py[:, None] - gy) ** 2, axis=1)
    r, c, inside = lat.nearest(px, py)
    assert np.array_equal(r, rr.ravel()[k]) and np.array_equal(c, cc.ravel()[k])
    assert np.array_equal(inside, (r >= 0) & (r < 7) & (c >= 0) & (c < 6))


def test_hex_cell_offsets_and_ties():
    """hex_cell's offset is the point minus its lens' centre, on both row parities and far from U(1,1), and
    no neighbour's centre is nearer; a point equidistant (exactly, in floating point) from an even-row and
    an odd-row lens goes to the even row."""
    rng = np.random.default_rng(3)
    u, v = rng.uniform(-500, 500, 100000), rng.uniform(-500, 500, 100000)
    r, c, du, dv = hex_cell(u, v)
    assert np.allclose(u - du, c + 0.5 * (r % 2), atol=1e-9) and np.allclose(v - dv, r * SQRT3_2, atol=1e-9)
    d0 = du * du + dv * dv
    for a, b in [(1, 0), (-1, 0), (0.5, SQRT3_2), (-0.5, SQRT3_2), (0.5, -SQRT3_2), (-0.5, -SQRT3_2)]:
        assert np.all((du - a) ** 2 + (dv - b) ** 2 >= d0 - 1e-12)
    r, c, _, _ = hex_cell(np.array([0.25, 1.25]), np.array([0.5 * SQRT3_2, 2.5 * SQRT3_2]))
    assert np.array_equal(r, [0.0, 2.0]) and np.array_equal(c, [0.0, 1.0])  # ties: rows 0 / 1 and 2 / 1


@pytest.mark.parametrize("packing, count", [("square", 8), ("hex", 6)])
def test_neighbours_are_the_lenses_one_pitch_away(packing, count):
    lat = Lattice(packing, 6, 7, 1.0)
    x, y = (a.ravel() for a in lat.centres())
    nb = lat.neighbours()
    assert nb.shape == (42, count)
    d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
    for k in range(42):  # brute force: every lens within 1 pitch (square: within sqrt 2) and no other
        reach = 1.0 + 1e-9 if packing == "hex" else math.sqrt(2) + 1e-9
        expect = set(np.flatnonzero((d[k] > 0) & (d[k] <= reach)))
        assert set(nb[k][nb[k] >= 0]) == expect
    if packing == "hex":  # the six vectors of an inner lens sum to zero and are 60 degrees apart
        k = 2 * 7 + 3
        v = np.stack([x[nb[k]] - x[k], y[nb[k]] - y[k]], 1)
        assert np.allclose(v.sum(0), 0) and np.allclose(np.sort(np.degrees(np.arctan2(v[:, 1], v[:, 0])) % 360),
                                                        [0, 60, 120, 180, 240, 300])
    assert neighbour_offsets("square", 0, diagonal=False) == [(0, -1), (0, 1), (-1, 0), (1, 0)]


@pytest.mark.parametrize("packing", ["square", "hex"])
def test_cell_outline_has_the_cell_area_and_tiles(packing):
    v = cell_vertices(packing)
    area = 0.5 * abs(np.dot(v[:, 0], np.roll(v[:, 1], -1)) - np.dot(v[:, 1], np.roll(v[:, 0], -1)))
    lat = Lattice(packing, 3, 3, 1.0)
    assert area == pytest.approx(lat.cell_area)
    # a point just inside an outline vertex is in the centre lens' cell, just outside it is not
    centre = lat.position(1, 1)
    for vx, vy in v:
        r, c, _ = lat.nearest(centre[0] + 0.99 * vx, centre[1] + 0.99 * vy)
        assert (int(r), int(c)) == (1, 1)
        r, c, _ = lat.nearest(centre[0] + 1.01 * vx, centre[1] + 1.01 * vy)
        assert (int(r), int(c)) != (1, 1)


def test_hex_extent_and_config_sensor_fit():
    lat = Lattice("hex", 116, 102, 100.0)
    assert lat.extent == pytest.approx((102.5 * 100, (115 * math.sqrt(3) / 2 + 2 / math.sqrt(3)) * 100))
    cfg = load_config(f"{FIXTURES}/hex_camera.toml")
    assert cfg.mla.packing == "hex" and (cfg.mla.count_h, cfg.mla.count_w) == (116, 102)
    with pytest.raises(InputError, match="mla.count_h.*hex MLA.*taller than the sensor"):
        config_from_dict({"mla": {"packing": "hex", "count_h": 119}})


@pytest.mark.parametrize("mla, key", [
    ({"packing": "hexagonal"}, "mla.packing"),
    ({"aperture": "round"}, "mla.aperture"),
    ({"aperture": "circle"}, "mla.aperture_diameter_um"),
    ({"aperture": "circle", "aperture_diameter_um": 120.0}, "mla.aperture_diameter_um"),
    ({"aperture_diameter_um": 90.0}, "mla.aperture_diameter_um"),
    ({"aperture": "circle", "aperture_diameter_um": 90.0, "gap": "glass"}, "mla.gap"),
    ({"packing": "hex", "radius_front_um": 55.0}, "mla.radius_front_um"),
])
def test_packing_and_aperture_keys_are_validated(mla, key):
    with pytest.raises(InputError, match=key.replace(".", r"\.")):
        config_from_dict({"mla": mla})


def test_circle_fixture_and_model_keys():
    circle = load_config(f"{FIXTURES}/hex_circle_camera.toml")
    assert circle.mla.aperture == "circle" and circle.mla.aperture_diameter_um == 90.0
    square = load_config(f"{FIXTURES}/paper_table1.toml")
    hexa = load_config(f"{FIXTURES}/hex_camera.toml")
    # the square, cell-filling default keeps the key of the tables shipped before these keys existed
    assert config_key(square) == "ce27af037735c6e4"
    assert len({config_key(square), config_key(hexa), config_key(circle)}) == 3


def test_error_maps_record_and_check_their_lattice(tmp_path):
    em = random_defects(28, 24, 5, seed=3, packing="hex")
    assert em.packing == "hex" and em.with_lens(1, 1, pitch_um=1).packing == "hex"
    path = tmp_path / "hex.json"
    em.save(path)
    assert json.loads(path.read_text())["packing"] == "hex"
    back = load_error_map(path, (28, 24), "hex")
    assert back.packing == "hex" and np.array_equal(back.lens["pitch_um"], em.lens["pitch_um"])
    with pytest.raises(InputError, match="hex lattice but the camera's MLA is square"):
        load_error_map(path, (28, 24), "square")
    old = ErrorMap.zeros(5, 5).to_json_dict()
    del old["packing"]  # a map written before hex support: square
    assert error_map_from_dict(old, "old.json", (5, 5), "square").packing == "square"
    with pytest.raises(InputError, match="packing"):
        error_map_from_dict({**old, "packing": "triangular"}, "bad.json")
