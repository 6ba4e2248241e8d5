"""Headless Chromium for the browser display's tests, driven over the Chrome DevTools
protocol on a pipe (`--remote-debugging-pipe`: JSON messages ending in NUL on file
descriptors 3 and 4), so no WebSocket client or browser-automation package is needed.

`chromium_or_skip()` finds Debian's `chromium` (or `$ARLIGHT_CHROMIUM`) and skips the test,
saying why, where there is none (run-tests.sh installs it where apt is available).
"""

from __future__ import annotations

import base64
import json
import os
import select
import shutil
import subprocess
import tempfile
import time

import pytest

CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def chromium_or_skip() -> str:
    """The path of a Chromium executable, or pytest.skip with the reason."""
    given = os.environ.get("ARLIGHT_CHROMIUM")
    if given:
        if shutil.which(given):
            return shutil.which(given)
        pytest.skip(f"ARLIGHT_CHROMIUM={given!r} is not an executable")
    for name in CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    pytest.skip(
        "no Chromium installed (apt-get install chromium; run-tests.sh does so "
        "where apt is available): the browser display's page test needs one"
    )


class Chromium:
    """One headless Chromium; call(method, params, session) sends a DevTools command and
    returns its result. Use as a context manager (the browser and its profile go away)."""

    def __init__(self, executable: str, window: tuple[int, int] = (1000, 640)):
        self._profile = tempfile.TemporaryDirectory(prefix="arlight-chromium-")
        to_read, self._to_write = os.pipe()
        self._from_read, from_write = os.pipe()

        def child_fds() -> None:  # the protocol's descriptors 3 (commands) and 4 (replies)
            a, b = os.dup(to_read), os.dup(from_write)
            os.dup2(a, 3)
            os.dup2(b, 4)

        self.process = subprocess.Popen(
            [
                executable,
                "--headless=new",
                "--no-sandbox",
                "--disable-gpu",
                "--no-first-run",
                "--disable-extensions",
                "--remote-debugging-pipe",
                f"--user-data-dir={self._profile.name}",
                f"--window-size={window[0]},{window[1]}",
                "about:blank",
            ],
            preexec_fn=child_fds,
            close_fds=False,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        os.close(to_read)
        os.close(from_write)
        self._id = 0
        self._buffer = b""

    def call(
        self,
        method: str,
        params: dict | None = None,
        session: str | None = None,
        timeout_s: float = 20.0,
    ) -> dict:
        self._id += 1
        message = {"id": self._id, "method": method, "params": params or {}}
        if session is not None:
            message["sessionId"] = session
        os.write(self._to_write, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout_s
        while True:
            while b"\0" in self._buffer:
                raw, self._buffer = self._buffer.split(b"\0", 1)
                reply = json.loads(raw)
                if reply.get("id") == self._id:
                    if "error" in reply:
                        raise RuntimeError(f"{method}: {reply['error']}")
                    return reply["result"]
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"Chromium did not answer {method} in {timeout_s:.0f} s")
            ready, _, _ = select.select([self._from_read], [], [], left)
            if ready:
                chunk = os.read(self._from_read, 1 << 20)
                if not chunk:
                    raise RuntimeError("Chromium exited")
                self._buffer += chunk

    def open(self, url: str) -> str:
        """Open url in a new tab; the DevTools session id to pass to call()."""
        target = self.call("Target.createTarget", {"url": url})["targetId"]
        return self.call("Target.attachToTarget", {"targetId": target, "flatten": True})[
            "sessionId"
        ]

    def evaluate(self, session: str, expression: str):
        """The JSON value of a JavaScript expression in the tab."""
        reply = self.call(
            "Runtime.evaluate", {"expression": expression, "returnByValue": True}, session
        )
        return reply["result"].get("value")

    def screenshot(self, session: str) -> bytes:
        """The tab as a PNG."""
        return base64.b64decode(
            self.call("Page.captureScreenshot", {"format": "png"}, session)["data"]
        )

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout_s=5.0)
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(5)
        for fd in (self._to_write, self._from_read):
            try:
                os.close(fd)
            except OSError:
                pass
        self._profile.cleanup()

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
