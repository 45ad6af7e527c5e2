"""A simulated wafer of microlens arrays for mock benches: where each array sits and what is wrong with it.

A wafer holds `cols` x `rows` arrays on a square grid of `pitch_mm`. Array W(m,n) is row m (1 = top) and
column n (1 = left), like the lens numbering U(m,n); its centre is at stage coordinates
``x = origin_x + (n - 1) * pitch``, ``y = origin_y + (m - 1) * pitch`` (mm; x right, y down as in the
raw image). Each array has its own seeded `ErrorMap` (`random_defects`), so a scan over the wafer can be
checked found-vs-seeded array by array. The arrays are the camera config's MLA: square or hex packed
(mla.packing; a hex array's outline is `Lattice.extent`, its error maps are made for the hex lattice).

A wafer can also tell a production story (`Production`): a defect of the master (mold or stamp) that most
replicas carry at the same lens, and a process drift — the MLA–sensor distance creeping from one array on, in
production order over the lot (row by row, wafer after wafer: `first_index` numbers this wafer's W(1,1)).

The camera looks at the wafer point under the optical axis, which is the stage position: an array
whose centre is at C appears shifted by ``C - position`` (that is the ErrorMap's global
``mla_shift_x_um`` / ``mla_shift_y_um``). Only the array nearest the position is drawn; `default_pitch_mm`
keeps neighbours out of the field of view, so nothing else could be seen anyway.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from mlaqc.errors import InputError
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.errormap import ERROR_TYPES, ErrorMap, random_defects
from mlaqc.optics.lattice import Lattice

TRUTH_FORMAT = "mlaqc-mock-wafer"
MAX_ARRAYS = 10_000
# the master defect's kinds: the error-map fields a (type, magnitude, direction) sets
MASTER_FIELDS = {"pitch": ("pitch_um", "pitch_dir_deg"), "decenter": ("decenter_um", "decenter_dir_deg"),
                 "radius": ("radius_front_rel", None), "thickness": ("thickness_um", None)}


@dataclass(frozen=True)
class Production:
    """A lot's story on the mock wafer: the master's defect on lens `master_lens` (type, magnitude in µm or
    relative, direction in degrees) in a seeded `master_share` of the arrays, and from production index
    `drift_from` on the MLA–sensor distance `drift_um` µm larger with every array."""

    master_lens: tuple[int, int] | None = None
    master_type: str = "pitch"
    master_magnitude: float = 1.5
    master_dir_deg: float = 30.0
    master_share: float = 0.8
    drift_from: int | None = None
    drift_um: float = 0.0
    first_index: int = 1

    def check(self, cfg: CameraConfig) -> None:
        if self.master_lens is not None:
            m, n = self.master_lens
            if not (1 <= m <= cfg.mla.count_h and 1 <= n <= cfg.mla.count_w):
                raise InputError(f"master lens U({m},{n}) is not on the {cfg.mla.count_h} x {cfg.mla.count_w} array")
            if self.master_type not in MASTER_FIELDS:
                raise InputError(f"master defect type {self.master_type!r} must be one of {', '.join(MASTER_FIELDS)}")
        if not (0.0 <= self.master_share <= 1.0):
            raise InputError(f"master_share={self.master_share!r} must lie in 0..1")
        if self.first_index < 1 or (self.drift_from is not None and self.drift_from < 1):
            raise InputError("first_index and drift_from are production indexes: 1 or more")
        if not math.isfinite(self.drift_um):
            raise InputError(f"drift_um={self.drift_um!r} must be a number")

    def carries_master(self, seed: int, m: int, n: int) -> bool:
        """Whether array W(m,n) of the wafer made with `seed` carries the master's defect (a seeded draw)."""
        if self.master_lens is None:
            return False
        digest = hashlib.sha256(f"mlaqc-master:{seed}:{m}:{n}".encode()).digest()
        return int.from_bytes(digest[:4], "little") / 2**32 < self.master_share

    def drift(self, index: int) -> float:
        """The MLA–sensor distance added to the array of production index `index` (µm)."""
        if self.drift_from is None or index < self.drift_from:
            return 0.0
        return self.drift_um * (index - self.drift_from + 1)

    def master_error(self) -> dict[str, float]:
        value_key, dir_key = MASTER_FIELDS[self.master_type]
        out = {value_key: self.master_magnitude}
        if self.master_type == "radius":
            out["radius_back_rel"] = self.master_magnitude
        if dir_key:
            out[dir_key] = self.master_dir_deg
        return out


@dataclass(frozen=True)
class WaferArray:
    """One microlens array on the wafer: W(m,n), its centre in stage coordinates and its seeded errors."""

    m: int  # row, 1 = top
    n: int  # column, 1 = left
    centre_mm: tuple[float, float]
    seed: int
    errors: ErrorMap

    @property
    def name(self) -> str:
        """'W(m,n)'."""
        return f"W({self.m},{self.n})"

    @cached_property
    def error_map_json(self) -> dict[str, Any]:
        """The ground-truth error map as JSON (computed once)."""
        return self.errors.to_json_dict()


def array_size_mm(cfg: CameraConfig) -> tuple[float, float]:
    """Width and height of one array (mm): its cells' outline (a hex array's rows are sqrt(3)/2 of a pitch
    apart and every other one half a pitch longer)."""
    if cfg.mla.packing == "hex":
        return Lattice.of(cfg).extent
    return cfg.mla.count_w * cfg.mla.pitch_um * 1e-3, cfg.mla.count_h * cfg.mla.pitch_um * 1e-3


def field_size_mm(cfg: CameraConfig) -> tuple[float, float]:
    """Width and height of the sensor's field at the MLA (mm; the MLA sits roughly on the sensor scale)."""
    pix = cfg.pixel_at_mla_um * 1e-3  # the field the sensor sees in the MLA's plane (through any relay)
    return cfg.sensor.width_px * pix, cfg.sensor.height_px * pix


def default_pitch_mm(cfg: CameraConfig) -> float:
    """Smallest whole-mm pitch at which a neighbouring array can never enter the field of view."""
    aw, ah = array_size_mm(cfg)
    fw, fh = field_size_mm(cfg)
    return float(math.ceil(max(aw + fw, ah + fh)))


def array_seed(seed: int, m: int, n: int) -> int:
    """The defect seed of array W(m,n) on a wafer made with `seed` (stable across versions)."""
    digest = hashlib.sha256(f"mlaqc-wafer:{seed}:{m}:{n}".encode()).digest()
    return int.from_bytes(digest[:4], "little")


class Wafer:
    """`cols` x `rows` arrays of the camera's MLA, `pitch_mm` apart, W(1,1) centred at `origin_mm`."""

    def __init__(self, cfg: CameraConfig, *, cols: int = 1, rows: int = 1, pitch_mm: float | None = None,
                 origin_mm: tuple[float, float] = (10.0, 10.0), defects: int = 5, seed: int = 0,
                 defect_types: tuple[str, ...] = ("pitch", "decenter", "radius"),
                 production: Production | None = None) -> None:
        if not (isinstance(cols, int) and isinstance(rows, int)) or cols < 1 or rows < 1 or cols * rows > MAX_ARRAYS:
            raise InputError(f"a wafer needs 1..{MAX_ARRAYS} arrays in cols x rows, got {cols}x{rows}")
        aw, ah = array_size_mm(cfg)
        pitch = default_pitch_mm(cfg) if pitch_mm is None else float(pitch_mm)
        if not math.isfinite(pitch) or pitch < max(aw, ah):
            raise InputError(f"wafer pitch_mm={pitch_mm!r} must be at least the array size "
                             f"({max(aw, ah):g} mm) so arrays do not overlap")
        if len(origin_mm) != 2 or not all(math.isfinite(v) for v in origin_mm):
            raise InputError(f"wafer origin_mm={origin_mm!r} must be two finite numbers (x, y)")
        bad = [t for t in defect_types if t not in ERROR_TYPES]
        if bad or not defect_types:
            raise InputError(f"wafer defect types {list(defect_types)} must be some of {', '.join(ERROR_TYPES)}")
        if not isinstance(defects, int) or defects < 0:
            raise InputError(f"wafer defects={defects!r} must be a whole number >= 0")
        self.cfg = cfg
        self.cols, self.rows = cols, rows
        self.pitch_mm = pitch
        self.origin_mm = (float(origin_mm[0]), float(origin_mm[1]))
        self.defects = defects
        self.seed = int(seed)
        self.defect_types = tuple(defect_types)
        self.production = production or Production()
        self.production.check(cfg)
        self._arrays: dict[tuple[int, int], WaferArray] = {}

    def __repr__(self) -> str:
        hex_ = " hex" if self.cfg.mla.packing == "hex" else ""
        return (f"<Wafer {self.cols}x{self.rows} arrays of {self.cfg.mla.count_w}x{self.cfg.mla.count_h}{hex_} lenses, "
                f"pitch {self.pitch_mm:g} mm, W(1,1) at {self.origin_mm} mm, {self.defects} defects each>")

    def centre_mm(self, m: int, n: int) -> tuple[float, float]:
        """Stage position (mm) that centres array W(m,n) in the field of view."""
        return self.origin_mm[0] + (n - 1) * self.pitch_mm, self.origin_mm[1] + (m - 1) * self.pitch_mm

    def array(self, m: int, n: int) -> WaferArray:
        """Array W(m,n) (1-based), its error map generated on first use."""
        if not (1 <= m <= self.rows and 1 <= n <= self.cols):
            raise InputError(f"wafer has no array W({m},{n}); it has {self.rows} rows and {self.cols} columns")
        key = (m, n)
        found = self._arrays.get(key)
        if found is None:
            seed = array_seed(self.seed, m, n)
            mla = self.cfg.mla
            if self.defects:
                errors = random_defects(mla.count_h, mla.count_w, self.defects, seed, types=self.defect_types,
                                        packing=mla.packing)
            else:
                errors = ErrorMap.zeros(mla.count_h, mla.count_w, mla.packing)
            errors = self._story(errors, m, n)
            found = self._arrays[key] = WaferArray(m, n, self.centre_mm(m, n), seed, errors)
        return found

    def index(self, m: int, n: int) -> int:
        """Production index of W(m,n) over the lot: row by row from this wafer's `first_index`."""
        return self.production.first_index + (m - 1) * self.cols + (n - 1)

    def _story(self, errors: ErrorMap, m: int, n: int) -> ErrorMap:
        """The production story's part of W(m,n)'s errors: the master's defect, the drift."""
        p = self.production
        if p.carries_master(self.seed, m, n):
            errors = errors.with_lens(*p.master_lens, **p.master_error())
        drift = p.drift(self.index(m, n))
        if drift:
            errors = errors.with_globals(mla_sensor_distance_um=errors.globals["mla_sensor_distance_um"] + drift)
        return errors

    def arrays(self) -> list[WaferArray]:
        """Every array, row by row."""
        return [self.array(m, n) for m in range(1, self.rows + 1) for n in range(1, self.cols + 1)]

    def nearest(self, x_mm: float, y_mm: float) -> WaferArray:
        """The array whose centre is nearest to stage position (x_mm, y_mm)."""
        n = int(np.clip(round((x_mm - self.origin_mm[0]) / self.pitch_mm), 0, self.cols - 1)) + 1
        m = int(np.clip(round((y_mm - self.origin_mm[1]) / self.pitch_mm), 0, self.rows - 1)) + 1
        return self.array(m, n)

    def locate(self, x_mm: float, y_mm: float) -> tuple[WaferArray, tuple[float, float]]:
        """(array seen at this stage position, its offset in µm = centre - position, x right / y down)."""
        arr = self.nearest(x_mm, y_mm)
        return arr, ((arr.centre_mm[0] - x_mm) * 1000.0, (arr.centre_mm[1] - y_mm) * 1000.0)

    def in_view(self, offset_um: tuple[float, float]) -> bool:
        """False when an array at this offset lies wholly outside the field of view (nothing to render)."""
        aw, ah = array_size_mm(self.cfg)
        fw, fh = field_size_mm(self.cfg)
        return abs(offset_um[0]) * 1e-3 < 0.5 * (aw + fw) and abs(offset_um[1]) * 1e-3 < 0.5 * (ah + fh)

    def layout(self) -> dict[str, Any]:
        """The wafer's geometry and seeding parameters (JSON)."""
        return {"cols": self.cols, "rows": self.rows, "pitch_mm": self.pitch_mm, "origin_mm": list(self.origin_mm),
                "defects_per_array": self.defects, "defect_types": list(self.defect_types), "seed": self.seed,
                "array_size_mm": list(array_size_mm(self.cfg)), "mla_shape": [self.cfg.mla.count_h, self.cfg.mla.count_w],
                **({"mla_packing": "hex"} if self.cfg.mla.packing == "hex" else {}),
                **({"production": dataclasses.asdict(self.production)} if self.production != Production() else {})}

    def truth(self) -> dict[str, Any]:
        """Ground truth for the whole wafer (JSON): geometry, and per array its name, centre, seed and errors."""
        return {
            "format": TRUTH_FORMAT,
            "version": 1,
            **self.layout(),
            "subimage_pitch_px": self.cfg.layout.subimage_pitch_px,
            "arrays": [{"name": a.name, "m": a.m, "n": a.n, "centre_mm": list(a.centre_mm), "seed": a.seed,
                        "error_map": a.error_map_json,
                        **({"index": self.index(a.m, a.n),
                            "master": self.production.carries_master(self.seed, a.m, a.n),
                            "drift_um": self.production.drift(self.index(a.m, a.n))}
                           if self.production != Production() else {})} for a in self.arrays()],
        }

    def truth_digest(self) -> str:
        """sha256 of the truth JSON: two wafers with the same digest hold the same arrays and defects."""
        return hashlib.sha256(json.dumps(self.truth(), sort_keys=True).encode()).hexdigest()
