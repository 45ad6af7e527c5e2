"""Identification with circular lens apertures (issue #22): a lens' flux does not answer to its focal
errors behind its circle, so the flux noise floor is low, and the baselines must not read a smooth
vignetting trend as deviations next to a defect or the array's edge.

Checked against the plain fact that a smooth trend holds no defect: index maps built here by hand (a
steep linear flux fall-off, one missing lens, one bright outlier), no lens but the seeded ones may be
flagged; and the same maps with square cells keep their old windows (unchanged behaviour)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mlaqc.inspection.baselines import local_deviations
from mlaqc.inspection.detection import DEVIATION_KEYS
from mlaqc.inspection.identify import identify
from mlaqc.inspection.results import LensMetrics
from mlaqc.models.signatures import FEATURES, RINGS
from mlaqc.optics.config import load_config

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
SMALL = load_config(FIXTURES / "small_camera.toml")
FLUX = FEATURES.index("flux")


def _circle_like_table():
    """The small camera's table with every flux response scaled to 2 %: what circular apertures do (the
    flux through a lens' circle hardly changes with its focal errors; the circle camera's tables set a
    flux floor of 9e-5, the cells' 4.8e-3), which sets the flux floor as low."""
    from mlaqc.inspection.pipeline import _models

    table = _models(SMALL)[1].tables[1]
    feats = {k: np.where(np.arange(len(FEATURES)) == FLUX, 0.02 * v, v) for k, v in table.features.items()}
    return dataclasses.replace(table, features=feats)


def _maps(rows: int, cols: int, slope_per_lens: float) -> dict[str, np.ndarray]:
    """Healthy index maps, all zero but flux: 1 at the top falling `slope_per_lens` per row and 0.37 of that
    per column (a steep vignetting), with a tiny deterministic ripple so no two values tie."""
    m, n = np.mgrid[:rows, :cols].astype(float)
    ripple = 1e-6 * np.sin(1.7 * m + 2.3 * n)
    maps = {k: np.zeros((rows, cols)) for k in DEVIATION_KEYS + RINGS}
    maps["flux"] = 1.0 - slope_per_lens * (m + 0.37 * n) + ripple
    return maps


@pytest.mark.parametrize("packing", ["square", "hex"])
def test_a_steep_flux_trend_with_a_missing_lens_and_an_outlier_flags_only_those(packing):
    rows, cols = 100, 100  # (the few lenses a defect's rank step reaches stay under 1 % of them)
    maps = _maps(rows, cols, 0.004)
    missing = np.zeros((rows, cols), bool)
    missing[40, 42] = True
    maps["flux"][40, 42] = 0.0  # a missing lens: its window is dark
    maps["flux"][60, 57] += 0.05  # a bright lens (a foreign anomaly)
    found = identify(LensMetrics(maps), missing, SMALL.qc, _circle_like_table(), packing=packing, aperture="circle")
    inner = np.zeros((rows, cols), bool)
    inner[4:-4, 4:-4] = True  # (the edges' clipped windows on a trend this steep are their own classes' matter)
    flagged = {(int(m), int(n)) for m, n in zip(*np.nonzero(found.flagged & inner))}
    assert flagged == {(40, 42), (60, 57)}


def test_the_second_rows_baseline_is_centred_on_a_trend():
    """A linear trend leaves no deviation where the baseline window is centred on its lens: on the second
    ring (the outermost ring left out of its window) with `centred`, while the off-centre window reads
    half a row of the trend (what square cells keep)."""
    rows, cols = 20, 20
    flux = _maps(rows, cols, 0.004)["flux"]
    off = local_deviations([flux], [""], packing="square")[0]
    on = local_deviations([flux], [""], packing="square", centred=True)[0]
    second = np.zeros((rows, cols), bool)
    second[2, 4:-4] = second[-3, 4:-4] = True
    assert np.abs(on[second]).max() < 1e-5
    assert np.abs(off[second]).min() > 0.5 * 0.004 * 0.5  # half a row's worth, at least half of it


def test_a_sub_pixel_phase_pattern_flags_no_lens_of_the_second_ring():
    """Healthy maps that vary only with each lens' sub-pixel phase (an array rotated 1.3°: how a rim
    sampled by the pixels reads, Airy rims most): the pattern is a property of the frame, removed per lens
    group. The second ring's windows behind circles are cut to 3 rows (centred), so they take up another
    share of it than the inner lenses' 5 x 5: fitted with the inner lenses, 13 of them were flagged here."""
    rows = cols = 100
    m, n = np.mgrid[:rows, :cols].astype(float)
    a, pitch = np.deg2rad(-1.3), 20.0476
    phase = (np.mod(10.3 + pitch * (n * np.cos(a) - m * np.sin(a)), 1.0),
             np.mod(7.6 + pitch * (n * np.sin(a) + m * np.cos(a)), 1.0))
    rng = np.random.default_rng(0)
    maps = _maps(rows, cols, 0.0)
    maps["flux"] = 1.0 + 1e-4 * rng.standard_normal((rows, cols))
    for k, key in enumerate(("asym_x", "asym_y", "offset_x_px", "offset_y_px")):
        a, b = phase[k % 2], phase[1 - k % 2]  # each index answers to both phases, one more than the other
        pattern = 0.03 * np.sin(2 * np.pi * a) + 0.01 * np.cos(4 * np.pi * a) + 0.02 * np.sin(2 * np.pi * b + k)
        maps[key] = pattern + 1e-3 * rng.standard_normal((rows, cols))
    found = identify(LensMetrics(maps), np.zeros((rows, cols), bool), SMALL.qc, _circle_like_table(),
                     phase=phase, packing="square", aperture="circle")
    assert not found.flagged.any()
