"""Who may use the Foxglove server (issue 26, item 1): programs and local pages, other
browser origins only by name; a few clients at once; the Foxglove subprotocols only. Tried
with a real WebSocket client (``websockets``) sending the headers a browser would."""

from __future__ import annotations

import contextlib

import pytest
import websockets.sync.client as websockets_sync
from helpers.live import wait_until
from websockets.exceptions import InvalidStatus

from beadsight.config import SensorGeometry
from beadsight.errors import ConfigError
from beadsight.live.config import LiveRunConfig
from beadsight.live.outputs.foxglove import FoxgloveServer

pytestmark = pytest.mark.usefixtures("no_thread_leaks")

SDK, OLDER = "foxglove.sdk.v1", "foxglove.websocket.v1"


@contextlib.contextmanager
def foxglove(**options):
    server = FoxgloveServer(SensorGeometry(image_size_px=64), port=0, **options)
    try:
        yield server
    finally:
        server.finish()


def connect(server, origin: str | None = None, subprotocols=(SDK,)):
    headers = {} if origin is None else {"Origin": origin}
    return websockets_sync.connect(
        server.url,
        subprotocols=list(subprotocols) or None,
        additional_headers=headers,
        open_timeout=10,
    )


def refusal(server, **kwargs) -> tuple[int, str]:
    with pytest.raises(InvalidStatus) as e:
        connect(server, **kwargs)
    return e.value.response.status_code, e.value.response.body.decode().strip()


@pytest.mark.parametrize(
    "origin",
    [
        None,
        "http://localhost:5173",
        "http://127.0.0.1",
        "https://127.0.0.1:8000",
        "http://[::1]:3000",
    ],
)
def test_programs_and_local_pages_connect(origin):
    with foxglove() as server, connect(server, origin) as ws:
        assert ws.subprotocol == SDK
        assert '"op": "serverInfo"' in ws.recv(10)


@pytest.mark.parametrize(
    "origin",
    [
        "https://evil.example",
        "http://localhost.evil.example",
        "http://127.0.0.1.nip.io:8765",
        "null",
    ],
)
def test_other_origins_are_refused_with_403(origin):
    with foxglove() as server:
        assert refusal(server, origin=origin) == (
            403,
            f"origin {origin} is not allowed: beadsight accepts local pages only, and "
            "origins named with --foxglove-allow-origin",
        )
        assert server.subscribers() == dict.fromkeys(server.topics(), 0)


def test_an_origin_allowed_by_name_connects_and_no_other():
    with foxglove(allowed_origins=("https://app.foxglove.dev",)) as server:
        with connect(server, "https://app.foxglove.dev") as ws:
            assert '"op": "serverInfo"' in ws.recv(10)
        assert refusal(server, origin="https://app.foxglove.dev.evil.example")[0] == 403


def test_clients_beyond_the_cap_are_refused_with_503_until_one_leaves():
    with foxglove(max_clients=2) as server:
        with contextlib.ExitStack() as both:
            for _ in range(2):
                both.enter_context(connect(server)).recv(10)
            assert refusal(server) == (
                503,
                "at most 2 Foxglove clients at once (--foxglove-max-clients)",
            )
        wait_until(lambda: server.clients() == 0, 10, "the two clients to leave")
        with connect(server) as again:  # a place is free again
            assert '"op": "serverInfo"' in again.recv(10)


def test_clients_without_a_foxglove_subprotocol_get_400_and_older_ones_connect():
    with foxglove() as server:
        assert refusal(server, subprotocols=()) == (
            400,
            f"expected the WebSocket subprotocol {SDK} or {OLDER}, got none",
        )
        assert refusal(server, subprotocols=("foxglove.websocket.v0",))[0] == 400
        with connect(server, subprotocols=(OLDER,)) as ws:
            assert ws.subprotocol == OLDER


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        (
            "foxglove_allow_origins",
            ("app.foxglove.dev",),
            "Foxglove allowed origin 'app.foxglove.dev'",
        ),
        (
            "foxglove_allow_origins",
            ("https://a.dev/path",),
            "Foxglove allowed origin 'https://a.dev/path'",
        ),
        ("foxglove_max_clients", 0, "Foxglove max_clients 0: expected an integer 1..1024"),
    ],
)
def test_bad_access_settings_are_refused_by_name(field, value, message):
    with pytest.raises(ConfigError) as e:
        LiveRunConfig(**{field: value})
    assert str(e.value).startswith(message)
