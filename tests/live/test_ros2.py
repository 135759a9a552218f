"""ROS 2 over DDS (``beadsight live --ros2``), received by an independent subscriber in another
process (tests/live/ros2_peer.py: its own IDL types, ROS 2's QoS profiles) and decoded by
rosbags (an independent ROS 2 CDR decoder).

DDS stays on the loopback interface: every test runs in its own random ROS domain with a
Cyclone config (``CYCLONEDDS_URI``) that selects 127.0.0.1, turns multicast off and finds
peers by unicast on 127.0.0.1; each participant's Cyclone trace shows what it selected.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import re
import subprocess
import sys
import threading
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers.live import (
    BACKEND,
    press_frames,
    tiny_model,
    wait_until,
)
from helpers.publish import Health, HealthTagger, PacedSource, live_without

from beadsight.cli import main
from beadsight.errors import BeadSightError
from beadsight.live.ros import messages as msg
from beadsight.live.sensor import LiveSensor

pytestmark = pytest.mark.usefixtures("no_thread_leaks")  # every test stops its threads

PEER = Path(__file__).with_name("ros2_peer.py")
STAMP_TOLERANCE_S = 1e-6  # header stamps are integer ns; float64 unix s resolve ~0.24 us


class Peer:
    """tests/live/ros2_peer.py in its own process: subscribed once it prints ``ready``.

    Its output is read as it comes (a thread): a pipe left unread fills at 64 KB and
    would stall the peer mid-run, so that it misses messages it should have seen."""

    def __init__(self, domain: int, namespace: str = msg.DEFAULT_NAMESPACE, *extra: str):
        self.proc = subprocess.Popen(
            [sys.executable, str(PEER), str(domain), namespace, "60", *extra],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        first = self.proc.stdout.readline()
        assert json.loads(first or "{}").get("ready"), self.proc.stderr.read()
        self._lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self._lines.append(line)

    def messages(self, timeout_s: float = 60) -> dict[str, list[dict]]:
        """By topic, once the peer has seen the sensor end (and exited)."""
        self.proc.wait(timeout=timeout_s)
        self._reader.join(timeout_s)
        err = self.proc.stderr.read()
        assert self.proc.returncode == 0, err
        by_topic: dict[str, list[dict]] = {}
        for line in self._lines:
            m = json.loads(line)
            by_topic.setdefault(m.pop("topic"), []).append(m)
        return by_topic


def _row(times: np.ndarray, t: float) -> int:
    i = int(np.argmin(np.abs(times - t)))
    assert abs(times[i] - t) < STAMP_TOLERANCE_S, f"stamp {t} is no reading's capture time"
    return i


def _sha(array: np.ndarray, dtype: str) -> str:
    return hashlib.sha256(np.ascontiguousarray(array, dtype=dtype).tobytes()).hexdigest()


@pytest.mark.slow
def test_beadsight_live_ros2_reaches_an_independent_subscriber(dds, tmp_path, capsys):
    """`beadsight live --source sim --ros2`: every topic arrives at a subscriber in another
    process with values, units, frames and stamps of the readings the run recorded."""
    domain, _ = dds
    peer = Peer(domain)
    out = tmp_path / "readings.h5"
    # the command in this process (a child spent ~3 s importing torch); the subscriber is
    # the other process. --max-age 30: every reading must arrive, also when a loaded
    # machine stalls the publisher for over the default 0.5 s (the age rule has its own test).
    # Seed 75: the finger is down from about the 10th reading to the 45th (seed 0: the 55th
    # to the 80th), so 60 readings hold a press and the rest around it
    code = main(
        [
            *("live", "--source", "sim", "--seed", "75", "--no-viewer", "--frames", "60"),
            *("--max-age", "30"),
            *("--ros2", "--ros-domain", str(domain), "--output", str(out), "--backend", "torch"),
        ]
    )
    said = capsys.readouterr()
    said = said.out + said.err
    assert code == 0, said
    started = rf"ros2: domain {domain}: /beadsight/pressure, /beadsight/force.*; reads (\S+)"
    match = re.search(started, said)
    assert match and match.group(1) == "/beadsight/retake_rest", said
    got = peer.messages()
    with h5py.File(out) as f:
        t, force, cop = f["timestamp_s"][:], f["force_n"][:], f["cop_mm"][:]
        kpa, area, reference = (
            f["pressure_kpa"][:],
            f["contact_area_mm2"][:],
            f["reference_force_n"][:],
        )
    # in order, each reading once; keep-last QoS drops samples when the peer falls behind
    # (two shared cores), and the first ones may go before the peer is matched
    assert len(got["force"]) >= 0.8 * len(t)
    rows = [_row(t, m["t"]) for m in got["force"]]
    assert rows == sorted(set(rows)), f"missing {sorted(set(range(len(t))) - set(rows))}"
    for m, i in zip(got["force"], rows, strict=True):
        assert m["frame"] == msg.FRAME_ID
        assert m["force"] == pytest.approx([0, 0, force[i]], rel=1e-6, abs=1e-12)
        assert m["torque"] == [0, 0, 0]
    # the contact area, stamped with its reading's capture time: m^2 in vector.x
    assert len(got["contact_area"]) >= 0.8 * len(t)
    for m in got["contact_area"]:
        i = _row(t, m["t"])
        assert m["frame"] == msg.FRAME_ID
        assert m["vector"] == pytest.approx([area[i] * 1e-6, 0, 0], rel=1e-6, abs=1e-15)
    assert max(m["vector"][0] for m in got["contact_area"]) > 0
    for m in got["reference_force"]:
        assert m["force"][2] == pytest.approx(reference[_row(t, m["t"])])
    # the pressure image: 32FC1 little-endian kPa, bit for bit the recorded map
    assert len(got["pressure"]) >= 0.8 * len(t)
    for m in got["pressure"]:
        i = _row(t, m["t"])
        h, w = kpa.shape[1:]
        assert (m["enc"], m["h"], m["w"], m["step"], m["big"]) == ("32FC1", h, w, 4 * w, 0)
        assert m["frame"] == msg.FRAME_ID and m["len"] == h * w * 4
        assert m["sha"] == _sha(kpa[i], "<f4")
    # the centre of pressure in metres, only for readings that have one
    pressed = [i for i in rows if np.all(np.isfinite(cop[i]))]
    assert len(pressed) >= 10, "the simulated session should press within 60 readings"
    by_row = {_row(t, m["t"]): m for m in got["cop"]}
    assert set(by_row) <= set(np.flatnonzero(np.isfinite(cop[:, 0])))
    assert len(by_row) >= 0.8 * len(pressed)
    for i, m in by_row.items():
        assert m["frame"] == msg.FRAME_ID
        assert m["point"] == pytest.approx([cop[i, 0] * 1e-3, cop[i, 1] * 1e-3, 0.0], rel=1e-6)
    # the sensor's state on the health topic, ending with "ended" (level STALE)
    states = [m["status"][0]["values"]["state"] for m in got["health"]]
    assert "ok" in states and states[-1] == "ended"
    last = got["health"][-1]["status"][0]
    assert (last["name"], last["level"], last["hardware_id"]) == (
        msg.SENSOR_STATUS,
        msg.DIAGNOSTIC_STALE,
        msg.FRAME_ID,
    )
    assert "camera" not in got
    assert f"ros2: published {len(t)} readings, skipped 0" in said


# --- in process: health, camera, a namespace; the wire format ------------------------------
def test_health_camera_and_namespace_reach_the_subscriber(dds):
    from beadsight.live.outputs.ros2 import Ros2Publisher

    domain, _ = dds
    namespace = "/robot/left_finger"
    peer = Peer(domain, namespace, "--camera")
    frames, _ = press_frames(presses=2, per_press=30)
    sensor = LiveSensor(tiny_model(), PacedSource(frames, fps=60.0), **BACKEND)
    updates = []
    sensor.on_update(updates.append)
    sensor.open()
    publisher = Ros2Publisher(namespace, domain, camera=True, max_age_s=30, queue_size=64)
    assert publisher.topics()[f"{namespace}/camera"] == "sensor_msgs/msg/Image"
    wait_until(lambda: all(n == 1 for n in publisher.subscribers().values()), 20, "matching")
    sensor.add_listener(HealthTagger(publisher, total=len(frames) - sensor.model.span + 1))
    sensor.start()
    sensor.wait(30)
    sensor.stop()
    publisher.finish()
    got = peer.messages()
    assert (publisher.published, publisher.skipped, publisher.errors) == (len(updates), 0, 0)
    # the camera: rgb8, the model-input frames bit for bit
    by_time = {u.reading.timestamp_s: u for u in updates}
    assert len(got["camera"]) == len(updates)
    for m in got["camera"]:
        frame = by_time[min(by_time, key=lambda t: abs(t - m["t"]))].frame_rgb
        h, w, _ = frame.shape
        assert (m["enc"], m["h"], m["w"], m["step"]) == ("rgb8", h, w, 3 * w)
        assert m["sha"] == _sha(frame, np.uint8)
    # health: every change at once, with its level and figures (as text, NaN as "")
    health = [m["status"] for m in got["health"] if len(m["status"]) == 2]
    seen = [(s[1]["values"]["state"], s[1]["level"]) for s in health]
    assert [k for k, _ in itertools.groupby(seen)] == [
        ("ok", 0),
        ("drifting", 1),
        ("recalibrate", 2),
    ]
    for status in health:
        sensor_status, drift = status
        assert sensor_status["name"] == msg.SENSOR_STATUS
        assert drift["name"] == msg.HEALTH_STATUS and drift["hardware_id"] == msg.FRAME_ID
        assert drift["message"] == f"{drift['values']['state']}: see docs/live.md"
        assert float(drift["values"]["bead_shift_px"]) >= 0
        assert drift["values"]["force_offset_n"] == "" and drift["values"]["n"] == "3"
    assert got["health"][-1]["status"][0]["values"]["state"] == "ended"


def test_a_robot_asks_for_a_new_rest_reference_on_retake_rest(dds):
    from beadsight.live.outputs.ros2 import Ros2Publisher

    domain, _ = dds
    asked = threading.Event()
    publisher = Ros2Publisher(msg.DEFAULT_NAMESPACE, domain, on_retake_rest=asked.set)
    try:
        assert publisher.retake_topic == "/beadsight/retake_rest"
        peer = Peer(domain, msg.DEFAULT_NAMESPACE, "--retake")
        assert asked.wait(30), "the robot's message on /beadsight/retake_rest did not arrive"
        assert publisher.retake_requests == 1
        node = publisher.graph.info["node_entities_info_seq"][0]
        assert len(node["reader_gid_seq"]) == 1  # ROS tools see the node read the topic
        peer.proc.kill()
        peer.proc.wait()
    finally:
        publisher.finish()


def test_messages_decode_with_rosbags(dds):
    """The bytes our writers put on the wire (XCDR1, as ROS 2) decode with rosbags'
    ROS 2 type store into the values of the reading."""
    from rosbags.typesys import Stores, get_typestore

    from beadsight.live.outputs.ros2 import Ros2Publisher
    from beadsight.live.ros.types import TOPIC_TYPES, build_struct

    store = get_typestore(Stores.ROS2_HUMBLE)
    domain, _ = dds
    publisher = Ros2Publisher(domain_id=domain, camera=True)
    try:
        t = 1_700_000_000.125  # exact in binary
        kpa = np.random.default_rng(0).uniform(0, 50, (64, 64)).astype(np.float32)
        rgb = np.random.default_rng(1).integers(0, 256, (64, 64, 3), dtype=np.uint8)
        report = msg.health_report(None, Health("drifting", {"shift_px": 1.25}, "settle"), t)
        messages = {
            msg.PRESSURE: msg.image_message(kpa, t),
            msg.CAMERA: msg.camera_message(rgb, t),
            msg.FORCE: msg.wrench_message(3.5, t),
            msg.COP: msg.point_message(np.array([1.5, -2.0]), t),
            msg.CONTACT_AREA: msg.area_message(12.5, t),
            msg.HEALTH: msg.diagnostics_message(report),
        }
        decoded = {}
        for name, message in messages.items():
            writer, cls = publisher._writers[name]
            assert writer._use_version_2 is False  # XCDR1 (plain CDR), what ROS 2 speaks
            raw = build_struct(cls, message).serialize(use_version_2=writer._use_version_2)
            assert raw[:2] == b"\x00\x01"  # CDR little-endian encapsulation
            decoded[name] = store.deserialize_cdr(raw, TOPIC_TYPES[name])
    finally:
        publisher.finish()
    image = decoded[msg.PRESSURE]
    assert (image.header.stamp.sec, image.header.stamp.nanosec) == (1_700_000_000, 125_000_000)
    assert image.header.frame_id == "beadsight" and image.encoding == "32FC1"
    assert (image.height, image.width, image.step, image.is_bigendian) == (64, 64, 256, 0)
    assert np.array_equal(np.frombuffer(image.data.tobytes(), "<f4").reshape(64, 64), kpa)
    camera = decoded[msg.CAMERA]
    assert camera.encoding == "rgb8" and np.array_equal(camera.data.reshape(64, 64, 3), rgb)
    assert decoded[msg.FORCE].wrench.force.z == 3.5
    point = decoded[msg.COP].point
    assert (point.x, point.y, point.z) == pytest.approx((1.5e-3, -2.0e-3, 0.0))
    area = decoded[msg.CONTACT_AREA]
    assert (area.header.stamp.sec, area.header.stamp.nanosec) == (1_700_000_000, 125_000_000)
    assert area.header.frame_id == "beadsight"
    assert (area.vector.x, area.vector.y, area.vector.z) == pytest.approx((12.5e-6, 0.0, 0.0))
    sensor_status, drift = decoded[msg.HEALTH].status
    assert (sensor_status.name, drift.name, drift.level, drift.message) == (
        msg.SENSOR_STATUS,
        msg.HEALTH_STATUS,
        msg.DIAGNOSTIC_WARN,
        "settle",
    )
    assert {kv.key: kv.value for kv in drift.values} == {"state": "drifting", "shift_px": "1.25"}


# --- the command line: options, defaults, errors -----------------------------------------
def test_ros_domain_defaults_to_ros_domain_id(monkeypatch):
    from beadsight.live.outputs.ros2 import domain_from_environment

    assert domain_from_environment({}) == 0
    assert domain_from_environment({"ROS_DOMAIN_ID": " 42 "}) == 42
    for bad in ("abc", "233", "-1"):
        with pytest.raises(BeadSightError, match="ROS_DOMAIN_ID"):
            domain_from_environment({"ROS_DOMAIN_ID": bad})


@pytest.mark.parametrize(
    "args, env, error",
    [
        (["--ros-namespace", "beadsight"], {}, "ROS namespace 'beadsight': expected '/name'"),
        (["--ros-namespace", "/bead-sight"], {}, "ROS namespace '/bead-sight'"),
        (["--ros-domain", "500"], {}, "ROS domain id 500: expected 0..232"),
        ([], {"ROS_DOMAIN_ID": "x"}, "ROS_DOMAIN_ID='x': expected an integer"),
    ],
)
def test_bad_ros_options_are_one_line_errors_before_the_model_loads(
    args, env, error, capsys, monkeypatch
):
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    missing = Path("no-such-checkpoint.pt")  # never opened: the options are refused first
    code = main(["live", "--checkpoint", str(missing), "--no-viewer", "--ros2", *args])
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1
    assert error in err and "no-such-checkpoint" not in err


def test_missing_cyclonedds_names_the_extra(monkeypatch, capsys):
    assert live_without(monkeypatch, capsys, "cyclonedds", "--ros2") == [
        "beadsight live: error: --ros2 needs Cyclone DDS (the 'cyclonedds' package): "
        "pip install 'beadsight[ros]'"
    ]
