"""Cheap input must not stall the other sessions (issue 39, item 2): a header that is cheap
to send and dear to parse, image payloads whose headers are dear to walk, and calibrations
the cost model would misprice are refused at a bounded cost, while a legitimate lossless
session beside them keeps its Results coming (largest gap under 3 s). Real server, real
sockets on loopback."""

from __future__ import annotations

import time

import msgpack
import numpy as np
from hostile_support import LegitStream
from streaming_support import RawPeer, edit_header, frame_parts, identity_step, wait_for

from arlight.protocols import PROTOCOL_VERSION, Error, decode
from arlight.protocols.codecs import encode_color


def _errors(peer: RawPeer, count: int, timeout_s: float = 60.0) -> list[Error]:
    out: list[Error] = []
    deadline = time.monotonic() + timeout_s
    while len(out) < count and time.monotonic() < deadline:
        if peer.socket.poll(200):
            message = decode(peer.socket.recv_multipart())
            if isinstance(message, Error):
                out.append(message)
    return out


def test_container_heavy_headers_are_refused_cheaply(make_server):
    server = make_server(identity_step())
    # 1 MiB of nested empty arrays in a Hello (parsed twice before): 0.4-1.3 s each
    body = msgpack.packb({"v": PROTOCOL_VERSION, "type": "hello", "config": [[[]] * 1000] * 1040})[
        : 2**20
    ]
    flat = msgpack.packb({"v": PROTOCOL_VERSION, "type": "hello", "config": [{}] * 2**19})
    attacker = RawPeer(server.connect_address)
    with LegitStream(server.connect_address) as legit:
        time.sleep(0.3)
        for _ in range(12):
            attacker.send([body])
            attacker.send([flat])
        errors = _errors(attacker, 24)
        time.sleep(0.5)
    legit.assert_served()
    attacker.close()
    assert len(errors) == 24
    assert {(e.code, e.field) for e in errors} == {("too_large", "header")}


def _with_color_payload(seq: int, payload: bytes, codec: str) -> list[bytes]:
    parts = frame_parts(seq, color_codec=codec)

    def edit(header):
        header["buffers"][0] = len(payload)

    parts = edit_header(parts, edit)
    return [parts[0], payload, parts[2]]


def test_image_payloads_with_endless_headers_are_refused_cheaply(make_server):
    server = make_server(identity_step(), heartbeat_interval_s=2.0)  # the attacker is silent
    color = np.zeros((48, 64, 3), np.uint8)
    jpeg = bytes(encode_color(color, "jpeg")[0])
    png = bytes(encode_color(color, "png")[0])
    size = 30 * 2**20
    empty_app = b"\xff\xe0\x00\x02" * (size // 4)  # 7.8 M empty APP0 segments
    empty_chunks = b"\x00\x00\x00\x00tEXt\x00\x00\x00\x00" * (size // 12)  # 2.6 M chunks
    payloads = [
        (jpeg[:2] + empty_app + jpeg[2:], "jpeg"),
        (png[:33] + empty_chunks + png[33:], "png"),
        (jpeg[:2] + b"\xff" * size + jpeg[2:], "jpeg"),
    ]
    attacker = RawPeer(server.connect_address)
    assert attacker.hello("attacker", mode="lossless").__class__.__name__ == "Welcome"
    with LegitStream(server.connect_address) as legit:
        time.sleep(0.3)
        for seq, (payload, codec) in enumerate(payloads):
            attacker.send(_with_color_payload(seq, payload, codec))
        errors = _errors(attacker, len(payloads))
        time.sleep(0.5)
    legit.assert_served()
    attacker.close()
    assert [e.code for e in errors] == ["decode_failed"] * len(payloads)
    assert all(e.field == "frame.color" for e in errors)


def test_legitimate_images_still_decode(make_server):
    """The bounded header checks keep every image the encoders make."""
    server = make_server(identity_step())
    peer = RawPeer(server.connect_address)
    peer.hello("plain", mode="lossless")
    for seq, (color, depth) in enumerate((("jpeg", "png"), ("png", "zstd"), ("raw", "rvl"))):
        peer.send(frame_parts(seq, value=40 + seq, color_codec=color, depth_codec=depth))
    got = [peer.receive(30) for _ in range(3)]
    assert [type(m).__name__ for m in got] == ["Result"] * 3
    wait_for(lambda: server.snapshot()["sessions"]["plain"]["frames_processed"] == 3, 10)
