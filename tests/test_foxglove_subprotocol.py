"""What the README says of Foxglove clients (issue 34, item 6): the live server (the
foxglove-sdk's) speaks the `foxglove.sdk.v1` WebSocket sub-protocol only; a client that
offers only `foxglove.websocket.v1` (older Foxglove and Lichtblick builds) gets HTTP 400.
Checked with a raw WebSocket handshake on loopback."""

from __future__ import annotations

import base64
import os
import socket

import pytest

from arlight.client.foxglove_sinks import LiveSink


def _handshake(port: int, offered: str | None) -> tuple[str, str | None]:
    """(HTTP status line, the sub-protocol the server chose) of a WebSocket upgrade."""
    key = base64.b64encode(os.urandom(16)).decode()
    lines = [
        "GET / HTTP/1.1",
        f"Host: 127.0.0.1:{port}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        f"Sec-WebSocket-Key: {key}",
        "Sec-WebSocket-Version: 13",
    ] + ([f"Sec-WebSocket-Protocol: {offered}"] if offered else [])
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = s.recv(4096)
            if not chunk:
                break
            data += chunk
    head = data.decode(errors="replace").split("\r\n")
    chosen = [h.split(":", 1)[1].strip() for h in head if h.lower().startswith("sec-websocket-p")]
    return head[0], chosen[0] if chosen else None


@pytest.fixture()
def sink():
    s = LiveSink("127.0.0.1", 0, name="subprotocol test")
    yield s
    s.close()


@pytest.mark.parametrize(
    "offered, status, chosen",
    [
        ("foxglove.sdk.v1", "101", "foxglove.sdk.v1"),
        ("foxglove.sdk.v1, foxglove.websocket.v1", "101", "foxglove.sdk.v1"),
        ("foxglove.websocket.v1", "400", None),
        (None, "400", None),
    ],
)
def test_which_sub_protocol_the_live_server_accepts(sink, offered, status, chosen):
    line, got = _handshake(sink.port, offered)
    assert line.split()[1] == status, line
    assert got == chosen
