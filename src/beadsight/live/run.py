"""Running a :class:`~beadsight.live.sensor.LiveSensor` from the command line: the viewer,
the stream, a recording, periodic reports, until the end, a duration or Ctrl-C."""

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
    :class:`~beadsight.live.stream.StreamServer` (max_age_s).
    """
    wake, servers, failed = threading.Event(), [], threading.Event()

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
        if viewer:
            from beadsight.live.viewer.server import ViewerServer

            servers.append(ViewerServer(sensor, host, port, **(viewer_options or {})))
            echo(f"viewer: {servers[-1].url}")
        sensor.start()
        _wait(sensor, wake, viewer, duration_s, report_every_s, echo, failed)
    except KeyboardInterrupt:
        echo("interrupted: stopping")
    finally:
        _finish(sensor, servers, echo)
    stats = sensor.stats()
    echo(f"final: {stats.summary()}")
    if sensor.error is not None:
        raise sensor.error
    return stats


def _finish(sensor: LiveSensor, servers: list[Any], echo: Callable[[str], None]) -> None:
    """Close the servers, finish the recording (raising its error), stop the sensor; safe to
    call twice."""
    try:
        while servers:
            servers.pop().close()
        recorded = sensor.stop_recording()
        if recorded is not None:
            echo(f"wrote {recorded}")
    finally:
        sensor.stop()


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
