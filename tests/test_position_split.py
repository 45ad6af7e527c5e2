"""Pitch or decenter from a white image (mlaqc.models.position_split): the neighbour contrast by hand, the
typing rule, the physics it rests on (sag-intersection boundaries: a decenter tilts its neighbours towards
it, a pitch error changes their flux evenly; grid boundaries: neither touches a neighbour), and the whole
inspection typing seeded lenses of a ray-traced frame."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mlaqc.inspection.pipeline import inspect_image, prepare
from mlaqc.inspection.rawio import RawFrame
from mlaqc.models.position_split import (SPLIT_Z, PositionSplit, neighbour_contrast, position_split, split_limits,
                                         type_position)
from mlaqc.models.signatures import nominal_windows, patch_config
from mlaqc.optics.config import default_config, load_config
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import WhiteScene
from mlaqc.optics.sensor import expose, white_level

SAG = "sag-intersection"
SMALL = load_config(Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml")


def with_boundaries(cfg, boundaries: str):
    return dataclasses.replace(cfg, mla=dataclasses.replace(cfg.mla, boundaries=boundaries))


def test_neighbour_contrast_is_the_four_neighbours_tilt_towards_the_lens():
    ax = np.zeros((3, 3))
    ay = np.zeros((3, 3))
    ax[1, 0], ax[1, 2] = 0.3, -0.2  # left brighter on its right side, right brighter on its left side
    ay[0, 1], ay[2, 1] = 0.1, 0.05  # upper tilted towards the lens, lower away from it
    c = neighbour_contrast(ax, ay)
    assert c[1, 1] == pytest.approx(0.3 + 0.2 + 0.1 - 0.05)
    assert np.isnan(c[0, 0]) and np.isnan(c[1, 0]) and np.isnan(c[2, 2])  # a neighbour off the array


def test_typing_rule_types_only_what_the_noise_separates():
    split = PositionSplit({"pitch": 0.04, "decenter": 0.12}, {"pitch": 0.19, "decenter": 0.095}, "k")
    sigma = 0.002
    assert type_position(split, 0.06, 0.5, sigma)[0] == "decenter"  # 0.12 * 0.5 = 0.06
    assert type_position(split, 0.021, 0.5, sigma)[0] == "pitch"  # 0.04 * 0.5 = 0.02
    kind, z = type_position(split, 0.003, 0.05, sigma)  # predictions 0.002 / 0.006 apart by 2 sigma
    assert kind == "position" and z == pytest.approx(2.0)
    assert type_position(split, float("nan"), 0.5, sigma)[0] == "position"
    # the smallest shift typed is SPLIT_Z sigma over the predictions' gap, in µm of each kind
    shift = SPLIT_Z * sigma / 0.08
    assert split_limits(split, sigma) == {"pitch_um": pytest.approx(shift / 0.19, rel=3e-3),
                                          "decenter_um": pytest.approx(shift / 0.095, rel=3e-3)}  # 3 digits
    assert split_limits(None, sigma) is None


def test_grid_boundaries_cannot_split_and_the_table_1_split_ships():
    # no boundary moves: no neighbour sees either error
    assert position_split(with_boundaries(default_config(), "grid")) is None
    split = position_split(default_config())  # the default is sag-intersection: its split ships
    assert split is not None and split is position_split(with_boundaries(default_config(), SAG))
    # a decenter's contrast per px of own shift is several times a pitch error's (measured: 3.5 x)
    assert split.contrast_per_px["decenter"] > 2.5 * split.contrast_per_px["pitch"] > 0
    # own sub-image shift per µm: a whole-lens shift moves it about twice as far as a rear-surface decenter
    assert split.shift_px_per_um["pitch"] / split.shift_px_per_um["decenter"] == pytest.approx(2.0, rel=0.1)


def _halves(img: np.ndarray, cfg, m: int, n: int) -> tuple[float, float]:
    """Flux of the left and right halves of lens [m, n]'s window (the patch grid is known exactly)."""
    win, cx, _ = nominal_windows(img, cfg)
    w = win[m, n]
    cut = int(round(cx[m, n]))
    return float(w[:, :cut].sum()), float(w[:, cut + 1:].sum())


@pytest.mark.parametrize("direction", [0.0, 180.0])
def test_sag_boundaries_a_decenter_tilts_its_neighbours_towards_it_a_pitch_error_does_not(direction):
    """The physics the split rests on, both ways along x: a rear-surface decenter moves only the rear
    boundary, so only the rays leaving through that strip change and each neighbour's side facing the lens
    brightens relative to its far side; a whole-lens shift changes the neighbours' apertures evenly."""
    cfg = with_boundaries(patch_config(default_config(), 5), SAG)
    render = lambda em: Renderer(cfg, em).render(WhiteScene(), rays_per_pixel=600, seed=3).photons
    base = render(ErrorMap.zeros(5, 5))
    tilt = {}
    for kind, fields in (("decenter", {"decenter_um": 6.0}), ("pitch", {"pitch_um": 3.0})):
        img = render(ErrorMap.zeros(5, 5).with_lens(3, 3, **fields, **{f"{kind}_dir_deg": direction}))
        (l0, r0), (l1, r1) = _halves(base, cfg, 2, 1), _halves(img, cfg, 2, 1)
        (L0, R0), (L1, R1) = _halves(base, cfg, 2, 3), _halves(img, cfg, 2, 3)
        # each neighbour's (near half - far half) change, relative to its flux: left neighbour's near side is its right
        tilt[kind] = ((r1 - r0) - (l1 - l0)) / (l0 + r0) + ((L1 - L0) - (R1 - R0)) / (L0 + R0)
    assert tilt["decenter"] > 3e-3  # measured about 6e-3
    assert abs(tilt["pitch"]) < 0.25 * tilt["decenter"]


def _frame(cfg, em: ErrorMap, rays_per_pixel: float, seed: int) -> np.ndarray:
    ph = Renderer(cfg, em, sampler="random").render(WhiteScene(), rays_per_pixel=rays_per_pixel, seed=seed).photons
    s = cfg.sensor
    raw = expose(ph * (0.8 * s.full_well_e / (s.qe * ph.max())), s, seed=seed)
    return prepare(RawFrame(raw, s.bit_depth, None, s.black_level_dn, white_level(s), {}, "test"))


@pytest.mark.parametrize("boundaries", [SAG, "grid"])
def test_inspection_types_pitch_and_decenter_on_a_sag_boundary_frame(boundaries):
    """Seeded pitch errors and decenters in several directions on a ray-traced frame: all are found and
    none else; with sag-intersection boundaries every lens this frame can type (its reported
    pitch-vs-decenter limit) is typed right with its own magnitude and direction, the others stay
    'position'; with grid boundaries all stay 'position' and the limit says the frame cannot tell."""
    cfg = with_boundaries(SMALL, boundaries)
    seeded = {(7, 7): ("pitch", 2.0, 30.0), (7, 17): ("decenter", 8.0, 200.0),
              (17, 7): ("decenter", 6.0, 95.0), (17, 17): ("pitch", 3.5, 300.0)}
    em = ErrorMap.zeros(24, 24)
    for (m, n), (kind, mag, d) in seeded.items():
        em = em.with_lens(m, n, **{f"{kind}_um": mag, f"{kind}_dir_deg": d})
    result = inspect_image(_frame(cfg, em, 400, 7), cfg)
    found = {(d.m, d.n): d for d in result.defects}
    assert set(found) == set(seeded)
    limit = result.detection_limit["pitch_vs_decenter"]
    if boundaries == "grid":
        assert limit is None and {d.error_type for d in result.defects} == {"position"}
        return
    for lens, (kind, mag, d) in seeded.items():
        got = found[lens]
        if mag >= 1.2 * limit[f"{kind}_um"]:
            assert got.error_type == kind, (lens, got)
            assert got.magnitude == pytest.approx(mag, rel=0.3) and not got.alternatives
            assert abs((got.direction_deg - d + 180) % 360 - 180) < 15
        else:
            assert got.error_type in (kind, "position"), (lens, got)
    assert sum(found[lens].error_type != "position" for lens in seeded) >= 2  # at 400 rays/pixel: 8 µm decenter, 3.5 µm pitch


def test_a_replicated_arrays_frame_inspected_with_grid_boundaries_is_inspected_as_one():
    """Issue #22: whatever the config says, a sag-intersection frame must not come out as 'position' with
    its decenters read at half their size. The decenters tilt their neighbours (a moved boundary), which
    grid apertures cannot do: the frame is inspected with sag-intersection boundaries and a note says so.
    A grid frame with the same errors keeps the grid model (tested above: every shift stays 'position')."""
    seeded = {(7, 7): ("pitch", 2.0, 30.0), (7, 17): ("decenter", 8.0, 200.0), (17, 17): ("pitch", 3.5, 300.0)}
    em = ErrorMap.zeros(24, 24)
    for (m, n), (kind, mag, d) in seeded.items():
        em = em.with_lens(m, n, **{f"{kind}_um": mag, f"{kind}_dir_deg": d})
    grid_cfg = with_boundaries(SMALL, "grid")
    result = inspect_image(_frame(with_boundaries(SMALL, SAG), em, 400, 7), grid_cfg)
    assert result.lens_boundaries == SAG
    assert any("replicated (sag-intersection)" in n for n in result.notes)
    found = {(d.m, d.n): d for d in result.defects}
    assert set(found) == set(seeded)
    assert found[(7, 17)].error_type == "decenter" and found[(7, 17)].magnitude == pytest.approx(8.0, rel=0.3)
    plain = inspect_image(_frame(grid_cfg, em, 400, 7), grid_cfg)
    assert plain.lens_boundaries == "grid" and not any("replicated" in n for n in plain.notes)
    assert {d.error_type for d in plain.defects} == {"position"}
