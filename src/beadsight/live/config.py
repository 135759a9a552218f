"""How ``beadsight live`` runs its outputs: the defaults and :class:`LiveRunConfig`, in one
light module (no numpy, no OpenCV) that the outputs and the command line both read, so
that ``beadsight live --help`` starts fast."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from beadsight.errors import ConfigError

DEFAULT_HOST = "127.0.0.1"  # the viewer and Foxglove answer this machine only by default
VIEWER_PORT = 8000
VIEWER_MAX_FPS = 20.0  # viewer updates per second, independent of the sensing rate
VIEWER_MAX_KPA = 150.0  # top of the fixed colour scale (about an 18 N finger press)
FOXGLOVE_PORT = 8765  # the Foxglove WebSocket server's usual port
FOXGLOVE_MAX_CLIENTS = 4  # Foxglove clients served at once (more are refused with 503)
MAX_AGE_S = 0.5  # an output never hands a client a reading older than this (the slow-client rule)
HEALTH_PERIOD_S = 1.0  # health is published and recorded this often while readings flow (ROS: 1 Hz)
ROS_NAMESPACE = "/beadsight"  # ROS 2 topics and Foxglove channels live under it
MAX_DOMAIN_ID = 232  # the highest ROS_DOMAIN_ID whose DDS ports fit (ROS 2 docs: Linux)
MAX_PORT = 65535
REPORT_EVERY_S = 5.0  # seconds between the rate/latency lines of `beadsight live`
MAX_REPORT_EVERY_S = 3600.0  # a longer report period is refused (a typo, not a wish)

_ROS_NAMESPACE = re.compile(r"^(/[A-Za-z][A-Za-z0-9_]*)+$")


def check_namespace(namespace: str) -> str:
    """A ROS 2 namespace as given (``/beadsight``, ``/robot/left_finger``); else an error."""
    if not isinstance(namespace, str) or not _ROS_NAMESPACE.match(namespace):
        raise ConfigError(
            f"ROS namespace {namespace!r}: expected '/name' or '/a/b' with each part starting "
            "with a letter, then letters, digits or '_' (e.g. /beadsight)"
        )
    return namespace


def check_domain(domain_id: int, where: str = "ROS domain id") -> int:
    """A ROS 2 domain id 0..:data:`MAX_DOMAIN_ID`; else an error naming ``where``."""
    if isinstance(domain_id, bool) or not isinstance(domain_id, int):
        raise ConfigError(f"{where} {domain_id!r}: expected an integer 0..{MAX_DOMAIN_ID}")
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise ConfigError(f"{where} {domain_id}: expected 0..{MAX_DOMAIN_ID}")
    return domain_id


def check_port(port: int, what: str) -> int:
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= MAX_PORT:
        raise ConfigError(f"{what} {port!r}: expected 0..{MAX_PORT} (0: any free port)")
    return port


_ORIGIN = re.compile(r"^https?://[A-Za-z0-9.\-\[\]:]+$")


def check_origins(origins: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """Browser origins as a browser sends them (``scheme://host[:port]``, no path)."""
    for origin in origins:
        if not isinstance(origin, str) or not _ORIGIN.match(origin):
            raise ConfigError(
                f"Foxglove allowed origin {origin!r}: expected scheme://host[:port] with no "
                "path, e.g. https://app.foxglove.dev"
            )
    return tuple(origins)


def check_count(value: int, what: str, upper: int = 1024) -> int:
    """An integer 1..``upper``; else an error naming ``what``."""
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= upper:
        raise ConfigError(f"{what} {value!r}: expected an integer 1..{upper}")
    return value


def check_positive(value: float, what: str, unit: str, upper: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{what} {value!r}: expected a number of {unit}")
    if not (math.isfinite(value) and 0 < value <= upper):
        bound = "" if upper == math.inf else f" and at most {upper:g}"
        raise ConfigError(f"{what} {value}: expected a finite number > 0{bound} {unit}")
    return float(value)


@dataclass(frozen=True)
class LiveRunConfig:
    """Everything :func:`beadsight.live.run.run_live` does beside sensing (checked when made).

    viewer, host, port: the web viewer on ``host:port`` (port 0: any free port); Foxglove
        listens on ``host`` too.
    max_fps: viewer updates per second. max_kpa: top of the colour scale of the viewer and
        of Foxglove's ``pressure_image``, kPa. record_dir: where the Record button writes.
    ros2, ros_domain, ros_namespace, ros_camera: publish ROS 2 topics in domain
        ``ros_domain`` under ``ros_namespace`` (also the Foxglove channels' namespace),
        with the camera frame if ``ros_camera``.
    foxglove, foxglove_port: serve Foxglove over WebSocket.
    foxglove_allow_origins: browser origins (``https://app.foxglove.dev``) accepted beside
        local pages; foxglove_max_clients: Foxglove clients served at once.
    max_age_s: the slow-client rule of ROS 2 and Foxglove: a reading older than this is
        skipped (and counted) instead of sent, s.
    output, overwrite: record every reading to ``output`` (.h5 or .mcap); an existing file
        is refused unless ``overwrite``.
    duration_s: stop after this many seconds (None: at the source's end or Ctrl-C).
    report_every_s: seconds between the printed rate/latency lines.
    """

    viewer: bool = True
    host: str = DEFAULT_HOST
    port: int = VIEWER_PORT
    max_fps: float = VIEWER_MAX_FPS
    max_kpa: float = VIEWER_MAX_KPA
    record_dir: Path = Path(".")
    ros2: bool = False
    ros_domain: int = 0
    ros_namespace: str = ROS_NAMESPACE
    ros_camera: bool = False
    foxglove: bool = False
    foxglove_port: int = FOXGLOVE_PORT
    foxglove_allow_origins: tuple[str, ...] = ()
    foxglove_max_clients: int = FOXGLOVE_MAX_CLIENTS
    max_age_s: float = MAX_AGE_S
    output: Path | None = None
    overwrite: bool = False
    duration_s: float | None = None
    report_every_s: float = REPORT_EVERY_S

    def __post_init__(self) -> None:
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        if not isinstance(self.host, str) or not self.host:
            raise ConfigError(f"live host {self.host!r}: expected an address such as 127.0.0.1")
        check_port(self.port, "viewer port")
        check_port(self.foxglove_port, "Foxglove port")
        if self.viewer and self.foxglove and self.port == self.foxglove_port != 0:
            raise ConfigError(
                f"viewer port and Foxglove port are both {self.port}: give them different ports"
            )
        set_("foxglove_allow_origins", check_origins(self.foxglove_allow_origins))
        check_count(self.foxglove_max_clients, "Foxglove max_clients")
        set_("max_fps", check_positive(self.max_fps, "viewer max_fps", "updates per second"))
        set_("max_kpa", check_positive(self.max_kpa, "max_kpa", "kPa"))
        set_("max_age_s", check_positive(self.max_age_s, "max_age_s", "s"))
        set_("record_dir", Path(self.record_dir))
        check_namespace(self.ros_namespace)
        check_domain(self.ros_domain)
        if self.output is not None:
            set_("output", Path(self.output))
        if self.duration_s is not None:
            set_("duration_s", check_positive(self.duration_s, "duration", "s"))
        set_(
            "report_every_s",
            check_positive(self.report_every_s, "report_every_s", "s", MAX_REPORT_EVERY_S),
        )
