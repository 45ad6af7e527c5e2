"""GRBL codec: every controller reply form, host commands, and encode/parse round trips."""

import pytest

from drivers.stage import grbl_codec as gc


def test_ok_error_alarm():
    assert gc.parse_line(b"ok\r\n") == gc.Ok()
    err = gc.parse_line(b"error:20\r\n")
    assert err == gc.Error(20)
    assert err.text == "Unsupported command: Unsupported or invalid g-code command found in block"
    alarm = gc.parse_line("ALARM:1")
    assert alarm == gc.Alarm(1) and alarm.position_lost
    assert alarm.text.startswith("Hard limit: Hard limit has been triggered")
    assert not gc.Alarm(2).position_lost


@pytest.mark.parametrize("code", sorted(gc.ERROR_TEXT))
def test_every_error_code_round_trips_with_text(code):
    msg = gc.parse_line(gc.encode_error(code))
    assert msg == gc.Error(code)
    assert msg.text.startswith(gc.ERROR_TEXT[code][0])


@pytest.mark.parametrize("code", sorted(gc.ALARM_TEXT))
def test_every_alarm_code_round_trips_with_text(code):
    msg = gc.parse_line(gc.encode_alarm(code))
    assert msg == gc.Alarm(code)
    assert msg.text.startswith(gc.ALARM_TEXT[code][0])


def test_unknown_codes_still_parse():
    assert gc.Error(99).text.startswith("Unknown error")
    assert gc.Alarm(42).text.startswith("Unknown alarm")


def test_banner_forms():
    assert gc.parse_line(b"Grbl 1.1h ['$' for help]\r\n") == gc.Banner("1.1h")
    assert gc.parse_line("Grbl 1.1f ['$' for help]") == gc.Banner("1.1f")
    assert gc.parse_line("GrblHAL 1.1f ['$' or '$HELP' for help]") == gc.Banner("1.1f")
    lines = gc.encode_banner().split(b"\r\n")
    assert [gc.parse_line(line) for line in lines] == [None, gc.Banner(gc.VERSION), None]


def test_feedback_messages_and_settings():
    assert gc.parse_line("[MSG:'$H'|'$X' to unlock]") == gc.Feedback("MSG", "'$H'|'$X' to unlock")
    assert gc.parse_line("[MSG:Caution: Unlocked]") == gc.Feedback("MSG", "Caution: Unlocked")
    assert gc.parse_line("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]").kind == "GC"
    assert gc.parse_line("[VER:1.1h.20190825:]") == gc.Feedback("VER", "1.1h.20190825:")
    assert gc.parse_line(gc.encode_feedback("MSG", "Reset to continue")) == gc.Feedback("MSG", "Reset to continue")
    assert gc.parse_line("$110=500.000") == gc.Setting(110, "500.000")
    assert gc.parse_line(gc.encode_setting(22, "1")) == gc.Setting(22, "1")


def test_status_idle_mpos_fs():
    status = gc.parse_line(b"<Idle|MPos:1.000,-2.500,0.000|FS:0,0>\r\n")
    assert status == gc.Status("Idle", mpos_mm=(1.0, -2.5, 0.0), feed_mm_min=0.0, spindle_rpm=0.0)
    assert status.idle and status.machine_position(None) == (1.0, -2.5, 0.0)


def test_status_run_with_every_field():
    text = "<Run|MPos:10.000,20.000,0.000|Bf:15,128|Ln:99|FS:500,8000|Pn:XYZ|WCO:1.000,2.000,0.000|Ov:100,100,100|A:SF>"
    status = gc.parse_status(text)
    assert status.state == "Run" and not status.idle
    assert status.buffer == (15, 128) and status.line_number == 99
    assert status.feed_mm_min == 500 and status.spindle_rpm == 8000
    assert status.pins == "XYZ" and status.overrides == (100, 100, 100)
    assert status.wco_mm == (1.0, 2.0, 0.0)
    assert status.extra == (("A", "SF"),)


def test_status_wpos_uses_wco_from_report_or_cache():
    with_wco = gc.parse_status("<Idle|WPos:5.000,5.000,0.000|FS:0,0|WCO:1.000,2.000,0.000>")
    assert with_wco.machine_position(None) == (6.0, 7.0, 0.0)
    without = gc.parse_status("<Idle|WPos:5.000,5.000,0.000|FS:0,0>")
    assert without.machine_position(None) is None
    assert without.machine_position((1.0, 1.0, 1.0)) == (6.0, 6.0, 1.0)


def test_status_substates_and_feed_only():
    hold = gc.parse_status("<Hold:1|MPos:0.000,0.000,0.000|F:200>")
    assert (hold.state, hold.substate, hold.feed_mm_min) == ("Hold", 1, 200.0)
    assert gc.parse_status("<Door:2|MPos:0,0,0>").substate == 2
    assert gc.parse_status("<Alarm|MPos:0.000,0.000,0.000|FS:0,0>").state == "Alarm"
    assert gc.parse_status("<Home|MPos:0.000,0.000,0.000>").state == "Home"


@pytest.mark.parametrize("status", [
    gc.Status("Idle", mpos_mm=(1.0, 2.0, 3.0), feed_mm_min=0.0, spindle_rpm=0.0),
    gc.Status("Run", mpos_mm=(1.25, -2.0, 0.0), feed_mm_min=3000.0, spindle_rpm=0.0, wco_mm=(0.0, 0.0, 0.0)),
    gc.Status("Hold", 0, wpos_mm=(4.0, 5.0, 6.0), feed_mm_min=0.0),
    gc.Status("Jog", mpos_mm=(0.0, 0.0, 0.0), buffer=(14, 120), line_number=7, feed_mm_min=100.0,
              spindle_rpm=0.0, pins="P", overrides=(100, 50, 10)),
])
def test_status_round_trip(status):
    assert gc.parse_line(gc.encode_status(status)) == status


def test_encode_status_never_prints_negative_zero():
    assert b"-0.000" not in gc.encode_status(gc.Status("Idle", mpos_mm=(-0.0001, 0.0, 0.0)))


@pytest.mark.parametrize("line", [
    b"\xfe\x01~#%garbled\x80\xff", b"<Bogus|MPos:0,0,0>", b"<Idle|MPos:1,2,nan>", b"<Idle|MPos:a,b,c>",
    b"error:x", b"ALARM:", b"ok ok", b"Grbl", b"<Idle|FS:1>", b"[MSG", b"okay",
])
def test_garbage_lines_are_kept_raw(line):
    msg = gc.parse_line(line)
    assert isinstance(msg, gc.Garbage) and msg.raw == line


def test_blank_lines_are_none():
    assert gc.parse_line(b"\r\n") is None and gc.parse_line("   ") is None


def test_host_commands():
    assert gc.encode_move(10, 20.5) == b"G90 G53 G0 X10.000 Y20.500\n"
    assert gc.encode_move(1, 2, feed_mm_min=600) == b"G90 G53 G1 X1.000 Y2.000 F600\n"
    assert gc.encode_home() == b"$H\n" and gc.encode_unlock() == b"$X\n"
    assert [gc.STATUS_QUERY, gc.FEED_HOLD, gc.CYCLE_START, gc.SOFT_RESET] == [b"?", b"!", b"~", b"\x18"]
    assert all(gc.is_realtime(b[0]) for b in (b"?", b"!", b"~", b"\x18")) and not gc.is_realtime(ord("G"))


def test_encode_line_refuses_realtime_bytes_newlines_and_long_lines():
    for bad in ("G0 X1?", "G0\nX1", "G0 X!", "G" + "0" * 90):
        with pytest.raises(ValueError):
            gc.encode_line(bad)
    with pytest.raises(ValueError):
        gc.encode_move(float("nan"), 0)


def test_move_round_trip_through_the_block_parser():
    block = gc.parse_block(gc.encode_move(12.345, -6.5, feed_mm_min=1200).decode())
    assert block.values("G") == [90, 53, 1]
    assert (block.get("X"), block.get("Y"), block.get("F")) == (12.345, -6.5, 1200)


def test_block_parser_comments_and_errors():
    assert gc.parse_block("g0 x1 (comment) y2 ; tail").words == (("G", 0), ("X", 1), ("Y", 2))
    assert gc.parse_block("").words == ()
    for text, code in (("1", 1), ("G0 X", 2), ("G0 X1..2", 1), ("X" + "1" * 90, 11)):
        with pytest.raises(gc.GcodeError) as info:
            gc.parse_block(text)
        assert info.value.code == code
