"""MCAP export with ROS 2 message types, checked with an independent MCAP reader."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from helpers.live import BACKEND, SPAN, ScriptedSource, press_frames, tiny_model

from beadsight.cli import main
from beadsight.live.recording.mcap import (
    TOPIC_CONTACT_AREA,
    TOPIC_COP,
    TOPIC_FORCE,
    TOPIC_HEALTH,
    TOPIC_PRESSURE,
    export_mcap,
)
from beadsight.live.recording.readings import ReadingsFileError, open_readings
from beadsight.live.ros.messages import FRAME_ID, SENSOR_STATUS
from beadsight.live.sensor import LiveSensor


def read_mcap(path) -> dict[str, list]:
    """topic -> [(schema name, log_time ns, decoded message)] with mcap's own reader."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert channel.message_encoding == "cdr"
            out.setdefault(channel.topic, []).append((schema.name, message.log_time, decoded))
    return out


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A readings file from a live run (presses and idle frames), and what was published."""
    frames, force = press_frames(presses=2, per_press=30)
    path = tmp_path_factory.mktemp("rec") / "readings.h5"
    seen = []
    sensor = LiveSensor(tiny_model(), ScriptedSource(frames, forces=force), **BACKEND).open()
    sensor.start_recording(path)  # before start(): every reading
    sensor.on_reading(seen.append)
    with sensor:
        assert sensor.wait(30)
    return path, seen


def check_messages(messages: dict[str, list], readings: list) -> None:
    assert len(messages[TOPIC_PRESSURE]) == len(messages[TOPIC_FORCE]) == len(readings)
    with_cop = [r for r in readings if np.all(np.isfinite(r.cop_mm))]
    assert len(messages.get(TOPIC_COP, [])) == len(with_cop)
    for r, (schema, log_ns, image) in zip(readings, messages[TOPIC_PRESSURE], strict=True):
        assert schema == "sensor_msgs/msg/Image"
        assert image.header.frame_id == FRAME_ID
        assert stamp_ns(image.header) == log_ns == round(Fraction(r.timestamp_s) * 10**9)
        assert (image.encoding, image.height, image.width) == ("32FC1", 64, 64)
        assert image.is_bigendian == 0 and image.step == 64 * 4
        kpa = np.frombuffer(bytes(image.data), "<f4").reshape(64, 64)
        np.testing.assert_array_equal(kpa, r.pressure_kpa)
    for r, (schema, log_ns, wrench) in zip(readings, messages[TOPIC_FORCE], strict=True):
        assert schema == "geometry_msgs/msg/WrenchStamped"
        assert stamp_ns(wrench.header) == log_ns == round(Fraction(r.timestamp_s) * 10**9)
        assert wrench.wrench.force.z == pytest.approx(r.force_n, rel=1e-6)
        assert (wrench.wrench.force.x, wrench.wrench.torque.z) == (0.0, 0.0)
    # the contact area: stamped with its reading's capture time, m^2 in vector.x
    areas = messages[TOPIC_CONTACT_AREA]
    assert len(areas) == len(readings)
    for r, (schema, log_ns, area) in zip(readings, areas, strict=True):
        assert schema == "geometry_msgs/msg/Vector3Stamped"
        assert area.header.frame_id == FRAME_ID
        assert stamp_ns(area.header) == log_ns == round(Fraction(r.timestamp_s) * 10**9)
        assert area.vector.x == pytest.approx(r.contact_area_mm2 * 1e-6, rel=1e-6, abs=1e-15)
        assert (area.vector.y, area.vector.z) == (0.0, 0.0)
    assert max(r.contact_area_mm2 for r in readings) > 0  # the presses made contact
    for r, (schema, _log, point) in zip(with_cop, messages.get(TOPIC_COP, []), strict=True):
        assert schema == "geometry_msgs/msg/PointStamped"
        assert point.header.frame_id == FRAME_ID
        assert stamp_ns(point.header) == round(Fraction(r.timestamp_s) * 10**9)
        # ROS uses metres
        assert point.point.x == pytest.approx(r.cop_mm[0] * 1e-3, rel=1e-5)
        assert point.point.y == pytest.approx(r.cop_mm[1] * 1e-3, rel=1e-5)
        assert point.point.z == 0.0


def test_readings_file_converts_to_ros2_mcap(recording, tmp_path):
    path, readings = recording
    out = export_mcap(path, tmp_path / "readings.mcap", progress=False)
    messages = read_mcap(out)
    check_messages(messages, readings)
    reference = messages["/beadsight/reference_force"]
    assert len(reference) == len(readings)
    with open_readings(path) as rf:
        np.testing.assert_allclose(
            [m[2].wrench.force.z for m in reference], rf.reference_force_n, rtol=1e-6
        )


def test_live_recording_straight_to_mcap(tmp_path):
    frames, _ = press_frames(presses=1, per_press=40, seed=2)
    out = tmp_path / "live.mcap"
    seen = []
    sensor = LiveSensor(tiny_model(scale_kpa=30.0), ScriptedSource(frames), **BACKEND).open()
    sensor.start_recording(out)
    sensor.on_reading(seen.append)
    with sensor:
        assert sensor.wait(30)
    assert not (tmp_path / "live.mcap.partial").exists()
    messages = read_mcap(out)
    assert len(seen) == len(frames) - SPAN + 1
    check_messages(messages, seen)
    assert "/beadsight/reference_force" not in messages  # the source knows no true force
    # the sensor's state, as on the ROS 2 health topic: at the first reading, on each change
    # and once a second of capture time, stamped with a reading's capture time
    health = messages[TOPIC_HEALTH]
    times = {round(Fraction(r.timestamp_s) * 10**9) for r in seen}
    assert 1 <= len(health) <= 2 + (seen[-1].timestamp_s - seen[0].timestamp_s)
    assert health[0][1] == round(Fraction(seen[0].timestamp_s) * 10**9)
    for schema, log_ns, array in health:
        assert schema == "diagnostic_msgs/msg/DiagnosticArray"
        assert stamp_ns(array.header) == log_ns and log_ns in times
        status = array.status[0]
        assert (status.name, status.hardware_id) == (SENSOR_STATUS, FRAME_ID)
        assert {kv.key: kv.value for kv in status.values}["state"] == "ok"


def test_cli_to_mcap(recording, tmp_path, capsys):
    path, readings = recording
    out = tmp_path / "cli.mcap"
    assert main(["to-mcap", str(path), "--out", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    check_messages(read_mcap(out), readings)


def test_cli_to_mcap_does_not_replace_a_file_unasked(recording, tmp_path, capsys):
    path, readings = recording
    out = tmp_path / "notes.mcap"
    out.write_bytes(b"someone's notes")
    assert main(["to-mcap", str(path), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "notes.mcap" in err[0] and "--overwrite" in err[0]
    assert out.read_bytes() == b"someone's notes"
    assert main(["to-mcap", str(path), "--out", str(out), "--overwrite"]) == 0
    check_messages(read_mcap(out), readings)


def test_to_mcap_bad_inputs_are_one_line_errors(make_dataset, recording, tmp_path, capsys):
    dataset = make_dataset()
    assert main(["to-mcap", str(dataset), "--out", str(tmp_path / "x.mcap")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "tiny.h5" in err[0] and "'format'" in err[0]
    assert not (tmp_path / "x.mcap").exists()
    with pytest.raises(ReadingsFileError, match="tiny.h5"):
        export_mcap(dataset, tmp_path / "y.mcap")
    path, _ = recording
    with pytest.raises(ValueError, match="overwrite its input"):
        export_mcap(path, path)


def test_nan_free_messages_for_frames_without_pressure(tmp_path):
    """An all-zero map has no centre of pressure: no PointStamped, force 0."""
    from types import SimpleNamespace

    from beadsight.config import SensorGeometry
    from beadsight.live.recording.mcap import McapReadingsWriter

    zero = SimpleNamespace(
        pressure_kpa=np.zeros((8, 8), np.float32),
        force_n=0.0,
        cop_mm=np.full(2, np.nan),
        has_contact=False,
        contact_area_mm2=0.0,
        timestamp_s=1.7e9,
        latency_s=0.01,
        frame_index=0,
    )
    with McapReadingsWriter(tmp_path / "z.mcap", SensorGeometry(image_size_px=8)) as w:
        w.append(zero)
    messages = read_mcap(tmp_path / "z.mcap")
    assert TOPIC_COP not in messages and TOPIC_HEALTH not in messages  # no report given
    assert messages[TOPIC_FORCE][0][2].wrench.force.z == 0.0
    assert not math.isnan(messages[TOPIC_FORCE][0][2].wrench.force.z)
