"""Headless XY scans: move, settle, capture, write atomically, record in a fsync'd manifest; resumable.

This module holds the runner (`ScanRunner`, `run_scan`) and the inspection hook's interface; the plan
is read by drivers.scan_plan, the manifest by drivers.scan_manifest, the run's counts are drivers.scan_result.

Plan (TOML; see fixtures/scan_plan_raster.toml and fixtures/scan_plan_list.toml)::

    [scan]                      # every key optional
    settle_s = 0.05             # wait after each move before capturing (s, >= 0)
    frames_per_position = 1     # raw files per position
    average = 1                 # frames averaged into each file
    retries = 3                 # extra attempts per position after a device error or an uninspectable frame
    retry_delay_s = 0.5         # pause before a retry (s, >= 0)
    move_timeout_s = 30.0       # deadline of each move (s, > 0)
    capture_timeout_s = 5.0     # deadline of each frame (s, > 0)
    home = "auto"               # auto: home if not homed (also after a reconnect); always; never
    format = "tiff"             # tiff or dng
    exposure_us = 10000.0       # optional, set once (and after every camera reopen)
    gain = 1.0                  # optional

    [raster]                    # either a raster ...
    origin_mm = [10.0, 10.0]    # first position (x, y)
    step_mm = [5.0, 5.0]        # spacing along x and y (may be negative)
    count = [3, 3]              # positions along x and y
    serpentine = true           # reverse every other line (default true)
    fast_axis = "x"             # the axis that changes from one position to the next (default x)

    [[positions]]               # ... or an explicit list, in order
    x_mm = 10.0
    y_mm = 10.0
    label = "W(1,1)"            # optional; default p00001, p00002, ...

    [through_focus]             # optional: the second measurement's frames at every position
    focus_offsets_mm = [5.0, -5.0]  # u of each lattice (mlaqc.optics.throughfocus), |u| >= 0.5, distinct
    f_number = 11.0             # main lens stopped to f/N for these frames
    spacing_lenses = 4          # pinhole images this many lens pitches apart
    offsets = "cover"           # lattice shifts: "cover" (every lens inside some disc) or [[0, 0], [3, 0], ...]
                                # (hex arrays: axial steps [q, r], q along a row, r rows down with r/2 pitch of x)
    exposure_us = 10000.0       # optional: exposure of these frames (default: the white frames')
    settle_s = 0.05             # optional: wait after each carrier move (default: scan.settle_s)
    average = 1                 # optional: frames averaged into each file (default: scan.average)
    iris = "camera"             # camera: the runner sets f/N through the camera (set_f_number) and back;
                                # manual: the lens is at f/N for the whole scan (needs white_frames = false)
    white_frames = true         # also capture the scan's white frames at each position
    config = "camera.toml"      # optional camera config (relative to the plan) for the geometry; default:
                                # the camera's own (mock) or the Table 1 camera
    z_white_mm = 50.0           # the carrier (mlaqc.optics.throughfocus.Carrier): Z with the mask in the
    a_centre_mm = 10.0          # white target's plane, A centring the lattices, B of the clear window,
    b_window_mm = 0.0           # and the spacing of the mask's fields along B (window, then one lattice
    field_pitch_mm = 25.0       # per focus offset, in the order of focus_offsets_mm)

Every key is checked; an error names it (``scan plan 'p.toml': key 'raster.count' must be ...``).

Through-focus frames: at each position, after the white frames (taken with the carrier's clear window
on the axis and the iris back at its starting f-number and the white exposure), the runner stops the
iris to f/N, sets the exposure, and for each focus offset and lattice offset moves the stage's
auxiliary axes Z, A, B to `carrier_axes` (Z from `stage_z_mm`, the field and offset on A and B),
settles, reads them back and captures. The stage must have the axes (URL ``aux=z,a,b``) and every
target within their soft limits, checked before the first move. Files ``pos_NNNNN_tfKK.tiff``
(K = 1.. in plan order: focus offsets outer, lattice offsets inner); each sidecar's ``context`` has
``through_focus`` (the frame's `ThroughFocus` record with its derived facts, the carrier targets and
the axes read back) and the manifest lists each file's ``through_focus`` record (null for white
frames). The header gets ``through_focus``: the expanded frames, the carrier, and where the camera
config came from; a resume with other frames is refused. The inspection hook runs on white frames only,
each with its position's pinhole frames (`ScanFrame.through_focus`; see Inspection below).

Output folder: ``pos_NNNNN.tiff`` (``pos_NNNNN_fK.tiff`` with several frames per position; N is the
1-based index in plan order) with ``.meta.json`` sidecars (see drivers.capture), ``manifest.jsonl``
and ``events.jsonl``.

Manifest (JSON Lines, the source of truth for --resume): line 1 is the header
``{"type": "header", "format": "mlaqc-scan-manifest", "version": 1, "plan_digest", "plan", "camera",
"stage", "camera_settings", "created", "truth", "truth_digest", "versions"}`` (`truth` is the camera's ground truth when it
has one, e.g. the mock's wafer: every array's position and error map) and ``camera_settings`` (the
camera's settings read back at the start; the mock's include its camera config). Then exactly one line per completed
position, appended and fsync'd only after its frames and sidecars are on disk:
``{"type": "position", "index", "label", "target_mm", "position_mm" (read back), "files": [{"file",
"sha256", "bytes", "sidecar", "sequence", "warnings"}], "attempts", "rejected": [{"file", "sha256", "bytes",
"sidecar", "sequence", "warnings", "attempt", "reason"}], "failed", "completed", "timing_s": {"move",
"settle", "capture", "write", "recover", "total"}, "truth"}`` (`truth`: which wafer array the frame shows
and its offset, from the mock camera; `rejected`: the frames of earlier attempts that could not be inspected;
`failed`: null, or why the position's own frames cannot be inspected either).

Resume: positions with a record whose files still match their checksums are skipped; a record whose
files are missing or altered, a torn last line (a kill mid-append) and leftover temporary files are
dropped, and the manifest is rewritten atomically without them; a frame on disk without a record (a
kill between the frame write and the manifest append) is simply captured again and overwritten.
A plan with other positions or capture settings than the header's is refused, and so is a camera whose
ground truth differs from the header's (another mock wafer or seed).

Faults: a DeviceError while moving or capturing makes the position retry up to `retries` times; before
each retry the failed device is reconnected (stage: closed and reopened from its URL, then homed; camera:
`reopen()`, exposure and gain re-applied). When the retries are used up, or on Ctrl-C, the stage is
stopped, the manifest is left consistent and ScanFailed (DeviceError, exit 3) or ScanInterrupted (exit
130) says in one sentence where the scan stopped and that --resume continues it.

Frames that cannot be inspected: a white frame that is black or saturated (`drivers.capture.exposure_problem`,
the inspection's own check) makes the position capture again within the same `retries` (no reconnect). The
rejected attempt's white frames are kept as ``pos_NNNNN_rejectedK.tiff`` (K: the first free number) with
sidecars whose ``context`` has ``rejected`` (the reason), listed under the position record's ``rejected``;
an event ``frame_rejected`` each. When the retries are used up the last attempt's frames are recorded as the
position's frames, the record's ``failed`` says why, a ``position_failed`` event is written, the inspection
hook is not run on it, and the scan goes on with the next position (a resume does not capture it again).
Pinhole (through-focus) frames are sparse spots by design: their exposure is checked per spot when they are
inspected, not here.

Inspection: `inspect` is a callable ``(frame: ScanFrame) -> dict | None`` run for each white raw file right
after its position is recorded (a ScanFrame carries the raw and sidecar paths, the manifest record, the
manifest header with the camera's settings and ground truth, and `through_focus`: the pinhole frames of
the same position, all on disk by then, since a position is recorded only once every frame of it is); a
returned dict is written to ``<raw name>.inspect.json``. Pinhole frames are not inspected on their own:
the default hook reads them with their white frame into one combined verdict. An exception in it is logged
as an ``inspect_failed`` event and the scan goes on (the frame is already safe). A resumed scan first
inspects the recorded positions whose white frames have no ``.inspect.json`` yet (a kill while the hook
ran, or a failed inspection: tried again), then goes on. `default_inspect_hook()` finds
``mlaqc.inspection.pipeline.scan_frame_hook`` once the inspection pipeline provides it, else returns None
(``mlaqc scan --inspect`` then says so and scans).
"""

from __future__ import annotations

import importlib
import json
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.camera import camera_from_url
from drivers.camera.base import Camera
from drivers.capture import Grab, SavedFrame, jsonable, check_out_dir, exposure_problem, grab, save_frame, versions
from drivers.scan_manifest import (MANIFEST_FORMAT, MANIFEST_NAME, _digest, _fsync_dir, _manifest_bytes, _ManifestWriter,
                                   _now_iso, _rejected_path, _temp_files, read_manifest, verify_record)
from drivers.scan_plan import PlanPosition, ScanPlan, load_plan
from drivers.scan_result import ScanResult
from mlaqc.atomic import write_bytes_atomic, write_json_atomic
from mlaqc.errors import DeviceError, InputError, MlaqcError
from mlaqc.optics.config import CameraConfig, default_config, load_config
from mlaqc.optics.throughfocus import Carrier, ThroughFocus, carrier_axes, white_axes

log = logging.getLogger(__name__)

EVENTS_NAME = "events.jsonl"
CARRIER_AXES = ("z", "a", "b")
HOME_TIMEOUT_S = 120.0
READBACK_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class ScanFrame:
    """What an inspection hook gets for each raw file of a recorded position."""

    path: Path  # the raw file
    sidecar: Path  # its .meta.json
    record: dict[str, Any]  # the position's manifest record
    header: dict[str, Any]  # the manifest header: plan, camera URL and settings, ground truth (mock)
    out_dir: Path
    through_focus: tuple[Path, ...] = ()  # the pinhole frames recorded at the same position, in plan order


InspectHook = Callable[[ScanFrame], "dict | None"]


class ScanFailed(DeviceError):
    """The scan stopped because a device kept failing at one position (exit status 3)."""


class FramesRejected(Exception):
    """An attempt's white frames cannot be inspected (black or saturated); the position is captured again."""


class ScanInterrupted(MlaqcError, KeyboardInterrupt):
    """Ctrl-C stopped the scan; the stage was stopped and the manifest is consistent (exit status 130)."""

    exit_status = 130


class ScanRunner:
    """Runs one scan plan into one folder; see the module docstring for the guarantees.

    `camera` and `stage` are device URLs (the runner opens, reopens and closes them) or open objects
    (the runner reconnects them in place and leaves them open). `before_position(runner, position)` is
    called before each position is attempted (a test hook for fault injection); `on_event(dict)` sees
    every event also written to events.jsonl; `progress(done, total)` is called after each position."""

    def __init__(self, plan: ScanPlan, out_dir: str | os.PathLike[str], *, camera: Camera | str, stage: Any,
                 resume: bool = False, inspect: InspectHook | None = None,
                 progress: Callable[[int, int], None] | None = None,
                 before_position: Callable[[ScanRunner, PlanPosition], None] | None = None,
                 on_event: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.plan = plan
        self.out = Path(out_dir)
        self.resume = resume
        self.inspect = inspect
        self.progress = progress
        self.before_position = before_position
        self.on_event = on_event
        if isinstance(camera, str):
            self.camera_url: str | None = camera
            self.camera: Camera = camera_from_url(camera)  # InputError for a bad URL, before anything else
            self._own_camera = True
        else:
            self.camera_url, self.camera, self._own_camera = None, camera, False
        if isinstance(stage, str):
            from drivers.url import parse_device_url

            parse_device_url(stage)
            self.stage_url: str | None = stage
            self.stage: Any = None
            self._own_stage = True
        else:
            self.stage_url, self.stage, self._own_stage = None, stage, False
        self.manifest_path = self.out / MANIFEST_NAME
        self.result = ScanResult(self.out, self.manifest_path, len(plan.positions))
        self._done: dict[int, dict[str, Any]] = {}
        self._header: dict[str, Any] | None = None
        self._rewrite = False
        self._writer: _ManifestWriter | None = None
        self._events = None
        self._stage_bad = False
        self._camera_bad = False
        self._attached = False
        self._current: PlanPosition | None = None
        self._pending: list[dict[str, Any]] = []  # events found before events.jsonl is open
        self._tf_frames: list[ThroughFocus] = []  # through-focus frames of each position (empty without)
        self._tf_axes: list[dict[str, float]] = []  # the carrier's Z, A, B for each
        self._tf_header: dict[str, Any] | None = None
        self._white_f_number: float | None = None
        self._rejected: list[dict[str, Any]] = []  # the current position's rejected frames (manifest items)

    # ------------------------------------------------------------ public

    def run(self) -> ScanResult:
        """Run (or resume) the scan to the end; raise ScanFailed, ScanInterrupted or InputError."""
        start = time.monotonic()
        try:
            self._prepare_through_focus()
            self._read_out_dir()
            self._open_devices()
            self._check_limits()
            self._setup_out_dir()
            self._event("resume" if self.result.resumed else "start", positions=self.result.total,
                        done=self.result.resumed, camera=self._camera_label(), stage=self._stage_label())
            self._loop()
            self._event("finished", **self._timing())
            return self.result
        except KeyboardInterrupt:
            stopped = self._stop_stage()
            msg = self._stopped_message("interrupted", stopped)
            self._event("interrupted", message=msg, **self._timing())
            raise ScanInterrupted(msg) from None
        finally:
            self.result.elapsed_s = time.monotonic() - start
            self._shutdown()

    # ------------------------------------------------------------ preparation

    def _read_out_dir(self) -> None:
        """Decide fresh vs resume and load what is already done (read only)."""
        check_out_dir(self.out)
        if not self.manifest_path.exists():
            if self.out.is_dir() and any(self.out.iterdir()):
                raise InputError(f"output folder {str(self.out)!r} is not empty and holds no scan manifest; "
                                 "choose an empty or new folder")
            return
        if not self.resume:
            raise InputError(f"output folder {str(self.out)!r} already holds a scan ({MANIFEST_NAME}); pass --resume "
                             "to continue it or choose another folder")
        data = read_manifest(self.manifest_path)
        if data.header.get("plan_digest") != self.plan.digest:
            raise InputError(f"the scan in {str(self.out)!r} was made with a different plan (other positions, "
                             "frames, averaging or format); resume it with its own plan or choose another folder")
        truth_fn = getattr(self.camera, "truth", None)
        recorded = data.header.get("truth_digest")
        if recorded is not None and callable(truth_fn) and _digest(truth_fn()) != recorded:
            raise InputError(f"the scan in {str(self.out)!r} was made with a camera showing other ground truth "
                             "(a different mock wafer or seed); resume it with the same camera URL")
        recorded_tf = (data.header.get("through_focus") or {}).get("frames")
        ours = None if self._tf_header is None else self._tf_header["frames"]
        if recorded_tf != ours:
            raise InputError(f"the scan in {str(self.out)!r} was made with other through-focus frames (another camera "
                             "config, carrier or lattice offsets); resume it with the same camera, plan and config")
        self._header = data.header
        self._rewrite = data.torn
        for rec in data.records:
            index = rec["index"]
            if not 0 <= index < len(self.plan.positions):
                raise InputError(f"scan manifest {str(self.manifest_path)!r} records position {index + 1}, "
                                 "which the plan does not have")
            if index in self._done:
                self._rewrite = True
            why = verify_record(self.out, rec)
            if why:
                self._rewrite = True
                self._done.pop(index, None)
                self._pending.append({"event": "invalid_record", "index": index, "reason": why})
                continue
            self._done[index] = rec
        self.result.resumed = len(self._done)

    def _prepare_through_focus(self) -> None:
        """Expand the plan's [through_focus] for this camera (no device I/O): frames, carrier axes, header."""
        tf = self.plan.through_focus
        if tf is None:
            return
        if tf.config is not None:
            cfg, origin = load_config(tf.config), tf.config
        elif isinstance(getattr(self.camera, "cfg", None), CameraConfig):
            cfg, origin = self.camera.cfg, "camera"
        else:
            cfg, origin = default_config(), "table1"
        self._tf_frames = tf.frames(cfg)
        self._tf_axes = [{k: round(v, 6) for k, v in carrier_axes(cfg, tf.carrier, f).items()} for f in self._tf_frames]
        self._white_f_number = round(cfg.layout.main.efl / cfg.main_lens.diameter_mm, 6)
        from mlaqc.optics.simulate import protocol_record

        self._tf_header = {
            "frames": [protocol_record(cfg, f) | {"carrier_axes_mm": a} for f, a in zip(self._tf_frames, self._tf_axes)],
            "white_axes_mm": white_axes(tf.carrier), "white_f_number": self._white_f_number,
            "carrier": tf.carrier.to_dict(), "config_source": origin, "config": cfg.to_dict(), "iris": tf.iris,
            "white_frames": tf.white_frames,
        }

    def _open_devices(self) -> None:
        """Open the camera and the stage (URLs), home if the plan says so, apply exposure and gain."""
        if self._own_camera or not self.camera.is_open:
            self.camera.open()
        if self._own_stage:
            self.stage = self._open_stage()
        elif not self.stage.is_connected:
            self.stage.connect()
        if self.plan.home == "always" or (self.plan.home == "auto" and not self.stage.homed):
            self._home()
        self._apply_camera_settings()
        attach = getattr(self.camera, "attach_stage", None)
        if callable(attach):
            attach(self._stage_reading)
            self._attached = True

    def _stage_reading(self) -> tuple[float, float, dict[str, float] | None] | None:
        """What a following (mock) camera sees of the stage: (x, y, auxiliary axes or None), None before a report."""
        stage = self.stage
        pos = None if stage is None else stage.last_position
        if pos is None:
            return None
        aux = getattr(stage, "last_aux", None)
        return float(pos[0]), float(pos[1]), (dict(aux) if aux else None)

    def _open_stage(self) -> Any:
        from drivers.stage import open_stage

        return open_stage(self.stage_url)

    def _home(self) -> None:
        t0 = time.monotonic()
        self.stage.home(timeout_s=HOME_TIMEOUT_S)
        self.result.home_s += time.monotonic() - t0

    def _apply_camera_settings(self) -> None:
        if self.plan.exposure_us is not None:
            self.camera.set_exposure_us(self.plan.exposure_us)
        if self.plan.gain is not None:
            self.camera.set_gain(self.plan.gain)

    def _check_limits(self) -> None:
        """Refuse the whole plan up front if any position (or carrier target) is outside the stage's soft
        limits, if the stage lacks the carrier's axes, or if the camera cannot set the iris it must."""
        tf = self.plan.through_focus
        if tf is not None:
            have = tuple(getattr(self.stage, "aux_axes", ()))
            missing = [a.upper() for a in CARRIER_AXES if a not in have]
            if missing:
                raise InputError(f"scan plan {self.plan.source!r} has through-focus frames, but stage {self._stage_label()} "
                                 f"has no {', '.join(missing)} axis; they move the pinhole mask (name the axes in the "
                                 "stage URL, e.g. aux=z,a,b)")
            aux_limits = getattr(self.stage, "aux_limits", {})
            for k, (frame, axes) in enumerate(zip(self._tf_frames, self._tf_axes), start=1):
                for name, value in (*axes.items(), *(white_axes(tf.carrier).items() if tf.white_frames else ())):
                    lo, hi = aux_limits[name]
                    if not lo <= value <= hi:
                        raise InputError(f"scan plan {self.plan.source!r}: through-focus frame {k} (u {frame.focus_offset_mm:+g} mm, "
                                         f"offset {frame.offset_lenses}) needs {name.upper()}={value:.3f} mm, outside the "
                                         f"stage's soft limits ({name} {lo:g}..{hi:g} mm); check the carrier keys")
            shown = getattr(self.camera, "carrier", None)  # a camera that models the mask itself (the mock)
            if isinstance(shown, Carrier) and shown != tf.carrier:
                raise InputError(f"scan plan {self.plan.source!r} describes a pinhole mask ({_mask_text(tf.carrier, shown)}) "
                                 f"other than the one camera {self._camera_label()} shows ({_mask_text(shown, tf.carrier)}); "
                                 "make the "
                                 "plan's [through_focus] and the camera's mask agree")
            if tf.iris == "camera" and (not callable(getattr(self.camera, "set_f_number", None))
                                        or getattr(self.camera, "has_iris", True) is False):
                raise InputError(f"camera {self._camera_label()} cannot set its iris, which through_focus.iris = 'camera' "
                                 "needs; set the lens to f/N by hand with iris = 'manual' and white_frames = false")
        limits = getattr(self.stage, "limits", None)
        if limits is None:
            return
        for pos in self.plan.positions:
            if not limits.contains(pos.x_mm, pos.y_mm):
                raise InputError(f"scan plan {self.plan.source!r}: position {pos.index + 1} ({pos.label}, "
                                 f"x={pos.x_mm:g} y={pos.y_mm:g} mm) is outside the stage's soft limits ({limits})")

    def _setup_out_dir(self) -> None:
        """Create the folder and header (fresh) or clean up and compact the manifest (resume)."""
        self.out.mkdir(exist_ok=True)
        self._events = open(self.out / EVENTS_NAME, "a", encoding="utf-8")
        for stray in _temp_files(self.out):
            stray.unlink(missing_ok=True)
            self._event("removed_temp_file", file=stray.name)
        for ev in self._pending:
            self._event(**ev)
        if self._header is None:
            self._header = self._make_header()
            write_bytes_atomic(self.manifest_path, _manifest_bytes(self._header, []))
        elif self._rewrite:
            records = sorted(self._done.values(), key=lambda r: r.get("completed", ""))
            write_bytes_atomic(self.manifest_path, _manifest_bytes(self._header, records))
            self._event("manifest_compacted", records=len(records))
        _fsync_dir(self.out)
        self._writer = _ManifestWriter(self.manifest_path)

    def _make_header(self) -> dict[str, Any]:
        truth = None
        truth_fn = getattr(self.camera, "truth", None)
        if callable(truth_fn):
            truth = truth_fn()
        return {"type": "header", "format": MANIFEST_FORMAT, "version": 1, "plan_digest": self.plan.digest,
                "plan": self.plan.to_dict(), "camera": self._camera_label(), "stage": self._stage_label(),
                "camera_settings": jsonable(self.camera.settings()), "created": _now_iso(), "truth": truth,
                "truth_digest": None if truth is None else _digest(truth),
                "versions": versions(), **({"through_focus": self._tf_header} if self._tf_header else {})}

    def _camera_label(self) -> str:
        return self.camera_url or self.camera.url

    def _stage_label(self) -> str:
        return self.stage_url or getattr(self.stage, "url", repr(self.stage))

    # ------------------------------------------------------------ the loop

    def _loop(self) -> None:
        total = self.result.total
        loop_start = time.monotonic()
        try:
            if self.progress is not None:
                self.progress(self.result.done, total)
            for pos in self.plan.positions:
                if pos.index in self._done:
                    self._inspect_missed(pos)
                    continue
                self._current = pos
                if self.before_position is not None:
                    self.before_position(self, pos)
                try:
                    self._position(pos)
                except InputError as exc:  # e.g. the disk filled up or the folder vanished: stop cleanly
                    stopped = self._stop_stage()
                    msg = self._stopped_message("stopped", stopped, error=exc)
                    self._event("failed", message=msg, **self._timing())
                    raise InputError(msg) from None
                if self.progress is not None:
                    self.progress(self.result.done, total)
            self._current = None
            self._reopen_iris()
        finally:
            self.result.loop_s += time.monotonic() - loop_start

    def _reopen_iris(self) -> None:
        """After a scan with through-focus frames: the iris back at full aperture (best effort)."""
        tf = self.plan.through_focus
        if tf is None or tf.iris != "camera" or not self.camera.is_open:
            return
        try:
            self.camera.set_f_number(self._white_f_number)  # type: ignore[attr-defined]
        except MlaqcError as exc:  # a device fault, or a full aperture the lens cannot reach
            self._event("iris_not_reopened", error=str(exc))

    def _position(self, pos: PlanPosition) -> None:
        """Attempt a position until it is recorded or the retries are used up."""
        attempt = 0
        self._rejected = []
        while True:
            attempt += 1
            phase = ["stage"]
            try:
                record = self._attempt(pos, attempt, phase)
            except FramesRejected:  # (the frames and the event are already written)
                self.result.retries += 1
                if self.plan.retry_delay_s:
                    time.sleep(self.plan.retry_delay_s)
                continue
            except DeviceError as exc:
                device = phase[0]
                self._event("device_error", index=pos.index, label=pos.label, attempt=attempt, device=device,
                            error=str(exc))
                if device == "stage":
                    self._stage_bad = True
                else:
                    self._camera_bad = True
                if attempt > self.plan.retries:
                    stopped = self._stop_stage()
                    msg = self._stopped_message("stopped", stopped, attempts=attempt, error=exc)
                    self._event("failed", message=msg, **self._timing())
                    raise ScanFailed(msg) from None
                self.result.retries += 1
                if self.plan.retry_delay_s:
                    time.sleep(self.plan.retry_delay_s)
                continue
            self._done[pos.index] = record
            self.result.captured += 1
            if record["failed"]:
                self.result.failed.append(pos.label)
                self._event("position_failed", index=pos.index, label=pos.label, attempts=attempt,
                            reason=record["failed"])
            self._run_inspect(pos, record)
            return

    def _attempt(self, pos: PlanPosition, attempt: int, phase: list[str]) -> dict[str, Any]:
        """One try: recover devices, move, settle, read back, capture (white, then through-focus), write, record."""
        t0 = time.monotonic()
        phase[0] = "stage"
        self._recover_stage()
        phase[0] = "camera"
        self._recover_camera()
        t_recover = time.monotonic() - t0
        phase[0] = "stage"
        t1 = time.monotonic()
        self.stage.move_to(pos.x_mm, pos.y_mm, timeout_s=self.plan.move_timeout_s)
        t2 = time.monotonic()
        if self.plan.settle_s:
            time.sleep(self.plan.settle_s)
        t3 = time.monotonic()
        self.result.motion_s += t3 - t1
        read_back = tuple(float(v) for v in self.stage.position(timeout_s=READBACK_TIMEOUT_S))
        tf = self.plan.through_focus
        names = pos.file_names(self.plan.frames_per_position, self.plan.suffix)
        failed: str | None = None
        grabs: list = []
        contexts: list[dict[str, Any]] = []
        if tf is None or tf.white_frames:
            if tf is not None:
                self._white_state(phase)
            phase[0] = "camera"
            grabs = [grab(self.camera, self.plan.average, self.plan.capture_timeout_s)
                     for _ in range(self.plan.frames_per_position)]
            contexts = [{} for _ in grabs]
            failed = self._check_white(pos, attempt, names, grabs, read_back)
        else:
            names = []
        t4 = time.monotonic()
        if tf is not None:
            base = f"pos_{pos.index + 1:05d}"
            for k, (frame, axes) in enumerate(zip(self._tf_frames, self._tf_axes), start=1):
                grabs.append(self._through_focus_grab(k, frame, axes, phase, contexts))
                names.append(f"{base}_tf{k:02d}{self.plan.suffix}")
        t5 = time.monotonic()
        phase[0] = "write"
        saved: list[SavedFrame] = []
        for k, (name, g, extra) in enumerate(zip(names, grabs, contexts), start=1):
            (self.out / (name + ".inspect.json")).unlink(missing_ok=True)
            item = save_frame(self.out / name, g, position_mm=read_back, context=self._context(pos, k, attempt, extra))
            saved.append(item)
            for text in item.warnings:
                self.result.warnings += 1
                self._event("frame_warning", index=pos.index, file=name, warning=text)
        _fsync_dir(self.out)
        t6 = time.monotonic()
        timing = {"recover": round(t_recover, 6), "move": round(t2 - t1, 6), "settle": round(t3 - t2, 6),
                  "capture": round(t4 - t3, 6), "write": round(t6 - t5, 6), "total": round(t6 - t0, 6)}
        if tf is not None:
            timing["through_focus"] = round(t5 - t4, 6)
        record: dict[str, Any] = {
            "type": "position", "index": pos.index, "label": pos.label, "target_mm": [pos.x_mm, pos.y_mm],
            "position_mm": list(read_back),
            "files": [{"file": s.path.name, "sha256": s.sha256, "bytes": s.record["bytes"], "sidecar": s.sidecar.name,
                       "sequence": s.record["sequence"], "warnings": s.warnings,
                       **({"through_focus": extra.get("through_focus", {}).get("record")} if tf is not None else {})}
                      for s, extra in zip(saved, contexts)],
            "attempts": attempt, "rejected": list(self._rejected), "failed": failed, "completed": _now_iso(),
            "timing_s": timing,
        }
        truth = grabs[0].first.extra.get("truth")
        if isinstance(truth, dict):
            record["truth"] = {k: v for k, v in truth.items() if k != "error_map"}
        self._writer.append(record)
        return record

    def _context(self, pos: PlanPosition, k: int, attempt: int, extra: dict[str, Any]) -> dict[str, Any]:
        """The sidecar context of frame k of an attempt at `pos`: where and when in the scan it was taken."""
        return {"scan": {"index": pos.index, "label": pos.label, "frame": k, "target_mm": [pos.x_mm, pos.y_mm],
                         "attempt": attempt, "plan_digest": self.plan.digest}, **extra}

    def _check_white(self, pos: PlanPosition, attempt: int, names: list[str], grabs: list[Grab],
                     read_back: tuple[float, ...]) -> str | None:
        """None if the white frames can be inspected; else, with retries left, keep them as rejected frames and
        raise FramesRejected (capture again), or on the last attempt return why (the position fails)."""
        problems = [p for p in (exposure_problem(g) for g in grabs) if p]
        if not problems:
            return None
        reason = problems[0]
        if attempt > self.plan.retries:
            return f"{reason.rstrip('.')} (after {attempt} attempt{'s' if attempt != 1 else ''})"
        for k, (name, g) in enumerate(zip(names, grabs), start=1):
            self._save_rejected(pos, attempt, k, name, g, read_back, reason)
        _fsync_dir(self.out)
        raise FramesRejected(reason)

    def _save_rejected(self, pos: PlanPosition, attempt: int, k: int, name: str, g: Grab,
                       read_back: tuple[float, ...], reason: str) -> None:
        """Write a frame that cannot be inspected beside the scan's frames (nothing is lost) and note it."""
        path = _rejected_path(self.out / name)
        context = {**self._context(pos, k, attempt, {}), "rejected": reason}
        item = save_frame(path, g, position_mm=read_back, context=context)
        self._rejected.append({"file": path.name, "sha256": item.sha256, "bytes": item.record["bytes"],
                               "sidecar": item.sidecar.name, "sequence": item.record["sequence"],
                               "warnings": item.warnings, "attempt": attempt, "reason": reason})
        self.result.rejected += 1
        self._event("frame_rejected", index=pos.index, label=pos.label, attempt=attempt, file=path.name,
                    reason=reason)

    def _move_carrier(self, axes: dict[str, float]) -> None:
        """Move the pinhole carrier's axes and settle (the through-focus settle time if the plan sets one)."""
        tf = self.plan.through_focus
        t0 = time.monotonic()
        self.stage.move_aux(axes, timeout_s=self.plan.move_timeout_s)
        settle = self.plan.settle_s if tf.settle_s is None else tf.settle_s
        if settle:
            time.sleep(settle)
        self.result.motion_s += time.monotonic() - t0

    def _white_state(self, phase: list[str]) -> None:
        """Carrier window on the axis, iris open, white exposure: what the white frames need."""
        tf = self.plan.through_focus
        phase[0] = "stage"
        target = white_axes(tf.carrier)
        last = self.stage.last_aux or {}
        if any(abs(last.get(k, math.inf) - v) > 0.001 for k, v in target.items()):
            self._move_carrier(target)
        phase[0] = "camera"
        if tf.iris == "camera":
            self.camera.set_f_number(self._white_f_number)  # type: ignore[attr-defined]
        if tf.exposure_us is not None:
            self.camera.set_exposure_us(self.plan.exposure_us)

    def _through_focus_grab(self, k: int, frame: ThroughFocus, axes: dict[str, float], phase: list[str],
                            contexts: list[dict[str, Any]]):
        """Stop down, move the carrier to frame k's Z, A, B, settle, read back, capture."""
        tf = self.plan.through_focus
        phase[0] = "camera"
        f_read = None
        if tf.iris == "camera":
            f_read = self.camera.set_f_number(frame.f_number)  # type: ignore[attr-defined]
        if tf.exposure_us is not None:
            self.camera.set_exposure_us(tf.exposure_us)
        phase[0] = "stage"
        self._move_carrier(axes)
        read_aux = self.stage.aux_position(timeout_s=READBACK_TIMEOUT_S)
        phase[0] = "camera"
        g = grab(self.camera, self.plan.average if tf.average is None else tf.average, self.plan.capture_timeout_s)
        header = self._tf_header["frames"][k - 1]
        contexts.append({"through_focus": {"frame": k, "record": frame.to_dict(),
                                           "derived": header["frame"], "carrier_axes_mm": axes,
                                           "aux_mm": {n: read_aux.get(n) for n in CARRIER_AXES},
                                           "f_number_read_back": f_read, "iris": tf.iris}})
        return g

    def _recover_stage(self) -> None:
        """Reconnect (and re-home) the stage after a failure, or if it lost its connection or homing."""
        if self._stage_bad or self.stage is None or not self.stage.is_connected:
            self.result.reconnects["stage"] += 1
            self._event("reconnect", device="stage")
            if self._own_stage:
                old, self.stage = self.stage, None
                if old is not None:
                    try:
                        old.close()
                    except Exception as exc:  # noqa: BLE001 - a dead device may fail to close; we replace it
                        log.debug("closing the failed stage: %s", exc)
                self.stage = self._open_stage()
            elif not self.stage.is_connected:
                self.stage.connect()  # a stage we were handed: reconnect it in place
            self._stage_bad = False
        if not self.stage.homed and self.plan.home != "never":
            self._home()

    def _recover_camera(self) -> None:
        """Reopen the camera after a failure (and re-apply exposure and gain)."""
        if self._camera_bad or not self.camera.is_open:
            self.result.reconnects["camera"] += 1
            self._event("reconnect", device="camera")
            self.camera.reopen(timeout_s=max(self.plan.capture_timeout_s, 1.0))
            self._apply_camera_settings()
            self._camera_bad = False

    def _inspect_missed(self, pos: PlanPosition) -> None:
        """A resumed scan: count a recorded position's failure and inspect its white frames that have no
        .inspect.json yet (the verdicts of those that have one are read back, so the exit status is the scan's)."""
        record = self._done[pos.index]
        if record.get("failed"):
            self.result.failed.append(pos.label)
        if self.inspect is not None:
            self._run_inspect(pos, record, missing_only=True)

    def _note_verdict(self, pos: PlanPosition, result: Any) -> None:
        """Remember a position whose inspection says FAIL."""
        if isinstance(result, dict) and result.get("verdict") == "FAIL" and pos.label not in self.result.verdict_failed:
            self.result.verdict_failed.append(pos.label)

    def _run_inspect(self, pos: PlanPosition, record: dict[str, Any], missing_only: bool = False) -> None:
        """Run the hook on each white frame of a recorded position, with the position's pinhole frames (not on
        a failed position's: they cannot be inspected)."""
        if self.inspect is None or record.get("failed"):
            return
        pinholes = tuple(self.out / item["file"] for item in record["files"] if item.get("through_focus"))
        for item in record["files"]:
            if item.get("through_focus"):
                continue  # the second measurement's frames are not white images: they go with each white frame
            path = self.out / item["file"]
            done = self.out / (item["file"] + ".inspect.json")
            if missing_only and done.exists():
                try:
                    self._note_verdict(pos, json.loads(done.read_text()))
                except (OSError, ValueError):
                    pass  # an unreadable earlier summary: the report it came from is the authority
                continue
            frame = ScanFrame(path, self.out / item["sidecar"], record, self._header or {}, self.out, pinholes)
            try:
                result = self.inspect(frame)
                if isinstance(result, dict):  # (a result that cannot be written is a failed inspection too)
                    write_json_atomic(self.out / (item["file"] + ".inspect.json"), result)
                self._note_verdict(pos, result)
            except (KeyboardInterrupt, MemoryError):
                raise
            except Exception as exc:  # noqa: BLE001 - a failed inspection must not lose the scan
                self.result.inspect_failures += 1
                self._event("inspect_failed", index=pos.index, file=item["file"], error=f"{type(exc).__name__}: {exc}")
                continue
            self.result.inspected += 1

    # ------------------------------------------------------------ stopping

    def _stop_stage(self) -> str | None:
        """Halt the stage now; None if it is stopped (or was not moving), else why that is not certain."""
        stage = self.stage
        if stage is None or not getattr(stage, "is_connected", False):
            return None
        try:
            stage.stop()
        except Exception as exc:  # noqa: BLE001 - report, never mask the original failure
            return str(exc).rstrip(".")
        return None

    def _stopped_message(self, how: str, stop_problem: str | None, *, attempts: int = 0,
                         error: BaseException | None = None) -> str:
        pos, total = self._current, self.result.total
        where = "before the first position"
        if pos is not None:
            where = f"at position {pos.index + 1} of {total} ({pos.label}, x={pos.x_mm:g} y={pos.y_mm:g} mm)"
        cause = ""
        if error is not None and attempts:
            cause = f" after {attempts} attempt{'s' if attempts != 1 else ''} ({str(error).rstrip('.')})"
        elif error is not None:
            cause = f" ({str(error).rstrip('.')})"
        stage = ("the stage was stopped" if stop_problem is None
                 else f"the stage may still be moving ({stop_problem})")
        if self._writer is None and not self.result.resumed:
            return f"scan {how} {where}{cause}; {stage} and nothing was recorded."
        return (f"scan {how} {where}{cause}; {stage} and {self.result.done} of {total} positions are recorded in "
                f"{self.manifest_path}; rerun with --resume to continue.")

    def _timing(self) -> dict[str, Any]:
        r = self.result
        return {"captured": r.captured, "resumed": r.resumed, "retries": r.retries, "reconnects": dict(r.reconnects),
                "loop_s": round(r.loop_s, 3), "motion_s": round(r.motion_s, 3), "home_s": round(r.home_s, 3)}

    def _shutdown(self) -> None:
        """Close files; detach and close the devices the runner opened."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._attached:
            try:
                self.camera.attach_stage(None)  # type: ignore[attr-defined]
            except Exception:  # noqa: BLE001
                pass
        if self._own_camera:
            self.camera.close()
        if self._own_stage and self.stage is not None:
            try:
                self.stage.close()
            except Exception as exc:  # noqa: BLE001
                log.warning("closing the stage: %s", exc)
        if self._events is not None:
            self._events.close()
            self._events = None

    def _event(self, event: str, **fields: Any) -> None:
        rec = {"time": _now_iso(), "event": event, **fields}
        if self._events is not None:
            self._events.write(json.dumps(rec, default=str) + "\n")
            self._events.flush()
        if self.on_event is not None:
            self.on_event(rec)


def run_scan(camera: Camera | str, stage: Any, plan: ScanPlan | str | os.PathLike[str], out_dir: str | os.PathLike[str],
             *, resume: bool = False, inspect: InspectHook | None = None,
             progress: Callable[[int, int], None] | None = None,
             before_position: Callable[[ScanRunner, PlanPosition], None] | None = None,
             on_event: Callable[[dict[str, Any]], None] | None = None) -> ScanResult:
    """Load the plan (if a path) and run the scan; see ScanRunner."""
    if not isinstance(plan, ScanPlan):
        plan = load_plan(plan)
    runner = ScanRunner(plan, out_dir, camera=camera, stage=stage, resume=resume, inspect=inspect, progress=progress,
                        before_position=before_position, on_event=on_event)
    return runner.run()


def _mask_text(c: Carrier, other: Carrier | None = None) -> str:
    """A pinhole mask in a few words: its lattices' focus offsets and spacing, and any other field in which
    it differs from `other`."""
    text = f"lattices for u = {', '.join(f'{u:+g}' for u in c.focus_offsets_mm)} mm, {c.spacing_lenses} lenses apart"
    mine, theirs = c.to_dict(), (other.to_dict() if other is not None else {})
    diff = [f"{k} {mine[k]:g}" for k in ("z_white_mm", "a_centre_mm", "b_window_mm", "field_pitch_mm")
            if k in theirs and mine[k] != theirs[k]]
    return text + "".join(f", {d}" for d in diff)


def default_inspect_hook() -> InspectHook | None:
    """`mlaqc.inspection.pipeline.scan_frame_hook` once the inspection pipeline provides it; None until then."""
    try:
        module = importlib.import_module("mlaqc.inspection.pipeline")
    except ModuleNotFoundError as exc:
        if exc.name in ("mlaqc.inspection.pipeline", "mlaqc"):
            return None
        raise
    hook = getattr(module, "scan_frame_hook", None)
    return hook if callable(hook) else None
