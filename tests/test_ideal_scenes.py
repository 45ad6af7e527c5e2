"""Point and texture scenes through an ideal (datasheet) main lens, given by their image
(`geometry.image_defocus_mm`): checked against first-order optics of the light-field microscope fixture
(a telecentric cone of the image-side NA through the point's image, the microlens' chief ray through its
principal planes), the texture's orientation, and the two engines against each other ray by ray."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mlaqc.cli import main
from mlaqc.errors import InputError
from mlaqc.optics import raytrace_kernels
from mlaqc.optics.config import config_from_dict, load_config
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import PointScene, TextureScene, WhiteScene

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
LFM = load_config(FIXTURES / "lfm_40x_relay.toml")
needs_numba = pytest.mark.skipif(not raytrace_kernels.AVAILABLE, reason="numba is not installed")


def small_lfm(count: int, defocus_mm: float | None = None):
    """The microscope's optics with `count` x `count` lenses on a sensor holding them plus a lens a side,
    no diffraction (geometry alone), the scene's image `defocus_mm` before the MLA."""
    d = json.loads(json.dumps(LFM.to_dict()))
    side = int(math.ceil((count + 2) * LFM.layout.subimage_pitch_px)) // 2 * 2
    d["mla"].update(count_w=count, count_h=count)
    d["sensor"].update(width_px=side, height_px=side)
    d["formation"] = {"diffraction": False}
    if defocus_mm is not None:
        d["geometry"]["image_defocus_mm"] = defocus_mm
    return config_from_dict(d)


def lens_centre_mm(cfg, m: int, n: int) -> tuple[float, float]:
    """U(m, n)'s axis on a square array centred on the optical axis (x right, y down)."""
    p = cfg.mla.pitch_um * 1e-3
    return (n - (cfg.mla.count_w + 1) / 2) * p, (m - (cfg.mla.count_h + 1) / 2) * p


def to_px(cfg, x_mm: float, y_mm: float) -> tuple[float, float]:
    """Continuous sensor coordinates (pixel i spans [i, i + 1)) of a point in the MLA's focal plane."""
    pix = cfg.pixel_at_mla_um * 1e-3
    return x_mm / pix + cfg.sensor.width_px / 2, y_mm / pix + cfg.sensor.height_px / 2


def cell_window(cfg, img: np.ndarray, m: int, n: int) -> tuple[np.ndarray, float, float]:
    """The pixels behind U(m, n) (telecentric: straight behind it, one pitch square) and their origin."""
    cx, cy = to_px(cfg, *lens_centre_mm(cfg, m, n))
    h = 0.5 * cfg.layout.subimage_pitch_px
    c0, r0 = int(round(cx - h)), int(round(cy - h))
    size = int(round(2 * h))
    return img[r0:r0 + size, c0:c0 + size], float(c0), float(r0)


def test_a_point_imaged_on_the_mla_lights_its_own_lens_only():
    """A point the main lens images onto the MLA: every ray passes through that point, inside one lens,
    and fills that lens' sub-image (the pupil's image, f tan u' = 22 px, inside the 46 px cell)."""
    cfg = small_lfm(5)
    x, y = lens_centre_mm(cfg, 3, 3)
    img = Renderer(cfg, engine="numpy").render(PointScene(((x + 0.03, y - 0.02),), 1e6), rays=200_000, seed=1).photons
    own, _, _ = cell_window(cfg, img, 3, 3)
    assert own.sum() / img.sum() > 0.995
    lit = own > 0.2 * own.max()
    radius_px = math.sqrt(lit.sum() / math.pi)
    expected = cfg.layout.micro.efl * math.tan(math.asin(1 / (2 * cfg.main_lens.f_number))) / (cfg.pixel_at_mla_um * 1e-3)
    assert radius_px == pytest.approx(expected, rel=0.05)


def test_a_defocused_point_lights_a_disc_of_lenses_each_seeing_it_along_its_chief_ray():
    """The point's image d before the MLA: the telecentric cone of half-angle u' (sin u' = 1 / 2N) meets the
    MLA in a disc of radius d tan u'; a lens at x_k from the point's image sees it along the chief ray
    through its front principal plane (the convex vertex of a plano-convex lens, t/2 before the mid-plane),
    which leaves the rear one parallel, f from the sensor: its spot centroid lies f (x_k - x') / (d - t/2)
    from the lens' axis."""
    d_mm = 20.0
    cfg = small_lfm(9, d_mm)
    x0, y0 = lens_centre_mm(cfg, 5, 5)
    img = Renderer(cfg, engine="numpy").render(PointScene(((x0, y0),), 1e6), rays=1_500_000, seed=2).photons
    tan_u = math.tan(math.asin(1 / (2 * cfg.main_lens.f_number)))
    cone_mm = d_mm * tan_u
    p = cfg.mla.pitch_um * 1e-3
    f = cfg.layout.micro.efl
    dist = d_mm - 0.5 * cfg.mla.thickness_um * 1e-3
    pix = cfg.pixel_at_mla_um * 1e-3
    got, want, dark = [], [], []
    for m in range(1, 10):
        for n in range(1, 10):
            xk, yk = lens_centre_mm(cfg, m, n)
            r = math.hypot(xk - x0, yk - y0)
            win, c0, r0 = cell_window(cfg, img, m, n)
            if r - p / math.sqrt(2) > cone_mm:  # the whole cell outside the cone
                dark.append(win.sum())
            if r + p / math.sqrt(2) < cone_mm:  # the whole cell inside it: a symmetric bundle
                rows, cols = np.indices(win.shape)
                cx = (win * (cols + 0.5)).sum() / win.sum() + c0
                cy = (win * (rows + 0.5)).sum() / win.sum() + r0
                ax, ay = to_px(cfg, xk, yk)
                got += [cx - ax, cy - ay]
                want += [f * (xk - x0) / dist / pix, f * (yk - y0) / dist / pix]
    got, want = np.array(got), np.array(want)
    assert len(got) >= 18 and np.ptp(want) > 20  # lenses up to 1.4 pitches out: offsets of +-10 px
    assert np.sum(dark) < 1e-3 * img.sum()
    assert np.max(np.abs(got - want)) < 0.4
    assert np.polyfit(want, got, 1)[0] == pytest.approx(1.0, abs=0.02)


def test_a_texture_through_an_ideal_lens_is_given_upright_at_its_image():
    """Imaged onto the lenses' apertures (their convex vertices, t/2 before the mid-plane), the texture is
    seen by each lens where it sits: a 2 x 2 texture puts its top-left value on the top-left quarter of the
    array (8 x 8 lenses: the quarters' borders are lens borders)."""
    cfg = small_lfm(8, 0.5 * LFM.mla.thickness_um * 1e-3)
    radiance = np.array([[1.0, 0.25], [0.5, 0.125]])
    r = Renderer(cfg, engine="numpy")
    tex = r.render(TextureScene(radiance=radiance), rays_per_pixel=20, seed=3).photons
    white = r.render(WhiteScene(), rays_per_pixel=20, seed=3).photons
    for m in range(1, 9):
        for n in range(1, 9):
            ratio = cell_window(cfg, tex, m, n)[0].sum() / cell_window(cfg, white, m, n)[0].sum()
            assert ratio == pytest.approx(radiance[(m - 1) // 4, (n - 1) // 4], rel=0.02)


@needs_numba
@pytest.mark.parametrize("sampler", ["sobol", "random"])
@pytest.mark.parametrize("defocus_mm", [None, 12.0, -8.0])
def test_engines_trace_an_ideal_lens_point_ray_by_ray_alike(sampler, defocus_mm):
    cfg = small_lfm(6, defocus_mm)
    x, y = lens_centre_mm(cfg, 3, 4)
    scene = PointScene(((x + 0.01, y),), 1e6)
    a = Renderer(cfg, engine="numpy", sampler=sampler).trace_batch(scene, 11, 40_000, point=scene.points_mm[0])
    b = Renderer(cfg, engine="numba", sampler=sampler).trace_batch(scene, 11, 40_000, point=scene.points_mm[0])
    assert len(a[0]) > 35_000
    assert np.array_equal(a[0], b[0])
    assert np.allclose(a[1], b[1], rtol=1e-12, atol=0)


@needs_numba
def test_engines_render_the_same_defocused_texture_through_an_ideal_lens():
    cfg = small_lfm(6, 5.0)
    scene = TextureScene(radiance=np.random.default_rng(4).random((64, 64)))
    a = Renderer(cfg, engine="numpy").render(scene, rays_per_pixel=4, seed=5, threads=2)
    b = Renderer(cfg, engine="numba").render(scene, rays_per_pixel=4, seed=5, threads=2)
    assert a.rays_landed == b.rays_landed
    assert np.allclose(a.photons, b.photons, rtol=1e-12, atol=0)


@pytest.mark.parametrize("data, key", [
    ({"geometry": {"image_defocus_mm": 1.0}}, "geometry.image_defocus_mm"),  # the thick Table 1 lens
    ({"main_lens": {"f_number": 4, "exit_pupil_mm": 50}, "geometry": {"image_defocus_mm": 60}}, "geometry.image_defocus_mm"),
])
def test_image_defocus_belongs_to_an_ideal_lens_and_behind_its_pupil(data, key):
    with pytest.raises(InputError, match=key.replace(".", r"\.")):
        config_from_dict(data)


def test_configs_without_image_defocus_keep_their_dicts():
    assert "image_defocus_mm" not in LFM.to_dict()["geometry"]
    assert small_lfm(4, 2.5).to_dict()["geometry"]["image_defocus_mm"] == 2.5


def test_the_microscope_simulates_a_point_scene_from_the_command_line(tmp_path):
    cfg = tmp_path / "lfm.toml"
    cfg.write_text((FIXTURES / "lfm_40x_relay.toml").read_text() + "\n[geometry]\nimage_defocus_mm = 3.0\n")
    out = tmp_path / "points.tiff"
    assert main(["simulate", "-c", str(cfg), "--scene", "points", "--points", "0,0;0.5,-0.4", "--rays", "200000",
                 "--no-noise", "--out", str(out), "-q"]) == 0
    assert out.exists() and Path(str(out) + ".sim.json").exists()
