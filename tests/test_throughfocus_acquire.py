"""The through-focus pinhole protocol, acquisition side: geometry (stage Z, the mask carrier), rendered
frames checked against independent facts (spot positions, the lit disc's edge, the spot peak), `mlaqc
simulate --scene through-focus`, auxiliary stage axes (GRBL, Zaber, simulators), the mock camera
following the carrier, and scans with [through_focus] frames (resume, retries, refusals)."""

from __future__ import annotations

import json
import math
import threading
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from drivers.camera.mock import MockCamera
from drivers.capture import load_sidecar
from drivers.scan import ScanInterrupted, run_scan
from drivers.scan_manifest import MANIFEST_NAME, read_manifest, verify_scan
from drivers.scan_plan import ThroughFocusPlan, load_plan, plan_from_dict
from drivers.sim import GrblSim
from drivers.stage import GrblStage, NotHomedError, StageStopped, open_stage
from mlaqc.cli import main
from mlaqc.errors import DeviceError, InputError
from mlaqc.optics.config import load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics import throughfocus as tfm
from mlaqc.optics.formation import aperture_corner_radius_um
from mlaqc.optics.sensor import white_level
from mlaqc.optics.simulate import simulate
from mlaqc.optics.throughfocus import F_NUMBER, FOCUS_OFFSET_MM, SPACING_LENSES, Carrier, ThroughFocus

REPO = Path(__file__).resolve().parents[1]
SMALL = load_config(REPO / "fixtures" / "small_camera.toml")
PITCH_MM = SMALL.mla.pitch_um * 1e-3
PX_MM = SMALL.sensor.pixel_um * 1e-3


# --------------------------------------------------------------------------------------------- geometry


@pytest.mark.parametrize("u", [10.0, -10.0, 3.7, -25.0])
def test_stage_z_inverts_and_obeys_newton(u):
    tf = ThroughFocus(u)
    dz = tfm.stage_z_mm(SMALL, tf)
    assert tfm.focus_offset_at_stage_z(SMALL, dz) == pytest.approx(u, abs=1e-9)
    assert math.copysign(1.0, dz) == -math.copysign(1.0, u)  # an image behind the MLA needs the target nearer
    lay = tfm.frame_config(SMALL, tf).layout  # Newton's form of the conjugates: (a - f)(b - f) = f^2
    a = lay.object_distance_mm + lay.main.front_principal
    b = lay.mla_distance_mm + lay.main.rear_principal + u
    assert (a - lay.main.efl) * (b - lay.main.efl) == pytest.approx(lay.main.efl ** 2, rel=1e-9)


def test_small_focus_steps_follow_the_longitudinal_magnification():
    m = tfm.magnification(tfm.frozen(SMALL))
    for u in (0.5, -0.5):
        assert tfm.stage_z_mm(SMALL, ThroughFocus(u)) == pytest.approx(-u / m ** 2, rel=0.01)


def shipped(u: float = FOCUS_OFFSET_MM, offset: tuple[int, int] = (0, 0)) -> ThroughFocus:
    """A frame of the shipped protocol (±5 mm, f/11, pinholes 4 lenses apart; `Carrier()`, the plan's defaults)."""
    return ThroughFocus(u, F_NUMBER, SPACING_LENSES, offset)


def first(u: float, offset: tuple[int, int] = (0, 0)) -> ThroughFocus:
    """A frame of the first protocol (±10 mm, f/8, 9 lenses apart), which some tests keep on purpose."""
    return ThroughFocus(u, 8.0, 9, offset)


def test_shipped_defaults_agree():
    """One protocol everywhere: the Carrier, the plan's [through_focus] defaults (an empty table too), the mock
    camera's mask and `mlaqc simulate`'s options (tested below) all default to ±5 mm, f/11, spacing 4."""
    assert (FOCUS_OFFSET_MM, F_NUMBER, SPACING_LENSES) == (5.0, 11.0, 4)
    car = Carrier()
    assert car.focus_offsets_mm == (5.0, -5.0) and car.spacing_lenses == 4
    plan = ThroughFocusPlan()
    assert (plan.focus_offsets_mm, plan.f_number, plan.spacing_lenses, plan.carrier) == ((5.0, -5.0), 11.0, 4, car)
    empty = plan_from_dict({"positions": [{"x_mm": 1.0, "y_mm": 1.0}], "through_focus": {}}, "p").through_focus
    assert (empty.focus_offsets_mm, empty.f_number, empty.spacing_lenses, empty.carrier) == ((5.0, -5.0), 11.0, 4, car)
    mock = MockCamera.from_url("mock://")
    assert mock.carrier == car and mock.pinhole_photons is None
    assert len(empty.frames(SMALL)) == 32  # 16 lattice offsets at each of the two focus offsets


def test_pinhole_photons_follow_the_protocol():
    """The default exposure is derived from the optics (no tuned constant): the brighter frame of the pair's
    best-phased spot pixel at FILL_FRACTION of full well, the same photons for +u and -u, the offset
    irrelevant, and the first protocol's 2.2e6 (tuned by hand for 80 %) recovered."""
    s = SMALL.sensor
    fill = tfm.FILL_FRACTION
    p = tfm.pinhole_photons(SMALL, shipped())
    assert p == tfm.pinhole_photons(SMALL, shipped(-5.0, (1, 3))) == pytest.approx(4.2e5 * fill / 0.8, rel=0.02)
    peaks = [tfm.spot_peak_per_photon(SMALL, shipped(u)) for u in (5.0, -5.0)]
    assert max(peaks) == peaks[1]  # -5 mm is the brighter frame; +5 mm falls where the optics put it
    assert p * s.qe * max(peaks) / s.full_well_e == pytest.approx(fill, rel=1e-9)
    assert p * s.qe * peaks[0] / s.full_well_e == pytest.approx(0.55 * fill, abs=0.025 * fill)
    assert tfm.pinhole_photons(SMALL, first(10.0)) * 0.8 / fill == pytest.approx(2.2e6, rel=0.03)  # the old constant
    # photons are counted into the stopped pupil: at f/16 the disc is smaller, each lens takes a larger share
    # of a pinhole's light into a tighter spot, and fewer photons fill it
    assert tfm.pinhole_photons(SMALL, ThroughFocus(5.0, 16.0, 3)) < p
    assert tfm.scene(SMALL, shipped()).photons == p
    assert tfm.scene(SMALL, replace(shipped(), photons_per_pinhole=123.0)).photons == 123.0


def test_carrier_axes_and_view_are_inverse():
    car = Carrier()
    for u, off in ((5.0, (0, 0)), (5.0, (1, 3)), (-5.0, (3, 2))):
        tf = shipped(u, off)
        axes = tfm.carrier_axes(SMALL, car, tf)
        view = tfm.carrier_view(SMALL, car, axes, tf.f_number)
        fc = tfm.frame_config(SMALL, tf)
        assert view.kind == "pinholes" and view.field == car.field_of(tf)
        assert view.cfg.main_lens == fc.main_lens
        assert view.cfg.layout.object_distance_mm == pytest.approx(fc.layout.object_distance_mm, abs=1e-9)
        assert view.cfg.layout.mla_distance_mm == pytest.approx(SMALL.layout.mla_distance_mm, abs=1e-12)
        np.testing.assert_allclose(view.scene.points_mm, tfm.scene(SMALL, tf).points_mm, atol=1e-9)
        assert replace(view.frame, focus_offset_mm=u, photons_per_pinhole=None) == tf
        assert view.frame.focus_offset_mm == pytest.approx(u, abs=1e-6)
        assert view.frame.photons_per_pinhole == view.scene.photons == tfm.pinhole_photons(SMALL, tf)
        m = tfm.magnification(fc)
        shifted = tfm.carrier_view(SMALL, car, axes | {"a": axes["a"] + 0.003}, tf.f_number)  # 3 µm: same lattice
        np.testing.assert_allclose(np.array(shifted.scene.points_mm) - view.scene.points_mm, [[0.003, 0.0]] * len(view.scene.points_mm), atol=1e-9)
        assert shifted.frame.offset_lenses == tf.offset_lenses and shifted.residual_mm[0] == pytest.approx(0.003)
        step = tfm.carrier_view(SMALL, car, axes | {"a": axes["a"] - PITCH_MM / m}, tf.f_number)  # one lens over
        assert step.frame.offset_lenses == ((off[0] + 1) % 4, off[1])
        assert max(step.residual_mm, key=abs) == pytest.approx(0.0, abs=1e-9)
    other = tfm.carrier_view(SMALL, car, tfm.carrier_axes(SMALL, car, shipped()) | {
        "z": car.z_white_mm + tfm.stage_z_mm(SMALL, shipped(7.0))}, 11.0)  # the +5 mask seen from u = 7
    assert other.frame.focus_offset_mm == pytest.approx(7.0, abs=1e-6) and other.field == 1
    assert other.scene.photons == tfm.pinhole_photons(SMALL, shipped())  # the light does not follow Z
    explicit = tfm.carrier_view(SMALL, car, tfm.carrier_axes(SMALL, car, shipped()), 11.0, photons_per_pinhole=3e5)
    assert explicit.scene.photons == explicit.frame.photons_per_pinhole == 3e5
    assert tfm.carrier_view(SMALL, car, tfm.white_axes(car) | {"z": 3.0}, 11.0).kind == "white"
    assert tfm.carrier_view(SMALL, car, {"z": 50.0, "a": 10.0, "b": 80.0}, 11.0).kind == "opaque"
    with pytest.raises(InputError, match="no lattice for a focus offset of 10"):
        car.field_of(shipped(10.0))
    with pytest.raises(InputError, match="lattices are 4 lenses apart, not 9"):
        car.field_of(first(5.0))
    for bad in (dict(focus_offsets_mm=(10.0, 10.0)), dict(focus_offsets_mm=()), dict(spacing_lenses=1),
                dict(field_pitch_mm=0.0), dict(z_white_mm=math.nan)):
        with pytest.raises(InputError):
            Carrier(**bad)


# --------------------------------------------------------------------------------------------- rendered frames


def _lens_grid():
    rc = np.stack(np.meshgrid(np.arange(SMALL.mla.count_h), np.arange(SMALL.mla.count_w), indexing="ij"), -1)
    return rc.reshape(-1, 2), tfm.lens_centres_mm(SMALL, rc.reshape(-1, 2))


def _to_px(xy_mm):
    return np.asarray(xy_mm) / PX_MM + (SMALL.sensor.width_px - 1) / 2


_RENDERS: dict = {}


def rendered(tf: ThroughFocus):
    """A noise-free small-camera frame (formation on, the default exposure) and its expected photons, each
    frame rendered once."""
    if tf not in _RENDERS:
        _RENDERS[tf] = simulate(tfm.frame_config(SMALL, tf), tfm.scene(SMALL, tf), rays=3_000_000, noise=False,
                                seed=3)
    return _RENDERS[tf]


@pytest.fixture(scope="module", params=[10.0, -10.0], ids=["u+10", "u-10"])
def frame(request):
    """A frame of the first protocol (±10 mm, f/8, 9 lenses apart: discs 3.1 / 4.5 lenses in radius, enough
    lenses to fit their edge), at each focus offset."""
    tf = first(request.param)
    return tf, rendered(tf)


@pytest.fixture(scope="module", params=[first(10.0), first(-10.0), shipped(5.0), shipped(-5.0)],
                ids=["first-u+10", "first-u-10", "shipped-u+5", "shipped-u-5"])
def any_frame(request):
    """Frames of the first and of the shipped protocol (±5 mm, f/11, 4 lenses apart)."""
    return request.param, rendered(request.param)


def test_spots_land_in_the_expected_lenses_sub_images(any_frame):
    """The chief ray from a pinhole crosses the MLA at its lens' centre C and meets the pinhole's image at
    C (b + u) / b; that lens' spot therefore lands at C (b + g) / b on the sensor (g the MLA-sensor gap):
    where the lens' white-image sub-image is centred. Every lens inside a lit disc has its spot within
    its own cell, and lenses beyond every disc get no light."""
    tf, sim = any_frame
    s = SMALL.sensor
    e = (sim.raw.astype(float) - s.black_level_dn) / s.gain_dn_per_e
    lay = tfm.frame_config(SMALL, tf).layout
    scale = (lay.pupil_to_mla_mm + lay.sensor_gap_mm) / lay.pupil_to_mla_mm
    pins = tfm.lens_centres_mm(SMALL, tfm.pinhole_lenses(SMALL, tf))
    assert len(pins) == math.ceil(24 / tf.spacing_lenses) ** 2  # 9 (spacing 9), 36 (spacing 4)
    for c in pins:
        cx, cy = _to_px(c * scale)
        x0, y0 = int(round(cx)) - 4, int(round(cy)) - 4
        box = e[y0:y0 + 9, x0:x0 + 9]
        yy, xx = np.mgrid[y0:y0 + 9, x0:x0 + 9]
        assert (box * xx).sum() / box.sum() == pytest.approx(cx, abs=0.3)
        assert (box * yy).sum() / box.sum() == pytest.approx(cy, abs=0.3)
    rc, cen = _lens_grid()
    dist = np.min(np.hypot(*(cen[:, None, :] - pins[None]).transpose(2, 0, 1)), axis=1) / PITCH_MM
    r_in, r_out = tfm.inner_radius_lenses(SMALL, tf), tfm.blur_radius_mm(SMALL, tf) / PITCH_MM + math.sqrt(0.5)
    peak_all = []
    for (x, y), d in zip(cen, dist):
        cx, cy = _to_px(np.array([x, y]) * scale)
        x0, y0 = int(round(cx)) - 10, int(round(cy)) - 10
        box = e[max(y0, 0):y0 + 20, max(x0, 0):x0 + 20]
        peak_all.append(box.max())
        if d < r_in:
            iy, ix = np.unravel_index(np.argmax(box), box.shape)
            assert math.hypot(max(x0, 0) + ix - cx, max(y0, 0) + iy - cy) < 4.0  # its own spot, ~2 px off centre
        elif d > r_out + 1:
            assert box.max() < 0.002 * s.full_well_e
    # the dimmer frame of the shipped pair peaks near 0.55 of the fill fraction (45 % of full well at 80 %)
    assert max(peak_all) > 0.5 * tfm.FILL_FRACTION * s.full_well_e


def test_lit_disc_edge_is_blur_radius(frame):
    """Per-lens flux of the four inner discs fitted with a sharp-edged disc of radius R and a cubic radial
    intensity profile (the discs are not uniform: spherical aberration brightens or dims the rim), every
    disc of the frame in the model (at u = -10 mm neighbouring discs touch): R is blur_radius_mm."""
    tf, sim = frame
    e = sim.render.photons
    lay = tfm.frame_config(SMALL, tf).layout
    scale = (lay.pupil_to_mla_mm + lay.sensor_gap_mm) / lay.pupil_to_mla_mm
    rc, cen = _lens_grid()
    flux = np.empty(len(cen))
    for i, (x, y) in enumerate(cen):
        cx, cy = _to_px(np.array([x, y]) * scale)
        x0, y0 = int(round(cx)) - 10, int(round(cy)) - 10
        flux[i] = e[max(y0, 0):y0 + 20, max(x0, 0):x0 + 20].sum()
    q = (np.arange(25) + 0.5) / 25 - 0.5  # the lens aperture: the cell less the opaque corners
    ax, ay = np.meshgrid(q * PITCH_MM, q * PITCH_MM)
    keep = np.hypot(ax, ay) <= aperture_corner_radius_um(SMALL) * 1e-3
    ax, ay = ax[keep], ay[keep]
    pins = tfm.lens_centres_mm(SMALL, tfm.pinhole_lenses(SMALL, tf))
    radius = tfm.blur_radius_mm(SMALL, tf)
    fits = []
    for p0 in pins:
        if np.max(np.abs(p0)) > 0.7:  # the four pinholes whose discs stay on the 24 x 24 array
            continue
        near = np.hypot(*(cen - p0).T) < 6 * PITCH_MM
        rr = np.stack([np.hypot(cen[near, 0, None] + ax - q0[0], cen[near, 1, None] + ay - q0[1]) for q0 in pins
                       if np.hypot(*(q0 - p0)) < 12 * PITCH_MM])  # (discs, lenses, aperture samples)

        def chi2(r):
            x = np.where(rr <= r, rr / r, 0.0)
            inside = (rr <= r).sum(axis=(0, 2))
            a = np.stack([inside] + [(x ** k).sum(axis=(0, 2)) for k in range(1, 4)], 1) / rr.shape[2]
            coef, *_ = np.linalg.lstsq(a, flux[near], rcond=None)
            return float(np.sum((a @ coef - flux[near]) ** 2))

        grid = np.linspace(0.8 * radius, 1.2 * radius, 41)  # coarse, then fine around the best
        r0 = grid[np.argmin([chi2(r) for r in grid])]
        fine = np.linspace(r0 - 0.01 * radius, r0 + 0.01 * radius, 21)
        values = [chi2(r) for r in fine]
        best = (min(values), fine[int(np.argmin(values))])
        assert math.sqrt(best[0] / near.sum()) < 0.02 * np.median(flux[near][flux[near] > 0])  # the model fits
        fits.append(best[1])
    assert len(fits) == 4
    assert np.mean(fits) == pytest.approx(radius, rel=0.02)
    # and the paraxial estimate is measurably off (spherical aberration), in the direction the physics says
    assert (np.mean(fits) / tfm.paraxial_blur_radius_mm(SMALL, tf) - 1) * tf.focus_offset_mm < -0.5


@pytest.mark.parametrize("pair", [(shipped(5.0), shipped(-5.0)), (first(10.0), first(-10.0))],
                         ids=["shipped", "first"])
def test_default_photons_put_the_pairs_brightest_spot_near_the_fill_fraction_of_full_well(pair):
    """The derived exposure on rendered frames: the brighter frame of each pair peaks near FILL_FRACTION of
    full well (a few % under it here: 9 or 36 spots hold fewer sub-pixel phases than the best one;
    measured at 80 %: -5 mm 76.5 %, +10 mm 79 %), the other frame where the traced spot peaks put it
    (+5 mm: 0.55 of the -5 mm peak), none saturated."""
    fill = tfm.FILL_FRACTION
    s = SMALL.sensor
    peak = {}
    for tf in pair:
        raw = rendered(tf).raw
        assert raw.max() < white_level(s)
        peak[tf.focus_offset_mm] = (raw.max() - s.black_level_dn) / s.gain_dn_per_e / s.full_well_e
    bright = max(peak, key=peak.get)
    assert 0.87 * fill < peak[bright] < 1.05 * fill
    dim = next(u for u in peak if u != bright)
    ratio = (tfm.spot_peak_per_photon(SMALL, replace(pair[0], focus_offset_mm=dim))
             / tfm.spot_peak_per_photon(SMALL, replace(pair[0], focus_offset_mm=bright)))
    assert peak[dim] / peak[bright] == pytest.approx(ratio, rel=0.1)
    if pair[0].f_number == F_NUMBER:
        assert bright == -5.0 and 0.47 * fill < peak[5.0] < 0.62 * fill


def test_defective_lenses_focused_by_their_error_stay_below_full_well():
    """The exposure leaves room for a defective lens whose focal error brings its spot into focus (the
    brightest a spot gets: all of its lens' light in a pixel or two): every lens of the shipped pair
    carrying a radius error from -16 to +16 %, no pixel reaches the white level, and the focused spots do
    peak well above the healthy ones (the reason for the room)."""
    s = SMALL.sensor
    rng = np.random.default_rng(1)
    eps = np.round(rng.uniform(-0.16, 0.16, size=(SMALL.mla.count_h, SMALL.mla.count_w)), 3)
    errors = ErrorMap.zeros(SMALL.mla.count_h, SMALL.mla.count_w)
    errors.lens["radius_front_rel"][:] = eps
    errors.lens["radius_back_rel"][:] = eps
    peaks = []
    for tf in (shipped(5.0), shipped(-5.0)):
        sim = simulate(tfm.frame_config(SMALL, tf), tfm.scene(SMALL, tf), errors, rays=4_000_000, noise=False, seed=3)
        assert sim.raw.max() < white_level(s)
        peaks.append((sim.raw.max() - s.black_level_dn) / s.gain_dn_per_e / s.full_well_e)
    assert max(peaks) > 1.3 * tfm.FILL_FRACTION  # measured 1.75x the healthy peak (the FILL_FRACTION note)


# --------------------------------------------------------------------------------------------- mlaqc simulate


def test_simulate_cli_writes_a_through_focus_frame(tmp_path, capsys):
    """The options' defaults are the shipped protocol's (f/11, 4 lenses apart, +5 mm; the derived exposure)."""
    out = tmp_path / "tf.npy"
    assert main(["simulate", "-c", str(REPO / "fixtures" / "small_camera.toml"), "--scene", "through-focus",
                 "--focus-offset-mm", "-5", "--pinhole-offset", "1,3", "--rays", "300000", "--no-noise", "-q",
                 "--out", str(out)]) == 0
    rec = json.loads((tmp_path / "tf.npy.sim.json").read_text())
    tf = shipped(-5.0, (1, 3))
    assert ThroughFocus.from_dict(rec["protocol"]) == tf and rec["protocol"]["photons_per_pinhole"] is None
    assert rec["scene"]["photons"] == pytest.approx(tfm.pinhole_photons(SMALL, tf))
    assert rec["protocol"]["frame"]["stage_z_mm"] == pytest.approx(tfm.stage_z_mm(SMALL, tf))
    assert rec["protocol"]["frame"]["pinholes"] == len(tfm.pinhole_lenses(SMALL, tf)) == len(rec["scene"]["points_mm"])
    assert rec["layout"]["object_distance_mm"] == pytest.approx(tfm.frame_config(SMALL, tf).layout.object_distance_mm)
    assert rec["config"]["main_lens"]["diameter_mm"] == SMALL.main_lens.diameter_mm  # the camera as given
    assert main(["simulate", "-c", str(REPO / "fixtures" / "small_camera.toml"), "--scene", "through-focus",
                 "--focus-offset-mm", "10", "--f-number", "8", "--pinhole-spacing", "9", "--pinhole-photons", "2e6",
                 "--rays", "1000", "-q", "--out", str(tmp_path / "first.npy")]) == 0
    rec = json.loads((tmp_path / "first.npy.sim.json").read_text())
    assert ThroughFocus.from_dict(rec["protocol"]) == replace(first(10.0), photons_per_pinhole=2e6)
    assert rec["scene"]["photons"] == 2e6
    assert main(["simulate", "-c", str(REPO / "fixtures" / "small_camera.toml"), "--scene", "through-focus",
                 "--rays", "1000", "-q", "--out", str(tmp_path / "default.npy")]) == 0
    rec = json.loads((tmp_path / "default.npy.sim.json").read_text())
    assert ThroughFocus.from_dict(rec["protocol"]) == shipped(5.0)


@pytest.mark.parametrize("args, message", [
    (["--scene", "white", "--f-number", "8"], "applies only to --scene through-focus"),
    (["--scene", "through-focus", "--pinhole-offset", "4,0"], "below the pinhole spacing"),  # the default: 4
    (["--scene", "through-focus", "--pinhole-offset", "1"], "two whole numbers"),
    (["--scene", "through-focus", "--focus-offset-mm", "0.2"], "at least 0.5 mm"),
    (["--scene", "through-focus", "--f-number", "0.5"], "f-number must be at least 1"),
    (["--scene", "through-focus", "--pinhole-photons", "-1"], "photons per pinhole must be positive"),
])
def test_simulate_cli_refuses_bad_through_focus_options(tmp_path, capsys, args, message):
    out = tmp_path / "x.npy"
    assert main(["simulate", "-c", str(REPO / "fixtures" / "small_camera.toml"), "--rays", "1000", "-q", "--out",
                 str(out), *args]) == 2
    assert message in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------- stages


@pytest.mark.parametrize("url", ["sim+grbl://?aux=z,a,b&speed_mm_s=1000&z_max_mm=90",
                                 "sim+zaber://?aux=z:1.3,a:2.1,b:2.2&speed_mm_s=1000&z_max_mm=90"])
def test_stage_auxiliary_axes(url):
    with open_stage(url) as stage:
        assert stage.aux_axes == ("z", "a", "b") and stage.aux_limits["z"] == (0.0, 90.0)
        with pytest.raises(NotHomedError):
            stage.move_aux({"z": 10.0})
        stage.home()
        assert stage.last_aux == {"z": 0.0, "a": 0.0, "b": 0.0}
        sent = len(stage.sim.received_lines)
        with pytest.raises(InputError, match="outside the soft limits"):
            stage.move_aux({"z": 95.0})
        with pytest.raises(InputError, match="no C axis|auxiliary"):
            stage.move_aux({"c": 1.0})
        assert len(stage.sim.received_lines) == sent  # refused before anything was sent
        stage.move_to(12.5, 40.0)
        stage.move_aux({"z": 31.104, "b": 24.5})
        stage.move_aux({"a": 9.5921})
        assert stage.aux_position() == pytest.approx({"z": 31.104, "a": 9.592, "b": 24.5}, abs=1e-3)
        assert stage.last_aux == pytest.approx({"z": 31.104, "a": 9.592, "b": 24.5}, abs=1e-3)
        assert stage.position() == pytest.approx((12.5, 40.0), abs=1e-3)  # XY untouched by the carrier's moves
        if "grbl" in url:
            assert "G90 G53 G0 Z31.104 B24.500" in stage.sim.received_lines
            assert stage.sim.axes_mm == pytest.approx((12.5, 40.0, 31.104, 9.592, 24.5), abs=1e-3)
        else:
            assert stage.sim.position_mm == pytest.approx((12.5, 40.0, 31.104, 9.592, 24.5), abs=1e-3)


def test_stage_without_the_axis_refuses_and_a_three_axis_grbl_reports_it():
    with open_stage("mock://") as stage:
        stage.home()
        with pytest.raises(InputError, match="has no Z axis"):
            stage.move_aux({"z": 1.0})
        assert stage.aux_position() == {} and stage.last_aux is None
    with GrblSim(speed_mm_s=1000.0) as sim:  # GRBL 1.1: X, Y, Z only
        stage = GrblStage(sim.path, aux_limits={"z": (0, 100), "a": (0, 100), "b": (0, 100)}, poll_s=0.01)
        with stage:
            stage.home()
            stage.move_aux({"z": 5.0})
            assert sim.axes_mm == pytest.approx((0.0, 0.0, 5.0))
            with pytest.raises(DeviceError, match="reports only 3 axes"):
                stage.aux_position()
            with pytest.raises(DeviceError, match="error:20"):
                stage.move_aux({"a": 1.0})


@pytest.mark.parametrize("message, url", [
    ("must include z", "sim+grbl://?aux=a"),
    ("needs axis 'z' in aux=", "sim+grbl://?z_max_mm=50"),
    ("must list distinct axes", "sim+grbl://?aux=z,z"),
    ("reuses device 1 axis 2", "sim+zaber://?aux=z:1.2"),
    ("NAME:DEVICE.AXIS", "sim+zaber://?aux=1.3"),
    ("below z_max_mm", "sim+grbl://?aux=z&z_min_mm=60&z_max_mm=50"),
])
def test_stage_url_auxiliary_axis_errors(message, url):
    with pytest.raises(InputError, match=message):
        open_stage(url)


def test_stop_halts_an_auxiliary_move():
    with GrblSim(speed_mm_s=20.0, homing_speed_mm_s=5000.0, axes="XYZAB") as sim:
        stage = GrblStage(sim.path, aux_limits={"z": (0, 100), "a": (0, 100), "b": (0, 100)}, poll_s=0.01)
        with stage:
            stage.home()
            errors = []

            def move():
                try:
                    stage.move_aux({"z": 80.0}, timeout_s=10.0)
                except StageStopped as exc:
                    errors.append(exc)

            worker = threading.Thread(target=move)
            worker.start()
            assert sim.wait_state("Run", 2.0)
            stage.stop()
            worker.join(5.0)
            assert errors and 0.0 < sim.axes_mm[2] < 80.0
            assert stage.homed  # a feed hold keeps the position
            stage.move_aux({"z": 1.0})
            assert stage.aux_position()["z"] == pytest.approx(1.0)


# --------------------------------------------------------------------------------------------- mock camera


def _camera(**params) -> MockCamera:
    text = "&".join(f"{k}={v}" for k, v in {"defects": 0, "rpp": 1, "exposure_us": 10000, **params}.items())
    return MockCamera.from_url(f"mock://?{text}").open()


def test_mock_camera_renders_what_the_carrier_shows():
    cam = _camera()
    x, y = cam.wafer.centre_mm(1, 1)
    reading = {}
    cam.attach_stage(lambda: (x, y, reading.get("aux")))
    white = cam.capture()
    assert white.extra["mock"]["view"] == "white" and "bench" not in white.extra["truth"]
    reading["aux"] = tfm.white_axes(cam.carrier)  # the clear window: the same white render (cache hit)
    again = cam.capture()
    assert again.extra["mock"]["cache_hit"] and again.extra["truth"]["bench"]["kind"] == "white"
    cam.set_f_number(11.0)  # the default mask: the shipped protocol's lattices
    tf = shipped(-5.0, (1, 2))
    reading["aux"] = {k: round(v, 3) for k, v in tfm.carrier_axes(SMALL, cam.carrier, tf).items()}  # as GRBL reports
    spots = cam.capture()
    bench = spots.extra["truth"]["bench"]
    assert bench["kind"] == "pinholes" and bench["field"] == 2
    rec = ThroughFocus.from_dict(bench["through_focus"])
    assert rec.offset_lenses == (1, 2) and rec.focus_offset_mm == pytest.approx(-5.0, abs=2e-3)
    assert rec.photons_per_pinhole == pytest.approx(tfm.pinhole_photons(SMALL, tf))  # the protocol's exposure
    data = spots.data.astype(float) - SMALL.sensor.black_level_dn
    s = SMALL.sensor
    for c in tfm.lens_centres_mm(SMALL, tfm.pinhole_lenses(SMALL, tf)):  # a spot at every pinhole lens
        cx, cy = _to_px(c)
        box = data[int(cy) - 3:int(cy) + 5, int(cx) - 3:int(cx) + 5]
        assert box.max() > 0.375 * tfm.FILL_FRACTION * s.full_well_e * s.gain_dn_per_e
    lit = np.count_nonzero(data > 0.05 * s.full_well_e * s.gain_dn_per_e) / data.size
    assert lit < 0.05  # spots, not sub-images
    reading["aux"] = {"z": 50.0, "a": 10.0, "b": 90.0}  # off the mask's fields: chrome
    dark = cam.capture()
    assert dark.extra["truth"]["bench"]["kind"] == "opaque"
    assert dark.data.max() < s.black_level_dn + 10 * s.read_noise_e * s.gain_dn_per_e
    settings = cam.settings()
    assert settings["f_number"] == 11.0 and settings["carrier"]["focus_offsets_mm"] == [5.0, -5.0]
    assert settings["carrier"]["spacing_lenses"] == 4 and settings["pinhole_photons"] is None
    fixed = _camera(pinhole_photons=2e5, mask="10,-10", mask_spacing=9, f_number=8)  # another mask, its light set
    fixed.attach_stage(lambda: (x, y, {k: round(v, 3) for k, v in tfm.carrier_axes(SMALL, fixed.carrier,
                                                                                     first(10.0)).items()}))
    assert fixed.capture().extra["truth"]["bench"]["through_focus"]["photons_per_pinhole"] == 2e5


def test_mock_iris_scales_the_white_flux_with_the_pupil_area():
    cam = _camera()
    wide = cam.expected_photons()
    cam.set_f_number(8.0)
    stopped = cam.expected_photons()
    assert cam.set_f_number(1.2) == pytest.approx(tfm.native_f_number(SMALL), abs=0.01)  # no wider than the rim
    assert stopped.sum() / wide.sum() == pytest.approx((tfm.native_f_number(SMALL) / 8.0) ** 2, rel=0.05)


@pytest.mark.parametrize("query, message", [
    ("mask=10,x", "numbers separated by commas"),
    ("mask=10,10", "distinct"),
    ("mask_spacing=1", "at least 2"),
    ("field_pitch_mm=0", "positive"),
    ("f_number=100", "outside the mock lens' range"),
    ("pinhole_photons=-3", "positive"),
])
def test_mock_camera_url_through_focus_errors(query, message):
    with pytest.raises(InputError, match=message):
        MockCamera.from_url(f"mock://?{query}")


# --------------------------------------------------------------------------------------------- scans

PLAN = """
[scan]
settle_s = 0.0
retry_delay_s = 0.0
capture_timeout_s = 0.5
exposure_us = 5000.0

[[positions]]
x_mm = 10.0
y_mm = 10.0
label = "a"

[[positions]]
x_mm = 10.0
y_mm = 10.0
label = "b"

[through_focus]
offsets = [[0, 0], [2, 2]]
exposure_us = 10000.0
settle_s = 0.0
"""  # the protocol's defaults: ±5 mm, f/11, 4 lenses apart
CAMERA = "mock://?defects=0&rpp=1"
STAGE = "mock://?aux=z,a,b"


def test_fixture_plan_and_cover_expansion():
    plan = load_plan(REPO / "fixtures" / "scan_plan_throughfocus.toml")
    tf = plan.through_focus
    assert tf.offsets == "cover" and tf.carrier == Carrier() and (tf.f_number, tf.spacing_lenses) == (11.0, 4)
    frames = tf.frames(SMALL)
    assert len(frames) == 32 and {f.focus_offset_mm for f in frames} == {5.0, -5.0}
    assert {(f.f_number, f.spacing_lenses) for f in frames} == {(11.0, 4)}
    assert sorted({f.offset_lenses for f in frames}) == sorted(tfm.coverage_offsets(SMALL, shipped()))
    assert len(tfm.coverage_offsets(SMALL, shipped())) == 16  # every lattice shift: one lens per disc
    assert plan.digest != replace(plan, through_focus=None).digest


@pytest.mark.parametrize("table, message", [
    ("focus_offsets_mm = [10.0, 10.0]", "through_focus.focus_offsets_mm"),
    ("focus_offsets_mm = [0.1]", "through_focus.focus_offsets_mm"),
    ("focus_offsets_mm = 10.0", "through_focus.focus_offsets_mm"),
    ("f_number = 0.5", "through_focus.f_number"),
    ("spacing_lenses = 1", "through_focus.spacing_lenses"),
    ("offsets = [[0, 9]]", "through_focus.offsets"),
    ("offsets = [[0, 0], [0, 0]]", "through_focus.offsets"),
    ("offsets = \"all\"", "through_focus.offsets"),
    ("iris = \"auto\"", "through_focus.iris"),
    ("iris = \"manual\"", "white_frames = false"),
    ("white_frames = 1", "through_focus.white_frames"),
    ("config = \"missing.toml\"", "through_focus.config"),
    ("field_pitch_mm = 0.0", "through_focus.field_pitch_mm"),
    ("z_white_mm = \"high\"", "through_focus.z_white_mm"),
    ("average = 0", "through_focus.average"),
    ("colour = 1", "unknown key 'through_focus.colour'"),
])
def test_plan_through_focus_keys_are_checked(table, message):
    data = {"positions": [{"x_mm": 1.0, "y_mm": 1.0}], "through_focus": tomllib.loads(table)}
    with pytest.raises(InputError, match=message.replace("[", r"\[")):
        plan_from_dict(data, "p.toml")


def test_plan_through_focus_exposure_needs_the_white_exposure():
    with pytest.raises(InputError, match="needs scan.exposure_us"):
        plan_from_dict({"positions": [{"x_mm": 1.0, "y_mm": 1.0}], "through_focus": {"exposure_us": 9000.0}}, "p")
    plan_from_dict({"positions": [{"x_mm": 1.0, "y_mm": 1.0}],
                    "through_focus": {"exposure_us": 9000.0, "iris": "manual", "white_frames": False}}, "p")


def test_scan_acquires_through_focus_frames(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    out = tmp_path / "scan"
    seen = []
    result = run_scan(CAMERA, STAGE, plan, out, inspect=lambda f: seen.append(f.path.name) or None)
    assert result.done == 2 and verify_scan(out) == []
    assert seen == ["pos_00001.tiff", "pos_00002.tiff"]  # the hook inspects white frames only
    data = read_manifest(out / MANIFEST_NAME)
    head = data.header["through_focus"]
    assert [ThroughFocus.from_dict(f) for f in head["frames"]] == [
        shipped(u, o) for u in (5.0, -5.0) for o in ((0, 0), (2, 2))]
    assert head["config_source"] == "camera" and head["white_f_number"] == pytest.approx(2.5, abs=1e-3)
    for rec in data.records:
        files = rec["files"]
        assert [f["file"] for f in files] == [f"pos_{rec['index'] + 1:05d}{s}.tiff" for s in ("", "_tf01", "_tf02", "_tf03", "_tf04")]
        assert files[0]["through_focus"] is None
        assert "through_focus" in rec["timing_s"]
        for k, item in enumerate(files[1:], start=1):
            want = ThroughFocus.from_dict(head["frames"][k - 1])
            assert ThroughFocus.from_dict(item["through_focus"]) == want
            side = load_sidecar(out / item["file"])
            ctx = side["context"]["through_focus"]
            assert ctx["aux_mm"] == pytest.approx(ctx["carrier_axes_mm"], abs=1.5e-3)  # read back = target
            assert ctx["f_number_read_back"] == 11.0 and side["exposure_us"] == 10000.0
            assert ctx["carrier_axes_mm"]["z"] == pytest.approx(50.0 + tfm.stage_z_mm(SMALL, want), abs=1e-6)
            bench = side["device_extra"]["truth"]["bench"]  # what the mock rendered: that frame
            got = ThroughFocus.from_dict(bench["through_focus"])
            assert got.offset_lenses == want.offset_lenses and got.focus_offset_mm == pytest.approx(want.focus_offset_mm, abs=2e-3)
            assert side["warnings"] == []
        white = load_sidecar(out / files[0]["file"])
        assert white["exposure_us"] == 5000.0 and white["device_extra"]["truth"]["bench"]["kind"] == "white"
        assert white["device_extra"]["mock"]["f_number"] == pytest.approx(2.5, abs=0.01)


def test_scan_through_focus_retries_resumes_and_refuses(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    out = tmp_path / "scan"

    def stop_at_b(runner, pos):
        if pos.label == "b":
            raise KeyboardInterrupt

    cam = MockCamera.from_url(CAMERA + "&faults=timeout@3")  # the second through-focus frame times out once
    with pytest.raises(ScanInterrupted):
        run_scan(cam, open_stage(STAGE), plan, out, before_position=stop_at_b)
    first = read_manifest(out / MANIFEST_NAME).records
    assert [r["label"] for r in first] == ["a"] and first[0]["attempts"] == 2
    changed = tmp_path / "changed.toml"
    changed.write_text(PLAN.replace("[[0, 0], [2, 2]]", "[[0, 0], [1, 1]]"))
    with pytest.raises(InputError, match="different plan"):
        run_scan(CAMERA, STAGE, changed, out, resume=True)
    result = run_scan(CAMERA, STAGE, plan, out, resume=True)
    assert result.resumed == 1 and result.captured == 1 and verify_scan(out) == []
    assert [r["label"] for r in read_manifest(out / MANIFEST_NAME).records] == ["a", "b"]


def test_scan_refuses_benches_that_cannot_take_through_focus_frames(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    with pytest.raises(InputError, match="has no Z, A, B axis"):
        run_scan(CAMERA, "mock://", plan, tmp_path / "s1")
    with pytest.raises(InputError, match="outside the stage's soft limits"):
        run_scan(CAMERA, STAGE + "&z_max_mm=40", plan, tmp_path / "s2")
    cam = MockCamera.from_url(CAMERA)
    cam.set_f_number = None  # a camera without an iris control
    with pytest.raises(InputError, match="cannot set its iris"):
        run_scan(cam, STAGE, plan, tmp_path / "s3")
    # a mock whose mask is not the plan's would render lattices the frame records do not describe
    with pytest.raises(InputError, match=r"other than the one camera .* shows \(lattices for u = \+10, -10 mm, 9"):
        run_scan(CAMERA + "&mask=10,-10&mask_spacing=9", STAGE, plan, tmp_path / "s4")
    for name in ("s1", "s2", "s3", "s4"):
        assert not (tmp_path / name / MANIFEST_NAME).exists()


def test_scan_through_focus_only_with_a_manual_iris(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN.replace("offsets = [[0, 0], [2, 2]]", 'offsets = [[2, 2]]\niris = "manual"\nwhite_frames = false'))
    cam = MockCamera.from_url(CAMERA + "&f_number=11")  # the operator stopped the lens down by hand
    out = tmp_path / "scan"
    run_scan(cam, STAGE, plan, out)
    rec = read_manifest(out / MANIFEST_NAME).records[0]
    assert [f["file"] for f in rec["files"]] == ["pos_00001_tf01.tiff", "pos_00001_tf02.tiff"]
    side = load_sidecar(out / "pos_00001_tf02.tiff")
    assert side["context"]["through_focus"]["iris"] == "manual"
    assert side["device_extra"]["truth"]["bench"]["kind"] == "pinholes"
    assert side["device_extra"]["mock"]["f_number"] == 11.0


def test_a_record_must_state_its_protocol(tmp_path):
    """A frame record that leaves out the f-number or spacing is refused, not read with some default."""
    from mlaqc.inspection.pinhole_frames import frame_record

    with pytest.raises(InputError, match="does not state f_number, spacing_lenses"):
        ThroughFocus.from_dict({"focus_offset_mm": 5.0})
    raw = tmp_path / "tf.tiff"
    (tmp_path / "tf.tiff.meta.json").write_text(json.dumps({"through_focus": {"focus_offset_mm": 5.0,
                                                                              "spacing_lenses": 4}}))
    with pytest.raises(InputError, match="tf.tiff.meta.json.*does not state f_number"):
        frame_record(raw)
    (tmp_path / "tf.tiff.meta.json").write_text(json.dumps({"through_focus": shipped(-5.0).to_dict()}))
    assert frame_record(raw) == shipped(-5.0)
