"""The camera and its image formation: config, paraxial optics, error map, ray tracer, scenes, sensor,
renderer and the `simulate` entry point."""

from mlaqc.lazy import lazy_exports

_EXPORTS = {
    "CameraConfig": "config", "default_config": "config", "load_config": "config",
    "ErrorMap": "errormap", "load_error_map": "errormap", "random_defects": "errormap",
    "WhiteScene": "scene", "PointScene": "scene", "TextureScene": "scene",
    "Renderer": "render", "render": "render",
    "simulate": "simulate", "write_simulation": "simulate",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
