"""Simulated raw frames with their ground truth: render -> sensor model -> raw file + `<name>.sim.json`.

The sidecar holds everything needed to reproduce or judge the frame: config, derived layout, scene,
the ground-truth error map, seed, ray counts, engine and versions, and the raw file's checksum. A
through-focus frame (mlaqc.optics.throughfocus) also has ``protocol``: its `ThroughFocus` record
(`ThroughFocus.from_dict` reads it back) plus the frame's derived facts under ``frame``; its ``config``
is the camera as given (before stopping down and moving the target), its ``layout`` the frame's own.
"""

from __future__ import annotations

import hashlib
import json
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mlaqc import __version__
from mlaqc.optics.datasheet import telecentric
from mlaqc.atomic import atomic_path
from mlaqc.errors import InputError
from mlaqc.inspection.raw_write import write_raw
from mlaqc.optics.config import CameraConfig
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.formation import apply_formation
from mlaqc.optics.render import Progress, Renderer, RenderResult
from mlaqc.optics.scene import PointScene, Scene, TextureScene, WhiteScene
from mlaqc.optics.sensor import expose, white_level
from mlaqc.optics.throughfocus import ThroughFocus, blur_radius_mm, frame_config, magnification, pinhole_lenses, stage_z_mm

RAW_SUFFIXES = (".tif", ".tiff", ".dng", ".npy", ".png")
SIDECAR_FORMAT = "mlaqc-simulation"


@dataclass(frozen=True)
class SimulatedRaw:
    """A rendered frame: raw counts as the sensor reads them, the expected photons, and the render facts."""

    raw: np.ndarray  # (H, W) uint16
    render: RenderResult
    errors: ErrorMap
    scene: Scene
    noise: bool
    engine: str
    sampler: str = "random"


def simulate(cfg: CameraConfig, scene: Scene | None = None, errors: ErrorMap | None = None, *,
             rays: int | None = None, rays_per_pixel: float | None = None, seed: int = 0, noise: bool = True,
             threads: int | None = None, progress: Progress | None = None, renderer: Renderer | None = None,
             client=None) -> SimulatedRaw:
    """Render `scene` through the camera with `errors` and read it out with the sensor model; with a Dask
    `client` the rays are traced on its workers (the same image, bit for bit)."""
    scene = scene if scene is not None else WhiteScene()
    errors = errors if errors is not None else ErrorMap.zeros(cfg.mla.count_h, cfg.mla.count_w, cfg.mla.packing)
    renderer = renderer or Renderer(cfg, errors)
    if client is not None:
        from mlaqc.optics.distributed import render_on_cluster

        result = render_on_cluster(client, renderer, scene, rays=rays, rays_per_pixel=rays_per_pixel, seed=seed,
                                   progress=progress)
    else:
        result = renderer.render(scene, rays=rays, rays_per_pixel=rays_per_pixel, seed=seed, threads=threads,
                                 progress=progress)
    raw = expose(apply_formation(result.photons, cfg), cfg.sensor, seed=seed + 1, noise=noise)
    return SimulatedRaw(raw, result, errors, scene, noise, renderer.engine, renderer.sampler)


def scene_record(scene: Scene) -> dict[str, Any]:
    """JSON description of a scene (textures by shape, not pixels)."""
    if isinstance(scene, PointScene):
        return {"kind": "points", "points_mm": [list(p) for p in scene.points_mm], "photons": scene.photons}
    if isinstance(scene, TextureScene):
        return {"kind": "texture", "shape": list(scene.radiance.shape)}
    return {"kind": "white"}


def sidecar_path(raw_path: str | Path) -> Path:
    """Where the simulation record of a raw file lives: `<name>.sim.json`."""
    p = Path(raw_path)
    return p.with_name(p.name + ".sim.json")


def check_output(out: str | Path) -> Path:
    """Refuse an output path with an unknown suffix or a missing folder (before any long render)."""
    out = Path(out)
    if out.suffix.lower() not in RAW_SUFFIXES:
        raise InputError(f"output {str(out)!r} must end in one of {', '.join(RAW_SUFFIXES)}")
    if not out.parent.is_dir():
        raise InputError(f"output folder {str(out.parent)!r} does not exist")
    return out


def write_simulation(out: str | Path, sim: SimulatedRaw, cfg: CameraConfig, *,
                     protocol: ThroughFocus | None = None) -> Path:
    """Write the raw file and its `.sim.json` record; neither appears unless both were written.
    `protocol`: the through-focus frame `sim` was rendered as (with `frame_config(cfg, protocol)`)."""
    out = check_output(out)
    s = cfg.sensor
    cfa = None if s.cfa == "none" else s.cfa
    record = _record(sim, cfg, out)
    if protocol is not None:
        record["layout"] = _layout(frame_config(cfg, protocol))
        record["protocol"] = protocol_record(cfg, protocol)
    with atomic_path(sidecar_path(out)) as tmp_json:
        write_raw(out, sim.raw, bits=s.bit_depth, cfa=cfa, black_level=s.black_level_dn, white_level=white_level(s),
                  metadata={"mlaqc_simulation": {"seed": sim.render.seed, "rays": sim.render.rays_traced,
                                                 "version": __version__}})
        record["raw"]["sha256"] = hashlib.sha256(out.read_bytes()).hexdigest()
        tmp_json.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    return sidecar_path(out)


def protocol_record(cfg: CameraConfig, tf: ThroughFocus) -> dict[str, Any]:
    """`tf.to_dict()` plus the frame's derived facts (for sidecars and scan records)."""
    fc = frame_config(cfg, tf)
    return tf.to_dict() | {"frame": {
        "main_lens_diameter_mm": fc.main_lens.diameter_mm,
        "object_distance_mm": fc.layout.object_distance_mm,
        "stage_z_mm": stage_z_mm(cfg, tf),
        "magnification": magnification(fc),
        "blur_radius_mm": blur_radius_mm(cfg, tf),
        "pinholes": int(len(pinhole_lenses(cfg, tf))),
    }}


def _layout(cfg: CameraConfig) -> dict[str, Any]:
    lay = cfg.layout
    if lay.main is None:  # an ideal main lens: where its exit pupil is, and its f-number
        far = telecentric(cfg.main_lens.exit_pupil_mm)  # null: at infinity
        main = {"exit_pupil_to_mla_mm": None if far else lay.pupil_to_mla_mm, "image_f_number": lay.image_f_number}
    else:
        main = {"object_distance_mm": lay.object_distance_mm, "mla_distance_mm": lay.mla_distance_mm,
                "main_efl_mm": lay.main.efl}
    return main | {
        "sensor_gap_mm": lay.sensor_gap_mm,
        "microlens_efl_um": lay.micro.efl * 1e3,
        "subimage_pitch_px": lay.subimage_pitch_px,
    }


def _record(sim: SimulatedRaw, cfg: CameraConfig, out: Path) -> dict[str, Any]:
    s = cfg.sensor
    return {
        "format": SIDECAR_FORMAT,
        "version": 1,
        "mlaqc_version": __version__,
        "numpy_version": np.__version__,
        "python": platform.python_version(),
        "config": cfg.to_dict(),
        "layout": _layout(cfg),
        "scene": scene_record(sim.scene),
        "error_map": sim.errors.to_json_dict(),
        "seed": sim.render.seed,
        "rays_traced": sim.render.rays_traced,
        "rays_landed": sim.render.rays_landed,
        "rays_per_pixel": sim.render.rays_traced / (s.width_px * s.height_px),
        "engine": sim.engine,
        "sampler": sim.sampler,
        "noise": sim.noise,
        "render_seconds": round(sim.render.seconds, 3),
        "raw": {"file": out.name, "bits": s.bit_depth, "cfa": s.cfa, "black_level": s.black_level_dn,
                "white_level": white_level(s)},
    }


def load_simulation_record(raw_path: str | Path) -> dict[str, Any]:
    """Read the `.sim.json` record beside a simulated raw file (InputError if absent or not one)."""
    p = sidecar_path(raw_path)
    try:
        rec = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"no simulation record {str(p)!r} beside {str(raw_path)!r}") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"simulation record {str(p)!r} is not readable JSON ({exc.__class__.__name__})") from None
    if not isinstance(rec, dict) or rec.get("format") != SIDECAR_FORMAT:
        raise InputError(f"{str(p)!r} is not an mlaqc simulation record")
    return rec
