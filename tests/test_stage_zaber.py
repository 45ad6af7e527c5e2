"""The real Zaber ASCII driver against the Zaber simulator on a pty, fault by fault."""

import re
import threading
import time

import pytest

from drivers.sim import ZaberSim
from drivers.stage import AxisAddress, Limits, NotHomedError, StageAlarm, StageStopped, StageTimeout, ZaberStage
from drivers.stage import zaber_codec as zc
from drivers.stage.zaber import parse_axes
from mlaqc.errors import DeviceError, InputError

pytestmark = pytest.mark.timeout(20)

TOPOLOGIES = {"one device, two axes": ((1, 1), (1, 2)), "two devices": ((1, 1), (2, 1))}


@pytest.fixture(params=list(TOPOLOGIES))
def sim(request):
    simulator = ZaberSim(axes=TOPOLOGIES[request.param], speed_mm_s=1000.0, start_mm=20.0).start()
    yield simulator
    simulator.close()


def make_stage(sim: ZaberSim, **options) -> ZaberStage:
    """A driver wired like the simulator, with short deadlines."""
    axes = tuple(AxisAddress(d, a) for d, a in sim.order)
    settings = dict(axes=axes, microstep_um=sim.microstep_um, poll_s=0.005, stop_timeout_s=0.5, connect_timeout_s=1.0)
    settings.update(options)
    return ZaberStage(sim.path, **settings)


@pytest.fixture
def stage(sim):
    driver = make_stage(sim)
    driver.connect()
    yield driver
    driver.close()


@pytest.fixture
def homed(stage):
    stage.home(timeout_s=2.0)
    return stage


def run_in_thread(fn):
    """Start fn in a thread; return (thread, outcome dict with 'error' or 'result')."""
    outcome = {}

    def target():
        try:
            outcome["result"] = fn()
        except BaseException as exc:
            outcome["error"] = exc

    thread = threading.Thread(target=target)
    thread.start()
    return thread, outcome


def sent_commands(sim: ZaberSim, stage: ZaberStage, action) -> list[str]:
    """Command lines the simulator received because of `action` (a round trip afterwards flushes the wire)."""
    before = len(sim.received_lines)
    action()
    stage.position()
    return [line for line in sim.received_lines[before:] if "get pos" not in line]


# ------------------------------------------------------------------ normal operation


def test_parse_axes():
    assert parse_axes("1.1,1.2") == (AxisAddress(1, 1), AxisAddress(1, 2))
    assert parse_axes("1,2") == (AxisAddress(1, 1), AxisAddress(2, 1))
    for bad in ("1", "1.1,1.1", "a,b", "1.1,1.2,1.3", "0,1", "1.10,2"):
        with pytest.raises(InputError):
            parse_axes(bad)


def test_connect_home_move_and_read_back(sim, stage):
    assert stage.is_connected and not stage.homed  # the simulator starts without a reference (WR)
    stage.home(timeout_s=2.0)
    assert stage.homed and stage.position() == (0.0, 0.0)
    stage.move_to(12.5, 40.0, timeout_s=2.0)
    assert stage.position() == (12.5, 40.0) == stage.last_position
    assert sim.position_mm == pytest.approx((12.5, 40.0))
    stage.move_by(-2.5, 10.0, timeout_s=2.0)
    assert stage.position() == (10.0, 50.0)
    assert not stage.is_busy()
    assert any(re.fullmatch(r"/\d 1 \d\d move abs 125000", line) for line in sim.received_lines)


def test_microstep_scale_is_configurable():
    sim = ZaberSim(microstep_um=0.047625, speed_mm_s=1000.0).start()
    try:
        with make_stage(sim) as stage:
            stage.home(timeout_s=2.0)
            stage.move_to(1.0, 2.0, timeout_s=2.0)
            assert stage.to_steps(1.0) == 20997
            assert "move abs 20997" in " ".join(sim.received_lines)
            assert stage.position() == pytest.approx((1.0, 2.0), abs=0.0001)
    finally:
        sim.close()


def test_referenced_axes_count_as_homed_at_connect():
    sim = ZaberSim(referenced=True, speed_mm_s=1000.0).start()
    try:
        with make_stage(sim) as stage:
            assert stage.homed
            stage.move_to(5, 5, timeout_s=2.0)
    finally:
        sim.close()


def test_checksummed_commands():
    sim = ZaberSim(speed_mm_s=1000.0).start()
    try:
        with make_stage(sim, checksum=True) as stage:
            stage.home(timeout_s=2.0)
            stage.move_to(3, 4, timeout_s=2.0)
        assert all(re.search(r":[0-9A-F]{2}$", line) for line in sim.received_lines)
    finally:
        sim.close()


# ------------------------------------------------------------------ refusals


def test_move_before_homing_is_refused_without_sending(sim, stage):
    def refused():
        with pytest.raises(NotHomedError):
            stage.move_to(10, 10)

    assert sent_commands(sim, stage, refused) == []


def test_soft_limit_move_is_refused_without_sending(sim, homed):
    def refused():
        with pytest.raises(InputError, match="outside the soft limits"):
            homed.move_to(10, 250)

    assert sent_commands(sim, homed, refused) == []


def test_controller_side_limit_rejection():
    sim = ZaberSim(speed_mm_s=1000.0, travel_mm=50.0).start()
    try:
        with make_stage(sim, limits=Limits(0, 100, 0, 100)) as stage:
            stage.home(timeout_s=2.0)
            with pytest.raises(DeviceError, match=r"rejected 'move abs 800000' on device 1 axis 1 with BADDATA \(the data"):
                stage.move_to(80, 10, timeout_s=1.0)
            stage.move_to(40, 10, timeout_s=1.0)
    finally:
        sim.close()


# ------------------------------------------------------------------ faults


def test_no_reply_times_out_sends_stop_and_raises(sim, homed):
    sim.drop_replies()
    with pytest.raises(StageTimeout, match=r"did not finish moving to \(10.000, 10.000\) mm within 0.3 s.*stop was sent"):
        homed.move_to(10, 10, timeout_s=0.3)
    assert sim.wait_for(lambda: any(line.endswith(" 0 stop") for line in sim.received_lines))
    assert not homed.homed


def test_rejection_raises_with_the_reason(sim, homed):
    sim.fail_next("BADCOMMAND", match="move")
    with pytest.raises(DeviceError, match=r"rejected 'move abs 100000' .* BADCOMMAND \(the command or setting"):
        homed.move_to(10, 10, timeout_s=1.0)
    homed.move_to(10, 10, timeout_s=1.0)
    assert homed.position() == (10.0, 10.0)


def test_fault_flag_mid_move_raises_and_unhomes(sim, homed):
    sim.fault_mid_move("FS", at_fraction=0.5)
    with pytest.raises(StageAlarm, match=r"fault FS \(Stalled and Stopped.*no longer homed"):
        homed.move_to(100, 100, timeout_s=2.0)
    assert not homed.homed
    with pytest.raises(NotHomedError):
        homed.move_to(5, 5)
    homed.home(timeout_s=2.0)  # clears the warning, re-references
    homed.move_to(5, 5, timeout_s=2.0)
    assert homed.position() == (5.0, 5.0)


def test_garbage_is_tolerated(sim, stage):
    sim.garble_replies(6)
    sim.send_garbage()
    stage.home(timeout_s=2.0)
    stage.move_to(7, 8, timeout_s=2.0)
    assert stage.position() == (7.0, 8.0)
    assert stage.garbage_lines >= 6


def test_slow_replies(sim, homed):
    sim.set_latency(0.01)
    homed.move_to(5, 6, timeout_s=2.0)
    sim.set_latency(1.0)
    with pytest.raises(StageTimeout, match="reading its position within 0.2 s"):
        homed.position(timeout_s=0.2)


def test_disconnect_mid_move_names_the_device(sim, homed):
    sim.disconnect_mid_move(at_fraction=0.3)
    with pytest.raises(DeviceError, match=rf"Zaber stage {re.escape(sim.path)} lost its connection while moving to \(150.000, 150.000\) mm"):
        homed.move_to(150, 150, timeout_s=2.0)
    assert not homed.is_connected and not homed.homed


def test_silent_chain_fails_to_connect(sim):
    sim.drop_replies()
    driver = make_stage(sim, connect_timeout_s=0.2)
    with pytest.raises(StageTimeout, match=r"did not answer while connecting \(reply from device 1 axis 0"):
        driver.connect()
    driver.close()


# ------------------------------------------------------------------ stop and threads


def test_stop_from_another_thread_halts_a_long_move(sim, homed):
    slow_speed = 100.0 * 1000.0 / sim.microstep_um
    for axes in sim.devices.values():
        for axis in axes:
            axis.speed_steps_s = slow_speed
    thread, outcome = run_in_thread(lambda: homed.move_to(190, 190, timeout_s=5.0))
    assert sim.wait_busy()
    homed.stop()
    thread.join(3.0)
    assert not thread.is_alive()
    assert isinstance(outcome.get("error"), StageStopped)
    assert not sim.busy
    assert sim.position_mm[0] < 190
    assert homed.homed
    assert homed.position() == pytest.approx(sim.position_mm, abs=0.0001)


def test_stop_never_interleaves_with_commands(sim, homed):
    errors = []

    def reader():
        for _ in range(25):
            try:
                homed.position(timeout_s=2.0)
            except Exception as exc:
                errors.append(exc)

    def stopper():
        for _ in range(25):
            homed.stop()

    threads = [threading.Thread(target=f) for f in (reader, reader, stopper)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert errors == []
    homed.position()
    for line in sim.received_lines:
        command = zc.parse_command(line)  # every line on the wire is one whole command
        assert command.text in ("", "get pos", "stop", "warnings", "warnings clear", "home"), line


def test_close_stops_a_move_in_flight(sim, homed):
    for axes in sim.devices.values():
        for axis in axes:
            axis.speed_steps_s = 50.0 * 1000.0 / sim.microstep_um
    thread, outcome = run_in_thread(lambda: homed.move_to(190, 190, timeout_s=5.0))
    assert sim.wait_busy()
    start = time.monotonic()
    homed.close()
    thread.join(3.0)
    assert time.monotonic() - start < 2.0
    assert isinstance(outcome.get("error"), DeviceError)
    assert sim.wait_for(lambda: not sim._any_busy())
