"""The browser display (`arlight display --http [HOST:]PORT`): a small HTTP server, standard
library only, that shows one session's Results in a browser tab, live.

Everything the page needs is served from here (no CDN):
- `/` the page (client/web/index.html), `/display.js` its script: the composite, a sphere
  shaded by the estimated SH with the dominant direction drawn on it, confidence, frames
  per second, latency and per-stage timings;
- `/stream.mjpeg` the composites as an MJPEG stream (multipart/x-mixed-replace of JPEGs, as
  IP cameras serve them; any `<img>` or VLC plays it);
- `/events` Server-Sent Events (text/event-stream): the state below as JSON, once per Result;
- `/state.json` that state now, `/frame.jpg` the newest composite.

State (JSON): `results`, `frame` (seq), `timestamp` (s), `fps` (Results per second over the
last FPS_WINDOW_S, display clock), `latency_ms` and `latency_kind` (end-to-end where the frames
carry capture times, else server receive -> display), `pipeline_ms`, `timings_ms` (per
stage), `confidence` (0..1) and its `confidence_detail`, `dominant_direction_camera` (unit,
OpenCV camera axes), `sh_camera` (radiance SH, luminance, camera frame, this project's basis),
`frames_dropped`, `has_composite`.

The server runs on daemon threads; `close()` stops it. At most MAX_STREAMS streaming
connections (MJPEG + events) at once; more get 503.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Mapping
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np

from arlight.client.connection import encoded_image

log = logging.getLogger(__name__)

WEB_DIR = Path(__file__).with_name("web")
FPS_WINDOW_S = 2.0
MAX_STREAMS = 16
JPEG_QUALITY = 85
MJPEG_BOUNDARY = "arlightframe"
_STATIC = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/index.html": ("index.html", "text/html; charset=utf-8"),
    "/display.js": ("display.js", "text/javascript; charset=utf-8"),
}


def parse_http_address(text: str) -> tuple[str, int]:
    """`[HOST:]PORT` of --http as (host, port); host defaults to 127.0.0.1 (loopback only;
    give 0.0.0.0:PORT for a tablet on the network). ValueError naming --http otherwise."""
    host, sep, port = text.rpartition(":")
    host = host if sep else "127.0.0.1"
    host = host.strip("[]") or "127.0.0.1"
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not 0 <= number <= 65535:
        raise ValueError(f"--http expects [HOST:]PORT with PORT 0..65535, got {text!r}")
    return host, number


class WebDisplay:
    """Serves the page and the live stream of one session on host:port (port 0 = any free
    port; `self.port` says which). Feed it with update(result, record)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, session: str = ""):
        self.session = session
        self._cond = threading.Condition()
        self._jpeg: bytes | None = None
        self._state: dict = {"session": session, "results": 0}
        self._version = 0  # counts updates; streams wait for it to change
        self._closed = False
        self._streams = 0
        self._window: deque[float] = deque()
        self.jpegs_streamed = 0  # MJPEG parts written to browsers, all connections
        self.events_sent = 0
        handler = type("Handler", (_Handler,), {"display": self})
        try:
            self._server = ThreadingHTTPServer((host, int(port)), handler)
        except OSError as exc:
            raise OSError(
                f"cannot serve the browser display on {host}:{port} (--http): {exc.strerror or exc}"
            ) from None
        self._server.daemon_threads = True
        bound_host, bound_port = self._server.server_address[:2]  # port 0: the one it chose
        self.host, self.port = str(bound_host), int(bound_port)

        self._thread = threading.Thread(
            target=self._server.serve_forever,
            kwargs={"poll_interval": 0.2},
            name="arlight-web-display",
            daemon=True,
        )
        self._thread.start()

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return f"http://{host}:{self.port}/"

    def update(self, result, record: Mapping, parts=None) -> None:
        """A new Result (protocols Result) and its received record (received_record);
        parts: the Result's message parts as received, whose JPEG composite is then streamed
        as it came (else the composite is encoded here)."""
        now = time.monotonic()
        self._window.append(now)
        while self._window and self._window[0] < now - FPS_WINDOW_S:
            self._window.popleft()
        span = self._window[-1] - self._window[0] if len(self._window) > 1 else 0.0
        fps = (len(self._window) - 1) / span if span > 0 else 0.0
        jpeg = None
        encoded = encoded_image(parts, "composite")
        if encoded is not None and encoded[0] == "jpeg":
            jpeg = encoded[1]
        elif result.composite is not None:
            bgr = cv2.cvtColor(np.ascontiguousarray(result.composite), cv2.COLOR_RGB2BGR)
            ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            jpeg = buf.tobytes() if ok else None
        e2e = record.get("end_to_end_ms")
        latency = (
            e2e if e2e is not None else (record["in_server_ms"] + record["server_to_client_ms"])
        )
        with self._cond:
            results = self._state.get("results", 0) + 1
            self._state = {
                "session": self.session,
                "results": results,
                "frame": result.seq,
                "timestamp": result.timestamp,
                "fps": round(fps, 2),
                "latency_ms": round(float(latency), 1),
                "latency_kind": "end_to_end" if e2e is not None else "server_receive_to_display",
                "pipeline_ms": record.get("pipeline_ms"),
                "timings_ms": {k: round(float(v), 2) for k, v in result.timings_ms.items()},
                "confidence": float(result.confidence.value),
                "confidence_detail": result.confidence.to_dict(),
                "dominant_direction_camera": [float(x) for x in result.dominant_direction_camera],
                "sh_camera": [float(x) for x in (result.sh_camera or result.sh)],
                "frames_dropped": result.frames_dropped,
                "has_composite": jpeg is not None or self._jpeg is not None,
            }
            if jpeg is not None:
                self._jpeg = jpeg
            self._version += 1
            self._cond.notify_all()

    def state(self) -> dict:
        with self._cond:
            return dict(self._state)

    def wait_update(self, version: int, timeout_s: float) -> tuple[int, dict, bytes | None]:
        """Block until an update newer than `version` (or timeout_s, or close); returns the
        current (version, state, jpeg)."""
        with self._cond:
            self._cond.wait_for(lambda: self._version != version or self._closed, timeout_s)
            return self._version, dict(self._state), self._jpeg

    @property
    def closed(self) -> bool:
        return self._closed

    def open_stream(self) -> bool:
        with self._cond:
            if self._streams >= MAX_STREAMS or self._closed:
                return False
            self._streams += 1
            return True

    def close_stream(self) -> None:
        with self._cond:
            self._streams -= 1

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5.0)


class _Handler(BaseHTTPRequestHandler):
    display: WebDisplay
    protocol_version = "HTTP/1.1"
    server_version = "arlight-display"

    def log_message(self, format: str, *args) -> None:  # noqa: A002 - the base's name
        log.debug("web display: " + format, *args)

    def _send(self, status: int, body: bytes, content_type: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self) -> None:  # noqa: N802 - the base's name
        path = self.path.split("?", 1)[0]
        if path in _STATIC:
            name, content_type = _STATIC[path]
            self._send(HTTPStatus.OK, (WEB_DIR / name).read_bytes(), content_type)
        elif path == "/state.json":
            self._send(HTTPStatus.OK, json.dumps(self.display.state()).encode(), "application/json")
        elif path == "/frame.jpg":
            _, _, jpeg = self.display.wait_update(-1, 0.0)
            if jpeg is None:
                self._send(HTTPStatus.NOT_FOUND, b"no composite yet\n", "text/plain")
            else:
                self._send(HTTPStatus.OK, jpeg, "image/jpeg")
        elif path in ("/stream.mjpeg", "/events"):
            if not self.display.open_stream():
                self._send(HTTPStatus.SERVICE_UNAVAILABLE, b"too many streams\n", "text/plain")
                return
            try:
                (self._mjpeg if path == "/stream.mjpeg" else self._events)()
            except (BrokenPipeError, ConnectionResetError, TimeoutError):
                pass  # the browser went away
            finally:
                self.display.close_stream()
                self.close_connection = True
        else:
            self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")

    def _mjpeg(self) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={MJPEG_BOUNDARY}")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        version, sent = -1, None
        while not self.display.closed:
            version, _, jpeg = self.display.wait_update(version, 1.0)
            if jpeg is None or jpeg is sent:
                continue
            self.wfile.write(
                f"--{MJPEG_BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                f"Content-Length: {len(jpeg)}\r\n\r\n".encode()
                + jpeg
                + b"\r\n"
            )
            self.wfile.flush()
            sent = jpeg
            self.display.jpegs_streamed += 1

    def _events(self) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        version = -1
        while not self.display.closed:
            new, state, _ = self.display.wait_update(version, 1.0)
            if new == version:
                self.wfile.write(b": keep-alive\n\n")
            else:
                self.wfile.write(b"data: " + json.dumps(state).encode() + b"\n\n")
                self.display.events_sent += 1
            self.wfile.flush()
            version = new
