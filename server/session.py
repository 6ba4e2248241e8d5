"""One streaming session: what its Hello set up, its queue of frames, its pipeline.

A session is created by a capture client's Hello and named by `SessionConfig.session`. Its
three parts each have one job:
- `SessionSetup` (here): what the Hello asked for, checked once (SessionSetupError names the
  field): the pipeline Config, the camera, the panorama light, the virtual scene, the budget;
- `FrameQueue` (server/frame_queue.py): the queue and credit state machine, the I/O thread's;
- `SessionCompute` (server/worker.py): the session's pipeline, one frame at a time in a
  worker (`run_frame`), so a session's frames are processed in order and its Pipeline is
  never used by two threads at once.
`Session` holds them and what the server keeps about the session's peers. Sessions share
nothing: each has its own setup, queue, pipeline and counters.

Clocks: liveness and expiry (`last_activity`, the latency log) run on time.monotonic();
wall-clock times (`*_wall`) are only the timestamps that go on the wire (a Result's
server_receive_time and server_finish_time).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.core.checks import CheckError
from arlight.pipeline import sh as sh_lib
from arlight.pipeline.config import Config
from arlight.pipeline.ibl import IblParams, IblResult, lighting_from_ldr
from arlight.pipeline.inverse_tone import DEFAULT_OPERATOR, OPERATORS
from arlight.pipeline.pipeline import FrameError
from arlight.pipeline.runtime import require_device
from arlight.pipeline.virtual_scene import (
    Anchor,
    Material,
    SceneError,
    VirtualObject,
    VirtualScene,
    demo_scene,
)
from arlight.protocols import PanoramaConfig, SceneObjectSpec, SessionConfig
from arlight.server.budget import SceneLoad, SessionBudget, SessionCost
from arlight.server.frame_queue import FrameQueue, Job
from arlight.server.worker import (  # PipelineLost: arlight/ray_serve.py imports it from here
    OverBudget,
    PipelineLost,
    ProcessStep,
    SessionCompute,
    volume_budget_error,
)

FRAME_HEADER_BYTES = 64 * 2**10  # a Frame's msgpack header, at most (a few hundred bytes)
QUEUED_FRAMES = 8  # frames of a session's calibration its queue's bytes allow for


class SessionSetupError(ValueError):
    """A Hello whose config cannot make a session; `field` names the offending field."""

    def __init__(self, field: str, message: str, code: str = "bad_field"):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.code = code


def pipeline_config(config: SessionConfig) -> Config:
    """The pipeline Config a session asks for (preset + overrides); SessionSetupError if bad."""
    overrides = dict(config.overrides or {})
    size = probe_size(config)
    if size is not None:
        overrides["probe_size"] = size
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


def probe_size(config: SessionConfig) -> int | None:
    """The probe size a Hello's `config.probe` asks for (None: no probe), checked against
    its overrides: the probe must not be switched off (`probe=false`), and a `probe_size`
    override must agree (SessionSetupError naming `probe` or `probe.size`)."""
    request = getattr(config, "probe", None)  # (callers may pass a config-like namespace)
    if request is None:
        return None
    overrides = config.overrides or {}
    if overrides.get("probe") is False:
        raise SessionSetupError(
            "probe",
            "the Hello asks for a reflection probe and its overrides switch the probe off "
            "(probe=false): drop one of the two",
        )
    given = overrides.get("probe_size")
    if given is not None and given != request.size:
        raise SessionSetupError(
            "probe.size",
            f"{request.size} texels a face, but overrides.probe_size is {given!r}: "
            "give the size once, in config.probe",
        )
    return int(request.size)


def check_probe(
    config: SessionConfig, camera: PinholeCamera | None, scene: VirtualScene | None
) -> None:
    """A probe needs a camera (not a panorama-only session) and a point: the Hello's
    `point_world`, or a virtual scene whose objects' centre it is (SessionSetupError)."""
    if config.probe is None:
        return
    if camera is None:
        raise SessionSetupError(
            "probe",
            "a panorama-only session (no calibration) has no room to make a reflection probe "
            "of; send RGB-D frames with a calibration, or drop config.probe",
        )
    if config.probe.point_world is None and not scene:
        raise SessionSetupError(
            "probe.point_world",
            "nil means the centre of the virtual scene's objects, and the session has no "
            "scene: give the point (world frame, metres) or a scene",
        )


# The focal lengths a session may declare, in multiples of the image's side along the same
# axis: 0.1 is a 157-degree field of view, 100 a 0.6-degree one. The cost model prices a
# frame by its pixels; far outside these, the same pixels unproject to a volume that grows
# as 1 / f^2 (fx = fy = 0.05 at 64 x 48, priced at 46 MiB, took 1.2 GB and 20 s a frame) or
# to non-finite points (issue 39, item 2). The principal point may lie up to one image side
# outside the image.
FOCAL_RANGE = (0.1, 100.0)


def check_intrinsics(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> None:
    """SessionSetupError (bad_field, hello.config.calibration.KEY) for intrinsics outside
    the range a camera has: fx / width and fy / height in FOCAL_RANGE, cx in [-w, 2w] and cy
    in [-h, 2h] (pixels)."""
    lo, hi = FOCAL_RANGE
    for key, f, side in (("fx", fx, width), ("fy", fy, height)):
        if not (math.isfinite(f) and lo * side <= f <= hi * side):
            raise SessionSetupError(
                f"calibration.{key}",
                f"{key} = {f:g} pixels is outside {lo:g} to {hi:g} times the image's "
                f"{'width' if key == 'fx' else 'height'} ({lo * side:g}..{hi * side:g} for "
                f"{width} x {height}): not a camera's focal length; check the calibration",
            )
    for key, c, side in (("cx", cx, width), ("cy", cy, height)):
        if not (math.isfinite(c) and -side <= c <= 2 * side):
            raise SessionSetupError(
                f"calibration.{key}",
                f"{key} = {c:g} pixels is more than one image side ({side}) outside the image",
            )


def camera_from_config(config: SessionConfig, max_pixels: int) -> PinholeCamera:
    """The pinhole camera of a capture session's calibration; SessionSetupError if unusable."""
    cal = config.calibration
    if cal is None:
        raise SessionSetupError("calibration", "a capture session needs the camera calibration")
    if cal.width * cal.height > max_pixels:
        raise SessionSetupError(
            "calibration",
            f"{cal.width}x{cal.height} = {cal.width * cal.height} pixels exceeds "
            f"the server's limit of {max_pixels}",
            code="too_large",
        )
    check_intrinsics(cal.width, cal.height, cal.fx, cal.fy, cal.cx, cal.cy)
    if any(float(d) != 0.0 for d in (cal.D or ())):
        raise SessionSetupError(
            "calibration.D",
            f"distortion model {cal.distortion_model!r} with non-zero "
            "coefficients is not supported; undistort the images before streaming",
        )
    try:
        return PinholeCamera(
            int(cal.width),
            int(cal.height),
            float(cal.fx),
            float(cal.fy),
            float(cal.cx),
            float(cal.cy),
        )
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
        raise SessionSetupError(
            "panorama.operator",
            f"unknown inverse tone mapping operator "
            f"{operator[:64]!r}; the server's: {', '.join(OPERATORS)}",
        )
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
                "virtual_scene",
                f"unknown virtual scene name {config.virtual_scene[:64]!r} "
                f"(the server's built-in scenes: {', '.join(sorted(BUILT_IN_SCENES))}); send "
                "the scene itself: arlight stream --scene FILE",
            )
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
    return VirtualObject(
        spec.name,
        spec.vertices,
        spec.triangles.view(np.int32),
        spec.normals,
        pose,
        Material(spec.albedo, spec.roughness, spec.metalness, spec.mirror),
        anchor,
    )


@dataclass(frozen=True, eq=False)
class SessionSetup:
    """What a capture Hello set up, checked once (`from_config`; SessionSetupError names the
    field of a config the server refuses). camera None: a panorama-only session; scene None:
    nothing to render; budget None: unlimited (else cost: the session's share of it)."""

    name: str
    config: SessionConfig
    pipeline_config: Config
    camera: PinholeCamera | None
    panorama_light: PanoramaLight
    scene: VirtualScene | None
    max_pixels: int
    max_message_bytes: int
    budget: SessionBudget | None = None
    cost: SessionCost | None = None

    @classmethod
    def from_config(
        cls,
        config: SessionConfig,
        *,
        max_pixels: int,
        max_message_bytes: int,
        budget: SessionBudget | None = None,
    ) -> SessionSetup:
        """budget: the per-frame time and per-session memory limits (server/budget.py); a
        Hello whose settings could not meet them is refused here (over_budget)."""
        pipeline = pipeline_config(config)
        if config.exports and pipeline.transfer.sh_bands < 3:
            raise SessionSetupError(
                "exports",
                f"the engine layouts hold 3 SH bands and the "
                f"session estimates {pipeline.transfer.sh_bands}"
                f" (override sh_bands, `--set sh_bands=N`): ask for 3 or "
                f"more, or no exports",
            )
        # a Hello without calibration (allowed with config.panorama): a panorama-only session
        camera = None if config.calibration is None else camera_from_config(config, max_pixels)
        panorama_light = panorama_light_from_config(config)
        scene = scene_from_config(config)
        check_probe(config, camera, scene)
        load = (
            None
            if scene is None or budget is None
            else SceneLoad.of([(o.vertices, o.triangles) for o in scene.objects])
        )
        cost = (
            None
            if budget is None
            else budget.check(config, pipeline, camera, len(scene.objects) if scene else 0, load)
        )
        if not (np.isfinite(config.depth_scale) and config.depth_scale > 0):
            raise SessionSetupError(
                "depth_scale",
                f"must be a finite number of units per metre > 0, got {config.depth_scale}",
            )
        return cls(
            config.session,
            config,
            pipeline,
            camera,
            panorama_light,
            scene,
            max_pixels,
            max_message_bytes,
            budget,
            cost,
        )

    def volume_budget_error(self, blocks: int) -> OverBudget | None:
        """The over_budget error of a volume of `blocks` blocks, None within the budget."""
        return volume_budget_error(blocks, self.budget, self.cost)

    @property
    def queue_bytes(self) -> int:
        """The most bytes of lossless frames this session keeps queued (issue 39, item 5):
        a full credit window of frames of its calibration's size (colour and depth raw or
        compressed, x 2: a codec may grow noise, and FRAME_HEADER_BYTES of header each),
        plus one frame as large as a message may be (one with a big panorama). Before, a
        session queued credits + 2 frames of max_message_bytes each whatever its
        calibration (4 small sessions: RSS 451 MB -> 2.49 GB). A frame past it is refused
        as one past the credit window is (retryable: sent again after a Result)."""
        pixels = 0 if self.camera is None else self.camera.width * self.camera.height
        frame = FRAME_HEADER_BYTES + 2 * 5 * pixels
        return QUEUED_FRAMES * frame + self.max_message_bytes


class Session:
    """One session: `setup`, `queue` (its frames, credits and counters), `compute` (its
    pipeline) and what the server keeps about its peers.

    A ProcessStep given to the server (server/worker.py) is called with the frame, the
    Session, the light to render with and the frame's deadline: it reads what the Hello set
    up (`name`, `config`, `pipeline_config`, `camera`, `scene`, `budget`) and calls
    `volume_budget_error(blocks)` for a volume it holds elsewhere.
    """

    def __init__(
        self,
        config: SessionConfig,
        *,
        credits: int,
        max_pixels: int,
        max_message_bytes: int,
        process: ProcessStep | None = None,
        budget: SessionBudget | None = None,
        cancel: threading.Event | None = None,
    ):
        """credits: the lossless credit window; process: a compute step in place of the
        Pipeline; budget: the server's limits (None: unlimited); cancel: set when the server
        stops, so a frame in a worker is abandoned at its next stage boundary.
        SessionSetupError for a config it refuses."""
        setup = SessionSetup.from_config(
            config, max_pixels=max_pixels, max_message_bytes=max_message_bytes, budget=budget
        )
        if config.probe is not None and process is not None:
            # the probe is read from the server's own Pipeline (SessionCompute.last_probe)
            raise SessionSetupError(
                "probe",
                "this server computes through a step of its own (arlight serve --ray), "
                "which makes no reflection probe: drop config.probe or use a server "
                "without --ray",
            )
        self.setup = setup
        # what the Hello set up, read-only (also a ProcessStep's view of the session)
        self.name = setup.name
        self.config = setup.config
        self.pipeline_config = setup.pipeline_config
        self.camera = setup.camera
        self.scene = setup.scene
        self.budget = setup.budget
        self.lossless = config.mode == "lossless"
        self.created_mono = time.monotonic()
        self.queue = FrameQueue(
            lossless=self.lossless,
            credits=credits,
            now=self.created_mono,
            max_queued_bytes=setup.queue_bytes,
        )
        self.compute = SessionCompute(self.setup, process, owner=self, cancel=cancel)
        self.capture_peer: bytes | None = None
        self.token: str | None = None  # admits displays and capture Hellos (server.py sets it)
        self.client = ""  # who created it (server/clients.py): counted per client
        self.ended = False  # the capture client said Bye: close once the queue is empty
        self.display_drops = 0  # Results not delivered to a display (its queue full)

    def volume_budget_error(self, blocks: int) -> OverBudget | None:
        return self.setup.volume_budget_error(blocks)

    # what the server keeps

    @property
    def last_activity(self) -> float:
        """time.monotonic() of the last frame, finished frame or Hello."""
        return self.queue.last_activity

    @last_activity.setter
    def last_activity(self, now: float) -> None:
        self.queue.last_activity = now

    @property
    def idle(self) -> bool:
        return self.queue.idle

    def same_setup(self, config: SessionConfig) -> bool:
        """True if `config` asks for the same session (a reconnecting client's Hello)."""
        a = dataclasses.replace(self.config, client_name="", token=None)
        b = dataclasses.replace(config, client_name="", token=None)
        return a == b

    def snapshot(self) -> dict:
        """The session's counters and state, plain (Server.snapshot: tests and logs)."""
        return {
            **self.counters(),
            "mode": self.config.mode,
            "capture_attached": self.capture_peer is not None,
            "pending": len(self.queue.pending),
        }

    def rate_line(self, now: float, interval_s: float, displays: int) -> str | None:
        """The periodic log line of the last `interval_s` seconds (None: nothing happened):
        frame rate, receive-to-finish latency, counters, displays and their losses."""
        recent = [lat for t, lat in self.queue.recent if t > now - interval_s]
        if not recent and self.idle:
            return None
        c = self.queue.counters()
        lat_ms = np.asarray(recent) * 1e3
        latency = (
            f"latency median {np.median(lat_ms):.0f} ms, p95 {np.percentile(lat_ms, 95):.0f} ms"
            if recent
            else "no frames finished"
        )
        return (
            f"session {self.name}: {len(recent) / interval_s:.1f} fps, {latency} (receive "
            f"to finish); received {c.received}, processed {c.processed}, dropped "
            f"{c.dropped}, failed {c.failed}; {displays} display(s), {self.display_drops} "
            "result(s) not delivered"
        )

    def counters(self) -> dict[str, int]:
        c = self.queue.counters()
        return {
            "frames_received": c.received,
            "frames_processed": c.processed,
            "frames_dropped": c.dropped,
            "frames_failed": c.failed,
        }


__all__ = [
    "BUILT_IN_SCENES",
    "Job",
    "PanoramaLight",
    "PipelineLost",
    "Session",
    "SessionSetup",
    "SessionSetupError",
    "camera_from_config",
    "panorama_light_from_config",
    "pipeline_config",
    "scene_from_config",
    "virtual_object",
]
