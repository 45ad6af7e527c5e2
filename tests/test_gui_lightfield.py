"""The app's light-field panel (offscreen, pytest-qt): it decodes the inspected frame in its worker thread,
shows the view its sliders pick and the refocused image its slope asks for, samples a flagged lens as
the inspection measured it, says a bad scene in one sentence, and the main window arms it after an
inspection and joins its thread on close. Frames are the analytic light fields of tests/test_decode.py."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")
pytest.importorskip("pytestqt")

sys.path.insert(0, str(Path(__file__).parent))

from test_decode import PITCH, RADIUS, centres, frame  # noqa: E402

from gui.lightfield import LightFieldPanel  # noqa: E402
from mlaqc.decode.lightfield import refocus  # noqa: E402
from mlaqc.inspection.results import Defect  # noqa: E402

MOVED = (4, 5)


def inspected(moved=(1.2, -0.8)):
    """A fake inspection: the analytic frame with lens U(5,6) moved, its grid, and that lens flagged."""
    x0, y0 = centres()
    x, y = centres({MOVED: moved})
    img = frame(x, y).astype(np.float32)
    grid = SimpleNamespace(grid_x_px=x0, grid_y_px=y0, measured_x_px=x, measured_y_px=y, missing=np.zeros(x.shape, bool),
                           pitch_px=(PITCH, PITCH), radius_px=np.full(x.shape, RADIUS), image_shape=img.shape,
                           packing="square", shape=x.shape)
    flag = Defect(MOVED[0] + 1, MOVED[1] + 1, "decenter", 7.0, "µm", 30.0, 12.0, False)
    return SimpleNamespace(result=SimpleNamespace(image=img, grid=grid, defects=(flag,)))


@pytest.fixture
def panel(qtbot):
    p = LightFieldPanel()
    qtbot.addWidget(p)
    yield p
    p.shutdown()
    assert p.thread is None


def _decoded(qtbot, p, scene=None):
    job = p.request_decode(scene)
    qtbot.waitUntil(lambda: p.lf is not None and p.job == job and "views" in p.status.text(), timeout=20_000)
    return p.lf


def test_panel_decodes_and_shows_the_chosen_view(qtbot, panel):
    assert not panel.decode_btn.isEnabled()
    panel.set_inspection(inspected(), cfg=None)
    assert panel.decode_btn.isEnabled()
    lf = _decoded(qtbot, panel)
    half = len(lf.view_offsets_px) // 2
    assert (panel.u.minimum(), panel.u.maximum()) == (-half, half)
    np.testing.assert_allclose(panel.img.image, np.where(lf.weights[half, half] > 0, lf.values[half, half], 0))
    panel.u.setValue(3)
    panel.v.setValue(-2)
    np.testing.assert_allclose(panel.img.image, lf.values[half - 2, half + 3])


def test_panel_samples_the_flagged_lens_as_measured(qtbot, panel):
    panel.set_inspection(inspected(), cfg=None)
    measured = _decoded(qtbot, panel)
    panel.lf = None
    panel.sampling.setCurrentIndex(1)  # the calibrated lattice
    lattice = _decoded(qtbot, panel)
    m, n = MOVED
    assert np.array_equal(measured.values[:, :, 2, 2], lattice.values[:, :, 2, 2])  # a healthy lens: the same
    offs = measured.view_offsets_px
    inner = np.hypot(offs[:, None], offs[None, :]) <= RADIUS - 3
    x0, y0 = centres()
    truth = frame(x0, y0)  # the lens where it belongs: what the measured sampling must read
    from mlaqc.decode.lightfield import decode, view_offsets
    from mlaqc.decode.sampling import LensSampling

    ref = decode(truth.astype(np.float32), LensSampling(x0, y0, np.ones_like(x0), np.ones_like(x0), "square", PITCH,
                                                         RADIUS, truth.shape, "lattice"), view_offsets(RADIUS))
    assert np.abs(measured.values[:, :, m, n] - ref.values[:, :, m, n])[inner].max() < 1e-4
    assert np.abs(lattice.values[:, :, m, n] - ref.values[:, :, m, n])[inner].max() > 0.02


def test_panel_refocuses_in_its_worker(qtbot, panel):
    panel.set_inspection(inspected(), cfg=None)
    lf = _decoded(qtbot, panel)
    panel.mode.setCurrentIndex(1)
    panel.slope.setValue(25)
    want = refocus(lf, 0.25)[0]
    qtbot.waitUntil(lambda: panel.img.image is not None and panel.img.image.shape == want.shape
                    and np.allclose(panel.img.image, want), timeout=20_000)


def test_a_scene_that_cannot_be_read_is_one_sentence(qtbot, panel, tmp_path):
    from mlaqc.optics.config import load_config

    panel.set_inspection(inspected(), cfg=load_config(Path(__file__).parent.parent / "fixtures" / "small_camera.toml"))
    panel.request_decode(str(tmp_path / "no-such.tiff"))
    qtbot.waitUntil(lambda: not panel.error.isHidden(), timeout=20_000)
    text = panel.error.text()
    assert "does not exist" in text and text.count(".") >= 1 and "\n" not in text


def test_the_main_window_arms_the_panel_and_joins_its_thread(qtbot, offline_window):
    w = offline_window
    assert "lightfield" in w.docks and not w.lightfield_panel.decode_btn.isEnabled()
    w.inspectionShown.emit(inspected())
    assert w.lightfield_panel.decode_btn.isEnabled()
    _decoded(qtbot, w.lightfield_panel)
    w.close()
    assert w.lightfield_panel.thread is None
