"""The thin display client: subscribes to one session's Results and writes/prints them.

It connects with one DEALER to the server (`--server` is the only address it needs), says
Hello(role=display, session=NAME) and receives every Result the server publishes for that
session from then on (a display that joins late starts from there; one that reads slowly
loses Results at its own queue, never stalling the pipeline). Writes, when asked:
`results.jsonl` (one line per Result: the record every `--out` writes, plus the delivery
fields and latencies below), `frames/NNNNNN.png` (the
composite each Result carries: only sessions started with want_composite send one), a
video of the composites (`--video out.mp4`, mp4v) and, when it ends, `latency.png` (latency
and fps over time, client/latency_plot.py). Live, when asked: an MCAP recording of the
Results (`--record FILE.mcap`: client/recording.py), Foxglove's WebSocket protocol
(`--foxglove`: client/foxglove_sinks.py) and a page for a browser (`--http`:
client/web_display.py).

Latency, all on one machine's clock or clocks kept in sync (protocols/records.py,
`received_record`):
- end_to_end_ms = display receive time - the frame's timestamp. Meaningful when the capture
  client stamps frames with their capture time (`--timestamps capture`, the default in live
  mode and in `arlight demo`); null when the timestamps are a data set's own clock (further
  than an hour from now).
- pipeline_ms: the pipeline's stages alone; in_server_ms = server finish - server receive
  (queueing + decoding + pipeline + encoding); server_to_client_ms = display receive time -
  server finish time (the trip back).
The printed "latency" is end_to_end_ms where available, else server receive -> display
(in_server_ms + server_to_client_ms: everything but the trip to the server).
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import cv2
import numpy as np
import zmq

from arlight.client.connection import Received, open_dealer, receive_message
from arlight.client.stop_signals import uninterrupted
from arlight.protocols import (
    PROTOCOL_VERSION,
    Bye,
    ByeKind,
    Error,
    ErrorField,
    Heartbeat,
    Hello,
    ProtocolError,
    Result,
    SessionConfig,
    Welcome,
    encode,
    received_record,
)
from arlight.protocols.curve import ClientKeys
from arlight.protocols.probe import probe_summary

if TYPE_CHECKING:  # imported when their flags ask for them (foxglove, the web server)
    from arlight.client.foxglove_sinks import LiveSink
    from arlight.client.recording import Recorder
    from arlight.client.web_display import WebDisplay

log = logging.getLogger(__name__)


class DisplayError(RuntimeError):
    """The display cannot go on (no server, or the server refused the subscription)."""


@dataclass(frozen=True)
class DisplayOptions:
    server: str
    session: str
    out_dir: str | None = None  # results.jsonl and frames/ go here
    # engine layouts (pipeline/engine_export.EXPORTERS) added to each results.jsonl line
    exports: tuple[str, ...] = ()
    video: str | None = None  # an .mp4 of the composites
    video_fps: float = 15.0
    max_results: int | None = None  # exit after this many Results
    idle_exit_s: float | None = None  # exit after this long without a Result
    follow: bool = False  # keep waiting for a new stream after the session ends
    print_interval_s: float = 1.0
    record: str | None = None  # an MCAP file of the Results (protocol + Foxglove channels)
    foxglove: tuple[str, int] | None = None  # (host, port): serve Foxglove's WebSocket protocol
    http: tuple[str, int] | None = None  # (host, port): serve the browser display
    client_name: str = "arlight-display"
    heartbeat_interval_s: float = 1.0
    liveness: int = 3
    reconnect_timeout_s: float = 30.0
    # security (docs/guides/security.md): the session's token (printed by `arlight stream`) or the
    # server's admin token; CURVE keys for a keyed server
    token: str | None = None
    keys: ClientKeys | None = None


@dataclass
class DisplaySummary:
    session: str
    results: int = 0
    composites: int = 0
    first_receive: float | None = None  # time.monotonic() of the first Result, seconds
    last_receive: float | None = None  # ... and of the last
    latencies_ms: list[float] = field(default_factory=list)  # the printed latency, per Result
    receive_times_s: list[float] = field(default_factory=list)  # monotonic, per Result
    end_to_end: bool = False  # latencies_ms are capture -> display
    timings_ms: dict[str, list[float]] = field(default_factory=dict)
    frames_dropped: int = 0  # the session's count, from the last Result
    seq_gaps: int = 0  # Results this display did not receive (dropped for it or the session)
    reconnects: int = 0
    ended: bool = False  # the stream ended (Bye from the server)

    @property
    def fps(self) -> float:
        if self.results < 2 or self.first_receive is None or self.last_receive is None:
            return 0.0
        return (self.results - 1) / max(self.last_receive - self.first_receive, 1e-9)

    def to_dict(self) -> dict:
        lat = np.asarray(self.latencies_ms, dtype=float)
        return {
            "session": self.session,
            "results": self.results,
            "composites": self.composites,
            "fps": round(self.fps, 3),
            "latency_ms": {
                "kind": "end_to_end" if self.end_to_end else "server_receive_to_display",
                "median": _round(np.median(lat)) if lat.size else None,
                "p95": _round(np.percentile(lat, 95)) if lat.size else None,
                "max": _round(lat.max()) if lat.size else None,
            },
            "timings_ms_median": {k: _round(np.median(v)) for k, v in self.timings_ms.items()},
            "frames_dropped": self.frames_dropped,
            "results_missed": self.seq_gaps,
            "reconnects": self.reconnects,
            "stream_ended": self.ended,
        }


def _round(x) -> float:
    return round(float(x), 3)


class DisplayClient:
    """Receives one session's Results until the stream ends (or a limit). `run()` blocks."""

    def __init__(
        self,
        options: DisplayOptions,
        on_result: Callable[[Result, dict], None] | None = None,
        printer: Callable[[str], None] | None = None,
        context: zmq.Context | None = None,
        read_delay_s: float = 0.0,
    ):
        self.options = options
        self.on_result = on_result
        self.printer = printer
        self.read_delay_s = read_delay_s  # tests: a display that reads slowly
        self._ctx = context or zmq.Context.instance()
        self._socket: zmq.Socket | None = None
        self._stop = threading.Event()
        self.subscribed = threading.Event()
        self.summary = DisplaySummary(options.session)
        self._heartbeat_s = options.heartbeat_interval_s
        self._last_seq: int | None = None
        self._jsonl: TextIO | None = None
        self._frames_dir: Path | None = None
        self._video: cv2.VideoWriter | None = None
        self._window: deque[tuple[float, float]] = deque()  # (monotonic receive, latency ms)
        self.recorder: Recorder | None = None  # with --record
        self.foxglove: LiveSink | None = None  # with --foxglove
        self.web: WebDisplay | None = None  # with --http
        self.plot_path: Path | None = None  # latency.png, once written

    def stop(self) -> None:
        self._stop.set()

    def _open(self) -> None:
        if self._socket is not None:
            self._socket.close(linger=0)
        self._socket = open_dealer(
            self._ctx, self.options.server, rcvhwm=100, error=DisplayError, keys=self.options.keys
        )
        hello = Hello(
            PROTOCOL_VERSION,
            SessionConfig(
                session=self.options.session,
                client_name=self.options.client_name,
                role="display",
                token=self.options.token,
            ),
        )
        self._dealer.send_multipart(encode(hello), copy=False)
        self._hello_sent = time.monotonic()
        self._welcomed = False

    @property
    def _dealer(self) -> zmq.Socket:
        """The socket to the server (there is one once _open ran)."""
        if self._socket is None:
            raise RuntimeError("not connected: _open() first")
        return self._socket

    def _receive(self, timeout_s: float) -> Received | None:
        """The next message within timeout_s, or None; an undecodable message is logged and
        skipped (it does not count as a sign of life here)."""
        got = receive_message(self._dealer, timeout_s, log)
        if got is not None and isinstance(got.message, ProtocolError):
            return None
        return got

    def _setup_outputs(self) -> None:
        opts = self.options
        if opts.out_dir:
            out = Path(opts.out_dir)
            self._frames_dir = out / "frames"
            self._frames_dir.mkdir(parents=True, exist_ok=True)
            self._jsonl = open(out / "results.jsonl", "w")  # noqa: SIM115 - closed in run()
        try:
            if opts.record:
                from arlight.client.recording import Recorder

                Path(opts.record).parent.mkdir(parents=True, exist_ok=True)
                self.recorder = Recorder(
                    opts.record, source=f"display {opts.session}", frames=False
                )
            if opts.foxglove is not None:
                from arlight.client.foxglove_sinks import LiveSink

                self.foxglove = LiveSink(*opts.foxglove, name=f"arlight {opts.session}")
            if opts.http is not None:
                from arlight.client.web_display import WebDisplay

                self.web = WebDisplay(*opts.http, session=opts.session)
        except OSError as exc:
            flag = (
                "--record"
                if self.recorder is None and opts.record
                else "--foxglove/--port"
                if self.foxglove is None and opts.foxglove
                else "--http"
            )
            self._close()
            raise DisplayError(f"{flag}: {exc}") from None
        if self.printer is not None:
            if self.foxglove is not None:
                self.printer(
                    f"display {opts.session}: Foxglove WebSocket on "
                    f"ws://{self.foxglove.host}:{self.foxglove.port} (Foxglove app: "
                    "Open connection -> Foxglove WebSocket)"
                )
            if self.web is not None:
                self.printer(f"display {opts.session}: browser display on {self.web.url}")

    def _write_composite(self, result: Result) -> None:
        image = result.composite
        if image is None:
            return
        self.summary.composites += 1
        bgr = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR)
        if self._frames_dir is not None:
            cv2.imwrite(str(self._frames_dir / f"{result.seq:06d}.png"), bgr)
        if self.options.video:
            if self._video is None:
                h, w = bgr.shape[:2]
                Path(self.options.video).parent.mkdir(parents=True, exist_ok=True)
                fourcc = cv2.VideoWriter.fourcc(*"mp4v")
                self._video = cv2.VideoWriter(
                    self.options.video, fourcc, self.options.video_fps, (w, h)
                )
                self._video_size = (w, h)
                if not self._video.isOpened():
                    raise DisplayError(
                        f"cannot write the video --video {self.options.video!r} "
                        "(OpenCV has no mp4v encoder here?)"
                    )
            if (bgr.shape[1], bgr.shape[0]) != self._video_size:
                bgr = cv2.resize(bgr, self._video_size, interpolation=cv2.INTER_AREA)
            self._video.write(bgr)

    def _on_result(self, result: Result, got: Received) -> None:
        s = self.summary
        if self._last_seq is not None and result.seq > self._last_seq + 1:
            s.seq_gaps += result.seq - self._last_seq - 1
        self._last_seq = result.seq
        record = received_record(result, got.receive_time_wall)  # with the session's exports
        if self.options.exports:  # and the layouts this display asked for, computed here
            from arlight.pipeline.engine_export import camera_exports, main_source_from_wire

            light = result.sh_rgb if result.sh_rgb is not None else result.sh
            source = main_source_from_wire(result.compact_sources)  # the main light, if any
            record["exports"] = {
                **(result.exports or {}),
                **camera_exports(
                    light,
                    result.pose,
                    self.options.exports,
                    result.dominant_direction_world,
                    source,
                ),
            }
        if result.probe is not None:  # what came, never the texels (output-record.md)
            record["probe"] = probe_summary(result.probe)
        now_m = got.receive_time_mono
        s.results += 1
        s.first_receive = now_m if s.first_receive is None else s.first_receive
        s.last_receive = now_m
        s.frames_dropped = result.frames_dropped
        if record["end_to_end_ms"] is not None:
            s.end_to_end = True
            latency = record["end_to_end_ms"]
        else:
            latency = record["in_server_ms"] + record["server_to_client_ms"]
        s.latencies_ms.append(latency)
        s.receive_times_s.append(now_m)
        for k, v in result.timings_ms.items():
            s.timings_ms.setdefault(k, []).append(v)
        self._window.append((now_m, latency))
        with uninterrupted():  # a stop signal waits: every file holds this Result or none does
            if self._jsonl is not None:
                self._jsonl.write(json.dumps(record) + "\n")
                self._jsonl.flush()
            self._write_composite(result)
            if self.recorder is not None:
                self.recorder.write_result(result, record, parts=got.parts or None)
        if self.foxglove is not None:
            from arlight.client.foxglove_sinks import publish_result

            publish_result(self.foxglove, result, record, time.time_ns(), parts=got.parts or None)
        if self.web is not None:
            self.web.update(result, record, parts=got.parts or None)
        if self.on_result is not None:
            self.on_result(result, record)

    def _print_rate(self, now_m: float) -> None:
        while self._window and self._window[0][0] < now_m - max(self.options.print_interval_s, 1.0):
            self._window.popleft()
        if self.printer is None:
            return
        n = len(self._window)
        span = max(self.options.print_interval_s, 1.0)
        kind = "end-to-end" if self.summary.end_to_end else "server-receive-to-display"
        latency = f"{np.median([x for _, x in self._window]):6.0f} ms" if n else "     - ms"
        self.printer(
            f"display {self.options.session}: {n / span:5.1f} fps, {kind} latency "
            f"{latency}, {self.summary.results} results, session dropped "
            f"{self.summary.frames_dropped}"
        )

    def run(self) -> DisplaySummary:
        """Receive Results until the stream ends, a limit is reached or stop() is called."""
        opts = self.options
        self._setup_outputs()
        try:
            self._open()
            now_m = time.monotonic()
            self._last_heard_mono = self._last_sent_mono = self._last_result_mono = now_m
            self._lost_since_mono: float | None = None
            next_print_mono = now_m + opts.print_interval_s
            while not self._stop.is_set():
                got = self._receive(0.1)
                if got is not None and self._on_message(got) == "end":
                    break
                now_m = time.monotonic()
                if self._limit_reached(now_m):
                    break
                if now_m >= next_print_mono:
                    self._print_rate(now_m)
                    next_print_mono = now_m + opts.print_interval_s
                self._keep_alive(now_m)
            if not self.summary.ended:
                self._say_bye()
        finally:
            self._close()
        return self.summary

    def _on_message(self, got: Received) -> str | None:
        """Act on one server message; "end" when the stream has ended (and not --follow)."""
        message = got.message
        self._last_heard_mono = got.receive_time_mono
        self._lost_since_mono = None
        if isinstance(message, Welcome):
            self._welcomed = True
            self._heartbeat_s = message.heartbeat_interval_s
            self.subscribed.set()
        elif isinstance(message, Result):
            self._on_result(message, got)
            self._last_result_mono = time.monotonic()
            if self.read_delay_s:
                time.sleep(self.read_delay_s)
        elif isinstance(message, Error):
            if message.retryable and message.field == ErrorField.SESSION:
                self._resubscribe("the server does not know this display")
            elif message.code == "unauthorized":  # refused, or unsubscribed: a new session
                # of this name has another token
                raise DisplayError(
                    f"the server refused the subscription: {message.message} (--token)"
                )
            elif not self._welcomed:
                raise DisplayError(
                    f"the server refused the subscription: {message.code}: {message.message}"
                )
        elif isinstance(message, Bye):
            if message.kind != ByeKind.END_OF_STREAM:  # shutdown: wait for the next server
                self._resubscribe(f"the server said Bye ({message.kind}: {message.reason})")
            elif not self.options.follow:
                self.summary.ended = True
                return "end"
        return None

    def _limit_reached(self, now_m: float) -> bool:
        opts = self.options
        if opts.max_results is not None and self.summary.results >= opts.max_results:
            return True
        return opts.idle_exit_s is not None and now_m - self._last_result_mono > opts.idle_exit_s

    def _keep_alive(self, now_m: float) -> None:
        """Resubscribe when the server went silent (DisplayError after reconnect_timeout_s);
        send a Heartbeat every interval."""
        opts = self.options
        silent_s = now_m - self._last_heard_mono
        if silent_s > opts.liveness * self._heartbeat_s:
            if self._lost_since_mono is None:
                self._lost_since_mono = self._last_heard_mono  # lost since last heard from
            if now_m - self._lost_since_mono > opts.reconnect_timeout_s:
                raise DisplayError(
                    f"no arlight server answered at {opts.server} within "
                    f"{opts.reconnect_timeout_s:.0f} s (--reconnect-timeout); "
                    "check --server and that `arlight serve` runs"
                )
            self._resubscribe(f"no message from the server for {silent_s:.1f} s")
            self._last_heard_mono = time.monotonic()
        if now_m - self._last_sent_mono >= self._heartbeat_s:
            try:
                self._dealer.send_multipart(encode(Heartbeat(time.time())), zmq.NOBLOCK, copy=False)
            except zmq.Again:
                pass  # queue full while the server is away: the next one will do
            self._last_sent_mono = now_m

    def _say_bye(self) -> None:
        if self._socket is None:
            return
        try:
            self._socket.send_multipart(
                encode(Bye("display closed", ByeKind.LEAVING)), zmq.NOBLOCK, copy=False
            )
            time.sleep(0.02)
        except zmq.Again:
            pass

    def _close(self) -> None:
        if self._socket is not None:
            self._socket.close(linger=0)
            self._socket = None
        if self._jsonl is not None:
            self._jsonl.close()
            self._jsonl = None
        if self._video is not None:
            self._video.release()
            self._video = None
        for name in ("recorder", "foxglove", "web"):
            output = getattr(self, name)
            if output is not None:
                output.close()
                setattr(self, name, None)
        if self.options.out_dir and self.summary.results:
            from arlight.client.latency_plot import write_latency_plot

            kind = "end-to-end" if self.summary.end_to_end else "server-receive-to-display"
            self.plot_path = write_latency_plot(
                Path(self.options.out_dir) / "latency.png",
                self.summary.receive_times_s,
                self.summary.latencies_ms,
                kind,
                title=f"arlight display {self.options.session}",
            )

    def _resubscribe(self, why: str) -> None:
        log.warning("display %s: %s; subscribing again", self.options.session, why)
        self.summary.reconnects += 1
        self._open()


def print_line(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
