"""Through-focus pinhole frames on a hex array (issue #22): the pinhole lattice, its coverage and the mask's
axes checked against hex geometry computed here from Lattice positions; rendered frames whose spots land
where the chief ray says; seeded focal errors read with their sign and size on the small hex camera; a
hex / square mismatch refused in one sentence."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from analytic_frames import AnalyticModel
from mlaqc.cli import main
from mlaqc.errors import InputError
from mlaqc.inspection.calibrate import calibrate
from mlaqc.inspection.rawio import RawFrame
from mlaqc.inspection.throughfocus import measure_through_focus
from mlaqc.inspection.throughfocus_geometry import coverage
from mlaqc.inspection.throughfocus_model import model_key
from mlaqc.inspection.throughfocus_optics import aperture_moment_mm2, focal_rel_of_radius
from mlaqc.inspection.throughfocus_spots import prepare_spots
from mlaqc.models.store import PACKAGE_DATA
from mlaqc.optics import throughfocus as tfm
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.formation import apply_formation
from mlaqc.optics.lattice import Lattice
from mlaqc.optics.render import Renderer
from mlaqc.optics.sensor import expose, white_level
from mlaqc.optics.throughfocus import F_NUMBER, FOCUS_OFFSET_MM, SPACING_LENSES, Carrier, ThroughFocus

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
HEX = load_config(FIXTURES / "hex_small_camera.toml")  # Table 1 optics, hex 24 columns x 28 rows, 496 x 496 px
HEX_T1 = load_config(FIXTURES / "hex_camera.toml")  # 102 x 116
SQUARE = load_config(FIXTURES / "small_camera.toml")
ROWS, COLS = 28, 24


def shipped(u: float = FOCUS_OFFSET_MM, offset: tuple[int, int] = (0, 0)) -> ThroughFocus:
    return ThroughFocus(u, F_NUMBER, SPACING_LENSES, offset)


def unit_positions(cfg):
    """Every lens' centre (x, y) in pitches, and the lattice that gave them."""
    lat = Lattice(cfg.mla.packing, cfg.mla.count_h, cfg.mla.count_w)
    x, y = lat.centres()
    return lat, x, y


# --------------------------------------------------------------------------------------------- geometry


def test_hex_pinholes_form_a_hex_lattice_s_pitches_apart_and_the_offsets_partition_the_array():
    """Each pinhole with a full ring on the array has exactly 6 pinholes at s pitches, 60 degrees apart, and
    none nearer; the s^2 offsets light every lens as a disc centre exactly once."""
    lat, x, y = unit_positions(HEX)
    s = SPACING_LENSES
    count = np.zeros((ROWS, COLS), int)
    for oq in range(s):
        for orow in range(s):
            pins = tfm.pinhole_lenses(HEX, shipped(offset=(oq, orow)))
            count[pins[:, 0], pins[:, 1]] += 1
            px, py = lat.position(pins[:, 0], pins[:, 1])
            d = np.hypot(px[:, None] - px[None], py[:, None] - py[None])
            np.fill_diagonal(d, np.inf)
            assert d.min() == pytest.approx(s, abs=1e-9)
            for i in range(len(pins)):
                ring = np.flatnonzero(np.abs(d[i] - s) < 1e-9)
                if len(ring) == 6:
                    ang = np.sort(np.degrees(np.arctan2(py[ring] - py[i], px[ring] - px[i])) % 360.0)
                    np.testing.assert_allclose(np.diff(ang), 60.0, atol=1e-9)
                assert len(ring) <= 6
    assert (count == 1).all()


@pytest.mark.parametrize("cfg", [HEX, HEX_T1], ids=["hex-small", "hex-table1"])
@pytest.mark.parametrize("u, f, s", [(5.0, 11.0, 4), (7.0, 8.0, 6), (10.0, 8.0, 9)])
def test_the_coverage_offsets_put_every_hex_lens_inside_a_lit_disc(cfg, u, f, s):
    """Every lens lies within the pair radius (the disc's inner radius less the rim margin, a hexagonal
    cell's corner 1/sqrt(3) pitch out) of a pinhole of some offset, distances from Lattice positions, and
    the analysis' own coverage reads every lens at those offsets."""
    tf = ThroughFocus(u, f, s)
    offsets = tfm.coverage_offsets(cfg, tf)
    r_in = tfm.pair_radius_lenses(cfg, tf)
    blur = min(tfm.blur_radius_mm(cfg, replace(tf, focus_offset_mm=v)) for v in (u, -u)) / (cfg.mla.pitch_um * 1e-3)
    assert r_in == pytest.approx(blur - 1.0 / math.sqrt(3.0) - tfm.RIM_MARGIN_LENSES)
    lat, x, y = unit_positions(cfg)
    best = np.full(x.shape, np.inf)
    read = np.zeros(x.shape, bool)
    for off in offsets:
        t = replace(tf, offset_lenses=off)
        pins = tfm.pinhole_lenses(cfg, t)
        px, py = lat.position(pins[:, 0], pins[:, 1])
        dmin = np.full(x.shape, np.inf)
        for k in range(0, len(px), 256):
            d = np.hypot(x[..., None] - px[k:k + 256], y[..., None] - py[k:k + 256])
            dmin = np.minimum(dmin, d.min(axis=-1))
        best = np.minimum(best, dmin)
        lit, near, dxy = coverage(cfg, t)
        read |= lit
        # the analysis' offsets are the lens' offset from its own pinhole, the nearest one
        np.testing.assert_allclose(dxy[..., 0], x - px[near], atol=1e-9)
        np.testing.assert_allclose(dxy[..., 1], y - py[near], atol=1e-9)
        np.testing.assert_allclose(np.hypot(dxy[..., 0], dxy[..., 1]), dmin, atol=1e-9)
    assert best.max() <= r_in + 1e-9 and read.all()
    if s == 4:  # the disc holds only the lens under its pinhole: all 16 offsets
        assert len(offsets) == 16


def test_hex_carrier_axes_move_the_mask_by_lattice_steps_and_the_view_inverts_them():
    """One axial step along a row moves the mask p / m along A; one along the 60-degree direction moves it
    p / 2m along A and sqrt(3) p / 2m along B (the image is inverted: minus signs); the mock's view of those
    axes is the same frame with no residual shift."""
    car = Carrier()
    p = HEX.mla.pitch_um * 1e-3
    for u in (5.0, -5.0):
        m = tfm.magnification(tfm.frame_config(HEX, shipped(u)))
        a0 = tfm.carrier_axes(HEX, car, shipped(u))
        a1 = tfm.carrier_axes(HEX, car, shipped(u, (1, 0)))
        a2 = tfm.carrier_axes(HEX, car, shipped(u, (0, 1)))
        assert (a1["a"] - a0["a"], a1["b"] - a0["b"]) == pytest.approx((-p / m, 0.0), abs=1e-12)
        assert (a2["a"] - a0["a"], a2["b"] - a0["b"]) == pytest.approx((-0.5 * p / m, -math.sqrt(0.75) * p / m), abs=1e-12)
        for off in [(q, r) for q in range(4) for r in range(4)]:
            tf = shipped(u, off)
            view = tfm.carrier_view(HEX, car, tfm.carrier_axes(HEX, car, tf), F_NUMBER)
            assert view.frame.offset_lenses == off and max(map(abs, view.residual_mm)) < 1e-9
            np.testing.assert_allclose(view.scene.points_mm, tfm.scene(HEX, tf).points_mm, atol=1e-9)


def test_the_hex_cells_aperture_moment_is_the_regular_hexagons():
    """A regular hexagon of side a has a per-axis second moment 5 a^2 / 24 (a = p / sqrt(3)); a circle of
    diameter d, d^2 / 16 (fixtures/hex_circle_camera.toml: 90 µm)."""
    a = HEX.mla.pitch_um / math.sqrt(3.0)
    assert aperture_moment_mm2(HEX) * 1e6 == pytest.approx(5.0 * a * a / 24.0, rel=5e-3)
    for name in ("hex_circle_camera.toml", "circle_camera.toml"):  # round lenses on hex and square arrays
        circle = load_config(FIXTURES / name)
        assert aperture_moment_mm2(circle) * 1e6 == pytest.approx(circle.mla.aperture_diameter_um ** 2 / 16.0, rel=5e-3)
    p = SQUARE.mla.pitch_um  # a square cell of side p: p^2 / 12, less its corners beyond the surfaces' crossing
    assert 0.99 * p * p / 12.0 < aperture_moment_mm2(SQUARE) * 1e6 < p * p / 12.0


def test_the_hex_and_round_lens_models_ship():
    """The shipped protocol's traced model of the hex and round-lens fixtures is package data (no build on
    first use)."""
    for cfg in (HEX, HEX_T1, *(load_config(FIXTURES / f"{n}.toml") for n in ("hex_circle_camera", "circle_camera"))):
        tf = shipped()
        key = model_key(cfg, FOCUS_OFFSET_MM, F_NUMBER, tfm.pair_radius_lenses(cfg, tf))
        assert (PACKAGE_DATA / f"throughfocus_{key}.npz").is_file()


# --------------------------------------------------------------------------------------------- frames


def test_simulated_hex_spots_land_where_the_chief_ray_says(tmp_path):
    """`mlaqc simulate --scene through-focus` on the hex camera: one spot per pinhole, each where the chief
    ray from the pinhole's image through its lens' centre C meets the sensor, C (b + g) / b (within 0.3 px),
    and the frame's record names the hex protocol's pinholes."""
    out = tmp_path / "tf.npy"
    assert main(["simulate", "-c", str(FIXTURES / "hex_small_camera.toml"), "--scene", "through-focus",
                 "--focus-offset-mm", "-5", "--pinhole-offset", "1,3", "--rays", "600000", "--no-noise", "-q",
                 "--out", str(out)]) == 0
    rec = json.loads((tmp_path / "tf.npy.sim.json").read_text())
    tf = shipped(-5.0, (1, 3))
    assert ThroughFocus.from_dict(rec["protocol"]) == tf
    pins = tfm.pinhole_lenses(HEX, tf)
    assert rec["protocol"]["frame"]["pinholes"] == len(pins) == len(rec["scene"]["points_mm"])
    s = HEX.sensor
    e = (np.load(out).astype(float) - s.black_level_dn) / s.gain_dn_per_e
    lay = tfm.frame_config(HEX, tf).layout
    scale = (lay.pupil_to_mla_mm + lay.sensor_gap_mm) / lay.pupil_to_mla_mm
    lat = Lattice("hex", ROWS, COLS, HEX.mla.pitch_um * 1e-3)
    px, py = lat.position(pins[:, 0], pins[:, 1])
    seen = 0
    for x, y in zip(px, py):
        cx = x * scale / (s.pixel_um * 1e-3) + (s.width_px - 1) / 2
        cy = y * scale / (s.pixel_um * 1e-3) + (s.height_px - 1) / 2
        x0, y0 = int(round(cx)) - 4, int(round(cy)) - 4
        if x0 < 0 or y0 < 0 or x0 + 9 > s.width_px or y0 + 9 > s.height_px:
            continue
        box = e[y0:y0 + 9, x0:x0 + 9]
        yy, xx = np.mgrid[y0:y0 + 9, x0:x0 + 9]
        assert (box * xx).sum() / box.sum() == pytest.approx(cx, abs=0.3)
        assert (box * yy).sum() / box.sum() == pytest.approx(cy, abs=0.3)
        seen += 1
    assert seen >= len(pins) - 4


def test_the_derived_exposure_puts_the_hex_pairs_brightest_spot_near_the_fill_fraction():
    """`pinhole_photons` on the hex camera (its exposure neighbours on the hex sub-lattice): rendered without
    noise, the brighter frame of the shipped pair peaks a few % under FILL_FRACTION of full well (42 spots hold
    fewer sub-pixel phases than the best one), the other where the traced peaks put it, none saturated."""
    from mlaqc.optics.simulate import simulate

    s = HEX.sensor
    peak = {}
    for u in (5.0, -5.0):
        tf = shipped(u)
        raw = simulate(tfm.frame_config(HEX, tf), tfm.scene(HEX, tf), rays=3_000_000, noise=False, seed=3).raw
        assert raw.max() < white_level(s)
        peak[u] = (raw.max() - s.black_level_dn) / s.gain_dn_per_e / s.full_well_e
    fill = tfm.FILL_FRACTION
    assert peak[-5.0] > peak[5.0] and 0.87 * fill < peak[-5.0] < 1.05 * fill
    ratio = tfm.spot_peak_per_photon(HEX, shipped(5.0)) / tfm.spot_peak_per_photon(HEX, shipped(-5.0))
    assert peak[5.0] / peak[-5.0] == pytest.approx(ratio, rel=0.1)


@pytest.fixture(scope="module")
def hex_grid():
    """The white frame's grid, calibrated on the independent analytic white frame of the hex lattice."""
    white = AnalyticModel(shape=(496, 496), lenses=(ROWS, COLS), packing="hex")
    img = (0.8 * white.render()).astype(np.float32)
    return calibrate(img, expected_pitch_px=HEX.layout.subimage_pitch_px, expected_shape=(ROWS, COLS), packing="hex")


# lenses under a pinhole of offsets (0, 0), (2, 1), (1, 3), (3, 2), rows of both parities
SEEDS = {(4, 6): -0.10, (16, 12): 0.10, (5, 16): -0.05, (13, 8): 0.05,
         (11, 18): 0.10, (19, 6): -0.10, (10, 12): -0.05, (22, 18): 0.05}
OFFSETS = [(0, 0), (2, 1), (1, 3), (3, 2)]


def test_seeded_focal_errors_on_the_hex_small_camera_read_with_sign_and_size(hex_grid):
    """±5 / ±10 % radius errors (both radii: the truth is the thick lens' focal length) on rows of both
    parities, frames rendered through the tracer with the realistic formation and the sensor's noise at the
    protocol's exposure, read on the shipped hex model: every sign right and every size within 15 % (the
    square protocol's bar), the healthy lenses' readings ten times below the largest seeded error."""
    for (m, n) in SEEDS:
        assert any(((m - o[1]) % 4 == 0) and ((n - m // 2 - o[0]) % 4 == 0) for o in OFFSETS), (m, n)
    em = ErrorMap.zeros(ROWS, COLS, "hex")
    for (m, n), e in SEEDS.items():
        em = em.with_lens(m + 1, n + 1, radius_front_rel=e, radius_back_rel=e)
    s = HEX.sensor
    frames = []
    for j, off in enumerate(OFFSETS):
        for u in (5.0, -5.0):
            tf = shipped(u, off)
            ph = Renderer(tfm.frame_config(HEX, tf), em).render(tfm.scene(HEX, tf), rays=4_000_000,
                                                                seed=11 + 2 * j + (u < 0)).photons
            raw = expose(apply_formation(ph, HEX), s, seed=31 + 2 * j + (u < 0), noise=True)
            frames.append((prepare_spots(RawFrame(raw, s.bit_depth, None, s.black_level_dn, white_level(s))), tf))
    res = measure_through_focus(frames, hex_grid, HEX)
    for (m, n), eps in SEEDS.items():
        truth, read = float(focal_rel_of_radius(HEX, eps)), res.focal_rel[m, n]
        assert res.covered[m, n]
        assert np.sign(read) == np.sign(truth), ((m, n), truth, read)
        assert abs(read - truth) <= 0.15 * abs(truth), ((m, n), truth, read)
    healthy = res.covered.copy()
    for key in SEEDS:
        healthy[key] = False
    assert healthy.sum() >= 120
    assert np.abs(res.focal_rel[healthy]).max() < 0.01
    assert 1.03 < res.pairs[0].gain < 1.15  # microlens spherical aberration: steeper than paraxial, as on square


def test_a_hex_square_mismatch_is_refused_in_one_sentence(hex_grid):
    """A hex white frame's grid read with a config whose MLA is square (and the reverse) names both lattices."""
    tf = shipped()
    frames = [(np.zeros((496, 496), np.float32), tf), (np.zeros((496, 496), np.float32), shipped(-5.0))]
    square_grid = replace(hex_grid, packing="square")
    with pytest.raises(InputError, match=r"^the white frame's grid is a square lattice but the camera config's MLA is hex"):
        measure_through_focus(frames, square_grid, HEX)
    square_cfg = replace(SQUARE, mla=replace(SQUARE.mla, count_h=ROWS, count_w=COLS))
    with pytest.raises(InputError, match=r"^the white frame's grid is a hex lattice but the camera config's MLA is square") as err:
        measure_through_focus(frames, hex_grid, square_cfg)
    assert str(err.value).count(". ") == 0


# --------------------------------------------------------------------------------------------- end to end


def test_inspect_a_hex_array_with_through_focus_frames_flags_and_signs_a_radius_error_at_best_focus(tmp_path, capsys):
    """+10 % radius sits near the camera's best focus, where the white frame hardly sees it; the shipped pair
    whose hex pinhole lattice has a pinhole on that lens (offset (0, 0): lens (13, 11), 1-based) reads it
    with its sign, and the joint verdict flags it and no healthy lens."""
    hexcfg = str(FIXTURES / "hex_small_camera.toml")
    em = ErrorMap.zeros(ROWS, COLS, "hex").with_lens(13, 11, radius_front_rel=0.10, radius_back_rel=0.10)
    em.save(tmp_path / "errs.json")
    assert any((tfm.pinhole_lenses(HEX, shipped()) == (12, 10)).all(axis=1))
    base = ["simulate", "-c", hexcfg, "-e", str(tmp_path / "errs.json"), "-q"]
    assert main(base + ["--rays-per-pixel", "100", "--out", str(tmp_path / "white.tiff")]) == 0
    frames = []
    for u in (5, -5):
        frames.append(str(tmp_path / f"tf{u}.tiff"))
        assert main(base + ["--scene", "through-focus", "--focus-offset-mm", str(u), "--rays", "3000000",
                            "--out", frames[-1]]) == 0
    code = main(["inspect", str(tmp_path / "white.tiff"), "-c", hexcfg, "-t", *frames, "-o", str(tmp_path / "rep")])
    assert code == 1 and "through-focus:" in capsys.readouterr().err
    report = json.loads((tmp_path / "rep" / "report.json").read_text())
    d = {(x["row"], x["col"]): x for x in report["defects"]}
    assert d[(13, 11)]["error_type"] == "radius" and d[(13, 11)]["magnitude"] > 0.05
    assert d[(13, 11)]["indexes"]["through_focus_z"] > 6
    assert len(d) == 1
    truth = float(focal_rel_of_radius(HEX, 0.10))
    assert report["through_focus"]["lenses"]["tf_focal_rel"][12][10] == pytest.approx(truth, rel=0.15)
    # the same frames with the square small camera's config: one sentence naming both lattices, exit 2, no report
    assert main(["inspect", str(tmp_path / "white.tiff"), "-c", str(FIXTURES / "small_camera.toml"), "-t", *frames,
                 "-o", str(tmp_path / "rep2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "hexagonal microlens lattice" in err[0] and "'square'" in err[0]
    assert not (tmp_path / "rep2").exists()


def test_scan_inspect_reads_the_hex_mock_cameras_pinhole_frames(tmp_path):
    """`mlaqc scan --inspect` on the mock camera's hex wafer (mock://?config=hex_small): the carrier's hex mask
    gives one +u / -u pair whose 42 pinholes (4 lenses apart on 24 x 28 lenses) are read with the white frame."""
    plan = tmp_path / "plan.toml"
    plan.write_text("[scan]\nsettle_s = 0.0\nretry_delay_s = 0.0\ncapture_timeout_s = 5.0\nexposure_us = 5000.0\n"
                    "[[positions]]\nx_mm = 10.0\ny_mm = 10.0\nlabel = \"a\"\n"
                    "[through_focus]\nfocus_offsets_mm = [5.0, -5.0]\nf_number = 11.0\nspacing_lenses = 4\n"
                    "offsets = [[1, 3]]\nexposure_us = 10000.0\nsettle_s = 0.0\niris = \"camera\"\nwhite_frames = true\n")
    out = tmp_path / "scan"
    assert main(["scan", "--camera", "mock://?defects=0&rpp=1&config=hex_small", "--stage", "mock://?aux=z,a,b",
                 "--plan", str(plan), "--out", str(out), "--inspect", "-q"]) in (0, 1)
    got = json.loads((out / "pos_00001.tiff.inspect.json").read_text())
    summary = got["through_focus"]["summary"]
    assert len(summary["pairs"]) == 1 and summary["pairs"][0]["offset"] == [1, 3]
    assert summary["pairs"][0]["lenses"] == summary["lenses_covered"] == len(tfm.pinhole_lenses(HEX, shipped(offset=(1, 3))))
    assert abs(summary["focal_rel_median"]) < 0.003
