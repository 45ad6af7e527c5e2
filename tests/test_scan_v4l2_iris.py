"""A through-focus scan with `iris = "camera"` on a V4L2 camera: the runner stops the lens down through the
camera's iris control and opens it again, against the fake ioctl layer (drivers.camera.fake_v4l2) and the
GRBL stage simulator with the pinhole carrier's axes."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.camera.fake_v4l2 import FakeV4L2Bus, FakeV4L2Device, default_controls, uvc_iris_control
from drivers.camera.v4l2 import V4L2Camera
from drivers.camera.v4l2_adapter import CID_IRIS_ABSOLUTE
from drivers.capture import load_sidecar
from drivers.scan import run_scan
from drivers.scan_manifest import MANIFEST_NAME, read_manifest
from drivers.scan_plan import plan_from_dict
from mlaqc.errors import InputError

pytestmark = pytest.mark.timeout(60)

PLAN = {
    "scan": {"settle_s": 0.0, "retry_delay_s": 0.0, "capture_timeout_s": 1.0, "retries": 0},
    "positions": [{"x_mm": 10.0, "y_mm": 10.0, "label": "a"}],
    "through_focus": {"focus_offsets_mm": [10.0, -10.0], "f_number": 8.0, "spacing_lenses": 9, "offsets": [[0, 0]],
                      "settle_s": 0.0, "iris": "camera", "white_frames": True},
}
STAGE = "mock://?aux=z,a,b"


def v4l2_camera(tmp_path, controls) -> tuple[FakeV4L2Device, V4L2Camera]:
    """A fake V4L2 camera with frames enough for a few positions."""
    dev = FakeV4L2Device(tmp_path / "video0", controls=controls, width=8, height=6)
    for seq in range(40):
        dev.plant_image(np.full((6, 8), 1000 + seq, np.uint16), sequence=seq)
    cam = V4L2Camera.from_url(f"v4l2://{dev.node}?settle_frames=0", adapter_factory=FakeV4L2Bus(dev),
                              by_id_dir=tmp_path)
    return dev, cam


def test_through_focus_scan_sets_the_iris_through_a_uvc_camera(tmp_path):
    dev, cam = v4l2_camera(tmp_path, default_controls() | uvc_iris_control())
    out = tmp_path / "scan"
    result = run_scan(cam, STAGE, plan_from_dict(PLAN, "p.toml"), out)
    assert result.done == 1
    files = read_manifest(out / MANIFEST_NAME).records[0]["files"]
    white, *pinholes = (load_sidecar(out / f["file"]) for f in files)
    assert len(pinholes) == 2
    # the white frame at the Table 1 camera's full aperture (the plan names no config), the pinholes at f/8
    assert white["device_extra"]["f_number"] == pytest.approx(2.5)
    for side in pinholes:
        assert side["context"]["through_focus"]["f_number_read_back"] == 8.0
        assert side["device_extra"]["f_number"] == 8.0
    writes = [c[2] for c in dev.calls if c[:2] == ("s_ctrl", CID_IRIS_ABSOLUTE)]
    assert writes[0] == 250 and 800 in writes and dev.values[CID_IRIS_ABSOLUTE] == 250  # opened again at the end


def test_through_focus_scan_on_a_camera_without_an_iris_is_refused_before_it_starts(tmp_path):
    """Refused up front (before the stage moves or a manifest is written), in one sentence."""
    _, cam = v4l2_camera(tmp_path, default_controls())
    with pytest.raises(InputError, match=r"cannot set its iris.*iris = 'manual'"):
        run_scan(cam, STAGE, plan_from_dict(PLAN, "p.toml"), tmp_path / "scan")
    assert not (tmp_path / "scan" / "manifest.jsonl").exists()
