"""Camera registry and URL handling: scheme dispatch, lazy scheme modules, v4l2 URL parameters, Frame checks."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import drivers.camera as cameras
from drivers.camera import (
    CAMERA_SCHEMES,
    SCHEME_MODULES,
    Camera,
    Frame,
    camera_from_url,
    camera_schemes,
    open_camera,
    register_camera_scheme,
)
from drivers.camera.base import SequenceTracker
from drivers.camera.fake_v4l2 import FakeV4L2Bus, FakeV4L2Device
from drivers.camera.v4l2 import V4L2Camera
from drivers.camera.v4l2_params import URL_PARAMS
from mlaqc.errors import InputError

pytestmark = pytest.mark.timeout(10)


class DummyCamera(Camera):
    """The smallest concrete Camera: serves frames counting up; records the URL and options it was made with."""

    def __init__(self, url, **options):
        super().__init__(str(url))
        self.parsed, self.options, self._open, self.count = url, options, False, 0

    is_open = property(lambda self: self._open)
    bit_depth = property(lambda self: 12)

    def open(self):
        self._open = True
        return self

    def close(self):
        self._open = False

    def settings(self):
        return {"url": self.url}

    def set_exposure_us(self, exposure_us):
        return exposure_us

    def set_gain(self, gain):
        return gain

    def set_format(self, pixel_format):
        return pixel_format

    def capture(self, timeout_s=1.0):
        self.count += 1
        return Frame(np.zeros((2, 3), np.uint16), 12, "Y12", None, self.count, 0.0, 0.0, 100.0, 1.0, self.url)


@pytest.fixture
def scheme(monkeypatch):
    """Register 'testcam' for one test only."""
    monkeypatch.setattr(cameras, "CAMERA_SCHEMES", dict(CAMERA_SCHEMES))
    register_camera_scheme("testcam", DummyCamera)
    return "testcam"


def test_custom_scheme_dispatch_variant_fallback_and_options(scheme):
    cam = open_camera("testcam://?speed=3", flavour="x")
    assert isinstance(cam, DummyCamera) and cam.is_open and cam.options == {"flavour": "x"}
    assert cam.parsed.param("speed") == "3"
    variant = camera_from_url("TestCam+bayer://")
    assert isinstance(variant, DummyCamera) and not variant.is_open and variant.parsed.variant == "bayer"
    assert "testcam" in camera_schemes() and "v4l2" in camera_schemes()


def test_registration_conflicts(scheme):
    register_camera_scheme("testcam", DummyCamera)  # same factory again: harmless (module reload)
    with pytest.raises(ValueError, match="already registered"):
        register_camera_scheme("testcam", lambda url: None)
    register_camera_scheme("testcam", V4L2Camera.from_url, replace=True)
    assert cameras.CAMERA_SCHEMES["testcam"] == V4L2Camera.from_url
    with pytest.raises(ValueError, match="bare name"):
        register_camera_scheme("x://", DummyCamera)


def test_unknown_scheme_and_missing_scheme_rejected():
    with pytest.raises(InputError, match=r"unknown camera scheme 'gige' in 'gige://cam1'; known: .*v4l2"):
        open_camera("gige://cam1")
    with pytest.raises(InputError, match="has no scheme"):
        open_camera("/dev/video0")


def test_scheme_module_imported_on_first_use(tmp_path, monkeypatch):
    (tmp_path / "lazy_cam_module.py").write_text(
        "from drivers.camera import register_camera_scheme\n"
        "from test_camera_registry import DummyCamera\n"
        "register_camera_scheme('lazycam', DummyCamera)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(cameras, "CAMERA_SCHEMES", dict(CAMERA_SCHEMES))
    monkeypatch.setitem(SCHEME_MODULES, "lazycam", "lazy_cam_module")
    monkeypatch.setitem(SCHEME_MODULES, "notyet", "drivers.camera.not_written_yet")
    monkeypatch.delitem(sys.modules, "lazy_cam_module", raising=False)
    monkeypatch.setitem(sys.modules, "test_camera_registry", sys.modules[__name__])
    assert isinstance(open_camera("lazycam://"), DummyCamera)
    with pytest.raises(InputError, match="unknown camera scheme 'notyet'"):
        open_camera("notyet://")


def test_v4l2_url_parameters_parsed_and_applied(tmp_path):
    dev = FakeV4L2Device(tmp_path / "video0", formats=("Y16", "Y10"), width=16, height=8)
    url = (f"v4l2://{dev.node}?format=Y10&width=16&height=8&exposure_us=5000&gain=7&roi=0,0,8,4"
           f"&buffers=6&settle_frames=2")
    cam = camera_from_url(url, adapter_factory=FakeV4L2Bus(dev), by_id_dir=tmp_path)
    assert isinstance(cam, V4L2Camera) and not cam.is_open and cam.url == url
    with cam:
        s = cam.settings()
        assert (s["pixel_format"], s["exposure_us"], s["gain"], s["roi"]) == ("Y10", 5000.0, 7.0, (0, 0, 8, 4))
        assert (s["width"], s["height"], s["settle_frames"]) == (8, 4, 2)
        dev.plant(bytes(8 * 4 * 2), sequence=0)
        cam.capture(timeout_s=2)
        assert cam.settings()["buffers"] == 4  # asked for 6, the driver granted 4: read back
    kernel_name = camera_from_url(f"v4l2://{dev.node}?format=srggb10p")
    assert kernel_name._desired.pixel_format.name == "pRAA"


@pytest.mark.parametrize("query, message", [
    ("fps=30", r"unknown parameter 'fps' in camera URL .*; known: format, width"),
    ("format=MJPG", r"unknown or unsupported raw pixel format 'MJPG'"),
    ("width=abc", r"parameter width='abc' in camera URL .* is not an integer"),
    ("height=0", r"parameter height=0 in camera URL .* must be at least 1"),
    ("exposure_us=-5", r"parameter exposure_us='-5' .* must be a positive number"),
    ("exposure_us=nan", r"parameter exposure_us='nan' .* must be a positive number"),
    ("gain=inf", r"parameter gain='inf' .* must be a finite number"),
    ("gain=high", r"parameter gain='high' .* is not a number"),
    ("roi=1,2,3", r"parameter roi in camera URL .* must be four integers"),
    ("roi=0,0,a,4", r"parameter roi='0,0,a,4' .* must be x,y,width,height"),
    ("roi=-1,0,4,4", r"must be four integers x, y >= 0"),
    ("buffers=1", r"parameter buffers=1 .* must be between 2 and 32"),
    ("settle_frames=-1", r"parameter settle_frames=-1 .* must be between 0 and 100"),
    ("exposure_unit_us=0", r"parameter exposure_unit_us='0' .* must be a positive number"),
    ("a=1&&b", r"malformed query string"),
])
def test_v4l2_bad_url_parameters_rejected(query, message):
    with pytest.raises(InputError, match=message):
        camera_from_url(f"v4l2:///dev/video0?{query}")


def test_v4l2_url_needs_an_absolute_path():
    with pytest.raises(InputError, match="needs an absolute device path"):
        camera_from_url("v4l2://video0")
    assert set(URL_PARAMS) >= {"format", "width", "height", "exposure_us", "gain"}


def test_frame_validation_and_properties():
    frame = Frame(np.zeros((2, 3), np.uint16), 10, "RG10", "RGGB", 1, 0.5, 1.5, 100.0, 2.0, "mock://")
    assert (frame.height, frame.width, frame.max_value, frame.extra) == (2, 3, 1023, {})
    with pytest.raises(ValueError, match="2-D uint16"):
        Frame(np.zeros((2, 3), np.uint8), 8, "GREY", None, 0, 0, 0, 0, 0, "x")
    with pytest.raises(ValueError, match="2-D uint16"):
        Frame(np.zeros(3, np.uint16), 8, "GREY", None, 0, 0, 0, 0, 0, "x")
    with pytest.raises(ValueError, match="bits must be 1..16"):
        Frame(np.zeros((1, 1), np.uint16), 17, "Y16", None, 0, 0, 0, 0, 0, "x")
    with pytest.raises(ValueError, match="cfa"):
        Frame(np.zeros((1, 1), np.uint16), 8, "RGGB", "RGBG", 0, 0, 0, 0, 0, "x")


def test_base_camera_defaults(scheme):
    cam = open_camera("testcam://")
    assert [f.sequence for f, _ in zip(cam.stream(1.0), range(3))] == [1, 2, 3]
    with pytest.raises(InputError, match="does not support a region of interest"):
        cam.set_roi(0, 0, 1, 1)
    with pytest.raises(InputError, match="timeout_s"):
        next(cam.stream(-1))
    assert cam.reopen().is_open and "open" in repr(cam)
    with cam:
        pass
    assert not cam.is_open


def test_sequence_tracker_wraps_and_detects_backwards():
    t = SequenceTracker()
    assert [t.update(s) for s in (2**32 - 2, 2**32 - 1, 0, 3)] == [0, 0, 0, 2]
    assert t.update(1) is None and t.update(2) == 0
    assert (t.lost_total, t.gap_events) == (2, 1)
