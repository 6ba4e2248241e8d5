"""Lighting of RGB-D frames without a server: the loop `arlight estimate` and `arlight batch`
share.

`estimate_frames` runs one Pipeline over a stream's frames in order and yields, per frame,
its FrameResult, its JSON record and the pipeline's milliseconds. `frame_record` is that
record: what `arlight stream --out` writes of the server's Result for the same frame, less
what only a client that received it knows (session counters, wall-clock times, latencies).
`open_recording` reads an `arlight record` file's frames as the server would receive them.
`FrameNotes` says on a terminal why a frame's light is not to be trusted: a frame without
usable depth, or a low confidence's reason (`Confidence.reason`).

Nothing here imports the server or opens a socket.
"""

from __future__ import annotations

import collections
import re
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.core.frames import FrameInput, FrameResult
from arlight.pipeline.engine_export import camera_exports
from arlight.pipeline.light_confidence import LOW_CONFIDENCE
from arlight.protocols import plain_diagnostics
from arlight.protocols.frame_result import compact_sources_to_wire

_NUMBER = re.compile(r"\d+(\.\d+)?(e[+-]?\d+)?")


def frame_record(result: FrameResult, index: int, exports: Sequence[str] = ()) -> dict:
    """The JSON record of frame `index` (0-based), in docs/reference/output-record.md's key order.

    exports: engine layouts (engine_export.EXPORTERS names) of the frame's light (RGB when
    the pipeline has it, else luminance) in the camera frame with each engine's axes; the
    "exports" key is absent when none is asked for. Raises ProtocolError (bad_field, naming
    `result.diagnostics.KEY`) for diagnostics the protocol could not carry, as the server
    does.
    """
    record = {
        "timestamp": float(result.timestamp),
        "frame": index,
        "sh": [float(x) for x in result.sh],
        "sh_camera": [float(x) for x in result.sh_camera],
        "sh_rgb": None if result.sh_rgb is None else np.asarray(result.sh_rgb, float).tolist(),
        "dominant_direction_camera": [float(x) for x in result.dominant_direction_camera],
        "dominant_direction_world": [float(x) for x in result.dominant_direction_world],
        "intensity": float(result.intensity),
        **(
            {}
            if not result.compact_sources
            else {"compact_sources": compact_sources_to_wire(result.compact_sources)}
        ),
        "confidence": result.confidence.to_dict(),
        "pose": np.asarray(result.pose, dtype=float).tolist(),
        "timings_ms": {k: round(float(v), 3) for k, v in result.timings_ms.items()},
        "diagnostics": plain_diagnostics(result.diagnostics),
    }
    if exports:
        light = result.sh if result.sh_rgb is None else result.sh_rgb
        source = result.compact_sources[0] if result.compact_sources else None  # main light
        record["exports"] = camera_exports(
            light, result.pose, tuple(exports), result.dominant_direction_world, source
        )
    return record


@dataclass(frozen=True)
class EstimatedFrame:
    """One processed frame: its index (0-based), input, result, JSON record (frame_record)
    and the milliseconds `Pipeline.process` took."""

    index: int
    frame: FrameInput
    result: FrameResult
    record: dict
    process_ms: float


def estimate_frames(
    pipeline, frames: Iterable[FrameInput], exports: Sequence[str] = (), overlap: bool = False
) -> Iterator[EstimatedFrame]:
    """Run `pipeline` (a Pipeline: one stream's state) over `frames` in order, lazily.

    overlap: through `Pipeline.process_overlapped` (the next frame's front stages beside
    this one's light fit). process_ms: how long the caller waited for the result.
    FrameError for a frame the pipeline refuses; the frames before it have been yielded."""
    taken: collections.deque[FrameInput] = collections.deque()

    def take() -> Iterator[FrameInput]:  # the frames as the pipeline reads them
        for frame in frames:
            taken.append(frame)
            yield frame

    results = pipeline.process_overlapped(take()) if overlap else map(pipeline.process, take())
    t0 = time.perf_counter()
    for index, result in enumerate(results):
        process_ms = (time.perf_counter() - t0) * 1e3
        frame = taken.popleft()
        yield EstimatedFrame(index, frame, result, frame_record(result, index, exports), process_ms)
        t0 = time.perf_counter()  # the caller's time with a result is not the pipeline's


def open_recording(
    path: str, max_frames: int | None = None
) -> tuple[PinholeCamera, int, Iterator[FrameInput]]:
    """(camera, number of frames, lazy FrameInputs) of a recording (`arlight record`).

    Each frame as the server receives it: colour and depth as recorded (the pipeline
    converts the depth with the session's depth_scale, so the metres equal those of reading
    the recorded source directly), poses as recorded. RecordingError (a ValueError) for a
    file that is no recording or whose session has no usable pinhole calibration; the
    pipeline checks each frame's images against it (FrameError).
    """
    from arlight.protocols import Frame, decode
    from arlight.sources.recording import Recording, RecordingError

    recording = Recording(path)
    config = recording.hello.config
    cal = config.calibration
    if cal is None:
        raise RecordingError(
            f"{path}: calibration: the recorded session has none (a "
            "panorama-only stream); there is no RGB-D to estimate from"
        )
    if any(float(d) != 0.0 for d in (cal.D or ())):
        raise RecordingError(
            f"{path}: calibration.D: distortion model "
            f"{cal.distortion_model!r} with non-zero coefficients is not "
            "supported; undistort the images before recording"
        )
    try:
        camera = PinholeCamera(
            int(cal.width),
            int(cal.height),
            float(cal.fx),
            float(cal.fy),
            float(cal.cx),
            float(cal.cy),
        )
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{path}: calibration: {exc}") from None
    n = recording.num_frames if max_frames is None else min(max_frames, recording.num_frames)
    depth_scale = float(config.depth_scale)

    def frames() -> Iterator[FrameInput]:
        for i, (_, parts) in enumerate(recording.frames()):
            if i >= n:
                return
            message = decode(parts)
            if not isinstance(message, Frame):
                raise RecordingError(
                    f"{path}: message {i} on the frame channel is a "
                    f"{type(message).__name__}, not a Frame"
                )
            if message.color is None or message.depth is None:
                raise RecordingError(
                    f"{path}: frame {i} carries no colour and depth image (a panorama-only frame)"
                )
            pose = None if message.pose is None else np.asarray(message.pose, np.float64)
            yield FrameInput(
                color=message.color,
                depth=message.depth,
                depth_scale=depth_scale,
                timestamp=float(message.timestamp),
                pose=pose,
                panorama=message.panorama,
            )

    return camera, n, frames()


def has_usable_depth(frame: FrameInput) -> bool:
    """True when some depth pixel is measured (> 0 and finite; 0 and NaN are missing)."""
    depth = np.asarray(frame.depth)
    return bool(np.any(np.isfinite(depth) & (depth > 0)))


class FrameNotes:
    """What a terminal says of each frame beyond its numbers.

    `note` gives a line for a frame without usable depth (every such frame: its light of
    zeros is no measurement) and for a confidence below LOW_CONFIDENCE (its reason, unless
    the frame before had the same causes: the same reason but for its numbers); None
    otherwise. `summary` counts them at the end (None when there was nothing to say).
    """

    def __init__(self) -> None:
        self.frames = 0
        self.without_depth = 0
        self.low_confidence = 0
        self._last_reason: str | None = None

    def note(self, confidence: float, reason: str, depth_usable: bool = True) -> str | None:
        self.frames += 1
        if not depth_usable:
            self.without_depth += 1
            self._last_reason = None
            return (
                "no usable depth (every depth pixel is 0 or missing): no light estimated; "
                "the zero light printed is not a measurement"
            )
        if not confidence < LOW_CONFIDENCE:
            self._last_reason = None
            return None
        self.low_confidence += 1
        reason = reason or "no reason recorded"
        causes = _NUMBER.sub("#", reason)
        if causes == self._last_reason:
            return None
        self._last_reason = causes
        return f"low confidence {confidence:.2f} (below {LOW_CONFIDENCE:g}): {reason}"

    def summary(self) -> str | None:
        parts = []
        if self.without_depth:
            parts.append(f"{self.without_depth} of {self.frames} frames without usable depth")
        if self.low_confidence:
            parts.append(
                f"{self.low_confidence} of {self.frames} frames with a confidence "
                f"below {LOW_CONFIDENCE:g} (the reason printed where its causes change)"
            )
        return "; ".join(parts) or None
