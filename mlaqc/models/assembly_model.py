"""The assembly readings' calibration through the camera model: what the projection fit reads on the
tracer's own frames of this camera.

The projection fit (mlaqc.inspection.projection) models a sub-image's centre as the lens centre seen from
one exit-pupil point. A real sub-image is a vignetted, aberrated image of the main lens' pupil, and the
calibration's disc centre of it is not exactly that point: on the Table 1 camera the design frame reads
+2.3 µm of distance, a tilt reads 4 % large and 10 % larger still with the sensor 15 µm further back, and
the distance reading's slope runs from 1.08 at -25 µm to 0.90 at +25 µm (the discs grow with the gap and
their vignetted rims pull the centres). So the camera is rendered by the tracer (every surface, both rims
of the main lens, the sensor formation) at its design placement, at `DISTANCE_NODES_UM`, at `SINGLE_NODES` x
`STEPS` of each other error and at steps of every pair of errors, each frame calibrated and read like an inspected
one, with the same rays (common random numbers: the differences are nearly noise-free). Each raw
component i (the six fit readings and the sub-images' median radius) is modelled to second order,

    raw_i = zero_i + sum_j P_ij(true_j) + sum_{j<k} (X_ijk true_j true_k + Y_ijk true_j true_k^2)

(P_ij: a cubic without constant, fitted to each error's frames alone; the pairs are rendered at
(+step_j, ±step_k), which gives X and Y), and an inspected frame's readings solve that system (Newton).
Two validation frames with all six errors at once, read through the model, measure what it leaves out
(higher-order cross terms): the larger error of each reading, scaled to a frame's own errors
(`systematic_at`), is added to its sigma as the calibration's systematic uncertainty. Cached on disk by
the optics' key.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import itertools
import json
import sys
from dataclasses import dataclass

import numpy as np

from mlaqc.errors import InputError

from mlaqc.inspection.projection import FIELDS, raw_components
from mlaqc.models.reference import geometry_hash_view, mla_hash_view, sensor_hash_view
from mlaqc.models.store import stored_json
from mlaqc.optics.config import CameraConfig

FORMAT_VERSION = 5
COMPONENTS = 7  # the six raw fit readings and the median sub-image radius (px)
DISTANCE_NODES_UM = (-40.0, -20.0, -10.0, 10.0, 20.0, 40.0)
# the other errors are rendered at SINGLE_NODES times these steps: of the size a QC spec bounds
SINGLE_NODES = (-2.0, -1.0, 1.0, 2.0)
STEPS = {"mla_rotation_deg": 0.3, "mla_tilt_x_deg": 0.3, "mla_tilt_y_deg": 0.3, "mla_shift_x_um": 20.0,
         "mla_shift_y_um": 20.0}
# all six errors at once, in two sign patterns: what the model leaves out (its systematic uncertainty)
VALIDATION = ({"mla_sensor_distance_um": -15.0, "mla_rotation_deg": -0.2, "mla_tilt_x_deg": -0.2,
               "mla_tilt_y_deg": 0.3, "mla_shift_x_um": -12.0, "mla_shift_y_um": 20.0},
              {"mla_sensor_distance_um": 10.0, "mla_rotation_deg": 0.2, "mla_tilt_x_deg": -0.3,
               "mla_tilt_y_deg": -0.3, "mla_shift_x_um": 15.0, "mla_shift_y_um": 15.0})
DISTANCE_STEP_UM = 15.0  # the distance of the pair frames
VALIDATION_SIZE = np.array([max(abs(v[k]) for v in VALIDATION) for k in FIELDS])
RAYS_PER_PIXEL = 100.0
SEED = 20180524


@dataclass(frozen=True)
class AssemblyModel:
    """Zero point, per-error response polynomials and systematic floor of the raw readings (module doc)."""

    pupil_mm: float  # exit-pupil distance the projection fit uses
    zero: tuple[float, ...]  # (COMPONENTS,) raw readings of the design frame
    zero_sigma: tuple[float, ...]  # their statistical 1-sigma
    poly: tuple  # [j][i] = (c1, c2, c3): P_ij(t) = c1 t + c2 t^2 + c3 t^3
    systematic: tuple[float, ...]  # (6,) per reading: the validation frame's error through the model
    distance_range_um: float  # the distance nodes' extent (readings beyond it are extrapolated)
    key: str
    cross: tuple = ()  # [0][j][k] = X_.jk, [1][j][k] = Y_.jk (COMPONENTS,) for j < k, zeros elsewhere
    single_fit: tuple[float, ...] = (0.0,) * 6  # per error: its cubic's rms misfit at its nodes (reading units)

    def systematic_at(self, true: np.ndarray) -> np.ndarray:
        """The model's systematic 1-sigma at readings `true`: the validation frames' error, scaled by what
        a cross term grows with (the product of the two largest errors, each in units of the validation
        frames' size) and by how far the largest goes beyond them; each error's own curve's misfit."""
        u = np.sort(np.abs(np.asarray(true, float)) / VALIDATION_SIZE)[::-1]
        scale = u[0] * u[1] + max(u[0] - 1.0, 0.0) ** 2
        out = np.asarray(self.systematic, float) * scale
        return np.hypot(out, self.single_fit)

    def extent(self) -> np.ndarray:
        """How far each error was rendered alone (FIELDS order): beyond it readings are extrapolated."""
        return np.array([self.distance_range_um] + [max(map(abs, SINGLE_NODES)) * STEPS[k] for k in FIELDS[1:]])

    @functools.cached_property
    def _tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """zero (COMPONENTS,), poly (6, COMPONENTS, 3) and the cross terms X, Y (6, 6, COMPONENTS) as arrays,
        made once (the Newton solves evaluate the model many times)."""
        x, y = np.asarray(self.cross, float)
        return np.asarray(self.zero, float), np.asarray(self.poly, float), x, y

    def raw(self, true: np.ndarray) -> np.ndarray:
        """Predicted raw components for true readings `true` (6,)."""
        zero, c, x, y = self._tables
        powers = np.stack([true, true ** 2, true ** 3], axis=-1)  # (6, 3)
        return (zero + np.einsum("jic,jc->i", c, powers)
                + np.einsum("jki,j,k->i", x, true, true) + np.einsum("jki,j,k->i", y, true, true ** 2))

    def slopes(self, true: np.ndarray) -> np.ndarray:
        """d raw_i / d true_j at `true`: (COMPONENTS, 6)."""
        _, c, x, y = self._tables
        d = np.stack([np.ones_like(true), 2 * true, 3 * true ** 2], axis=-1)
        return (np.einsum("jic,jc->ij", c, d) + np.einsum("jki,k->ij", x, true) + np.einsum("kji,k->ij", x, true)
                + np.einsum("jki,k->ij", y, true ** 2) + 2 * np.einsum("kji,k,j->ij", y, true, true))

    def solve(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True readings (6,) whose model prediction matches the raw fit readings raw[:6] (Newton), and the
        model's slopes there (6 x 6)."""
        true = np.zeros(6)
        for _ in range(30):
            slopes = self.slopes(true)[:6]
            step = np.linalg.solve(slopes, raw[:6] - self.raw(true)[:6])
            true = true + step
            if np.all(np.abs(step) < 1e-9 * (1 + np.abs(true))):
                break
        return true, self.slopes(true)[:6]

    def to_json_dict(self) -> dict:
        return {"format": "mlaqc-assembly-model", "version": FORMAT_VERSION, "fields": list(FIELDS),
                "pupil_mm": self.pupil_mm, "zero": list(self.zero), "zero_sigma": list(self.zero_sigma),
                "poly": [[list(c) for c in row] for row in self.poly], "systematic": list(self.systematic),
                "distance_range_um": self.distance_range_um, "key": self.key,
                "cross": np.asarray(self.cross, float).tolist(), "single_fit": list(self.single_fit)}

    @classmethod
    def from_json_dict(cls, d: dict) -> AssemblyModel:
        if not isinstance(d, dict) or d.get("format") != "mlaqc-assembly-model" or d.get("version") != FORMAT_VERSION:
            raise ValueError("not an mlaqc assembly model of this version")
        shapes = {"zero": (COMPONENTS,), "zero_sigma": (COMPONENTS,), "poly": (6, COMPONENTS, 3),
                  "systematic": (6,), "cross": (2, 6, 6, COMPONENTS), "single_fit": (6,)}
        arrays = {k: np.asarray(d[k], float) for k in shapes}
        for k, shape in shapes.items():
            if arrays[k].shape != shape or not np.all(np.isfinite(arrays[k])):
                raise ValueError(f"assembly model {k} is not {' x '.join(map(str, shape))} finite numbers")
        if not (np.isfinite(float(d["pupil_mm"])) and float(d["distance_range_um"]) > 0):
            raise ValueError("assembly model pupil or range is not a number")
        return cls(float(d["pupil_mm"]), _nested(arrays["zero"]), _nested(arrays["zero_sigma"]), _nested(arrays["poly"]),
                   _nested(arrays["systematic"]), float(d["distance_range_um"]), str(d["key"]),
                   _nested(arrays["cross"]), _nested(arrays["single_fit"]))


def _nested(a: np.ndarray) -> tuple:
    """A float array as nested tuples (a frozen dataclass' field)."""
    return tuple(_nested(v) for v in a) if a.ndim > 1 else tuple(float(v) for v in a)


def assembly_key(cfg: CameraConfig) -> str:
    """Hash of what places the sub-images: optics, sensor geometry (not the sensor's noise or the image
    formation's blur, which leave the centres where they are, nor the lens-boundary model: with no lens
    error the sag-intersection boundaries lie on the grid, and a global error moves the array whole)."""
    d = cfg.to_dict()
    keep = {"main_lens": d["main_lens"], "mla": mla_hash_view(d["mla"], design=True), "geometry": geometry_hash_view(d["geometry"]),
            "sensor": sensor_hash_view(cfg),
            "fresnel": d["trace"]["fresnel"], "format": FORMAT_VERSION,
            "nodes": DISTANCE_NODES_UM, "single": SINGLE_NODES, "steps": STEPS, "pair_distance": DISTANCE_STEP_UM, "validation": VALIDATION,
            "rpp": RAYS_PER_PIXEL, "seed": SEED}
    return hashlib.sha256(json.dumps(keep, sort_keys=True, default=str).encode()).hexdigest()[:16]


def assembly_model(cfg: CameraConfig, *, build_if_missing: bool = True, rebuild: bool = False,
                   progress=None) -> AssemblyModel:
    """The calibration for `cfg`: shipped, cached, or rendered now (59 full frames: about seven minutes
    for Table 1) and cached; kept in memory once read (a batch or a scan reads it for every frame)."""
    key = assembly_key(cfg)
    if not rebuild and key in _LOADED:
        return _LOADED[key]

    def build() -> AssemblyModel:
        if progress is None:
            print(f"mlaqc: calibrating the assembly readings for these optics ({key}): 59 rendered "
                  "frames, once (`mlaqc models` builds it ahead)", file=sys.stderr, flush=True)
        return build_assembly_model(cfg, progress=progress)

    def checked(d: dict) -> AssemblyModel:
        model = AssemblyModel.from_json_dict(d)
        if model.key != key:
            raise ValueError(f"assembly model {model.key} stored as {key}")
        return model

    model = stored_json(f"assembly_{key}.json", build, AssemblyModel.to_json_dict, checked, rebuild=rebuild,
                        build_if_missing=build_if_missing)
    _LOADED[key] = model
    return model


_LOADED: dict[str, AssemblyModel] = {}


def render_grid(cfg: CameraConfig, glob: dict[str, float], *, rays_per_pixel: float, seed: int):
    """Render `cfg`'s white frame with global errors `glob` and calibrate it (its Grid)."""
    from mlaqc.inspection.calibrate import calibrate_for
    from mlaqc.optics.errormap import ErrorMap
    from mlaqc.optics.sensor import white_level
    from mlaqc.optics.simulate import simulate

    em = ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w, cfg.mla.packing).with_globals(**glob)
    raw = simulate(cfg, errors=em, rays_per_pixel=rays_per_pixel, seed=seed).raw
    blk = cfg.sensor.black_level_dn
    img = (raw.astype(np.float32) - blk) / (white_level(cfg.sensor) - blk)
    return calibrate_for(img, cfg)


def read_grid(grid, cfg: CameraConfig, pupil_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A calibrated frame's raw components (COMPONENTS,) and their statistical 1-sigma."""
    out = raw_components(grid, cfg, pupil_mm)
    if out is None:
        raise ValueError("a rendered frame of the camera could not be read for its assembly calibration")
    return out[0], np.sqrt(np.diag(out[1]))


def build_assembly_model(cfg: CameraConfig, *, rays_per_pixel: float = RAYS_PER_PIXEL, seed: int = SEED,
                         progress=None) -> AssemblyModel:
    """Render and read the frames of the module docstring (59) and fit the model to them."""
    from mlaqc.inspection.projection import pupil_distance_mm

    b = pupil_distance_mm(cfg)
    steps = {FIELDS[0]: DISTANCE_STEP_UM} | STEPS
    pairs = list(itertools.combinations(range(6), 2))
    total = 1 + len(DISTANCE_NODES_UM) + len(SINGLE_NODES) * len(STEPS) + 2 * len(pairs) + len(VALIDATION)
    done = 0

    def read(glob):
        nonlocal done
        try:
            grid = render_grid(cfg, glob, rays_per_pixel=rays_per_pixel, seed=seed)
        except InputError as exc:
            placed = ", ".join(f"{k} = {v:g}" for k, v in glob.items()) or "the design placement"
            raise InputError(f"the assembly calibration's frame at {placed} could not be calibrated: {exc}") from None
        out = read_grid(grid, cfg, b)
        done += 1
        if progress is not None:
            progress(done, total)
        return out

    zero_raw, zero_sigma = read({})
    poly = np.zeros((6, COMPONENTS, 3))
    misfit = np.zeros(6)
    for j, name in enumerate(FIELDS):  # each error alone at its nodes: a cubic without constant
        t = np.asarray(DISTANCE_NODES_UM) if j == 0 else STEPS[name] * np.asarray(SINGLE_NODES)
        dev = np.stack([read({name: float(v)})[0] for v in t]) - zero_raw  # (nodes, COMPONENTS)
        design = np.stack([t, t ** 2, t ** 3], axis=1)
        poly[j] = np.linalg.lstsq(design, dev, rcond=None)[0].T
        resid = dev[:, j] - design @ poly[j, j]
        with np.errstate(invalid="ignore", divide="ignore"):  # an error the frame does not answer: NaN
            misfit[j] = np.sqrt(resid @ resid / max(t.size - 3, 1)) / abs(poly[j, j, 0])
    model = AssemblyModel(float(b), tuple(map(float, zero_raw)), tuple(map(float, zero_sigma)), _nested(poly),
                          (0.0,) * 6, float(max(DISTANCE_NODES_UM)), assembly_key(cfg),
                          _nested(np.zeros((2, 6, 6, COMPONENTS))), tuple(map(float, misfit)))
    cross = np.zeros((2, 6, 6, COMPONENTS))
    for j, k in pairs:  # what a pair does beyond its two errors alone, odd and even in the second one
        hj, hk = steps[FIELDS[j]], steps[FIELDS[k]]
        beyond = []
        for sign in (1.0, -1.0):
            true = np.zeros(6)
            true[[j, k]] = hj, sign * hk
            beyond.append(read({FIELDS[j]: hj, FIELDS[k]: sign * hk})[0] - model.raw(true))
        cross[0, j, k] = (beyond[0] - beyond[1]) / (2 * hj * hk)
        cross[1, j, k] = (beyond[0] + beyond[1]) / (2 * hj * hk * hk)
    model = dataclasses.replace(model, cross=_nested(cross))
    error = np.zeros(6)
    for check in VALIDATION:
        truth = np.array([check[k] for k in FIELDS])
        error = np.maximum(error, np.abs(model.solve(read(check)[0])[0] - truth))
    return dataclasses.replace(model, systematic=tuple(float(v) for v in error))
