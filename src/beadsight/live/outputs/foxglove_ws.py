"""The Foxglove WebSocket protocol, served by beadsight on ``websockets`` (the ``ros`` extra).

Why not the Foxglove SDK's own server: it owns its client sockets, whose kernel send buffer
grows to megabytes, so a client that reads slowly got readings 5-7 s old, and it checks
neither the ``Origin`` of a browser's request nor how many clients connect. Here the SDK only
encodes (``foxglove.messages``) and gives the schemas; this module serves them:

* **Who may connect.** A request without ``Origin`` (a program, not a browser) or from a
  local page (``http(s)://localhost``, ``127.0.0.1``, ``[::1]``, any port) is accepted;
  another origin only where allowed by name (``--foxglove-allow-origin``), else ``403``. At
  most :data:`MAX_CLIENTS` clients at once (``503`` beyond). A client must offer one of
  :data:`SUBPROTOCOLS` (``400`` otherwise) and finish its handshake within
  :data:`OPEN_TIMEOUT_S`; what it sends is at most :data:`MAX_CLIENT_MESSAGE_BYTES`.
* **Pacing: credit by the client's pongs.** Each message is followed by a WebSocket ping,
  whose pong says the client has read it off its socket. A client may have as many
  messages awaiting their pong as it reads in :data:`CREDIT_S` at the rate its pongs
  came over the last second (at least one): a slow client one, a fast one more
  (docs/live.md measures it by round trip). Readings that arrive meanwhile replace the
  one waiting (counted in ``skipped``), and a reading older than ``max_age_s`` when its
  turn comes is skipped too. So nothing queues in the server or the kernel for a slow
  client. A client silent for :data:`PONG_TIMEOUT_S` is disconnected.
"""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import re
import struct
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any

from beadsight.errors import BeadSightError
from beadsight.live.config import FOXGLOVE_MAX_CLIENTS as MAX_CLIENTS
from beadsight.live.config import MAX_AGE_S

logger = logging.getLogger(__name__)

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")  # same ops for what we serve
OPEN_TIMEOUT_S = 5.0  # a client must finish its WebSocket handshake within this
PONG_TIMEOUT_S = 10.0  # a client that has not read its reading for this long is dropped
CREDIT_S = 0.1  # a client may have in flight as many frames as it reads in this time
RATE_S = 1.0  # ... at its rate of answers over this time
MAX_IN_FLIGHT = 8  # ... but never more (2 readings)
CLOSE_TIMEOUT_S = 1.0  # closing waits this long for a client's close frame
MAX_CLIENT_MESSAGE_BYTES = 64 * 1024  # subscribe/unsubscribe ops are far smaller
MAX_WAITING_OPS = 64  # status/health messages waiting for a slow client (oldest dropped)
START_TIMEOUT_S = 10.0
MESSAGE_DATA = 0x01  # binary opcode: u8 op, u32 subscription id, u64 log time ns, payload
STATUS_LEVELS = {"info": 0, "warning": 1, "error": 2}
_LOCAL_ORIGIN = re.compile(r"^https?://(localhost|127\.0\.0\.1|\[::1\])(:\d{1,5})?$")


def origin_allowed(origin: str | None, allowed: Sequence[str] = ()) -> bool:
    """No ``Origin`` (not a browser), a local page, or one named in ``allowed`` (exactly)."""
    return origin is None or bool(_LOCAL_ORIGIN.match(origin)) or origin in allowed


@dataclass(frozen=True)
class ChannelSpec:
    """One advertised channel: ``encoding`` of its messages (``protobuf``, ``json``), its
    schema's name, encoding (``protobuf``: a FileDescriptorSet; ``jsonschema``) and bytes."""

    topic: str
    encoding: str
    schema_name: str
    schema_encoding: str
    schema: bytes

    def advertised(self, channel_id: int) -> dict[str, Any]:
        text = self.schema_encoding in ("jsonschema", "ros2msg", "ros2idl", "omgidl")
        return {
            "id": channel_id,
            "topic": self.topic,
            "encoding": self.encoding,
            "schemaName": self.schema_name,
            "schemaEncoding": self.schema_encoding,
            "schema": self.schema.decode() if text else base64.b64encode(self.schema).decode(),
        }


class _Client:
    """One connection's state, on the event loop: its subscriptions; what waits for it in
    order (ops as text, messages as ``(channel, log_ns, payload, produced s or None)``);
    and the newest message of each reading channel not yet sent, ``channel -> (produced
    s, log_ns, payload)``, sent in turn (oldest waiting first)."""

    def __init__(self, ws: Any):
        self.ws = ws
        self.subscriptions: dict[int, int] = {}  # channel id -> the client's subscription id
        self.ordered: deque[Any] = deque(maxlen=MAX_WAITING_OPS)
        self.newest: dict[int, tuple[float, int, bytes]] = {}
        self.wake = asyncio.Event()
        self.skipped = 0  # reading messages not sent to this client (replaced, or too old)

    def offer_reading(self, produced_s: float, messages: list[tuple[int, int, bytes]]) -> None:
        for channel, log_ns, payload in messages:
            if channel in self.subscriptions:
                self.skipped += channel in self.newest
                self.newest[channel] = (produced_s, log_ns, payload)
        self.wake.set()

    def offer(self, item: Any) -> None:
        """An op (text), sent after the reading messages already waiting (so "ended"
        follows the last reading), or a message ``(channel, log_ns, payload)`` (health),
        sent in order with the ops and before the readings waiting: it moves none of them
        into the order, where newer readings could no longer replace them."""
        if isinstance(item, str):
            for channel, (produced_s, log_ns, payload) in self.newest.items():
                self.ordered.append((channel, log_ns, payload, produced_s))
            self.newest.clear()
        self.ordered.append(item if isinstance(item, str) else (*item, None))
        self.wake.set()

    def _message(self, channel: int, log_ns: int, payload: bytes) -> bytes | None:
        sub = self.subscriptions.get(channel)
        if sub is None:
            return None
        return struct.pack("<BIQ", MESSAGE_DATA, sub, log_ns) + payload

    def next_frame(self, max_age_s: float) -> str | bytes | None:
        """The next WebSocket frame to send: ops and ordered messages first, then the
        oldest-waiting reading channel's newest message (skipped if older than
        ``max_age_s``); None when nothing waits."""
        while self.ordered:
            item = self.ordered.popleft()
            if isinstance(item, str):
                return item
            channel, log_ns, payload, produced_s = item
            frame = self._message(channel, log_ns, payload)
            if produced_s is not None and time.monotonic() - produced_s > max_age_s:
                self.skipped += frame is not None
            elif frame is not None:
                return frame
        while self.newest:
            channel = next(iter(self.newest))  # dicts keep insertion order: oldest first
            produced_s, log_ns, payload = self.newest.pop(channel)
            frame = self._message(channel, log_ns, payload)
            if frame is not None and time.monotonic() - produced_s <= max_age_s:
                return frame
            self.skipped += frame is not None
        return None


class FoxgloveWebSocket:
    """A Foxglove WebSocket server on ``host:port`` (port 0: any free port, see
    :attr:`port`), on its own thread and event loop; the methods may be called from any
    thread. ``channels`` are advertised with ids 1, 2, ... in order; ``allowed_origins``
    are browser origins accepted beside local pages."""

    def __init__(
        self,
        name: str,
        host: str,
        port: int,
        channels: Sequence[ChannelSpec],
        *,
        allowed_origins: Sequence[str] = (),
        max_clients: int = MAX_CLIENTS,
        max_age_s: float = MAX_AGE_S,
    ):
        self.name, self.channels = name, list(channels)
        self.allowed_origins = tuple(allowed_origins)
        self.max_clients, self.max_age_s = max_clients, max_age_s
        self.refused: dict[int, int] = {}  # HTTP status -> requests refused with it
        self._clients: set[_Client] = set()
        self._lock = threading.Lock()  # guards the counts read from other threads
        self._counts = {c.topic: 0 for c in self.channels}
        self._gone_skipped = 0
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name="beadsight-foxglove-ws", daemon=True
        )
        self._thread.start()
        try:
            future = asyncio.run_coroutine_threadsafe(self._start(host, port), self._loop)
            self._server = future.result(START_TIMEOUT_S)
        except Exception as e:
            self._stop_loop()
            raise BeadSightError(f"Foxglove server on {host}:{port}: {e}") from e
        self.host, self.port = host, self._server.sockets[0].getsockname()[1]

    async def _start(self, host: str, port: int) -> Any:
        from websockets.asyncio.server import serve

        return await serve(
            self._handler,
            host,
            port,
            subprotocols=list(SUBPROTOCOLS),
            process_request=self._check_request,
            compression=None,
            open_timeout=OPEN_TIMEOUT_S,
            ping_interval=None,  # the pacing pings after every frame
            close_timeout=CLOSE_TIMEOUT_S,
            max_size=MAX_CLIENT_MESSAGE_BYTES,
            server_header=None,
        )

    # --- the handshake --------------------------------------------------------------------
    def _refuse(self, connection: Any, status: HTTPStatus, text: str) -> Any:
        self.refused[status.value] = self.refused.get(status.value, 0) + 1
        return connection.respond(status, text + "\n")

    def _check_request(self, connection: Any, request: Any) -> Any:
        origin = request.headers.get("Origin")
        if not origin_allowed(origin, self.allowed_origins):
            logger.warning(
                "foxglove: refused a client from origin %s (allow it with "
                "--foxglove-allow-origin %s)",
                origin,
                origin,
            )
            return self._refuse(
                connection,
                HTTPStatus.FORBIDDEN,
                f"origin {origin} is not allowed: beadsight accepts local pages only, and "
                "origins named with --foxglove-allow-origin",
            )
        offered = [
            p.strip()
            for h in request.headers.get_all("Sec-WebSocket-Protocol")
            for p in h.split(",")
        ]
        if not set(offered) & set(SUBPROTOCOLS):
            return self._refuse(
                connection,
                HTTPStatus.BAD_REQUEST,
                f"expected the WebSocket subprotocol {' or '.join(SUBPROTOCOLS)}, got "
                f"{', '.join(offered) or 'none'}",
            )
        if len(self._clients) >= self.max_clients:
            return self._refuse(
                connection,
                HTTPStatus.SERVICE_UNAVAILABLE,
                f"at most {self.max_clients} Foxglove clients at once (--foxglove-max-clients)",
            )
        return None

    # --- one client -----------------------------------------------------------------------
    async def _handler(self, ws: Any) -> None:
        if len(self._clients) >= self.max_clients:  # handshakes that raced past the check
            self.refused[1013] = self.refused.get(1013, 0) + 1
            await ws.close(1013, f"at most {self.max_clients} clients")
            return
        client = _Client(ws)
        self._clients.add(client)
        info = {"op": "serverInfo", "name": self.name, "capabilities": [], "metadata": {}}
        adverts = [c.advertised(i) for i, c in enumerate(self.channels, 1)]
        client.offer(json.dumps(info))
        client.offer(json.dumps({"op": "advertise", "channels": adverts}))
        sender = asyncio.create_task(self._send_loop(client))
        try:
            async for text in ws:
                if isinstance(text, str):
                    self._client_op(client, text)
        except Exception as e:  # a closed or misbehaving connection ends this client only
            logger.debug("foxglove: client %s: %s", ws.remote_address, e)
        finally:
            sender.cancel()
            self._clients.discard(client)
            self._set_subscriptions(client, {})
            with self._lock:
                self._gone_skipped += client.skipped

    def _client_op(self, client: _Client, text: str) -> None:
        try:
            op = json.loads(text)
            subs = dict(client.subscriptions)
            if op.get("op") == "subscribe":
                for s in op["subscriptions"]:
                    if 1 <= int(s["channelId"]) <= len(self.channels):
                        subs[int(s["channelId"])] = int(s["id"])
            elif op.get("op") == "unsubscribe":
                gone = {int(i) for i in op["subscriptionIds"]}
                subs = {c: s for c, s in subs.items() if s not in gone}
        except (ValueError, KeyError, TypeError, AttributeError):
            logger.debug("foxglove: ignored a malformed client op %.200r", text)
            return
        self._set_subscriptions(client, subs)

    def _set_subscriptions(self, client: _Client, subs: dict[int, int]) -> None:
        with self._lock:
            for channel in client.subscriptions:
                self._counts[self.channels[channel - 1].topic] -= 1
            for channel in subs:
                self._counts[self.channels[channel - 1].topic] += 1
        client.subscriptions = subs

    async def _send_loop(self, client: _Client) -> None:
        """Send one frame at a time, each followed by a ping. A client may have as many
        frames awaiting their pong as it answers in :data:`CREDIT_S`, at its rate over the
        last :data:`RATE_S` (at least one, at most :data:`MAX_IN_FLIGHT`). The rate, not
        how fast one pong came: a client library answers the pings of every frame it takes
        off the socket at once, however slowly its application reads them. With nothing
        to send it waits for a reading or the oldest pong, whichever comes first."""
        in_flight: deque[Any] = deque()  # pong waiters, oldest first
        answered: deque[float] = deque()  # when each pong of the last RATE_S came

        def window() -> int:
            while answered and answered[0] < time.monotonic() - RATE_S:
                answered.popleft()
            return min(max(int(len(answered) * CREDIT_S / RATE_S), 1), MAX_IN_FLIGHT)

        async def pong() -> None:
            await asyncio.wait_for(in_flight.popleft(), PONG_TIMEOUT_S)
            answered.append(time.monotonic())

        try:
            while True:
                while len(in_flight) >= window():
                    await pong()
                frame = client.next_frame(self.max_age_s)
                if frame is None:  # wait for a reading, or for the oldest pong
                    client.wake.clear()
                    woken = asyncio.ensure_future(client.wake.wait())
                    waits = (woken, in_flight[0]) if in_flight else (woken,)
                    try:
                        await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
                    finally:
                        woken.cancel()
                    if in_flight and in_flight[0].done():
                        await pong()
                    continue
                await asyncio.wait_for(client.ws.send(frame), PONG_TIMEOUT_S)
                in_flight.append(await client.ws.ping())
        except TimeoutError:
            logger.warning(
                "foxglove: client %s read nothing for %.0f s: disconnected",
                client.ws.remote_address,
                PONG_TIMEOUT_S,
            )
            await client.ws.close(1008, "read nothing for too long")
        except Exception as e:  # the connection closed
            logger.debug("foxglove: client %s: %s", client.ws.remote_address, e)

    # --- called from other threads ------------------------------------------------------
    def _offer_all(self, kind: str, item: Any) -> None:
        for client in list(self._clients):
            if kind == "reading":
                client.offer_reading(*item)
            else:
                client.offer(item)

    def _call(self, kind: str, item: Any) -> None:
        if not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._offer_all, kind, item)

    def log_reading(self, produced_s: float, messages: list[tuple[int, int, bytes]]) -> None:
        """One reading's messages, ``(channel id, log time ns, payload)``; ``produced_s``:
        when the reading was made (``time.monotonic()``), for the age rule."""
        self._call("reading", (produced_s, messages))

    def log(self, channel: int, log_ns: int, payload: bytes) -> None:
        """A message every client gets in order (not replaced by newer ones): health."""
        self._call("message", (channel, log_ns, payload))

    def publish_status(self, message: str, level: str, status_id: str) -> None:
        op = {"op": "status", "level": STATUS_LEVELS[level], "message": message, "id": status_id}
        self._call("op", json.dumps(op))

    def remove_status(self, status_ids: list[str]) -> None:
        self._call("op", json.dumps({"op": "removeStatus", "statusIds": status_ids}))

    def subscribers(self) -> dict[str, int]:
        """Topic -> how many clients are subscribed to it now."""
        with self._lock:
            return dict(self._counts)

    def clients(self) -> int:
        return len(self._clients)

    def skipped(self) -> int:
        """Readings not sent to a client (summed over every client, past and present)."""
        with self._lock:
            return self._gone_skipped + sum(c.skipped for c in list(self._clients))

    def stop(self) -> None:
        if self._loop.is_closed():
            return

        async def close() -> None:
            deadline = time.monotonic() + CLOSE_TIMEOUT_S  # let clients take what waits
            while time.monotonic() < deadline and any(c.ordered or c.newest for c in self._clients):
                await asyncio.sleep(0.01)
            self._server.close()
            await self._server.wait_closed()

        try:
            asyncio.run_coroutine_threadsafe(close(), self._loop).result(START_TIMEOUT_S)
        except Exception:
            logger.exception("foxglove: closing the server failed")
        self._stop_loop()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(START_TIMEOUT_S)
        self._loop.close()
