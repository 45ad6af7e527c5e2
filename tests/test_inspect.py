"""Inspection chain against ground truth: registration, metrics, identification, robustness, CLI."""

import json
from pathlib import Path

import numpy as np
import pytest

from mlaqc.cli import main
from mlaqc.inspection.metrics import compute_metrics, reference_windows
from mlaqc.inspection.pipeline import inspect_image, prepare
from mlaqc.inspection.rawio import RawFrame
from mlaqc.models.reference import reference_model
from mlaqc.models.signatures import nominal_windows, um_per_px_at_mla
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene
from mlaqc.optics.sensor import expose, white_level

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
SMALL = load_config(FIXTURES / "small_camera.toml")

# seeded defects, each kept away from the others and from the border
SEEDED = {
    (5, 6): dict(pitch_um=2.0, pitch_dir_deg=30.0),
    (5, 18): dict(pitch_um=1.5, pitch_dir_deg=200.0),
    (11, 11): dict(decenter_um=8.0, decenter_dir_deg=120.0),
    (18, 5): dict(decenter_um=6.0, decenter_dir_deg=300.0),
    (12, 20): dict(radius_front_rel=-0.1, radius_back_rel=-0.1),
    (19, 14): dict(radius_front_rel=-0.06, radius_back_rel=-0.06),
}


def render(errors=None, **kw):
    """A white frame of the small camera, traced with plain Monte-Carlo sampling: its noise is independent
    from pixel to pixel and the same for a defective lens as for its neighbours, as a sensor's photon noise
    is. (The stratified Sobol sampler reduces the noise of ideal lenses only: measured at 50 rays/pixel, a
    -10 % radius lens came out 2.3 x noisier than its neighbours, which moves noise-sensitive indexes such
    as the gradient-energy sharpness by more than the defect does, and its radius sign then reads wrong.)"""
    return Renderer(SMALL, errors, sampler="random").render(WhiteScene(), **kw).photons


def seeded_map():
    em = ErrorMap.zeros(24, 24)
    for (m, n), kw in SEEDED.items():
        em = em.with_lens(m, n, **kw)
    return em


@pytest.fixture(scope="module")
def photons():
    return render(seeded_map(), rays_per_pixel=50, seed=21)


def frame_of(ph, seed=2, scale=1.0):
    s = SMALL.sensor
    raw = expose(ph * scale, s, seed=seed)
    return RawFrame(raw, s.bit_depth, None, s.black_level_dn, white_level(s), {}, "test")


def test_registration_recovers_known_subpixel_shifts():
    """Windows made from the reference itself, displaced by known amounts, register to those amounts."""
    model = reference_model(SMALL)
    rng = np.random.default_rng(1)
    true_dx = rng.uniform(-0.6, 0.6, (6, 7))
    true_dy = rng.uniform(-0.6, 0.6, (6, 7))
    cx = 10 + rng.uniform(-0.5, 0.5, (6, 7))
    cy = 10 + rng.uniform(-0.5, 0.5, (6, 7))
    (img, *_), qx, qy = reference_windows(model, cx + true_dx, cy + true_dy, 21, 21)
    # the gathered windows sit at the quantized (qx, qy): that is the true position
    met = compute_metrics(img, cx, cy, model, um_per_px_at_mla=5.0)
    assert np.abs(met["offset_x_px"] - (qx - cx)).max() < 0.01
    assert np.abs(met["offset_y_px"] - (qy - cy)).max() < 0.01
    assert np.nanmin(met["ssim"]) > 0.999 and np.nanmin(met["ncc"]) > 0.999


def test_pitch_error_reads_as_its_physical_shift(photons):
    """A pitch error's sub-image offset is close to dp*(b+f)/b in the seeded direction."""
    model = reference_model(SMALL)
    win, cx, cy = nominal_windows(photons / photons.max(), SMALL)
    met = compute_metrics(win, cx, cy, model, um_per_px_at_mla=um_per_px_at_mla(SMALL))
    m, n = 5, 6
    dx, dy = met["offset_x_px"][m - 1, n - 1], met["offset_y_px"][m - 1, n - 1]
    gain = SMALL.layout.subimage_pitch_px / (SMALL.mla.pitch_um / SMALL.sensor.pixel_um)  # (b+f)/b
    expect = 2.0 * gain / SMALL.sensor.pixel_um  # dp (um) * (b+f)/b / pixel (um) = 0.401 px
    assert np.hypot(dx, dy) == pytest.approx(expect, rel=0.25)
    assert np.degrees(np.arctan2(-dy, dx)) == pytest.approx(30.0, abs=8.0)
    healthy = np.ones((24, 24), bool)
    for (mm, nn) in SEEDED:
        healthy[mm - 2:mm + 1, nn - 2:nn + 1] = False
    healthy[[0, -1], :] = healthy[:, [0, -1]] = False
    assert np.nanmedian(np.abs(met["offset_x_px"][healthy])) < 0.05


def _check_found(result, allow_missing_types=()):
    by_lens = {(d.m, d.n): d for d in result.defects}
    for (m, n), kw in SEEDED.items():
        d = by_lens.get((m, n))
        assert d is not None, f"U({m},{n}) {kw} not found"
        if "pitch_um" in kw or "decenter_um" in kw:
            kind = "pitch" if "pitch_um" in kw else "decenter"
            assert d.error_type in ("position", kind)
            readings = {a[0]: a for a in d.alternatives} or {kind: (kind, d.magnitude, d.unit, d.direction_deg)}
            _, mag, unit, direction = readings[kind]
            true_mag = kw.get("pitch_um", kw.get("decenter_um"))
            true_dir = kw.get("pitch_dir_deg", kw.get("decenter_dir_deg"))
            assert mag == pytest.approx(true_mag, rel=0.25), (m, n)
            assert abs((direction - true_dir + 180) % 360 - 180) < 15, (m, n)
            assert unit == "µm"
        else:
            assert d.error_type == "radius"
            assert d.magnitude == pytest.approx(kw["radius_front_rel"], rel=0.25)
    false = [(d.m, d.n) for d in result.defects if (d.m, d.n) not in SEEDED]
    assert len(false) == 0, false


def test_identification_finds_types_sizes_and_directions(photons):
    result = inspect_image(prepare(frame_of(photons)), SMALL)
    _check_found(result)
    assert result.verdict == "FAIL"


@pytest.mark.parametrize("change", ["exposure", "vignetting", "crop"])
def test_same_defects_found_under_exposure_vignetting_and_crop(photons, change):
    ph = photons
    if change == "exposure":
        ph = ph * 0.55
    elif change == "vignetting":
        h, w = ph.shape
        yy, xx = np.mgrid[:h, :w]
        ph = ph * (1 - 0.35 * (((xx - 0.3 * w) ** 2 + (yy - 0.6 * h) ** 2) / (0.8 * w) ** 2))
    elif change == "crop":  # the frame shifted by 3 px: the top and left lose pixels, black comes in
        ph = np.pad(ph[3:, 3:], ((0, 3), (0, 3)))
    result = inspect_image(prepare(frame_of(ph)), SMALL)
    _check_found(result)


def test_a_perfect_array_passes_with_no_flags():
    ph = render(rays_per_pixel=50, seed=8)
    result = inspect_image(prepare(frame_of(ph, seed=9)), SMALL)
    assert result.verdict == "PASS" and len(result.defects) == 0


def test_cut_windows_gather_the_right_lens():
    from mlaqc.inspection.subimages import cut_windows
    img = np.zeros((60, 80), np.float32)
    img[30, 50] = 7.0
    win, valid, ox, oy = cut_windows(img, np.array([[50.2, 10.0]]), np.array([[29.6, 10.0]]), 9, 9)
    assert win[0, 0, 4, 4] == 7.0 and (ox[0, 0], oy[0, 0]) == (46, 26)
    edge, valid, _, _ = cut_windows(img, np.array([[1.0]]), np.array([[1.0]]), 9, 9)
    assert np.isnan(edge[0, 0, 0, 0]) and not valid[0, 0, 0, 0] and not np.isnan(edge[0, 0, 4, 4])


# --- command line ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def raw_files(tmp_path_factory, photons):
    d = tmp_path_factory.mktemp("raws")
    np.save(d / "defects.npy", frame_of(photons).data)
    ok = render(rays_per_pixel=30, seed=3)
    np.save(d / "perfect.npy", frame_of(ok).data)
    return d


def test_inspect_cli_reports_and_exit_status(raw_files, tmp_path):
    out = tmp_path / "rep"
    assert main(["inspect", str(raw_files / "defects.npy"), "-c", str(FIXTURES / "small_camera.toml"), "-o", str(out), "-q"]) == 1
    rep = json.loads((out / "report.json").read_text())
    assert rep["verdict"] == "FAIL"
    assert {(d["row"], d["col"]) for d in rep["defects"]} == set(SEEDED)
    lines = (out / "lenses.csv").read_text().splitlines()
    assert len(lines) == 1 + 24 * 24
    assert lines[0].startswith("row,col,x_px,y_px,grid_x_px,grid_y_px,flagged,error_type")
    out2 = tmp_path / "rep2"
    assert main(["inspect", str(raw_files / "perfect.npy"), "-c", str(FIXTURES / "small_camera.toml"), "-o", str(out2), "-q"]) == 0


@pytest.mark.parametrize("make, message", [
    (lambda p: p.write_bytes(b""), "empty"),
    (lambda p: p.write_bytes(b"\x93NUMPY garbage"), ""),
    (lambda p: np.save(p, np.zeros((100, 100), np.uint16)), "496"),
    (lambda p: np.save(p, np.full((496, 496), np.nan)), "NaN"),
    (lambda p: np.save(p, np.zeros((496, 496), np.uint16)), "black"),
    (lambda p: np.save(p, np.full((496, 496), 65535, np.uint16)), "saturated"),
])
def test_inspect_bad_input_exit_2_and_no_report(tmp_path, capsys, make, message):
    raw = tmp_path / "bad.npy"
    make(raw)
    out = tmp_path / "rep"
    code = main(["inspect", str(raw), "-c", str(FIXTURES / "small_camera.toml"), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and err.count("\n") == 1
    assert message.lower() in err.lower()
    assert not out.exists() or not any(out.iterdir())


def test_demo_runs_the_whole_chain(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "-c", str(FIXTURES / "small_camera.toml"), "--defects", "4", "--seed", "2",
                 "--rays-per-pixel", "30", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "seeded 4, found" in err
    for name in ("report.json", "lenses.csv", "defect_map.png", "report.html", "demo_white.dng", "demo_white.dng.sim.json"):
        assert (out / name).is_file(), name


def test_demo_says_whether_a_missed_lens_was_below_the_frames_limit():
    from mlaqc.commands.demo import _missed

    errors = ErrorMap.zeros(4, 4)
    errors.lens["radius_front_rel"][1, 2] = 0.07
    errors.lens["decenter_um"][2, 1] = 5.0
    limit = {"radius_rel_pos": 0.142, "radius_rel_neg": 0.05, "decenter_um": 2.0}
    assert _missed(errors, "radius", 1, 2, limit) == "MISSED (below this frame's detection limit, +14.2 %)"
    assert _missed(errors, "decenter", 2, 1, limit) == "MISSED (at or above this frame's detection limit, 2 µm)"
    assert _missed(errors, "radius", 1, 2, {}) == "MISSED"


def test_inspect_with_a_separate_white_image(raw_files, tmp_path):
    """The grid comes from a white image of the same MLA; the raw's defects are still found."""
    white = raw_files / "white_defects.npy"
    ph = render(seeded_map(), rays_per_pixel=30, seed=77)
    np.save(white, frame_of(ph, seed=5).data)
    out = tmp_path / "rep"
    code = main(["inspect", str(raw_files / "defects.npy"), "--white", str(white), "-c",
                 str(FIXTURES / "small_camera.toml"), "-o", str(out), "-q"])
    assert code == 1
    rep = json.loads((out / "report.json").read_text())
    assert {(d["row"], d["col"]) for d in rep["defects"]} == set(SEEDED)
    bad = tmp_path / "nowhite.npy"
    assert main(["inspect", str(raw_files / "defects.npy"), "--white", str(bad), "-c",
                 str(FIXTURES / "small_camera.toml"), "-o", str(tmp_path / "rep2"), "-q"]) == 2


def test_signature_table_is_rendered_from_the_tracer():
    """A pitch error's signature: the shift grows with the error and points along +x for direction 0."""
    from mlaqc.models.signatures import FEATURES, KINDS, build_signatures
    table = build_signatures(SMALL, rays_per_pixel=30, kinds=(KINDS[0],))
    shift = table.features["pitch"][:, FEATURES.index("shift_par")]
    assert np.all(np.diff(shift) > 0)
    assert abs(table.phi0_deg["pitch"]) < 5.0
    mags = table.magnitudes["pitch"]
    gain = SMALL.layout.subimage_pitch_px / (SMALL.mla.pitch_um / SMALL.sensor.pixel_um) / SMALL.sensor.pixel_um
    assert shift[mags == 2.0][0] == pytest.approx(2.0 * gain, rel=0.25)  # ~0.40 px for 2 um


# ------------------------------------------------------------------ per-lens measured quantities


def test_every_lens_gets_its_optical_centre_and_focal_error_with_uncertainties(photons):
    """Physics, not captured output: a pitch error moves the optical centre by Δp along its direction; a
    rear-surface decenter δ of the symmetric biconvex lens moves it by δ·R1/(R1+|R2|) = δ/2 (the axis through
    both centres of curvature); a radius error ε changes f by the thick lens' Δf/f ≈ ε."""
    result = inspect_image(prepare(frame_of(photons)), SMALL)
    M = result.measurements
    sig = float(np.nanmedian(M["centre_sigma_um"]))
    assert 0 < sig < 0.5
    for (m, n), truth in SEEDED.items():
        dx, dy = M["centre_dx_um"][m - 1, n - 1], M["centre_dy_um"][m - 1, n - 1]
        if "pitch_um" in truth or "decenter_um" in truth:
            size = truth.get("pitch_um", 0.5 * truth.get("decenter_um", 0.0))
            angle = truth.get("pitch_dir_deg", truth.get("decenter_dir_deg"))
            assert np.hypot(dx, dy) == pytest.approx(size, rel=0.15, abs=3 * sig)
            assert np.degrees(np.arctan2(-dy, dx)) % 360 == pytest.approx(angle, abs=8.0)
        else:  # a radius error does not move the lens
            assert np.hypot(dx, dy) < 4 * sig
            eps = truth["radius_front_rel"]
            assert M["focal_rel"][m - 1, n - 1] == pytest.approx(eps, rel=0.15)
            assert M["focal_um"][m - 1, n - 1] == pytest.approx(eps * 420.36, rel=0.16)
            assert 0 < M["focal_sigma_rel"][m - 1, n - 1] < abs(eps) / 3
    healthy = np.ones((24, 24), bool)
    for (mm, nn) in SEEDED:
        healthy[mm - 2:mm + 1, nn - 2:nn + 1] = False
    healthy[[0, -1], :] = healthy[:, [0, -1]] = False
    centre = np.hypot(M["centre_dx_um"], M["centre_dy_um"])[healthy]
    assert np.median(centre) < 2 * sig  # healthy lenses sit where the grid says, within their noise
    focal = M["focal_rel"][healthy]
    assert abs(np.median(focal)) < 0.01 and np.percentile(np.abs(focal), 90) < 0.03


def test_measurements_reach_lenses_csv_report_json_and_the_maps(raw_files, tmp_path):
    out = tmp_path / "rep"
    assert main(["inspect", str(raw_files / "defects.npy"), "-c", str(FIXTURES / "small_camera.toml"), "-o", str(out), "-q"]) == 1
    rows = (out / "lenses.csv").read_text().splitlines()
    head = rows[0].split(",")
    for name in ("centre_dx_um", "centre_dy_um", "centre_sigma_um", "focal_rel", "focal_um", "focal_sigma_rel"):
        assert name in head
    m_col, n_col, dx_col = head.index("row"), head.index("col"), head.index("centre_dx_um")
    by_lens = {(int(r.split(",")[m_col]), int(r.split(",")[n_col])): r.split(",") for r in rows[1:]}
    report = json.loads((out / "report.json").read_text())
    meas = report["measurements"]
    assert len(meas["lenses"]["centre_dx_um"]) == 24 and len(meas["lenses"]["centre_dx_um"][0]) == 24
    assert float(by_lens[(5, 6)][dx_col]) == pytest.approx(meas["lenses"]["centre_dx_um"][4][5], rel=1e-4)
    assert meas["summary"]["focal_length_um"] == pytest.approx(420.36, abs=0.05)
    import cv2
    maps = cv2.imread(str(out / "lens_maps.png"))
    assert maps is not None and maps.shape[1] > 3 * 24 * 4
    assert 'id="lens-maps"' in (out / "report.html").read_text()
