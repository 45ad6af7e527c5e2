"""Detection limits that do not depend on the array's size (issue #22 part 4): a frame's noise is that of
one sub-image, so the same optics at the same rays per pixel report the same limits on a small and a
large array, whatever defects they carry; a defect's light in its neighbours' windows is no noise."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from analytic_frames import AnalyticModel, Anomaly

from mlaqc.inspection.filters import lattice_max_of_neighbours, with_neighbours
from mlaqc.inspection.spreads import class_sigmas
from mlaqc.inspection.lens_classes import noise_classes
from mlaqc.inspection.phase_pattern import phase_model, remove_phase_pattern
from mlaqc.inspection.pipeline import inspect_image, prepare
from mlaqc.inspection.rawio import RawFrame
from mlaqc.optics.config import CameraConfig, load_config
from mlaqc.optics.errormap import ErrorMap, lens_error_fields
from mlaqc.optics.lattice import Lattice
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene
from mlaqc.optics.sensor import expose, white_level

SMALL = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")
LIMIT_KEYS = ("pitch_um", "decenter_um", "radius_rel_neg", "radius_rel_pos", "thickness_um_neg", "thickness_um_pos")
# the paper's nine example errors (bench/paper_examples.py), on a 3 x 3 lattice of lenses around the centre
NINE = (("pitch", 1.0, 90.0), ("pitch", 1.5, 30.0), ("pitch", 2.0, 225.0),
        ("decenter", 5.0, 0.0), ("decenter", 7.0, 135.0), ("decenter", 10.0, 90.0),
        ("radius", -0.10, None), ("radius", 0.05, None), ("radius", 0.08, None))


def _camera(lenses: int) -> CameraConfig:
    """The small camera's optics (Table 1's) with `lenses` a side on a sensor just holding them."""
    side = 16 * math.ceil((lenses * SMALL.layout.subimage_pitch_px + 8) / 16)
    return dataclasses.replace(SMALL, mla=dataclasses.replace(SMALL.mla, count_w=lenses, count_h=lenses),
                               sensor=dataclasses.replace(SMALL.sensor, width_px=side, height_px=side))


def _nine(lenses: int, step: int) -> tuple[ErrorMap, set[tuple[int, int]]]:
    """The nine `step` lenses apart around the array's centre; their U(m, n)."""
    em, seeded = ErrorMap.zeros(lenses, lenses), set()
    c = (lenses + 1) // 2
    for k, (kind, mag, d) in enumerate(NINE):
        m, n = c + step * (k // 3 - 1), c + step * (k % 3 - 1)
        em = em.with_lens(m, n, **lens_error_fields(kind, mag, d))
        seeded.add((m, n))
    return em, seeded


def _inspect(cfg: CameraConfig, em: ErrorMap, rays_per_pixel: float, seed: int):
    ph = Renderer(cfg, em).render(WhiteScene(), rays_per_pixel=rays_per_pixel, seed=seed).photons
    s = cfg.sensor
    frame = RawFrame(expose(ph, s, seed=seed + 1), s.bit_depth, None, s.black_level_dn, white_level(s), {}, "test")
    return inspect_image(prepare(frame), cfg)


@pytest.fixture(scope="module")
def frames():
    """The nine on 12 x 12 (4 apart: 81 of 144 lenses are a seeded one or its neighbour) and on 24 x 24
    (6 apart), and the 12 x 12 array healthy, at 100 rays/pixel (sensor noise); and the nine on 12 x 12
    at 50 rays/pixel, where a decenter next to the edge lit its inner neighbour more than its own score."""
    out = {}
    for name, lenses, step, rays, seed in (("12", 12, 4, 100, 7), ("24", 24, 6, 100, 7), ("12 healthy", 12, 0, 100, 7),
                                           ("12 at 50", 12, 4, 50, 8)):
        em, seeded = _nine(lenses, step) if step else (ErrorMap.zeros(lenses, lenses), set())
        out[name] = (_inspect(_camera(lenses), em, rays, seed), seeded)
    return out


def _ratio(a: dict, b: dict, key: str) -> float:
    va, vb = a[key], b[key]
    assert va is not None and vb is not None, key
    return max(va, vb) / min(va, vb)


@pytest.mark.parametrize("a, b", [("12", "24"), ("12", "12 healthy"), ("24", "12 healthy")])
def test_the_same_optics_report_the_same_limits_whatever_the_size_and_the_defects(frames, a, b):
    """The limits of two frames of the same optics at the same rays per pixel agree within 1.5 x (they
    were 1.6-2.1 x apart on 12 against 24 x 24 when nine defects' neighbourhoods widened the noise)."""
    la, lb = frames[a][0].detection_limit, frames[b][0].detection_limit
    for key in LIMIT_KEYS:
        assert _ratio(la, lb, key) <= 1.5, (key, la[key], lb[key])


@pytest.mark.parametrize("name", ["12", "24", "12 at 50"])
def test_every_seeded_lens_is_found_and_no_neighbour_is_flagged_for_its_light(frames, name):
    result, seeded = frames[name]
    found = {(d.m, d.n) for d in result.defects}
    assert found == seeded


def test_a_noise_free_frame_has_finite_limits_alike_on_two_sizes():
    """Analytic frames (no code shared with the tracer), noise-free, a few anomalies each: every limit is
    finite (the noise floors hold z bounded), at most the QC tolerance, and the same on 12 x 12 and 24 x 24."""
    limits = []
    for lenses in (12, 24):
        cfg = _camera(lenses)
        c = lenses // 2
        model = AnalyticModel(shape=(cfg.sensor.height_px, cfg.sensor.width_px), lenses=(lenses, lenses),
                              exit_pupil_px=900.0, rotation_deg=0.4, phase_px=(0.3, 0.2),
                              anomalies=(Anomaly(c - 3, c - 3, "shift", 0.5, 30.0), Anomaly(c, c + 2, "blur", 2.0),
                                         Anomaly(c + 3, c - 1, "dim", 0.8)))
        lim = inspect_image(model.render().astype(np.float32), cfg).detection_limit
        qc = cfg.qc
        tolerance = {"pitch_um": qc.pitch_um, "decenter_um": qc.decenter_um, "radius_rel_neg": qc.radius_rel,
                     "radius_rel_pos": qc.radius_rel, "thickness_um_neg": qc.thickness_um,
                     "thickness_um_pos": qc.thickness_um}
        for key in LIMIT_KEYS:
            assert lim[key] is not None and 0 < lim[key] <= tolerance[key], (lenses, key, lim[key])
        limits.append(lim)
    for key in LIMIT_KEYS:
        assert _ratio(limits[0], limits[1], key) <= 1.5, key


# ------------------------------------------------------------------ the statistics, against known noise


def _blocks(shape: tuple[int, int], centres) -> np.ndarray:
    """The 3 x 3 blocks around `centres` (0-based): a defect and its 8 neighbours."""
    mask = np.zeros(shape, bool)
    for r, c in centres:
        mask[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2] = True
    return mask


NINE_12 = [(r, c) for r in (1, 5, 9) for c in (1, 5, 9)]  # the nine 4 apart on 12 x 12


def test_the_noise_left_by_defect_neighbourhoods_is_the_sub_images_own():
    """Unit Gaussian noise on 12 x 12 lenses, nine 3 x 3 neighbourhoods carrying a defect's light (+3 to
    +6 sigma, inside the outlier cut): with them the inner spread is far above 1 (the cause); without them
    it is the noise's own."""
    rng = np.random.default_rng(11)
    dev = rng.normal(size=(12, 12))
    disturbed = _blocks(dev.shape, NINE_12)
    dev[disturbed] += rng.uniform(3.0, 6.0, disturbed.sum())
    inner = noise_classes(dev.shape) == 2
    assert class_sigmas(dev)[inner][0] > 1.5
    assert 0.75 < class_sigmas(dev, exclude=disturbed)[inner][0] < 1.3


def test_a_phase_pattern_fitted_without_the_defects_neighbourhoods_is_the_true_one():
    """A known sub-pixel phase pattern plus unit noise on 12 x 12 lenses, the nine neighbourhoods shifted
    by +3 sigma (within the fit's 4-sigma cut): fitted without them, the quiet lenses' residuals are the
    noise (mean 0, spread 1); fitted with them, the pattern's offset is pulled by about 1.5 sigma."""
    rng = np.random.default_rng(5)
    rows = cols = 12
    pitch = 20.047820979297924
    m, n = np.mgrid[:rows, :cols]
    phase = (np.mod(0.3 + n * pitch + m * 0.07, 1.0), np.mod(0.6 + m * pitch - n * 0.07, 1.0))
    truth = 2.0 * np.cos(2 * np.pi * phase[0]) - 1.5 * np.sin(2 * np.pi * phase[1])
    noise = rng.normal(size=(rows, cols))
    disturbed = _blocks((rows, cols), NINE_12)
    values = truth + noise + np.where(disturbed, 3.0, 0.0)
    model = phase_model(phase)
    quiet = (noise_classes((rows, cols)) == 2) & ~disturbed
    clean = remove_phase_pattern([values], model, disturbed)[0] - noise
    pulled = remove_phase_pattern([values], model)[0] - noise
    assert abs(np.mean(clean[quiet])) < 0.4 and np.std(clean[quiet]) < 0.5
    assert abs(np.mean(pulled[quiet])) > 1.0


@pytest.mark.parametrize("packing", ["square", "hex"])
def test_neighbours_are_the_lenses_one_pitch_away(packing):
    """with_neighbours / lattice_max_of_neighbours against the geometry: a lens' neighbours are the lenses
    whose centres lie one pitch from its own (square: and the diagonals, sqrt(2) pitches)."""
    rows, cols = 9, 8
    lat = Lattice(packing, rows, cols)
    u, v = lat.uv(*np.mgrid[:rows, :cols])
    d = np.hypot(u.ravel()[:, None] - u.ravel()[None], v.ravel()[:, None] - v.ravel()[None])
    near = (d > 0) & (d < (1.5 if packing == "square" else 1.01))
    rng = np.random.default_rng(2)
    mask = rng.random((rows, cols)) < 0.1
    grown = mask.ravel() | (near & mask.ravel()[None]).any(axis=1)
    assert np.array_equal(with_neighbours(mask, packing).ravel(), grown)
    a = rng.random((rows, cols))
    brute = np.where(near, a.ravel()[None], 0.0).max(axis=1)
    assert np.array_equal(lattice_max_of_neighbours(a, packing).ravel(), brute)
