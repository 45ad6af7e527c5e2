"""Cameras by URL: a registry of scheme factories and `open_camera(url)`.

A factory takes the parsed `DeviceURL` (plus keyword options, e.g. a fake adapter in tests) and returns an
unopened `Camera`, raising InputError for bad parameters. Modules register their scheme at import time with
`register_camera_scheme('mock', factory)`; schemes listed in `SCHEME_MODULES` are imported on first use,
so `open_camera('mock://')` works without importing the mock module first. A scheme like 'mock+bayer'
falls back to the 'mock' factory, which reads `url.variant`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from drivers.camera.base import Camera, Frame
from drivers.url import DeviceURL, parse_device_url
from mlaqc.errors import InputError

CameraFactory = Callable[..., Camera]

CAMERA_SCHEMES: dict[str, CameraFactory] = {}
SCHEME_MODULES: dict[str, str] = {"v4l2": "drivers.camera.v4l2", "mock": "drivers.camera.mock"}

__all__ = ["CAMERA_SCHEMES", "Camera", "CameraFactory", "Frame", "SCHEME_MODULES", "camera_from_url",
           "camera_schemes", "open_camera", "register_camera_scheme"]


def register_camera_scheme(scheme: str, factory: CameraFactory, *, replace: bool = False) -> None:
    """Make `factory(url: DeviceURL, **options) -> Camera` handle URLs with this scheme."""
    key = scheme.lower()
    if not key or "://" in key:
        raise ValueError(f"camera scheme must be a bare name like 'mock', got {scheme!r}")
    if not callable(factory):
        raise TypeError(f"camera factory for {scheme!r} is not callable")
    existing = CAMERA_SCHEMES.get(key)
    if existing is not None and existing != factory and not replace:
        raise ValueError(f"camera scheme {key!r} is already registered; pass replace=True to override")
    CAMERA_SCHEMES[key] = factory


def camera_schemes() -> list[str]:
    """Every scheme that is registered or can be loaded on demand."""
    return sorted(set(CAMERA_SCHEMES) | set(SCHEME_MODULES))


def _factory_for(url: DeviceURL, text: str) -> CameraFactory:
    """The factory for the URL's scheme (or its kind), importing its module on first use."""
    for key in dict.fromkeys((url.scheme, url.kind)):
        if key not in CAMERA_SCHEMES and key in SCHEME_MODULES:
            _load_scheme_module(SCHEME_MODULES[key])
        if key in CAMERA_SCHEMES:
            return CAMERA_SCHEMES[key]
    raise InputError(f"unknown camera scheme {url.scheme!r} in {text!r}; known: {', '.join(camera_schemes())}")


def _load_scheme_module(module: str) -> None:
    """Import a module that registers a scheme; a module not written yet just leaves the scheme unknown."""
    try:
        importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name != module:
            raise


def camera_from_url(url: str | DeviceURL, **options: Any) -> Camera:
    """Build an unopened camera from a device URL; InputError for an unknown scheme or parameter."""
    parsed = parse_device_url(url) if isinstance(url, str) else url
    return _factory_for(parsed, str(url))(parsed, **options)


def open_camera(url: str | DeviceURL, **options: Any) -> Camera:
    """Build and open a camera from a device URL, e.g. 'v4l2:///dev/video0?format=Y16&exposure_us=5000'."""
    return camera_from_url(url, **options).open()
