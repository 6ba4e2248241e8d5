"""One client cannot take the workers or the sessions (issue 39, items 3 and 4). Two
sessions whose frames the budget allows but that run long (here 4 s each, priced heavy by the
cost model) used to hold both workers, and a light legitimate stream beside them waited for
each of their frames. Real server, real sockets on loopback."""

from __future__ import annotations

import time

import pytest
from hostile_support import LegitStream
from streaming_support import RawPeer, frame_parts, identity_step

from arlight.protocols import Welcome

HEAVY_S = 4.0


@pytest.fixture(scope="module", autouse=True)
def parallel_kernels_ran():
    """As in a server whose pipelines ran: Numba's threading layer chosen (OpenMP or TBB
    here), so sessions' frames may run side by side (`concurrent_pipelines_safe`; with the
    'workqueue' layer the server runs one frame at a time and no worker can be kept free)."""
    import numba
    import numpy as np

    from arlight.pipeline.runtime import concurrent_pipelines_safe

    @numba.njit(parallel=True, cache=False)
    def total(a):
        s = 0.0
        for i in numba.prange(a.size):
            s += a[i]
        return s

    total(np.ones(8))
    if not concurrent_pipelines_safe():
        pytest.skip("Numba's threading layer is 'workqueue': frames run one at a time")


def heavy_or_light_step():
    """Sessions named heavy*: each frame takes HEAVY_S seconds; the others: at once."""
    fast = identity_step()

    def step(frame, session, render_light, deadline):
        if session.name.startswith("heavy"):
            time.sleep(HEAVY_S)
        return fast(frame, session, render_light, deadline)

    return step


def test_heavy_sessions_leave_a_worker_for_a_light_one(make_server):
    server = make_server(heavy_or_light_step(), heartbeat_interval_s=5.0, workers=2)
    heavy = []
    for name in ("heavy-a", "heavy-b"):
        peer = RawPeer(server.connect_address)
        # priced just under the 60 s deadline: robust_iterations=57000 at 160 x 120, fast (59 s)
        welcome = peer.hello(
            name, width=160, height=120, preset="fast", overrides={"robust_iterations": 57000}
        )
        assert isinstance(welcome, Welcome), welcome
        heavy.append(peer)
    with LegitStream(server.connect_address) as legit:
        for peer in heavy:
            for seq in range(4):
                peer.send(frame_parts(seq, width=160, height=120))
        time.sleep(2.5 * HEAVY_S)
    legit.assert_served(3.0)
    done = [server.snapshot()["sessions"][n]["frames_processed"] for n in ("heavy-a", "heavy-b")]
    assert sum(done) >= 2  # the heavy sessions still progress, on the other worker
    for peer in heavy:
        peer.close()


def test_one_connection_cannot_take_every_session(make_server):
    """32 capture Hellos of distinct names from one connection filled --max-sessions."""
    server = make_server(identity_step(), heartbeat_interval_s=5.0)
    squatter = RawPeer(server.connect_address)
    replies = [squatter.hello(f"squat{i}") for i in range(32)]
    welcomed = [r for r in replies if isinstance(r, Welcome)]
    refused = [r for r in replies if not isinstance(r, Welcome)]
    assert len(welcomed) == server.options.max_sessions_per_client == 8
    # past 8: the per-client limit; past 20 Hellos at once: the Hello rate too
    kinds = {(r.code, r.field) for r in refused}
    assert ("too_large", "hello.config.session") in kinds
    assert kinds <= {("too_large", "hello.config.session"), ("too_large", "hello")}
    with LegitStream(server.connect_address) as legit:
        time.sleep(1.0)
    legit.assert_served()
    squatter.close()


def test_hellos_do_not_keep_a_session_without_frames(make_server):
    """A Hello every < 60 s held a session that never received a frame."""
    server = make_server(identity_step(), heartbeat_interval_s=5.0, session_timeout_s=1.0)
    peer = RawPeer(server.connect_address)
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        assert isinstance(peer.hello("held"), Welcome)
        time.sleep(0.3)
    assert server.stats.sessions_expired >= 1
    peer.close()


def test_hellos_are_rate_limited_per_client(make_server):
    server = make_server(identity_step(), heartbeat_interval_s=5.0, hellos_per_client_s=2.0)
    peer = RawPeer(server.connect_address)
    replies = [peer.hello("same", role="display") for _ in range(40)]
    refused = [r for r in replies if not isinstance(r, Welcome)]
    assert 40 - len(refused) <= 20 + 2 * 10  # the burst, and the rate over the exchange
    assert refused and all((r.code, r.field) == ("too_large", "hello") for r in refused)
    assert "--hellos-per-client" in refused[0].message
    time.sleep(1.0)  # the bucket refills
    assert isinstance(peer.hello("same", role="display"), Welcome)
    peer.close()


def test_a_slow_hello_is_charged_its_time_on_the_io_thread():
    """Priced by triangles, two 2 M-triangle Hellos fit the burst on a machine of any speed; on
    a slow one (2 s each, not 0.9 s) the measured time takes the rest of the bucket."""
    from arlight.server.clients import HELLO_IO_SHARE, HelloLimiter, hello_cost

    cost = hello_cost(1_990_000)
    fast, slow = HelloLimiter(5.0), HelloLimiter(5.0)
    for limiter, busy_s in ((fast, 0.9), (slow, 2.0)):
        assert limiter.allow("c", 0.0, cost)
        limiter.settle("c", busy_s, cost, busy_s)
    assert fast.allow("c", 0.9, cost)  # 0.9 s at 40 %: what the triangle price says
    assert not slow.allow("c", 2.0, cost)
    # 20 - cost, + 10 refilled in the 2 s, - (2 s x 5 / HELLO_IO_SHARE - cost) owed: 5 left
    left = min(20.0, 20.0 - cost + 2.0 * 5.0) - (2.0 * 5.0 / HELLO_IO_SHARE - cost)
    wait_s = (cost - left) / 5.0
    assert not slow.allow("c", 2.0 + wait_s - 0.1, cost)
    assert slow.allow("c", 2.0 + wait_s + 0.1, cost)


def test_a_cheap_hello_is_not_charged_beyond_its_token():
    from arlight.server.clients import HelloLimiter

    limiter = HelloLimiter(2.0)
    for _ in range(20):
        assert limiter.allow("c", 0.0, 1.0)
        limiter.settle("c", 0.0, 1.0, busy_s=0.002)
    assert not limiter.allow("c", 0.0, 1.0)


def test_a_key_is_one_client_across_its_connections(make_server, tmp_path):
    """Under CURVE the limit follows the key: new connections do not reset it."""
    import zmq.auth

    from arlight.server.security import generate_keys

    generate_keys(str(tmp_path))
    server_public, _ = zmq.auth.load_certificate(str(tmp_path / "server.key"))
    public, secret = zmq.auth.load_certificate(str(tmp_path / "client.key_secret"))
    server = make_server(
        identity_step(),
        heartbeat_interval_s=5.0,
        keys_dir=str(tmp_path),
        max_sessions_per_client=3,
    )
    replies = []
    peers = []
    for i in range(5):
        peer = RawPeer.__new__(RawPeer)
        peer.ctx = zmq.Context.instance()
        peer.socket = peer.ctx.socket(zmq.DEALER)
        peer.socket.setsockopt(zmq.LINGER, 0)
        peer.socket.curve_serverkey = server_public
        peer.socket.curve_publickey = public
        peer.socket.curve_secretkey = secret
        peer.socket.connect(server.connect_address)
        replies.append(peer.hello(f"keyed{i}"))
        peers.append(peer)
    assert [isinstance(r, Welcome) for r in replies] == [True] * 3 + [False] * 2
    for peer in peers:
        peer.close()


def test_queued_lossless_frames_are_held_to_the_calibrations_bytes(make_server):
    """A 64 x 48 lossless session queued credits + 2 frames of max_message_bytes whatever
    its calibration (4 small sessions: RSS 451 MB -> 2.49 GB); now its queue holds a credit
    window of 64 x 48 frames and one large frame, and the rest is refused retryable."""
    from streaming_support import edit_header

    server = make_server(heavy_or_light_step(), heartbeat_interval_s=5.0)
    attacker = RawPeer(server.connect_address)
    assert isinstance(attacker.hello("heavy-bloat"), Welcome)
    junk = b"\x00" * (35 * 2**20)  # declared a 64 x 48 raw colour image

    def bloated(seq: int) -> list[bytes]:
        parts = edit_header(frame_parts(seq), lambda h: h["buffers"].__setitem__(0, len(junk)))
        return [parts[0], junk, parts[2]]

    with LegitStream(server.connect_address) as legit:
        attacker.send(frame_parts(0))  # in a worker for HEAVY_S: the others queue
        for seq in range(1, 5):
            attacker.send(bloated(seq))
        replies = [attacker.receive(10) for _ in range(3)]
        snapshot = server.snapshot()["sessions"]["heavy-bloat"]
        time.sleep(0.5)
    legit.assert_served()
    attacker.close()
    assert snapshot["frames_received"] == 2 and snapshot["pending"] == 1
    assert [(r.code, r.field, r.retryable, r.seq) for r in replies] == [
        ("bad_state", "credits", True, 2),
        ("bad_state", "credits", True, 3),
        ("bad_state", "credits", True, 4),
    ]
    assert "MiB) unacknowledged" in replies[0].message
