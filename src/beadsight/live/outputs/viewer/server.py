"""The live web viewer: a stdlib HTTP server pushing updates to one static page over SSE.

Routes:

* ``GET /`` -- the page (``static/index.html``, self-contained).
* ``GET /api/config`` -- fixed settings: colour scale (``max_kpa`` and the 256-entry
  colour map), trace length, image size, checkpoint/source/backend names.
* ``GET /events`` -- Server-Sent Events; each ``data:`` line is one JSON state (below),
  sent at most ``max_fps`` times a second and at least every :data:`KEEPALIVE_S`; at most
  ``max_clients`` at once (more are answered 503).
* ``GET /api/state`` -- the same JSON once, without images (for scripts).
* ``POST /api/record`` with JSON ``{"action": "start" | "stop"}`` -- start/stop
  recording readings to a new HDF5 file in ``record_dir`` (a new name each time).
* ``POST /api/rest`` with JSON ``{}`` -- take a new rest reference from the next still
  frames (the pouch is unloaded; :meth:`beadsight.live.sensor.LiveSensor.retake_rest`).

Requests for another ``Host`` than this machine's are refused (DNS rebinding); requests
are read by one event loop, so half-sent ones cost nothing and time out (see
:mod:`beadsight.live.outputs.viewer.http`).

A state message: ``status`` (state, message), ``stats`` (rate, latency percentiles),
``reading`` (force, centre of pressure, contact area, ...; null before the first),
``frame`` / ``map`` (data: URLs of the camera frame (JPEG) and the colour-mapped kPa
map (PNG); only when a new reading came since the last message to this client),
``contours`` (contact outline polygons) and ``cop`` (marker position), both as
fractions of the image side, ``rest`` (the rest reference's origin and frame time, and
whether a new one was asked for; null where none is kept), ``trace`` (new
``[t_s, force_n, reference_force_n]`` points since this client's previous message),
``recording`` and ``record_error`` (why the last recording stopped by itself, e.g. a
full disk; else null).

The viewer is a :class:`beadsight.live.listeners.LiveListener`: the sensing thread only stores a
reference to the newest update and appends one trace point. One thread serves every
browser (:mod:`beadsight.live.outputs.viewer.events`): it builds the state and encodes the
images at most ``max_fps`` times a second, once for all; a slow browser only misses
messages.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from beadsight.errors import BeadSightError, ConfigError
from beadsight.files import Closes
from beadsight.geometry import mm_to_px
from beadsight.live.config import DEFAULT_HOST
from beadsight.live.config import VIEWER_MAX_FPS as DEFAULT_MAX_FPS
from beadsight.live.config import VIEWER_MAX_KPA as DEFAULT_MAX_KPA
from beadsight.live.config import VIEWER_PORT as DEFAULT_PORT
from beadsight.live.outputs.colormap import colormap_bgr, colour_indices
from beadsight.live.outputs.viewer.events import (
    KEEPALIVE_S,
    MAX_EVENT_CLIENTS,
    EventBroadcaster,
    Snapshot,
)
from beadsight.live.outputs.viewer.http import LOCAL_HOSTS, REQUEST_TIMEOUT_S, ViewerHTTPServer
from beadsight.live.recording.partial import unique_recording_path
from beadsight.live.ros.messages import health_report

logger = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"
DEFAULT_HISTORY_S = 10.0  # length of the force trace
JPEG_QUALITY = 85
PNG_COMPRESSION = 1  # fast; maps compress well anyway
MAX_CONTOURS = 8  # largest contact outlines sent to the page
CONTOUR_EPSILON_PX = 0.75  # polygon simplification tolerance


def _data_url(kind: str, ok: bool, buf: np.ndarray) -> str | None:
    if not ok:
        return None
    return f"data:image/{kind};base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def encode_frame(frame_rgb: np.ndarray) -> str | None:
    """(S, S, 3) uint8 RGB -> JPEG data URL."""
    ok, buf = cv2.imencode(
        ".jpg", cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
    )
    return _data_url("jpeg", ok, buf)


def encode_map(pressure_kpa: np.ndarray, max_kpa: float, lut_bgr: np.ndarray) -> str | None:
    """(H, W) kPa -> PNG data URL on the fixed scale 0..max_kpa (values above saturate)."""
    index = colour_indices(pressure_kpa, max_kpa, len(lut_bgr))
    ok, buf = cv2.imencode(".png", lut_bgr[index], [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    return _data_url("png", ok, buf)


def contact_outlines(mask: np.ndarray) -> list[list[list[float]]]:
    """Outlines of a (H, W) bool mask: polygons of [x, y] as fractions of the side."""
    h, w = mask.shape
    contours, _ = cv2.findContours(
        mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
    )
    contours = sorted(contours, key=cv2.contourArea, reverse=True)[:MAX_CONTOURS]
    out = []
    for c in contours:
        poly = cv2.approxPolyDP(c, CONTOUR_EPSILON_PX, True).reshape(-1, 2).astype(np.float64)
        out.append([[round((x + 0.5) / w, 4), round((y + 0.5) / h, 4)] for x, y in poly])
    return out


def _finite(value: float, digits: int = 4) -> float | None:
    value = float(value)
    return round(value, digits) if math.isfinite(value) else None


def _ms(seconds: float) -> float | None:
    return _finite(seconds * 1e3, 2)


class ViewerServer(Closes):
    """Serve the live viewer for ``sensor`` (a started :class:`beadsight.live.sensor.LiveSensor`).

    Binds ``host:port`` (port 0 = a free port) in the constructor and serves on background
    threads until :meth:`close`. Registers itself as the sensor's listener.
    max_clients: browsers (``/events`` connections) served at once. allowed_hosts: names
    besides localhost, IP addresses and ``host`` under which the page may be opened.
    request_timeout_s: time a client has to send a whole request.
    """

    def __init__(
        self,
        sensor: Any,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        *,
        max_fps: float = DEFAULT_MAX_FPS,
        max_kpa: float = DEFAULT_MAX_KPA,
        history_s: float = DEFAULT_HISTORY_S,
        record_dir: str | Path = ".",
        max_clients: int = MAX_EVENT_CLIENTS,
        allowed_hosts: tuple[str, ...] = (),
        request_timeout_s: float = REQUEST_TIMEOUT_S,
    ):
        if not max_fps > 0:
            raise ConfigError(f"max_fps must be > 0, got {max_fps}")
        if not max_kpa > 0:
            raise ConfigError(f"max_kpa must be > 0, got {max_kpa}")
        if not request_timeout_s > 0:
            raise ConfigError(f"request_timeout_s must be > 0, got {request_timeout_s}")
        self.sensor = sensor
        self.geometry = sensor.geometry
        self.max_fps = float(max_fps)
        self.max_kpa = float(max_kpa)
        self.history_s = float(history_s)
        self.record_dir = Path(record_dir)
        self.request_timeout_s = float(request_timeout_s)
        self._lut = colormap_bgr()
        self._cond = threading.Condition()
        self._update: Any = None
        self._version = 0  # bumped per reading and per status change
        self._status = sensor.status
        self._trace: deque[tuple[float, float, float | None]] = deque()
        self._images: tuple[int, dict[str, Any], bytes] = (-1, {}, b"")
        self._image_lock = threading.Lock()
        self._record_lock = threading.Lock()
        self._record_epoch = 0  # bumped by every start/stop from the page
        self.page = (STATIC_DIR / "index.html").read_bytes()
        allowed = {h.lower() for h in (*LOCAL_HOSTS, host, *allowed_hosts)}
        try:
            self._httpd = ViewerHTTPServer((host, port), self, frozenset(allowed))
        except OSError as e:
            raise BeadSightError(
                f"viewer: cannot listen on {host}:{port} ({e.strerror or e}); choose another "
                "port with --port"
            ) from None
        self.host, self.port = self._httpd.server_address[:2]
        self.events = EventBroadcaster(self._snapshot, self.max_fps, max_clients)
        self._thread = threading.Thread(
            target=self._httpd.serve_forever, name="viewer-http", daemon=True
        )
        self._thread.start()
        self._remove_listener = sensor.add_listener(self)
        self._closed = False
        logger.debug("viewer: %s", self.url)

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return f"http://{host}:{self.port}/"

    def close(self) -> None:
        """Stop serving; closes every connection and waits for the server's threads."""
        if self._closed:
            return
        self._closed = True
        self._remove_listener()
        self._httpd.shutdown()
        self._thread.join()
        self.events.close()
        self._httpd.server_close()

    # --- listener interface (sensing thread: keep it cheap) -----------------------
    def push(self, update: Any) -> None:
        t = float(update.reading.timestamp_s)
        ref = update.reference_force_n
        with self._cond:
            self._update = update
            self._trace.append(
                (t, float(update.reading.force_n), ref if math.isfinite(ref) else None)
            )
            while self._trace and self._trace[0][0] < t - self.history_s:
                self._trace.popleft()
            self._version += 1

    def status(self, status: Any) -> None:
        with self._cond:
            self._status = status
            self._version += 1

    def finish(self) -> None:
        self.status(self.sensor.status)

    # --- state messages --------------------------------------------------------------
    def _images_for(self, update: Any, version: int) -> tuple[dict[str, Any], bytes]:
        """Encoded images and overlays of ``update`` (and as JSON members), cached."""
        with self._image_lock:
            if self._images[0] == version:
                return self._images[1], self._images[2]
            r = update.reading
            cop = np.asarray(r.cop_mm, dtype=np.float64)
            marker = None
            if np.all(np.isfinite(cop)):
                row, col = mm_to_px(cop, self.geometry.with_image_size(r.pressure_kpa.shape[-1]))
                s = r.pressure_kpa.shape[-1]
                marker = [round(float(col) / s, 4), round(float(row) / s, 4)]
            images = {
                "frame": encode_frame(update.frame_rgb),
                "map": encode_map(r.pressure_kpa, self.max_kpa, self._lut),
                "contours": contact_outlines(np.asarray(r.contact_mask)),
                "cop": marker,
            }
            members = json.dumps(images, allow_nan=False).encode()[1:-1]
            self._images = (version, images, members)
            return images, members

    def _common(self) -> tuple[dict[str, Any], Any, int, list]:
        """(state without trace and images, newest update, version, trace points)."""
        with self._cond:
            update, version, status = self._update, self._version, self._status
            trace = list(self._trace)
        stats = self.sensor.stats()
        record_epoch = self._record_epoch  # before reading the recording: see record()
        rec = self.sensor.recording
        state: dict[str, Any] = {
            "version": version,
            "server_time_s": time.time(),
            "record_epoch": record_epoch,
            "status": {
                "state": status.state,
                "message": status.message,
                "signal": status.has_signal,
            },
            "stats": {
                "rate_hz": _finite(stats.rate_hz, 2),
                "source_rate_hz": _finite(stats.source_rate_hz, 2),
                "latency_p50_ms": _ms(stats.latency_p50_s),
                "latency_p99_ms": _ms(stats.latency_p99_s),
                "inference_p50_ms": _ms(stats.inference_p50_s),
                "inference_p99_ms": _ms(stats.inference_p99_s),
                "readings": stats.readings,
                "skipped_frames": stats.skipped_frames,
                "dropped_frames": stats.dropped_frames,
            },
            "recording": None if rec is None else {"path": str(rec[0]), "readings": rec[1]},
            "record_error": self.sensor.recording_error,
            "reading": None,
            "health": None,
            "rest": self._rest(),
        }
        if update is not None and update.health is not None:
            state["health"] = health_report(status, update.health, time.time())
        if update is not None:
            r = update.reading
            cop = [float(v) for v in np.asarray(r.cop_mm).reshape(2)]
            state["reading"] = {
                "timestamp_s": float(r.timestamp_s),
                "frame_index": int(r.frame_index),
                "force_n": _finite(r.force_n),
                "reference_force_n": _finite(update.reference_force_n),
                "cop_mm": [_finite(v, 3) for v in cop] if all(map(math.isfinite, cop)) else None,
                "has_contact": bool(r.has_contact),
                "contact_area_mm2": _finite(r.contact_area_mm2, 2),
                "peak_kpa": _finite(float(np.max(r.pressure_kpa)), 2),
            }
        return state, update, version, trace

    @staticmethod
    def _point(t: float, f: float, g: float | None) -> list:
        return [round(t, 4), round(f, 4), None if g is None else round(g, 4)]

    def state(self, since_t: float = -math.inf, images: bool = False) -> dict[str, Any]:
        """The current state as a JSON-able dict (see the module docstring)."""
        state, update, version, trace = self._common()
        state["trace"] = [self._point(*p) for p in trace if p[0] > since_t]
        if images and update is not None:
            state.update(self._images_for(update, version)[0])
        return state

    def _snapshot(self) -> Snapshot:
        """The state as shared JSON text for the event stream (its own thread)."""
        state, update, version, trace = self._common()
        images = None if update is None else self._images_for(update, version)[1]
        return Snapshot(
            version=version,
            common=json.dumps(state, allow_nan=False).encode()[1:-1],
            images=images,
            trace_t=[p[0] for p in trace],
            trace=[json.dumps(self._point(*p)).encode() for p in trace],
        )

    def config(self) -> dict[str, Any]:
        sensor = self.sensor
        return {
            "max_kpa": self.max_kpa,
            "colormap": self._lut[:, ::-1].tolist(),  # RGB
            "history_s": self.history_s,
            "max_fps": self.max_fps,
            "keepalive_s": KEEPALIVE_S,
            "image_size_px": self.geometry.image_size_px,
            "sensor_size_mm": self.geometry.sensor_size_mm,
            "checkpoint": str(sensor.model.source) if sensor.model is not None else None,
            "source": sensor.source.name if sensor.source is not None else None,
            "backend": sensor.predictor.backend.describe() if sensor.predictor else None,
        }

    def _rest(self) -> dict[str, Any] | None:
        """The rest reference in use (None where the sensor keeps none)."""
        if self.sensor.watch is None:
            return None
        rest = self.sensor.rest
        return {
            "origin": None if rest is None else rest.origin,
            "taken_at_s": None if rest is None else _finite(rest.taken_at_s, 3),
            "requested": self.sensor.rest_requested,
        }

    def retake_rest(self) -> dict[str, Any]:
        """Ask the sensor for a new rest reference (:meth:`LiveSensor.retake_rest`)."""
        self.sensor.retake_rest()
        return {"rest": self._rest()}

    def record(self, action: str) -> dict[str, Any]:
        """Start/stop recording (each start to a new file). The answer carries
        ``record_epoch``, bumped by every change, so the page ignores state messages built
        before the change."""
        with self._record_lock:
            if action == "start":
                if self.sensor.recording is None:
                    self.sensor.start_recording(unique_recording_path(self.record_dir))
            elif action == "stop":
                self.sensor.stop_recording()
            else:
                raise ValueError(f"action must be 'start' or 'stop', got {action!r}")
            self._record_epoch += 1
            rec = self.sensor.recording
            return {
                "recording": None if rec is None else {"path": str(rec[0]), "readings": rec[1]},
                "record_epoch": self._record_epoch,
            }
