"""The viewer's HTTP side: one event loop reads every request, hardened for a page on localhost.

* **Host check (DNS rebinding).** A web page on another site can make its own name
  resolve to 127.0.0.1 and then talk to the viewer as "same origin". Its requests still
  carry its name in ``Host``, so every request whose ``Host`` is not ``localhost``,
  ``127.0.0.1``, ``[::1]``, the address the viewer is bound to, an IP address (which no
  DNS name can stand for) or a name allowed explicitly is refused with 403.
* **Half-sent requests cost nothing ("slowloris").** One thread (:class:`ViewerHTTPServer`)
  reads every connection's request from non-blocking sockets into a buffer; only a whole
  request (line, headers, and a body as long as its ``Content-Length``) is answered, on
  the same thread, from memory, and the answer is written without blocking. A request
  must arrive within ``request_timeout_s`` in all (else ``408`` and the connection is
  closed), and at most :data:`MAX_OPEN_CONNECTIONS` connections are open at once: a new
  one closes the oldest that has not sent its request yet, so a crowd of half-sent
  requests only ever pushes out its own oldest members, never a browser whose request
  arrives whole in a millisecond. ``/events`` connections leave this loop once their
  headers are sent (see :mod:`beadsight.live.outputs.viewer.events`).
* **Strict sizes.** Headers over :data:`MAX_HEADER_BYTES` are answered 431. A missing,
  malformed, conflicting or too large ``Content-Length`` is answered 411/400/413; a body
  shorter than announced, 400.
"""

from __future__ import annotations

import io
import ipaddress
import json
import logging
import re
import selectors
import socket
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler
from typing import Any

from beadsight.errors import BeadSightError

logger = logging.getLogger(__name__)

REQUEST_TIMEOUT_S = 5.0  # a whole request must arrive within this
WRITE_TIMEOUT_S = 5.0  # a response that the client does not take within this is dropped
MAX_OPEN_CONNECTIONS = 256  # connections read or answered at once; more close the oldest
MAX_HEADER_BYTES = 16 * 1024  # request line and headers
MAX_REQUEST_BYTES = 4096  # largest request body
ACCEPT_BACKLOG = 128  # connections the kernel holds before accept() (a page opens several)
RECV_BYTES = 65536
POLL_S = 0.25  # the loop looks at deadlines (and shutdown) at least this often
LOCAL_HOSTS = frozenset({"localhost", "127.0.0.1", "::1"})
_HEADER_END = re.compile(rb"\r?\n\r?\n")
_CONTENT_LENGTH = re.compile(rb"^content-length:[ \t]*([0-9]+)[ \t]*\r?$", re.I | re.M)


def _canned(status: HTTPStatus, error: str) -> bytes:
    body = json.dumps({"error": error}).encode()
    return (
        f"HTTP/1.0 {status.value} {status.phrase}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
    ).encode() + body


TIMED_OUT = _canned(HTTPStatus.REQUEST_TIMEOUT, "the request did not arrive in time")
HEADERS_TOO_LARGE = _canned(
    HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE, f"headers over {MAX_HEADER_BYTES} bytes"
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


def request_complete(data: bytes) -> bool | None:
    """Whether ``data`` holds a whole request: True, False (more to come), or None (headers
    too large). The body counts when its ``Content-Length`` is one whole number within
    :data:`MAX_REQUEST_BYTES`; anything else is answered by the handler at once."""
    end = _HEADER_END.search(data)
    if end is None:
        return None if len(data) > MAX_HEADER_BYTES else False
    if end.start() > MAX_HEADER_BYTES:
        return None
    lengths = set(_CONTENT_LENGTH.findall(data[: end.end()]))
    if len(lengths) != 1:
        return True
    length = int(lengths.pop())
    return length > MAX_REQUEST_BYTES or len(data) - end.end() >= length


class _Connection:
    """A connection of the loop: reading its request, then writing its answer."""

    __slots__ = ("sock", "address", "data", "deadline", "out", "reading")

    def __init__(self, sock: socket.socket, address: Any, deadline: float):
        self.sock, self.address, self.deadline = sock, address, deadline
        self.data = bytearray()
        self.out = memoryview(b"")
        self.reading = True


class ViewerHTTPServer:
    """Serves :class:`ViewerHandler` requests for ``viewer`` from one event loop.

    ``serve_forever()`` runs the loop (on the viewer's thread) until :meth:`shutdown`;
    :meth:`server_close` then closes every connection and the listening socket.
    """

    def __init__(self, address: tuple[str, int], viewer: Any, allowed_hosts: frozenset[str]):
        self.viewer = viewer
        self.allowed_hosts = allowed_hosts
        family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        self.socket = socket.socket(family, socket.SOCK_STREAM)
        try:
            self.socket.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.socket.bind(address)
            self.socket.listen(ACCEPT_BACKLOG)
        except OSError:
            self.socket.close()
            raise
        self.socket.setblocking(False)
        self.server_address = self.socket.getsockname()
        self._selector = selectors.DefaultSelector()
        self._selector.register(self.socket, selectors.EVENT_READ)
        self._open: dict[socket.socket, _Connection] = {}  # in order of arrival
        self._stop = threading.Event()
        self._stopped = threading.Event()
        self.evicted = 0  # half-sent requests closed to make room
        self.timed_out = 0  # requests that did not arrive in time

    @property
    def open_connections(self) -> int:
        return len(self._open)

    def serve_forever(self) -> None:
        try:
            while not self._stop.is_set():
                for key, mask in self._selector.select(POLL_S):
                    conn = self._open.get(key.fileobj)  # (None: closed earlier in this batch)
                    if key.fileobj is self.socket:
                        self._accept()
                    elif conn is not None and conn.reading:
                        self._read(conn)
                    elif conn is not None and mask & selectors.EVENT_WRITE:
                        self._write(conn)
                self._expire(time.monotonic())
        finally:
            self._stopped.set()

    def shutdown(self) -> None:
        self._stop.set()
        self._stopped.wait()

    def server_close(self) -> None:
        for conn in list(self._open.values()):
            self._close(conn)
        self._selector.close()
        self.socket.close()

    # --- the loop --------------------------------------------------------------------
    def _accept(self) -> None:
        for _ in range(ACCEPT_BACKLOG):
            try:
                sock, address = self.socket.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:  # out of file descriptors: leave it in the backlog
                logger.warning("viewer: cannot accept a connection (%s)", e)
                return
            if len(self._open) >= MAX_OPEN_CONNECTIONS:
                self._evict()
            sock.setblocking(False)
            deadline = time.monotonic() + self.viewer.request_timeout_s
            self._open[sock] = _Connection(sock, address, deadline)
            self._selector.register(sock, selectors.EVENT_READ)

    def _evict(self) -> None:
        """Close the oldest connection still sending its request (else the oldest)."""
        oldest = next((c for c in self._open.values() if c.reading), None)
        oldest = oldest or next(iter(self._open.values()))
        self.evicted += 1
        if self.evicted == 1 or self.evicted % 1000 == 0:
            logger.warning(
                "viewer: %d connections at once; closed %d half-sent requests (oldest first)",
                MAX_OPEN_CONNECTIONS,
                self.evicted,
            )
        self._close(oldest)

    def _read(self, conn: _Connection) -> None:
        try:
            chunk = conn.sock.recv(RECV_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return self._close(conn)
        conn.data += chunk
        complete = request_complete(bytes(conn.data))
        if complete is None:
            return self._answer(conn, HEADERS_TOO_LARGE)
        if complete or (not chunk and _HEADER_END.search(conn.data)):
            return self._handle(conn)  # whole, or ended early: the handler says what is wrong
        if not chunk:
            self._close(conn)

    def _handle(self, conn: _Connection) -> None:
        handler = ViewerHandler(conn.sock, conn.address, self, bytes(conn.data))
        if handler.events_headers is None:
            return self._answer(conn, handler.response)
        # an event stream: its headers go now (a fresh socket takes them), then the
        # broadcaster owns the socket
        events = self.viewer.events
        self._forget(conn)
        try:
            conn.sock.send(handler.events_headers)
        except OSError:
            events.release()
            return _close_socket(conn.sock)
        events.add(conn.sock)

    def _answer(self, conn: _Connection, response: bytes) -> None:
        conn.reading, conn.data = False, bytearray()
        conn.out = memoryview(response)
        conn.deadline = time.monotonic() + WRITE_TIMEOUT_S
        self._write(conn)

    def _write(self, conn: _Connection) -> None:
        try:
            sent = conn.sock.send(conn.out)
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError:
            return self._close(conn)
        conn.out = conn.out[sent:]
        if not conn.out:
            return self._close(conn)
        # the rest when the socket takes it; what the client sends now is not read
        self._selector.modify(conn.sock, selectors.EVENT_WRITE)

    def _expire(self, now: float) -> None:
        for conn in [c for c in self._open.values() if c.deadline <= now]:
            if conn.reading:  # the request did not arrive in time
                self.timed_out += 1
                logger.debug("viewer %s: request not received in time", conn.address[0])
                conn.deadline = now + WRITE_TIMEOUT_S
                self._answer(conn, TIMED_OUT)
            else:  # the client does not take its answer
                self._close(conn)

    def _forget(self, conn: _Connection) -> None:
        if self._open.pop(conn.sock, None) is not None:
            self._selector.unregister(conn.sock)

    def _close(self, conn: _Connection) -> None:
        self._forget(conn)
        _close_socket(conn.sock)


def _close_socket(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    sock.close()


class ViewerHandler(BaseHTTPRequestHandler):
    """The viewer's routes (see :mod:`beadsight.live.outputs.viewer.server`), for one whole
    request held in memory: the answer is collected in ``response`` (bytes), or, for an
    event stream, its headers in ``events_headers``."""

    server: ViewerHTTPServer
    protocol_version = "HTTP/1.0"  # one request per connection: no idle keep-alive

    def __init__(self, sock: socket.socket, address: Any, server: ViewerHTTPServer, data: bytes):
        self._data = data
        self.events_headers: bytes | None = None
        self.response = b""
        super().__init__(sock, address, server)

    def setup(self) -> None:
        self.connection = self.request
        self.rfile = io.BytesIO(self._data)
        self.wfile = io.BytesIO()

    def finish(self) -> None:
        self.response = self.wfile.getvalue()

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - stdlib name
        logger.debug("viewer %s: " + format, self.address_string(), *args)

    def _send(self, status: int, body: bytes, content_type: str, **headers: str) -> None:
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
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.events_headers = self.wfile.getvalue()  # the server sends them, then hands off

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
        if self.path not in ("/api/record", "/api/rest"):
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
            if self.path == "/api/rest":
                self._json(viewer.retake_rest())
            else:
                self._json(viewer.record(str(request.get("action"))))
        except (ValueError, AttributeError) as e:  # ConfigError is a ValueError too
            self._json({"error": str(e)}, HTTPStatus.BAD_REQUEST)
        except (BeadSightError, OSError) as e:
            logger.error("viewer: %s: %s", self.path, e)
            self._json({"error": str(e)}, HTTPStatus.INTERNAL_SERVER_ERROR)
