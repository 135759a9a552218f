"""Running a :class:`~beadsight.live.sensor.LiveSensor` from the command line: the viewer,
the stream, ROS 2 topics, the Foxglove server, a recording, periodic reports, until the
end, a duration or Ctrl-C."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

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
    sensor: LiveSensor,
    *,
    viewer: bool = True,
    host: str = "127.0.0.1",
    port: int = 8000,
    viewer_options: dict[str, Any] | None = None,
    stream_port: int | None = None,
    stream_options: dict[str, Any] | None = None,
    ros2: bool = False,
    ros2_options: dict[str, Any] | None = None,
    foxglove_port: int | None = None,
    foxglove_options: dict[str, Any] | None = None,
    output: str | Path | None = None,
    overwrite: bool = False,
    duration_s: float | None = None,
    report_every_s: float = 5.0,
    echo: Callable[[str], None] = print,
) -> LiveStats:
    """Run ``sensor`` with the viewer / stream / recording asked for, reporting stats every
    ``report_every_s``, until sensing ends (source end, ``max_readings``), ``duration_s``
    or Ctrl-C. With the viewer on, the end of sensing leaves the page up (showing "no
    signal") until Ctrl-C or ``duration_s``. The recording and the stream get every
    reading from the first. An existing ``output`` is refused unless ``overwrite``; a
    recording that fails (disk full) ends the run. Returns the final stats; re-raises the
    error that stopped sensing or the recording, if any.

    viewer_options: keyword arguments of :class:`~beadsight.live.viewer.server.ViewerServer`
    (max_fps, max_kpa, history_s, record_dir). stream_options: keyword arguments of
    :class:`~beadsight.live.stream.StreamServer` (max_age_s). ros2: publish ROS 2 topics
    with :class:`~beadsight.live.ros2.Ros2Publisher` (``ros2_options``: namespace,
    domain_id, camera). foxglove_port: serve Foxglove on ``host:foxglove_port`` with
    :class:`~beadsight.live.foxglove.FoxgloveServer` (``foxglove_options``: max_kpa,
    namespace). Both publish from their own threads (sensing never waits for them); a
    missing optional package is refused before the model loads.
    """
    wake, servers, publishers, failed = threading.Event(), [], [], threading.Event()
    kinds = _publisher_options(ros2, ros2_options, foxglove_port, foxglove_options)

    def recording_failed(error: BaseException) -> None:
        failed.set()
        wake.set()

    sensor.open()
    try:
        sensor.add_listener(_Wake(wake))
        if output is not None:
            path = sensor.start_recording(output, overwrite=overwrite, on_error=recording_failed)
            echo(f"recording to {path}")
        if stream_port is not None:
            from beadsight.live.stream import StreamServer

            servers.append(
                StreamServer(sensor.geometry, host, stream_port, **(stream_options or {}))
            )
            sensor.add_listener(servers[-1])
            echo(f"stream: tcp://{servers[-1].host}:{servers[-1].port} (see docs/live.md)")
        for kind, options in kinds:
            publishers.append(_start_publisher(kind, options, sensor, host, echo))
            sensor.add_listener(publishers[-1])
        if viewer:
            from beadsight.live.viewer.server import ViewerServer

            servers.append(ViewerServer(sensor, host, port, **(viewer_options or {})))
            echo(f"viewer: {servers[-1].url}")
        sensor.start()
        _wait(sensor, wake, viewer, duration_s, report_every_s, echo, failed)
    except KeyboardInterrupt:
        echo("interrupted: stopping")
    finally:
        _finish(sensor, servers, publishers, echo)
    stats = sensor.stats()
    echo(f"final: {stats.summary()}")
    if sensor.error is not None:
        raise sensor.error
    return stats


def _publisher_options(
    ros2: bool,
    ros2_options: dict[str, Any] | None,
    foxglove_port: int | None,
    foxglove_options: dict[str, Any] | None,
) -> list[tuple[str, dict[str, Any]]]:
    """The publishers asked for, as (kind, keyword arguments), checked now (packages
    installed, valid settings) so that a mistake is refused before the model loads."""
    kinds = []
    if ros2:
        from beadsight.live.ros2 import check_options

        kinds.append(("ros2", check_options(**(ros2_options or {}))))
    if foxglove_port is not None:
        from beadsight.live.foxglove import check_options

        kinds.append(("foxglove", check_options(port=foxglove_port, **(foxglove_options or {}))))
    return kinds


def _start_publisher(
    kind: str, options: dict[str, Any], sensor: LiveSensor, host: str, echo: Callable
) -> Any:
    if kind == "ros2":
        from beadsight.live.ros2 import Ros2Publisher

        publisher = Ros2Publisher(**options)
        echo(f"ros2: domain {publisher.domain_id}: {', '.join(publisher.topics())}")
        return publisher
    from beadsight.live.foxglove import FoxgloveServer

    server = FoxgloveServer(sensor.geometry, host, **options)
    echo(f"foxglove: {server.url} (layout: docs/foxglove-layout.json)")
    return server


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
            echo(
                f"{publisher.name}: published {publisher.published} readings, "
                f"dropped {publisher.dropped}"
            )


def _wait(sensor, wake, viewer, duration_s, report_every_s, echo, failed) -> None:
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
