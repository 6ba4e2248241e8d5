"""One frame through its session's pipeline, on a worker thread: `run_frame(job, compute)`.

A step from a received frame to a typed outcome: `Processed` (the FrameResult as the pipeline
returned it, untouched, with what the frame's panorama added beside it) or `Rejected` (the
Error to answer with). It touches no socket, no queue and no counter: the server turns the
outcome into a Result (server/results.py), counts and sends it. run_frame never raises: every
failure becomes a Rejected.

`SessionCompute` is the session's pipeline as the step sees it: the session's setup (what its
Hello asked for, checked once) and its compute, a Pipeline built on first use or a step given
to the server (`ProcessStep`: tests, the transport benchmark, `arlight serve --ray`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.core.checks import CheckError, check_image
from arlight.core.frames import Confidence, Diagnostics, FrameInput, FrameResult, RenderLight
from arlight.pipeline import sh as sh_lib
from arlight.pipeline.glossy import mip_pyramid
from arlight.pipeline.ibl import IblParams, IblResult
from arlight.pipeline.pipeline import FrameError, Pipeline
from arlight.pipeline.probe import ProbeResult
from arlight.pipeline.rendering import EnvironmentMap
from arlight.protocols import (
    DEFAULT_JPEG_QUALITY,
    Error,
    ErrorField,
    Frame,
    ProtocolError,
    decode,
    error_from_exception,
    peek_header,
)
from arlight.server.budget import PANORAMA_BYTES_PER_PIXEL, SessionBudget, SessionCost
from arlight.server.frame_queue import Job

if TYPE_CHECKING:
    from arlight.server.session import Session, SessionSetup

log = logging.getLogger(__name__)

# A compute step given to the server in place of the session's Pipeline, called as the
# Pipeline is: step(frame, session, render_light, deadline) -> FrameResult. session: the
# Session (what its Hello set up: name, config, pipeline_config, camera, scene, and
# volume_budget_error for a volume held elsewhere); render_light: the light to render the
# virtual objects with (None: the frame's own estimate); deadline: the frame's Deadline, called
# with a stage's name where the frame may be abandoned (Pipeline.process's checkpoint).
ProcessStep = Callable[[FrameInput, "Session", "RenderLight | None", "Deadline"], FrameResult]


class OverBudget(Exception):
    """A frame over the session's memory budget: `field` the frame's field ("frame" for
    the volume it grew, "frame.panorama"), the message says by how much."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field


class PipelineLost(Exception):
    """The session's pipeline was lost with the frame in it (`arlight serve --ray`: its Ray
    actor died). The frame was not processed: reported retryable (`pipeline_lost`), the
    session's queued frames are un-accepted, and the next frame gets a new pipeline."""


class FrameAbandoned(Exception):
    """A frame given up at a pipeline checkpoint: past its deadline ("deadline") or the
    server stopping ("shutdown"). stage: the stage it would have started (or was in)."""

    def __init__(self, reason: str, stage: str, elapsed_s: float, limit_s: float):
        super().__init__(f"{reason} before {stage} after {elapsed_s:.1f} s")
        self.reason = reason
        self.stage = stage
        self.elapsed_s = elapsed_s
        self.limit_s = limit_s


class Deadline:
    """One frame's checkpoint (`Pipeline.process(checkpoint=...)`): called with a stage's name
    before the stage starts, it raises FrameAbandoned once `limit_s` seconds have passed since
    the frame's processing began, or once `cancel` is set (the server stopping)."""

    def __init__(self, limit_s: float = math.inf, cancel: threading.Event | None = None):
        self.start_mono = time.monotonic()
        self.limit_s = limit_s
        self.cancel = cancel

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self.start_mono

    def __call__(self, stage: str) -> None:
        elapsed = self.elapsed_s
        if self.cancel is not None and self.cancel.is_set():
            raise FrameAbandoned("shutdown", stage, elapsed, 0.0)
        if elapsed > self.limit_s:
            raise FrameAbandoned("deadline", stage, elapsed, self.limit_s)


# ---------------------------------------------------------------------------- outcomes


@dataclass(frozen=True)
class PanoramaUse:
    """What a frame's 360-degree panorama added: its light (in the panorama's frame), which
    light rendered the virtual objects ("rgbd" or "panorama") and the operator used."""

    light: IblResult
    light_source: str
    operator: str

    @property
    def timings_ms(self) -> dict[str, float]:
        """The panorama path's stages, named apart from the pipeline's (they add up)."""
        return {f"Panorama{k}": v for k, v in self.light.timings_ms.items()}

    @property
    def diagnostics(self) -> Diagnostics:
        return {"light_source": self.light_source, "panorama_operator": self.operator}


@dataclass(frozen=True)
class Processed:
    """A frame processed: `result` as the pipeline returned it (not edited afterwards); the
    composite to send (None: none asked for, or none possible) and how to encode it (as the
    frame's colour came); `panorama`: what the frame's panorama added, None without one."""

    result: FrameResult
    composite: np.ndarray | None = None
    composite_codec: str = "jpeg"
    jpeg_quality: int = DEFAULT_JPEG_QUALITY
    panorama: PanoramaUse | None = None
    probe: ProbeResult | None = None  # the frame's probe, when the Hello asked for one


@dataclass(frozen=True)
class Rejected:
    """A frame not processed (or not to the end): the Error that answers it."""

    error: Error


FrameOutcome = Processed | Rejected


# ---------------------------------------------------------------------------- the compute


class SessionCompute:
    """A session's pipeline as the worker step uses it: `setup` (server/session.py,
    SessionSetup) and the compute, a `Pipeline` built on first use (in a worker: it
    allocates the volume), or `step` (a ProcessStep given to the server), called with
    `owner` (the Session) as its session.

    Used by one worker at a time (the server runs one frame per session at a time)."""

    def __init__(
        self,
        setup: SessionSetup,
        step: ProcessStep | None = None,
        owner: Any = None,
        cancel: threading.Event | None = None,
    ):
        self.setup = setup
        self.step = step
        self.owner = owner
        self.cancel = cancel  # set when the server stops: frames are abandoned
        self._pipeline: Pipeline | None = None
        self._told_no_render = False  # logged once: a scene but no composite from the pipeline

    @property
    def pipeline(self) -> Pipeline:
        """The session's Pipeline, built on first use."""
        if self._pipeline is None:
            if self.setup.camera is None:
                raise FrameError(
                    "color",
                    "this session has no camera calibration (a "
                    "panorama-only session): send frames without colour and depth",
                )
            self._pipeline = Pipeline(
                self.setup.pipeline_config, self.setup.camera, scene=self.setup.scene
            )
            request = self.setup.config.probe
            if request is not None:  # Hello config.probe: a probe every frame, at its point
                self._pipeline.probe_wanted = True
                if request.point_world is not None:
                    self._pipeline.probe_point = np.asarray(request.point_world, np.float64)
        return self._pipeline

    def last_probe(self) -> ProbeResult | None:
        """The probe the session's Pipeline made of its last frame, when the Hello asked for
        one (None otherwise, before the objects it is centred on are placed, and with a
        ProcessStep, which makes none)."""
        if self.setup.config.probe is None or self.step is not None or self._pipeline is None:
            return None
        probe = self._pipeline.last_probe
        self._pipeline.last_probe = None  # read once: a frame that makes none sends none
        return probe

    @property
    def pipeline_built(self) -> bool:
        """Whether the session has a Pipeline now (a volume over budget drops it)."""
        return self._pipeline is not None

    def deadline_for_frame(self) -> Deadline:
        budget = self.setup.budget
        return Deadline(math.inf if budget is None else budget.frame_deadline_s, self.cancel)

    def process(
        self, frame: FrameInput, render_light: RenderLight | None, deadline: Deadline
    ) -> FrameResult:
        """The session's estimate of one frame: its Pipeline, or its ProcessStep."""
        if self.step is None:
            return self.pipeline.process(frame, render_light=render_light, checkpoint=deadline)
        return self.step(frame, self.owner, render_light, deadline)

    def check_volume_budget(self) -> None:
        """The volume grows with the surface seen: past the session's memory budget it is
        dropped (the next frame starts a new one) and this frame fails (OverBudget)."""
        if self._pipeline is None:
            return
        setup = self.setup
        over = volume_budget_error(self._pipeline.volume_blocks, setup.budget, setup.cost)
        if over is not None:
            self._pipeline = None
            raise over

    def composite(self, frame: FrameInput, result: FrameResult) -> np.ndarray:
        """The frame a Result carries: without a virtual scene the input colour frame,
        unchanged; with one the pipeline's rendering of it (the input frame while the
        pipeline makes none)."""
        scene = self.setup.scene
        if scene and result.composite is not None:
            return result.composite
        if scene and not self._told_no_render:
            self._told_no_render = True
            log.info(
                "session %s: the pipeline rendered no composite; the Results carry the input frame",
                self.setup.name,
            )
        return frame.color

    def environment(self, panorama: IblResult) -> EnvironmentMap | None:
        """The panorama's HDR map as the environment mirror and glossy objects reflect, or
        None when no virtual object reflects (the mip pyramid costs a pass over the map)."""
        scene = self.setup.scene
        if (
            panorama.hdr is None
            or not scene
            or not any(o.material.mirror or o.material.metalness > 0 for o in scene.objects)
        ):
            return None
        return EnvironmentMap(
            mip_pyramid(panorama.hdr), self.setup.panorama_light.panorama_from_world
        )


def volume_budget_error(
    blocks: int, budget: SessionBudget | None, cost: SessionCost | None
) -> OverBudget | None:
    """The over_budget error of a volume of `blocks` blocks, None within the session's
    share of the budget (or without a budget)."""
    if budget is None or cost is None:
        return None
    used = blocks * cost.bytes_per_block
    if used > cost.volume_limit_bytes:
        return OverBudget(
            "frame",
            f"the session's volume grew to {blocks} blocks ({used / 2**20:.0f} "
            f"MiB), over its share of the per-session memory budget "
            f"({cost.volume_limit_bytes / 2**20:.0f} MiB of "
            f"{budget.session_memory_bytes / 2**20:.0f} MiB, `arlight serve "
            "--session-memory-mb`); the volume is reset and the session goes on",
        )
    return None


# ---------------------------------------------------------------------------- the step


def run_frame(job: Job, compute: SessionCompute) -> FrameOutcome:
    """Decode, check and process one received frame. Never raises."""
    deadline = compute.deadline_for_frame()
    try:
        return _process(job, compute, deadline)
    except Exception as exc:  # noqa: BLE001 - every failure becomes an Error reply
        return Rejected(frame_error(exc, job.seq))


def _process(job: Job, compute: SessionCompute, deadline: Deadline) -> Processed:
    setup = compute.setup
    check_declared_sizes(job.parts, setup)
    frame = decode(
        job.parts, max_message_bytes=setup.max_message_bytes, max_pixels=setup.max_pixels
    )
    if not isinstance(frame, Frame):
        raise ProtocolError("bad_state", f"expected a Frame, got {type(frame).__name__}")
    panorama = world = render_light = None
    lights = setup.panorama_light
    if frame.panorama is not None:  # first: a bad panorama fails before the pipeline
        panorama = lights.light(frame.panorama)
        world = lights.to_world(panorama)
        if lights.light_source == "panorama":
            render_light = RenderLight(world[0], world[1], compute.environment(panorama))
    composite = probe = None
    if frame.color is None and world is not None:  # panorama-only: no RGB-D pipeline
        result = panorama_only_result(frame, world)
    else:
        if setup.camera is None:
            raise FrameError(
                "color",
                "this session has no camera calibration (a panorama-only "
                "session): send frames without colour and depth",
            )
        frame_input = frame_to_input(frame, setup.camera, setup.config.depth_scale)
        result = compute.process(frame_input, render_light, deadline)
        if setup.config.want_composite:
            composite = compute.composite(frame_input, result)
        probe = compute.last_probe()  # before a volume over budget drops the pipeline
    compute.check_volume_budget()
    used = (
        None
        if panorama is None
        else PanoramaUse(
            panorama,
            "panorama" if frame.color is None else lights.light_source,
            lights.params.operator,
        )
    )
    return Processed(result, composite, frame.color_codec, frame.jpeg_quality, used, probe)


def check_declared_sizes(parts: list, setup: SessionSetup) -> None:
    """Before any payload is decoded: colour or depth declared at another size than the
    calibration's is refused (FrameError naming the image), and a panorama larger than
    the session's memory budget leaves room for (OverBudget, frame.panorama)."""
    header = peek_header(parts)
    pano = header.get("panorama")
    budget, cost = setup.budget, setup.cost
    if isinstance(pano, dict) and budget is not None and cost is not None:
        w, h = pano.get("width"), pano.get("height")
        if type(w) is int and type(h) is int and 0 < w * h <= setup.max_pixels:
            need = w * h * PANORAMA_BYTES_PER_PIXEL
            room = budget.session_memory_bytes - cost.session_bytes
            if need > room:
                raise OverBudget(
                    "frame.panorama",
                    (
                        f"a {w} x {h} panorama needs about {need / 2**20:.0f} MiB, over what "
                        f"the session's memory budget leaves for it ({max(room, 0) / 2**20:.0f}"
                        f" MiB of {budget.session_memory_bytes / 2**20:.0f} MiB, `arlight "
                        "serve --session-memory-mb`); send a smaller panorama"
                    ),
                )
    camera = setup.camera
    if camera is None:
        return
    for key in ("color", "depth"):
        d = header.get(key)
        if not isinstance(d, dict):
            continue
        w, h = d.get("width"), d.get("height")
        if type(w) is not int or type(h) is not int or w * h > setup.max_pixels:
            continue  # the decoder names these (bad_field, too_large)
        if (w, h) != (camera.width, camera.height):
            raise FrameError(
                key,
                f"{key} is {w} x {h}, the session's calibration {camera.width} x {camera.height}",
            )


def frame_to_input(frame: Frame, camera: PinholeCamera, depth_scale: float) -> FrameInput:
    """Pipeline input of a wire frame: its uint16 depth as received, with the session's
    depth_scale (units per metre); Pipeline.process turns it into metres, once.

    Checks the image sizes against the session's calibration (FrameError names the field);
    everything else (NaN poses, dtypes) is checked by Pipeline.process.
    """
    size = (camera.width, camera.height)
    color, depth = frame.color, frame.depth
    if color is None or depth is None:  # decode gives both or neither
        raise FrameError(
            "color" if color is None else "depth",
            "missing: the RGB-D pipeline "
            "needs colour and depth (a frame with neither is panorama-only)",
        )
    try:
        for name, image in (("color", color), ("depth", depth)):
            check_image(
                image,
                name,
                channels=3 if name == "color" else None,
                size=size,
                size_of="the session's calibration",
            )
    except CheckError as exc:
        raise FrameError(exc.field, exc.message) from None
    # the sources' integers and depth_scale, untouched: a stream of recorded depth gives the
    # pipeline the metres that reading the recording directly gives, bit for bit
    pose = None if frame.pose is None else np.asarray(frame.pose, dtype=np.float64)
    return FrameInput(
        color=color,
        depth=depth,
        depth_scale=float(depth_scale),
        timestamp=float(frame.timestamp),
        pose=pose,
        panorama=frame.panorama,
    )


def panorama_only_result(
    frame: Frame, world: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> FrameResult:
    """The FrameResult of a frame without colour and depth (SPEC.md, "result"): the
    panorama's light in the world frame as the estimate; no camera, so pose is the identity
    and the camera frame is the world frame; confidence: the map's SH are a projection, not
    a fit (every pixel of the area-averaged map counts as a sample, condition number 1)."""
    sh_world, rgb_world, direction = world
    # the SH are projected from the map area-averaged to sh_source_size (or as it came, when
    # not larger): every pixel of that map is one sample
    rows = 0 if frame.panorama is None else frame.panorama.shape[0]
    height = min(rows, IblParams().sh_source_size[1])
    samples = height * 2 * height
    bands = sh_lib.bands_of(len(sh_world))
    return FrameResult(
        timestamp=float(frame.timestamp),
        sh=sh_world,
        sh_camera=sh_world,
        dominant_direction_world=direction,
        dominant_direction_camera=direction,
        intensity=sh_lib.intensity_along(sh_world, direction) if np.any(direction) else 0.0,
        confidence=Confidence(
            samples=samples,
            condition_number=1.0,
            bands_estimated=bands,
            value=1.0 if np.any(direction) else 0.0,
            reason="" if np.any(direction) else "black panorama",
        ),
        pose=np.eye(4),
        sh_rgb=rgb_world,
        timings_ms={},
        diagnostics={},
    )


def frame_error(exc: Exception, seq: int | None) -> Error:
    """The Error reply for an exception raised while handling frame `seq`."""
    if isinstance(exc, ProtocolError):
        error = error_from_exception(exc)
        return dataclasses.replace(error, seq=seq)
    if isinstance(exc, FrameError):
        return Error(code="bad_field", message=str(exc), field=f"frame.{exc.field}", seq=seq)
    if isinstance(exc, FrameAbandoned):
        if exc.reason == "shutdown":
            return Error(
                code="bad_state",
                field=ErrorField.SHUTDOWN,
                seq=seq,
                retryable=True,
                message="the server shut down before finishing this frame; send it "
                "again after reconnecting",
            )
        return Error(
            code="deadline",
            seq=seq,
            message=(
                f"frame abandoned before {exc.stage}: {exc.elapsed_s:.1f} s in the pipeline, over "
                f"the server's per-frame deadline of {exc.limit_s:g} s (`arlight serve "
                "--frame-deadline`); lower the session's cost (--preset fast, a smaller image, "
                "fewer rt_directions or robust_iterations)"
            ),
        )
    if isinstance(exc, OverBudget):
        return Error(code="over_budget", seq=seq, field=exc.field, message=str(exc))
    if isinstance(exc, PipelineLost):
        return Error(
            code="bad_state",
            field=ErrorField.PIPELINE_LOST,
            seq=seq,
            retryable=True,
            message=f"{exc}; this frame and the session's queued frames were not "
            "processed: send them again (a new pipeline, a fresh volume)",
        )
    log.error("frame %s: unexpected failure", seq, exc_info=exc)
    return Error(
        code="internal",
        message=f"the server failed to process this frame ({type(exc).__name__}: {exc})"[:4096],
        seq=seq,
    )
