"""Zaber ASCII codec: commands, replies, alerts, info, checksums, garbage."""

import pytest

from drivers.stage import zaber_codec as zc


def test_encode_command_forms():
    assert zc.encode_command(1, 1, "move abs 1000") == b"/1 1 move abs 1000\n"
    assert zc.encode_command(1, 2, "get pos", message_id=7) == b"/1 2 07 get pos\n"
    assert zc.encode_command(2, 0, "") == b"/2 0\n"
    with pytest.raises(ValueError):
        zc.encode_command(1, 1, "move abs 1\n/2 0 home")
    with pytest.raises(ValueError):
        zc.encode_command(1, 1, "home", message_id=100)


@pytest.mark.parametrize("checksum", [False, True])
@pytest.mark.parametrize("device,axis,mid,text", [(1, 1, 12, "move abs 1000"), (2, 0, None, "stop"), (1, 2, 3, "")])
def test_command_round_trip(device, axis, mid, text, checksum):
    line = zc.encode_command(device, axis, text, message_id=mid, checksum=checksum)
    assert zc.parse_command(line) == zc.Command(device, axis, mid, text)


def test_parse_short_commands():
    assert zc.parse_command("/") == zc.Command(0, 0, None, "")
    assert zc.parse_command("/1 home") == zc.Command(1, 0, None, "home")
    assert zc.parse_command("/home") == zc.Command(0, 0, None, "home")
    with pytest.raises(zc.ZaberSyntaxError):
        zc.parse_command("move abs 1")
    with pytest.raises(zc.ZaberSyntaxError):
        zc.parse_command("/1 1 home:00")


def test_checksum_is_the_lrc_of_the_body():
    payload = b"01 0 OK IDLE -- 0"
    assert (sum(payload) + zc.lrc(payload)) & 0xFF == 0
    line = zc.encode_command(1, 0, "get pos", checksum=True)
    assert line == b"/1 0 get pos:%02X\n" % zc.lrc(b"1 0 get pos")


@pytest.mark.parametrize("checksum", [False, True])
def test_reply_round_trip(checksum):
    reply = zc.Reply(1, 1, 12, "OK", "BUSY", "--", "0")
    line = zc.encode_reply(reply, checksum=checksum)
    assert line.startswith(b"@01 1 12 OK BUSY -- 0")
    assert zc.parse_message(line) == reply


def test_reply_forms():
    rej = zc.parse_message(b"@01 1 RJ IDLE -- BADDATA\r\n")
    assert rej.rejected and not rej.busy and rej.data == "BADDATA" and rej.message_id is None
    multi = zc.parse_message("@02 0 05 OK IDLE WR 1000 2000")
    assert (multi.device, multi.axis, multi.message_id, multi.warning, multi.values) == (2, 0, 5, "WR", ["1000", "2000"])
    stall = zc.parse_message("@01 1 OK IDLE FS 0")
    assert stall.warning == "FS" and zc.warning_text("FS").startswith("Stalled")


def test_alert_and_info_round_trip():
    alert = zc.Alert(1, 2, "IDLE", "--")
    assert zc.parse_message(zc.encode_alert(alert)) == alert
    info = zc.Info(1, 0, None, "Visit www.example.invalid for help")
    assert zc.parse_message(zc.encode_info(info)) == info


@pytest.mark.parametrize("line", [b"\xfe\x01garbled\xff", b"@xx 1 OK IDLE -- 0", b"@01 1 MAYBE IDLE -- 0",
                                  b"@01 1 OK IDLE -- 0:00", b"hello", b"@01"])
def test_garbage(line):
    assert isinstance(zc.parse_message(line), zc.Garbage)


def test_blank_is_none():
    assert zc.parse_message(b"\r\n") is None


def test_warning_rank_and_tables():
    assert zc.warning_rank("FS") > zc.warning_rank("WR") > zc.warning_rank("NI") > zc.warning_rank("--")
    assert zc.rejection_text("BADDATA").startswith("the data")
    assert zc.rejection_text("NOPE") == "unknown rejection reason"
