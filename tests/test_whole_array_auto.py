"""count_w = count_h = "auto" on a frame that holds the whole array, dark margins on every side (an array
smaller than the sensor, a user who did not count its lenses): the lenses are counted from the frame and the
array is inspected as with those counts given — U(1,1) its corner, its edge lenses judged as edges, the same
flags — on frames of the independent analytic model (tests/analytic_frames.py), square and hex."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import analytic_frames as am
from mlaqc.inspection.array_extent import whole_array_counts
from mlaqc.inspection.pipeline import inspect_file
from mlaqc.optics.config import config_from_dict, load_config

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
UM_TO_PX = (am.TABLE1_B_MM + am.TABLE1_F_MM) / am.TABLE1_B_MM / am.TABLE1_PIXEL_UM  # a pitch error's shift


def cameras(fixture: str, rows: int, cols: int, margin_lenses: float = 3.0):
    """(counts given, counts "auto") of a fixture's optics: `rows` x `cols` lenses in a sensor that leaves
    `margin_lenses` pitches dark on every side."""
    cfg = load_config(FIXTURES / fixture)
    p = cfg.layout.subimage_pitch_px
    w = (cols + 0.5 + 2 * margin_lenses) * p
    h = ((rows - 1) * (math.sqrt(3.0) / 2 if cfg.mla.packing == "hex" else 1.0) + 1 + 2 * margin_lenses) * p
    given = dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, count_w=cols, count_h=rows),
                                sensor=dataclasses.replace(cfg.sensor, width_px=16 * math.ceil(w / 16),
                                                           height_px=16 * math.ceil(h / 16)))
    d = json.loads(json.dumps(given.to_dict()))
    d["mla"]["count_w"] = d["mla"]["count_h"] = "auto"
    return given, config_from_dict(d)


def inspect(cfg, model, tmp: Path, name: str, noise: float = 0.01):
    counts = am.to_counts(am.expose(model.render(), noise, np.random.default_rng(3)), 12)
    return inspect_file(am.write_container(tmp / f"{name}.tif", counts, 12, 0), cfg)


@pytest.mark.parametrize("fixture,rows,cols", [("small_camera.toml", 12, 14), ("hex_small_camera.toml", 14, 12)])
def test_auto_counts_on_a_whole_array_inspect_it_as_that_array(tmp_path, fixture, rows, cols):
    given, auto = cameras(fixture, rows, cols)
    assert (auto.mla.count_h, auto.mla.count_w) != (rows, cols)  # "auto" alone lays a larger lattice
    model = am.AnalyticModel(shape=(given.sensor.height_px, given.sensor.width_px), lenses=(rows, cols),
                             pitch_px=given.layout.subimage_pitch_px, packing=given.mla.packing, phase_px=(0.3, -0.2))
    healthy = inspect(auto, model, tmp_path, "healthy")
    assert healthy.grid.shape == (rows, cols) and healthy.defects == ()
    assert any(f"{cols} x {rows} lenses with dark margins" in n and "U(1,1) is the array's top-left lens" in n for n in healthy.notes)
    assert not any("relative to the frame" in n for n in healthy.notes)
    # shifts of 3 µm (clear of every limit these frames state) on an inner lens, an edge lens and the
    # second ring: reported at the array's own indexes, as with the counts given
    seeded = {(5, 6): 30.0, (0, 4): 120.0, (rows - 2, cols - 2): 250.0, (6, 0): 300.0}
    flawed = model.with_anomalies(am.Anomaly(m, n, "shift", 3.0 * UM_TO_PX, a) for (m, n), a in seeded.items())
    by_auto, by_given = inspect(auto, flawed, tmp_path, "auto"), inspect(given, flawed, tmp_path, "given")
    flags = {(d.m - 1, d.n - 1): d.error_type for d in by_auto.defects}
    assert flags == {(d.m - 1, d.n - 1): d.error_type for d in by_given.defects}
    assert set(flags) == set(seeded), sorted(flags)


def _grid(missing: np.ndarray, pitch: float = 20.0, margin_px: float = 20.0, packing: str = "square"):
    """A grid-like record of a lattice `pitch` px apart whose lit (not missing) lenses' box starts
    `margin_px` inside a frame that ends `margin_px` past it."""
    rows, cols = missing.shape
    lit_r, lit_c = np.flatnonzero((~missing).any(axis=1)), np.flatnonzero((~missing).any(axis=0))
    step_y = pitch * (math.sqrt(3.0) / 2 if packing == "hex" else 1.0)
    m, n = np.mgrid[0:rows, 0:cols]
    x, y = margin_px + (n - lit_c[0]) * pitch, margin_px + (m - lit_r[0]) * step_y
    shape = (int(np.ceil(y[lit_r[-1], 0] + margin_px)) + 1, int(np.ceil(x[0, lit_c[-1]] + margin_px)) + 1)
    return SimpleNamespace(missing=missing, grid_x_px=x, grid_y_px=y, pitch_px=(pitch, pitch), packing=packing,
                           image_shape=shape)


def test_only_an_array_wholly_in_view_is_counted():
    lit = np.ones((10, 12), bool)
    lit[2:8, 1:11] = False  # 6 x 10 lenses
    assert whole_array_counts(_grid(lit)) == (6, 10)
    hexed = lit.copy()
    hexed[3:8:2, 1] = True  # hex: alternate rows one column on (offset columns)
    hexed[3:8:2, 11] = False
    assert whole_array_counts(_grid(hexed, packing="hex")) == (6, 10)
    # the lattice place beyond an edge not in view (a lens centre closer to the frame's edge than a pitch):
    # the array may run on past the frame
    assert whole_array_counts(_grid(lit, margin_px=19.0)) is None
    assert whole_array_counts(_grid(hexed, margin_px=0.8 * 20 * math.sqrt(3.0) / 2, packing="hex")) is None
    field_stop = lit.copy()
    field_stop[2, 1] = field_stop[2, 10] = True  # a round field of view: the box's corners dark
    assert whole_array_counts(_grid(field_stop)) == (6, 10)  # 2 of 60 places dark: one array, 2 lenses missing ...
    field_stop[2, 2] = field_stop[7, 1] = field_stop[7, 10] = True
    assert whole_array_counts(_grid(field_stop)) is None  # ... 5 of 60 (8 %): a field stop, not one array


def test_a_saved_or_white_frame_grid_counts_the_whole_array_too(tmp_path, capsys):
    """`mlaqc calibrate` writes the whole array's grid for an "auto" config, and `inspect --grid` and
    `inspect --white` inspect with it as a self-calibrated frame does: the same lenses, the same note."""
    from mlaqc.cli import main
    from mlaqc.optics.config import config_to_toml

    given, auto = cameras("small_camera.toml", 12, 14)
    model = am.AnalyticModel(shape=(given.sensor.height_px, given.sensor.width_px), lenses=(12, 14),
                             pitch_px=given.layout.subimage_pitch_px, phase_px=(0.3, -0.2))
    counts = am.to_counts(am.expose(model.render(), 0.01, np.random.default_rng(3)), 12)
    white = am.write_container(tmp_path / "white.tif", counts, 12, 0)
    config = tmp_path / "auto.toml"
    config.write_text(config_to_toml(auto))
    assert main(["calibrate", str(white), "-c", str(config), "-o", str(tmp_path / "grid.json"), "-q"]) == 0
    assert json.loads((tmp_path / "grid.json").read_text())["shape"] == {"rows": 12, "cols": 14}
    for how in (["--grid", str(tmp_path / "grid.json")], ["--white", str(white)]):
        out = tmp_path / how[0].strip("-")
        assert main(["inspect", str(white), "-c", str(config), *how, "-o", str(out), "--no-db"]) == 0
        report = json.loads((out / "report.json").read_text())
        assert (report["summary"]["rows"], report["summary"]["cols"], report["summary"]["flagged"]) == (12, 14, 0)
        assert any("14 x 12 lenses with dark margins" in n for n in report["notes"])


def test_a_white_frame_path_counts_the_array_too(tmp_path):
    """inspect_file with a white frame (the app's path: it calibrates on the white, then inspects) counts
    the array as the self-calibrated path does."""
    given, auto = cameras("small_camera.toml", 12, 14)
    shape = (given.sensor.height_px, given.sensor.width_px)
    model = am.AnalyticModel(shape=shape, lenses=(12, 14), pitch_px=given.layout.subimage_pitch_px, phase_px=(0.3, -0.2))
    counts = am.to_counts(am.expose(model.render(), 0.01, np.random.default_rng(3)), 12)
    white = am.write_container(tmp_path / "white.tif", counts, 12, 0)
    result = inspect_file(white, auto, white=white)
    assert result.grid.shape == (12, 14) and result.defects == ()
    assert any("the grid given holds the whole array" in n for n in result.notes)


@pytest.mark.parametrize("fixture,rows,cols", [("small_camera.toml", 12, 14), ("hex_small_camera.toml", 14, 12)])
def test_a_frame_showing_some_of_the_arrays_edges_judges_them_as_edges(tmp_path, fixture, rows, cols):
    """The array runs off the frame on one side and shows its other edges with dark places beyond: the
    lattice is cut at the edges seen, so no dark place is flagged 'missing' and the edge lenses are judged
    as edges; with its top-left corner in view U(m,n) are the array's own (the same flags as a frame holding
    it whole), and otherwise relative to the frame. Before: 47 'missing' flags on the hex frame, and the
    square one refused as not a flat field (its edge lenses, lacking a neighbour's light, read as a scene)."""
    given, auto = cameras(fixture, rows, cols)  # (the frames of the whole-array test: their models cached)
    p = given.layout.subimage_pitch_px
    seeded = {(5, 6): 30.0, (0, 4): 120.0, (rows - 1, 5): 250.0, (6, 0): 300.0}  # top, bottom, left edges
    shape = (given.sensor.height_px, given.sensor.width_px)
    whole = am.AnalyticModel(shape=shape, lenses=(rows, cols), pitch_px=p, packing=given.mla.packing,
                             phase_px=(0.3, -0.2)).with_anomalies(
        am.Anomaly(m, n, "shift", 3.0 * UM_TO_PX, a) for (m, n), a in seeded.items())
    by_whole = {(d.m - 1, d.n - 1): d.error_type for d in inspect(given, whole, tmp_path, "whole").defects}
    assert set(by_whole) == set(seeded)
    runs_off = dataclasses.replace(whole, phase_px=(4.5 * p + 0.3, -0.2))  # a lens and a half off the right
    part = inspect(auto, runs_off, tmp_path, "right")
    assert {(d.m - 1, d.n - 1): d.error_type for d in part.defects} == by_whole
    assert any("shows the array's top, bottom, left edges" in n and "U(1,1) is the array's top-left lens" in n
               for n in part.notes)
    healthy = dataclasses.replace(runs_off, anomalies=(), phase_px=(-4.5 * p + 0.3, -0.2))  # off the left
    left_cut = inspect(auto, healthy, tmp_path, "left")
    assert left_cut.defects == () and left_cut.grid.rows == rows
    assert any("U(1,1) is the top-left lens the frame shows, not the array's corner" in n for n in left_cut.notes)


def test_a_round_field_or_a_hex_array_off_the_top_is_refused_not_cut(tmp_path):
    """The lattice is cut only to a box its lit lenses fill: a whole array seen through a round field stop
    (its box's corners dark) is refused in one sentence asking for the counts, as before; so is a hex array
    running off the frame's top (its top row in view may be a shifted one, which a box cannot hold)."""
    from mlaqc.errors import InputError

    given, auto = cameras("small_camera.toml", 16, 18)
    shape = (given.sensor.height_px, given.sensor.width_px)
    model = am.AnalyticModel(shape=shape, lenses=(16, 18), pitch_px=given.layout.subimage_pitch_px, phase_px=(0.3, -0.2))
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    field = np.hypot(yy - shape[0] / 2, xx - shape[1] / 2) < 0.42 * min(shape)  # cuts the array's corners
    counts = am.to_counts(am.expose(model.render() * field, 0.01, np.random.default_rng(3)), 12)
    with pytest.raises(InputError, match="not one whole array with dark margins on every side: give the array's counts"):
        inspect_file(am.write_container(tmp_path / "field.tif", counts, 12, 0), auto)
    given, auto = cameras("hex_small_camera.toml", 18, 16, margin_lenses=1.5)
    p = given.layout.subimage_pitch_px
    off_top = am.AnalyticModel(shape=(given.sensor.height_px, given.sensor.width_px), lenses=(18, 16), pitch_px=p,
                               packing="hex", phase_px=(0.3, -3 * p * math.sqrt(3.0) / 2 - 0.2))
    with pytest.raises(InputError, match="give the array's counts"):
        inspect(auto, off_top, tmp_path, "off_top")


def test_through_focus_needs_the_counts_of_a_cut_array():
    """Through-focus frames are read where each lens sits on the MLA: a whole counted array gives it, a
    lattice cut to part of the array does not (one sentence asking for the counts)."""
    from mlaqc.errors import InputError
    from mlaqc.inspection.array_extent import through_focus_config

    _, auto = cameras("small_camera.toml", 6, 10)

    def grid_of(missing):
        g = _grid(missing)
        g.shape, g.rows, g.cols = missing.shape, *missing.shape
        return g

    lattice = np.zeros((auto.mla.count_h, auto.mla.count_w), bool)
    lattice[0, 0] = True  # the sensor-wide lattice itself (a lens dark somewhere): unchanged
    assert through_focus_config(auto, grid_of(lattice)) is auto
    whole = np.zeros((6, 10), bool)  # a grid fitted to a whole array (every lens lit, margins beyond)
    assert not through_focus_config(auto, grid_of(whole)).mla.counts_auto
    cut = whole.copy()
    cut[:, 0] = True  # its first column dark: a box of part of the array, not the whole
    with pytest.raises(InputError, match="set mla.count_w / count_h to the array's counts"):
        through_focus_config(auto, grid_of(cut))
