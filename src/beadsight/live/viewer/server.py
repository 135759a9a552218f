"""The live web viewer: a stdlib HTTP server pushing updates to one static page over SSE.

Routes:

* ``GET /`` -- the page (``static/index.html``, self-contained).
* ``GET /api/config`` -- fixed settings: colour scale (``max_kpa`` and the 256-entry
  colour map), trace length, image size, checkpoint/source/backend names.
* ``GET /events`` -- Server-Sent Events; each ``data:`` line is one JSON state (below),
  sent at most ``max_fps`` times a second and at least every :data:`KEEPALIVE_S`.
* ``GET /api/state`` -- the same JSON once, without images (for scripts).
* ``POST /api/record`` with JSON ``{"action": "start" | "stop"}`` -- start/stop
  recording readings to a new HDF5 file in ``record_dir`` (a new name each time).

A state message: ``status`` (state, message), ``stats`` (rate, latency percentiles),
``reading`` (force, centre of pressure, contact area, ...; null before the first),
``frame`` / ``map`` (data: URLs of the camera frame (JPEG) and the colour-mapped kPa
map (PNG); only when a new reading came since the last message to this client),
``contours`` (contact outline polygons) and ``cop`` (marker position), both as
fractions of the image side, ``trace`` (new ``[t_s, force_n, reference_force_n]``
points since this client's previous message), ``recording`` and ``record_error`` (why
the last recording stopped by itself, e.g. a full disk; else null).

The viewer is a :class:`beadsight.live.sensor.LiveListener`: the sensing thread only stores a
reference to the newest update and appends one trace point; images are encoded at
most ``max_fps`` times a second, once for all clients, on the clients' threads. A slow
browser slows only its own stream.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import threading
import time
from collections import deque
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from beadsight.errors import BeadSightError
from beadsight.geometry import mm_to_px
from beadsight.live.recorder import unique_recording_path

logger = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"
DEFAULT_PORT = 8000
DEFAULT_HOST = "127.0.0.1"
DEFAULT_MAX_FPS = 20.0  # viewer updates per second, independent of the sensing rate
DEFAULT_MAX_KPA = 150.0  # top of the fixed colour scale (about an 18 N finger press)
DEFAULT_HISTORY_S = 10.0  # length of the force trace
KEEPALIVE_S = 0.5  # a state message goes out at least this often (the page's watchdog)
COLORMAP = cv2.COLORMAP_INFERNO
JPEG_QUALITY = 85
PNG_COMPRESSION = 1  # fast; maps compress well anyway
MAX_CONTOURS = 8  # largest contact outlines sent to the page
CONTOUR_EPSILON_PX = 0.75  # polygon simplification tolerance
MAX_REQUEST_BYTES = 4096


def colormap_bgr(levels: int = 256) -> np.ndarray:
    """(levels, 3) uint8 BGR colours of the fixed pressure scale (0 kPa first)."""
    ramp = np.arange(levels, dtype=np.uint8).reshape(-1, 1)
    return cv2.applyColorMap(ramp, COLORMAP).reshape(levels, 3)


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
    levels = len(lut_bgr) - 1
    index = np.clip(np.nan_to_num(pressure_kpa) * (levels / max_kpa), 0, levels)
    ok, buf = cv2.imencode(
        ".png", lut_bgr[index.astype(np.uint8)], [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION]
    )
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


class ViewerServer:
    """Serve the live viewer for ``sensor`` (a started :class:`beadsight.live.sensor.LiveSensor`).

    Binds ``host:port`` (port 0 = a free port) in the constructor and serves on a
    background thread until :meth:`close`. Registers itself as the sensor's listener.
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
    ):
        if not max_fps > 0:
            raise ValueError(f"max_fps must be > 0, got {max_fps}")
        if not max_kpa > 0:
            raise ValueError(f"max_kpa must be > 0, got {max_kpa}")
        self.sensor = sensor
        self.geometry = sensor.geometry
        self.max_fps = float(max_fps)
        self.max_kpa = float(max_kpa)
        self.history_s = float(history_s)
        self.record_dir = Path(record_dir)
        self._lut = colormap_bgr()
        self._cond = threading.Condition()
        self._closing = threading.Event()
        self._update: Any = None
        self._version = 0  # bumped per reading and per status change
        self._status = sensor.status
        self._trace: deque[tuple[float, float, float | None]] = deque()
        self._images: tuple[int, dict[str, Any]] = (-1, {})
        self._image_lock = threading.Lock()
        self._handlers: set[threading.Thread] = set()
        self._record_lock = threading.Lock()
        self._record_epoch = 0  # bumped by every start/stop from the page
        self._page = (STATIC_DIR / "index.html").read_bytes()
        try:
            self._httpd = _HTTPServer((host, port), _Handler, self)
        except OSError as e:
            raise BeadSightError(
                f"viewer: cannot listen on {host}:{port} ({e.strerror or e}); choose another "
                "port with --port"
            ) from None
        self.host, self.port = self._httpd.server_address[:2]
        self._thread = threading.Thread(
            target=self._httpd.serve_forever, name="viewer-http", daemon=True
        )
        self._thread.start()
        self._remove_listener = sensor.add_listener(self)
        logger.debug("viewer: %s", self.url)

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return f"http://{host}:{self.port}/"

    def close(self) -> None:
        """Stop serving; waits for every request thread to finish."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._remove_listener()
        with self._cond:
            self._cond.notify_all()
        self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join()
        for thread in list(self._handlers):
            thread.join()

    def __enter__(self) -> ViewerServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

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
            self._cond.notify_all()

    def status(self, status: Any) -> None:
        with self._cond:
            self._status = status
            self._version += 1
            self._cond.notify_all()

    def finish(self) -> None:
        self.status(self.sensor.status)

    # --- state messages --------------------------------------------------------------
    def _images_for(self, update: Any, version: int) -> dict[str, Any]:
        """Encoded images and overlays of ``update``, cached for all clients."""
        with self._image_lock:
            if self._images[0] == version:
                return self._images[1]
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
            self._images = (version, images)
            return images

    def state(self, since_t: float = -math.inf, images: bool = False) -> dict[str, Any]:
        """The current state as a JSON-able dict (see the module docstring)."""
        with self._cond:
            update, version, status = self._update, self._version, self._status
            trace = [p for p in self._trace if p[0] > since_t]
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
            "trace": [
                [round(t, 4), round(f, 4), None if g is None else round(g, 4)] for t, f, g in trace
            ],
            "reading": None,
        }
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
            if images:
                state.update(self._images_for(update, version))
        return state

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

    def record(self, action: str) -> dict[str, Any]:
        """Start/stop recording. The answer carries ``record_epoch``, bumped by every
        change, so the page ignores state messages built before the change."""
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

    # --- SSE loop (one per client, on the request's thread) ----------------------------
    def stream_events(self, write) -> None:
        """Write state messages with ``write(bytes)`` until the server closes or the
        client goes away (write raises OSError)."""
        me = threading.current_thread()
        self._handlers.add(me)
        try:
            min_interval = 1.0 / self.max_fps
            sent_version, since_t = -1, -math.inf
            while not self._closing.is_set():
                with self._cond:
                    self._cond.wait_for(
                        lambda seen=sent_version: self._version != seen or self._closing.is_set(),
                        KEEPALIVE_S,
                    )
                if self._closing.is_set():
                    return
                with self._cond:
                    version = self._version
                fresh = version != sent_version
                state = self.state(since_t, images=fresh)
                if state["trace"]:
                    since_t = state["trace"][-1][0]
                write(b"data: " + json.dumps(state, allow_nan=False).encode() + b"\n\n")
                sent_version = version
                # rate limit: at most max_fps messages; the sensor never waits for this
                if self._closing.wait(min_interval):
                    return
        finally:
            self._handlers.discard(me)


class _HTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address, handler, viewer: ViewerServer):
        self.viewer = viewer
        super().__init__(address, handler)


class _Handler(BaseHTTPRequestHandler):
    server: _HTTPServer
    protocol_version = "HTTP/1.0"  # one request per connection: no idle keep-alive threads

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - stdlib name
        logger.debug("viewer %s: " + format, self.address_string(), *args)

    def _send(self, status: int, body: bytes, content_type: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, obj: Any, status: int = HTTPStatus.OK) -> None:
        self._send(status, json.dumps(obj, allow_nan=False).encode(), "application/json")

    def do_GET(self) -> None:  # noqa: N802 - stdlib name
        viewer = self.server.viewer
        path = self.path.split("?", 1)[0]
        if path in ("/", "/index.html"):
            self._send(HTTPStatus.OK, viewer._page, "text/html; charset=utf-8")
        elif path == "/api/config":
            self._json(viewer.config())
        elif path == "/api/state":
            self._json(viewer.state())
        elif path == "/events":
            self._events(viewer)
        else:
            self._json({"error": f"no such page: {path}"}, HTTPStatus.NOT_FOUND)

    def _events(self, viewer: ViewerServer) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True

        def write(data: bytes) -> None:
            self.wfile.write(data)
            self.wfile.flush()

        try:
            viewer.stream_events(write)
        except OSError:  # the browser closed the page
            pass

    def do_POST(self) -> None:  # noqa: N802 - stdlib name
        viewer = self.server.viewer
        if self.path != "/api/record":
            self._json({"error": f"no such endpoint: {self.path}"}, HTTPStatus.NOT_FOUND)
            return
        # JSON only: a cross-site form cannot send it without a CORS preflight we refuse
        if self.headers.get("Content-Type", "").split(";")[0].strip() != "application/json":
            self._json(
                {"error": "expected Content-Type: application/json"},
                HTTPStatus.UNSUPPORTED_MEDIA_TYPE,
            )
            return
        length = int(self.headers.get("Content-Length") or 0)
        if length > MAX_REQUEST_BYTES:
            self._json({"error": "request too large"}, HTTPStatus.REQUEST_ENTITY_TOO_LARGE)
            return
        try:
            request = json.loads(self.rfile.read(length) or b"{}")
            self._json(viewer.record(str(request.get("action"))))
        except (ValueError, AttributeError) as e:
            self._json({"error": str(e)}, HTTPStatus.BAD_REQUEST)
        except (BeadSightError, OSError) as e:
            logger.error("viewer: record: %s", e)
            self._json({"error": str(e)}, HTTPStatus.INTERNAL_SERVER_ERROR)
