"""Per-microlens manufacturing errors and global assembly errors, with a JSON format keyed by U(m,n).

Conventions (DESIGN.md §2-3):
- Tables have shape (N_H, N_W); element [m-1, n-1] is lens U(m,n), row m from the top, column n from the left.
- Direction angles (alpha, beta) are in degrees, counterclockwise from the image's +x (towards larger n)
  towards the image's top (smaller m), as the raw image is displayed (the paper's y-z frame).
- pitch: the whole lens (both surfaces) shifted in the MLA plane. With `mla.boundaries = "grid"` the
  cell aperture (square or hexagon) stays on the nominal grid, only the optics move; with "sag-intersection" the lens
  ends where its sags meet its neighbours', so its boundaries move by about half the shift.
- decenter: the rear (sensor-side) surface shifted against the front one.
- radius_front/back: relative radius errors, r -> r * (1 + eps).
- tilt_x/y: the lens rotated about its centre, about the image x axis and the image y axis (pointing
  down), right-handed with z along the light.
- thickness: vertex thickness error; the front vertex stays on the array's reference plane.
Global: MLA shift in its plane (x right, y down, as in the raw image: the stage position of a mock
bench), MLA-sensor distance error, MLA rotation about the optical axis (counterclockwise as displayed),
MLA tilt about x and y.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc.atomic import write_json_atomic
from mlaqc.errors import InputError
from mlaqc.optics.lattice import packing_of

FORMAT = "mlaqc-error-map"
VERSION = 1

# Per-lens fields: (name in JSON and ErrorMap, unit).
LENS_FIELDS: dict[str, str] = {
    "pitch_um": "µm",
    "pitch_dir_deg": "deg",
    "decenter_um": "µm",
    "decenter_dir_deg": "deg",
    "radius_front_rel": "1",
    "radius_back_rel": "1",
    "tilt_x_deg": "deg",
    "tilt_y_deg": "deg",
    "thickness_um": "µm",
}
GLOBAL_FIELDS: dict[str, str] = {
    "mla_shift_x_um": "µm",
    "mla_shift_y_um": "µm",
    "mla_sensor_distance_um": "µm",
    "mla_rotation_deg": "deg",
    "mla_tilt_x_deg": "deg",
    "mla_tilt_y_deg": "deg",
}
ERROR_TYPES = ("pitch", "decenter", "radius", "tilt", "thickness")

# Physical bounds a map is checked against (beyond them the lens model is meaningless).
_BOUNDS = {
    "pitch_um": (0.0, 50.0),
    "decenter_um": (0.0, 50.0),
    "radius_front_rel": (-0.5, 1.0),
    "radius_back_rel": (-0.5, 1.0),
    "tilt_x_deg": (-20.0, 20.0),
    "tilt_y_deg": (-20.0, 20.0),
    "thickness_um": (-9.0, 100.0),
}


@dataclass(frozen=True)
class ErrorMap:
    """All errors of one MLA: a (N_H, N_W) float64 array per lens field, and the global errors."""

    shape: tuple[int, int]
    lens: dict[str, np.ndarray]
    globals: dict[str, float] = field(default_factory=lambda: {k: 0.0 for k in GLOBAL_FIELDS})
    packing: str = "square"  # the lattice the tables index (mlaqc.optics.lattice)

    @classmethod
    def zeros(cls, count_h: int, count_w: int, packing: str = "square") -> ErrorMap:
        """A perfect array of the given size."""
        return cls((count_h, count_w), {k: np.zeros((count_h, count_w)) for k in LENS_FIELDS}, packing=packing)

    def with_lens(self, m: int, n: int, **values: float) -> ErrorMap:
        """A copy with lens U(m,n) (1-based) given the named error values."""
        lens = {k: v.copy() for k, v in self.lens.items()}
        for key, value in values.items():
            if key not in LENS_FIELDS:
                raise InputError(f"unknown per-lens error field {key!r}; expected one of {list(LENS_FIELDS)}")
            lens[key][m - 1, n - 1] = value
        out = ErrorMap(self.shape, lens, dict(self.globals), self.packing)
        out.validate("error map")
        return out

    def with_globals(self, **values: float) -> ErrorMap:
        """A copy with global errors set."""
        unknown = set(values) - set(GLOBAL_FIELDS)
        if unknown:
            raise InputError(f"unknown global error field {sorted(unknown)[0]!r}; expected one of {list(GLOBAL_FIELDS)}")
        return ErrorMap(self.shape, {k: v.copy() for k, v in self.lens.items()}, {**self.globals, **values}, self.packing)

    def defective(self) -> np.ndarray:
        """Boolean (N_H, N_W): lenses with any non-zero error."""
        mags = [self.lens[k] for k in LENS_FIELDS if not k.endswith("_dir_deg")]
        return np.any(np.stack(mags) != 0, axis=0)

    def lens_type(self) -> np.ndarray:
        """(N_H, N_W) array of the dominant error type name per lens ('' for a perfect lens)."""
        out = np.full(self.shape, "", dtype=object)
        for name, keys in (("thickness", ["thickness_um"]), ("tilt", ["tilt_x_deg", "tilt_y_deg"]),
                           ("radius", ["radius_front_rel", "radius_back_rel"]), ("decenter", ["decenter_um"]),
                           ("pitch", ["pitch_um"])):
            hit = np.any(np.stack([self.lens[k] != 0 for k in keys]), axis=0)
            out[hit] = name
        return out

    def has_tilt(self) -> bool:
        """True if any lens is tilted (the tracer then takes its slower rotated-frame path)."""
        return bool(np.any(self.lens["tilt_x_deg"]) or np.any(self.lens["tilt_y_deg"]))

    def validate(self, source: str) -> None:
        """Check shapes, finiteness and physical bounds; raise InputError naming lens and field."""
        for key in LENS_FIELDS:
            arr = self.lens.get(key)
            if arr is None or arr.shape != self.shape:
                raise InputError(f"{source}: per-lens table {key!r} is missing or not of shape {self.shape}")
            bad = ~np.isfinite(arr)
            if bad.any():
                m, n = (int(i) + 1 for i in np.argwhere(bad)[0])
                raise InputError(f"{source}: lens U({m},{n}) field {key!r} is not a finite number")
            if key in _BOUNDS:
                lo, hi = _BOUNDS[key]
                out = (arr < lo) | (arr > hi)
                if out.any():
                    m, n = (int(i) + 1 for i in np.argwhere(out)[0])
                    raise InputError(f"{source}: lens U({m},{n}) field {key!r} = {arr[m - 1, n - 1]:g} is outside [{lo:g}, {hi:g}]")
        for key, value in self.globals.items():
            if key not in GLOBAL_FIELDS or not math.isfinite(value):
                raise InputError(f"{source}: global error {key!r} must be a known field with a finite value")

    def to_json_dict(self) -> dict[str, Any]:
        """JSON form: only lenses with a non-zero field are listed, keyed by m and n (1-based)."""
        nonzero = np.any(np.stack([self.lens[k] != 0 for k in LENS_FIELDS]), axis=0)
        lenses = []
        for m, n in np.argwhere(nonzero):
            entry: dict[str, Any] = {"m": int(m) + 1, "n": int(n) + 1}
            entry.update({k: float(self.lens[k][m, n]) for k in LENS_FIELDS if self.lens[k][m, n] != 0})
            entry["type"] = str(self.lens_type()[m, n]) or "none"
            lenses.append(entry)
        return {
            "format": FORMAT,
            "version": VERSION,
            "shape": {"rows": self.shape[0], "cols": self.shape[1]},
            "packing": self.packing,
            "units": {**LENS_FIELDS, **GLOBAL_FIELDS},
            "global": {k: float(v) for k, v in self.globals.items()},
            "lenses": lenses,
        }

    def save(self, path: str | Path) -> None:
        """Write the JSON error map atomically."""
        write_json_atomic(path, self.to_json_dict())


def load_error_map(path: str | Path, shape: tuple[int, int] | None = None, packing: str | None = None) -> ErrorMap:
    """Read and validate a JSON error map; `shape` (N_H, N_W) and `packing` must match the camera's MLA
    if given (a map without "packing" was written for a square array)."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"error map {str(p)!r} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"error map {str(p)!r} is not readable JSON ({exc.__class__.__name__}: {exc})") from None
    return error_map_from_dict(data, str(p), shape, packing)


def error_map_from_dict(data: Any, source: str, shape: tuple[int, int] | None = None,
                        packing: str | None = None) -> ErrorMap:
    """Build an ErrorMap from its JSON dict, naming the entry at fault in any error."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"{source}: not an mlaqc error map (missing \"format\": \"{FORMAT}\")")
    if data.get("version") != VERSION:
        raise InputError(f"{source}: error map version {data.get('version')!r} is not supported (expected {VERSION})")
    sh = data.get("shape")
    if not (isinstance(sh, dict) and all(isinstance(sh.get(k), int) and sh[k] > 0 for k in ("rows", "cols"))):
        raise InputError(f"{source}: \"shape\" must be {{\"rows\": N_H, \"cols\": N_W}} with positive integers")
    map_shape = (sh["rows"], sh["cols"])
    if shape is not None and tuple(shape) != map_shape:
        raise InputError(f"{source}: error map is for a {map_shape[0]}x{map_shape[1]} MLA but the camera has {shape[0]}x{shape[1]}")
    map_packing = packing_of(data, source)
    if packing is not None and packing != map_packing:
        raise InputError(f"{source}: error map is for a {map_packing} lattice but the camera's MLA is {packing} "
                         f"(mla.packing)")
    emap = ErrorMap.zeros(*map_shape, packing=map_packing)
    glob = data.get("global", {})
    if not isinstance(glob, dict):
        raise InputError(f"{source}: \"global\" must be an object")
    for key, value in glob.items():
        if key not in GLOBAL_FIELDS or not _is_number(value):
            raise InputError(f"{source}: global error {key!r} must be one of {list(GLOBAL_FIELDS)} with a number")
        emap.globals[key] = float(value)
    lenses = data.get("lenses", [])
    if not isinstance(lenses, list):
        raise InputError(f"{source}: \"lenses\" must be a list")
    for i, entry in enumerate(lenses):
        _apply_lens_entry(emap, entry, i, source)
    emap.validate(source)
    return emap


def _apply_lens_entry(emap: ErrorMap, entry: Any, index: int, source: str) -> None:
    """Copy one JSON lens entry into the tables."""
    if not isinstance(entry, dict):
        raise InputError(f"{source}: lenses[{index}] must be an object")
    m, n = entry.get("m"), entry.get("n")
    rows, cols = emap.shape
    if not (isinstance(m, int) and isinstance(n, int) and 1 <= m <= rows and 1 <= n <= cols):
        raise InputError(f"{source}: lenses[{index}] needs integer m in 1..{rows} and n in 1..{cols}, got m={m!r}, n={n!r}")
    for key, value in entry.items():
        if key in ("m", "n", "type"):
            continue
        if key not in LENS_FIELDS:
            raise InputError(f"{source}: lenses[{index}] (U({m},{n})) has unknown field {key!r}")
        if not _is_number(value):
            raise InputError(f"{source}: lenses[{index}] (U({m},{n})) field {key!r} must be a number, got {value!r}")
        emap.lens[key][m - 1, n - 1] = float(value)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


@dataclass(frozen=True)
class DefectSpec:
    """Magnitude ranges for the random defect generator (uniform in [lo, hi], random sign/direction)."""

    pitch_um: tuple[float, float] = (1.0, 5.0)
    decenter_um: tuple[float, float] = (5.0, 15.0)
    radius_rel: tuple[float, float] = (0.05, 0.2)
    tilt_deg: tuple[float, float] = (1.0, 5.0)
    thickness_um: tuple[float, float] = (2.0, 8.0)


def physical_types(types: tuple[str, ...], mla) -> tuple[str, ...]:
    """The requested defect types that the MLA can have: no decenter on a flat-sided (plano-convex) one,
    where it would change nothing; InputError if none is left."""
    kept = tuple(t for t in types if not (t == "decenter" and mla.flat_sided))
    if not kept:
        raise InputError("a decenter changes nothing on a plano-convex MLA (one surface is flat): ask for other "
                         "defect types")
    return kept


def random_defects(count_h: int, count_w: int, n_defects: int, seed: int,
                   types: tuple[str, ...] = ("pitch", "decenter", "radius"),
                   spec: DefectSpec = DefectSpec(), margin: int = 1, packing: str = "square") -> ErrorMap:
    """A seeded map with `n_defects` lenses of random type, magnitude and direction.

    Defective lenses are kept `margin` lenses from the border and never touch each other (the 3 x 3 index
    box, which holds a square lens' 8 and a hex lens' 6 neighbours), so each defect's signature can be
    told apart.
    """
    for t in types:
        if t not in ERROR_TYPES:
            raise InputError(f"unknown defect type {t!r}; expected some of {ERROR_TYPES}")
    rng = np.random.default_rng(seed)
    emap = ErrorMap.zeros(count_h, count_w, packing)
    taken = np.zeros((count_h, count_w), bool)
    inner = [(m, n) for m in range(margin, count_h - margin) for n in range(margin, count_w - margin)]
    order = rng.permutation(len(inner))
    placed = 0
    for idx in order:
        if placed == n_defects:
            break
        m, n = inner[idx]
        if taken[max(m - 1, 0):m + 2, max(n - 1, 0):n + 2].any():
            continue
        taken[m, n] = True
        _seed_one(emap, m, n, types[int(rng.integers(len(types)))], spec, rng)
        placed += 1
    if placed < n_defects:
        raise InputError(f"cannot place {n_defects} separated defects on a {count_h}x{count_w} MLA (placed {placed})")
    return emap


def lens_error_fields(kind: str, magnitude: float, direction_deg: float = 0.0) -> dict[str, float]:
    """The per-lens fields (`ErrorMap.with_lens` keywords) of one basic error of `kind`: pitch and decenter
    in µm along `direction_deg`, radius (both surfaces alike) and thickness signed, tilt in degrees."""
    if kind == "pitch":
        return {"pitch_um": magnitude, "pitch_dir_deg": direction_deg}
    if kind == "decenter":
        return {"decenter_um": magnitude, "decenter_dir_deg": direction_deg}
    if kind == "radius":
        return {"radius_front_rel": magnitude, "radius_back_rel": magnitude}
    if kind == "tilt":
        mag, a = math.radians(magnitude), math.radians(direction_deg)
        return {"tilt_x_deg": math.degrees(mag * math.cos(a)), "tilt_y_deg": math.degrees(mag * math.sin(a))}
    if kind == "thickness":
        return {"thickness_um": magnitude}
    raise InputError(f"unknown error kind {kind!r}; expected pitch, decenter, radius, tilt or thickness")


def _seed_one(emap: ErrorMap, m: int, n: int, kind: str, spec: DefectSpec, rng: np.random.Generator) -> None:
    """Give lens (m, n) (0-based) one random error of `kind`."""
    direction = float(rng.uniform(0.0, 360.0))
    if kind in ("pitch", "decenter", "tilt"):
        magnitude = rng.uniform(*getattr(spec, {"pitch": "pitch_um", "decenter": "decenter_um", "tilt": "tilt_deg"}[kind]))
    else:  # radius, thickness: either sign
        magnitude = rng.uniform(*getattr(spec, {"radius": "radius_rel", "thickness": "thickness_um"}[kind])) \
            * rng.choice([-1.0, 1.0])
    for key, value in lens_error_fields(kind, float(magnitude), direction).items():
        emap.lens[key][m, n] = value
