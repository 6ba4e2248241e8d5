"""`arlight ibl`: a 360-degree panorama (video, image sequence, image) -> lighting per frame.

Per frame: inverse tone mapping (LDR input; HDR input is used as it is), SH radiance
(luminance and RGB), the dominant direction and the diffuse map (`pipeline/ibl.py`); one
JSON record per frame, optionally the HDR map as OpenEXR and, with `--render`, the virtual
objects lit by the frame (`FrameRenderer`, `pipeline/ibl_render.py`). Decoding runs on the
source's own thread (`sources/panorama.py`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from arlight.pipeline.ibl import IblParams, IblResult, angle_deg, lighting_from_hdr
from arlight.pipeline.inverse_tone import expand
from arlight.sources.synthetic_panorama import (
    keyed_exposure,
    ldr_frame,
    sun_direction,
    synthetic_sky,
)

if TYPE_CHECKING:  # imported with the renderer, when --render asks for it (Open3D)
    from arlight.pipeline.virtual_scene import VirtualScene

SYNTHETIC = "synthetic"
SYNTHETIC_FRAMES = 8
SYNTHETIC_STEP_RAD = math.radians(45.0)  # the sky turns by this about +y per frame
SYNTHETIC_WIDTH = 512


@dataclass
class SyntheticPanorama:
    """The built-in input: a procedural sky turning about +y, as 8-bit LDR frames, with the
    dominant direction of each frame's HDR original (the truth)."""

    frames: list[tuple[float, np.ndarray]]
    truth_directions: list[np.ndarray]
    hdr = False
    kind = "synthetic"
    path = SYNTHETIC
    fps = 30.0
    decode_ms: list[float] = field(default_factory=list)
    wait_ms: list[float] = field(default_factory=list)

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    @property
    def size(self) -> tuple[int, int]:
        h, w = self.frames[0][1].shape[:2]
        return w, h

    def __iter__(self) -> Iterator[tuple[float, np.ndarray]]:
        return iter(self.frames)

    def close(self) -> None:
        pass


def synthetic_panorama(
    num_frames: int = SYNTHETIC_FRAMES, width: int = SYNTHETIC_WIDTH, key: float = 0.18
) -> SyntheticPanorama:
    """The built-in sky (sun 35 degrees up) turning by 45 degrees per frame at 30 fps; one
    exposure for the whole clip (that of the first frame), as a camera with a locked
    exposure records it."""
    from arlight.pipeline.sh import dominant_direction

    first = synthetic_sky(width, sun_direction(math.radians(35), 0.0))
    exposure = keyed_exposure(first, key)
    frames, truth = [], []
    for i in range(num_frames):
        hdr = synthetic_sky(width, sun_direction(math.radians(35), i * SYNTHETIC_STEP_RAD))
        frames.append((i / 30.0, ldr_frame(hdr, exposure=exposure)))
        truth.append(dominant_direction(_luminance_sh(hdr)))
    return SyntheticPanorama(frames, truth)


def _luminance_sh(hdr: np.ndarray) -> np.ndarray:
    from arlight.pipeline.color import LUMA
    from arlight.pipeline.ibl import radiance_sh

    return LUMA @ radiance_sh(hdr)  # every pixel of the HDR original


@dataclass
class FrameOutput:
    """One processed frame: its index, timestamp, lighting and HDR map."""

    index: int
    timestamp_s: float
    result: IblResult
    hdr: np.ndarray
    process_ms: float
    image: np.ndarray | None = None  # the source's frame (LDR uint8 RGB, or the HDR map)


def process_frames(
    frames: Iterable[tuple[float, np.ndarray]], params: IblParams, hdr_input: bool
) -> Iterator[FrameOutput]:
    """Each (timestamp_s, image) -> FrameOutput; LDR images through `params.operator`."""
    for i, (t, image) in enumerate(frames):
        t0 = time.perf_counter()
        hdr = image if hdr_input else expand(image, params.operator)
        expand_ms = (time.perf_counter() - t0) * 1e3
        result = lighting_from_hdr(hdr, params)
        result.timings_ms = {"InverseTone": expand_ms, **result.timings_ms}
        yield FrameOutput(i, float(t), result, hdr, (time.perf_counter() - t0) * 1e3, image)


@dataclass
class RenderSetup:
    """What `--render` draws: the scene (panorama frame, camera at `world_from_cam`), the
    view size (per eye when stereo), the horizontal field of view."""

    scene: VirtualScene
    world_from_cam: np.ndarray
    size: tuple[int, int]
    hfov_deg: float
    stereo: bool = False


class FrameRenderer:
    """Renders each FrameOutput into one image (mono, or the stereo pair side by side);
    the views' G-buffers are made once (the scene and the camera do not move)."""

    def __init__(self, setup: RenderSetup):
        from arlight.pipeline import glossy, ibl_render

        self._ibl_render = ibl_render
        self._packed_rows = glossy.packed_rows
        self.setup = setup
        self.renderer = ibl_render.IblRenderer(setup.scene)
        camera = ibl_render.view_camera(setup.size, setup.hfov_deg)
        poses = (
            ibl_render.eye_poses(setup.world_from_cam) if setup.stereo else (setup.world_from_cam,)
        )
        self.views = [self.renderer.prepare_view(camera, pose) for pose in poses]
        self.timings_ms: list[dict[str, float]] = []
        self._hdr_exposure: float | None = None
        # the pyramid of each frame is built in this one array (each frame's is dropped
        # before the next): no 33 MB of fresh pages per frame at 2048x1024
        self._pyramid_buffer: np.ndarray | None = None

    def render(self, frame: FrameOutput) -> np.ndarray:
        """(H, W, 3) uint8 RGB (W doubled for stereo) of one frame."""
        r = self._ibl_render
        t0 = time.perf_counter()
        ldr = frame.image if frame.image is not None and frame.image.dtype == np.uint8 else None
        # LDR input: the HDR map is at the LDR's own scale (exposure 1); HDR input (no LDR to
        # show): exposed as a camera with a locked exposure records it, the first frame's
        # median luminance keyed to 0.18
        if ldr is not None:
            exposure = 1.0
        else:
            if self._hdr_exposure is None:
                self._hdr_exposure = keyed_exposure(frame.hdr, 0.18)
            exposure = self._hdr_exposure
        rows = self._packed_rows(frame.hdr.shape[0])
        if self._pyramid_buffer is None or len(self._pyramid_buffer) != rows:
            self._pyramid_buffer = np.empty((rows, 3), np.float32)
        light = r.frame_light(
            frame.hdr, frame.result.diffuse_map, ldr, exposure, self._pyramid_buffer
        )
        images = [self.renderer.render(view, light).rgb for view in self.views]
        out = r.side_by_side(*images) if self.setup.stereo else images[0]
        self.timings_ms.append(
            {
                "Pyramid": light.pyramid_ms,
                "Prefilter": light.prefilter_ms,
                "Render": (time.perf_counter() - t0) * 1e3,
            }
        )
        return out


def frame_record(frame: FrameOutput, operator: str) -> dict:
    """The JSON line of one frame (docs/guides/ibl.md, "Inputs, options and the output line")."""
    r = frame.result
    return {
        "timestamp": frame.timestamp_s,
        "frame": frame.index,
        "sh": [float(v) for v in r.sh],
        "sh_rgb": [[float(v) for v in row] for row in r.sh_rgb],
        "dominant_direction": [float(v) for v in r.dominant_direction],
        "operator": operator,
        "timings_ms": {k: round(v, 3) for k, v in r.timings_ms.items()},
    }


def truth_error_deg(frame: FrameOutput, truth: list[np.ndarray] | None) -> float | None:
    """Angle to the known dominant direction of the built-in sky, else None."""
    if truth is None:
        return None
    return angle_deg(frame.result.dominant_direction, truth[frame.index])


def run(source, params: IblParams, on_frame: Callable[[FrameOutput], None]) -> int:
    """Process every frame of `source` in order, calling `on_frame`; returns the count."""
    n = 0
    for frame in process_frames(source, params, hdr_input=bool(source.hdr)):
        on_frame(frame)
        n += 1
    return n
