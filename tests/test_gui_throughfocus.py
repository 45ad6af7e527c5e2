"""The QC app with the second measurement (issue #12): a white frame plus through-focus pinhole frames of
the same array, inspected together; both frames on display, per-lens readings from both. Offscreen, no
devices (the window is built without connecting them). Timings are printed, never asserted."""

from __future__ import annotations

import json
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")
pytest.importorskip("pytestqt")

from PySide6.QtCore import Qt  # noqa: E402

from gui.app import MainWindow  # noqa: E402
from gui.widgets import DefectTableModel  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SMALL = str(ROOT / "fixtures" / "small_camera.toml")
# radius errors (both surfaces) on lenses at the centre of the (0, 0) pinhole lattice's fully lit discs
SEEDED = {(10, 10): 0.05, (19, 19): -0.05}


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """A white frame and one +u / -u pair (u = ±10 mm, offset (0, 0)) of the small camera with SEEDED, each
    with its .sim.json record; plus a copy of the +u frame without a record and a wrong-size frame with one."""
    from mlaqc.inspection.raw_write import write_raw
    from mlaqc.optics.config import load_config
    from mlaqc.optics.errormap import ErrorMap
    from mlaqc.optics.simulate import simulate, write_simulation
    from mlaqc.optics.throughfocus import ThroughFocus, frame_config, scene

    t0 = time.perf_counter()
    cfg = load_config(SMALL)
    em = ErrorMap.zeros(24, 24)
    for (m, n), eps in SEEDED.items():
        em = em.with_lens(m, n, radius_front_rel=eps, radius_back_rel=eps)
    d = tmp_path_factory.mktemp("throughfocus")
    white = d / "white.tiff"
    write_simulation(white, simulate(cfg, None, em, rays_per_pixel=100, seed=11), cfg)
    pair = []
    for k, u in enumerate((10.0, -10.0)):
        # the first protocol on purpose (f/8, 9 lenses apart: SEEDED sit at its pinholes), not the shipped one
        tf = ThroughFocus(focus_offset_mm=u, f_number=8.0, spacing_lenses=9, offset_lenses=(0, 0))
        path = d / f"tf_{u:+g}_0_0.tiff"
        write_simulation(path, simulate(frame_config(cfg, tf), scene(cfg, tf), em, seed=21 + k), cfg, protocol=tf)
        pair.append(path)
    bare = d / "no_record.tiff"
    bare.write_bytes(pair[0].read_bytes())
    small = d / "small.tiff"
    write_raw(small, np.full((64, 64), 300, np.uint16), bits=12)
    small.with_name(small.name + ".sim.json").write_text(json.dumps(
        {"protocol": {"focus_offset_mm": -10.0, "f_number": 8.0, "spacing_lenses": 9, "offset_lenses": [0, 0]}}))
    print(f"\nthrough-focus test frames rendered in {time.perf_counter() - t0:.1f} s")
    return white, pair, bare, small


@pytest.fixture
def window(offline_window):
    return offline_window


def choose_frames(qtbot, w: MainWindow, paths) -> None:
    """Pick through-focus frames and wait until the frames worker has checked them (good or bad)."""
    w.set_through_focus([str(p) for p in paths])
    qtbot.waitUntil(lambda: w.tf_pending is None, timeout=10_000)


def one_sentence(text: str) -> bool:
    return bool(text) and "\n" not in text and "Traceback" not in text and text.rstrip().endswith(".")


def focal_reading(text: str) -> float:
    """The through-focus Δf/f (in %) from the lens detail's pinhole-frames line."""
    m = re.search(r"focal Δf/f ([+-]\d+\.\d+) ± (\d+\.\d+) %", text)
    assert m, text
    return float(m.group(1))


def test_white_and_through_focus_frames_inspected_together(qtbot, window, frames, tmp_path):
    w = window
    white, pair, bare, small = frames
    ip = w.inspection_panel
    w.open_raw(str(white))

    # bad picks: one sentence each in the panel, nothing in use, the app keeps going
    for paths, words in (([bare, pair[1]], "no record"), ([pair[0]], "no partner"), ([pair[0], small], "pixels")):
        choose_frames(qtbot, w, paths)
        assert ip.error.isVisible() and words in ip.error.text(), ip.error.text()
        assert one_sentence(ip.error.text()), ip.error.text()
        assert w.tf_frames == () and ip.throughfocus.text() == "none"
    assert ip.run.isEnabled() and ip.open_tf.isEnabled()

    # the pair: checked, listed, carried by the request
    choose_frames(qtbot, w, reversed(pair))
    assert not ip.error.isVisible()
    assert [f.u_mm for f in w.tf_frames] == [10.0, -10.0] and w.tf_frames[0].offset == (0, 0)
    assert ip.throughfocus.text() == "2 frames: 1 +u / −u pair at u = ±10 mm"

    # cancel while the worker reads the through-focus frames: nothing is shown, the app stays usable
    texts: list[str] = []
    reached, go = threading.Event(), threading.Event()

    def on_progress(_job: int, _pct: int, text: str) -> None:  # runs in the inspection thread
        texts.append(text)
        if text.startswith("reading through-focus frames") and not reached.is_set():
            reached.set()
            go.wait(10.0)  # hold the worker in the through-focus step until Cancel was pressed

    cancelled = threading.Event()
    w.inspection_worker.progress.connect(on_progress, Qt.ConnectionType.DirectConnection)
    w.inspection_worker.cancelled.connect(lambda _job: cancelled.set(), Qt.ConnectionType.DirectConnection)
    w.run_inspection()
    qtbot.waitUntil(reached.is_set, timeout=30_000)
    w.cancel_inspection()
    go.set()
    qtbot.waitUntil(cancelled.is_set, timeout=30_000)  # the worker stopped at its next stage
    assert w.view is None and ip.run.isEnabled() and w.banner.verdict == "IDLE"

    # the full run: white inspection, then the pinhole pair read on its grid and combined
    texts.clear()
    t0 = time.perf_counter()
    with qtbot.waitSignal(w.inspectionShown, timeout=60_000) as shown:
        w.run_inspection()
    view = shown.args[0]
    print(f"\ninspection with one through-focus pair: {time.perf_counter() - t0:.2f} s "
          f"(timings {view.result.timings_s})")
    assert any(t.startswith("reading through-focus frames") for t in texts), texts
    r = view.result
    tf = r.through_focus
    assert tf is not None and "through_focus" in r.timings_s
    assert [f.path for f in view.frames] == [str(p) for p in pair]
    assert "through-focus:" in w.table_title.text() and "through-focus:" in view.summary

    # per lens: the pinhole frames' reading beside the white frame's, with the seeded sign
    for (m, n), eps in SEEDED.items():
        assert tf.covered[m - 1, n - 1]
        w.select_lens(m, n)
        assert w.lens_detail.lens == (m, n)
        assert "white frame" in w.lens_detail.title.text() and "focal Δf/f" in w.lens_detail.title.text()
        line = w.lens_detail.throughfocus.text()
        assert w.lens_detail.throughfocus.isVisible() and "pinhole frames" in line
        assert "radius-equivalent" in line and "covered" in line and "optical centre" in line
        reading = focal_reading(line)
        print(f"U({m},{n}) radius {eps:+.2f}: {line}")
        assert np.sign(reading) == np.sign(eps) and abs(reading) > 1.0
        # the defects table: the lens is there, read (or flagged) by the pinhole pairs, with that sign
        model = w.table_model
        row = model.row_of(m, n)
        assert row >= 0, (m, n)
        d = model.defects[row]
        assert d.error_type == "radius" and "through_focus_z" in d.indexes and np.sign(d.magnitude) == np.sign(eps)
        source = model.data(model.index(row, DefectTableModel.COLUMNS.index("Source")))
        assert "pinholes" in source, source
    # a lens no pair lit fully says so
    far = np.argwhere(~np.asarray(tf.covered))[0] + 1
    w.select_lens(int(far[0]), int(far[1]))
    assert "not covered" in w.lens_detail.throughfocus.text()

    # the frame selector: the white frame, then each pinhole frame under the same rings
    box = w.image.frame_box
    assert box.isVisible() and box.count() == 3
    assert box.itemText(1).startswith(pair[0].name) and "u = +10 mm" in box.itemText(1) and "offset (0, 0)" in box.itemText(1)
    white_img = np.asarray(w.image.img.image)
    rings = len(w.image.ring_item.points())
    assert rings == len(view.rings) >= len(SEEDED)
    with qtbot.waitSignal(w.frameShown, timeout=10_000) as sh:
        box.activated.emit(2)  # as when the operator picks the -u frame
    assert sh.args == [2] and w.image.frame_index == 2 and box.currentIndex() == 2
    shown_img = np.asarray(w.image.img.image)
    assert shown_img.shape == white_img.shape and not np.array_equal(shown_img, white_img)
    assert np.median(shown_img) < 0.1 * np.median(white_img)  # a pinhole frame is mostly dark
    assert len(w.image.ring_item.points()) == rings and w.image.ring_item.isVisible()
    assert w.image.mode == "result"
    w.select_lens(*next(iter(SEEDED)))  # selecting a lens keeps the frame on display
    assert w.image.frame_index == 2
    with qtbot.waitSignal(w.frameShown, timeout=10_000):
        box.activated.emit(0)
    assert w.image.frame_index == 0 and np.array_equal(np.asarray(w.image.img.image), white_img)

    # the report set is still written
    out = tmp_path / "report"
    with qtbot.waitSignal(w.reportWritten, timeout=30_000):
        w.export_report(str(out))
    assert json.loads((out / "report.json").read_text())["verdict"] == r.verdict

    # frames that break at inspection time (a -u frame of another size): one sentence, then clearing works
    w.tf_pending = (str(pair[0]), str(small))  # as if picked a moment before Inspect (checked in the worker)
    w.run_inspection()
    qtbot.waitUntil(lambda: ip.error.isVisible(), timeout=30_000)
    assert one_sentence(ip.error.text()) and "pixels" in ip.error.text() and w.banner.verdict == "ERROR"
    w.tf_pending = None
    w.clear_through_focus()
    assert ip.throughfocus.text() == "none"
    with qtbot.waitSignal(w.inspectionShown, timeout=30_000) as again:
        w.run_inspection()
    assert again.args[0].result.through_focus is None and not w.image.frame_box.isVisible()
    w.select_lens(*next(iter(SEEDED)))
    assert not w.lens_detail.throughfocus.isVisible()
