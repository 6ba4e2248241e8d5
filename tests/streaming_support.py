"""Shared pieces of the streaming tests: loopback servers, small sources, a raw peer, timeouts.

Every server binds tcp://127.0.0.1:* (an ephemeral port); every blocking step has a timeout,
so a hang fails the test instead of blocking CI.
"""

from __future__ import annotations

import socket
import threading
import time

import msgpack
import numpy as np
import pytest
import zmq
from conftest import DATA, SMALL, need_data  # noqa: F401 - also the streaming tests' names

from arlight.core.camera import PinholeCamera
from arlight.core.checks import depth_metres
from arlight.core.frames import Confidence, FrameInput, FrameResult
from arlight.protocols import PROTOCOL_VERSION, Frame, Hello, SessionConfig, decode, encode
from arlight.server.server import Server, ServerOptions
from arlight.sources.source import Source, SourceFrame, calibration_of

TUM_FOLDER = DATA / "real" / "corner_18frames"
HEARTBEAT_S = 0.2
STEP_TIMEOUT_S = 60.0


def server_options(**overrides) -> ServerOptions:
    """Options of a loopback test server. Session tokens are off (these tests are about other
    things and speak for several clients at once); tests/test_security.py turns them on."""
    base = dict(
        bind="tcp://127.0.0.1:*",
        heartbeat_interval_s=HEARTBEAT_S,
        log_interval_s=60.0,
        shutdown_grace_s=5.0,
        session_tokens=False,
    )
    base.update(overrides)
    return ServerOptions(**base)


def identity_step(delay_s: float = 0.0):
    """A compute step standing in for the Pipeline: sh[0] = mean colour value, intensity =
    mean depth (metres), so every Result identifies the frame it came from."""

    def step(frame: FrameInput, session, render_light, deadline) -> FrameResult:
        if delay_s:
            time.sleep(delay_s)
        sh = np.zeros(16)
        sh[0] = float(np.asarray(frame.color, dtype=np.float64).mean())
        pose = np.eye(4) if frame.pose is None else np.asarray(frame.pose)
        return FrameResult(
            timestamp=frame.timestamp,
            sh=sh,
            sh_camera=sh,
            dominant_direction_world=np.zeros(3),
            dominant_direction_camera=np.zeros(3),
            intensity=float(depth_metres(frame.depth, frame.depth_scale).mean()),
            confidence=Confidence(),
            pose=pose,
            timings_ms={"Identity": 0.0},
        )

    return step


def flat_source(
    num_frames: int,
    width: int = 64,
    height: int = 48,
    base: int = 10,
    name: str = "flat",
    noise: bool = False,
) -> Source:
    """Frames of one flat colour each (value base + i, wrapping at 256) and depth 1.5 m;
    noise=True: random colour instead (large after compression)."""
    camera = PinholeCamera.kinect_v1(width, height)

    def frames():
        rng = np.random.default_rng(0)
        for i in range(num_frames):
            color = (
                np.full((height, width, 3), (base + i) % 256, np.uint8)
                if not noise
                else rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
            )
            depth = np.full((height, width), 7500, np.uint16)
            yield SourceFrame(timestamp=1000.0 + i / 30.0, color=color, depth=depth)

    return Source(name, calibration_of(camera), 5000.0, num_frames, frames)


def run_with_timeout(fn, timeout_s: float = STEP_TIMEOUT_S, stop=None):
    """fn() in a thread; its return value, or its exception; fails if it takes too long."""
    box: dict = {}

    def target():
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - re-raised in the test thread
            box["error"] = exc

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(timeout_s)
    if thread.is_alive():
        if stop is not None:
            stop()
        pytest.fail(f"timed out after {timeout_s:.0f} s")
    if "error" in box:
        raise box["error"]
    return box.get("value")


def wait_for(condition, timeout_s: float, what: str = "the condition") -> None:
    """Poll condition() until it is true; fail after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.02)


class CaptureClientThread:
    """A CaptureClient running in a thread; join() returns its summary (or fails on timeout)."""

    def __init__(self, client):
        self.client = client
        self.box: dict = {}
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        try:
            self.box["summary"] = self.client.run()
        except BaseException as exc:  # noqa: BLE001 - re-raised by join()
            self.box["error"] = exc

    def start(self) -> None:
        self.thread.start()

    def join(self, timeout_s: float = STEP_TIMEOUT_S):
        self.thread.join(timeout_s)
        if self.thread.is_alive():
            self.client.stop()
            pytest.fail(f"capture client still running after {timeout_s:.0f} s")
        if "error" in self.box:
            raise self.box["error"]
        return self.box["summary"]


class RawPeer:
    """A bare DEALER for speaking the protocol by hand (and sending hostile bytes)."""

    def __init__(self, address: str, rcvhwm: int | None = None, rcvbuf: int | None = None):
        self.ctx = zmq.Context.instance()
        self.socket = self.ctx.socket(zmq.DEALER)
        self.socket.setsockopt(zmq.LINGER, 0)
        if rcvhwm is not None:
            self.socket.setsockopt(zmq.RCVHWM, rcvhwm)
        if rcvbuf is not None:
            self.socket.setsockopt(zmq.RCVBUF, rcvbuf)
        self.socket.connect(address)

    def send(self, parts) -> None:
        self.socket.send_multipart(parts, copy=False)

    def send_message(self, message) -> None:
        self.send(encode(message))

    def _receive_parts(self, timeout_s: float, skip_heartbeats: bool):
        """(parts as received, decoded message) of the next message within timeout_s
        seconds (Heartbeats skipped if asked); fails the test if none comes."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or not self.socket.poll(int(left * 1000)):
                pytest.fail(f"no message within {timeout_s} s")
            parts = self.socket.recv_multipart()
            message = decode(parts)
            if skip_heartbeats and type(message).__name__ == "Heartbeat":
                continue
            return parts, message

    def receive(self, timeout_s: float = 10.0, skip_heartbeats: bool = True):
        return self._receive_parts(timeout_s, skip_heartbeats)[1]

    def receive_raw(self, timeout_s: float = 10.0) -> list[bytes]:
        """The next message other than a Heartbeat, as received (undecoded parts)."""
        return self._receive_parts(timeout_s, skip_heartbeats=True)[0]

    def hello(
        self,
        session: str,
        mode: str = "lossless",
        role: str = "capture",
        width: int = 64,
        height: int = 48,
        timeout_s: float = 10.0,
        **config,
    ):
        calibration = (
            calibration_of(PinholeCamera.kinect_v1(width, height)) if role == "capture" else None
        )
        self.send_message(
            Hello(
                PROTOCOL_VERSION,
                SessionConfig(
                    session=session,
                    role=role,
                    calibration=calibration,
                    depth_scale=5000.0,
                    mode=mode,
                    **config,
                ),
            )
        )
        return self.receive(timeout_s)

    def keep_alive(self, interval_s: float = 0.1) -> threading.Event:
        """Send heartbeats from a thread (which then owns the socket) until the event is set;
        the peer stays alive without reading anything."""
        from arlight.protocols import Heartbeat

        done = threading.Event()

        def beat():
            while not done.wait(interval_s):
                try:
                    self.socket.send_multipart(encode(Heartbeat(time.time())), zmq.NOBLOCK)
                except zmq.Again:
                    pass

        threading.Thread(target=beat, daemon=True).start()
        return done

    def close(self) -> None:
        self.socket.close(linger=0)


def server_factory():
    """Generator for a `make_server` fixture: make(process=None, **option overrides) -> a
    started Server; every server made is stopped afterwards."""
    servers: list[Server] = []

    def make(process=None, **overrides) -> Server:
        server = Server(server_options(**overrides), process=process).start()
        servers.append(server)
        return server

    yield make
    for server in servers:
        server.stop(timeout=15)


class CuttableProxy:
    """A TCP relay between clients and a server that a test can cut, like a network drop.

    `address` is what clients connect to. `cut(hold=True)` closes every relayed connection
    (both ends see the drop) and, while held, leaves new connections waiting unanswered in
    the listen backlog; `release()` relays them again.
    """

    def __init__(self, target_port: int):
        self.target_port = target_port
        self.listener = socket.socket()
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(16)
        self.address = f"tcp://127.0.0.1:{self.listener.getsockname()[1]}"
        self._open = threading.Event()
        self._open.set()
        self._closed = False
        self._lock = threading.Lock()
        self._sockets: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self._closed:
            self._open.wait()
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            try:
                upstream = socket.create_connection(("127.0.0.1", self.target_port), 5)
            except OSError:
                client.close()
                continue
            with self._lock:
                if not self._open.is_set() or self._closed:  # cut meanwhile: drop it
                    client.close()
                    upstream.close()
                    continue
                self._sockets += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(source: socket.socket, sink: socket.socket) -> None:
        try:
            while data := source.recv(65536):
                sink.sendall(data)
        except OSError:
            pass
        for s in (source, sink):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def cut(self, hold: bool = True) -> None:
        with self._lock:
            if hold:
                self._open.clear()
            sockets, self._sockets = self._sockets, []
        for s in sockets:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def release(self) -> None:
        self._open.set()

    def close(self) -> None:
        self._closed = True
        self._open.set()
        self.cut(hold=False)
        self.listener.close()


# ------------------------------------------------------------------ raw messages (server tests)


def frame_parts(
    seq: int = 0,
    width: int = 64,
    height: int = 48,
    value: int = 7,
    color_codec: str = "raw",
    depth_codec: str = "raw",
) -> list[bytes]:
    """The parts of a flat Frame message (colour `value`, depth 7500) as a RawPeer sends."""
    frame = Frame(
        seq,
        1.0,
        np.full((height, width, 3), value, np.uint8),
        np.full((height, width), 7500, np.uint16),
        None,
        None,
        color_codec,
        depth_codec,
    )
    return [bytes(memoryview(p)) for p in encode(frame)]


def edit_header(parts: list[bytes], edit) -> list[bytes]:
    """`parts` with the header re-packed after edit(header) changed it in place."""
    header = msgpack.unpackb(parts[0])
    edit(header)
    return [msgpack.packb(header, use_bin_type=True), *parts[1:]]


def hello_parts(**config) -> list:
    """The parts of a capture Hello (session "hostile", no calibration) with `config`'s keys."""
    base = dict(session="hostile", role="capture", calibration=None)
    base.update(config)
    return encode(Hello(PROTOCOL_VERSION, SessionConfig(**base)))


def calibrated(**config):
    """`config` with the calibration of a 64x48 Kinect v1 camera."""
    return dict(calibration=calibration_of(PinholeCamera.kinect_v1(64, 48)), **config)
