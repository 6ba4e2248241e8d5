"""`arlight demo`: the whole service on this machine, in one process.

It starts a server on a free loopback port, subscribes a display client to a session, streams
the built-in synthetic scene (known light) into that session in lossless mode with
composites and a virtual scene (a sphere and a torus anchored on the detected ground,
`virtual_scene.demo_scene`), and writes what the display received: `frames/` (the
composites: the objects rendered in with their shadows),
`results.jsonl`, and `summary.json` (frames per second, latencies, median per-stage
timings, the angular error of the dominant light against the light that can reach the
scene, its upper hemisphere, and, on frames that kept a compact source, that source's
angle from the scene's sun).
The server, the display and the capture client talk over real TCP sockets, exactly as they
would across machines.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from arlight import __version__

DEMO_SESSION = "demo"


def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return float("nan")
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def _spearman(confidences: dict[int, float], errors: dict[int, float]) -> float | None:
    """Spearman's rank correlation of the confidence with the error over the frames that have
    both (negative: the confidence falls as the error grows); None where it is undefined."""
    from arlight.report import spearman

    rho = spearman([(confidences[k], e) for k, e in errors.items() if k in confidences])
    return None if rho is None else round(rho, 3)


def run_demo(
    out_dir: str | Path = "out",
    frames: int = 24,
    size: tuple[int, int] = (320, 240),
    preset: str = "fast",
    video: str | None = None,
    printer: Callable[[str], None] = print,
) -> dict:
    """Run the demo; returns the summary (also written to out_dir/summary.json)."""
    from arlight.client.capture import CaptureClient, StreamOptions
    from arlight.client.display import DisplayClient, DisplayOptions
    from arlight.pipeline.virtual_scene import demo_scene
    from arlight.protocols import new_token
    from arlight.server.server import Server, ServerOptions
    from arlight.sources.source import sequence_source
    from arlight.sources.synthetic import make_sequence

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = make_sequence(num_frames=frames, width=size[0], height=size[1])
    source = sequence_source("synthetic", scene.camera, scene.frames)
    from arlight.evaluation import scene_truth
    from arlight.offline import FrameNotes

    # the light that can reach the scene (its upper hemisphere), camera frame
    truths = scene_truth(scene)
    truth = [t.dominant_upper_camera for t in truths]
    sun = [t.sun_camera for t in truths]  # what a kept compact source is
    errors: dict[int, float] = {}
    sun_errors: dict[int, float] = {}
    sh_errors: dict[int, float] = {}  # the SH's own direction, a source kept or not
    confidences: dict[int, float] = {}
    pipeline_ms: list[float] = []
    notes = FrameNotes()  # why a confidence is low, printed where the reason changes

    def on_result(result, record) -> None:
        err = _angle_deg(result.dominant_direction_camera, truth[result.seq])
        errors[result.seq] = err
        confidences[result.seq] = float(result.confidence.value)
        sh_world = result.diagnostics.get("sh_direction_world")
        if sh_world is not None:
            rotation = np.asarray(result.pose, float).reshape(4, 4)[:3, :3]
            sh_errors[result.seq] = _angle_deg(rotation.T @ np.asarray(sh_world), truth[result.seq])
        sources = result.compact_sources or []
        if sources:
            sun_errors[result.seq] = _angle_deg(sources[0]["direction_camera"], sun[result.seq])
        pipeline_ms.append(record["pipeline_ms"])
        d = result.dominant_direction_camera
        e2e = record["end_to_end_ms"]
        source_note = (
            f"(a compact source, {sun_errors[result.seq]:4.1f} deg from the sun)  "
            if sources
            else ""
        )
        printer(
            f"[{result.seq + 1:>3}/{frames}] light(cam)=({d[0]:+.2f}, {d[1]:+.2f}, "
            f"{d[2]:+.2f})  conf={result.confidence.value:.2f}  "
            f"error={f'{err:5.1f}' if np.isfinite(err) else '  -  '} deg  {source_note}"
            f"pipeline {record['pipeline_ms']:6.0f} ms  "
            f"in server {record['in_server_ms']:6.0f} ms (incl. queue)  end-to-end "
            + ("-" if e2e is None else f"{e2e:6.0f} ms")
        )
        note = notes.note(result.confidence.value, result.confidence.reason)
        if note:
            printer(f"      {note}")

    started = time.monotonic()
    # the session's token, chosen here: the display subscribes before the session exists
    # and presents it; the capture client gives it to the new session
    token = new_token()
    server = Server(ServerOptions(bind="tcp://127.0.0.1:*", workers=1)).start()
    try:
        address = server.connect_address
        printer(
            f"arlight demo: server on {address}; streaming the synthetic scene "
            f"({frames} frames, {size[0]}x{size[1]}, preset {preset}, lossless) to "
            f"session {DEMO_SESSION!r}; display writes {out}/"
        )
        display = DisplayClient(
            DisplayOptions(
                server=address,
                session=DEMO_SESSION,
                out_dir=str(out),
                video=video,
                idle_exit_s=120.0,
                token=token,
            ),
            on_result=on_result,
        )
        with _display_in_background(display):
            capture = CaptureClient(
                source,
                StreamOptions(
                    server=address,
                    session=DEMO_SESSION,
                    client_name="arlight-demo",
                    mode="lossless",
                    rate="max",
                    preset=preset,
                    want_composite=True,
                    timestamps="capture",
                    overrides={},
                    scene=demo_scene(size),
                    token=token,
                ),
            )
            stream = capture.run()
    finally:
        server.stop()
    if notes.summary():
        printer(f"arlight demo: {notes.summary()}")
    summary = _summary(
        display.summary.to_dict(),
        stream,
        errors,
        sun_errors,
        sh_errors,
        confidences,
        pipeline_ms,
        frames,
        size,
        preset,
        time.monotonic() - started,
    )
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


@contextmanager
def _display_in_background(display) -> Iterator[None]:
    """Run `display` in a thread, subscribed before the block starts; wait for it after."""
    errors: list[BaseException] = []

    def run() -> None:
        try:
            display.run()
        except BaseException as exc:  # noqa: BLE001 - re-raised by the main thread
            errors.append(exc)

    thread = threading.Thread(target=run, name="arlight-demo-display", daemon=True)
    thread.start()
    if not display.subscribed.wait(10.0):
        raise RuntimeError("the display client could not subscribe to the demo server")
    yield
    thread.join(60.0)
    if thread.is_alive():
        display.stop()
        thread.join(5.0)
    if errors:
        raise errors[0]


def _summary(
    shown: dict,
    stream,
    errors: dict[int, float],
    sun_errors: dict[int, float],
    sh_errors: dict[int, float],
    confidences: dict[int, float],
    pipeline_ms: list[float],
    frames: int,
    size: tuple[int, int],
    preset: str,
    wall_time_s: float,
) -> dict:
    """summary.json: what the display received, the capture client's counts, the errors
    (of the dominant light against the upper hemisphere's first moment, and of the SH's own
    direction, which a kept compact source's replaces as the dominant one; of the kept
    compact sources against the scene's sun), and how the confidence ranks the first and
    the last of these (Spearman over the frames; None with fewer than 3 frames or a constant
    column).

    fps is what the service delivered: results per second of streaming (first frame sent to
    last result, JIT compilation of a first run included); pipeline_fps is 1000 / the median
    pipeline milliseconds per frame (the pipeline alone, no waiting).
    """
    valid_errors = [e for e in errors.values() if np.isfinite(e)]
    valid_sh = [e for e in sh_errors.values() if np.isfinite(e)]
    median_pipeline_ms = float(np.median(pipeline_ms)) if pipeline_ms else None
    return {
        "arlight_version": __version__,
        "scene": {"source": "synthetic", "frames": frames, "width": size[0], "height": size[1]},
        "preset": preset,
        "mode": "lossless",
        "session": DEMO_SESSION,
        "frames_sent": stream.frames_sent,
        "results": shown["results"],
        "composites": shown["composites"],
        "frame_errors": len(stream.errors),
        "fps": round(shown["results"] / stream.elapsed_s, 3) if stream.elapsed_s > 0 else None,
        "pipeline_ms_median": None if median_pipeline_ms is None else round(median_pipeline_ms, 3),
        "pipeline_fps": (round(1000.0 / median_pipeline_ms, 3) if median_pipeline_ms else None),
        "display_fps": shown["fps"],
        "latency_ms": shown["latency_ms"],
        "capture_round_trip_ms_median": (
            round(float(np.median(stream.latencies_s)) * 1e3, 3) if stream.latencies_s else None
        ),
        "timings_ms_median": shown["timings_ms_median"],
        "angular_error_deg": {
            "median": round(float(np.median(valid_errors)), 3) if valid_errors else None,
            "p90": round(float(np.percentile(valid_errors, 90)), 3) if valid_errors else None,
        },
        "sh_direction_error_deg": {
            "median": round(float(np.median(valid_sh)), 3) if valid_sh else None,
            "p90": round(float(np.percentile(valid_sh, 90)), 3) if valid_sh else None,
        },
        "compact_source_to_sun_deg": {
            "frames": len(sun_errors),
            "median": round(float(np.median(list(sun_errors.values()))), 3) if sun_errors else None,
        },
        "confidence_vs_error_spearman": {
            "first_moment": _spearman(confidences, errors),
            "source_to_sun": _spearman(confidences, sun_errors),
        },
        "frames_dropped": shown["frames_dropped"],
        "reconnects": stream.reconnects,
        "wall_time_s": round(wall_time_s, 3),
        "composite": "the input frame with a virtual sphere and torus rendered in "
        "(differential rendering: their shadows, occlusion, one bounce)",
        "latency_note": "end-to-end = display receive time - capture timestamp (one clock); "
        "lossless mode queues up to `credits` frames, so it includes waiting; "
        "pipeline_ms is the pipeline alone",
    }
