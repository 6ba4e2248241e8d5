"""360-degree panoramas as streaming sources (`arlight stream pano.mp4`, `--panorama FILE`).

- `panorama_only_source(path)`: a Source whose frames carry the panorama alone (no colour,
  no depth, no calibration): the server answers each with the panorama's light.
- `with_panorama(source, path)`: an RGB-D Source whose i-th frame also carries the i-th
  panorama frame (a 360 camera beside the depth camera, paired by index; the stream ends
  with the shorter of the two).
- `is_panorama_input(spec)`: whether `arlight stream SPEC` names a panorama: a video file,
  an image file, or a folder of image files directly inside it (RGB-D data sets keep their
  images in sub-folders), whose first frame is 2:1.

Frames come from `sources/panorama.py` (a video is decoded on its own thread, opened anew
for each pass over the source, so `--loop` works). Only 8-bit panoramas stream: the wire
carries `rgb8` (an HDR file is refused, naming it).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from arlight.sources.panorama import (
    HDR_EXTS,
    LDR_EXTS,
    VIDEO_EXTS,
    PanoramaError,
    PanoramaSource,
    open_panorama,
)
from arlight.sources.source import Source, SourceFrame

PANORAMA_ONLY_DEPTH_SCALE = 1000.0  # sent in the Hello; no depth travels


def is_panorama_input(spec: str) -> bool:
    """True when `spec` names a video, an image or a folder of images (a panorama input;
    whether it is 2:1 is checked when it is opened)."""
    p = Path(spec)
    if p.is_file():
        return p.suffix.lower() in VIDEO_EXTS + LDR_EXTS + HDR_EXTS
    if p.is_dir():
        return any(f.is_file() and f.suffix.lower() in LDR_EXTS + HDR_EXTS for f in p.iterdir())
    return False


def _open_ldr(path: str, fps: float | None, max_frames: int | None) -> PanoramaSource:
    source = open_panorama(path, fps=fps, max_frames=max_frames)
    if source.hdr:
        source.close()
        raise PanoramaError(
            f"{path}: an HDR panorama; the wire carries 8-bit RGB (rgb8) "
            "panoramas only: stream an LDR video or images, or run "
            "`arlight ibl` on the HDR file"
        )
    return source


def _panorama_frames(
    path: str, fps: float | None, max_frames: int | None
) -> Iterator[tuple[float, np.ndarray]]:
    source = _open_ldr(path, fps, max_frames)
    try:
        yield from source
    finally:
        source.close()


def panorama_only_source(
    path: str, fps: float | None = None, max_frames: int | None = None
) -> Source:
    """The panorama at `path` as a Source of panorama-only frames (calibration None).
    Raises PanoramaError (a DatasetError) when it cannot be read, is HDR or is not 2:1."""
    probe = _open_ldr(path, fps, max_frames)
    num_frames = probe.num_frames or 0
    probe.close()

    def frames() -> Iterator[SourceFrame]:
        for t, image in _panorama_frames(path, fps, max_frames):
            yield SourceFrame(timestamp=float(t), panorama=image)

    name = Path(path).stem or "panorama"
    return Source(
        name,
        None,
        PANORAMA_ONLY_DEPTH_SCALE,
        num_frames,
        frames,
        [f"{path}: panorama-only frames (no colour, no depth)"],
    )


def with_panorama(source: Source, path: str, fps: float | None = None) -> Source:
    """`source` (RGB-D) with the panorama at `path` attached to its frames, paired by index.
    Recorded frames (sent as recorded) cannot take a panorama: ValueError."""
    if source.recorded_config is not None:
        raise ValueError(
            "--panorama cannot be added to a recording (its frames are sent exactly as recorded)"
        )
    probe = _open_ldr(path, fps, None)
    count = probe.num_frames
    probe.close()

    def frames() -> Iterator[SourceFrame]:
        pairs = zip(source.frames(), _panorama_frames(path, fps, None), strict=False)
        for frame, (_, image) in pairs:
            yield SourceFrame(
                frame.timestamp, frame.color, frame.depth, frame.pose, frame.parts, image
            )

    num = source.num_frames if count is None else min(source.num_frames, count)
    return Source(
        source.name,
        source.calibration,
        source.depth_scale,
        num,
        frames,
        list(source.notes) + [f"with the panorama {path}"],
    )


__all__ = [
    "PANORAMA_ONLY_DEPTH_SCALE",
    "is_panorama_input",
    "panorama_only_source",
    "with_panorama",
]
