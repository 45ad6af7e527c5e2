"""The QC app with dark frames (issue #24): "Dark frames…" beside "Through-focus frames…"; the master
dark is subtracted from the inspected raw, its bad pixels replaced, and the verdict line says so; a dark
that does not match the frame is one sentence in the panel. Offscreen, no devices."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")
pytest.importorskip("pytestqt")

import analytic_frames as am  # noqa: E402
from mlaqc.inspection.raw_write import write_raw  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SMALL = str(ROOT / "fixtures" / "small_camera.toml")


@pytest.fixture
def window(offline_window):
    return offline_window


def test_dark_frames_in_the_app(qtbot, window, tmp_path):
    model = am.AnalyticModel(shape=(496, 496), lenses=(24, 24), exit_pupil_px=900.0, rotation_deg=0.7)
    level = am.DarkPattern(shape=(496, 496)).level()
    rng = np.random.default_rng(1)
    counts = 64 + model.render() * 0.8 * 4031 + level + 3 * rng.standard_normal(level.shape)
    raw = tmp_path / "white.tiff"
    write_raw(raw, np.clip(np.rint(counts), 0, 4095).astype(np.uint16), bits=12, black_level=64)
    darks = []
    for k in range(3):
        darks.append(tmp_path / f"dark{k}.tiff")
        write_raw(darks[-1], am.dark_frame(level, 3.0, rng, 12, 64), bits=12, black_level=64)
    w = window
    assert any(a.text() == "Dark frames…" for a in w.menuBar().actions()[0].menu().actions())
    assert w.inspection_panel.open_darks.text() == "Dark frames…"
    w.open_raw(str(raw))
    w.set_darks([str(p) for p in darks])
    assert w.inspection_panel.darks.text().startswith("3 frames")
    with qtbot.waitSignal(w.inspectionShown, timeout=60_000) as shown:
        w.run_inspection()
    r = shown.args[0].result
    assert r.detection_limit["noise"]["dark"]["hot_pixels"] == 2000
    assert "dark-subtracted" in shown.args[0].summary
    assert [(d.m, d.n) for d in r.defects] == []  # a healthy array: no hot pixel left to flag

    # a dark taken at another exposure: one sentence, no result
    Path(str(darks[0]) + ".meta.json").write_text(json.dumps({"dark": True, "exposure_us": 500.0}))
    Path(str(raw) + ".meta.json").write_text(json.dumps({"dark": False, "exposure_us": 1000.0}))
    w.set_darks([str(darks[0])])
    with qtbot.waitSignal(w.inspection_worker.failed, timeout=60_000) as failed:
        w.run_inspection()
    assert "was exposed 500 µs but the frame white.tiff 1000 µs" in failed.args[1]
    w.set_darks(())
    assert w.inspection_panel.darks.text() == "none"
