"""A TCP stream of live readings on localhost, readable without beadsight (see docs/live.md).

Every message is one line of UTF-8 JSON (the header, ending in ``\\n``) followed by
exactly ``header["payload_bytes"]`` bytes of payload::

    {"type": "reading", ..., "height": 256, "width": 256, "payload_bytes": 262144}\\n
    <height * width little-endian float32: the pressure map in kPa, row-major>

Header ``type`` is ``"hello"`` (first message: protocol version, geometry),
``"reading"`` (one per reading), or ``"status"`` (state changes: ``ok``, ``no_signal``,
``ended``, ...; no payload). A client reads a line, parses it, reads ``payload_bytes``
bytes, and repeats. A client that reads slower than the sensor loses the oldest
messages (``"skipped"`` in the next reading header counts them); the sensor never waits
for a client.
"""

from __future__ import annotations

import json
import logging
import math
import socket
import threading
from collections import deque
from typing import Any

import numpy as np

from beadsight import __version__
from beadsight.config import SensorGeometry

logger = logging.getLogger(__name__)

PROTOCOL = "beadsight-stream"
PROTOCOL_VERSION = 1
DEFAULT_PORT = 8765
DEFAULT_HOST = "127.0.0.1"
CLIENT_QUEUE_SIZE = 8  # messages waiting per client before the oldest are dropped
ACCEPT_BACKLOG = 8
SEND_TIMEOUT_S = 5.0  # a client that accepts nothing for this long is disconnected
CLOSE_GRACE_S = 1.0  # on close, time a client gets to take its last messages


def _finite_or_none(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def encode_header(header: dict[str, Any], payload: bytes = b"") -> bytes:
    """One message: compact JSON header line (with payload_bytes) + payload."""
    header = {**header, "payload_bytes": len(payload)}
    return json.dumps(header, separators=(",", ":"), allow_nan=False).encode() + b"\n" + payload


def encode_reading(update: Any, seq: int, skipped: int = 0) -> bytes:
    """A ``reading`` message for a :class:`beadsight.live.sensor.LiveUpdate`."""
    r = update.reading
    kpa = np.ascontiguousarray(r.pressure_kpa, dtype="<f4")
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
        "height": int(kpa.shape[0]),
        "width": int(kpa.shape[1]),
        "dtype": "<f4",
        "unit": "kPa",
    }
    return encode_header(header, kpa.tobytes())


def encode_status(status: Any) -> bytes:
    return encode_header(
        {
            "type": "status",
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


class _Client:
    """One connection: a bounded outbox and a sender thread."""

    def __init__(self, sock: socket.socket, address: Any, hello: bytes, on_close):
        self.sock, self.address = sock, address
        self._outbox: deque[bytes] = deque([hello])
        self._cond = threading.Condition()
        self._closed = False
        self.skipped = 0  # readings dropped for this client since its last delivered one
        self._on_close = on_close
        sock.settimeout(SEND_TIMEOUT_S)
        self._thread = threading.Thread(target=self._run, name=f"stream-{address}", daemon=True)
        self._thread.start()

    def offer(self, message: bytes | None, make_reading=None) -> None:
        """Queue a message (or build a reading with the current skip count)."""
        with self._cond:
            if self._closed:
                return
            while len(self._outbox) >= CLIENT_QUEUE_SIZE:
                self._outbox.popleft()
                self.skipped += 1
            if make_reading is not None:
                message, self.skipped = make_reading(self.skipped), 0
            self._outbox.append(message)
            self._cond.notify()

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    self._cond.wait_for(lambda: self._outbox or self._closed)
                    if not self._outbox:
                        return
                    message = self._outbox.popleft()
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

    def close(self, final: bytes | None = None) -> None:
        """Send ``final`` (and what is queued), then close; waits for the sender."""
        with self._cond:
            if final is not None and not self._closed:
                self._outbox.append(final)
            self._closed = True
            self._cond.notify()
        self._thread.join(CLOSE_GRACE_S)
        if self._thread.is_alive():  # stalled client: cut it off
            self._shutdown_socket()
            self._thread.join()


class StreamServer:
    """Serve readings to TCP clients on ``host:port`` (port 0 = pick a free one).

    A :class:`beadsight.live.sensor.LiveListener`: ``sensor.add_listener(server)``. Encoding
    happens on the sensing thread only while clients are connected (about 0.1 ms for a
    256x256 map); sending happens on one thread per client.
    """

    def __init__(
        self, geometry: SensorGeometry, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT
    ):
        self.geometry = geometry
        self._hello = encode_hello(geometry)
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._seq = 0
        self._last_status: bytes | None = None
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
            with self._lock:
                if self._closed:
                    sock.close()
                    return
                hello = self._hello + (self._last_status or b"")
                self._clients.append(_Client(sock, address, hello, self._remove))
            logger.info("stream client %s connected", address)

    def _remove(self, client: _Client) -> None:
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)

    # --- listener interface ----------------------------------------------------------
    def push(self, update: Any) -> None:
        with self._lock:
            clients = list(self._clients)
            self._seq += 1
            seq = self._seq
        if not clients:
            return
        body: dict[int, bytes] = {}

        def make(skipped: int) -> bytes:  # one encoding shared by clients with equal skips
            if skipped not in body:
                body[skipped] = encode_reading(update, seq, skipped)
            return body[skipped]

        for client in clients:
            client.offer(None, make)

    def status(self, status: Any) -> None:
        message = encode_status(status)
        with self._lock:
            self._last_status = message
            clients = list(self._clients)
        for client in clients:
            client.offer(message)

    def finish(self) -> None:
        """Sensing ended: clients already got the final status; keep serving until close()."""

    def close(self) -> None:
        """Stop accepting, flush and close every client connection."""
        with self._lock:
            self._closed = True
            clients, self._clients = list(self._clients), []
        try:
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the blocked accept() on Linux
        except OSError:
            pass
        self._sock.close()
        self._thread.join()
        bye = encode_header({"type": "status", "state": "closed", "message": "server closed"})
        for client in clients:
            client.close(bye)

    def __enter__(self) -> StreamServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
