"""The browser display (`arlight display --http`): its HTTP endpoints over loopback, and the
page in headless Chromium against a running server, display and capture client (skipped,
with the reason, where no Chromium is installed)."""

from __future__ import annotations

import http.client
import json
import threading
import time

import cv2
import numpy as np
import pytest
from browser_support import Chromium, chromium_or_skip
from streaming_support import flat_source, identity_step, run_with_timeout, server_factory

from arlight.client.capture import CaptureClient, StreamOptions
from arlight.client.display import DisplayClient, DisplayOptions
from arlight.client.web_display import MJPEG_BOUNDARY, WebDisplay, parse_http_address
from arlight.protocols import Result, received_record


@pytest.fixture
def make_server():
    yield from server_factory()


def _result(seq: int, value: int = 120) -> tuple[Result, dict]:
    now = time.time()
    sh = [0.5, 0.0, -0.3, 0.2] + [0.0] * 12
    result = Result(
        seq=seq,
        timestamp=now - 0.05,
        sh=sh,
        sh_camera=sh,
        dominant_direction_camera=[0.6, -0.8, 0.0],
        dominant_direction_world=[0.0, 0.0, 1.0],
        intensity=1.0,
        confidence={"value": 0.5},
        pose=np.eye(4).tolist(),
        timings_ms={"Input": 1.5, "LightEst": 2.0},
        frames_received=seq + 1,
        frames_processed=seq + 1,
        frames_dropped=0,
        server_receive_time=now - 0.03,
        server_finish_time=now - 0.01,
        composite=np.full((24, 32, 3), value, np.uint8),
    )
    return result, received_record(result, now)


class TestAddress:
    @pytest.mark.parametrize(
        "text, expected",
        [
            ("8080", ("127.0.0.1", 8080)),
            ("0.0.0.0:80", ("0.0.0.0", 80)),
            ("[::1]:9000", ("::1", 9000)),
            (":0", ("127.0.0.1", 0)),
        ],
    )
    def test_parses(self, text, expected):
        assert parse_http_address(text) == expected

    @pytest.mark.parametrize("text", ["", "host:", "x:99999", "a:b"])
    def test_refuses_naming_the_flag(self, text):
        with pytest.raises(ValueError, match="--http"):
            parse_http_address(text)


class TestEndpoints:
    def test_page_state_frame_mjpeg_and_events(self):
        web = WebDisplay("127.0.0.1", 0, session="ep")
        try:
            conn = http.client.HTTPConnection("127.0.0.1", web.port, timeout=10)
            for path, kind in (("/", "text/html"), ("/display.js", "text/javascript")):
                conn.request("GET", path)
                reply = conn.getresponse()
                body = reply.read()
                assert reply.status == 200 and reply.getheader("Content-Type").startswith(kind)
                assert b"http://" not in body and b"https://" not in body  # no CDN
            conn.request("GET", "/frame.jpg")
            reply = conn.getresponse()
            assert reply.status == 404 and reply.read()
            web.update(*_result(0, value=200))
            conn.request("GET", "/state.json")
            state = json.loads(conn.getresponse().read())
            assert state["results"] == 1 and state["frame"] == 0
            assert state["timings_ms"] == {"Input": 1.5, "LightEst": 2.0}
            assert state["latency_kind"] == "end_to_end" and state["latency_ms"] > 0
            conn.request("GET", "/frame.jpg")
            jpeg = conn.getresponse().read()
            image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
            assert image.shape == (24, 32, 3) and abs(float(image.mean()) - 200) < 3

            stream = http.client.HTTPConnection("127.0.0.1", web.port, timeout=10)
            stream.request("GET", "/stream.mjpeg")
            mjpeg = stream.getresponse()
            assert (
                mjpeg.getheader("Content-Type")
                == f"multipart/x-mixed-replace; boundary={MJPEG_BOUNDARY}"
            )
            events = http.client.HTTPConnection("127.0.0.1", web.port, timeout=10)
            events.request("GET", "/events")
            sse = events.getresponse()
            assert sse.getheader("Content-Type") == "text/event-stream"
            first = json.loads(sse.readline().removeprefix(b"data: "))
            sse.readline()
            assert first["frame"] == 0

            def mjpeg_part() -> bytes:
                assert mjpeg.readline() == f"--{MJPEG_BOUNDARY}\r\n".encode()
                headers = {}
                while (line := mjpeg.readline()) != b"\r\n":
                    key, value = line.decode().split(":", 1)
                    headers[key.strip().lower()] = value.strip()
                assert headers["content-type"] == "image/jpeg"
                part = mjpeg.read(int(headers["content-length"]))
                assert mjpeg.readline() == b"\r\n"
                return part

            parts = [mjpeg_part()]  # a new viewer gets the newest composite at once
            for seq in (1, 2):
                web.update(*_result(seq, value=60 * seq))
                parts.append(mjpeg_part())
                data = sse.readline()
                sse.readline()
                assert json.loads(data.removeprefix(b"data: "))["frame"] == seq
            means = [
                cv2.imdecode(np.frombuffer(p, np.uint8), cv2.IMREAD_COLOR).mean() for p in parts
            ]
            np.testing.assert_allclose(means, [200, 60, 120], atol=3)
            _wait(lambda: web.jpegs_streamed == 3 and web.events_sent == 3, "the counts")
            stream.close()
            events.close()
            conn.close()
        finally:
            web.close()


class TestBrowser:
    def test_page_shows_frames_and_live_numbers_in_chromium(self, make_server, tmp_path):
        """The page against a running server and display: frames arrive (MJPEG), the numbers
        update (Server-Sent Events), the sphere is drawn; a screenshot is kept."""
        executable = chromium_or_skip()
        server = make_server(process=identity_step())
        display = DisplayClient(
            DisplayOptions(
                server=server.connect_address,
                session="web",
                http=("127.0.0.1", 0),
                idle_exit_s=30.0,
            )
        )
        thread = threading.Thread(target=display.run, daemon=True)
        thread.start()
        assert display.subscribed.wait(10)
        web = display.web
        with Chromium(executable) as browser:
            tab = browser.open(web.url)
            _wait(
                lambda: (
                    (
                        browser.evaluate(
                            tab, "document.body ? Number(document.body.dataset.updates) : 0"
                        )
                        or 0
                    )
                    >= 1
                ),
                "the page's first state",
            )
            options = StreamOptions(
                server=server.connect_address,
                session="web",
                mode="live",
                rate="native",
                want_composite=True,
                timestamps="capture",
            )
            source = flat_source(75, width=160, height=120, base=180)  # 2.5 s at 30 fps
            streamer = threading.Thread(
                target=lambda: run_with_timeout(lambda: CaptureClient(source, options).run()),
                daemon=True,
            )
            streamer.start()
            seen = "document.body.dataset.framesSeen || ''"
            _wait(lambda: len(browser.evaluate(tab, seen).split(",")) >= 5, "five Results shown")
            state = browser.evaluate(
                tab,
                """JSON.stringify({
                fps: document.getElementById('fps').textContent,
                latency: document.getElementById('latency').textContent,
                confidence: document.getElementById('confidence').textContent,
                frame: document.getElementById('frame').textContent,
                timings: document.getElementById('timings').textContent,
                status: document.getElementById('status').textContent,
                width: document.getElementById('composite').naturalWidth,
                rect: document.getElementById('composite').getBoundingClientRect(),
                sphere: document.getElementById('sphere').getBoundingClientRect()})""",
            )
            png = browser.screenshot(tab)
            later = browser.evaluate(tab, seen)
            _wait(
                lambda: browser.evaluate(tab, seen) != later or not streamer.is_alive(),
                "the numbers to change again",
            )
            changed = browser.evaluate(tab, seen) != later
            streamer.join(30)
            later2 = browser.evaluate(tab, seen)
        thread.join(30)
        state = json.loads(state)
        (tmp_path / "page.png").write_bytes(png)
        frames = [int(x) for x in later2.split(",")]
        assert frames == sorted(frames) and len(set(frames)) >= 5  # the numbers update
        assert changed or frames[-1] >= 60  # still updating, or at the stream's end
        assert float(state["fps"]) > 5 and float(state["latency"]) >= 0
        assert state["status"] == "live" and "Identity" in state["timings"]
        assert state["width"] == 160  # the MJPEG stream's frames reached the <img>
        assert web.jpegs_streamed >= 2 and web.events_sent >= 5
        shot = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        ratio = shot.shape[1] / 1000  # device pixels per CSS pixel
        r = {k: int(v * ratio) for k, v in state["rect"].items() if k in "xywidthheight"}
        inner = shot[r["y"] + 5 : r["y"] + r["height"] - 5, r["x"] + 5 : r["x"] + r["width"] - 5]
        assert inner.size and inner.mean() > 150  # the bright composite, not the dark page
        s = {k: int(v * ratio) for k, v in state["sphere"].items() if k in "xywidthheight"}
        disc = shot[s["y"] : s["y"] + s["height"], s["x"] : s["x"] + s["width"]]
        assert disc.max() > 200 and disc.std() > 20  # a shaded sphere on the dark panel


def _wait(condition, what: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.05)
