"""The viewer's Server-Sent Events, served to every browser from one thread.

Each ``/events`` connection, once its request is answered, becomes a non-blocking socket
of one loop (:class:`EventBroadcaster`). At most ``max_fps`` times a second the loop
builds the state once (:class:`Snapshot`: JSON text shared by all clients) and sends each
client what is new for it: the state, the images when they changed since its last
message, and the force-trace points it has not seen. A client whose socket is full gets
nothing more until it has taken what it was given (its trace points wait for it); one
that takes nothing for :data:`STALLED_CLIENT_S` is disconnected. So the cost for the
sensing thread does not grow with the number of browsers, and the number is capped
(``max_clients``; more are answered 503 by the HTTP server).
"""

from __future__ import annotations

import bisect
import logging
import selectors
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

logger = logging.getLogger(__name__)

KEEPALIVE_S = 0.5  # a state message goes out at least this often (the page's watchdog)
STALLED_CLIENT_S = 10.0  # a browser that takes nothing for this long is disconnected
MAX_EVENT_CLIENTS = 16  # /events connections served at once (more are refused with 503)
RECV_BYTES = 4096


@dataclass(frozen=True)
class Snapshot:
    """The viewer state at one moment, as JSON text shared by all clients.

    version: bumped per reading and status change. common: the state's members except
    images and trace, as JSON object members without braces. images: the image members
    (same form) of this version, or None. trace_t: the trace points' times (ascending);
    trace: each point as a JSON array.
    """

    version: int
    common: bytes
    images: bytes | None
    trace_t: list[float]
    trace: list[bytes]


class _Client:
    __slots__ = ("sock", "pending", "since_t", "image_version", "sent_version", "sent_s", "stuck_s")

    def __init__(self, sock: socket.socket, now: float):
        self.sock = sock
        self.pending: memoryview | None = None  # the unsent end of the last message
        self.since_t = float("-inf")  # time of the last trace point sent
        self.image_version = -1  # version of the last images sent
        self.sent_version = -1
        self.sent_s = -float("inf")
        self.stuck_s = now  # since when the client has had pending bytes


def compose(client: _Client, snap: Snapshot) -> bytes:
    """The SSE message for ``client``: shared state, new images, new trace points."""
    start = bisect.bisect_right(snap.trace_t, client.since_t)
    parts = [b"data: {", snap.common]
    if snap.images is not None and client.image_version != snap.version:
        parts += [b",", snap.images]
        client.image_version = snap.version
    parts += [b',"trace":[', b",".join(snap.trace[start:]), b"]}\n\n"]
    if start < len(snap.trace_t):
        client.since_t = snap.trace_t[-1]
    return b"".join(parts)


class EventBroadcaster:
    """Send :class:`Snapshot` messages to event-stream sockets from one thread.

    snapshot(): builds the current state (called at most ``max_fps`` times a second).
    The HTTP handler calls :meth:`reserve` before answering a request, then :meth:`add`
    (or :meth:`release` if the answer failed).
    """

    def __init__(
        self,
        snapshot: Callable[[], Snapshot],
        max_fps: float,
        max_clients: int = MAX_EVENT_CLIENTS,
    ):
        if max_clients < 1:
            raise ValueError(f"max_clients must be >= 1, got {max_clients}")
        self._snapshot = snapshot
        self._interval_s = 1.0 / max_fps
        self.max_clients = max_clients
        self._lock = threading.Lock()
        self._reserved = 0
        self._new: list[socket.socket] = []
        self._clients: dict[socket.socket, _Client] = {}
        self._selector = selectors.DefaultSelector()
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, name="viewer-events", daemon=True)
        self._thread.start()

    @property
    def client_count(self) -> int:
        with self._lock:
            return self._reserved

    def reserve(self) -> bool:
        """Take one of the ``max_clients`` places; False if all are taken."""
        with self._lock:
            if self._reserved >= self.max_clients or self._closing.is_set():
                return False
            self._reserved += 1
            return True

    def release(self) -> None:
        with self._lock:
            self._reserved -= 1

    def add(self, sock: socket.socket) -> None:
        """Serve ``sock`` (its response headers sent) from now on; it is ours to close."""
        sock.setblocking(False)
        with self._lock:
            self._new.append(sock)

    def close(self) -> None:
        """Stop the loop and close every connection."""
        self._closing.set()
        self._thread.join()
        with self._lock:
            socks, self._new = [*self._clients, *self._new], []
            self._clients = {}
        for sock in socks:
            _close(sock)
        self._selector.close()

    # --- the loop (its own thread) ---------------------------------------------------
    def _run(self) -> None:
        next_tick = time.monotonic()
        while not self._closing.is_set():
            timeout = max(next_tick - time.monotonic(), 0.0)
            if self._clients:
                for key, mask in self._selector.select(timeout):
                    self._on_event(key.fileobj, mask)
            else:
                self._closing.wait(timeout)
            self._take_new()
            now = time.monotonic()
            if now >= next_tick:
                next_tick = max(next_tick + self._interval_s, now)
                if self._clients:
                    self._broadcast(now)

    def _take_new(self) -> None:
        with self._lock:
            new, self._new = self._new, []
        now = time.monotonic()
        for sock in new:
            self._clients[sock] = _Client(sock, now)
            self._selector.register(sock, selectors.EVENT_READ)

    def _drop(self, sock: socket.socket) -> None:
        if self._clients.pop(sock, None) is not None:
            self._selector.unregister(sock)
            _close(sock)
            self.release()

    def _on_event(self, sock, mask: int) -> None:
        if sock not in self._clients:
            return
        if mask & selectors.EVENT_READ:  # browsers send nothing more: EOF means gone
            try:
                if not sock.recv(RECV_BYTES):
                    return self._drop(sock)
            except BlockingIOError:
                pass
            except OSError:
                return self._drop(sock)
        if mask & selectors.EVENT_WRITE:
            self._send(self._clients[sock], None, time.monotonic())

    def _send(self, client: _Client, message: bytes | None, now: float) -> None:
        data = client.pending if message is None else memoryview(message)
        try:
            sent = client.sock.send(data)
        except BlockingIOError:
            sent = 0
        except OSError:
            return self._drop(client.sock)
        was_pending = client.pending is not None
        client.pending = data[sent:] if sent < len(data) else None
        if client.pending is None:
            if was_pending:
                self._selector.modify(client.sock, selectors.EVENT_READ)
        elif not was_pending:
            client.stuck_s = now
            self._selector.modify(client.sock, selectors.EVENT_READ | selectors.EVENT_WRITE)

    def _broadcast(self, now: float) -> None:
        try:
            snap = self._snapshot()
        except Exception:
            logger.exception("viewer: building the state failed")
            return
        for client in list(self._clients.values()):
            if client.pending is not None:
                if now - client.stuck_s > STALLED_CLIENT_S:
                    logger.info("viewer: dropping a browser that takes nothing")
                    self._drop(client.sock)
                continue
            if snap.version == client.sent_version and now - client.sent_s < KEEPALIVE_S:
                continue
            client.sent_version, client.sent_s = snap.version, now
            self._send(client, compose(client, snap), now)


def _close(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    sock.close()
