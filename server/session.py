"""One streaming session: its Pipeline, its queue of frames and its counters.

A session is created by a capture client's Hello and named by `SessionConfig.session`. The
I/O thread owns the queue (`offer`, `next_job`, `finish`); a worker thread runs one job at a
time per session (`run`), so a session's frames are processed in order and its Pipeline is
never used by two threads at once. Sessions share nothing: each has its own Pipeline, queue,
counters and outcome cache.

Delivery modes (docs/architecture.md; drops are counted, never silent):
- live: the queue holds the newest frame only; an older pending frame is replaced and
  counted in `frames_dropped`, which every Result reports.
- lossless: every frame is processed exactly once, in order. The client keeps at most
  `credits` frames unacknowledged; a frame whose seq was already accepted is a duplicate
  (a client resending after a reconnect): it is not processed again. Its final outcome, the
  Result or the final Error, is cached for the last `credits + OUTCOME_CACHE_EXTRA` frames
  and sent again; a duplicate still queued or in a worker is answered when it finishes; an
  older one gets a final `bad_state` Error (field "duplicate"), so every frame the client
  sends gets an answer and a lossless stream never waits forever.

Clocks: liveness and expiry (`last_activity`, the latency log) run on time.monotonic();
wall-clock times (`*_wall`) are only the timestamps that go on the wire (a Result's
server_receive_time and server_finish_time).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from arlight.checks import CheckError, check_image
from arlight.pipeline import sh as sh_lib
from arlight.pipeline.camera import PinholeCamera
from arlight.pipeline.config import Config
from arlight.pipeline.frames import Confidence, FrameInput, FrameResult, RenderLight
from arlight.pipeline.glossy import mip_pyramid
from arlight.pipeline.ibl import IblParams, IblResult, lighting_from_ldr
from arlight.pipeline.inverse_tone import DEFAULT_OPERATOR, OPERATORS
from arlight.pipeline.pipeline import FrameError, Pipeline
from arlight.pipeline.rendering import EnvironmentMap
from arlight.pipeline.runtime import require_device
from arlight.pipeline.virtual_scene import (
    Anchor,
    Material,
    SceneError,
    VirtualObject,
    VirtualScene,
    demo_scene,
)
from arlight.protocols import (
    Error,
    ErrorField,
    Frame,
    PanoramaConfig,
    ProtocolError,
    SceneObjectSpec,
    SessionConfig,
    decode,
    encode,
    error_from_exception,
    peek_header,
)
from arlight.protocols.fields import MAX_INT as MAX_SEQ
from arlight.server.budget import PANORAMA_BYTES_PER_PIXEL, SessionBudget
from arlight.server.results import result_message

log = logging.getLogger(__name__)

# a compute step: (FrameInput, Session) -> FrameResult; the default runs the session's Pipeline.
# Tests and the transport benchmark inject an identity step (they never ship in the server).
ProcessStep = Callable[[FrameInput, "Session"], FrameResult]

LOSSLESS_QUEUE_SLACK = 2  # frames beyond the credit window a lossless queue tolerates
OUTCOME_CACHE_EXTRA = 4  # final outcomes kept for resending after a reconnect: credits + this


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


class SessionSetupError(ValueError):
    """A Hello whose config cannot make a session; `field` names the offending field."""

    def __init__(self, field: str, message: str, code: str = "bad_field"):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.code = code


class FrameAbandoned(Exception):
    """A frame given up at a pipeline checkpoint: past its deadline ("deadline") or the
    server stopping ("shutdown"). stage: the stage it would have started (or was in)."""

    def __init__(self, reason: str, stage: str, elapsed_s: float, limit_s: float):
        super().__init__(f"{reason} before {stage} after {elapsed_s:.1f} s")
        self.reason = reason
        self.stage = stage
        self.elapsed_s = elapsed_s
        self.limit_s = limit_s


def encode_error(error: Error) -> list:
    """The parts of an Error; never raises. An Error that cannot be encoded (a seq outside
    0..2^63-1, an over-long text) is replaced by an `internal` one that can."""
    try:
        return encode(error)
    except Exception as exc:  # noqa: BLE001 - the fallback below always encodes
        seq = error.seq if isinstance(error.seq, int) and 0 <= error.seq <= MAX_SEQ else None
        log.error("an Error could not be encoded (%s); sent as internal", exc)
        return encode(Error(code="internal", seq=seq,
                            message=f"the server failed to report an error "
                                    f"({type(exc).__name__})"))


def pipeline_config(config: SessionConfig) -> Config:
    """The pipeline Config a session asks for (preset + overrides); SessionSetupError if bad."""
    overrides = dict(config.overrides or {})
    try:
        pipeline = Config.from_preset(config.preset, **overrides)
    except (TypeError, ValueError) as exc:
        field = "preset" if "preset" in str(exc) else "overrides"
        raise SessionSetupError(field, str(exc)) from None
    try:
        require_device(pipeline.device)  # refused at Hello, not by every frame
    except ValueError as exc:
        raise SessionSetupError("overrides", str(exc)) from None
    return pipeline


def camera_from_config(config: SessionConfig, max_pixels: int) -> PinholeCamera:
    """The pinhole camera of a capture session's calibration; SessionSetupError if unusable."""
    cal = config.calibration
    if cal is None:
        raise SessionSetupError("calibration", "a capture session needs the camera calibration")
    if cal.width * cal.height > max_pixels:
        raise SessionSetupError(
            "calibration", f"{cal.width}x{cal.height} = {cal.width * cal.height} pixels exceeds "
            f"the server's limit of {max_pixels}", code="too_large")
    if any(float(d) != 0.0 for d in (cal.D or ())):
        raise SessionSetupError(
            "calibration.D", f"distortion model {cal.distortion_model!r} with non-zero "
            "coefficients is not supported; undistort the images before streaming")
    try:
        return PinholeCamera(int(cal.width), int(cal.height), float(cal.fx), float(cal.fy),
                             float(cal.cx), float(cal.cy))
    except (TypeError, ValueError) as exc:
        raise SessionSetupError("calibration", str(exc)) from None


@dataclass(frozen=True)
class PanoramaLight:
    """How a session turns the Frames' panoramas into light (SessionConfig.panorama, or its
    defaults when the Hello has none): the IBL parameters (the session's inverse tone
    mapping operator), which light renders the virtual objects, and panorama_from_world
    (3, 3): d_panorama = R d_world."""

    params: IblParams
    light_source: str
    panorama_from_world: np.ndarray

    def light(self, panorama: np.ndarray) -> IblResult:
        """The light of one LDR panorama in ITS frame; FrameError (frame.panorama) when the
        image is not a 2:1 equirectangular RGB frame."""
        try:
            return lighting_from_ldr(panorama, self.params)
        except CheckError as exc:
            raise FrameError("panorama", exc.message) from None
        except ValueError as exc:
            raise FrameError("panorama", str(exc)) from None

    def to_world(self, result: IblResult) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(sh (n,), sh_rgb (3, n), dominant direction (3,)) of the panorama's light in the
        world frame: L_world(d) = L_panorama(R d), i.e. the SH rotated by R^T."""
        world_from_panorama = self.panorama_from_world.T
        sh_world = sh_lib.rotate(result.sh, world_from_panorama)
        rgb_world = sh_lib.rotate(result.sh_rgb, world_from_panorama)
        return sh_world, rgb_world, world_from_panorama @ result.dominant_direction


def panorama_light_from_config(config: SessionConfig) -> PanoramaLight:
    """The session's PanoramaLight; SessionSetupError (hello.config.panorama.operator) for an
    operator the server does not have."""
    pano = config.panorama or PanoramaConfig()
    operator = pano.operator or DEFAULT_OPERATOR
    if operator not in OPERATORS:
        raise SessionSetupError("panorama.operator", f"unknown inverse tone mapping operator "
                                f"{operator[:64]!r}; the server's: {', '.join(OPERATORS)}")
    rotation = np.asarray(pano.panorama_from_world, dtype=np.float64).reshape(3, 3)
    return PanoramaLight(IblParams(operator=operator), pano.light_source, rotation)


# the scenes SessionConfig.virtual_scene may name; any other scene travels in config.scene
BUILT_IN_SCENES: dict[str, Callable[[], VirtualScene]] = {"demo": demo_scene}


def scene_from_config(config: SessionConfig) -> VirtualScene | None:
    """The session's virtual scene: a built-in one by name (`virtual_scene`), the one the
    Hello carries (`scene`), or None. SessionSetupError names the field (the object) when the
    name is unknown or an object cannot be rendered (virtual_scene.SceneError)."""
    if config.virtual_scene is not None:
        make = BUILT_IN_SCENES.get(config.virtual_scene)
        if make is None:
            raise SessionSetupError(
                "virtual_scene", f"unknown virtual scene name {config.virtual_scene[:64]!r} "
                f"(the server's built-in scenes: {', '.join(sorted(BUILT_IN_SCENES))}); send "
                "the scene itself: arlight stream --scene FILE")
        return make()
    if config.scene is None:
        return None
    objects = []
    for i, spec in enumerate(config.scene.objects):
        try:
            objects.append(virtual_object(spec))
        except SceneError as exc:
            raise SessionSetupError(f"scene.objects[{i}]", str(exc)) from None
    try:
        return VirtualScene(tuple(objects))
    except SceneError as exc:
        raise SessionSetupError("scene", str(exc)) from None


def virtual_object(spec: SceneObjectSpec) -> VirtualObject:
    """The pipeline's object of a wire object (SceneError if it cannot be rendered). The
    arrays are shared, not copied: uint32 indices viewed as int32 (an index >= 2^31 then
    reads negative and is refused by the object's own check)."""
    anchor = None if spec.anchor is None else Anchor(spec.anchor.pixel, spec.anchor.yaw_deg)
    pose = np.eye(4) if spec.world_from_object is None else spec.world_from_object
    return VirtualObject(spec.name, spec.vertices, spec.triangles.view(np.int32), spec.normals,
                         pose, Material(spec.albedo, spec.roughness, spec.metalness,
                                        spec.mirror), anchor)


def frame_to_input(frame: Frame, camera: PinholeCamera, depth_scale: float) -> FrameInput:
    """Pipeline input of a wire frame: its uint16 depth as received, with the session's
    depth_scale (units per metre); Pipeline.process turns it into metres, once.

    Checks the image sizes against the session's calibration (FrameError names the field);
    everything else (NaN poses, dtypes) is checked by Pipeline.process.
    """
    size = (camera.width, camera.height)
    try:
        for name, image in (("color", frame.color), ("depth", frame.depth)):
            check_image(image, name, channels=3 if name == "color" else None, size=size,
                        size_of="the session's calibration")
    except CheckError as exc:
        raise FrameError(exc.field, exc.message) from None
    # the sources' integers and depth_scale, untouched: a stream of recorded depth gives the
    # pipeline the metres that reading the recording directly gives, bit for bit
    pose = None if frame.pose is None else np.asarray(frame.pose, dtype=np.float64)
    return FrameInput(color=frame.color, depth=frame.depth, depth_scale=float(depth_scale),
                      timestamp=float(frame.timestamp), pose=pose, panorama=frame.panorama)


def default_process(frame: FrameInput, session: Session) -> FrameResult:
    return session.pipeline.process(frame, render_light=session.render_light,
                                    checkpoint=session.checkpoint)


def panorama_only_result(frame: Frame, world: tuple[np.ndarray, np.ndarray, np.ndarray]
                         ) -> FrameResult:
    """The FrameResult of a frame without colour and depth (SPEC.md, "result"): the
    panorama's light in the world frame as the estimate; no camera, so pose is the identity
    and the camera frame is the world frame; confidence: the map's SH are a projection, not
    a fit (every pixel of the area-averaged map counts as a sample, condition number 1)."""
    sh_world, rgb_world, direction = world
    # the SH are projected from the map area-averaged to sh_source_size (or as it came, when
    # not larger): every pixel of that map is one sample
    height = min(frame.panorama.shape[0], IblParams().sh_source_size[1])
    samples = height * 2 * height
    bands = sh_lib.bands_of(len(sh_world))
    return FrameResult(
        timestamp=float(frame.timestamp), sh=sh_world, sh_camera=sh_world,
        dominant_direction_world=direction, dominant_direction_camera=direction,
        intensity=sh_lib.intensity_along(sh_world, direction) if np.any(direction) else 0.0,
        confidence=Confidence(samples=samples, condition_number=1.0, bands_estimated=bands,
                              value=1.0 if np.any(direction) else 0.0,
                              reason="" if np.any(direction) else "black panorama"),
        pose=np.eye(4), sh_rgb=rgb_world, timings_ms={}, diagnostics={})


@dataclass
class Job:
    """A received frame waiting for (or in) a worker. parts: the encoded message, undecoded."""

    seq: int
    parts: list
    receive_time_wall: float  # time.time(), seconds: the Result's server_receive_time
    receive_time_mono: float  # time.monotonic(), seconds: latency and liveness


@dataclass
class JobOutcome:
    """What a worker hands back to the I/O thread: encoded Result or Error parts."""

    session: Session
    job: Job
    parts: list
    ok: bool
    finish_time_mono: float  # time.monotonic(), seconds
    error: Error | None = None


class Session:
    """One session's state. Counters are read by workers and written by the I/O thread."""

    def __init__(self, config: SessionConfig, *, credits: int, max_pixels: int,
                 max_message_bytes: int, process: ProcessStep | None = None,
                 budget: SessionBudget | None = None, cancel: threading.Event | None = None):
        """budget: the per-frame time and per-session memory limits (server/budget.py;
        None: unlimited); cancel: set when the server stops, so a frame in a worker is
        abandoned at its next stage boundary. SessionSetupError for a config it refuses."""
        self.name = config.session
        self.config = config
        self.credits = credits
        self.max_pixels = max_pixels
        self.max_message_bytes = max_message_bytes
        self.pipeline_config = pipeline_config(config)
        if config.exports and self.pipeline_config.transfer.sh_bands < 3:
            raise SessionSetupError("exports", f"the engine layouts hold 3 SH bands and the "
                                    f"session estimates {self.pipeline_config.transfer.sh_bands}"
                                    f" (override sh_bands, `--set sh_bands=N`): ask for 3 or "
                                    f"more, or no exports")
        # a Hello without calibration (allowed with config.panorama): a panorama-only session
        self.camera = None if config.calibration is None else camera_from_config(config,
                                                                                 max_pixels)
        self.panorama_light = panorama_light_from_config(config)
        self.render_light: RenderLight | None = None  # of the job in run()
        self.scene = scene_from_config(config)  # None: nothing to render
        self.budget = budget
        # refused here, at Hello, when its settings could not meet the server's budgets
        self.cost = None if budget is None else budget.check(
            config, self.pipeline_config, self.camera,
            len(self.scene.objects) if self.scene else 0)
        self._cancel = cancel
        self._job_start = 0.0  # time.monotonic() when the job in run() started
        if not (np.isfinite(config.depth_scale) and config.depth_scale > 0):
            raise SessionSetupError("depth_scale", f"must be a finite number of units per metre "
                                                   f"> 0, got {config.depth_scale}")
        self.lossless = config.mode == "lossless"
        self._process = process or default_process
        self._told_no_render = False  # logged once: a scene but no composite from the pipeline
        self._pipeline: Pipeline | None = None
        self.pending: collections.deque[Job] = collections.deque()
        self.in_flight: Job | None = None
        self.capture_peer: bytes | None = None
        self.token: str | None = None  # admits displays and capture Hellos (server.py sets it)
        self.ended = False  # the capture client said Bye: close once the queue is empty
        self.created_mono = time.monotonic()
        self.last_activity = self.created_mono  # time.monotonic() of the last frame or Hello
        self.highest_seq = -1  # highest seq accepted (lossless duplicate detection)
        self.refused_from: int | None = None  # lossless: first seq refused for credits
        # lossless: seq -> encoded final reply (Result or final Error) of the last frames
        self.outcomes: collections.OrderedDict[int, list] = collections.OrderedDict()
        self._lock = threading.Lock()
        self.frames_received = 0
        self.frames_processed = 0
        self.frames_dropped = 0
        self.frames_failed = 0
        self.display_drops = 0
        # (monotonic finish time, receive-to-finish latency), seconds, for the periodic log
        self.recent: collections.deque[tuple[float, float]] = collections.deque(maxlen=512)

    # ------------------------------------------------------------------ I/O thread

    @property
    def pipeline(self) -> Pipeline:
        """The session's Pipeline, built on first use (in a worker: it allocates the volume)."""
        if self._pipeline is None:
            if self.camera is None:
                raise FrameError("color", "this session has no camera calibration (a "
                                 "panorama-only session): send frames without colour and depth")
            self._pipeline = Pipeline(self.pipeline_config, self.camera, scene=self.scene)
        return self._pipeline

    def same_setup(self, config: SessionConfig) -> bool:
        """True if `config` asks for the same session (a reconnecting client's Hello)."""
        a = dataclasses.replace(self.config, client_name="", token=None)
        b = dataclasses.replace(config, client_name="", token=None)
        return a == b

    def offer(self, job: Job) -> str:
        """Queue a received frame. Returns what happened:

        "queued"; "replaced" (live: an older pending frame was dropped); "duplicate" (lossless:
        seq already accepted, still queued or in a worker: its reply comes when it finishes);
        "resend" (lossless: already finished, its Result or final Error is in `outcomes`);
        "expired" (lossless: seq at or below the highest accepted, neither waiting nor in
        `outcomes`: its outcome can no longer be sent again); "overflow" (lossless: the
        client ignored its credit window; the frame is refused).
        """
        seq = job.seq
        self.last_activity = job.receive_time_mono
        if self.lossless:
            if seq <= self.highest_seq:
                if seq in self.outcomes:
                    return "resend"
                waiting = (self.in_flight is not None and self.in_flight.seq == seq) or any(
                    job.seq == seq for job in self.pending)
                return "duplicate" if waiting else "expired"
            # once a frame is refused, later ones are refused too until it comes again: a
            # client that retries in order then keeps its frames in order
            if len(self.pending) >= self.credits + LOSSLESS_QUEUE_SLACK or (
                    self.refused_from is not None and seq > self.refused_from):
                self.refused_from = seq if self.refused_from is None else self.refused_from
                return "overflow"
            self.refused_from = None
            with self._lock:
                self.frames_received += 1
            self.highest_seq = seq
            self.pending.append(job)
            return "queued"
        with self._lock:
            self.frames_received += 1
            outcome = "queued"
            if self.pending:
                self.pending.clear()
                self.frames_dropped += 1
                outcome = "replaced"
        self.highest_seq = max(self.highest_seq, seq)
        self.pending.append(job)
        return outcome

    def next_job(self) -> Job | None:
        """The next frame to process, if none of this session's frames is in a worker."""
        if self.in_flight is not None or not self.pending:
            return None
        self.in_flight = self.pending.popleft()
        return self.in_flight

    def finish(self, outcome: JobOutcome) -> None:
        self.in_flight = None
        self.last_activity = max(self.last_activity, outcome.finish_time_mono)
        if self.lossless and (outcome.ok or not outcome.error.retryable):
            # the frame's final reply: a duplicate of this seq gets it again, so a reply lost
            # on the way (the client disconnected) is recovered by resending the frame
            self.outcomes[outcome.job.seq] = outcome.parts
            while len(self.outcomes) > self.credits + OUTCOME_CACHE_EXTRA:
                self.outcomes.popitem(last=False)
        if outcome.ok:
            self.recent.append((outcome.finish_time_mono,
                                outcome.finish_time_mono - outcome.job.receive_time_mono))

    def pipeline_lost(self, job: Job) -> list[Job]:
        """After `job` failed with PipelineLost (its outcome already finished): un-accept it
        and the queued frames, returned (the caller reports them retryable). Lossless: the
        highest accepted seq goes back below job's, and frames above it are refused
        (`credits`) until it comes again, so the resent frames keep their order."""
        jobs = list(self.pending)
        self.pending.clear()
        with self._lock:
            self.frames_received -= 1 + len(jobs)
        if self.lossless:
            self.highest_seq = min(self.highest_seq, job.seq - 1)
            self.refused_from = job.seq
        return jobs

    def drop_pending(self) -> list[Job]:
        """Remove and return the queued frames (shutdown); live frames count as dropped."""
        jobs = list(self.pending)
        self.pending.clear()
        if not self.lossless:
            with self._lock:
                self.frames_dropped += len(jobs)
        return jobs

    @property
    def idle(self) -> bool:
        return self.in_flight is None and not self.pending

    def counters(self) -> dict:
        with self._lock:
            return {"frames_received": self.frames_received,
                    "frames_processed": self.frames_processed,
                    "frames_dropped": self.frames_dropped,
                    "frames_failed": self.frames_failed}

    def _environment(self, panorama: IblResult) -> EnvironmentMap | None:
        """The panorama's HDR map as the environment mirror and glossy objects reflect, or
        None when no virtual object reflects (the mip pyramid costs a pass over the map)."""
        scene = self.scene
        if panorama.hdr is None or not scene or not any(
                o.material.mirror or o.material.metalness > 0 for o in scene.objects):
            return None
        return EnvironmentMap(mip_pyramid(panorama.hdr), self.panorama_light.panorama_from_world)

    # ------------------------------------------------------------------ worker thread

    def checkpoint(self, stage: str) -> None:
        """Called by the pipeline before each stage (and each robust iteration of the
        light estimate): FrameAbandoned when the frame is past the budget's deadline or the
        server is stopping (the step is not started)."""
        elapsed = time.monotonic() - self._job_start
        if self._cancel is not None and self._cancel.is_set():
            raise FrameAbandoned("shutdown", stage, elapsed, 0.0)
        limit = math.inf if self.budget is None else self.budget.frame_deadline_s
        if elapsed > limit:
            raise FrameAbandoned("deadline", stage, elapsed, limit)

    def _check_declared_sizes(self, parts: list) -> None:
        """Before any payload is decoded: colour or depth declared at another size than the
        calibration's is refused (FrameError naming the image), and a panorama larger than
        the session's memory budget leaves room for (OverBudget, frame.panorama)."""
        header = peek_header(parts)
        pano = header.get("panorama")
        if isinstance(pano, dict) and self.budget is not None:
            w, h = pano.get("width"), pano.get("height")
            if type(w) is int and type(h) is int and 0 < w * h <= self.max_pixels:
                need = w * h * PANORAMA_BYTES_PER_PIXEL
                room = self.budget.session_memory_bytes - self.cost.session_bytes
                if need > room:
                    raise OverBudget("frame.panorama", (
                        f"a {w} x {h} panorama needs about {need / 2**20:.0f} MiB, over what "
                        f"the session's memory budget leaves for it ({max(room, 0) / 2**20:.0f}"
                        f" MiB of {self.budget.session_memory_bytes / 2**20:.0f} MiB, `arlight "
                        "serve --session-memory-mb`); send a smaller panorama"))
        if self.camera is None:
            return
        for key in ("color", "depth"):
            d = header.get(key)
            if not isinstance(d, dict):
                continue
            w, h = d.get("width"), d.get("height")
            if type(w) is not int or type(h) is not int or w * h > self.max_pixels:
                continue  # the decoder names these (bad_field, too_large)
            if (w, h) != (self.camera.width, self.camera.height):
                raise FrameError(key, f"{key} is {w} x {h}, the session's calibration "
                                 f"{self.camera.width} x {self.camera.height}")

    def run(self, job: Job) -> JobOutcome:
        """Decode, check, process and encode one frame. Never raises: errors become Error."""
        self._job_start = time.monotonic()
        try:
            self._check_declared_sizes(job.parts)
            frame = decode(job.parts, max_message_bytes=self.max_message_bytes,
                           max_pixels=self.max_pixels)
            if not isinstance(frame, Frame):
                raise ProtocolError("bad_state", f"expected a Frame, got {type(frame).__name__}")
            panorama = world = None
            self.render_light = None
            if frame.panorama is not None:  # first: a bad panorama fails before the pipeline
                panorama = self.panorama_light.light(frame.panorama)
                world = self.panorama_light.to_world(panorama)
                if self.panorama_light.light_source == "panorama":
                    self.render_light = RenderLight(world[0], world[1], self._environment(panorama))
            composite = None
            if frame.color is None:  # panorama-only: no RGB-D pipeline
                result = panorama_only_result(frame, world)
            else:
                if self.camera is None:
                    raise FrameError("color", "this session has no camera calibration (a "
                                     "panorama-only session): send frames without colour "
                                     "and depth")
                frame_input = frame_to_input(frame, self.camera, self.config.depth_scale)
                result = self._process(frame_input, self)
                composite = self.composite(frame_input, result) if self.config.want_composite \
                    else None
            if panorama is not None:
                result.timings_ms = {**result.timings_ms, **{  # stages: they add up
                    f"Panorama{k}": v for k, v in panorama.timings_ms.items()}}
                result.diagnostics = {**result.diagnostics, "light_source": (
                    "panorama" if frame.color is None else self.panorama_light.light_source),
                    "panorama_operator": self.panorama_light.params.operator}
            self._check_volume_budget()
        except Exception as exc:  # noqa: BLE001 - every failure becomes an Error reply
            return self._failed(job, frame_error(exc, job.seq))
        finally:
            self.render_light = None
        finish_wall = time.time()
        with self._lock:
            self.frames_processed += 1
            counters = (self.frames_received, self.frames_processed, self.frames_dropped)
        try:
            message = result_message(result, seq=job.seq, counters=counters,
                                     receive_time_wall=job.receive_time_wall,
                                     finish_time_wall=finish_wall, composite=composite,
                                     composite_codec=frame.color_codec,
                                     jpeg_quality=frame.jpeg_quality, panorama=panorama,
                                     exports=self.config.exports)
            return JobOutcome(self, job, encode(message), True, time.monotonic())
        except Exception as exc:  # noqa: BLE001 - e.g. a non-finite estimate
            return self._failed(job, Error(
                code="internal", seq=job.seq,
                message=f"the server could not send the Result of this frame ({exc})"))

    def composite(self, frame: FrameInput, result: FrameResult) -> np.ndarray:
        """The frame a Result carries: without a virtual scene the input colour frame,
        unchanged; with one the pipeline's rendering of it (the input frame while the
        pipeline makes none)."""
        if self.scene and result.composite is not None:
            return result.composite
        if self.scene and not self._told_no_render:
            self._told_no_render = True
            log.info("session %s: the pipeline rendered no composite; the Results carry the "
                     "input frame", self.name)
        return frame.color

    def _check_volume_budget(self) -> None:
        """The volume grows with the surface seen: past the session's memory budget it is
        dropped (the next frame starts a new one) and this frame fails (over_budget)."""
        if self._pipeline is None:
            return
        over = self.volume_budget_error(self._pipeline.volume_blocks)
        if over is not None:
            self._pipeline = None
            raise over

    def volume_budget_error(self, blocks: int) -> OverBudget | None:
        """The over_budget error of a volume of `blocks` blocks, None within the budget."""
        if self.budget is None:
            return None
        used = blocks * self.cost.bytes_per_block
        if used > self.cost.volume_limit_bytes:
            return OverBudget("frame",
                f"the session's volume grew to {blocks} blocks ({used / 2**20:.0f} "
                f"MiB), over its share of the per-session memory budget "
                f"({self.cost.volume_limit_bytes / 2**20:.0f} MiB of "
                f"{self.budget.session_memory_bytes / 2**20:.0f} MiB, `arlight serve "
                "--session-memory-mb`); the volume is reset and the session goes on")
        return None

    def crashed(self, job: Job, exc: BaseException | None) -> JobOutcome:
        """The outcome of a job whose worker failed outside run()'s own handling."""
        log.error("session %s: frame %d: worker failed: %r", self.name, job.seq, exc)
        return self._failed(job, Error(code="internal", seq=job.seq,
                                       message=f"the server failed to process this frame "
                                               f"({type(exc).__name__})"))

    def _failed(self, job: Job, error: Error) -> JobOutcome:
        if error.code == "internal":
            log.error("session %s: frame %d failed: %s", self.name, job.seq, error.message)
        else:
            log.info("session %s: frame %d rejected: %s", self.name, job.seq, error.message)
        with self._lock:
            self.frames_failed += 1
        return JobOutcome(self, job, encode_error(error), False, time.monotonic(), error)


def frame_error(exc: Exception, seq: int | None) -> Error:
    """The Error reply for an exception raised while handling frame `seq`."""
    if isinstance(exc, ProtocolError):
        error = error_from_exception(exc)
        return dataclasses.replace(error, seq=seq)
    if isinstance(exc, FrameError):
        return Error(code="bad_field", message=str(exc), field=f"frame.{exc.field}", seq=seq)
    if isinstance(exc, FrameAbandoned):
        if exc.reason == "shutdown":
            return Error(code="bad_state", field=ErrorField.SHUTDOWN, seq=seq, retryable=True,
                         message="the server shut down before finishing this frame; send it "
                                 "again after reconnecting")
        return Error(code="deadline", seq=seq, message=(
            f"frame abandoned before {exc.stage}: {exc.elapsed_s:.1f} s in the pipeline, over "
            f"the server's per-frame deadline of {exc.limit_s:g} s (`arlight serve "
            "--frame-deadline`); lower the session's cost (--preset fast, a smaller image, "
            "fewer rt_directions or robust_iterations)"))
    if isinstance(exc, OverBudget):
        return Error(code="over_budget", seq=seq, field=exc.field, message=str(exc))
    if isinstance(exc, PipelineLost):
        return Error(code="bad_state", field=ErrorField.PIPELINE_LOST, seq=seq, retryable=True,
                     message=f"{exc}; this frame and the session's queued frames were not "
                             "processed: send them again (a new pipeline, a fresh volume)")
    log.error("frame %s: unexpected failure", seq, exc_info=exc)
    return Error(code="internal", message=f"the server failed to process this frame "
                                          f"({type(exc).__name__}: {exc})"[:4096], seq=seq)

