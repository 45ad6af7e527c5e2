"""Regenerate docs/screenshot.png: the app on the paper's Table 1 camera (offscreen, no display needed).

    QT_QPA_PLATFORM=offscreen python -m gui.screenshot [--out docs/screenshot.png] [--work DIR] [--config TOML]

It renders a Table 1 white image with seeded defects (as `mlaqc demo` does), runs a 3 x 3 wafer scan on
the mock camera (one inspected frame per array), inspects the seeded image, selects the worst lens and
grabs the window. Prints the inspection's GUI-thread stall and the live-view frame rate on the way.
Takes a minute or two. `--config` takes another camera (e.g. fixtures/hex_camera.toml: the same optics with
a hex-packed MLA, drawn as hexagonal cells).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(ROOT / "docs" / "screenshot.png"))
    p.add_argument("--work", help="folder for the simulated raw and the scan (default: a temporary folder)")
    p.add_argument("--defects", type=int, default=20)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--rays-per-pixel", type=float, default=30.0)
    p.add_argument("--no-scan", action="store_true")
    p.add_argument("--config", default=str(ROOT / "fixtures" / "paper_table1.toml"),
                   help="camera config TOML (default: the paper's Table 1 camera)")
    args = p.parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

    from mlaqc.optics.config import load_config
    from mlaqc.optics.errormap import DefectSpec, random_defects
    from mlaqc.optics.simulate import simulate, write_simulation

    work = Path(args.work or tempfile.mkdtemp(prefix="mlaqc-shot-"))
    work.mkdir(parents=True, exist_ok=True)
    table1 = Path(args.config)
    cfg = load_config(table1)
    raw = work / f"{table1.stem}_defects{args.defects}_seed{args.seed}.dng"
    if not raw.exists():
        t = time.perf_counter()
        spec = DefectSpec(pitch_um=(1.0, 4.0), decenter_um=(5.0, 12.0), radius_rel=(0.05, 0.2))
        errors = random_defects(cfg.mla.count_h, cfg.mla.count_w, args.defects, args.seed, spec=spec,
                                packing=cfg.mla.packing)
        sim = simulate(cfg, None, errors, rays_per_pixel=args.rays_per_pixel, seed=args.seed)
        write_simulation(raw, sim, cfg)
        print(f"rendered {raw} in {time.perf_counter() - t:.1f} s")

    import numpy as np
    from PySide6.QtCore import QEventLoop, QTimer
    from PySide6.QtWidgets import QApplication

    from gui.app import MainWindow

    app = QApplication.instance() or QApplication([])
    app.setStyle("Fusion")

    def wait(pred, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            app.processEvents(QEventLoop.ProcessEventsFlag.AllEvents, 50)
            if pred():
                return True
            time.sleep(0.005)
        return False

    from drivers.wafer import default_pitch_mm

    step_mm = default_pitch_mm(cfg)  # the mock wafer's arrays sit this far apart (21 mm for Table 1)
    w = MainWindow(f"mock://?config={table1}&wafer=3x3&rpp=2", "sim+grbl://?speed_mm_s=200", str(table1))
    w.resize(1760, 1080)
    w.show()
    assert wait(lambda: w.camera_obj is not None and w.stage_obj is not None, 20), w.errors
    w.home_stage()
    assert wait(lambda: w.stage_state.get("homed"), 30), w.errors
    w.move_stage(10.0, 10.0)
    assert wait(lambda: w.stage_state.get("pos") == (10.0, 10.0) and not w.stage_panel._busy, 30), w.errors

    # live view on the full sensor
    w.set_live(True)
    assert wait(lambda: w.image.displayed >= 2, 120), w.errors
    n0, t0 = w.image.displayed, time.perf_counter()
    wait(lambda: False, 3.0)
    fps = (w.image.displayed - n0) / (time.perf_counter() - t0)
    w.set_live(False)
    wait(lambda: not w.camera_panel.live.isChecked(), 10)
    print(f"live view, {cfg.sensor.width_px}x{cfg.sensor.height_px} 16-bit mock frames: {fps:.1f} frames/s displayed "
          f"(the mock's sensor noise model, not the display, sets the pace)")

    if not args.no_scan:
        scan_out = work / time.strftime("scan-%H%M%S")
        plan = work / f"{table1.stem}_wafer_plan.toml"
        plan.write_text(f"[scan]\nsettle_s = 0.02\n\n[raster]\norigin_mm = [10.0, 10.0]\nstep_mm = [{step_mm}, {step_mm}]\n"
                        "count = [3, 3]\nserpentine = true\n")
        w.load_plan(str(plan))
        w.start_scan(str(scan_out))
        assert wait(lambda: not w.scan_running, 900), w.errors
        print("scan:", w.scan_panel.status.text())
        w.move_stage(10.0, 10.0)
        wait(lambda: w.stage_state.get("pos") == (10.0, 10.0) and not w.stage_panel._busy, 30)

    # the inspection, with the event loop watched
    stamps = [time.perf_counter()]
    timer = QTimer()
    timer.setInterval(10)
    timer.timeout.connect(lambda: stamps.append(time.perf_counter()))
    w.open_raw(str(raw))
    timer.start()
    w.run_inspection()
    assert wait(lambda: w.view is not None and w.token is None, 300), w.errors
    wait(lambda: False, 0.3)
    timer.stop()
    gaps = np.diff(stamps)
    at = stamps[int(np.argmax(gaps))] - stamps[0]
    print(f"inspection of {cfg.sensor.width_px}x{cfg.sensor.height_px}: {w.view.elapsed_s:.1f} s in the worker; longest GUI-thread stall "
          f"{gaps.max() * 1000:.0f} ms at {at:.2f} s of {stamps[-1] - stamps[0]:.2f} s "
          f"({len(gaps)} ticks of a 10 ms timer)")
    print(w.view.summary)

    first = w.table_model.defects[0] if w.table_model.defects else None
    if first is not None:
        w.select_lens(first.m, first.n)
    w.image.grid_box.setChecked(False)
    w.image.fit_view()
    w.docks["scan"].raise_()
    wait(lambda: False, 0.5)
    if first is not None:  # the cursor over that lens: pixel value and U(m,n) in the status bar
        from PySide6.QtCore import QPointF

        x, y = w.view.centre(first.m, first.n)
        w.image.glw.scene().sigMouseMoved.emit(w.image.vb.mapViewToScene(QPointF(x + 2, y - 1)))
        wait(lambda: False, 0.2)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    w.grab().save(str(out))
    print(f"wrote {out}")
    w.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
