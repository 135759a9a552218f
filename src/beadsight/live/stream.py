"""A TCP stream of live readings on localhost, readable without beadsight (see docs/live.md).

Every message is one line of UTF-8 JSON (the header, ending in ``\\n``) followed by
exactly ``header["payload_bytes"]`` bytes of payload::

    {"type": "reading", ..., "height": 256, "width": 256, "payload_bytes": 262144}\\n
    <height * width little-endian float32: the pressure map in kPa, row-major>

Header ``type`` is ``"hello"`` (first message: protocol version, geometry),
``"reading"`` (one per reading), or ``"status"`` (state changes: ``ok``, ``no_signal``,
``ended``, ...; no payload). A client reads a line, parses it, reads ``payload_bytes``
bytes, and repeats.

Slow clients get fresh readings, not old ones: the sensor never waits for a client; each
client has a queue of at most :data:`CLIENT_QUEUE_SIZE` readings (the oldest is dropped)
and a socket send buffer of about one message; a reading is never sent more than
``max_age_s`` after it was produced. Readings are numbered (``seq``); every reading and
status message says how many readings this client missed since its previous message
(``skipped``), so that for consecutive messages ``a``, ``b`` of one client
``b.seq - a.seq - (1 if b is a reading else 0) == b.skipped``. Status messages are never
dropped: every client gets the final ``ended`` and ``closed``.
"""

from __future__ import annotations

import json
import logging
import math
import socket
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from beadsight import __version__
from beadsight.config import SensorGeometry
from beadsight.files import Closes
from beadsight.live.config import DEFAULT_HOST
from beadsight.live.config import STREAM_MAX_AGE_S as DEFAULT_MAX_AGE_S
from beadsight.live.config import STREAM_PORT as DEFAULT_PORT
from beadsight.live.ros_messages import health_report

logger = logging.getLogger(__name__)

PROTOCOL = "beadsight-stream"
PROTOCOL_VERSION = 1
CLIENT_QUEUE_SIZE = 2  # readings waiting per client; the oldest beyond this is dropped
HEADER_BYTES = 1024  # room for a message's header line (beside the map) in the send buffer
ACCEPT_BACKLOG = 8
SEND_TIMEOUT_S = 5.0  # a client that takes no message for this long is disconnected
CLOSE_GRACE_S = 2.0  # on close, time the clients (together) get to take their last messages


def _finite_or_none(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def encode_header(header: dict[str, Any], payload: bytes = b"") -> bytes:
    """One message: compact JSON header line (with payload_bytes) + payload."""
    header = {**header, "payload_bytes": len(payload)}
    return json.dumps(header, separators=(",", ":"), allow_nan=False).encode() + b"\n" + payload


def encode_reading(update: Any, seq: int, skipped: int = 0) -> bytes:
    """A ``reading`` message for a :class:`beadsight.live.listeners.LiveUpdate`."""
    return reading_header(update, seq, skipped) + map_payload(update)


def map_payload(update: Any) -> bytes:
    """The payload of a reading message: the map as little-endian float32, row-major."""
    return np.ascontiguousarray(update.reading.pressure_kpa, dtype="<f4").tobytes()


def _health(update: Any) -> dict[str, Any] | None:
    """The reading's health: state, message, figures (None where it is not tracked)."""
    health = getattr(update, "health", None)
    if health is None:
        return None
    report = health_report(None, health, float(update.reading.timestamp_s))
    return {k: report[k] for k in ("state", "message", "figures")}


def reading_header(update: Any, seq: int, skipped: int = 0) -> bytes:
    """The header line of a ``reading`` message (its payload is :func:`map_payload`)."""
    r = update.reading
    h, w = np.shape(r.pressure_kpa)
    cop = [float(v) for v in np.asarray(r.cop_mm).reshape(2)]
    header = {
        "type": "reading",
        "seq": seq,
        "skipped": skipped,
        "timestamp_s": float(r.timestamp_s),
        "frame_index": int(r.frame_index),
        "force_n": float(r.force_n),
        "cop_mm": cop if all(math.isfinite(v) for v in cop) else None,
        "has_contact": bool(r.has_contact),
        "contact_area_mm2": float(r.contact_area_mm2),
        "latency_s": float(update.latency_s),
        "inference_s": float(r.latency_s),
        "dropped_frames": int(r.dropped_frames),
        "reference_force_n": _finite_or_none(update.reference_force_n),
        "health": _health(update),
        "height": int(h),
        "width": int(w),
        "dtype": "<f4",
        "unit": "kPa",
        "payload_bytes": int(h) * int(w) * 4,
    }
    return json.dumps(header, separators=(",", ":"), allow_nan=False).encode() + b"\n"


def encode_status(status: Any, seq: int = 0, skipped: int = 0) -> bytes:
    """A ``status`` message; ``seq``: the number of the last reading produced before it."""
    return encode_header(
        {
            "type": "status",
            "seq": seq,
            "skipped": skipped,
            "state": status.state,
            "message": status.message,
            "since_s": status.since_s,
        }
    )


def encode_hello(geometry: SensorGeometry) -> bytes:
    return encode_header(
        {
            "type": "hello",
            "protocol": PROTOCOL,
            "version": PROTOCOL_VERSION,
            "beadsight_version": __version__,
            "image_size_px": geometry.image_size_px,
            "sensor_size_mm": geometry.sensor_size_mm,
            "mm_per_px": geometry.mm_per_px,
            "frame": "x, y mm from the sensor centre, printer frame; map row 0 = +y edge, "
            "column 0 = +x edge",
        }
    )


class _Reading:
    """One reading as every client sends it: numbered, timed, its map encoded once."""

    __slots__ = ("update", "seq", "produced_s", "_payload")

    def __init__(self, update: Any, seq: int):
        self.update, self.seq = update, seq
        self.produced_s = time.monotonic()
        self._payload: bytes | None = None

    def message(self, skipped: int) -> bytes:
        if self._payload is None:  # (two clients may both build it: same bytes)
            self._payload = map_payload(self.update)
        return reading_header(self.update, self.seq, skipped) + self._payload


class _Item:
    """A message waiting for one client: a reading, or a status (never dropped)."""

    __slots__ = ("reading", "status", "seq", "skipped")

    def __init__(self, seq: int, reading: _Reading | None = None, status: Any = None):
        self.reading, self.status, self.seq = reading, status, seq
        self.skipped = 0  # readings dropped just before this one

    def message(self, skipped: int) -> bytes:
        if self.reading is not None:
            return self.reading.message(skipped)
        return encode_status(self.status, self.seq, skipped)


class _Client:
    """One connection: a short queue and a sender thread that drops stale readings."""

    def __init__(self, sock: socket.socket, address: Any, first: list, max_age_s: float, on_close):
        self.sock, self.address = sock, address
        self.max_age_s = max_age_s
        self._outbox: deque[_Item | bytes] = deque(first)
        self._carry = 0  # readings dropped at the head, reported in the next message
        self._cond = threading.Condition()
        self._closed = False
        self.skipped = 0  # readings this client missed in all
        self._on_close = on_close
        sock.settimeout(SEND_TIMEOUT_S)
        self._thread = threading.Thread(target=self._run, name=f"stream-{address}", daemon=True)
        self._thread.start()

    def offer(self, item: _Item) -> None:
        """Queue a message; beyond CLIENT_QUEUE_SIZE readings the oldest one is dropped."""
        with self._cond:
            if self._closed:
                return
            if item.reading is not None:
                waiting = [i for i, x in enumerate(self._outbox) if getattr(x, "reading", None)]
                if len(waiting) >= CLIENT_QUEUE_SIZE:
                    first = waiting[0]
                    dropped = self._outbox[first]
                    del self._outbox[first]
                    after = self._outbox[first] if first < len(self._outbox) else item
                    after.skipped += dropped.skipped + 1
                    self.skipped += 1
            self._outbox.append(item)
            self._cond.notify()

    def _next(self) -> bytes | None:
        """The next message to send (None: closed and done); drops stale readings."""
        with self._cond:
            while True:
                self._cond.wait_for(lambda: self._outbox or self._closed)
                if not self._outbox:
                    return None
                item = self._outbox.popleft()
                if isinstance(item, bytes):
                    return item
                skipped, self._carry = item.skipped + self._carry, 0
                reading = item.reading
                if reading is not None and time.monotonic() - reading.produced_s > self.max_age_s:
                    self._carry, self.skipped = skipped + 1, self.skipped + 1
                    continue
                return item.message(skipped)

    def _run(self) -> None:
        try:
            while (message := self._next()) is not None:
                self.sock.sendall(message)
        except OSError as e:  # client went away or stalled
            logger.info("stream client %s disconnected (%s)", self.address, e)
        finally:
            self._shutdown_socket()
            self._on_close(self)

    def _shutdown_socket(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()

    def finish(self, final: _Item) -> None:
        """Send ``final`` after what is queued, then close (see :meth:`join`)."""
        with self._cond:
            if not self._closed:
                self._outbox.append(final)
            self._closed = True
            self._cond.notify()

    def join(self, timeout: float) -> None:
        """Wait for the last messages to go; cut a client off that does not take them."""
        self._thread.join(max(timeout, 0.0))
        if self._thread.is_alive():  # stalled client
            self._shutdown_socket()
            self._thread.join()


class StreamServer(Closes):
    """Serve readings to TCP clients on ``host:port`` (port 0 = pick a free one).

    A :class:`beadsight.live.listeners.LiveListener`: ``sensor.add_listener(server)``. The
    sensing thread only queues a reference per client; each client's thread encodes and
    sends (about 0.1 ms for a 256x256 map), never a reading older than ``max_age_s``
    (since it was produced; slow clients skip readings instead, see the module docstring).
    """

    def __init__(
        self,
        geometry: SensorGeometry,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        *,
        max_age_s: float = DEFAULT_MAX_AGE_S,
    ):
        if not max_age_s > 0:
            raise ValueError(f"stream: max_age_s must be > 0 s, got {max_age_s}")
        self.geometry = geometry
        self.max_age_s = float(max_age_s)
        self._hello = encode_hello(geometry)
        # SO_SNDBUF: the kernel doubles the value asked for (bookkeeping), so half a message
        # (map + header line) gives a send buffer that holds about one message
        self._send_buffer = (geometry.image_size_px**2 * 4 + HEADER_BYTES) // 2
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._seq = 0
        self._last_status: Any = None
        try:
            self._sock = socket.create_server((host, port), backlog=ACCEPT_BACKLOG)
        except OSError as e:
            from beadsight.errors import BeadSightError

            raise BeadSightError(
                f"stream: cannot listen on {host}:{port} ({e.strerror or e}); choose another "
                "port with --stream-port"
            ) from None
        self.host, self.port = self._sock.getsockname()[:2]
        self._closed = False
        self._thread = threading.Thread(target=self._accept, name="stream-accept", daemon=True)
        self._thread.start()
        logger.debug("stream: serving readings on tcp://%s:%d", self.host, self.port)

    @property
    def address(self) -> tuple[str, int]:
        return self.host, self.port

    @property
    def client_count(self) -> int:
        with self._lock:
            return len(self._clients)

    def _accept(self) -> None:
        while True:
            try:
                sock, address = self._sock.accept()
            except OSError:
                return  # the listening socket was closed
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self._send_buffer)
            with self._lock:
                if self._closed:
                    sock.close()
                    return
                first: list = [self._hello]
                if self._last_status is not None:
                    first.append(_Item(self._seq, status=self._last_status))
                client = _Client(sock, address, first, self.max_age_s, self._remove)
                self._clients.append(client)
            logger.info("stream client %s connected", address)

    def _remove(self, client: _Client) -> None:
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)

    # --- listener interface ----------------------------------------------------------
    def push(self, update: Any) -> None:
        with self._lock:
            self._seq += 1
            reading = _Reading(update, self._seq)
            clients = list(self._clients)
        for client in clients:
            client.offer(_Item(reading.seq, reading=reading))

    def status(self, status: Any) -> None:
        with self._lock:
            self._last_status = status
            seq, clients = self._seq, list(self._clients)
        for client in clients:
            client.offer(_Item(seq, status=status))

    def finish(self) -> None:
        """Sensing ended: clients already got the final status; keep serving until close()."""

    def close(self) -> None:
        """Stop accepting; send every client what is queued and a ``closed`` status, then
        close the connections (clients that take nothing for CLOSE_GRACE_S are cut off)."""
        with self._lock:
            self._closed = True
            clients, self._clients = list(self._clients), []
            bye = _Item(self._seq, status=_Closed())
        try:
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the blocked accept() on Linux
        except OSError:
            pass
        self._sock.close()
        self._thread.join()
        for client in clients:
            client.finish(bye)
        deadline = time.monotonic() + CLOSE_GRACE_S
        for client in clients:
            client.join(deadline - time.monotonic())


class _Closed:
    """The last status every client gets."""

    state, message, since_s = "closed", "server closed", None
