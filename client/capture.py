"""The capture client: frames from a source -> protocol Frames -> the server; Results back.

Sources (`arlight.sources.source.open_source`): "synthetic" (the built-in scene with known
light), every folder layout `arlight estimate` reads (TUM RGB-D, Open3D/Redwood, 7-Scenes) and
MCAP recordings made by `arlight record`, whose Frame messages are sent exactly as recorded.
Depth goes out as the source gives it, uint16 with the source's depth_scale in the Hello's
SessionConfig; the server turns it into metres once. A frame may also carry a 360-degree
panorama (sources/panorama_stream.py): beside the RGB-D images, or alone (a panorama-only
source has no calibration; its Hello carries `config.panorama`, SPEC.md).

Delivery (SessionConfig.mode):
- live: frames go out as the source produces them (`rate="native"`: at the source's own
  pace; "max": as fast as they can be encoded); the server keeps the newest, counts drops.
- lossless: at most `credits` frames (from Welcome) unacknowledged; each Result (or Error for
  that frame) acknowledges one. Every frame gets exactly one Result or Error.

Liveness (zguide's Paranoid Pirate): any message from the server counts as a sign of life; a
server silent for `liveness` heartbeat intervals, a Bye from it, or an Error saying it does
not know this peer (it restarted) makes the client reconnect: new socket (LINGER 0), capped
exponential back-off, Hello again, then in lossless mode the unacknowledged frames are sent
again in order (the server does not process a seq twice: it sends the frame's Result or
Error again, or a final `bad_state` Error with field "duplicate" once it no longer keeps
it), so no frame is lost and none is waited for forever. A second answer to a frame already
answered is ignored: each frame returns its credit once. The client gives up after
`reconnect_timeout_s` without a Welcome.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import re
import secrets
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import msgpack
import numpy as np
import zmq

from arlight.client.connection import Received, open_dealer, receive_message
from arlight.protocols import (
    DEFAULT_COLOR_CODEC,
    DEFAULT_DEPTH_CODEC,
    DEFAULT_JPEG_QUALITY,
    PROTOCOL_VERSION,
    Bye,
    ByeKind,
    Credit,
    Error,
    ErrorField,
    Frame,
    Heartbeat,
    Hello,
    PanoramaConfig,
    ProtocolError,
    Result,
    SceneAnchorSpec,
    SceneObjectSpec,
    SceneSpec,
    SessionConfig,
    Welcome,
    encode,
    new_token,
    peek_header,
)
from arlight.protocols.curve import ClientKeys
from arlight.protocols.probe import ProbeRequest
from arlight.sources.source import Source

if TYPE_CHECKING:  # hints only: virtual_scene loads Open3D, which streaming does not need
    from arlight.pipeline.virtual_scene import VirtualObject, VirtualScene

log = logging.getLogger(__name__)

DEFAULT_SERVER = "tcp://127.0.0.1:5555"


class StreamError(RuntimeError):
    """The stream cannot go on: no server, or the server refused the session (fatal Error)."""


# --------------------------------------------------------------------------- frames


def default_session_name(source_name: str) -> str:
    """`<source>-<4 hex>`, within the protocol's [A-Za-z0-9_.-]{1,64}."""
    base = re.sub(r"[^A-Za-z0-9_.-]+", "_", source_name).strip("_") or "stream"
    return f"{base[:55]}-{secrets.token_hex(2)}"


def restamp_seq(parts: list[bytes], seq: int) -> list[bytes]:
    """A recorded Frame with a new seq (looping a recording): the header is re-packed, the
    image payloads are left untouched."""
    header = msgpack.unpackb(parts[0], raw=False)
    header["seq"] = seq
    return [msgpack.packb(header, use_bin_type=True), *parts[1:]]


def encoded_frames(
    source: Source, options: StreamOptions, timestamps: str
) -> Iterator[tuple[int, float, list]]:
    """(seq, source timestamp, encoded Frame parts) for every frame to send, looping if asked.

    timestamps: "capture" stamps each frame with time.time() as it is encoded, "source" keeps
    the source's. Recorded frames are passed on as recorded (re-stamped seq when looping);
    other frames' depth is encoded as the source gives it (uint16, source.depth_scale).
    """
    seq = 0
    offset_s = 0.0
    while True:
        first_ts = last_ts = None
        for frame in source.frames():
            if options.max_frames is not None and seq >= options.max_frames:
                return
            first_ts = frame.timestamp if first_ts is None else first_ts
            last_ts = frame.timestamp
            ts = frame.timestamp + offset_s
            parts: list  # bytes, and memoryviews of the images (zero-copy)
            if frame.parts is not None:  # a recording: as recorded (bit-exact)
                parts = (
                    frame.parts
                    if seq == peek_header(frame.parts)["seq"]
                    else restamp_seq(frame.parts, seq)
                )
            else:
                stamp_s = time.time() if timestamps == "capture" else ts  # goes on the wire
                parts = encode(
                    Frame(
                        seq,
                        stamp_s,
                        frame.color,
                        frame.depth,
                        frame.pose,
                        frame.panorama,
                        options.color_codec,
                        options.depth_codec,
                        options.jpeg_quality,
                    )
                )
            yield seq, ts, parts
            seq += 1
        if not options.loop or first_ts is None or last_ts is None:
            return
        period = (
            1.0 / 30.0 if source.num_frames < 2 else (last_ts - first_ts) / (source.num_frames - 1)
        )
        offset_s += last_ts - first_ts + period


def scene_spec(scene: VirtualScene) -> SceneSpec:
    """The Hello's `scene` of a virtual scene (what the server turns back into it)."""
    return SceneSpec(tuple(object_spec(obj) for obj in scene.objects))


def object_spec(obj: VirtualObject) -> SceneObjectSpec:
    """One object as the wire carries it. The wire gives an anchored object no pose (the
    anchor places it); the uniform scale its world_from_object carries, the one part of it
    an anchor keeps, is applied to its vertices instead."""
    vertices = obj.vertices
    world_from_object = np.asarray(obj.world_from_object, np.float64)
    pose: np.ndarray | None = world_from_object
    anchor = None
    if obj.anchor is not None:
        pixel = obj.anchor.pixel
        anchor = SceneAnchorSpec(
            None if pixel is None else (float(pixel[0]), float(pixel[1])), float(obj.anchor.yaw_deg)
        )
        scale = float(np.cbrt(np.linalg.det(world_from_object[:3, :3])))
        if scale != 1.0:
            vertices = (np.asarray(vertices, np.float64) * scale).astype(np.float32)
        pose = None
    m = obj.material
    albedo = (float(m.albedo[0]), float(m.albedo[1]), float(m.albedo[2]))
    return SceneObjectSpec(
        obj.name,
        vertices,
        obj.triangles,
        obj.normals,
        pose,
        anchor,
        albedo,
        float(m.roughness),
        float(m.metalness),
        bool(m.mirror),
    )


# --------------------------------------------------------------------------- client


# the `arlight stream` flag that sets a Hello field the server may refuse
HELLO_FIELD_FLAGS = {
    "hello.config.session": "--session",
    "hello.config.preset": "--preset",
    "hello.config.overrides": "--set",
    "hello.config.calibration": "--size (synthetic) or the data set's calibration",
    "hello.config.mode": "--mode",
    "hello.config.scene": "--scene",
    "hello.config.virtual_scene": "--scene",
    "hello.config.panorama.operator": "--panorama-operator",
    "hello.config.panorama": "--light-source / --panorama-from-world",
    "hello.config.token": "--token",
    "hello.config.exports": "--export",
    "hello.config.probe": "--probe",
    "hello.config.probe.point_world": "--probe-at (or --scene)",
}


def hello_field_flag(field: str | None) -> str | None:
    """The flag of HELLO_FIELD_FLAGS for `field` or the nearest field above it (a refusal of
    `hello.config.overrides.KEY` names --set)."""
    name = field or ""
    while name:
        if name in HELLO_FIELD_FLAGS:
            return HELLO_FIELD_FLAGS[name]
        name = name.rpartition(".")[0]
    return None


@dataclass(frozen=True)
class StreamOptions:
    """How to stream. timestamps: "capture" stamps each frame with time.time() when it is
    sent (end-to-end latency becomes measurable), "source" keeps the source's timestamps;
    None = capture in live mode, source in lossless mode. Recordings keep theirs always."""

    server: str = DEFAULT_SERVER
    session: str | None = None
    client_name: str = "arlight-stream"
    mode: str = "live"
    rate: str = "native"
    loop: bool = False
    color_codec: str = DEFAULT_COLOR_CODEC
    depth_codec: str = DEFAULT_DEPTH_CODEC
    jpeg_quality: int = DEFAULT_JPEG_QUALITY
    preset: str = "full"
    overrides: dict = field(default_factory=dict)
    want_composite: bool = False
    virtual_scene: str | None = None  # a scene the server has built in ("demo")
    scene: VirtualScene | None = None  # or the scene itself, sent in the Hello
    # the Hello's config.panorama (operator, light_source, panorama_from_world); a
    # panorama-only source (calibration None) sends PanoramaConfig() when this is None
    panorama: PanoramaConfig | None = None
    # engine layouts (protocols.EXPORT_LAYOUTS) every Result of the session carries
    exports: tuple[str, ...] = ()
    # a reflection probe in every Result (the Hello's config.probe; protocols/probe.py)
    probe: ProbeRequest | None = None
    timestamps: str | None = None
    max_frames: int | None = None  # stop after this many frames (with --loop: in total)
    heartbeat_interval_s: float = 1.0  # until the server's Welcome says otherwise
    liveness: int = 3
    reconnect_timeout_s: float = 30.0
    backoff_initial_s: float = 0.1
    backoff_max_s: float = 2.0
    final_result_timeout_s: float = 30.0  # live mode: wait this long for the last Result
    # lossless: a frame unanswered this long is sent again (its Result may have been lost at
    # a full send queue; the server answers a duplicate once, when it has the outcome); the
    # wait doubles at each resend of the same frame
    resend_after_s: float = 20.0
    # security (docs/guides/security.md): the session token this client gives a new session (and
    # presents when resuming one; None: a random one); CURVE keys for a keyed server
    token: str | None = None
    keys: ClientKeys | None = None

    def __post_init__(self) -> None:
        if self.mode not in ("live", "lossless"):
            raise ValueError(f"--mode must be 'live' or 'lossless', got {self.mode!r}")
        if self.rate not in ("native", "max"):
            raise ValueError(f"--rate must be 'native' or 'max', got {self.rate!r}")
        if self.timestamps not in (None, "capture", "source"):
            raise ValueError(f"--timestamps must be 'capture' or 'source', got {self.timestamps!r}")


@dataclass
class StreamSummary:
    session: str
    frames_sent: int = 0
    results: int = 0
    errors: list[Error] = field(default_factory=list)
    frames_dropped: int = 0  # as reported by the server's last Result
    frames_not_sent: int = 0  # live: the client's own queue was full
    reconnects: int = 0
    elapsed_s: float = 0.0
    latencies_s: list[float] = field(default_factory=list)  # send -> Result, per frame


class CaptureClient:
    """Streams one source into one session. `run()` blocks; `stop()` ends it from any thread.

    on_result(result, receive_time_wall) (time.time() when the Result came, seconds) and
    on_error(error) are called in the client's thread.
    recorder: optional client/recording.Recorder receiving the Hello and every frame sent.
    """

    def __init__(
        self,
        source: Source,
        options: StreamOptions,
        on_result: Callable[[Result, float], None] | None = None,
        on_error: Callable[[Error], None] | None = None,
        recorder=None,
        context: zmq.Context | None = None,
    ):
        self.source = source
        self.options = options
        self.on_result = on_result
        self.on_error = on_error
        self.recorder = recorder
        self.session = options.session or default_session_name(source.name)
        self._ctx = context or zmq.Context.instance()
        self._socket: zmq.Socket | None = None
        self._stop = threading.Event()
        self._timestamps = options.timestamps or ("capture" if options.mode == "live" else "source")
        self.hello = self._make_hello()  # as recorded: without the token
        # the session's token: displays present it (`arlight display --token`); the Hello
        # carries it (a new session takes it, resuming one needs it); a secret
        self.token = options.token or new_token()
        self.session_token = self.token  # as the server's Welcome confirms it
        self.credits = 1
        self.heartbeat_interval_s = options.heartbeat_interval_s
        self.summary = StreamSummary(self.session)
        # lossless: seq -> encoded parts, sent (or to be sent again) and not yet acknowledged
        self._unacked: collections.OrderedDict[int, list] = collections.OrderedDict()
        self._sent_time_mono: dict[int, float] = {}  # seq -> time.monotonic() it was sent
        # lossless: seq -> (monotonic time it was last handed to the socket, wait before the
        # next resend)
        self._resend_due: dict[int, tuple[float, float]] = {}
        self._resend: collections.deque[int] = collections.deque()
        self._after_result: list[int] = []  # refused for credits: send again after a Result
        self._last_seq = -1  # the last frame taken from the source
        self._last_delivered_seq = -1  # the last frame handed to the socket
        self._last_result_seq = -1
        self._hello_recorded = False
        self._last_heard = self._last_sent = time.monotonic()  # liveness, monotonic seconds
        self._source_t0: float | None = None  # the first frame's source timestamp ...
        self._start_t0_mono = 0.0  # ... and when it was due (rate native)
        self._finish_deadline_mono: float | None = None  # live: wait for the last Result

    def _make_hello(self) -> Hello:
        opts = self.options
        base = self.source.recorded_config
        config = SessionConfig(
            session=self.session,
            client_name=opts.client_name,
            role="capture",
            calibration=self.source.calibration,
            depth_scale=self.source.depth_scale,
            preset=opts.preset,
            overrides=dict(opts.overrides),
            virtual_scene=opts.virtual_scene,
            mode=opts.mode,
            want_composite=opts.want_composite,
            scene=None if opts.scene is None else scene_spec(opts.scene),
            panorama=opts.panorama
            if opts.panorama is not None or self.source.calibration is not None
            else PanoramaConfig(),
            exports=tuple(opts.exports),
            probe=opts.probe,
        )
        if base is not None:  # a recording: its calibration and depth scale always hold
            config = dataclasses.replace(
                config, calibration=base.calibration, depth_scale=base.depth_scale
            )
        return Hello(PROTOCOL_VERSION, config)

    def stop(self) -> None:
        self._stop.set()

    # ------------------------------------------------------------------ socket

    def _open_socket(self) -> None:
        if self._socket is not None:
            self._socket.close(linger=0)
        self._socket = open_dealer(
            self._ctx,
            self.options.server,
            sndhwm=64,
            rcvhwm=1000,
            error=StreamError,
            keys=self.options.keys,
        )

    @property
    def _dealer(self) -> zmq.Socket:
        """The socket to the server (there is one once _open_socket ran)."""
        if self._socket is None:
            raise RuntimeError("not connected: _open_socket() first")
        return self._socket

    def _send(self, parts: list, block: bool = False) -> bool:
        try:
            self._dealer.send_multipart(parts, 0 if block else zmq.NOBLOCK, copy=False)
            return True
        except zmq.Again:
            return False

    def _receive(self, timeout_s: float) -> Received | None:
        """One message from the server within timeout_s, or None (see receive_message)."""
        return receive_message(self._dealer, timeout_s, log)

    def _connect(self) -> None:
        """(Re)connect and say Hello until Welcome; StreamError after reconnect_timeout_s."""
        opts = self.options
        deadline = time.monotonic() + opts.reconnect_timeout_s
        backoff = opts.backoff_initial_s
        try:  # once: a scene may be tens of MB
            hello_parts = encode(
                dataclasses.replace(
                    self.hello, config=dataclasses.replace(self.hello.config, token=self.token)
                )
            )
        except ProtocolError as exc:
            raise StreamError(
                f"the Hello of session {self.session!r} cannot be sent: "
                f"{exc.code} ({exc.field}): {exc.message}"
            ) from None
        while not self._stop.is_set():
            self._open_socket()
            self._send(hello_parts, block=False)
            wait_until = time.monotonic() + max(opts.liveness * self.heartbeat_interval_s, 1.0)
            while time.monotonic() < wait_until and not self._stop.is_set():
                got = self._receive(min(0.1, wait_until - time.monotonic()))
                if got is None:
                    continue
                if isinstance(got.message, Welcome):
                    self._welcomed(got.message, got.receive_time_mono)
                    return
                if (
                    isinstance(got.message, Error)
                    and got.message.seq is None
                    and not got.message.retryable
                ):
                    raise StreamError(self._refusal_text(got.message))
                self._handle(got)  # late Results of the previous connection
            if time.monotonic() + backoff > deadline:
                raise StreamError(
                    f"no arlight server answered at {opts.server} within "
                    f"{opts.reconnect_timeout_s:.0f} s (--reconnect-timeout); "
                    "start one with `arlight serve` or check --server"
                )
            if backoff == opts.backoff_initial_s:  # the first miss: say what is going on
                log.warning(
                    "no answer from %s yet; trying again for up to %.0f s (--reconnect-timeout)",
                    opts.server,
                    max(deadline - time.monotonic(), 0.0),
                )
            else:
                log.info("no Welcome from %s; retrying in %.1f s", opts.server, backoff)
            self._stop.wait(backoff)
            backoff = min(backoff * 2, opts.backoff_max_s)

    def _welcomed(self, welcome: Welcome, receive_time_mono: float) -> None:
        self.credits = max(1, welcome.credits)
        self.heartbeat_interval_s = welcome.heartbeat_interval_s
        if welcome.token is not None:  # the session's (differs from ours after an admin resume)
            self.session_token = welcome.token
        if self.recorder is not None and not self._hello_recorded:  # never the token
            self.recorder.write_hello(encode(self.hello), time.time_ns())
            self._hello_recorded = True
        self._last_heard = receive_time_mono
        self._last_sent = time.monotonic()

    def _refusal_text(self, error: Error) -> str:
        """The StreamError text of a refused Hello, naming the command-line flag if any."""
        flag = hello_field_flag(error.field)
        where = f" ({error.field}{', see ' + flag if flag else ''})" if error.field else ""
        return f"the server refused session {self.session!r}: {error.code}{where}: {error.message}"

    def _reconnect(self, why: str) -> None:
        log.warning("session %s: %s; reconnecting to %s", self.session, why, self.options.server)
        self.summary.reconnects += 1
        self._connect()
        self._resend = collections.deque(self._unacked)  # lossless: send them all again
        self._after_result.clear()

    # ------------------------------------------------------------------ messages

    def _handle(self, got: Received) -> str | None:
        """Act on one server message; returns "reconnect" or "rehello" when that is needed."""
        self._last_heard = got.receive_time_mono
        message = got.message
        if isinstance(message, Result):
            self._on_result(message, got)
        elif isinstance(message, Error):
            return self._on_error(message)
        elif isinstance(message, Bye):  # shutdown (or any other kind): find the next server
            log.info(
                "session %s: the server said Bye (%s: %s)",
                self.session,
                message.kind.value,
                message.reason,
            )
            return "reconnect"
        elif isinstance(message, Credit):
            self.credits += message.credits  # the server widened the window
        return None  # Heartbeat, Welcome, an undecodable message: a sign of life only

    def _on_result(self, result: Result, got: Received) -> None:
        if self.options.mode == "lossless":
            if result.seq not in self._unacked:
                return  # a duplicate (re-sent after a reconnect)
            del self._unacked[result.seq]
            self._resend_due.pop(result.seq, None)
        elif result.seq <= self._last_result_seq:
            return
        self._last_result_seq = max(self._last_result_seq, result.seq)
        if self._after_result:
            self._resend.extend(sorted(self._after_result))
            self._after_result.clear()
        sent_mono = self._sent_time_mono.pop(result.seq, None)
        if sent_mono is not None:
            self.summary.latencies_s.append(got.receive_time_mono - sent_mono)
        self.summary.results += 1
        self.summary.frames_dropped = result.frames_dropped
        if self.on_result is not None:
            self.on_result(result, got.receive_time_wall)

    def _on_error(self, error: Error) -> str | None:
        if error.retryable:  # the frame was not processed: it stays unacknowledged
            if error.field == ErrorField.SESSION:
                return "rehello"
            if (
                error.field == ErrorField.CREDITS
                and error.seq is not None
                and error.seq in self._unacked
            ):
                self._after_result.append(error.seq)  # the server's queue was full: retry
            if (
                error.field == ErrorField.PIPELINE_LOST
                and error.seq is not None
                and error.seq in self._unacked
            ):
                # the session's pipeline was lost (`serve --ray`): send it again now, in order
                self._resend = collections.deque(sorted({*self._resend, error.seq}))
            return None  # shutdown: the Bye follows, then a reconnect re-sends the frame
        if error.seq is not None:
            if self.options.mode == "lossless" and error.seq not in self._unacked:
                log.debug("session %s: second answer to frame %d ignored", self.session, error.seq)
                return None  # already answered (a frame sent again): no second credit
            self._unacked.pop(error.seq, None)
            self._resend_due.pop(error.seq, None)
            self._sent_time_mono.pop(error.seq, None)
            self._last_result_seq = max(self._last_result_seq, error.seq)
        self.summary.errors.append(error)
        if error.field == ErrorField.DUPLICATE:
            log.warning(
                "session %s: frame %s was sent again but the server no longer keeps "
                "its Result or Error (it may have been processed; it is not processed "
                "again): counted as failed",
                self.session,
                error.seq,
            )
        else:
            log.warning(
                "session %s: server error for frame %s: %s%s: %s",
                self.session,
                error.seq,
                error.code,
                f" ({error.field})" if error.field else "",
                error.message,
            )
        if self.on_error is not None:
            self.on_error(error)
        return None

    # ------------------------------------------------------------------ frames

    def run(self) -> StreamSummary:
        """Stream until the source ends (and, lossless, every frame is acknowledged)."""
        start_mono = time.monotonic()
        self._connect()
        frames = encoded_frames(self.source, self.options, self._timestamps)
        pending: tuple[int, float, list] | None = None  # (seq, source timestamp, parts)
        try:
            while not self._stop.is_set():
                now_m = time.monotonic()
                self._send_resends(now_m)
                if pending is None:
                    pending = next(frames, None)
                if pending is None:  # the source is exhausted
                    if self._stream_done(now_m):
                        break
                    next_due = None
                else:
                    next_due = self._due_time(pending[1], now_m)
                    if next_due is not None and now_m >= next_due:
                        self._send_frame(pending[0], pending[2])
                        pending = None
                        continue
                self._serve(now_m, next_due)
            if not self._stop.is_set():
                self._say_bye("end of stream", ByeKind.END_OF_STREAM)
        except KeyboardInterrupt:
            self._say_bye("interrupted", ByeKind.LEAVING)  # the session closes now
            raise
        finally:
            self.summary.elapsed_s = time.monotonic() - start_mono
            self.summary.frames_sent = self._last_seq + 1
            if self._socket is not None:
                self._socket.close(linger=0)
                self._socket = None
        return self.summary

    def _due_time(self, source_ts: float, now_m: float) -> float | None:
        """When the next frame may go (monotonic seconds): at its source time (rate native)
        or now (max); None while the lossless credit window is full."""
        if self._source_t0 is None:
            self._source_t0, self._start_t0_mono = source_ts, now_m
        if self.options.mode == "lossless" and len(self._unacked) >= self.credits:
            return None
        if self.options.rate == "native":
            return self._start_t0_mono + (source_ts - self._source_t0)
        return now_m

    def _stream_done(self, now_m: float) -> bool:
        """Every frame is sent: done once each is answered (live: the last Result came, or
        final_result_timeout_s passed)."""
        if self.options.mode == "lossless":
            return not self._unacked
        if self._last_result_seq >= self._last_delivered_seq:
            return True
        if self._finish_deadline_mono is None:
            self._finish_deadline_mono = now_m + self.options.final_result_timeout_s
        elif now_m > self._finish_deadline_mono:
            log.warning(
                "session %s: no Result for the last frame within %.0f s",
                self.session,
                self.options.final_result_timeout_s,
            )
            return True
        return False

    def _serve(self, now_m: float, next_due: float | None) -> None:
        """Wait for the server until the next frame is due (or a heartbeat, or 0.25 s),
        handle what came, and keep the connection alive (reconnect, heartbeat, resends)."""
        heartbeat_due = self._last_sent + self.heartbeat_interval_s
        wake = min(x for x in (next_due, heartbeat_due, now_m + 0.25) if x is not None)
        action = None
        got = self._receive(max(0.0, wake - now_m))
        while got is not None:
            action = self._handle(got) or action
            got = self._receive(0)
        now_m = time.monotonic()
        silent_s = now_m - self._last_heard
        if action == "rehello":
            self._reconnect("the server does not know this session (restarted or expired)")
        elif action == "reconnect":
            self._reconnect("the server said Bye")
        elif silent_s > self.options.liveness * self.heartbeat_interval_s:
            self._reconnect(f"no message from the server for {silent_s:.1f} s")
        elif now_m >= heartbeat_due:
            self._send(encode(Heartbeat(time.time())))
            self._last_sent = now_m
        self._resend_overdue(now_m)

    def _send_resends(self, now_m: float) -> None:
        """Lossless: hand the frames queued for sending again to the socket, in order."""
        while self._resend:
            seq = self._resend.popleft()
            if seq in self._unacked:
                self._send(self._unacked[seq], block=True)
                self._sent_time_mono.setdefault(seq, now_m)
                self._last_sent = now_m
                _, wait = self._resend_due.get(seq, (now_m, self.options.resend_after_s))
                self._resend_due[seq] = (now_m, wait)

    def _resend_overdue(self, now_m: float) -> None:
        """Lossless: queue again the frames unanswered for longer than their wait."""
        if self.options.mode != "lossless":
            return
        for seq in self._unacked:
            sent, wait = self._resend_due.get(seq, (now_m, self.options.resend_after_s))
            if now_m - sent > wait and seq not in self._resend:
                log.warning(
                    "session %s: no answer to frame %d for %.0f s; sending it again",
                    self.session,
                    seq,
                    now_m - sent,
                )
                self._resend.append(seq)
                self._resend_due[seq] = (now_m, 2.0 * wait)

    def _send_frame(self, seq: int, parts: list) -> None:
        now_m = time.monotonic()
        if self.options.mode == "lossless":
            self._unacked[seq] = parts
            self._resend_due[seq] = (now_m, self.options.resend_after_s)
            self._send(parts, block=True)
        elif not self._send(parts, block=False):
            self.summary.frames_not_sent += 1
            self._last_seq = seq
            return
        self._last_delivered_seq = seq
        self._sent_time_mono[seq] = now_m
        if len(self._sent_time_mono) > 4096:  # live: Results of dropped frames never come
            for old in list(self._sent_time_mono)[:2048]:
                del self._sent_time_mono[old]
        self._last_seq = seq
        self._last_sent = now_m
        if self.recorder is not None:
            self.recorder.write_frame(parts, time.time_ns())

    def _say_bye(self, reason: str, kind: ByeKind) -> None:
        if self._socket is not None:
            self._send(encode(Bye(reason, kind)), block=False)
            time.sleep(0.05)  # let the Bye leave before the socket closes (LINGER 0)


def stream(source: Source, options: StreamOptions, **kwargs) -> StreamSummary:
    """Stream `source` with `options` (see CaptureClient) and return the summary."""
    return CaptureClient(source, options, **kwargs).run()
