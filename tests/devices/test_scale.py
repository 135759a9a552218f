"""HX711Scale against the virtual scale over real pseudo-terminals, and the line formats."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest

from beadsight.data.recording.scale_protocol import (
    ProtocolDetector,
    ReferenceDecoder,
    encode_reference_value,
    parse_info,
    parse_reading,
    parse_reference_value,
)
from beadsight.devices import DeviceNotConnectedError, DeviceTimeoutError, HX711Scale, ScaleError
from beadsight.devices.virtual import VirtualScale
from beadsight.geometry import grams_to_newtons


def virtual_scale(**kwargs) -> VirtualScale:
    kwargs.setdefault("noise_g", 0.02)
    kwargs.setdefault("boot_delay_s", 0.05)
    return VirtualScale(**kwargs)


def wait_fresh(scale: HX711Scale, count: int = 3):
    """The reading ``count`` readings after now (lets a load change reach the host)."""
    reading = None
    for _ in range(count):
        reading = scale.wait_for_reading(1.0, after_mono=time.monotonic())
    return reading


# --- line formats ------------------------------------------------------------------------
def test_beadsight_lines_parse():
    sample = parse_reading("R,41,123456,-12.34")
    assert (sample.seq, sample.device_ms, sample.grams) == (41, 123456, -12.34)
    info = parse_info("I,beadsight-scale,1.0.0,rate_hz=80,factor=464.38")
    assert (info.firmware, info.version, info.rate_hz, info.factor) == (
        "beadsight-scale",
        "1.0.0",
        80.0,
        464.38,
    )
    for bad in ("R,1,2", "R,a,2,3.0", "R,-1,2,3.0", "X,1,2,3", "R,1,2,nan"):
        with pytest.raises(ValueError):
            parse_reading(bad)
    assert parse_reference_value("30012.50") == 30012.5
    for bad in ("", "start", "12.3.4", "1e5", "inf"):
        with pytest.raises(ValueError):
            parse_reference_value(bad)


def test_reference_counter_decoding_recovers_grams_and_counter():
    rng = np.random.default_rng(0)
    grams = np.cumsum(rng.normal(0, 300, size=200))  # a load that wanders to +-kilograms
    grams[50:60] = np.linspace(-40, 4900, 10)  # and a steep ramp
    decoder = ReferenceDecoder()
    for i, g in enumerate(np.round(grams, 2)):
        # what the Arduino prints: a 32-bit float with 2 decimals
        printed = float(f"{float(np.float32(encode_reference_value(g, i % 10))):.2f}")
        decoded, counter, lost = decoder.decode(printed)
        assert decoded == pytest.approx(g, abs=0.02)
        assert counter == i % 10
        assert lost == 0


def test_reference_decoding_of_negative_loads_and_wraparound():
    decoder = ReferenceDecoder()
    # counter 0..3 with readings around zero, including negative ones
    assert decoder.decode(-0.5) == (-0.5, 0, 0)
    assert decoder.decode(10000 - 1.25) == (-1.25, 1, 0)  # 9998.75 is -1.25 g at counter 1
    assert decoder.decode(20000 + 3.0) == (3.0, 2, 0)
    assert decoder.decode(90000 + 7.0)[1:] == (9, 6)  # counter 2 -> 9: six lines lost
    assert decoder.decode(0 + 7.5) == (7.5, 0, 0)  # 9 -> 0 wraps without loss
    assert decoder.decode(10000 + 8.0) == (8.0, 1, 0)
    assert decoder.decode(10000 + 8.5) == (8.5, 1, 9)  # the same counter again: nine lost


def test_plain_grams_without_counter_report_no_losses():
    decoder = ReferenceDecoder()
    results = [decoder.decode(v) for v in (0.1, 0.3, 120.0, 480.25, 12.0)]
    assert [g for g, _, _ in results] == [0.1, 0.3, 120.0, 480.25, 12.0]
    assert all(lost == 0 for _, _, lost in results)


# --- beadsight firmware -------------------------------------------------------------------
def test_beadsight_protocol_stream():
    with (
        virtual_scale(protocol="beadsight", rate_hz=80, load_g=0.0) as vs,
        HX711Scale(vs.port) as scale,
    ):
        assert scale.protocol == "beadsight"
        assert scale.info is not None and scale.info.version == "1.0.0" and scale.info.rate_hz == 80
        vs.load_g = 250.0
        reading = wait_fresh(scale)
        assert reading.grams == pytest.approx(250.0, abs=0.2)
        assert reading.force_n == pytest.approx(float(grams_to_newtons(reading.grams)))
        assert isinstance(reading.t_unix, float) and abs(reading.t_unix - time.time()) < 5
        readings = scale.drain()
        seqs = [r.seq for r in readings]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        ms = [r.device_ms for r in readings]
        assert ms == sorted(ms)
        monos = [r.t_mono for r in readings]
        assert monos == sorted(monos)
        assert scale.dropped == 0 and scale.garbage_lines == 0
        info = scale.query_info()
        assert info.firmware == "beadsight-scale"


def test_beadsight_tare_and_calibrate():
    with (
        virtual_scale(protocol="beadsight", load_g=40.0, factor_error=0.1) as vs,
        HX711Scale(vs.port) as scale,
    ):
        assert wait_fresh(scale).grams == pytest.approx(0.0, abs=0.2)  # tared at boot
        vs.load_g = 0.0
        assert wait_fresh(scale).grams == pytest.approx(-40.0 / 1.1, abs=0.3)
        scale.tare()
        assert vs.commands[-1] == "T"
        assert wait_fresh(scale).grams == pytest.approx(0.0, abs=0.2)
        vs.load_g = 200.0
        assert wait_fresh(scale).grams == pytest.approx(200.0 / 1.1, abs=0.5)  # mis-calibrated
        factor = scale.calibrate(200.0)
        assert factor == pytest.approx(vs.counts_per_gram, rel=1e-3)
        assert vs.commands[-1] == "C 200.00"
        assert wait_fresh(scale).grams == pytest.approx(200.0, abs=0.2)


def test_calibrate_without_load_is_refused():
    with virtual_scale(protocol="beadsight") as vs, HX711Scale(vs.port) as scale:
        with pytest.raises(ScaleError, match="no load on the scale"):
            scale.calibrate(100.0)
        with pytest.raises(ValueError, match="known_grams"):
            scale.calibrate(-5.0)


def test_sample_rate_and_rate_command():
    with virtual_scale(protocol="beadsight", rate_hz=80) as vs, HX711Scale(vs.port) as scale:
        time.sleep(0.6)
        assert scale.measured_rate_hz(0.5) == pytest.approx(80, rel=0.25)
        scale.set_rate(10)
        assert vs.commands[-1] == "S 10"
        time.sleep(0.7)
        assert scale.measured_rate_hz(0.6) == pytest.approx(10, rel=0.3)
        with pytest.raises(ValueError, match="rate_hz"):
            scale.set_rate(20)


def test_unanswered_command_times_out():
    with virtual_scale(protocol="beadsight") as vs, HX711Scale(vs.port, timeout_s=0.3) as scale:
        vs.ignore_commands()
        with pytest.raises(DeviceTimeoutError, match="no reply to 'T' within 0.3 s"):
            scale.tare()


def test_dropped_readings_are_counted_from_sequence_gaps():
    with virtual_scale(protocol="beadsight", rate_hz=80) as vs, HX711Scale(vs.port) as scale:
        wait_fresh(scale)
        vs.drop_next(5)
        time.sleep(0.2)
        wait_fresh(scale)
        assert scale.dropped == 5
        seqs = [r.seq for r in scale.drain()]
        assert len(set(np.diff(seqs))) == 2  # steps of 1 and one step of 6


def test_garbage_lines_are_counted_and_skipped(caplog):
    with virtual_scale(protocol="beadsight", rate_hz=80) as vs, HX711Scale(vs.port) as scale:
        with caplog.at_level(logging.WARNING, logger="beadsight.devices.hx711"):
            vs.emit_garbage(4)
            time.sleep(0.1)
            wait_fresh(scale)
        assert scale.garbage_lines == 4
        assert scale.dropped == 0
        assert sum("unreadable line" in r.message for r in caplog.records) == 4


def test_drift_check_measures_grams_per_minute():
    with virtual_scale(protocol="beadsight", rate_hz=80, noise_g=0.01, drift_g_per_min=30.0) as vs:
        with HX711Scale(vs.port) as scale:
            assert scale.check_drift(1.0) == pytest.approx(30.0, abs=6.0)
    with pytest.raises(ValueError):
        HX711Scale("/dev/null").check_drift(0)


# --- reference sketch -------------------------------------------------------------------------
def test_reference_protocol_decodes_counter_and_host_tare():
    with (
        virtual_scale(protocol="reference", rate_hz=40, load_g=0.0) as vs,
        HX711Scale(vs.port) as scale,
    ):
        assert scale.protocol == "reference"
        vs.load_g = 123.45
        reading = wait_fresh(scale)
        assert reading.grams == pytest.approx(123.45, abs=0.1)
        assert reading.device_ms is None
        readings = scale.drain()
        assert [r.seq for r in readings] == list(
            range(readings[0].seq, readings[0].seq + len(readings))
        )
        scale.tare()  # host-side: the reference sketch takes no commands
        assert vs.commands == []
        assert wait_fresh(scale).grams == pytest.approx(0.0, abs=0.1)
        vs.load_g = 123.45 + 100.0
        assert scale.calibrate(100.0) == pytest.approx(1.0, abs=0.005)
        with pytest.raises(ScaleError, match="needs the beadsight firmware"):
            scale.set_rate(80)


def test_reference_protocol_counts_lost_lines():
    with (
        virtual_scale(protocol="reference", rate_hz=40) as vs,
        HX711Scale(vs.port, protocol="reference") as scale,
    ):
        wait_fresh(scale)
        vs.drop_next(3)
        time.sleep(0.2)
        wait_fresh(scale)
        assert scale.dropped == 3


# --- protocol detection -------------------------------------------------------------------------
def test_detector_needs_more_than_one_number_line():
    detector = ProtocolDetector()
    assert detector.feed("1.23", 0) == (None, [])  # the tail of 'R,12,3456,1.23'
    assert detector.feed("R,13,3468,1.25", 1) == ("beadsight", [1])
    assert detector.dropped == "1.23"
    detector = ProtocolDetector()
    assert detector.feed("2.50", 0) == (None, [])  # the tail of '30012.50'
    assert detector.feed("40012.61", 1) == (None, [])
    assert detector.feed("50012.70", 2) == ("reference", [1, 2])  # the first may be partial
    detector = ProtocolDetector()
    assert detector.feed("start", 0) == ("reference", [0])
    with pytest.raises(ValueError, match="not a scale line"):
        ProtocolDetector().feed("\ufffd\ufffd", 0)


def test_beadsight_board_joined_mid_line_is_not_taken_for_the_reference():
    # a board that does not reset on connect: the first line is the tail of a reading
    with (
        virtual_scale(protocol="beadsight", rate_hz=80, reset_on_open=False) as vs,
        HX711Scale(vs.port) as scale,
    ):
        assert scale.protocol == "beadsight"
        vs.load_g = 250.0
        assert wait_fresh(scale).grams == pytest.approx(250.0, abs=0.2)
        assert scale.garbage_lines == 0 and scale.dropped == 0
        seqs = [r.seq for r in scale.drain()]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))


@pytest.mark.parametrize("seed", range(3))  # joins at different points of the counter cycle
def test_reference_sketch_joined_mid_line_decodes_without_false_losses(seed):
    with (
        virtual_scale(protocol="reference", rate_hz=40, reset_on_open=False, seed=seed) as vs,
        HX711Scale(vs.port) as scale,
    ):
        assert scale.protocol == "reference"
        vs.load_g = 123.45
        assert wait_fresh(scale).grams == pytest.approx(123.45, abs=0.1)
        assert scale.dropped == 0  # a partial first line decoded as a reading looks like losses
        assert scale.garbage_lines == 0


# --- faults ------------------------------------------------------------------------------------
def test_absent_port_hint():
    with pytest.raises(DeviceNotConnectedError) as err:
        HX711Scale("/dev/ttyACM97").connect()
    assert "/dev/ttyACM97" in str(err.value)
    assert "is the Arduino plugged in? ls /dev/ttyACM*" in str(err.value)


def test_silent_device_fails_connect_quickly():
    with virtual_scale(boot_delay_s=60.0) as vs:
        start = time.monotonic()
        with pytest.raises(DeviceTimeoutError, match="no readings within 0.5 s"):
            HX711Scale(vs.port, boot_timeout_s=0.5).connect()
        assert time.monotonic() - start < 2.0


def test_stopped_stream_times_out():
    with virtual_scale(protocol="beadsight") as vs, HX711Scale(vs.port) as scale:
        wait_fresh(scale)
        vs.stop_streaming()
        time.sleep(0.05)
        with pytest.raises(DeviceTimeoutError, match=f"scale {vs.port}: no reading for 0.3 s"):
            scale.wait_for_reading(0.3, after_mono=time.monotonic())


def test_unplugged_scale_keeps_buffer_then_raises():
    with virtual_scale(protocol="beadsight", rate_hz=80) as vs:
        scale = HX711Scale(vs.port)
        scale.connect()
        try:
            wait_fresh(scale)
            vs.unplug()
            time.sleep(0.3)
            buffered = scale.drain()
            assert len(buffered) > 0
            with pytest.raises(DeviceNotConnectedError, match="unplugged"):
                scale.drain()
            with pytest.raises(DeviceNotConnectedError):
                scale.wait_for_reading(0.2, after_mono=time.monotonic())
        finally:
            scale.close()


def test_bad_protocol_name():
    with pytest.raises(ValueError, match="protocol"):
        HX711Scale("/dev/ttyACM0", protocol="hx")
