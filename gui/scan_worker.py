"""The scan job, off the GUI thread (threading model: gui.workers).

`ScanWorker` (the ``scan`` thread) runs `drivers.scan.ScanRunner` with the devices the app already has
open, wrapped so that once the operator aborts (`ScanControl`, the pause/abort flags the GUI sets) no move
and no capture starts: the abort raises inside the runner, which stops the stage and leaves the manifest
consistent. Pause waits between positions.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gui.qt  # noqa: F401 - first: the PySide6 reference-count guard
from PySide6.QtCore import QObject, Signal, Slot

from gui.workers import one_sentence


class ScanAborted(KeyboardInterrupt):
    """Raised inside the scan runner when the operator aborts (the runner treats it like Ctrl-C)."""


class ScanControl:
    """Pause/abort flags shared by the GUI (sets) and the scan worker (waits/reads)."""

    def __init__(self) -> None:
        self._abort = threading.Event()
        self._running = threading.Event()
        self._running.set()

    def abort(self) -> None:
        self._abort.set()
        self._running.set()

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

    @property
    def aborted(self) -> bool:
        return self._abort.is_set()

    @property
    def paused(self) -> bool:
        return not self._running.is_set()

    def check(self) -> None:
        if self._abort.is_set():
            raise ScanAborted()

    def wait_while_paused(self, on_pause: Any = None) -> None:
        """Block while paused (abort wakes it); raise ScanAborted if aborted."""
        self.check()
        if not self._running.is_set():
            if on_pause is not None:
                on_pause(True)
            while not self._running.wait(0.05):
                pass
            if on_pause is not None:
                on_pause(False)
        self.check()


class _AbortableStage:
    """The stage as the scan runner sees it: motion raises ScanAborted once the operator aborted."""

    def __init__(self, stage: Any, control: ScanControl) -> None:
        self._stage = stage
        self._control = control

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stage, name)

    def _motion(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        from drivers.stage import StageStopped

        self._control.check()
        try:
            return fn(*args, **kwargs)
        except StageStopped:
            if self._control.aborted:
                raise ScanAborted() from None
            raise

    def home(self, *a: Any, **k: Any) -> None:
        return self._motion(self._stage.home, *a, **k)

    def move_to(self, *a: Any, **k: Any) -> None:
        return self._motion(self._stage.move_to, *a, **k)

    def move_by(self, *a: Any, **k: Any) -> None:
        return self._motion(self._stage.move_by, *a, **k)


class _AbortableCamera:
    """The camera as the scan runner sees it: no new capture starts once the operator aborted."""

    def __init__(self, camera: Any, control: ScanControl) -> None:
        self._camera = camera
        self._control = control

    def __getattr__(self, name: str) -> Any:
        return getattr(self._camera, name)

    def capture(self, *a: Any, **k: Any) -> Any:
        self._control.check()
        return self._camera.capture(*a, **k)


@dataclass
class ScanRequest:
    plan: Any  # drivers.scan_plan.ScanPlan
    out_dir: str
    camera: Any
    stage: Any
    cfg: Any = None  # inspect each position when set
    resume: bool = False
    control: ScanControl = field(default_factory=ScanControl)


class ScanWorker(QObject):
    """Runs one scan at a time in the ``scan`` thread."""

    positionStarted = Signal(int)  # plan index
    positionDone = Signal(int, object)  # plan index, {'verdict', 'flagged', 'out_of_tolerance', 'file'}
    progress = Signal(int, int)  # done, total
    event = Signal(object)  # the runner's event dicts
    pausedChanged = Signal(bool)
    finished = Signal(str, object)  # outcome ('finished', 'aborted', 'failed'), message

    @Slot(object)
    def run(self, req: ScanRequest) -> None:
        from drivers.scan import ScanRunner

        control = req.control
        verdicts: dict[int, dict[str, Any]] = {}
        current: list[Any] = []  # the position being attempted

        def before(runner: Any, pos: Any) -> None:
            control.wait_while_paused(self.pausedChanged.emit)
            current[:] = [pos]
            self.positionStarted.emit(pos.index)

        def progress(done: int, total: int) -> None:
            if current:  # called after each recorded (and inspected) position
                pos = current.pop()
                info = dict(verdicts.get(pos.index, {}))
                info.setdefault("verdict", None)
                name = pos.file_names(req.plan.frames_per_position, req.plan.suffix)[0]
                info["file"] = str(Path(req.out_dir) / name)
                self.positionDone.emit(pos.index, info)
            self.progress.emit(done, total)
            control.check()

        def on_event(ev: dict) -> None:
            if ev.get("event") in ("inspect_failed", "position_failed") and "index" in ev:
                verdicts[int(ev["index"])] = {"verdict": "ERROR", "error": str(ev.get("error") or ev.get("reason", ""))}
            self.event.emit(ev)

        inspect_hook = None
        if req.cfg is not None:
            cfg = req.cfg

            def inspect_hook(frame: Any) -> dict:
                from mlaqc.inspection.pipeline import inspect_image, load_frame

                result = inspect_image(load_frame(frame.path, cfg), cfg, source=str(frame.path))
                out = sum(1 for d in result.defects if not d.within_tolerance)
                info = {"verdict": result.verdict, "flagged": len(result.defects), "out_of_tolerance": out,
                        "defects": [d.to_json_dict() for d in result.defects], "source": frame.path.name}
                verdicts[int(frame.record["index"])] = info
                return info

        try:
            runner = ScanRunner(req.plan, req.out_dir, camera=_AbortableCamera(req.camera, control),
                                stage=_AbortableStage(req.stage, control), resume=req.resume, inspect=inspect_hook,
                                progress=progress, before_position=before, on_event=on_event)
            result = runner.run()
        except KeyboardInterrupt as exc:  # ScanInterrupted (our abort, via the runner)
            self.finished.emit("aborted", str(exc) or "scan aborted; the stage was stopped.")
            return
        except Exception as exc:  # noqa: BLE001
            self.finished.emit("failed", one_sentence(exc))
            return
        self.finished.emit("finished", result.summary())
