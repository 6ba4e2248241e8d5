"""What a data set reader returns (`RgbdSequence`, frames read lazily) and how it builds one.

Every frame leaves a reader as a `FrameInput`:
    color: (H, W, 3) uint8, RGB order (OpenCV's BGR converted here, at the edge);
    depth: (H, W) uint16, the sensor's units, 0 = missing, with
    depth_scale: units per metre (metres = arlight.core.checks.depth_metres(depth, depth_scale));
    timestamp: seconds (float);
    pose: (4, 4) float64 camera-to-world (world_from_cam) or None.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import overload

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.core.frames import FrameInput
from arlight.sources.depth_encodings import read_depth
from arlight.sources.errors import DatasetError
from arlight.sources.images import read_color
from arlight.sources.registration import DepthRegistration

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameRecord:
    """Where one frame lives on disk. world_from_cam: (4, 4) or None."""

    color_path: Path
    depth_path: Path
    timestamp_s: float
    world_from_cam: np.ndarray | None = None


class LazyFrames(Sequence[FrameInput]):
    """Read-only sequence of frames; each access reads (and decodes) the files again."""

    def __init__(self, load: Callable[[int, bool], FrameInput], indices: range) -> None:
        self._load = load
        self._indices = indices

    def __len__(self) -> int:
        return len(self._indices)

    @overload
    def __getitem__(self, index: int) -> FrameInput: ...

    @overload
    def __getitem__(self, index: slice) -> LazyFrames: ...

    def __getitem__(self, index: int | slice) -> FrameInput | LazyFrames:
        if isinstance(index, slice):
            return LazyFrames(self._load, self._indices[index])
        return self._load(self._indices[index], True)  # IndexError past the end

    def __repr__(self) -> str:
        return f"LazyFrames(len={len(self)})"


@dataclass
class RgbdSequence:
    """A recorded RGB-D sequence.

    name: folder (or file) name; camera: intrinsics of the colour image, which the depth is
    registered to; frames: lazy sequence of FrameInput (frame i read on access; len() works);
    format: "tum", "redwood", "7scenes" or "pair"; has_poses: the data set ships camera-to-world
    poses (groundtruth.txt / trajectory.log / every frame's pose.txt; read only when asked
    for); poses_attached: the frames carry them (open_sequence(use_poses=True));
    depth_encoding: how stored depth was decoded; source: the path opened; notes: choices
    made while opening (defaults, skipped frames, registration), also logged.
    """

    name: str
    camera: PinholeCamera
    frames: Sequence[FrameInput]
    format: str
    has_poses: bool
    poses_attached: bool = False
    depth_encoding: str = ""
    source: Path | None = None
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[FrameInput]:
        for i in range(len(self.frames)):
            yield self.frames[i]

    def frame(self, index: int, with_pose: bool = True) -> FrameInput:
        """Frame `index` (negative counts from the end); with_pose=False drops its pose."""
        frame = self.frames[index]
        return frame if with_pose else replace(frame, pose=None)


class _Loader:
    """Reads and decodes the frames of one sequence."""

    def __init__(
        self,
        records: list[FrameRecord],
        camera: PinholeCamera,
        encoding: str,
        units_per_metre: float | None,
        attach_poses: bool,
        registration: DepthRegistration | None = None,
    ) -> None:
        self.records = records
        self.camera = camera
        self.encoding = encoding
        self.units_per_metre = units_per_metre
        self.attach_poses = attach_poses
        self.registration = registration

    def __call__(self, index: int, with_pose: bool = True) -> FrameInput:
        rec = self.records[index]
        color = read_color(rec.color_path)
        depth, depth_scale = read_depth(rec.depth_path, self.encoding, self.units_per_metre)
        h, w = color.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise DatasetError(
                f"{rec.color_path}: colour image is {w}x{h} but the camera is "
                f"{self.camera.width}x{self.camera.height}; fix the intrinsics file or the "
                "images so that they agree"
            )
        dh, dw = depth.shape
        if self.registration is not None:
            reg = self.registration
            if (dw, dh) != (reg.depth_camera.width, reg.depth_camera.height):
                raise DatasetError(
                    f"{rec.depth_path}: depth image is {dw}x{dh} but the depth camera is "
                    f"{reg.depth_camera.width}x{reg.depth_camera.height}; all depth images "
                    "of a sequence must have one size"
                )
            depth, depth_scale = reg(depth, depth_scale, self.camera), reg.depth_scale
        elif (dh, dw) != (h, w):
            raise DatasetError(
                f"colour {rec.color_path} is {w}x{h} but depth {rec.depth_path} is {dw}x{dh}; "
                "colour and depth must have the same size (register or resize the depth first)"
            )
        pose = None
        if with_pose and self.attach_poses and rec.world_from_cam is not None:
            pose = rec.world_from_cam.copy()
        return FrameInput(
            color=color,
            depth=depth,
            depth_scale=depth_scale,
            timestamp=float(rec.timestamp_s),
            pose=pose,
        )


def build_sequence(
    name: str,
    fmt: str,
    source: Path,
    records: list[FrameRecord],
    camera: PinholeCamera,
    encoding: str,
    units_per_metre: float | None,
    has_poses: bool,
    use_poses: bool,
    max_frames: int | None,
    notes: list[str],
    registration: DepthRegistration | None = None,
) -> RgbdSequence:
    """The RgbdSequence of a reader's records; reads the first frame now, so that sizes,
    dtypes and codecs fail at opening, not later. units_per_metre None: the encoding's."""
    if not records:
        raise DatasetError(f"{source}: the sequence has no frames")
    if max_frames is not None:
        records = records[:max_frames]
    loader = _Loader(records, camera, encoding, units_per_metre, use_poses, registration)
    seq = RgbdSequence(
        name=name,
        camera=camera,
        frames=LazyFrames(loader, range(len(records))),
        format=fmt,
        has_poses=has_poses,
        poses_attached=use_poses,
        depth_encoding=encoding,
        source=source,
        notes=notes,
    )
    loader(0)
    return seq


def note(notes: list[str], message: str, level: int = logging.WARNING) -> None:
    """Record a choice made while opening (kept in RgbdSequence.notes) and log it."""
    notes.append(message)
    log.log(level, message)


def default_camera(color_path: Path, notes: list[str], missing: str) -> PinholeCamera:
    """Kinect v1 intrinsics at the size of the colour image, with a note that `missing`
    (the intrinsics file) was not found."""
    first = read_color(color_path)
    camera = PinholeCamera.kinect_v1(first.shape[1], first.shape[0])
    note(
        notes,
        f"{missing}; using Kinect v1 default intrinsics "
        f"(fx = fy = {camera.fx:g}, cx = {camera.cx:g}, cy = {camera.cy:g})",
    )
    return camera
