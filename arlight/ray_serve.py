"""`arlight serve --ray`: each session's pipeline in a Ray actor, the server's I/O stays here.

The server keeps its ZeroMQ socket, its I/O thread, the sessions' queues, credits and
lossless bookkeeping; only the compute step (server/worker.py `ProcessStep`) changes. A
worker thread hands the decoded frame and the light to render with to the session's actor
(`SessionActor.process`) and waits for the result, calling the frame's deadline (its
`Deadline`: past the per-frame limit or the server stopping) between short waits, as the
built-in Pipeline calls it between stages; the actor holds the session's `Pipeline` (volume,
pose, temporal filter), so one server address serves as many sessions as the Ray cluster has
room for.

Resources: one actor per session, asking Ray for the preset's CPUs and one GPU for a CUDA
session (`arlight.batch.actor_resources`, the rule `arlight batch` uses). A session whose
actor cannot be placed yet (the cluster is full) waits for it; its frames count against the
frame deadline meanwhile.

A lost actor (its node or worker process died, `ray.kill`): Ray raises `RayActorError` on the
frame's result. The frame becomes `PipelineLost`, which the server reports as the retryable
`bad_state` Error `pipeline_lost` and un-accepts the session's queued frames (SPEC.md,
"Retryable Errors"): the client sends them again and they go to a new actor. The volume and
the tracked pose die with the actor: the new actor starts a fresh volume (with poses sent by
the client nothing else changes; with tracking, the trajectory restarts at the identity).
A session whose actors die MAX_LOSSES_IN_A_ROW times without finishing a frame (an actor
that cannot be constructed there, a frame that kills it every time) gets a final `internal`
Error instead, so a poisoned frame cannot loop forever.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import weakref
from typing import TYPE_CHECKING, Any, NoReturn

from arlight.batch import BatchUsageError, actor_resources, import_ray, init_local_ray
from arlight.server.session import PipelineLost

if TYPE_CHECKING:
    from arlight.core.camera import PinholeCamera
    from arlight.core.frames import FrameInput, FrameResult, RenderLight
    from arlight.pipeline.config import Config
    from arlight.pipeline.virtual_scene import VirtualScene
    from arlight.server.session import Session
    from arlight.server.worker import Deadline

log = logging.getLogger(__name__)

WAIT_SLICE_S = 0.05  # between deadline/shutdown checks while an actor works on a frame
MAX_LOSSES_IN_A_ROW = 3


class SessionActor:
    """The body of one session's Ray actor: its Pipeline, one frame at a time."""

    def __init__(
        self, config: Config, camera: PinholeCamera, scene: VirtualScene | None, num_cpus: int
    ):
        from arlight.pipeline.pipeline import Pipeline
        from arlight.pipeline.runtime import configure_process, limit_numba_threads

        configure_process(num_cpus)  # Open3D on the actor's own cores
        with contextlib.suppress(Exception):  # and the kernels, where numba allows it
            limit_numba_threads(num_cpus)
        self._make = lambda: Pipeline(config, camera, scene=scene)
        self._pipeline = self._make()

    def process(
        self, frame: FrameInput, render_light: RenderLight | None = None
    ) -> tuple[FrameResult, int]:
        """(FrameResult, the volume's block count after it) of one frame."""
        result = self._pipeline.process(frame, render_light=render_light)
        return result, self._pipeline.volume_blocks

    def reset(self) -> None:
        """A fresh Pipeline (the volume went over the session's memory budget)."""
        self._pipeline = self._make()

    def pid(self) -> int:
        return os.getpid()


def connect(address: str | None) -> tuple[Any, bool]:
    """The ray module, connected: `None`/"local" starts a local Ray (no dashboard), "auto" or
    HOST:PORT / ray://HOST:10001 joins a cluster; an existing connection is reused.
    Returns (ray, started: whether this call started the connection). BatchUsageError (a
    ValueError: exit 2) when Ray is missing or the address cannot be reached."""
    ray = import_ray()
    if ray.is_initialized():
        return ray, False
    local = address is None or address == "local"
    if address is not None and address not in ("local", "auto"):
        _check_reachable(address)
    try:
        if local:  # "local": always a new Ray of this machine, never a `ray start` one
            init_local_ray(ray)  # its servers on loopback only
        else:
            ray.init(address=address, log_to_driver=False)
    except Exception as exc:  # noqa: BLE001 - Ray raises many types for "cannot connect"
        where = "a local Ray" if local else f"--ray {address}"
        first = (str(exc).strip().splitlines() or [""])[0][:300]
        raise BatchUsageError(
            f"{where}: cannot start or connect ({type(exc).__name__}: {first})"
        ) from None
    return ray, True


CONNECT_CHECK_S = 5.0


def _check_reachable(address: str) -> None:
    """BatchUsageError unless HOST:PORT (or ray://HOST:PORT) accepts a TCP connection within
    CONNECT_CHECK_S: ray.init itself retries an unreachable address for minutes."""
    import socket

    host, _, port = address.removeprefix("ray://").rpartition(":")
    try:
        socket.create_connection((host.strip("[]"), int(port)), CONNECT_CHECK_S).close()
    except (OSError, ValueError) as exc:
        raise BatchUsageError(
            f"--ray {address}: no Ray cluster answers there ({exc}); start "
            "one (`ray start --head`) or give its address (HEAD:6379, "
            "ray://HEAD:10001 or auto)"
        ) from None


class RayCompute:
    """The server's compute step on Ray (`Server(options, process=RayCompute(ray))`).

    Called by the server's worker threads, one frame per session at a time; `release` when
    a session closes (its actor is killed), `close` when the server stops.
    """

    runs_elsewhere = True  # the worker threads only wait: no compute lock, one per session

    def __init__(self, ray: Any):
        self._ray = ray
        self._cls = ray.remote(SessionActor)
        self._lock = threading.Lock()
        self._actors: dict[Session, Any] = {}  # Session -> actor handle
        # Session -> actors lost in a row without a finished frame
        self._losses: dict[Session, int] = {}
        # sessions released: no new actor for them
        self._closed: weakref.WeakSet[Session] = weakref.WeakSet()
        self._count = 0
        self.actors_lost = 0
        cluster = ray.cluster_resources()
        log.info(
            "Ray: %g CPUs, %g GPUs in the cluster; one actor per session",
            cluster.get("CPU", 0),
            cluster.get("GPU", 0),
        )

    def actor(self, session: Session) -> Any:
        """The session's actor (None if it has none now): tests and diagnostics."""
        with self._lock:
            return self._actors.get(session)

    def _actor_for(self, session: Session) -> Any:
        with self._lock:
            if session in self._closed:
                raise PipelineLost(f"session {session.name} is closed")
            actor = self._actors.get(session)
            if actor is not None:
                return actor
            self._count += 1
            number = self._count
        config = session.pipeline_config
        res = actor_resources(session.config.preset, config.device, self._ray.cluster_resources())
        actor = self._cls.options(
            num_cpus=res["num_cpus"],
            num_gpus=res["num_gpus"],
            max_restarts=0,
            name=f"arlight-{os.getpid()}-{number}",
        ).remote(config, session.camera, session.scene, res["num_cpus"])
        with self._lock:
            self._actors[session] = actor
        log.info(
            "session %s: pipeline in Ray actor %d (%d CPU, %d GPU)",
            session.name,
            number,
            res["num_cpus"],
            res["num_gpus"],
        )
        return actor

    def __call__(
        self,
        frame: FrameInput,
        session: Session,
        render_light: RenderLight | None,
        deadline: Deadline,
    ) -> FrameResult:
        """The session's estimate of one frame (a ProcessStep, server/worker.py): its actor's
        Pipeline.process(frame, render_light), `deadline` called while it waits."""
        from arlight.pipeline.pipeline import FrameError

        if session.camera is None:
            raise FrameError(
                "color",
                "this session has no camera calibration (a panorama-"
                "only session): send frames without colour and depth",
            )
        ray = self._ray
        actor = self._actor_for(session)
        ref = actor.process.remote(frame, render_light)
        try:
            while not ray.wait([ref], timeout=WAIT_SLICE_S)[0]:
                deadline("the Ray actor's result")  # FrameAbandoned
        except BaseException:
            with contextlib.suppress(Exception):
                ray.cancel(ref)
            raise
        try:
            result, blocks = ray.get(ref)
        except ray.exceptions.RayActorError as exc:
            self._lost(session, actor, exc)
        except ray.exceptions.RayTaskError as exc:  # the pipeline raised: its own exception
            cause = getattr(exc, "cause", None)
            if isinstance(cause, Exception):
                raise cause from None
            raise
        with self._lock:
            self._losses.pop(session, None)
        over = session.volume_budget_error(blocks)
        if over is not None:
            actor.reset.remote()  # ordered before the session's next frame on this actor
            raise over
        return result

    def _lost(self, session: Session, actor: Any, exc: BaseException) -> NoReturn:
        with self._lock:
            if session in self._closed:  # killed by release(): the session is gone
                raise PipelineLost(f"session {session.name} closed")
            if self._actors.get(session) is actor:
                del self._actors[session]
            losses = self._losses.get(session, 0) + 1
            self._losses[session] = losses
            self.actors_lost += 1
        why = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        log.warning(
            "session %s: its Ray actor was lost (%s: %s); %s",
            session.name,
            type(exc).__name__,
            why,
            "the frame is reported retryable and the next goes to a new actor (a fresh volume)"
            if losses < MAX_LOSSES_IN_A_ROW
            else f"{losses} actors lost in a row without a finished frame: the frame fails",
        )
        with contextlib.suppress(Exception):
            self._ray.kill(actor, no_restart=True)
        if losses >= MAX_LOSSES_IN_A_ROW:
            with self._lock:
                self._losses.pop(session, None)
            raise RuntimeError(
                f"{losses} Ray actors of this session were lost in a row "
                f"without finishing a frame (last: {why})"
            )
        raise PipelineLost(f"the session's pipeline (a Ray actor) was lost: {why}")

    def release(self, session: Session) -> None:
        """The session closed: kill its actor (its resources go back to Ray)."""
        with self._lock:
            actor = self._actors.pop(session, None)
            self._losses.pop(session, None)
            self._closed.add(session)
        if actor is not None:
            with contextlib.suppress(Exception):
                self._ray.kill(actor, no_restart=True)

    def close(self) -> None:
        with self._lock:
            actors = list(self._actors.values())
            self._actors.clear()
        for actor in actors:
            with contextlib.suppress(Exception):
                self._ray.kill(actor, no_restart=True)
