"""A mock camera that renders what the real bench would see: the MLA under test, moved by the stage.

URL (every parameter optional)::

    mock://?config=small&wafer=3x3&pitch_mm=5&origin_mm=10,10&defects=5&seed=1&rpp=4
           &exposure_us=5000&gain=1&pos_mm=10,10&stage=NAME&quantum_um=1&cache_mb=256
           &light=1&faults=timeout@5,black@9x2&threads=0&f_number=11&mask=5,-5&mask_spacing=4
           &z_white_mm=50&a_centre_mm=10&b_window_mm=0&field_pitch_mm=25&pinhole_photons=2.6e5

- ``config``: camera config — ``small`` (default: the 24x24-lens, 496x496-px test camera, the same as
  fixtures/small_camera.toml), ``hex_small`` (its hex-packed twin, 24 columns x 28 rows, the same as
  fixtures/hex_small_camera.toml), ``table1`` (the paper's full camera) or a TOML path. The wafer's arrays
  are the config's MLA, square or hex (mla.packing).
- ``wafer=COLSxROWS``, ``pitch_mm``, ``origin_mm=X,Y``: the wafer of arrays (see drivers.wafer); default
  one array, W(1,1) centred at (10, 10) mm, pitch large enough that neighbours never enter the view.
- ``defects`` per array (default 5), ``defect_types`` (comma list, default pitch,decenter,radius), ``seed``
  (defects, render and noise; default 0).
- A production story (drivers.wafer.Production): ``master=M,N`` the master's defect on lens U(M,N) of a
  seeded ``master_share`` of the arrays (default 0.8), ``master_type`` (pitch, decenter, radius, thickness;
  default pitch), ``master_size`` (µm, or relative for radius; default 1.5), ``master_dir`` (degrees, default
  30); ``drift_from=K`` and ``drift_um=X``: from production index K on, the MLA–sensor distance X µm larger
  with every array; ``first_index``: the production index of this wafer's W(1,1) (wafers of one lot in turn).
- ``rpp``: rays per pixel of each render (default 4).
- ``exposure_us`` (default 5000 µs; the config's `exposure_photons` apply at 10000 µs and photons scale
  linearly with exposure, so the default keeps the brightest sub-image centres below full well even with
  the Monte-Carlo noise of a low-rpp render), ``gain`` (a multiplier of the sensor's DN per electron,
  default 1; the white level scales with it).
- Where the stage is: ``pos_mm=X,Y`` a fixed position (default: the centre of W(1,1)); ``stage=NAME``
  a position source published with `publish_stage(NAME, stage)`; or, in code,
  `camera.attach_stage(stage_or_callable)` (reads `stage.last_position`). The scan runner attaches its
  stage; the position source wins over ``pos_mm`` while attached.
- ``quantum_um`` (default 1): offsets are rounded to this before rendering, so renders can be cached.
- ``cache_mb`` (default 256): LRU cache of expected-photon images per (array, quantized offset).
- ``light=0``: the illumination is off (every frame is a dark frame: black level plus read noise).
- ``faults``: faults armed at given capture attempts, ``KIND@N`` or ``KIND@NxCOUNT`` (see below).
- ``threads``: tracer threads (default: one per core).
- ``f_number``: the main lens' iris (default: full aperture, efl / D = 2.5 for Table 1); also
  `set_f_number()` at run time (the scan runner stops down for through-focus frames). A stopped-down
  white view passes (D_N / D)^2 of the light (`white_flux_scale`), as a real iris does.
- The through-focus bench (see mlaqc.optics.throughfocus, `Carrier`): when the stage also reports the
  target carrier's auxiliary axes Z, A and B (a stage URL with ``aux=z,a,b``), the camera renders
  what the mask shows there instead of the plain white target: the clear window (field 0: the white
  frame), a pinhole lattice field (the pinholes at the object distance Z gives, moved by A and B) or
  opaque chrome (dark). ``mask`` (the lattices' focus offsets, mm, in field order along B),
  ``mask_spacing`` (lenses), ``z_white_mm``, ``a_centre_mm``, ``b_window_mm``, ``field_pitch_mm``
  describe the mask and where it sits (defaults: `Carrier()`, the shipped protocol's: lattices for
  u = 5 and -5 mm, 4 lenses apart; stop the iris to f/11 for them; on a hex config, e.g. ``config=hex_small``,
  each lattice is the hex sub-lattice 4 lenses apart and A, B step it in axial lens steps), ``pinhole_photons`` the photons each
  pinhole sends into the pupil at the reference exposure (default: the protocol's exposure,
  `mlaqc.optics.throughfocus.pinhole_photons` for the field's |u| at the current f-number and the mask's
  spacing, so that the brighter frame of each +u / -u pair peaks near `FILL_FRACTION` (50 %) of full well
  at 10 ms; about 2.6e5 at ±5 mm, f/11; settings() reports None). Pinhole views go through the config's image formation
  model (diffraction, crosstalk, PRNU; mlaqc.optics.formation) as `mlaqc simulate` does: their spots are
  1-2.5 px wide at ±5 mm, about a pixel at ±10 mm. Without auxiliary readings every frame shows the
  white target.

Frames: each capture takes the stage position, finds the wafer array nearest to it, renders (or takes
from the cache) the expected photons with the tracer, the array's ErrorMap given
``mla_shift = centre - position`` and the view (white target, or the carrier's mask at its quantized
Z, A, B, through the iris), scales by exposure, and reads it out with `mlaqc.optics.sensor.expose`
seeded per frame, so repeated frames differ by fresh shot and read noise. Pixel format ``Y16`` (or the
16-bit Bayer format of a CFA config) with the config's bit depth. Sequence numbers count frames since
the camera was made (dropped frames leave gaps); `device_timestamp_s` is time.monotonic() when the
frame completed. ``Frame.extra`` holds ``sequence_gap``, ``black_level``, ``white_level``, ``truth``
(array name and W(m,n), its centre, the stage position and offset, the array's error map and, with a
carrier, ``bench``: the axes read, the view's kind, field and through-focus record) and ``mock``
(cache hit, render time, fault).

Faults (``inject_fault(kind, at=None, count=1)`` or the ``faults`` URL parameter; `at` is the 1-based
capture attempt counted over the camera's life, None = the next one):
- ``timeout``: `count` capture attempts wait their whole `timeout_s` and raise DeviceError;
- ``disconnect``: the capture raises DeviceError and every call does until `reopen()` (or close and
  open); `count` - 1 further open attempts fail first, like a camera still being re-plugged;
- ``drop``: `count` frames are lost before the next one (a sequence-number gap);
- ``black`` / ``saturated``: `count` frames come back black (black level plus noise) / all at the
  white level.
`clear_faults()` disarms them. `stats` counts captures, frames, renders, cache hits and faults.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import zlib
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from drivers.camera import register_camera_scheme
from drivers.camera.base import DEFAULT_TIMEOUT_S, Camera, Frame, check_timeout_s
from drivers.camera.formats import lookup_format
from drivers.url import DeviceURL, parse_device_url
from drivers.wafer import Production, Wafer, WaferArray
from mlaqc.errors import DeviceError, InputError
from mlaqc.optics.config import CameraConfig, config_from_dict, default_config, load_config
from mlaqc.optics.sensor import expose, white_level
from mlaqc.optics.throughfocus import (Carrier, CarrierView, carrier_view, iris_config, native_f_number,
                                      white_flux_scale)

log = logging.getLogger(__name__)

URL_PARAMS = ("config", "wafer", "pitch_mm", "origin_mm", "defects", "defect_types", "seed", "rpp", "exposure_us",
              "gain", "pos_mm", "stage", "quantum_um", "cache_mb", "light", "faults", "threads", "f_number", "mask",
              "mask_spacing", "z_white_mm", "a_centre_mm", "b_window_mm", "field_pitch_mm", "pinhole_photons",
              "master", "master_type", "master_size", "master_dir", "master_share", "drift_from", "drift_um",
              "first_index")
FAULT_KINDS = ("timeout", "disconnect", "drop", "black", "saturated")
REFERENCE_EXPOSURE_US = 10_000.0  # the config's exposure_photons are the photons of this exposure
DEFAULT_EXPOSURE_US = 5_000.0  # half the reference: sub-image peaks stay below full well even at low rpp
EXPOSURE_RANGE_US = (10.0, 10_000_000.0)
EXPOSURE_STEP_US = 1.0
GAIN_RANGE = (0.1, 16.0)
GAIN_STEP = 0.01
F_NUMBER_MAX = 64.0
F_NUMBER_STEP = 0.01
SMALL_CAMERA = {"mla": {"count_w": 24, "count_h": 24}, "sensor": {"width_px": 496, "height_px": 496}}
HEX_SMALL_CAMERA = {"mla": {"packing": "hex", "count_w": 24, "count_h": 28}, "sensor": {"width_px": 496, "height_px": 496}}

PositionSource = Callable[[], "tuple[float, float] | tuple[float, float, dict[str, float] | None] | None"]

_PUBLISHED: dict[str, PositionSource] = {}
_PUBLISHED_LOCK = threading.Lock()


def publish_stage(name: str, source: Any) -> None:
    """Make a stage (anything with `last_position`) or a position callable visible to ``mock://?stage=NAME``."""
    with _PUBLISHED_LOCK:
        _PUBLISHED[name] = _as_source(source)


def unpublish_stage(name: str) -> None:
    """Withdraw a published position source (no error if absent)."""
    with _PUBLISHED_LOCK:
        _PUBLISHED.pop(name, None)


def stage_reading(stage: Any) -> tuple[float, float, dict[str, float] | None] | None:
    """(x, y, auxiliary axes or None) a stage last reported, None before its first report."""
    pos = stage.last_position
    if pos is None:
        return None
    aux = getattr(stage, "last_aux", None)
    return float(pos[0]), float(pos[1]), (dict(aux) if aux else None)


def _as_source(source: Any) -> PositionSource:
    """A callable returning (x_mm, y_mm), (x_mm, y_mm, {axis: mm}) or None, from a stage-like object or a callable."""
    if callable(source):
        return source
    if hasattr(source, "last_position"):
        return lambda: stage_reading(source)
    raise TypeError(f"a position source must be a stage (with last_position) or a callable, not {type(source).__name__}")


@dataclass
class _Fault:
    kind: str
    at: int | None  # capture attempt number, None = next
    count: int


class MockCamera(Camera):
    """A rendered camera over a simulated wafer; see the module docstring."""

    def __init__(self, url: str = "mock://", *, cfg: CameraConfig | None = None, wafer: Wafer | None = None,
                 rays_per_pixel: float = 4.0, exposure_us: float = DEFAULT_EXPOSURE_US, gain: float = 1.0,
                 position_mm: tuple[float, float] | None = None, stage: Any = None, stage_name: str | None = None,
                 quantum_um: float = 1.0, cache_mb: float = 256.0, light: bool = True, seed: int = 0,
                 faults: list[tuple[str, int | None, int]] = (), threads: int | None = None,
                 f_number: float | None = None, carrier: Carrier | None = None,
                 pinhole_photons: float | None = None) -> None:
        super().__init__(url)
        self.cfg = cfg or (wafer.cfg if wafer is not None else config_from_dict(SMALL_CAMERA, "small camera"))
        self.wafer = wafer or Wafer(self.cfg, seed=seed)
        if self.wafer.cfg is not self.cfg and self.wafer.cfg != self.cfg:
            raise InputError("mock camera: the wafer was made for a different camera config")
        _check_positive("rpp", rays_per_pixel)
        _check_positive("quantum_um", quantum_um)
        _check_positive("cache_mb", cache_mb)
        self.rays_per_pixel = float(rays_per_pixel)
        self.quantum_um = float(quantum_um)
        self.cache_bytes = int(cache_mb * 1e6)
        self.seed = int(seed)
        self.threads = threads
        self._lock = threading.RLock()
        self._closing = threading.Event()
        self._open = False
        self._disconnected = False
        self._failing_opens = 0
        self._light = bool(light)
        self._fixed_position = tuple(position_mm) if position_mm is not None else self.wafer.centre_mm(1, 1)
        self._source: PositionSource | None = _as_source(stage) if stage is not None else None
        self._stage_name = stage_name
        self._exposure_us = self._snap_exposure(exposure_us)
        self._gain = self._snap_gain(gain)
        self.carrier = carrier or Carrier()
        if pinhole_photons is not None:
            _check_positive("pinhole_photons", pinhole_photons)
        self.pinhole_photons = None if pinhole_photons is None else float(pinhole_photons)  # None: the protocol's
        self._f_number = self._snap_f_number(native_f_number(self.cfg) if f_number is None else f_number)
        self._format = _format_for(self.cfg)
        self._sequence = 0
        self._attempts = 0
        self._faults: list[_Fault] = []
        for kind, at, count in faults:
            self.inject_fault(kind, at=at, count=count)
        self._cache: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._cache_size = 0
        self._empty: np.ndarray | None = None
        self.stats = {"captures": 0, "frames": 0, "renders": 0, "cache_hits": 0, "render_s": 0.0, "timeouts": 0,
                      "disconnects": 0, "dropped_frames": 0, "black_frames": 0, "saturated_frames": 0}

    # ----------------------------------------------------------------- construction from a URL

    @classmethod
    def from_url(cls, url: DeviceURL | str, **options: Any) -> MockCamera:
        """Build an unopened mock camera from a ``mock://`` URL; InputError naming any bad parameter.

        `options` are constructor keywords (cfg, wafer, stage, ...) and override the URL's parameters."""
        parsed = parse_device_url(url) if isinstance(url, str) else url
        text = str(url)
        unknown = sorted(set(parsed.params) - set(URL_PARAMS))
        if unknown:
            raise InputError(f"unknown parameter {unknown[0]!r} in camera URL {text!r}; known: {', '.join(URL_PARAMS)}")
        if parsed.path not in ("", "/"):
            raise InputError(f"camera URL {text!r} must not name a device path; use e.g. 'mock://?wafer=3x3'")
        p = _Params(text, parsed.params)
        cfg = options.pop("cfg", None) or _load_camera_config(text, parsed.param("config", "small"))
        seed = p.integer("seed", 0, minimum=0)
        wafer = options.pop("wafer", None)
        if wafer is None:
            cols, rows = p.grid("wafer", (1, 1))
            types = tuple(t.strip() for t in parsed.param("defect_types", "pitch,decenter,radius").split(",") if t.strip())
            try:
                production = Production(
                    master_lens=_lens(parsed.param("master", "")),
                    master_type=parsed.param("master_type", "pitch"), master_magnitude=p.number("master_size", 1.5),
                    master_dir_deg=p.number("master_dir", 30.0), master_share=p.number("master_share", 0.8),
                    drift_from=p.integer("drift_from", 0, minimum=0) or None, drift_um=p.number("drift_um", 0.0),
                    first_index=p.integer("first_index", 1, minimum=1))
                wafer = Wafer(cfg, cols=cols, rows=rows, pitch_mm=p.number("pitch_mm", None),
                              origin_mm=p.pair("origin_mm", (10.0, 10.0)), defects=p.integer("defects", 5, minimum=0),
                              seed=seed, defect_types=types, production=production)
            except InputError as exc:
                raise InputError(f"camera URL {text!r}: {exc}") from None
        threads = p.integer("threads", 0, minimum=0)
        d = Carrier()
        try:
            carrier = Carrier(focus_offsets_mm=p.numbers("mask", d.focus_offsets_mm),
                              spacing_lenses=p.integer("mask_spacing", d.spacing_lenses, minimum=2),
                              z_white_mm=p.number("z_white_mm", d.z_white_mm),
                              a_centre_mm=p.number("a_centre_mm", d.a_centre_mm),
                              b_window_mm=p.number("b_window_mm", d.b_window_mm),
                              field_pitch_mm=p.number("field_pitch_mm", d.field_pitch_mm, positive=True))
        except InputError as exc:
            raise InputError(f"camera URL {text!r}: {exc}") from None
        kwargs: dict[str, Any] = dict(
            cfg=cfg, wafer=wafer, seed=seed,
            rays_per_pixel=p.number("rpp", 4.0, positive=True),
            exposure_us=p.number("exposure_us", DEFAULT_EXPOSURE_US, positive=True),
            gain=p.number("gain", 1.0, positive=True),
            position_mm=p.pair("pos_mm", None),
            stage_name=parsed.param("stage") or None,
            quantum_um=p.number("quantum_um", 1.0, positive=True),
            cache_mb=p.number("cache_mb", 256.0, positive=True),
            light=p.flag("light", True),
            faults=parse_faults(text, parsed.param("faults", "")),
            threads=threads or None,
            f_number=p.number("f_number", None, positive=True),
            carrier=carrier,
            pinhole_photons=p.number("pinhole_photons", None, positive=True),
        )
        kwargs.update(options)
        try:
            return cls(text, **kwargs)
        except InputError as exc:
            raise InputError(f"camera URL {text!r}: {exc}") from None

    # ----------------------------------------------------------------- identity and state

    @property
    def name(self) -> str:
        """'mock camera (24x24 lenses, 3x3 wafer)'."""
        mla = self.cfg.mla
        hex_ = " hex" if mla.packing == "hex" else ""
        return f"mock camera ({mla.count_w}x{mla.count_h}{hex_} lenses, {self.wafer.cols}x{self.wafer.rows} wafer)"

    @property
    def is_open(self) -> bool:
        return self._open

    @property
    def bit_depth(self) -> int:
        return self.cfg.sensor.bit_depth

    @property
    def pixel_format(self) -> str:
        """'Y16' for a monochrome config, the 16-bit Bayer format name for a CFA config."""
        return self._format

    @property
    def sequence(self) -> int:
        """Sequence number of the last frame delivered (0 before the first)."""
        return self._sequence

    @property
    def light(self) -> bool:
        """Whether the illumination is on."""
        return self._light

    def set_light(self, on: bool) -> bool:
        """Switch the (simulated) illumination; off gives dark frames. Returns the state read back."""
        with self._lock:
            self._light = bool(on)
            return self._light

    @property
    def f_number(self) -> float:
        """The main lens' iris setting (its full aperture efl / D when wide open)."""
        return self._f_number

    def set_f_number(self, f_number: float) -> float:
        """Set the iris to f/N (snapped to 0.01; no wider than the lens' full aperture); return it as read back."""
        with self._lock:
            self._require_open("setting the iris")
            self._f_number = self._snap_f_number(f_number)
            return self._f_number

    # ----------------------------------------------------------------- open / close

    def open(self) -> MockCamera:
        """Open; fails with DeviceError while a 'disconnect' fault keeps the camera unplugged."""
        with self._lock:
            if self._open:
                return self
            if self._failing_opens > 0:
                self._failing_opens -= 1
                raise DeviceError(f"camera {self.name} was not found while opening the device (simulated unplug); "
                                  "check the cable and try again")
            self._open = True
            self._disconnected = False
            self._closing.clear()
            return self

    def close(self) -> None:
        """Close; a capture waiting out a simulated timeout is woken. Safe to call twice."""
        self._closing.set()
        with self._lock:
            self._open = False

    # ----------------------------------------------------------------- stage coupling

    def attach_stage(self, source: Any) -> None:
        """Follow a stage: an object with `last_position` (a Stage) or a callable returning (x, y) mm or None.

        None detaches it (frames then use the fixed ``pos_mm`` position)."""
        with self._lock:
            self._source = None if source is None else _as_source(source)

    def position_mm(self) -> tuple[tuple[float, float], str]:
        """(stage position used for the next frame, where it came from: 'stage', 'published' or 'fixed')."""
        pos, _, origin = self._reading()
        return pos, origin

    def _reading(self) -> tuple[tuple[float, float], dict[str, float] | None, str]:
        """(x, y) and the auxiliary axes (or None) for the next frame, and where they came from."""
        source, origin = self._source, "stage"
        if source is None and self._stage_name is not None:
            with _PUBLISHED_LOCK:
                source = _PUBLISHED.get(self._stage_name)
            if source is None:
                raise DeviceError(f"camera {self.name} follows stage {self._stage_name!r}, but no stage is published "
                                  "under that name; call drivers.camera.mock.publish_stage() first")
            origin = "published"
        if source is not None:
            pos = source()
            if pos is not None:
                aux = pos[2] if len(pos) > 2 and isinstance(pos[2], dict) else None
                return (float(pos[0]), float(pos[1])), aux, origin
            log.debug("camera %s: stage has not reported a position yet; using the fixed position", self.name)
        return (float(self._fixed_position[0]), float(self._fixed_position[1])), None, "fixed"

    def truth(self) -> dict[str, Any]:
        """The wafer's ground truth (every array's position and error map), as JSON."""
        return self.wafer.truth()

    # ----------------------------------------------------------------- settings

    def settings(self) -> dict[str, Any]:
        """Settings as read back, plus the simulation's parameters and counters."""
        with self._lock:
            self._require_open("reading its settings")
            s = self.cfg.sensor
            return {
                "url": self.url, "name": self.name, "pixel_format": self._format, "bits": s.bit_depth,
                "cfa": None if s.cfa == "none" else s.cfa, "width": s.width_px, "height": s.height_px,
                "exposure_us": self._exposure_us, "gain": self._gain, "light": self._light,
                "black_level": s.black_level_dn, "white_level": white_level(self._sensor()),
                "rays_per_pixel": self.rays_per_pixel, "quantum_um": self.quantum_um, "seed": self.seed,
                "f_number": self._f_number, "carrier": self.carrier.to_dict(), "pinhole_photons": self.pinhole_photons,
                "wafer": self.wafer.layout(), "position_source": self._source_name(), "config": self.cfg.to_dict(),
                "cache": self.cache_info(), "stats": dict(self.stats),
            }

    def _source_name(self) -> str:
        if self._source is not None:
            return "stage"
        if self._stage_name is not None:
            return f"published:{self._stage_name}"
        return f"fixed:{self._fixed_position[0]:g},{self._fixed_position[1]:g}"

    def set_exposure_us(self, exposure_us: float) -> float:
        """Set the exposure (snapped to 1 µs); return it as read back."""
        with self._lock:
            self._require_open("setting the exposure")
            self._exposure_us = self._snap_exposure(exposure_us)
            return self._exposure_us

    def set_gain(self, gain: float) -> float:
        """Set the gain (a multiplier of DN per electron, snapped to 0.01); return it as read back."""
        with self._lock:
            self._require_open("setting the gain")
            self._gain = self._snap_gain(gain)
            return self._gain

    def set_format(self, pixel_format: str) -> str:
        """Only the native 16-bit container format is offered; return it."""
        fmt = lookup_format(pixel_format)
        with self._lock:
            self._require_open("setting the pixel format")
            if fmt.name != self._format:
                raise InputError(f"camera {self.name} offers only pixel format {self._format}, not {fmt.name}")
            return self._format

    def _snap_exposure(self, exposure_us: float) -> float:
        lo, hi = EXPOSURE_RANGE_US
        value = _finite("exposure_us", exposure_us)
        if not lo <= value <= hi:
            raise InputError(f"exposure {value:g} µs is outside the mock camera's range {lo:g}..{hi:g} µs")
        return float(round(value / EXPOSURE_STEP_US) * EXPOSURE_STEP_US)

    def _snap_gain(self, gain: float) -> float:
        lo, hi = GAIN_RANGE
        value = _finite("gain", gain)
        if not lo <= value <= hi:
            raise InputError(f"gain {value:g} is outside the mock camera's range {lo:g}..{hi:g}")
        return float(round(value / GAIN_STEP) * GAIN_STEP)

    def _snap_f_number(self, f_number: float) -> float:
        value = _finite("f_number", f_number)
        lo = native_f_number(self.cfg)
        if not 1.0 <= value <= F_NUMBER_MAX:
            raise InputError(f"f-number {value:g} is outside the mock lens' range f/1..f/{F_NUMBER_MAX:g} (anything "
                             f"wider than its full aperture f/{lo:.2f} opens the iris fully)")
        return max(round(lo, 2), float(round(value / F_NUMBER_STEP) * F_NUMBER_STEP))

    def _sensor(self):
        """The sensor model at the current gain."""
        s = self.cfg.sensor
        return replace(s, gain_dn_per_e=s.gain_dn_per_e * self._gain)

    # ----------------------------------------------------------------- faults

    def inject_fault(self, kind: str, *, at: int | None = None, count: int = 1) -> None:
        """Arm a fault for capture attempt `at` (1-based, over the camera's life) or the next one."""
        if kind not in FAULT_KINDS:
            raise InputError(f"unknown mock camera fault {kind!r}; expected one of {', '.join(FAULT_KINDS)}")
        if not isinstance(count, int) or count < 1:
            raise InputError(f"mock camera fault count must be a whole number >= 1, got {count!r}")
        if at is not None and (not isinstance(at, int) or at < 1):
            raise InputError(f"mock camera fault position must be a capture number >= 1, got {at!r}")
        with self._lock:
            self._faults.append(_Fault(kind, at, count))

    def clear_faults(self) -> None:
        """Disarm every pending fault and plug the camera back in (it still needs reopening if disconnected)."""
        with self._lock:
            self._faults.clear()
            self._failing_opens = 0

    def _due_fault(self, attempt: int) -> _Fault | None:
        """The fault that applies to this capture attempt, consuming it (or one count of it)."""
        for fault in self._faults:
            if fault.at is None:
                fault.at = attempt
            if fault.at <= attempt:
                if fault.kind in ("timeout", "black", "saturated") and fault.count > 1:
                    self._faults.append(_Fault(fault.kind, attempt + 1, fault.count - 1))
                self._faults.remove(fault)
                return fault
        return None

    # ----------------------------------------------------------------- frames

    def capture(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> Frame:
        """Render (or take from the cache) the view at the stage position and read it out with fresh noise."""
        timeout_s = check_timeout_s(timeout_s)
        with self._lock:
            self._require_open("capturing a frame")
            self._attempts += 1
            self.stats["captures"] += 1
            fault = self._due_fault(self._attempts)
            kind = fault.kind if fault else None
            if kind == "disconnect":
                self._open = False
                self._disconnected = True
                self._failing_opens = fault.count - 1
                self.stats["disconnects"] += 1
                raise DeviceError(f"camera {self.name} was disconnected while capturing a frame (simulated); "
                                  "reconnect it and reopen the camera")
            if kind == "timeout":
                self.stats["timeouts"] += 1
                self._closing.wait(timeout_s)
                raise DeviceError(f"camera {self.name} timed out after {timeout_s:g} s waiting for a frame while "
                                  "capturing a frame (simulated)")
            position, aux, origin = self._reading()
            array, offset = self.wafer.locate(*position)
            view, axes = self._view(aux)
            photons, hit, render_s, key = self._photons(array, offset, view, axes)
            gap = fault.count if kind == "drop" else 0
            self.stats["dropped_frames"] += gap
            self._sequence += 1 + gap
            sensor = self._sensor()
            wl = white_level(sensor)
            noise_seed = int(np.random.SeedSequence([self.seed, 0x5EED, self._sequence]).generate_state(1)[0])
            if kind == "saturated":
                data = np.full(photons.shape, wl, np.uint16)
                self.stats["saturated_frames"] += 1
            elif kind == "black" or not self._light:
                data = expose(np.zeros(photons.shape), sensor, noise_seed)
                self.stats["black_frames"] += kind == "black"
            else:
                data = expose(photons * (self._exposure_us / REFERENCE_EXPOSURE_US), sensor, noise_seed)
            self.stats["frames"] += 1
            truth = {"array": array.name, "m": array.m, "n": array.n, "array_centre_mm": list(array.centre_mm),
                     "stage_mm": list(position), "position_source": origin,
                     "offset_um": [round(offset[0], 6), round(offset[1], 6)],
                     "rendered_offset_um": list(key[2:4]) if key[2:4] else None,
                     "in_view": self.wafer.in_view(offset), "error_map": array.error_map_json}
            if aux is not None:
                truth["bench"] = {"axes_mm": dict(aux), "rendered_axes_mm": axes, "f_number": self._f_number,
                                  **view.to_dict()}
            extra = {"sequence_gap": gap, "black_level": sensor.black_level_dn, "white_level": wl, "truth": truth,
                     "mock": {"cache_hit": hit, "render_s": round(render_s, 6), "fault": kind, "light": self._light,
                              "rays_per_pixel": self.rays_per_pixel, "noise_seed": noise_seed,
                              "f_number": self._f_number, "view": view.kind}}
            s = self.cfg.sensor
            return Frame(data=data, bits=s.bit_depth, pixel_format=self._format,
                         cfa=None if s.cfa == "none" else s.cfa, sequence=self._sequence,
                         device_timestamp_s=time.monotonic(), host_timestamp_s=time.time(),
                         exposure_us=self._exposure_us, gain=self._gain, device=self.url, extra=extra)

    def expected_photons(self, position_mm: tuple[float, float] | None = None,
                         aux_mm: dict[str, float] | None = None) -> np.ndarray:
        """The noise-free expected photons at the reference exposure for a stage position and auxiliary
        axes (default: where the stage is now)."""
        with self._lock:
            position, aux, _ = self._reading()
            if position_mm is not None:
                position, aux = position_mm, aux_mm
            array, offset = self.wafer.locate(*position)
            return self._photons(array, offset, *self._view(aux))[0]

    def _quantize(self, offset_um: tuple[float, float]) -> tuple[float, float]:
        q = self.quantum_um
        return (round(offset_um[0] / q) * q + 0.0, round(offset_um[1] / q) * q + 0.0)

    def _view(self, aux: dict[str, float] | None) -> tuple[CarrierView, dict[str, float] | None]:
        """What the camera looks at: the carrier's mask at the quantized Z, A, B if the stage reports them
        all, else the white target; through the iris. Also the quantized axes (None without a carrier)."""
        if aux is None or not all(k in aux for k in ("z", "a", "b")):
            cam = iris_config(self.cfg, self._f_number)
            from mlaqc.optics.scene import WhiteScene

            return CarrierView("white", cam, WhiteScene(), 0, flux_scale=white_flux_scale(self.cfg, self._f_number)), None
        q = self.quantum_um * 1e-3
        axes = {k: round(round(float(aux[k]) / q) * q, 9) + 0.0 for k in ("z", "a", "b")}
        return carrier_view(self.cfg, self.carrier, axes, self._f_number, self.pinhole_photons), axes

    def _photons(self, array: WaferArray, offset_um: tuple[float, float], view: CarrierView,
                 axes: dict[str, float] | None) -> tuple[np.ndarray, bool, float, tuple]:
        """(expected photons, cache hit?, render seconds, cache key) for an array at an offset, seen as `view`."""
        s = self.cfg.sensor
        if not self.wafer.in_view(offset_um) or view.scene is None:
            if self._empty is None:
                self._empty = np.zeros((s.height_px, s.width_px), np.float32)
                self._empty.setflags(write=False)
            return self._empty, True, 0.0, (array.m, array.n)
        qx, qy = self._quantize(offset_um)
        key: tuple = (array.m, array.n, qx, qy)
        tag = ""
        if view.cfg is not self.cfg or view.kind != "white":  # the plain white view keeps its historical key and seed
            key += (view.kind, self._f_number, *((axes["z"], axes["a"], axes["b"]) if view.kind != "white" else ()))
            tag = ":" + ":".join(f"{v}" for v in key[4:])
        cached = self._cache.get(key)
        if cached is not None:
            self._cache.move_to_end(key)
            self.stats["cache_hits"] += 1
            return cached, True, 0.0, key
        from mlaqc.optics.render import Renderer

        start = time.perf_counter()
        errors = array.errors.with_globals(mla_shift_x_um=qx, mla_shift_y_um=qy)
        render_seed = zlib.crc32(f"{self.seed}:{array.m}:{array.n}:{qx:.6f}:{qy:.6f}{tag}".encode())
        result = Renderer(view.cfg, errors).render(view.scene, rays_per_pixel=self.rays_per_pixel,
                                                   seed=render_seed, threads=self.threads)
        photons = result.photons * view.flux_scale if view.flux_scale != 1.0 else result.photons
        if view.kind == "pinholes":  # spots 1-2.5 px wide: diffraction and crosstalk shape their peaks
            from mlaqc.optics.formation import apply_formation

            photons = apply_formation(photons, view.cfg)
        photons = photons.astype(np.float32)
        photons.setflags(write=False)
        elapsed = time.perf_counter() - start
        self.stats["renders"] += 1
        self.stats["render_s"] += elapsed
        self._cache[key] = photons
        self._cache_size += photons.nbytes
        while self._cache_size > self.cache_bytes and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._cache_size -= old.nbytes
        return photons, False, elapsed, key

    def cache_info(self) -> dict[str, Any]:
        """Cached renders, their memory, hits and renders so far."""
        return {"entries": len(self._cache), "bytes": self._cache_size, "limit_bytes": self.cache_bytes,
                "hits": self.stats["cache_hits"], "renders": self.stats["renders"]}

    def clear_cache(self) -> None:
        """Forget every cached render."""
        with self._lock:
            self._cache.clear()
            self._cache_size = 0

    # ----------------------------------------------------------------- errors

    def _require_open(self, doing: str) -> None:
        if self._open:
            return
        if self._disconnected:
            raise DeviceError(f"camera {self.name} is disconnected; reconnect it and call reopen() before {doing}")
        raise DeviceError(f"camera {self.name} is not open; open it before {doing}")


# --------------------------------------------------------------------------------------------- URL parsing


def _lens(text: str) -> tuple[int, int] | None:
    """A lens 'M,N' (row, column, 1-based) of a URL parameter; None for ''."""
    if not text:
        return None
    try:
        m, n = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"master={text!r} must name a lens as 'M,N' (row, column)") from None
    return m, n


def parse_faults(url: str, text: str) -> list[tuple[str, int | None, int]]:
    """'timeout@5,black@9x2' -> [('timeout', 5, 1), ('black', 9, 2)]; InputError naming a bad entry."""
    faults = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        kind, _, rest = part.partition("@")
        at_text, _, count_text = rest.partition("x")
        try:
            at = int(at_text)
            count = int(count_text) if count_text else 1
        except ValueError:
            at = count = 0
        if kind not in FAULT_KINDS or at < 1 or count < 1:
            raise InputError(f"camera URL {url!r}: fault {part!r} must be KIND@N or KIND@NxCOUNT with KIND one of "
                             f"{', '.join(FAULT_KINDS)} and N, COUNT >= 1")
        faults.append((kind, at, count))
    return faults


def _load_camera_config(url: str, name: str) -> CameraConfig:
    """'small', 'hex_small', 'table1' or a TOML path."""
    if name == "small":
        return config_from_dict(SMALL_CAMERA, "small camera")
    if name == "hex_small":
        return config_from_dict(HEX_SMALL_CAMERA, "small hex camera")
    if name == "table1":
        return default_config()
    try:
        return load_config(name)
    except InputError as exc:
        raise InputError(f"camera URL {url!r}: {exc}") from None


def _format_for(cfg: CameraConfig) -> str:
    """The 16-bit container format matching the config's CFA."""
    if cfg.sensor.cfa == "none":
        return "Y16"
    return lookup_format(f"S{cfg.sensor.cfa}16").name


def _finite(name: str, value: Any) -> float:
    if isinstance(value, bool):
        raise InputError(f"{name} {value!r} is not a number")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} {value!r} is not a number") from None
    if not math.isfinite(number):
        raise InputError(f"{name} {value!r} is not a finite number")
    return number


def _check_positive(name: str, value: float) -> None:
    if not (_finite(name, value) > 0):
        raise InputError(f"{name} must be positive, got {value!r}")


class _Params:
    """Typed access to the URL's query parameters; InputError naming the parameter."""

    def __init__(self, url: str, params: dict[str, str]) -> None:
        self.url, self.params = url, params

    def _bad(self, name: str, what: str) -> InputError:
        return InputError(f"camera URL {self.url!r}: parameter {name}={self.params[name]!r} {what}")

    def number(self, name: str, default: float | None, *, positive: bool = False) -> float | None:
        if name not in self.params:
            return default
        try:
            value = float(self.params[name])
        except ValueError:
            raise self._bad(name, "is not a number") from None
        if not math.isfinite(value) or (positive and value <= 0):
            raise self._bad(name, "must be a positive number" if positive else "must be finite")
        return value

    def integer(self, name: str, default: int, *, minimum: int) -> int:
        if name not in self.params:
            return default
        try:
            value = int(self.params[name])
        except ValueError:
            raise self._bad(name, "is not a whole number") from None
        if value < minimum:
            raise self._bad(name, f"must be at least {minimum}")
        return value

    def numbers(self, name: str, default: tuple[float, ...]) -> tuple[float, ...]:
        if name not in self.params:
            return default
        try:
            values = tuple(float(v) for v in self.params[name].split(","))
        except ValueError:
            raise self._bad(name, "must be numbers separated by commas, e.g. 10,-10") from None
        if not all(math.isfinite(v) for v in values):
            raise self._bad(name, "must be finite")
        return values

    def pair(self, name: str, default: tuple[float, float] | None) -> tuple[float, float] | None:
        if name not in self.params:
            return default
        try:
            x, y = (float(v) for v in self.params[name].split(","))
        except ValueError:
            raise self._bad(name, "must be two numbers 'X,Y' in mm") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise self._bad(name, "must be finite")
        return x, y

    def grid(self, name: str, default: tuple[int, int]) -> tuple[int, int]:
        if name not in self.params:
            return default
        try:
            cols, rows = (int(v) for v in self.params[name].lower().split("x"))
        except ValueError:
            raise self._bad(name, "must be COLSxROWS, e.g. 3x3") from None
        if cols < 1 or rows < 1:
            raise self._bad(name, "must have at least one column and one row")
        return cols, rows

    def flag(self, name: str, default: bool) -> bool:
        if name not in self.params:
            return default
        text = self.params[name].lower()
        if text not in ("0", "1", "true", "false", "on", "off"):
            raise self._bad(name, "must be 0 or 1")
        return text in ("1", "true", "on")


register_camera_scheme("mock", MockCamera.from_url)
