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
        # priced just under the 60 s deadline: robust_iterations=20700 at 160 x 120, fast
        welcome = peer.hello(
            name, width=160, height=120, preset="fast", overrides={"robust_iterations": 20700}
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
