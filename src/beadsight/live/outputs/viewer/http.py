"""The viewer's HTTP side: a small threaded server, hardened for a page on localhost.

* **Host check (DNS rebinding).** A web page on another site can make its own name
  resolve to 127.0.0.1 and then talk to the viewer as "same origin". Its requests still
  carry its name in ``Host``, so every request whose ``Host`` is not ``localhost``,
  ``127.0.0.1``, ``[::1]``, the address the viewer is bound to, an IP address (which no
  DNS name can stand for) or a name allowed explicitly is refused with 403.
* **Slow requests time out.** A request (line, headers and body) must arrive within
  ``request_timeout_s`` in all, however slowly it trickles in ("slowloris").
* **Bounded threads.** At most :data:`MAX_REQUEST_THREADS` requests are read at once; more
  connections are answered 503 at once. ``/events`` connections leave their thread as
  soon as their headers are sent (see :mod:`beadsight.live.outputs.viewer.events`).
* **Strict bodies.** A missing, malformed, conflicting or too large ``Content-Length``
  is answered 411/400/413; a body shorter than announced, 400.
"""

from __future__ import annotations

import io
import ipaddress
import json
import logging
import socket
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from beadsight.errors import BeadSightError

logger = logging.getLogger(__name__)

REQUEST_TIMEOUT_S = 5.0  # a whole request must arrive within this
WRITE_TIMEOUT_S = 5.0  # a response that the client does not take within this is dropped
MAX_REQUEST_THREADS = 32  # requests read at once; more connections get 503 at once
MAX_REQUEST_BYTES = 4096  # largest request body
ACCEPT_BACKLOG = 128  # connections the kernel holds before accept() (a page opens several)
LOCAL_HOSTS = frozenset({"localhost", "127.0.0.1", "::1"})
BUSY = (
    b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: application/json\r\n"
    b"Retry-After: 1\r\nContent-Length: 36\r\nConnection: close\r\n\r\n"
    b'{"error": "viewer busy, retry soon"}'
)


def host_name(header: str) -> str:
    """The host of a ``Host`` header, lower case, without port, brackets or final dot."""
    header = header.strip().lower()
    if header.startswith("["):
        return header[1 : header.find("]")] if "]" in header else header
    return header.rsplit(":", 1)[0].rstrip(".") if ":" in header else header.rstrip(".")


def host_allowed(header: str | None, allowed: frozenset[str]) -> bool:
    """Whether a request with this ``Host`` header may be served (None: no header, as from
    simple HTTP/1.0 scripts; browsers always send one)."""
    if header is None:
        return True
    name = host_name(header)
    if name in allowed:
        return True
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


class _DeadlineReader(io.RawIOBase):
    """Reads a socket, failing with TimeoutError once ``deadline`` (monotonic) has passed."""

    def __init__(self, sock: socket.socket, deadline: float):
        self._sock, self._deadline = sock, deadline

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        remaining = self._deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError("request not received in time")
        self._sock.settimeout(remaining)
        return self._sock.recv_into(buffer)


class ViewerHTTPServer(ThreadingHTTPServer):
    """Serves :class:`ViewerHandler` requests for ``viewer`` with a bounded thread count."""

    daemon_threads = False
    block_on_close = True  # server_close() waits for request threads (bounded by timeouts)
    allow_reuse_address = True
    request_queue_size = ACCEPT_BACKLOG

    def __init__(self, address, viewer: Any, allowed_hosts: frozenset[str]):
        self.viewer = viewer
        self.allowed_hosts = allowed_hosts
        self._slots = threading.BoundedSemaphore(MAX_REQUEST_THREADS)
        self._active: set[socket.socket] = set()
        self._handed_off: set[socket.socket] = set()
        self._lock = threading.Lock()
        super().__init__(address, ViewerHandler)

    def process_request(self, request, client_address) -> None:
        if not self._slots.acquire(blocking=False):
            request.setblocking(False)
            try:
                request.send(BUSY)
            except OSError:
                pass
            self.shutdown_request(request)
            return
        with self._lock:
            self._active.add(request)
        super().process_request(request, client_address)

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self._lock:
                self._active.discard(request)
            self._slots.release()

    def hand_off(self, request: socket.socket) -> None:
        """Keep ``request`` open after its handler returns (an event stream's)."""
        with self._lock:
            self._handed_off.add(request)

    def shutdown_request(self, request) -> None:
        with self._lock:
            if request in self._handed_off:
                self._handed_off.discard(request)
                return
        super().shutdown_request(request)

    def server_close(self) -> None:
        with self._lock:
            active = list(self._active)
        for sock in active:  # wake handlers blocked reading a request
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        super().server_close()


class ViewerHandler(BaseHTTPRequestHandler):
    """The viewer's routes (see :mod:`beadsight.live.outputs.viewer.server`)."""

    server: ViewerHTTPServer
    protocol_version = "HTTP/1.0"  # one request per connection: no idle keep-alive threads

    def setup(self) -> None:
        super().setup()
        deadline = time.monotonic() + self.server.viewer.request_timeout_s
        self.rfile = io.BufferedReader(_DeadlineReader(self.connection, deadline))

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - stdlib name
        logger.debug("viewer %s: " + format, self.address_string(), *args)

    def _send(self, status: int, body: bytes, content_type: str, **headers: str) -> None:
        self.connection.settimeout(WRITE_TIMEOUT_S)
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for name, value in headers.items():
            self.send_header(name.replace("_", "-"), value)
        self.end_headers()
        self.wfile.write(body)

    def _json(self, obj: Any, status: int = HTTPStatus.OK, **headers: str) -> None:
        self._send(status, json.dumps(obj, allow_nan=False).encode(), "application/json", **headers)

    def _host_ok(self) -> bool:
        host = self.headers.get("Host")
        if host_allowed(host, self.server.allowed_hosts):
            return True
        logger.warning("viewer: refused a request for host %r (DNS rebinding?)", host)
        self._json(
            {
                "error": f"host {host!r} is not served here; open the viewer as "
                f"http://127.0.0.1:{self.server.server_address[1]}/ (or allow the name)"
            },
            HTTPStatus.FORBIDDEN,
        )
        return False

    def do_GET(self) -> None:  # noqa: N802 - stdlib name
        if not self._host_ok():
            return
        viewer = self.server.viewer
        path = self.path.split("?", 1)[0]
        if path in ("/", "/index.html"):
            self._send(HTTPStatus.OK, viewer.page, "text/html; charset=utf-8")
        elif path == "/api/config":
            self._json(viewer.config())
        elif path == "/api/state":
            self._json(viewer.state())
        elif path == "/events":
            self._events(viewer)
        else:
            self._json({"error": f"no such page: {path}"}, HTTPStatus.NOT_FOUND)

    def _events(self, viewer: Any) -> None:
        events = viewer.events
        if not events.reserve():
            self._json(
                {"error": f"too many viewer connections ({events.max_clients}); close a tab"},
                HTTPStatus.SERVICE_UNAVAILABLE,
                Retry_After="2",
            )
            return
        try:
            self.connection.settimeout(WRITE_TIMEOUT_S)
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.send_header("Connection", "close")
            self.end_headers()
        except OSError:
            events.release()
            raise
        self.close_connection = True
        self.server.hand_off(self.connection)
        events.add(self.connection)

    def _body(self) -> bytes | None:
        """The request body, or None after answering a bad Content-Length."""
        if self.headers.get("Transfer-Encoding") is not None:
            self._json({"error": "send a Content-Length, not Transfer-Encoding"}, 400)
            return None
        values = {v.strip() for v in self.headers.get_all("Content-Length") or []}
        if not values:
            self._json({"error": "Content-Length is required"}, HTTPStatus.LENGTH_REQUIRED)
            return None
        value = values.pop()
        if values or not (value.isascii() and value.isdigit()):
            self._json({"error": "Content-Length must be one whole number of bytes"}, 400)
            return None
        length = int(value)
        if length > MAX_REQUEST_BYTES:
            self._json({"error": "request too large"}, HTTPStatus.REQUEST_ENTITY_TOO_LARGE)
            return None
        body = self.rfile.read(length)
        if len(body) != length:
            self._json({"error": "the body is shorter than its Content-Length"}, 400)
            return None
        return body

    def do_POST(self) -> None:  # noqa: N802 - stdlib name
        if not self._host_ok():
            return
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
        body = self._body()
        if body is None:
            return
        try:
            request = json.loads(body or b"{}")
            self._json(viewer.record(str(request.get("action"))))
        except (ValueError, AttributeError) as e:
            self._json({"error": str(e)}, HTTPStatus.BAD_REQUEST)
        except (BeadSightError, OSError) as e:
            logger.error("viewer: record: %s", e)
            self._json({"error": str(e)}, HTTPStatus.INTERNAL_SERVER_ERROR)
