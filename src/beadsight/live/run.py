"""Running a :class:`~beadsight.live.sensor.LiveSensor` from the command line: the viewer,
ROS 2 topics, the Foxglove server, a recording, periodic reports, until the end, a
duration or Ctrl-C; what to run is one :class:`~beadsight.live.config.LiveRunConfig`."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

from beadsight.live.config import LiveRunConfig
from beadsight.live.listeners import LiveStatus, LiveUpdate
from beadsight.live.sensor import LiveSensor
from beadsight.live.stats import LiveStats


class _Wake:
    """A listener that wakes :func:`run_live` when sensing ends."""

    def __init__(self, event: threading.Event):
        self.event = event

    def push(self, update: LiveUpdate) -> None:
        pass

    def status(self, status: LiveStatus) -> None:
        pass

    def finish(self) -> None:
        self.event.set()


def run_live(
    sensor: LiveSensor, config: LiveRunConfig = LiveRunConfig(), echo: Callable[[str], None] = print
) -> LiveStats:
    """Run ``sensor`` with the outputs and recording ``config`` asks for, reporting stats
    every ``config.report_every_s``, until sensing ends (source end, ``max_readings``),
    ``config.duration_s`` or Ctrl-C. With the viewer on, the end of sensing leaves the page
    up (showing "no signal") until Ctrl-C or the duration. The recording gets every reading
    from the first; ROS 2 and Foxglove publish from their own threads under the slow-client
    rule (:class:`~beadsight.live.outputs.base.OutputListener`). An existing
    ``config.output`` is refused unless ``config.overwrite``; a recording that fails (disk
    full) ends the run. A missing optional package is refused before the model loads.
    Returns the final stats; re-raises the error that stopped sensing or the recording.
    """
    wake, servers, publishers, failed = threading.Event(), [], [], threading.Event()
    _require_packages(config)

    def recording_failed(error: BaseException) -> None:
        failed.set()
        wake.set()

    sensor.open()
    try:
        sensor.add_listener(_Wake(wake))
        if config.output is not None:
            path = sensor.start_recording(
                config.output, overwrite=config.overwrite, on_error=recording_failed
            )
            echo(f"recording to {path}")
        for publisher in _start_publishers(config, sensor, echo):
            publishers.append(publisher)
            sensor.add_listener(publisher)
        if config.viewer:
            from beadsight.live.outputs.viewer.server import ViewerServer

            servers.append(
                ViewerServer(
                    sensor,
                    config.host,
                    config.port,
                    max_fps=config.max_fps,
                    max_kpa=config.max_kpa,
                    record_dir=config.record_dir,
                )
            )
            echo(f"viewer: {servers[-1].url}")
        sensor.start()
        _wait(sensor, wake, config, echo, failed)
    except KeyboardInterrupt:
        echo("interrupted: stopping")
    finally:
        _finish(sensor, servers, publishers, echo)
    stats = sensor.stats()
    echo(f"final: {stats.summary()}")
    if sensor.error is not None:
        raise sensor.error
    return stats


def _require_packages(config: LiveRunConfig) -> None:
    """Refuse now (before the model loads) an output whose optional package is missing."""
    if config.ros2:
        from beadsight.live.outputs.ros2 import require_cyclonedds

        require_cyclonedds()
    if config.foxglove:
        from beadsight.live.outputs.foxglove import require_foxglove

        require_foxglove()


def _start_publishers(config: LiveRunConfig, sensor: LiveSensor, echo: Callable) -> list[Any]:
    started = []
    if config.ros2:
        from beadsight.live.outputs.ros2 import Ros2Publisher

        started.append(
            Ros2Publisher(
                config.ros_namespace,
                config.ros_domain,
                config.ros_camera,
                max_age_s=config.max_age_s,
                on_retake_rest=sensor.retake_rest if sensor.watch is not None else None,
            )
        )
        ros = started[-1]
        reads = f"; reads {ros.retake_topic}" if ros.on_retake_rest else ""
        echo(f"ros2: domain {config.ros_domain}: {', '.join(ros.topics())}{reads}")
    if config.foxglove:
        from beadsight.live.outputs.foxglove import FoxgloveServer

        started.append(
            FoxgloveServer(
                sensor.geometry,
                config.host,
                config.foxglove_port,
                config.ros_namespace,
                config.max_kpa,
                max_age_s=config.max_age_s,
                allowed_origins=config.foxglove_allow_origins,
                max_clients=config.foxglove_max_clients,
            )
        )
        echo(f"foxglove: {started[-1].url} (layout: docs/foxglove-layout.json)")
    return started


def _finish(
    sensor: LiveSensor, servers: list[Any], publishers: list[Any], echo: Callable[[str], None]
) -> None:
    """Close the servers, finish the recording (raising its error), stop the sensor, then
    let the publishers send what is left; safe to call twice."""
    try:
        while servers:
            servers.pop().close()
        recorded = sensor.stop_recording()
        if recorded is not None:
            echo(f"wrote {recorded}")
    finally:
        sensor.stop()  # the sensing thread's end finishes the publishers' queues
        while publishers:
            publisher = publishers.pop()
            publisher.finish()  # also when sensing never started
            to_clients = getattr(publisher, "client_skipped", None)
            echo(
                f"{publisher.name}: published {publisher.published} readings, "
                f"skipped {publisher.skipped}"
                + ("" if to_clients is None else f"; clients skipped {to_clients} messages")
            )


def _wait(sensor, wake, config: LiveRunConfig, echo, failed) -> None:
    viewer, duration_s, report_every_s = config.viewer, config.duration_s, config.report_every_s
    now = time.monotonic()
    deadline = math.inf if duration_s is None else now + duration_s
    next_report = now + report_every_s
    ended = False
    while now < deadline:
        wake.wait(min(next_report, deadline) - now)
        now = time.monotonic()
        if failed.is_set():  # the recording failed: its error ends the run
            return
        if wake.is_set() and not ended:  # sensing ended
            if not viewer or sensor.error is not None:
                return
            ended = True
            echo(
                f"{sensor.status.state}: {sensor.status.message}; the viewer stays up "
                "(Ctrl-C to quit)"
            )
        if ended:
            wake.clear()
        if now >= next_report:
            next_report += report_every_s * max(1, math.ceil((now - next_report) / report_every_s))
            echo(f"{sensor.status.state}: {sensor.stats().summary()}")
