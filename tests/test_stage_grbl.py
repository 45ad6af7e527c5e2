"""The real GRBL driver against the GRBL simulator on a pty, fault by fault.

No fixed sleeps: tests wait on simulator state (wait_state / wait_for / waiting.wait_until) and on the driver's
own deadlines. State the simulator records on its own thread after the driver has already reacted (the pty hung
up, then `hung_up`) is waited for, never read at once.
"""

import re
import threading
import time

import pytest

from drivers.sim import GrblSim
from drivers.stage import GrblStage, Limits, NotHomedError, StageAlarm, StageStopped, StageTimeout
from mlaqc.errors import DeviceError, InputError
from waiting import wait_until

pytestmark = pytest.mark.timeout(20)

VALID_LINE = re.compile(r"^(\$H|\$X|G90 G53 G[01] X-?\d+\.\d{3} Y-?\d+\.\d{3}( F\d+(\.\d+)?)?)$")


@pytest.fixture
def sim():
    simulator = GrblSim(speed_mm_s=1000.0, start_mm=(20.0, 20.0), decel_s=0.002).start()
    yield simulator
    simulator.close()


def make_stage(sim: GrblSim, **options) -> GrblStage:
    """A driver with short deadlines and fast polling, for tests."""
    settings = dict(poll_s=0.005, stop_timeout_s=0.5, connect_timeout_s=1.0)
    settings.update(options)
    return GrblStage(sim.path, **settings)


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


def received(sim: GrblSim, byte: bytes) -> bool:
    """Wait until the simulator has read the real-time `byte` (it reads on its own thread)."""
    return sim.wait_for(lambda: byte in sim.realtime_log)


def run_in_thread(fn):
    """Start fn in a thread; return (thread, outcome dict with 'error' or 'result')."""
    outcome = {}

    def target():
        try:
            outcome["result"] = fn()
        except BaseException as exc:  # handed back to the test
            outcome["error"] = exc

    thread = threading.Thread(target=target)
    thread.start()
    return thread, outcome


# ------------------------------------------------------------------ normal operation


def test_connect_waits_for_banner_and_starts_unhomed(sim, stage):
    assert stage.is_connected and not stage.homed
    assert b"\x18" in sim.realtime_log  # soft reset on connect, answered by the banner
    assert stage.last_status is not None and stage.last_status.state == "Alarm"  # GRBL homing lock


def test_home_then_moves_reach_the_target(sim, homed):
    assert homed.homed and sim.homed
    assert homed.position() == (0.0, 0.0)
    homed.move_to(12.5, 40.0, timeout_s=2.0)
    assert homed.position() == (12.5, 40.0)
    assert sim.position_mm == pytest.approx((12.5, 40.0))
    homed.move_by(-2.5, 10.0, timeout_s=2.0)
    assert homed.position() == (10.0, 50.0) == homed.last_position
    assert not homed.is_busy()
    assert homed.garbage_lines == 0


def test_moves_use_feed_rate_when_configured(sim):
    with make_stage(sim, feed_mm_min=30000) as stage:
        stage.home(timeout_s=2.0)
        stage.move_to(5, 5, timeout_s=2.0)
    assert "G90 G53 G1 X5.000 Y5.000 F30000" in sim.received_lines


def test_move_reports_busy_while_running(sim):
    slow = GrblSim(speed_mm_s=100.0, start_mm=(0, 0)).start()
    try:
        with make_stage(slow) as stage:
            stage.home(timeout_s=2.0)
            thread, outcome = run_in_thread(lambda: stage.move_to(50, 0, timeout_s=3.0))
            assert slow.wait_state("Run")
            assert stage.is_busy()  # the move holds the command lock
            seen = []
            assert slow.wait_for(lambda: seen.append(slow._state_text()) or len(seen) > 3, 2.0)
            thread.join(5)
            assert "error" not in outcome
            assert stage.position() == (50.0, 0.0)
    finally:
        slow.close()


def test_work_position_reports_are_converted_with_wco():
    wpos = GrblSim(speed_mm_s=1000.0, report_wpos=True, wco_mm=(5.0, -3.0, 0.0)).start()
    try:
        with make_stage(wpos) as stage:
            stage.home(timeout_s=2.0)
            stage.move_to(20, 30, timeout_s=2.0)
            assert stage.position() == pytest.approx((20.0, 30.0))
    finally:
        wpos.close()


# ------------------------------------------------------------------ refusals (nothing sent)


def sent_during(sim: GrblSim, stage: GrblStage, action) -> bytes:
    """Bytes the simulator received because of `action` (a '?' round trip afterwards flushes the wire)."""
    before = len(sim.received_bytes)
    action()
    stage.position()
    return bytes(sim.received_bytes[before:-1])


def test_move_before_homing_is_refused_without_sending(sim, stage):
    def refused():
        with pytest.raises(NotHomedError, match="not homed; call home"):
            stage.move_to(10, 10)
        with pytest.raises(NotHomedError):
            stage.move_by(1, 1)

    assert sent_during(sim, stage, refused) == b""


@pytest.mark.parametrize("x_mm,y_mm", [(-0.001, 10), (10, 200.001), (1e9, 0)])
def test_soft_limit_move_is_refused_without_sending(sim, homed, x_mm, y_mm):
    def refused():
        with pytest.raises(InputError, match="outside the soft limits"):
            homed.move_to(x_mm, y_mm)

    assert sent_during(sim, homed, refused) == b""


def test_relative_move_past_the_limits_sends_no_motion(sim, homed):
    homed.move_to(190, 10, timeout_s=2.0)

    def refused():
        with pytest.raises(InputError, match=r"move to \(210.000, 10.000\) mm"):
            homed.move_by(20, 0)

    assert sent_during(sim, homed, refused) == b"?"  # the position read-back only, no G-code


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), "ten", None])
def test_non_numbers_are_input_errors(homed, bad):
    with pytest.raises(InputError):
        homed.move_to(bad, 1)


def test_bad_timeout_is_an_input_error(homed):
    with pytest.raises(InputError, match="timeout_s"):
        homed.move_to(1, 1, timeout_s=0)


# ------------------------------------------------------------------ faults


def test_no_reply_times_out_sends_stop_and_raises(sim, homed):
    sim.drop_replies()  # the link goes silent
    start = time.monotonic()
    with pytest.raises(StageTimeout, match=r"did not finish moving to \(10.000, 10.000\) mm within 0.3 s.*stop was sent"):
        homed.move_to(10, 10, timeout_s=0.3)
    assert time.monotonic() - start < 0.3 + 0.5 + 0.5
    assert received(sim, b"!")  # feed hold
    assert sim.wait_for(lambda: sim.realtime_log[-1:] == [b"\x18"])  # hold not confirmed -> soft reset
    assert not homed.homed


def test_move_longer_than_its_deadline_is_halted_and_position_kept(sim, homed):
    sim.speed_mm_s = 100.0
    with pytest.raises(StageTimeout, match="stop was sent"):
        homed.move_to(150, 150, timeout_s=0.2)
    assert received(sim, b"!")
    assert sim.state == "Idle"  # held, then reset from Hold:0: GRBL keeps its position
    x_mm, y_mm = homed.position()
    assert 0 < x_mm < 150 and x_mm == pytest.approx(y_mm, abs=0.01)
    assert homed.homed  # position retained, so still homed
    sim.speed_mm_s = 1000.0
    homed.move_to(1, 2, timeout_s=2.0)
    assert homed.position() == (1.0, 2.0)


def test_error_reply_raises_with_grbl_text_and_stage_recovers(sim, homed):
    sim.fail_next(20, match="G")
    with pytest.raises(DeviceError, match=r"answered error:20 \(Unsupported command: Unsupported or invalid g-code"):
        homed.move_to(10, 10, timeout_s=1.0)
    assert homed.homed
    homed.move_to(10, 10, timeout_s=1.0)
    assert homed.position() == (10.0, 10.0)


def test_error_reply_to_homing(sim, stage):
    sim.fail_next(5, match="$H")
    with pytest.raises(DeviceError, match=r"error:5 \(Setting disabled: Homing cycle failure"):
        stage.home(timeout_s=1.0)
    assert not stage.homed


def test_alarm_mid_move_raises_and_unhomes(sim, homed):
    sim.alarm_mid_move(code=1, at_fraction=0.5)
    with pytest.raises(StageAlarm, match=r"ALARM:1 \(Hard limit: Hard limit has been triggered.*no longer homed"):
        homed.move_to(100, 100, timeout_s=2.0)
    assert not homed.homed
    assert 0 < sim.position_mm[0] < 100
    with pytest.raises(NotHomedError):
        homed.move_to(10, 10)
    homed.home(timeout_s=2.0)  # resets out of the critical alarm, then homes
    homed.move_to(10, 10, timeout_s=2.0)
    assert homed.position() == (10.0, 10.0)


def test_controller_side_soft_limit_alarm(sim):
    small = GrblSim(speed_mm_s=1000.0, travel_mm=(50.0, 50.0)).start()
    try:
        with make_stage(small, limits=Limits(0, 100, 0, 100)) as stage:
            stage.home(timeout_s=2.0)
            with pytest.raises(StageAlarm, match=r"ALARM:2 \(Soft limit"):
                stage.move_to(80, 10, timeout_s=1.0)
            assert small.position_mm == (0.0, 0.0)  # refused before moving
            stage.home(timeout_s=2.0)
            stage.move_to(40, 10, timeout_s=1.0)
    finally:
        small.close()


def test_garbage_lines_are_tolerated(sim, stage):
    sim.garble_replies(8)
    sim.send_garbage(b"\x00\xff\xfe noise\r\n")
    stage.home(timeout_s=2.0)
    stage.move_to(30, 40, timeout_s=2.0)
    assert stage.position() == (30.0, 40.0)
    assert stage.garbage_lines >= 8


def test_corrupted_reply_is_a_timeout_with_stop(sim, homed):
    sim.corrupt_replies(1)  # the first reply of the move (its status check) is lost in noise
    with pytest.raises(StageTimeout, match="within 0.3 s .*stop was sent"):
        homed.move_to(10, 10, timeout_s=0.3)
    assert received(sim, b"!")
    assert homed.garbage_lines == 1


def test_slow_replies_within_the_deadline_work(sim, homed):
    sim.set_latency(0.02)
    homed.move_to(5, 5, timeout_s=2.0)
    assert homed.position() == (5.0, 5.0)


def test_replies_slower_than_the_deadline_time_out(sim, homed):
    sim.set_latency(1.0)
    with pytest.raises(StageTimeout, match="reading its position within 0.2 s"):
        homed.position(timeout_s=0.2)


def test_disconnect_mid_move_names_the_device(sim, homed):
    sim.disconnect_mid_move(at_fraction=0.3)
    with pytest.raises(DeviceError, match=rf"GRBL stage {re.escape(sim.path)} lost its connection while moving to \(150.000, 150.000\) mm"):
        homed.move_to(150, 150, timeout_s=2.0)
    assert wait_until(lambda: sim.hung_up, timeout_s=2.0)  # the server thread records it after closing the pty
    assert not homed.is_connected and not homed.homed
    with pytest.raises(DeviceError, match="is not connected"):
        homed.position()
    homed.stop()  # harmless once disconnected


def test_silent_device_fails_to_connect(sim):
    sim.drop_replies()
    driver = make_stage(sim, connect_timeout_s=0.3)
    with pytest.raises(StageTimeout, match=r"did not answer while connecting \((startup banner|status report)"):
        driver.connect()
    assert not driver.is_connected
    driver.close()


# ------------------------------------------------------------------ stop and threads


def test_stop_from_another_thread_halts_a_long_move(sim, homed):
    sim.speed_mm_s = 100.0
    thread, outcome = run_in_thread(lambda: homed.move_to(190, 190, timeout_s=5.0))
    assert sim.wait_state("Run")
    homed.stop()
    thread.join(timeout=3.0)
    assert not thread.is_alive()
    assert isinstance(outcome.get("error"), StageStopped)
    assert "was stopped while moving to (190.000, 190.000) mm" in str(outcome["error"])
    assert sim.state == "Idle"
    x_mm, _ = sim.position_mm
    assert x_mm < 190
    assert homed.homed  # feed hold, then reset from Hold:0 keeps the position
    assert homed.position() == pytest.approx(sim.position_mm, abs=0.001)
    sim.speed_mm_s = 1000.0
    homed.move_to(5, 5, timeout_s=2.0)


def test_stop_while_idle_does_not_block_the_next_move(sim, homed):
    homed.stop()
    assert sim.state == "Idle"  # the '!' hold was cleared by a reset
    homed.move_to(3, 4, timeout_s=2.0)
    assert homed.position() == (3.0, 4.0)


def test_stop_cancels_moves_waiting_for_the_lock(sim, homed):
    sim.speed_mm_s = 100.0
    first, first_outcome = run_in_thread(lambda: homed.move_to(150, 150, timeout_s=5.0))
    assert sim.wait_state("Run")
    second, second_outcome = run_in_thread(lambda: homed.move_to(10, 10, timeout_s=5.0))
    homed.stop()
    first.join(3.0)
    second.join(3.0)
    assert isinstance(first_outcome.get("error"), StageStopped)
    assert isinstance(second_outcome.get("error"), StageStopped)
    homed.position()  # round trip: everything sent before has been read by the simulator
    assert not any(line.startswith("G90 G53 G0 X10.000") for line in sim.received_lines)


def test_stop_during_homing_aborts_it(sim):
    slow = GrblSim(speed_mm_s=20.0, start_mm=(150, 150)).start()
    try:
        with make_stage(slow) as stage:
            thread, outcome = run_in_thread(lambda: stage.home(timeout_s=5.0))
            assert slow.wait_state("Home")
            stage.stop()
            thread.join(3.0)
            assert isinstance(outcome.get("error"), StageStopped)
            assert not stage.homed and slow.state == "Alarm" and 6 in slow.alarms_sent
    finally:
        slow.close()


def test_two_threads_never_interleave_bytes_on_the_wire(sim, homed):
    errors = []

    def mover():
        for i in range(15):
            homed.move_to(10 + i, 20 + i, timeout_s=2.0)

    def reader():
        for _ in range(30):
            homed.position(timeout_s=2.0)
            homed.is_busy(timeout_s=2.0)

    threads = [threading.Thread(target=lambda f=f: _collect(f, errors)) for f in (mover, reader, reader)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert errors == []
    lines = [line for line in sim.received_lines if line]
    assert lines and all(VALID_LINE.match(line) for line in lines), [l for l in lines if not VALID_LINE.match(l)]
    assert sum(line.startswith("G90") for line in lines) == 15
    assert homed.garbage_lines == 0


def _collect(fn, errors):
    """Run fn, appending any exception to errors."""
    try:
        fn()
    except Exception as exc:
        errors.append(exc)


def test_unlock_clears_the_alarm_but_not_the_homing_requirement(sim, stage):
    stage.unlock()
    assert sim.state == "Idle"
    with pytest.raises(NotHomedError):
        stage.move_to(1, 1)


def test_second_driver_on_the_same_port_is_refused(sim, stage):
    with pytest.raises(DeviceError, match="already open"):
        make_stage(sim).connect()
