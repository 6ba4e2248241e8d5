"""The streaming server over real loopback sockets: live sessions that drop frames, slow
displays, idle and dead peers, restarts and shutdown (issue 3, item 5)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
from streaming_support import (
    CaptureClientThread,
    RawPeer,
    flat_source,
    identity_step,
    run_with_timeout,
    wait_for,
)
from streaming_support import frame_parts as _frame_parts

from arlight.client.capture import CaptureClient, StreamOptions, stream
from arlight.client.display import DisplayClient, DisplayOptions
from arlight.protocols import Bye, Error, Result, Welcome


class TestLive:
    def test_fast_producer_drops_frames_and_reports_them(self, make_server):
        server = make_server(process=identity_step(delay_s=0.05))
        results: list[Result] = []
        options = StreamOptions(
            server=server.connect_address, session="live", mode="live", rate="max"
        )
        summary = run_with_timeout(
            lambda: stream(flat_source(40), options, on_result=lambda r, _: results.append(r))
        )
        assert summary.frames_sent == 40 and summary.frames_not_sent == 0
        last = results[-1]
        assert last.seq == 39  # the newest frame is never dropped
        assert last.frames_received == 40
        assert last.frames_dropped > 0
        assert last.frames_processed + last.frames_dropped == 40
        assert len(results) == last.frames_processed
        assert summary.frames_dropped == last.frames_dropped
        seqs = [r.seq for r in results]
        assert seqs == sorted(seqs)
        for r in results:  # every Result is its own frame's, and reports the counters
            assert r.sh[0] == pytest.approx(10 + r.seq)
            assert r.frames_processed + r.frames_dropped <= r.frames_received


class TestDisplays:
    def test_late_and_slow_displays_never_stall_the_pipeline(self, make_server):
        server = make_server(process=identity_step())
        address = server.connect_address
        deaf = RawPeer(address, rcvhwm=1, rcvbuf=4096)  # subscribes, then never reads
        assert isinstance(deaf.hello("shared", role="display"), Welcome)
        deaf_alive = deaf.keep_alive()  # heartbeats only: the server must not think it dead
        slow = DisplayClient(
            DisplayOptions(server=address, session="shared", idle_exit_s=3.0), read_delay_s=0.02
        )
        late = DisplayClient(DisplayOptions(server=address, session="shared", idle_exit_s=3.0))
        threads = {
            "slow": threading.Thread(target=slow.run, daemon=True),
            "late": threading.Thread(target=late.run, daemon=True),
        }
        threads["slow"].start()
        assert slow.subscribed.wait(10)
        late_seqs: list[int] = []
        late.on_result = lambda r, _: late_seqs.append(r.seq)

        def on_result(result, _):
            if result.seq == 100:
                threads["late"].start()

        n = 300
        options = StreamOptions(
            server=address,
            session="shared",
            mode="lossless",
            rate="max",
            color_codec="raw",
            depth_codec="raw",
            want_composite=True,
        )
        summary = run_with_timeout(
            lambda: stream(flat_source(n, 320, 240, noise=True), options, on_result=on_result)
        )
        assert summary.results == n and summary.errors == []
        for thread in threads.values():
            thread.join(30)
            assert not thread.is_alive()
        assert late_seqs and late_seqs[0] > 0  # it joined late: no history is replayed
        assert late_seqs == sorted(late_seqs)
        assert 0 < slow.summary.results <= n
        # the deaf display's queue filled up: the server dropped Results for it alone
        assert server.stats.display_results_dropped > 0
        deaf_alive.set()
        deaf.close()


class TestLiveness:
    def test_idle_session_expires_and_silent_peer_is_dead(self, make_server):
        server = make_server(process=identity_step(), session_timeout_s=1.5)
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("idle"), Welcome)
        peer.send(_frame_parts(seq=0))
        assert isinstance(peer.receive(), Result)
        # the peer now stays silent (no heartbeats): dead after 3 intervals (0.6 s); the
        # session expires after its timeout (1.5 s without frames) and frees its state
        wait_for(lambda: "idle" not in server.snapshot()["sessions"], 10)
        snapshot = server.snapshot()
        assert snapshot["sessions_expired"] == 1 and snapshot["peers_expired"] >= 1
        peer.send(_frame_parts(seq=1))
        error = peer.receive()
        assert isinstance(error, Error) and error.code == "bad_state"
        assert error.field == "session" and error.seq == 1
        peer.close()

    def test_killed_capture_client_leaves_the_server_serving_others(self, make_server, tmp_path):
        server = make_server(process=identity_step())
        script = tmp_path / "victim.py"
        script.write_text(
            "import sys\n"
            f"sys.path.insert(0, {os.path.dirname(__file__)!r})\n"
            "from streaming_support import flat_source\n"
            "from arlight.client.capture import StreamOptions, stream\n"
            f"stream(flat_source(100000), StreamOptions(server={server.connect_address!r}, "
            "session='victim', mode='live', rate='native'))\n"
        )
        victim = subprocess.Popen(
            [sys.executable, str(script)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
        )
        try:
            wait_for(
                lambda: (
                    server.snapshot()["sessions"].get("victim", {}).get("frames_received", 0) >= 5
                ),
                60,
                what="the victim's frames",
            )
        finally:
            victim.kill()
            victim.wait(10)
        survivor = StreamOptions(
            server=server.connect_address, session="survivor", mode="lossless", rate="max"
        )
        summary = run_with_timeout(lambda: stream(flat_source(5), survivor))
        assert summary.results == 5 and summary.errors == []
        wait_for(
            lambda: not server.snapshot()["sessions"]["victim"]["capture_attached"],
            10,
            what="the dead capture peer to be detached",
        )

    def test_capture_client_survives_a_server_restart_without_losing_frames(self, make_server):
        server = make_server(process=identity_step(delay_s=0.02))
        port = server.port
        seqs: list[int] = []
        client = CaptureClient(
            flat_source(60),
            StreamOptions(
                server=f"tcp://127.0.0.1:{port}",
                session="phoenix",
                mode="lossless",
                rate="max",
                reconnect_timeout_s=20.0,
            ),
            on_result=lambda r, _: seqs.append(r.seq),
        )
        runner = CaptureClientThread(client)
        runner.start()
        wait_for(lambda: len(seqs) >= 15, 30, what="15 results before the restart")
        server.stop()
        time.sleep(0.3)  # the client notices (Bye) and retries while the port is closed
        second = make_server(process=identity_step(delay_s=0.02), bind=f"tcp://127.0.0.1:{port}")
        summary = runner.join()
        assert summary.reconnects >= 1
        assert seqs == list(range(60))  # every frame exactly once, in order
        assert summary.errors == []
        assert (
            "phoenix" in second.snapshot()["sessions"] or second.stats.sessions_closed >= 1
        )  # it said Hello again to the new server

    def test_shutdown_finishes_or_reports_in_flight_lossless_frames(self, make_server):
        server = make_server(
            process=identity_step(delay_s=0.4), shutdown_grace_s=1.0, heartbeat_interval_s=5.0
        )  # the raw peer sends no heartbeats
        peer = RawPeer(server.connect_address)
        welcome = peer.hello("drain")
        assert welcome.credits >= 4
        for seq in range(4):
            peer.send(_frame_parts(seq=seq))
        time.sleep(0.1)
        stopper = threading.Thread(target=server.stop)
        stopper.start()
        outcome: dict[int, str] = {}
        while True:
            message = peer.receive(15)
            if isinstance(message, Bye):
                break
            assert message.seq not in outcome
            if isinstance(message, Result):
                outcome[message.seq] = "processed"
            else:
                assert message.code == "bad_state" and message.field == "shutdown"
                outcome[message.seq] = "reported"
        stopper.join(15)
        assert sorted(outcome) == [0, 1, 2, 3]
        assert "processed" in outcome.values() and "reported" in outcome.values()
        peer.close()

    def test_serve_command_shuts_down_cleanly_on_sigterm(self):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "arlight.cli",
                "serve",
                "--bind",
                f"tcp://127.0.0.1:{port}",
                "--heartbeat",
                "0.2",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            peer = RawPeer(f"tcp://127.0.0.1:{port}")
            welcome = peer.hello("cli", timeout_s=60)  # includes the interpreter's start-up
            assert isinstance(welcome, Welcome)
            proc.send_signal(signal.SIGTERM)
            assert isinstance(peer.receive(15), Bye)
            _, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == 0, stderr
        assert "SIGTERM" in stderr and "server stopped" in stderr
        peer.close()
