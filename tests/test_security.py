"""Security (docs/guides/security.md, issue 14 items 1, 2): CURVE keys, exposure, session tokens.

Real sockets on loopback and real CURVE handshakes (pyzmq's ThreadAuthenticator on the
server). Every blocking step has a timeout.
"""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import time

import pytest
import zmq
from conftest import run_cli
from streaming_support import (
    CaptureClientThread,
    CuttableProxy,
    RawPeer,
    flat_source,
    identity_step,
    server_factory,
    server_options,
)

from arlight.cli import EXIT_BAD_INPUT
from arlight.client.capture import CaptureClient, StreamError, StreamOptions
from arlight.client.display import DisplayClient, DisplayError, DisplayOptions
from arlight.protocols import (
    PROTOCOL_VERSION,
    Bye,
    Error,
    Hello,
    ProtocolError,
    Result,
    SessionConfig,
    Welcome,
    decode,
    encode,
)
from arlight.protocols.curve import ClientKeys
from arlight.server.security import (
    InsecureBindError,
    SecurityError,
    add_client_key,
    generate_keys,
    is_loopback,
)
from arlight.server.server import Server

TOKEN = "session-token_0123456789"
OTHER = "other-token_0123456789ab"
ADMIN = "admin-token_0123456789abc"


@pytest.fixture
def make_server():
    yield from server_factory()


def secure_server(make_server, process=None, **overrides):
    """A loopback server with session tokens on and a known admin token."""
    return make_server(
        process=process or identity_step(), session_tokens=True, admin_token=ADMIN, **overrides
    )


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    """DIR from `arlight keys generate DIR`, plus an unauthorised pair in another folder."""
    d = tmp_path_factory.mktemp("keys")
    generate_keys(str(d / "k"))
    generate_keys(str(d / "stranger"))  # a valid pair the server has never heard of
    return d


def client_keys(keys, who: str = "client", server_dir: str = "k") -> ClientKeys:
    folder = "stranger" if who == "stranger" else "k"
    name = "client" if who == "stranger" else who
    return ClientKeys.load(
        str(keys / server_dir / "server.key"), str(keys / folder / f"{name}.key_secret")
    )


def stream_opts(address: str, session: str, **kw) -> StreamOptions:
    base = dict(
        server=address, session=session, mode="lossless", rate="max", reconnect_timeout_s=5.0
    )
    base.update(kw)
    return StreamOptions(**base)


# --------------------------------------------------------------------------- key files


class TestKeyFiles:
    def test_generate_writes_the_zmq_auth_certificates(self, tmp_path, capsys):
        d = tmp_path / "keys"
        code, text = run_cli(["keys", "generate", str(d)], capsys)
        assert code == 0, text
        names = sorted(p.name for p in d.iterdir())
        assert names == [
            "authorized",
            "client.key",
            "client.key_secret",
            "server.key",
            "server.key_secret",
        ]
        assert (d / "authorized" / "client.key").read_bytes() == (d / "client.key").read_bytes()
        for secret in ("server.key_secret", "client.key_secret"):
            assert stat.S_IMODE((d / secret).stat().st_mode) == 0o600  # owner only
        public, secret = zmq.auth.load_certificate(str(d / "server.key_secret"))
        assert zmq.auth.load_certificate(str(d / "server.key")) == (public, None) and secret
        assert "--keys" in text and "--server-key" in text

    def test_generate_never_overwrites(self, tmp_path, capsys):
        d = tmp_path / "keys"
        assert run_cli(["keys", "generate", str(d)], capsys)[0] == 0
        before = (d / "server.key_secret").read_bytes()
        code, text = run_cli(["keys", "generate", str(d)], capsys)
        assert code == EXIT_BAD_INPUT and "never overwrites" in text
        assert "Traceback" not in text
        assert (d / "server.key_secret").read_bytes() == before

    def test_add_makes_and_authorises_another_client(self, tmp_path, capsys):
        d = tmp_path / "keys"
        generate_keys(str(d))
        code, text = run_cli(["keys", "add", str(d), "tablet"], capsys)
        assert code == 0, text
        assert (d / "authorized" / "tablet.key").read_bytes() == (d / "tablet.key").read_bytes()
        assert stat.S_IMODE((d / "tablet.key_secret").stat().st_mode) == 0o600
        assert run_cli(["keys", "add", str(d), "tablet"], capsys)[0] == EXIT_BAD_INPUT
        with pytest.raises(SecurityError, match="arlight keys generate"):
            add_client_key(str(tmp_path / "none"), "x")


# --------------------------------------------------------------------------- CURVE


class TestCurve:
    def test_keyed_server_admits_an_authorised_client_and_streams(self, make_server, keys):
        server = secure_server(make_server, keys_dir=str(keys / "k"))
        summary = CaptureClient(
            flat_source(4), stream_opts(server.connect_address, "curve", keys=client_keys(keys))
        ).run()
        assert summary.results == 4 and not summary.errors

    def test_second_authorised_client_and_display(self, make_server, keys, tmp_path):
        folder = tmp_path / "k"
        generate_keys(str(folder))
        add_client_key(str(folder), "tablet")
        server = secure_server(make_server, keys_dir=str(folder))
        tablet = ClientKeys.load(str(folder / "server.key"), str(folder / "tablet.key_secret"))
        got = []
        display = DisplayClient(
            DisplayOptions(
                server=server.connect_address,
                session="two",
                token=TOKEN,
                keys=tablet,
                max_results=3,
                idle_exit_s=10.0,
            ),
            on_result=lambda r, rec: got.append(r.seq),
        )
        import threading

        thread = threading.Thread(target=display.run, daemon=True)
        thread.start()
        assert display.subscribed.wait(10)
        mine = ClientKeys.load(str(folder / "server.key"), str(folder / "client.key_secret"))
        CaptureClient(
            flat_source(3), stream_opts(server.connect_address, "two", token=TOKEN, keys=mine)
        ).run()
        thread.join(20)
        assert got == [0, 1, 2]

    def test_unauthorised_key_is_refused_before_any_message(self, make_server, keys, caplog):
        server = secure_server(make_server, keys_dir=str(keys / "k"))
        t0 = time.monotonic()
        with pytest.raises(StreamError, match="refused this client's key") as caught:
            CaptureClient(
                flat_source(2),
                stream_opts(server.connect_address, "intruder", keys=client_keys(keys, "stranger")),
            ).run()
        assert time.monotonic() - t0 < 5.0  # within its reconnect timeout
        assert "arlight keys add" in str(caught.value)
        assert server.stats.messages == 0 and not server.sessions
        refused = [r for r in caplog.records if r.name == "arlight.server.security.zap"]
        assert refused and refused[0].levelname == "WARNING"  # the operator sees who knocked
        assert "DENIED (CURVE)" in refused[0].getMessage()

    def test_plain_client_against_keyed_server_gets_a_clear_error(self, make_server, keys):
        server = secure_server(make_server, keys_dir=str(keys / "k"))
        t0 = time.monotonic()
        with pytest.raises(StreamError, match="--server-key"):
            CaptureClient(flat_source(2), stream_opts(server.connect_address, "plain")).run()
        with pytest.raises(DisplayError, match="--client-key"):
            DisplayClient(
                DisplayOptions(
                    server=server.connect_address,
                    session="plain",
                    token=TOKEN,
                    reconnect_timeout_s=5.0,
                )
            ).run()
        assert time.monotonic() - t0 < 10.0
        assert server.stats.messages == 0

    def test_wrong_server_key_fails_the_handshake(self, make_server, keys):
        server = secure_server(make_server, keys_dir=str(keys / "k"))
        wrong = client_keys(keys, server_dir="stranger")  # another server's public key
        with pytest.raises(StreamError, match="--server-key"):
            CaptureClient(
                flat_source(2), stream_opts(server.connect_address, "mitm", keys=wrong)
            ).run()

    def test_keyed_client_against_plain_server(self, make_server, keys):
        server = secure_server(make_server)
        with pytest.raises(StreamError, match="runs without keys"):
            CaptureClient(
                flat_source(2), stream_opts(server.connect_address, "k", keys=client_keys(keys))
            ).run()

    def test_keyed_lossless_stream_survives_a_network_drop(self, make_server, keys):
        """A CURVE client whose connection drops mid-stream reconnects (its handshakes may
        fail while the network is down: not fatal), presents its session token, resumes the
        session and delivers every frame once."""
        import threading

        step, at_two, go = identity_step(), threading.Event(), threading.Event()
        seen: list[int] = []

        def process(frame, session, render_light, deadline):
            seq = int(round(float(frame.color[0, 0, 0]))) - 10  # flat_source: 10 + i
            seen.append(seq)
            if seq == 2:
                at_two.set()
                assert go.wait(10)
            return step(frame, session, render_light, deadline)

        server = secure_server(make_server, process=process, keys_dir=str(keys / "k"))
        proxy = CuttableProxy(server.port)
        client = CaptureClient(
            flat_source(6),
            stream_opts(
                proxy.address,
                "dropped",
                keys=client_keys(keys),
                color_codec="png",
                reconnect_timeout_s=20.0,
            ),
        )
        runner = CaptureClientThread(client)
        try:
            runner.start()
            assert at_two.wait(30)
            proxy.cut()
            time.sleep(1.5)  # the client retries into the cut: failed handshakes meanwhile
            go.set()
            proxy.release()
            summary = runner.join(40)
        finally:
            go.set()
            proxy.close()
        assert summary.reconnects >= 1 and summary.results == 6 and not summary.errors
        assert sorted(seen) == list(range(6))  # each frame processed once

    def test_bad_key_files_name_the_flag(self, keys, make_server, tmp_path):
        with pytest.raises(ValueError, match="--client-key.*no secret key"):
            ClientKeys.load(str(keys / "k" / "server.key"), str(keys / "k" / "client.key"))
        with pytest.raises(ValueError, match="--server-key"):
            ClientKeys.load(str(tmp_path / "missing.key"), str(keys / "k" / "client.key_secret"))
        with pytest.raises(SecurityError, match="--keys"):
            Server(server_options(keys_dir=str(tmp_path))).start()


# --------------------------------------------------------------------------- exposure


class TestExposure:
    @pytest.mark.parametrize(
        "address, local",
        [
            ("tcp://127.0.0.1:5555", True),
            ("tcp://127.8.0.1:1", True),
            ("tcp://[::1]:5555", True),
            ("tcp://localhost:5555", True),
            ("ipc:///tmp/arlight", True),
            ("inproc://x", True),
            ("tcp://*:5555", False),
            ("tcp://0.0.0.0:5555", False),
            ("tcp://[::]:5555", False),
            ("tcp://192.168.1.4:5555", False),
            ("tcp://eth0:5555", False),
            ("tcp://example.org:5555", False),
        ],
    )
    def test_loopback(self, address, local):
        assert is_loopback(address) is local

    def test_default_bind_is_loopback(self):
        from arlight.server.server import DEFAULT_BIND, ServerOptions

        assert ServerOptions().bind == DEFAULT_BIND == "tcp://127.0.0.1:5555"

    def test_exposed_bind_without_keys_is_refused(self, capsys):
        code, text = run_cli(["serve", "--bind", "tcp://0.0.0.0:0"], capsys)
        assert code == EXIT_BAD_INPUT
        assert "arlight keys generate" in text and "--insecure" in text and "--keys" in text
        assert "Traceback" not in text
        with pytest.raises(InsecureBindError):
            Server(server_options(bind="tcp://*:0")).start()

    def test_insecure_warns_on_every_start(self, make_server, caplog):
        for _ in range(2):
            with caplog.at_level("WARNING", logger="arlight.server.security"):
                server = make_server(bind="tcp://0.0.0.0:0", insecure=True)
            assert server.port
        warnings = [r for r in caplog.records if "--insecure" in r.getMessage()]
        assert len(warnings) == 2

    def test_cli_insecure_starts_with_a_warning(self):
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "arlight.cli",
                "serve",
                "--bind",
                "tcp://0.0.0.0:0",
                "--insecure",
            ],
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
        )
        lines = []
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                line = proc.stderr.readline()
                lines.append(line)
                if "admin token" in line or not line:  # its last start-up line
                    break
            proc.send_signal(signal.SIGTERM)
            rest = proc.communicate(timeout=30)[1]
        finally:
            if proc.poll() is None:
                proc.kill()
        text = "".join(lines) + rest
        assert proc.returncode == 0, text
        assert "--insecure" in text and "WARNING" in text and "Traceback" not in text
        assert "admin token" in text


# --------------------------------------------------------------------------- session tokens


class TestTokens:
    def test_display_with_the_token_gets_results_others_get_an_error(self, make_server):
        server = secure_server(make_server, heartbeat_interval_s=5.0)  # raw peers: no beats
        right, wrong, missing = (RawPeer(server.connect_address) for _ in range(3))
        # subscribed before the session exists (SPEC section 3): any token is taken then
        assert isinstance(right.hello("desk", role="display", token=TOKEN), Welcome)
        early_wrong = RawPeer(server.connect_address)
        assert isinstance(early_wrong.hello("desk", role="display", token=OTHER), Welcome)
        reply = missing.hello("desk", role="display")  # no token: refused at once
        assert isinstance(reply, Error) and reply.code == "unauthorized"
        assert reply.field == "hello.config.token" and "--token" in reply.message
        capture = RawPeer(server.connect_address)
        welcome = capture.hello("desk", token=TOKEN)
        assert isinstance(welcome, Welcome) and welcome.token == TOKEN
        # the session exists now: a wrong token is answered as for a name that does not
        # exist (issue 39: a display Hello reveals nothing about the name), and gets nothing
        assert isinstance(wrong.hello("desk", role="display", token=OTHER), Welcome)
        for seq in range(3):
            capture.send(frame_parts(seq))
            assert isinstance(capture.receive(), Result)
        assert [right.receive().seq for _ in range(3)] == [0, 1, 2]
        for peer in (wrong, missing, early_wrong):
            assert_no_result(peer)
        assert server.snapshot()["displays"] == {"desk": 3}  # two of them wait, told nothing

    def test_admin_token_admits_to_any_session(self, make_server):
        server = secure_server(make_server, heartbeat_interval_s=5.0)
        admin = RawPeer(server.connect_address)
        capture = RawPeer(server.connect_address)
        welcome = capture.hello("lab", token=TOKEN)
        assert isinstance(welcome, Welcome) and welcome.token == TOKEN
        assert isinstance(admin.hello("lab", role="display", token=ADMIN), Welcome)
        capture.send(frame_parts(0))
        assert isinstance(capture.receive(), Result)
        assert admin.receive().seq == 0

    def test_generated_admin_token(self):
        a, b = Server(server_options()), Server(server_options())
        assert a.admin_token != b.admin_token and len(a.admin_token) >= 32

    def test_results_of_one_session_never_reach_another_sessions_display(self, make_server):
        server = secure_server(make_server, heartbeat_interval_s=5.0)
        display = RawPeer(server.connect_address)
        assert isinstance(display.hello("a", role="display", token=TOKEN), Welcome)
        other = RawPeer(server.connect_address)
        assert isinstance(other.hello("b", token=OTHER), Welcome)  # b stays open
        other.send(frame_parts(0))
        assert isinstance(other.receive(), Result)
        CaptureClient(flat_source(1), stream_opts(server.connect_address, "a", token=TOKEN)).run()
        assert display.receive().seq == 0  # session a's only Result
        assert_no_result(display)
        stranger = RawPeer(server.connect_address)
        assert isinstance(stranger.hello("b", role="display", token=TOKEN), Welcome)
        other.send(frame_parts(1))
        assert isinstance(other.receive(), Result)
        assert_no_result(stranger)  # b's token is OTHER: nothing of b reaches it

    def test_capture_needs_the_token_to_take_over_a_session(self, make_server):
        server = secure_server(make_server, heartbeat_interval_s=5.0)
        owner = RawPeer(server.connect_address)
        welcome = owner.hello("own")  # a client from before tokens: none sent back
        assert isinstance(welcome, Welcome) and welcome.token is None
        token = server.sessions["own"].token
        assert token and len(token) >= 32
        thief = RawPeer(server.connect_address)
        reply = thief.hello("own")  # same name and configuration, no token
        assert isinstance(reply, Error) and reply.code == "unauthorized"
        assert "--token" in reply.message and not reply.retryable
        reply = thief.hello("own", width=32, height=24, token=OTHER)  # replacing: refused too
        assert isinstance(reply, Error) and reply.code == "unauthorized"
        assert server.sessions["own"].capture_peer is not None
        resumed = RawPeer(server.connect_address).hello("own", token=token)
        assert isinstance(resumed, Welcome) and resumed.token == token
        admin = RawPeer(server.connect_address).hello("own", token=ADMIN)
        assert isinstance(admin, Welcome) and admin.token == token  # admin learns it
        fresh = RawPeer(server.connect_address).hello("new-by-admin", token=ADMIN)
        assert isinstance(fresh, Welcome) and fresh.token != ADMIN  # a session token of its own
        assert fresh.token == server.sessions["new-by-admin"].token

    def test_stream_cli_prints_the_display_command(self, make_server, capsys):
        server = secure_server(make_server)
        code, text = run_cli(
            [
                "stream",
                "synthetic",
                "--size",
                "32x24",
                "--max-frames",
                "1",
                "--server",
                server.connect_address,
                "--session",
                "cli",
                "--rate",
                "max",
                "--token",
                TOKEN,
            ],
            capsys,
        )
        assert code == 0, text
        assert (
            f"arlight display --server {server.connect_address} --session cli --token "
            f"{TOKEN}" in text
        )

    def test_capture_client_reconnects_into_its_session(self, make_server):
        """The reference client presents its token when it says Hello again."""
        server = secure_server(make_server)
        client = CaptureClient(flat_source(3), stream_opts(server.connect_address, "again"))
        client._connect()
        first_socket_token = client.token
        client._connect()  # a reconnect: the session exists, the token resumes it
        assert client.session_token == first_socket_token == server.sessions["again"].token
        client._socket.close(linger=0)

    def test_recordings_never_hold_the_token(self, make_server, tmp_path):
        from arlight.client.recording import Recorder, record
        from arlight.sources.source import open_source

        path = tmp_path / "r.mcap"
        record(flat_source(2), path, stream_opts("tcp://127.0.0.1:9", "rec", token=TOKEN))
        assert open_source(str(path)).recorded_config.token is None
        assert TOKEN.encode() not in path.read_bytes()
        server = secure_server(make_server)
        streamed = tmp_path / "s.mcap"
        source = flat_source(2)
        with Recorder(streamed, source=source.name, depth_scale=source.depth_scale) as rec:
            CaptureClient(
                source, stream_opts(server.connect_address, "rec2", token=TOKEN), recorder=rec
            ).run()
        assert TOKEN.encode() not in streamed.read_bytes()

    def test_admin_token_file(self, tmp_path, capsys):
        from arlight.server.security import read_token_file
        from arlight.server.server import ServerOptions

        good = tmp_path / "admin"
        good.write_text(ADMIN + "\n")
        assert read_token_file(str(good), "--admin-token-file") == ADMIN
        bad = tmp_path / "bad"
        bad.write_text("secret but short")
        with pytest.raises(SecurityError, match="--admin-token-file") as caught:
            read_token_file(str(bad), "--admin-token-file")
        assert "secret but short" not in str(caught.value)
        with pytest.raises(ValueError, match="--admin-token-file") as caught:
            ServerOptions(admin_token="secret but short")
        assert "secret but short" not in str(caught.value)
        code, text = run_cli(["serve", "--admin-token-file", str(bad)], capsys)
        assert code == EXIT_BAD_INPUT and "--admin-token-file" in text
        assert "Traceback" not in text and "secret but short" not in text

    def test_display_token_file(self, make_server, tmp_path):
        server = secure_server(make_server)
        token_file = tmp_path / "t"
        token_file.write_text(TOKEN)
        from arlight.cli import _token_of, build_parser

        args = build_parser().parse_args(
            [
                "display",
                "--server",
                server.connect_address,
                "--session",
                "s",
                "--token-file",
                str(token_file),
            ]
        )
        assert _token_of(args) == TOKEN

    def test_tokens_off_checks_nothing(self, make_server):
        server = make_server(process=identity_step())  # tests' default: session_tokens False
        assert isinstance(RawPeer(server.connect_address).hello("x", role="display"), Welcome)


def frame_parts(seq: int) -> list:
    import numpy as np

    from arlight.protocols import Frame

    return encode(
        Frame(
            seq,
            1.0 + seq,
            np.full((48, 64, 3), 9, np.uint8),
            np.full((48, 64), 5000, np.uint16),
            None,
        )
    )


def assert_no_result(peer: RawPeer, wait_s: float = 0.5) -> None:
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        if peer.socket.poll(50):
            message = decode(peer.socket.recv_multipart())
            assert not isinstance(message, Result), "a Result reached an unauthorised peer"


# --------------------------------------------------------------------------- wire format


class TestTokenWireFormat:
    def test_round_trip_and_absent_key(self):
        hello = Hello(PROTOCOL_VERSION, SessionConfig("s", role="display", token=TOKEN))
        assert decode(encode(hello)).config.token == TOKEN
        assert decode(encode(Welcome(PROTOCOL_VERSION, "s", 0, 1.0, "x", TOKEN))).token == TOKEN
        import msgpack

        header = msgpack.unpackb(
            bytes(encode(Hello(PROTOCOL_VERSION, SessionConfig("s", role="display")))[0])
        )
        assert "token" not in header["config"]  # absent: byte for byte as before

    @pytest.mark.parametrize(
        "bad", ["short", "x" * 129, "has space in it 0123", "ünïcode-0123456789"]
    )
    def test_bad_tokens_are_refused_without_echo(self, bad):
        with pytest.raises(ProtocolError) as caught:
            encode(Hello(PROTOCOL_VERSION, SessionConfig("s", role="display", token=bad)))
        assert caught.value.code == "bad_field" and caught.value.field == "hello.config.token"
        assert bad not in str(caught.value)

    def test_cli_flags(self, capsys):
        code, text = run_cli(
            ["display", "--server", "tcp://127.0.0.1:9", "--session", "s", "--token", "short"],
            capsys,
        )
        assert code == EXIT_BAD_INPUT and "--token" in text and "Traceback" not in text
        code, text = run_cli(
            ["display", "--server", "tcp://127.0.0.1:9", "--session", "s", "--server-key", "x.key"],
            capsys,
        )
        assert code == EXIT_BAD_INPUT and "--client-key" in text
        code, text = run_cli(["serve", "--keys", "/no/such/dir"], capsys)
        assert code == EXIT_BAD_INPUT and "--keys" in text and "Traceback" not in text


def test_a_display_hello_reveals_nothing_about_a_session_name(make_server):
    """Welcome for a session that exists (wrong token) and for one that does not: the same
    answer (issue 39, item 3); neither display gets that session's Results or its Bye."""
    server = secure_server(make_server, heartbeat_interval_s=5.0)
    capture = RawPeer(server.connect_address)
    assert isinstance(capture.hello("private", token=TOKEN), Welcome)
    known, unknown = RawPeer(server.connect_address), RawPeer(server.connect_address)
    a = known.hello("private", role="display", token=OTHER)
    b = unknown.hello("no-such-session", role="display", token=OTHER)
    assert isinstance(a, Welcome) and isinstance(b, Welcome)
    assert (a.credits, a.token, a.heartbeat_interval_s) == (b.credits, b.token, 5.0)
    capture.send(frame_parts(0))
    assert isinstance(capture.receive(), Result)
    capture.send_message(Bye("done"))
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline:
        if known.socket.poll(50):
            message = decode(known.socket.recv_multipart())
            assert type(message).__name__ == "Heartbeat", message
    for peer in (capture, known, unknown):
        peer.close()
