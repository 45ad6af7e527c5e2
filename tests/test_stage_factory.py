"""open_stage(url): schemes, parameters, errors, simulator ownership and clean shutdown."""

import os
import threading

import pytest

from drivers.sim import GrblSim, ZaberSim
from drivers.stage import GrblStage, Limits, Stage, ZaberStage, open_stage
from mlaqc.errors import DeviceError, InputError

pytestmark = pytest.mark.timeout(20)


def open_fds() -> set[str]:
    """This process's open descriptors."""
    return set(os.listdir("/proc/self/fd"))


def test_mock_runs_the_real_grbl_driver_fast():
    with open_stage("mock://") as stage:
        assert isinstance(stage, GrblStage) and isinstance(stage.sim, GrblSim)
        stage.home(timeout_s=2.0)
        stage.move_to(150, 150, timeout_s=2.0)
        assert stage.position() == (150.0, 150.0)
        assert any(line.startswith("G90 G53 G0") for line in stage.sim.received_lines)


def test_sim_grbl_parameters_reach_the_simulator_and_driver():
    with open_stage("sim+grbl://?speed_mm_s=500&latency_ms=2&x_max_mm=50&y_max_mm=60&poll_s=0.005") as stage:
        assert stage.sim.speed_mm_s == 500 and stage.sim.latency_s == pytest.approx(0.002)
        assert stage.sim.travel_mm == (50.0, 60.0)
        assert stage.limits == Limits(0, 50, 0, 60)
        stage.home(timeout_s=2.0)
        stage.move_to(50, 60, timeout_s=2.0)
        with pytest.raises(InputError):
            stage.move_to(51, 0)


def test_sim_zaber_parameters():
    with open_stage("sim+zaber://?axes=1,2&microstep_um=0.5&speed_mm_s=1000&poll_s=0.005") as stage:
        assert isinstance(stage, ZaberStage) and isinstance(stage.sim, ZaberSim)
        assert sorted(stage.sim.devices) == [1, 2] and stage.microstep_um == 0.5
        stage.home(timeout_s=2.0)
        stage.move_to(3, 4, timeout_s=2.0)
        assert stage.position() == (3.0, 4.0)


def test_serial_url_opens_a_real_port_path():
    sim = GrblSim(speed_mm_s=1000.0).start()
    try:
        with open_stage(f"serial://{sim.path}?protocol=grbl&baud=115200&poll_s=0.005") as stage:
            assert isinstance(stage, GrblStage) and stage.sim is None
            assert stage.name == f"GRBL stage serial://{sim.path}?protocol=grbl&baud=115200&poll_s=0.005"
            stage.home(timeout_s=2.0)
            stage.move_to(1, 1, timeout_s=2.0)
    finally:
        sim.close()


def test_serial_zaber_url():
    sim = ZaberSim(axes=((1, 1), (2, 1)), speed_mm_s=1000.0, referenced=True).start()
    try:
        with open_stage(f"serial://{sim.path}?protocol=zaber&axes=1,2&poll_s=0.005") as stage:
            assert stage.homed
            stage.move_to(2, 3, timeout_s=2.0)
    finally:
        sim.close()


@pytest.mark.parametrize("url,message", [
    ("ftp://x", "unknown scheme 'ftp'"),
    ("serial:///dev/ttyUSB0", "needs protocol=grbl or protocol=zaber"),
    ("serial:///dev/ttyUSB0?protocol=marlin", "not 'marlin'"),
    ("serial://?protocol=grbl", "names no serial port"),
    ("sim+grbl://?speed=5", "unknown parameter 'speed'"),
    ("mock://?colour=red", "unknown parameter 'colour'"),
    ("sim+grbl://?speed_mm_s=fast", "speed_mm_s='fast' is not a number"),
    ("sim+grbl://?speed_mm_s=-1", "speed_mm_s='-1' is out of range"),
    ("sim+grbl://?latency_ms=nan", "latency_ms='nan' is out of range"),
    ("sim+grbl://?x_min_mm=10&x_max_mm=5", "are empty"),
    ("sim+zaber://?axes=1", "must name two axes"),
    ("sim+zaber://?checksum=yes", "must be 0 or 1"),
    ("sim+zaber://?feed_mm_min=100", "unknown parameter 'feed_mm_min'"),
    ("serial:///dev/ttyUSB0?protocol=grbl&axes=1,2", "unknown parameter 'axes'"),
    ("no-scheme", "has no scheme"),
])
def test_bad_urls_are_input_errors_naming_the_problem(url, message):
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace("?", r"\?")):
        open_stage(url)


def test_missing_serial_port_is_a_device_error():
    with pytest.raises(DeviceError, match="could not open serial port /dev/does-not-exist"):
        open_stage("serial:///dev/does-not-exist?protocol=grbl")


def test_stage_is_abstract():
    with pytest.raises(TypeError):
        Stage(url="x", limits=Limits())


@pytest.mark.parametrize("url", ["mock://", "sim+zaber://?speed_mm_s=1000&poll_s=0.005"])
def test_close_leaves_no_threads_or_descriptors(url):
    threads_before, fds_before = set(threading.enumerate()), open_fds()
    for _ in range(3):
        stage = open_stage(url)
        stage.home(timeout_s=2.0)
        stage.move_to(1, 1, timeout_s=2.0)
        stage.close()
        stage.close()  # idempotent
    assert set(threading.enumerate()) == threads_before
    assert open_fds() == fds_before


def test_failed_connect_closes_the_simulator():
    threads_before, fds_before = set(threading.enumerate()), open_fds()
    with pytest.raises(DeviceError):
        open_stage("sim+grbl://?connect_timeout_s=0.2&latency_ms=500")
    assert set(threading.enumerate()) == threads_before
    assert open_fds() == fds_before


def test_simulator_disconnect_then_close_is_clean():
    threads_before, fds_before = set(threading.enumerate()), open_fds()
    stage = open_stage("mock://")
    stage.home(timeout_s=2.0)
    stage.sim.disconnect()
    with pytest.raises(DeviceError, match="lost its connection while reading its position"):
        stage.position(timeout_s=2.0)
    stage.close()
    assert set(threading.enumerate()) == threads_before
    assert open_fds() == fds_before
