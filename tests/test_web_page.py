"""The browser page (client/web/, issue 34 item 7) in headless Chromium, fed by a real
WebDisplay over loopback: the sphere lit in the camera's exposure (a dim light stays dim, a
bright one clips; not scaled to its own peak), the confidence with its reason, and the plots
over time. A screenshot is checked pixel by pixel and kept (skipped, with the reason, where
no Chromium is installed)."""

from __future__ import annotations

import json
import math
import time

import cv2
import numpy as np
import pytest
from browser_support import Chromium, chromium_or_skip

from arlight.client.web_display import WebDisplay
from arlight.protocols import Result, received_record

REASON = "few samples: 120 pixels with depth fitted (need 2000)"


def _result(seq: int, e_uniform: float, confidence: float, reason: str) -> tuple[Result, dict]:
    """A Result whose light is a uniform radiance giving irradiance e_uniform everywhere
    (sh[0] = E / (pi * Y00)) plus a little band 1 towards the camera's upper right."""
    now = time.time()
    sh = [e_uniform / (math.pi * 0.282095), 0.0, 0.0, 0.0] + [0.0] * 12
    result = Result(
        seq=seq,
        timestamp=now - 0.05,
        sh=sh,
        sh_camera=sh,
        dominant_direction_camera=[0.6, -0.8, 0.0],
        dominant_direction_world=[0.0, 0.0, 1.0],
        intensity=1.0,
        confidence={"value": confidence, "reason": reason},
        pose=np.eye(4).tolist(),
        timings_ms={"Input": 1.5, "LightEst": 2.0},
        frames_received=seq + 1,
        frames_processed=seq + 1,
        frames_dropped=0,
        server_receive_time=now - 0.03 - 0.01 * seq,
        server_finish_time=now - 0.01,
        composite=np.full((120, 160, 3), 90, np.uint8),
    )
    return result, received_record(result, now)


def _srgb8(v: float) -> int:
    v = min(max(v, 0.0), 1.0)
    return round(255 * (12.92 * v if v <= 0.0031308 else 1.055 * v ** (1 / 2.4) - 0.055))


def _wait(condition, what: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.05)


def _sphere_patch(browser, tab, shot: np.ndarray) -> np.ndarray:
    rect = json.loads(
        browser.evaluate(
            tab, "JSON.stringify(document.getElementById('sphere').getBoundingClientRect())"
        )
    )
    ratio = shot.shape[1] / 1000  # device pixels per CSS pixel (the window is 1000 wide)
    # 30 CSS pixels left of and below the centre: off the arrow towards the upper right
    cx = int((rect["x"] + rect["width"] / 2 - 30) * ratio)
    cy = int((rect["y"] + rect["height"] / 2 + 30) * ratio)
    return shot[cy - 3 : cy + 4, cx - 3 : cx + 4].reshape(-1, 3)


def test_page_in_exposure_with_reason_and_plots(tmp_path):
    executable = chromium_or_skip()
    web = WebDisplay("127.0.0.1", 0, session="page")
    try:
        with Chromium(executable, window=(1000, 900)) as browser:
            tab = browser.open(web.url)
            _wait(
                lambda: browser.evaluate(tab, "document.body ? 1 : 0") == 1,
                "the page",
            )
            time.sleep(0.5)  # the page's EventSource connects
            # a dim light (E = 0.05: a dark grey, not white) and low confidence with a reason
            for seq in range(12):
                web.update(*_result(seq, 0.05, 0.1 + 0.05 * seq, REASON))
                time.sleep(0.03)
            _wait(
                lambda: browser.evaluate(tab, "document.body.dataset.frame") == "11",
                "the twelfth Result",
            )
            dim = browser.evaluate(
                tab,
                """JSON.stringify({
                reason: document.getElementById('confidence-reason').textContent,
                points: Number(document.body.dataset.plotPoints),
                peak: Number(document.body.dataset.spherePeak)})""",
            )
            png_dim = browser.screenshot(tab)
            # a bright light (E = 3): clips to white, as a camera would
            web.update(*_result(12, 3.0, 0.9, ""))
            _wait(
                lambda: browser.evaluate(tab, "document.body.dataset.frame") == "12",
                "the bright Result",
            )
            bright = json.loads(
                browser.evaluate(
                    tab,
                    """JSON.stringify({
                    reason: document.getElementById('confidence-reason').textContent,
                    points: Number(document.body.dataset.plotPoints)})""",
                )
            )
            png_bright = browser.screenshot(tab)
            shot_dim = cv2.imdecode(np.frombuffer(png_dim, np.uint8), cv2.IMREAD_COLOR)
            shot_bright = cv2.imdecode(np.frombuffer(png_bright, np.uint8), cv2.IMREAD_COLOR)
            centre_dim = _sphere_patch(browser, tab, shot_dim)
            centre_bright = _sphere_patch(browser, tab, shot_bright)
            plot = json.loads(
                browser.evaluate(
                    tab,
                    "JSON.stringify(document.getElementById('plot-confidence')"
                    ".getBoundingClientRect())",
                )
            )
    finally:
        web.close()
    (tmp_path / "page_dim.png").write_bytes(png_dim)
    (tmp_path / "page_bright.png").write_bytes(png_bright)
    dim = json.loads(dim)
    assert dim["reason"] == REASON and bright["reason"].startswith("no reason")
    assert dim["points"] == 12 and bright["points"] == 13
    assert dim["peak"] == pytest.approx(0.05, rel=1e-3)
    # the sphere (the light is uniform: every normal alike) in the camera's exposure: sRGB(0.05),
    # not the peak-normalised white the page drew before
    assert np.abs(centre_dim.astype(int) - _srgb8(0.05)).max() <= 3, centre_dim[:3]
    assert centre_bright.min() >= 250  # clipped
    # the confidence plot drew its rising line on the panel (not an empty canvas)
    ratio = shot_dim.shape[1] / 1000
    x0, y0 = int(plot["x"] * ratio), int(plot["y"] * ratio)
    w, h = int(plot["width"] * ratio), int(plot["height"] * ratio)
    area = shot_dim[y0 : y0 + h, x0 : x0 + w]
    green = (area[..., 1] > 150) & (area[..., 2] < 80)  # #06d6a0 in BGR: (160, 214, 6)
    assert green.sum() > 20
    cols = np.nonzero(green.any(axis=0))[0]
    rows_left = np.nonzero(green[:, cols[0]])[0].mean()
    rows_right = np.nonzero(green[:, cols[-1]])[0].mean()
    assert rows_right < rows_left  # confidence rose from 0.1 to 0.65: the line climbs
