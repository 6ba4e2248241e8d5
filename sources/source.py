"""A frame source as the capture client streams it: `Source`, and `open_source(spec)`.

Specs: "synthetic" (the built-in scene with known light, arlight.sources.synthetic), every
folder layout `arlight estimate` reads (TUM RGB-D, Open3D/Redwood, 7-Scenes, pairs;
arlight.sources.sequence), MCAP recordings made by `arlight record`
(arlight.sources.recording), whose Frame messages are sent exactly as recorded, and live
cameras: "depthai[:DEVICE_ID]", "openni2[:URI]" or "FILE.oni", "realsense[:SERIAL]"
(arlight.sources.camera and one module per library, imported only when opened).

Depth goes out as the source gives it: the sensor's uint16 with the source's depth_scale
(units per metre), which the Hello's SessionConfig carries; nothing is rescaled on the way.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from arlight.core.checks import check_image
from arlight.core.frames import FrameInput
from arlight.protocols import CameraCalibration, SessionConfig
from arlight.sources.recording import Recording
from arlight.sources.sequence import open_sequence
from arlight.sources.synthetic import CLI_FRAMES, LazyFrames


@dataclass
class SourceFrame:
    """One frame as sent: timestamp (source clock, s), color (H, W, 3) uint8 RGB,
    depth (H, W) uint16 in the source's depth_scale units per metre, pose (4, 4) or None.
    parts: for recordings, the encoded Frame exactly as recorded (sent verbatim).
    panorama: (h, 2h, 3) uint8 RGB equirectangular 360-degree frame, or None; a frame with
    a panorama and neither colour nor depth is a panorama-only frame.
    gravity: (3,) unit vector, the direction of gravity (down) in the colour camera's frame
    (OpenCV axes) from a camera's IMU, or None; kept for later use (not yet on the wire)."""

    timestamp: float
    color: np.ndarray | None = None
    depth: np.ndarray | None = None
    pose: np.ndarray | None = None
    parts: list[bytes] | None = None
    panorama: np.ndarray | None = None
    gravity: np.ndarray | None = None


@dataclass
class Source:
    """Frames plus what a Hello needs. frames(): a fresh iterator over all frames.

    depth_scale: units per metre of every frame's uint16 depth. calibration None: a
    panorama-only source (sources/panorama_stream.py).
    """

    name: str
    calibration: CameraCalibration | None
    depth_scale: float
    num_frames: int
    frames: Callable[[], Iterator[SourceFrame]]
    notes: list[str] = field(default_factory=list)
    recorded_config: SessionConfig | None = None  # recordings: the recorded session config


def calibration_of(camera) -> CameraCalibration:
    """The wire calibration of a PinholeCamera (no distortion: images are undistorted)."""
    return CameraCalibration(
        int(camera.width),
        int(camera.height),
        float(camera.fx),
        float(camera.fy),
        float(camera.cx),
        float(camera.cy),
    )


def sequence_source(
    name: str, camera, frames: Sequence[FrameInput], notes: list[str] | None = None
) -> Source:
    """A Source over FrameInputs with raw depth (a data set, the synthetic scene).

    Every frame must carry (H, W) uint16 depth with one depth_scale (what the readers
    yield); it is sent unchanged. ValueError for float metres (depth_scale None).
    """
    first = frames[0]
    scale = first.depth_scale
    if scale is None:
        raise ValueError(
            f"{name}: frame depth is float metres (depth_scale None); a Source "
            "sends the sensor's uint16 depth with its units per metre"
        )

    def iterate() -> Iterator[SourceFrame]:
        for i in range(len(frames)):
            f = frames[i]
            if f.depth_scale != scale:
                raise ValueError(
                    f"{name}: frame {i} has depth_scale {f.depth_scale}, the "
                    f"first frame {scale}; a source has one depth_scale"
                )
            depth = check_image(f.depth, f"{name} frame {i} depth", dtype=np.uint16)
            yield SourceFrame(
                float(f.timestamp),
                np.ascontiguousarray(f.color),
                np.ascontiguousarray(depth),
                f.pose,
            )

    return Source(
        name, calibration_of(camera), float(scale), len(frames), iterate, list(notes or [])
    )


def open_recording_source(path: str | Path, max_frames: int | None = None) -> Source:
    """A Source replaying a recording: its Frames are sent exactly as recorded."""
    recording = Recording(path)
    config = recording.hello.config
    n = recording.num_frames if max_frames is None else min(max_frames, recording.num_frames)

    def iterate() -> Iterator[SourceFrame]:
        for i, (log_ns, parts) in enumerate(recording.frames()):
            if i >= n:
                return
            yield SourceFrame(timestamp=log_ns * 1e-9, parts=parts)

    name = config.session if config.session else recording.path.stem
    return Source(
        name,
        config.calibration,
        config.depth_scale,
        n,
        iterate,
        [f"recording of session {config.session!r}: {recording.num_frames} frames"],
        recorded_config=config,
    )


def open_source(
    spec: str,
    *,
    use_poses: bool = False,
    max_frames: int | None = None,
    depth_encoding: str | None = None,
    synthetic_size: tuple[int, int] = (640, 480),
    synthetic_frames: int = CLI_FRAMES,
    camera_fps: float = 30.0,
) -> Source:
    """A frame source: "synthetic", a data set folder (arlight.sources.sequence), FILE.mcap,
    or a camera (arlight.sources.camera; synthetic_size is then its image size, camera_fps
    its frame rate).

    Raises DatasetError (arlight.sources.errors), RecordingError or CameraError
    (arlight.sources.camera) for unusable input.
    """
    from arlight.sources.camera import open_camera, parse_camera_spec

    camera = parse_camera_spec(spec, synthetic_size, camera_fps)
    if camera is not None:
        return open_camera(camera, max_frames=max_frames)
    if spec == "synthetic":
        # the first max_frames of a synthetic_frames orbit (a longer one if they are more):
        # a shorter orbit's steps may be too long to track
        n = max(max_frames or 0, synthetic_frames)
        w, h = synthetic_size
        frames = LazyFrames(n, w, h, use_poses=use_poses, first=max_frames)
        return sequence_source("synthetic", frames.camera, frames, [])  # rendered as sent
    if spec.lower().endswith(".mcap"):
        return open_recording_source(spec, max_frames=max_frames)
    sequence = open_sequence(
        spec, depth_encoding=depth_encoding, use_poses=use_poses, max_frames=max_frames
    )
    return sequence_source(sequence.name, sequence.camera, sequence.frames, list(sequence.notes))
