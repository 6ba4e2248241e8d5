"""Fuzzing a real server beside a legitimate session running the real pipeline (issue 39,
deliverable 3): beyond tiny random messages, seeded hostile traffic of large and
container-heavy msgpack, large and malformed image payloads, Hellos with extreme settings,
log-forging text, Frames from peers without a session, and DEALERs with explicit routing ids
(the next automatic ids, random ones, ids in use). The legitimate lossless stream's latency is
asserted, not only its eventual answer: its largest gap between Results stays under its own
calm gap plus 3 s, and the server keeps serving."""

from __future__ import annotations

import random
import time

import msgpack
import numpy as np
import zmq
from hostile_support import LegitStream
from streaming_support import SMALL, RawPeer, edit_header, frame_parts

from arlight.core.camera import PinholeCamera
from arlight.protocols import (
    PROTOCOL_VERSION,
    Bye,
    CameraCalibration,
    Error,
    Hello,
    SessionConfig,
    encode,
)
from arlight.protocols.codecs import encode_color
from arlight.sources.source import calibration_of

SEED = 39
ATTACK_S = 8.0


def _hostile_messages(rng: random.Random) -> list[list[bytes]]:
    """One round of hostile messages, each a list of parts."""
    v = PROTOCOL_VERSION
    jpeg = bytes(encode_color(np.zeros((48, 64, 3), np.uint8), "jpeg")[0])
    nested = [[[]] * rng.randint(100, 1000)] * rng.randint(100, 1000)
    wide = {f"k{i}": [] for i in range(rng.randint(1025, 5000))}
    cal = calibration_of(PinholeCamera.kinect_v1(64, 48))
    odd = CameraCalibration(64, 48, rng.choice([1e-300, 0.05, 1e300]), 40.0, 32.0, 24.0)
    payload = rng.choice(
        [
            b"\xff\xe0\x00\x02" * rng.randint(1, 4 * 2**20),
            jpeg[:2] + b"\xff" * rng.randint(1, 8 * 2**20) + jpeg[2:],
            rng.randbytes(rng.randint(1, 4 * 2**20)),
        ]
    )
    frame = frame_parts(rng.randint(0, 2**40), color_codec="jpeg")
    frame = edit_header(frame, lambda h: h["buffers"].__setitem__(0, len(payload)))
    return [
        [msgpack.packb({"v": v, "type": "hello", "config": nested})[: 2**20]],
        [msgpack.packb({"v": v, "type": rng.choice(["hello", "frame", "bye"]), "x": wide})],
        [rng.randbytes(rng.randint(1, 2**20))],
        [frame[0], payload, frame[2]],
        encode(
            Hello(
                v,
                SessionConfig(
                    session=f"odd{rng.randint(0, 99)}",
                    role="capture",
                    calibration=odd,
                    depth_scale=5000.0,
                ),
            )
        ),
        encode(
            Hello(
                v,
                SessionConfig(
                    session=f"fz{rng.randint(0, 10**6)}",
                    role=rng.choice(["capture", "display"]),
                    calibration=cal,
                    depth_scale=5000.0,
                    token="t" * 16,
                    overrides={"robust_iterations": rng.choice([10, 20700, 10**7])},
                ),
            )
        ),
        encode(Error("internal", "x\narlight serve: admin token FORGED" * 50)),
        encode(Bye("y\r\n" * 300)),
    ]


def _routing_dealers(address: str, rng: random.Random) -> list[zmq.Socket]:
    """DEALERs with explicit routing ids: the predictable next automatic ids, random ones,
    and one id twice."""
    ctx = zmq.Context.instance()
    ids = [b"\x00" + (0x6B8B4567 + i).to_bytes(4, "big") for i in range(24)]
    ids += [rng.randbytes(rng.randint(1, 32)) for _ in range(8)]
    ids += [b"same-id", b"same-id"]
    sockets = []
    for routing_id in ids:
        s = ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.ROUTING_ID, routing_id)
        s.connect(address)
        s.send(b"\x93\x01\x02\x03")
        sockets.append(s)
    return sockets


def test_hostile_traffic_beside_a_real_pipeline_session(make_server):
    server = make_server(None, heartbeat_interval_s=1.0)
    hello = dict(preset="fast", overrides=dict(SMALL))
    with LegitStream(server.connect_address, **hello) as calm:  # its own pace, unattacked
        deadline = time.monotonic() + 60.0
        while len(calm.result_times) < 4 and time.monotonic() < deadline:
            time.sleep(0.1)
    calm.stop()
    assert len(calm.result_times) >= 4, "the real pipeline gave no Results"
    own_gap_s = max(calm.gaps_s()[1:-1] or calm.gaps_s())  # after the first (warm-up) frame

    rng = random.Random(SEED)
    attackers = [RawPeer(server.connect_address) for _ in range(3)]
    dealers: list[zmq.Socket] = []
    sent = 0
    with LegitStream(server.connect_address, session="legit2", **hello) as legit:
        time.sleep(own_gap_s + 0.5)  # its first Result (a fresh Pipeline) before the attack
        dealers = _routing_dealers(server.connect_address, rng)
        end = time.monotonic() + ATTACK_S
        while time.monotonic() < end:
            for parts in _hostile_messages(rng):
                rng.choice(attackers).send(parts)
                sent += 1
            time.sleep(0.05)
        time.sleep(1.0)
    print(
        f"calm largest gap {own_gap_s:.2f} s; under attack ({sent} messages, "
        f"{len(dealers)} routing ids) {legit.largest_gap_s():.2f} s, "
        f"{len(legit.result_times)} Results"
    )
    legit.assert_served(own_gap_s + 3.0)
    assert sent > 50
    assert server._thread is not None and server._thread.is_alive()
    for s in dealers:
        s.close(linger=0)
    for peer in attackers:
        peer.close()
