"""MarlinPrinter against the virtual Marlin printer over real pseudo-terminals."""

from __future__ import annotations

import math
import threading
import time

import pytest

from beadsight.config import REFERENCE_CENTRE_XY_MM, ConfigError
from beadsight.devices import (
    CommandRecord,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    MarlinPrinter,
    PrinterDesyncError,
    PrinterError,
    SafetyEnvelope,
    SafetyError,
)
from beadsight.devices.marlin import checksum, clean_gcode, frame_line, parse_position
from beadsight.devices.virtual import VirtualPrinter

CENTRE = REFERENCE_CENTRE_XY_MM
ENVELOPE = SafetyEnvelope(
    centre_xy_mm=CENTRE, xy_half_range_mm=15.0, z_floor_mm=126.5, z_clear_mm=135.0
)
HOME = (0.0, 0.0, 180.0)
FAST = 20.0  # simulated seconds per host second in motion tests
SETTLE_S = 0.05  # the virtual printer's boot chatter is instantaneous


@pytest.fixture
def virtual():
    with VirtualPrinter(
        time_scale=FAST, home_position_mm=HOME, boot_delay_s=0.2, busy_interval_s=2.0
    ) as vp:
        yield vp


@pytest.fixture
def printer(virtual):
    with MarlinPrinter(virtual.port, envelope=ENVELOPE, timeout_s=1.0, boot_settle_s=SETTLE_S) as p:
        yield p


def homed(printer: MarlinPrinter) -> MarlinPrinter:
    printer.home()
    return printer


def within(seconds: float, fn, *args):
    """Run fn(*args) in a thread; its result or exception, or fail if it hangs."""
    result: dict = {}

    def run():
        try:
            result["value"] = fn(*args)
        except BaseException as e:  # noqa: BLE001 - handed to the test
            result["error"] = e

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"{fn.__name__} still waiting after {seconds} s"
    return result


def line_number(framed: str) -> int:
    return int(framed.split()[0][1:])


# --- framing ------------------------------------------------------------------------------
def test_checksum_is_xor_of_bytes():
    text = "N12 G1 X10 Y20"
    expected = 0
    for ch in text:
        expected ^= ord(ch)
    assert checksum(text) == expected
    assert frame_line(12, "G1 X10 Y20") == f"{text}*{expected}"
    assert frame_line(0, "M110 N0") == "N0 M110 N0*125"  # the classic host handshake line


def test_clean_gcode_strips_comments_and_refuses_bad_text():
    assert clean_gcode("  M105 ; temperatures ") == "M105"
    for bad in ("", "; only a comment", "G1 X1*12", "M117 caf\u00e9", "G1 " + "X1 " * 40):
        with pytest.raises(ValueError):
            clean_gcode(bad)


def test_parse_position_ignores_count_section():
    lines = ["X:151.80 Y:108.90 Z:137.50 E:0.00 Count X:12144 Y:8712 Z:55000"]
    assert parse_position(lines) == (151.8, 108.9, 137.5)
    assert parse_position(["T:22.0 /0.0"]) is None


# --- connection -------------------------------------------------------------------------
def test_connect_waits_for_banner_and_resets_line_numbers(virtual):
    with MarlinPrinter(virtual.port, envelope=ENVELOPE, timeout_s=1.0, boot_settle_s=SETTLE_S) as p:
        assert p.banner_seen
        assert p.connected
    assert virtual.received[0] == "N0 M110 N0*125"
    assert virtual.received[1] == frame_line(1, "G90")
    assert virtual.executed[:2] == ["M110 N0", "G90"]


def test_printer_without_banner_connects_after_banner_timeout():
    with VirtualPrinter(banner=False) as vp:
        start = time.monotonic()
        with MarlinPrinter(vp.port, envelope=ENVELOPE, timeout_s=1.0, banner_timeout_s=0.3) as p:
            elapsed = time.monotonic() - start
            assert not p.banner_seen
            assert p.send("M105") == ["T:22.0 /0.0 B:22.0 /0.0 @:0 B@:0"]
        assert 0.3 <= elapsed < 2.0


def test_absent_port_is_named_with_a_hint():
    with pytest.raises(DeviceNotConnectedError) as err:
        MarlinPrinter("/dev/ttyUSB97").connect()
    message = str(err.value)
    assert "/dev/ttyUSB97" in message and "does not exist" in message
    assert "ls /dev/ttyUSB*" in message


def test_busy_port_is_named(virtual):
    with MarlinPrinter(virtual.port, envelope=ENVELOPE, timeout_s=1.0, boot_settle_s=SETTLE_S):
        with pytest.raises(DeviceNotConnectedError, match=f"{virtual.port} is busy"):
            MarlinPrinter(virtual.port).connect()


def test_silent_printer_times_out_naming_port_and_command(virtual):
    virtual.set_silent()
    start = time.monotonic()
    with pytest.raises(DeviceTimeoutError) as err:
        MarlinPrinter(virtual.port, timeout_s=0.4, banner_timeout_s=0.1).connect()
    assert time.monotonic() - start < 3.0
    message = str(err.value)
    assert virtual.port in message and "'M110 N0'" in message and "0.4 s" in message


# --- handshake faults -----------------------------------------------------------------------
def test_resend_after_checksum_errors_executes_once(printer, virtual):
    homed(printer)
    virtual.corrupt_next(2)
    printer.move(CENTRE[0], CENTRE[1], 140.0, 3000)
    assert printer.resend_count == 2
    assert virtual.executed.count("G1 X151.8 Y108.9 Z140 F3000") == 1
    printer.wait_for_motion()
    assert printer.position() == pytest.approx((*CENTRE, 140.0), abs=0.01)


def test_endless_resends_give_up_with_printer_error(printer, virtual):
    virtual.corrupt_next(20)
    with pytest.raises(PrinterError, match="rejected 5 times.*checksum mismatch"):
        printer.send("M105")


def test_busy_keepalives_extend_the_deadline():
    with VirtualPrinter(time_scale=2.0, busy_interval_s=0.1) as vp:
        with MarlinPrinter(vp.port, timeout_s=0.5, boot_settle_s=SETTLE_S) as p:
            vp.busy_next(2.0)  # 1.0 s host, with a keep-alive every 0.05 s
            start = time.monotonic()
            p.send("M17")
            assert time.monotonic() - start >= 0.95


def test_busy_without_keepalives_times_out():
    with (
        VirtualPrinter(busy_interval_s=10.0) as vp,
        MarlinPrinter(vp.port, timeout_s=0.3, boot_settle_s=SETTLE_S) as p,
    ):
        vp.busy_next(1.0)
        with pytest.raises(DeviceTimeoutError, match="'M17'"):
            p.send("M17")


# --- transmission errors in OctoPrint's words, lost lines, lost oks (issue 13, item 8) ---
@pytest.fixture
def octo():
    with VirtualPrinter(time_scale=FAST, home_position_mm=HOME, error_style="octoprint") as vp:
        with MarlinPrinter(vp.port, envelope=ENVELOPE, timeout_s=1.0, boot_settle_s=SETTLE_S) as p:
            yield p, vp


def test_octoprint_missing_checksum_with_resend_is_recovered(octo):
    printer, virtual = octo
    homed(printer)
    virtual.reject_next("Error: Missing checksum", resend=0)  # then 'Resend:n', 'ok'
    printer.move(*CENTRE, 140.0, 3000)
    assert virtual.executed.count("G1 X151.8 Y108.9 Z140 F3000") == 1
    assert printer.resend_count == 1
    printer.wait_for_motion()
    assert printer.position() == pytest.approx((*CENTRE, 140.0), abs=0.01)


def test_printer_ahead_expected_line_error_resynchronises(octo):
    printer, virtual = octo
    homed(printer)
    virtual.reject_next(resend=+1)  # 'Error: expected line 16 got 15', 'Resend:16', 'ok'
    printer.move(*CENTRE, 140.0, 3000)
    assert any(t.startswith("Error: expected line") for t in virtual.replies)
    assert printer.resyncs == 1
    assert any(" M110 N" in line for line in virtual.received[2:])
    assert virtual.executed.count("G1 X151.8 Y108.9 Z140 F3000") == 1
    printer.wait_for_motion()
    assert virtual.current_position() == pytest.approx((*CENTRE, 140.0))
    assert printer.send("M105")[0].startswith("T:")  # line numbers agree again


@pytest.mark.parametrize(
    "fault",
    [
        lambda vp: vp.lose_next("line"),
        lambda vp: vp.reject_next(
            "Error: No Line Number with checksum, Last Line: 7", resend=None, ok=False
        ),
    ],
    ids=["line-lost", "error-without-resend"],
)
def test_line_without_ok_is_sent_again_after_resynchronising(octo, fault):
    printer, virtual = octo
    homed(printer)
    fault(virtual)
    start = time.monotonic()
    printer.move(*CENTRE, 140.0, 3000)
    assert time.monotonic() - start < 5.0  # one ok timeout (1 s) and one reply grace (1 s)
    assert printer.resyncs == 1
    assert virtual.executed.count("G1 X151.8 Y108.9 Z140 F3000") == 1
    printer.wait_for_motion()
    assert printer.position() == pytest.approx((*CENTRE, 140.0), abs=0.01)


def test_lost_ok_repeats_only_the_current_absolute_move(octo):
    printer, virtual = octo
    homed(printer)
    virtual.lose_next("ok")
    printer.move(*CENTRE, 140.0, 3000)
    # the printer ran it, its ok was lost: the same absolute move again is harmless
    assert virtual.executed.count("G1 X151.8 Y108.9 Z140 F3000") == 2
    assert [r.gcode for r in printer.command_log].count("G1 X151.8 Y108.9 Z140 F3000") == 1
    printer.wait_for_motion()
    assert printer.position() == pytest.approx((*CENTRE, 140.0), abs=0.01)


def test_octoprint_style_position_report_on_the_ok_line(octo):
    printer, _ = octo
    assert printer.home() == HOME  # 'ok X:0.0 Y:0.0 Z:180.0 E:0.0 Count: ...'


# --- a resend request for an acknowledged line (item 9) --------------------------------------
def test_resend_of_acknowledged_line_never_replays_motion(printer, virtual):
    homed(printer)
    travel = "G1 X156.8 Y108.9 Z137.5 F3000"
    printer.move(CENTRE[0] + 5, CENTRE[1], 137.5, 3000)
    printer.wait_for_motion()
    printer.move(None, None, 128.0, 200)  # the finger goes down
    travel_n = next(line_number(r) for r in virtual.received if travel in r)
    next_n = line_number(virtual.received[-1]) + 1
    # the board lost its place: it asks again for the travel line, acknowledged long ago
    virtual.reject_next(resend=travel_n - next_n)
    with pytest.raises(PrinterDesyncError) as err:
        printer.wait_for_motion()
    assert virtual.executed.count(travel) == 1  # never replayed at press depth
    message = str(err.value)
    assert f"resend line {travel_n}" in message and "already acknowledged" in message
    assert "raised to Z=135" in message
    assert virtual.current_position()[2] == pytest.approx(ENVELOPE.z_clear_mm)
    assert virtual.current_position()[:2] == pytest.approx((CENTRE[0] + 5, CENTRE[1]))
    assert printer.target == pytest.approx((CENTRE[0] + 5, CENTRE[1], 135.0))
    assert printer.send("M105")[0].startswith("T:")  # line numbers re-synchronised
    assert isinstance(err.value, PrinterError)


def test_position_other_than_commanded_after_a_wait_is_a_desync(printer, virtual):
    homed(printer)
    printer.move(*CENTRE, 137.5, 3000)
    virtual.m114_reply_next("X:151.80 Y:98.90 Z:137.50 E:0.00 Count X:0 Y:0 Z:0")
    with pytest.raises(PrinterDesyncError, match="reports X=151.800 Y=98.900"):
        printer.wait_for_motion()


# --- timeouts, acknowledgements, messages (item 10) ------------------------------------------
def test_endless_busy_keepalives_do_not_defeat_the_homing_deadline():
    with VirtualPrinter(busy_interval_s=0.05) as vp:
        with MarlinPrinter(vp.port, timeout_s=0.3, home_timeout_s=1.0, boot_settle_s=SETTLE_S) as p:
            vp.busy_next(math.inf)
            start = time.monotonic()
            result = within(5.0, p.home)
    assert isinstance(result.get("error"), DeviceTimeoutError)
    assert time.monotonic() - start < 3.0
    assert "'G28'" in str(result["error"]) and "busy" in str(result["error"])


def test_endless_busy_keepalives_do_not_defeat_the_command_deadline():
    with VirtualPrinter(busy_interval_s=0.05) as vp:
        with MarlinPrinter(vp.port, timeout_s=0.3, busy_timeout_s=0.7, boot_settle_s=SETTLE_S) as p:
            vp.busy_next(math.inf)
            start = time.monotonic()
            result = within(5.0, p.send, "M17")
            elapsed = time.monotonic() - start
    assert isinstance(result.get("error"), DeviceTimeoutError)
    assert 0.9 <= elapsed < 3.0
    assert "overall limit of 1.0 s" in str(result["error"])


def test_duplicated_ok_does_not_end_wait_for_motion_early(printer, virtual):
    homed(printer)
    target = (*CENTRE, 137.5)
    virtual.duplicate_ok_next()  # the G1 gets two oks; the second meets the M400
    printer.move(*target, 700)  # ~16 s simulated, ~0.8 s host
    printer.wait_for_motion()
    assert virtual.current_position() == pytest.approx(target)
    assert printer.extra_oks == 1


def test_duplicated_ok_does_not_end_a_dwell_early(printer, virtual):
    homed(printer)
    virtual.duplicate_ok_next()
    printer.send("M105")
    start = time.monotonic()
    printer.dwell(10_000)  # 10 s simulated = 0.5 s host
    assert time.monotonic() - start >= 10.0 / FAST - 0.02


def test_malformed_position_report_raises_printer_error(printer, virtual):
    virtual.m114_reply_next("X:1.2.3 Y:0.00 Z:180.00 E:0.00 Count X:0 Y:0 Z:0")
    with pytest.raises(PrinterError, match="could not read the position.*X:1.2.3"):
        printer.position()
    assert printer.position() == HOME  # the next report is fine
    virtual.m114_reply_next("echo:no position today")  # a bare 'ok'
    with pytest.raises(PrinterError, match="the reply to 'M114' carried no data"):
        printer.position()


def test_move_refused_after_homing_to_z0_names_the_target_and_the_fix():
    with (
        VirtualPrinter(time_scale=FAST, home_position_mm=(0.0, 0.0, 0.0)) as vp,
        MarlinPrinter(vp.port, envelope=ENVELOPE, timeout_s=1.0, boot_settle_s=SETTLE_S) as p,
    ):
        assert p.home() == (0.0, 0.0, 0.0)
        sent = len(vp.received)
        with pytest.raises(SafetyError) as err:
            p.move(*CENTRE, 137.5, 700)
        message = str(err.value)
        assert "refused move to X=151.800 Y=108.900 Z=137.500" in message
        assert "the head is at X=0.000 Y=0.000 Z=0.000" in message
        assert "raise Z first: move(None, None, 135" in message
        assert len(vp.received) == sent
        p.move(None, None, 137.5, 3000)  # the fix works
        p.move(*CENTRE, 137.5, 3000)
        p.wait_for_motion()
        assert vp.current_position() == pytest.approx((*CENTRE, 137.5))


def test_error_line_raises_with_printer_text_and_halts(printer, virtual):
    virtual.fail_next("MINTEMP triggered, system stopped! Heater_ID: 0")
    with pytest.raises(PrinterError, match="MINTEMP triggered"):
        printer.send("M105")
    with pytest.raises(PrinterError, match="halted"):
        printer.send("M105")


def test_garbage_lines_are_skipped(printer, virtual):
    virtual.emit_garbage(3)
    time.sleep(0.05)
    assert printer.send("M105")[0].startswith("T:")
    assert printer.garbage_lines == 3


def test_garbage_replies_time_out(printer, virtual):
    virtual.set_garbage_replies()
    with pytest.raises(DeviceTimeoutError, match="no 'ok' for 'M105'"):
        printer.send("M105", timeout_s=0.3)
    assert printer.garbage_lines >= 1


def test_unplugged_printer_raises_not_connected(printer, virtual):
    virtual.unplug()
    with pytest.raises(DeviceNotConnectedError, match="unplugged"):
        printer.send("M105")


# --- motion -------------------------------------------------------------------------------
def test_home_reports_home_position(printer):
    assert printer.target is None
    assert printer.home() == HOME
    assert printer.target == HOME


def test_position_interpolates_then_arrives(printer, virtual):
    homed(printer)
    printer.move(CENTRE[0], CENTRE[1], 137.5, 3000)  # ~186 mm: ~3.7 s simulated
    mid = printer.position()
    assert 0 < mid[0] < CENTRE[0] and 0 < mid[1] < CENTRE[1]
    printer.wait_for_motion()
    assert printer.position() == pytest.approx((*CENTRE, 137.5), abs=0.01)
    assert virtual.current_position() == pytest.approx((*CENTRE, 137.5))


def test_press_moves_and_dwell(printer, virtual):
    homed(printer)
    printer.move(CENTRE[0] + 5, CENTRE[1] - 5, 137.5, 3000)
    printer.move(None, None, 127.5, 200)
    printer.wait_for_motion()
    assert printer.position() == pytest.approx((CENTRE[0] + 5, CENTRE[1] - 5, 127.5), abs=0.01)
    start = time.monotonic()
    printer.dwell(2000)  # 2 s simulated = 0.1 s host
    assert time.monotonic() - start >= 2.0 / FAST - 0.02
    assert "G1 Z127.5 F200" in virtual.executed
    assert "G4 P2000" in virtual.executed


def test_command_log_records_times_and_positions(virtual):
    records: list[CommandRecord] = []
    with MarlinPrinter(
        virtual.port, envelope=ENVELOPE, timeout_s=1.0, on_command=records.append
    ) as p:
        t0 = time.monotonic()
        p.home()
        p.move(*CENTRE, 140.0, 3000)
        p.wait_for_motion()
        p.heaters_off()
    assert records == p.command_log
    gcodes = [r.gcode for r in records]
    assert gcodes[:4] == ["M110 N0", "G90", "G28", "M114"]
    assert gcodes[-2:] == ["M104 S0", "M140 S0"]
    move = records[gcodes.index("G1 X151.8 Y108.9 Z140 F3000")]
    assert (move.x_mm, move.y_mm, move.z_mm) == (*CENTRE, 140.0)
    assert math.isnan(records[0].x_mm)  # before homing the position is unknown
    t_unix, t_mono, gcode, x, y, z = move  # unpacks as the 6-tuple the recorder writes
    assert isinstance(t_unix, float) and abs(t_unix - time.time()) < 60
    assert t_mono >= t0
    monos = [r.t_mono for r in records]
    assert monos == sorted(monos)


# --- safety --------------------------------------------------------------------------------
def test_moves_refused_before_homing_send_nothing(printer, virtual):
    sent = len(virtual.received)
    with pytest.raises(SafetyError, match="home"):
        printer.move(*CENTRE, 137.5, 700)
    assert len(virtual.received) == sent


@pytest.mark.parametrize(
    ("target", "feed", "match"),
    [
        ((CENTRE[0], CENTRE[1], 120.0), 200, "below the safety floor Z=126.5"),
        ((CENTRE[0] + 20, CENTRE[1], 130.0), 200, r"within \+-15 mm of the sensor centre"),
        ((CENTRE[0], CENTRE[1], 137.5), 9000, "feed rate F9000"),
        ((CENTRE[0], CENTRE[1], math.nan), 700, "finite"),
    ],
)
def test_envelope_refusals_send_nothing(printer, virtual, target, feed, match):
    homed(printer)
    printer.move(*CENTRE, 137.5, 3000)
    printer.wait_for_motion()
    sent = len(virtual.received)
    with pytest.raises(SafetyError, match=match) as err:
        printer.move(*target, feed)
    assert len(virtual.received) == sent
    assert "nothing was sent" in str(err.value) or "finite" in str(err.value)
    assert printer.name in str(err.value)


def test_diagonal_descent_into_the_box_edge_is_refused(printer, virtual):
    homed(printer)
    printer.move(CENTRE[0] + 40, CENTRE[1], 137.5, 3000)
    printer.wait_for_motion()
    sent = len(virtual.received)
    # the target is inside the box, but the path dips below the clear height outside it
    with pytest.raises(SafetyError, match="refused move through"):
        printer.move(CENTRE[0] + 10, CENTRE[1], 128.0, 700)
    assert len(virtual.received) == sent


def test_send_refuses_motion_commands(printer, virtual):
    sent = len(virtual.received)
    for gcode in ("G1 Z0", "G28", "G91", "G92 Z0", "M112"):
        with pytest.raises(SafetyError, match="refused"):
            printer.send(gcode)
    assert len(virtual.received) == sent


def test_envelope_validation_and_vertical_escape():
    with pytest.raises(ConfigError, match="z_floor_mm"):
        SafetyEnvelope(z_floor_mm=140.0, z_clear_mm=135.0)
    with pytest.raises(ConfigError, match="xy_half_range_mm"):
        SafetyEnvelope(xy_half_range_mm=0)
    env = SafetyEnvelope()
    assert env.contains((151.8, 108.9, 127.0))
    assert not env.contains((0.0, 0.0, 127.0))
    # a head parked low outside the box (e.g. after homing) may only rise straight up
    env.check_move((0.0, 0.0, 130.0), (0.0, 0.0, 150.0), 700, device="p")
    with pytest.raises(SafetyError):
        env.check_move((0.0, 0.0, 130.0), (5.0, 0.0, 150.0), 700, device="p")
    assert SafetyEnvelope.from_dict(env.to_dict()) == env


# --- emergency stop -------------------------------------------------------------------------
def test_emergency_stop_halts_mid_move(virtual):
    with MarlinPrinter(virtual.port, envelope=ENVELOPE, timeout_s=1.0, boot_settle_s=SETTLE_S) as p:
        p.home()
        p.move(*CENTRE, 137.5, 700)  # ~16 s simulated, 0.8 s host
        time.sleep(0.1)
        stopper = threading.Thread(target=p.emergency_stop)
        stopper.start()
        stopper.join()
        time.sleep(0.1)
        assert virtual.halted
        frozen = virtual.current_position()
        time.sleep(0.1)
        assert virtual.current_position() == frozen
        assert frozen[0] < CENTRE[0] - 1.0  # stopped on the way
        assert p.halted
        with pytest.raises(PrinterError, match="halted"):
            p.position()
    assert "M112" in virtual.received
    assert p.command_log[-1].gcode == "M112"
