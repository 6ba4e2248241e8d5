"""The replies to a frame: its Result, from the pipeline's FrameResult (`result_message`, the
one conversion), or its Error (`encode_error`);
`reply_to` turns a worker step's outcome (server/worker.py) into the encoded `Reply` a worker
hands to the server's I/O thread."""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from arlight.core.frames import Diagnostics, FrameResult
from arlight.pipeline.engine_export import camera_exports
from arlight.pipeline.ibl import IblResult
from arlight.pipeline.probe import ProbeResult
from arlight.protocols import (
    DEFAULT_JPEG_QUALITY,
    Error,
    Result,
    encode,
    plain_diagnostics,
)
from arlight.protocols.fields import MAX_INT as MAX_SEQ
from arlight.protocols.frame_result import compact_sources_to_wire
from arlight.protocols.probe import ProbeCube
from arlight.server.frame_queue import Job
from arlight.server.logtext import printable
from arlight.server.worker import FrameOutcome, Rejected

if TYPE_CHECKING:
    from arlight.server.session import Session

log = logging.getLogger(__name__)


def result_message(
    result: FrameResult,
    *,
    seq: int,
    counters: tuple[int, int, int],
    receive_time_wall: float,
    finish_time_wall: float,
    composite: np.ndarray | None = None,
    composite_codec: str = "jpeg",
    jpeg_quality: int = DEFAULT_JPEG_QUALITY,
    panorama: IblResult | None = None,
    exports: tuple[str, ...] = (),
    extra_timings_ms: Mapping[str, float] | None = None,
    extra_diagnostics: Diagnostics | None = None,
    probe: ProbeResult | None = None,
    probe_mips: bool = False,
) -> Result:
    """The Result of frame `seq`. counters: the session's (frames_received,
    frames_processed, frames_dropped); receive/finish times: wall clock, seconds;
    composite_codec, jpeg_quality: how the composite is encoded (the server: as the frame's
    colour came, so lossless colour gives a lossless composite).

    panorama: the light of the frame's 360-degree panorama, in the panorama's frame (the
    Result's optional panorama_* fields); None: the frame had none (the keys are omitted).

    exports: engine layouts (engine_export.EXPORTERS names) of the frame's light (RGB when the
    pipeline has it, else luminance) in the camera frame with each engine's axes
    (`engine_export.camera_exports`); () = none (the Result's optional key is omitted).

    extra_timings_ms, extra_diagnostics: what the server adds beside the pipeline's own
    (the panorama path's stages and light source), after them; `result` is not changed.

    probe: the frame's reflection probe (the Hello's `config.probe`), sent as the Result's
    `probe` with every mip level when probe_mips, else level 0 only (`probe_to_wire`); None:
    the key is omitted.

    Raises ProtocolError (bad_field, naming `result.diagnostics.KEY`) when the pipeline's
    diagnostics hold a value the protocol does not carry.
    """
    received, processed, dropped = counters
    light = result.sh if result.sh_rgb is None else result.sh_rgb
    source = result.compact_sources[0] if result.compact_sources else None  # main light
    layouts = (
        camera_exports(light, result.pose, exports, result.dominant_direction_world, source)
        if exports
        else None
    )
    return Result(
        seq=seq,
        timestamp=float(result.timestamp),
        sh=[float(x) for x in result.sh],
        sh_camera=[float(x) for x in result.sh_camera],
        sh_rgb=None if result.sh_rgb is None else np.asarray(result.sh_rgb, float).tolist(),
        dominant_direction_camera=[float(x) for x in result.dominant_direction_camera],
        dominant_direction_world=[float(x) for x in result.dominant_direction_world],
        intensity=float(result.intensity),
        compact_sources=compact_sources_to_wire(result.compact_sources),
        confidence=result.confidence,
        pose=np.asarray(result.pose, dtype=float).tolist(),
        timings_ms={
            k: float(v) for k, v in {**result.timings_ms, **(extra_timings_ms or {})}.items()
        },
        diagnostics=plain_diagnostics({**result.diagnostics, **(extra_diagnostics or {})}),
        frames_received=received,
        frames_processed=processed,
        frames_dropped=dropped,
        server_receive_time=receive_time_wall,
        server_finish_time=finish_time_wall,
        composite=composite,
        composite_codec=composite_codec,
        jpeg_quality=jpeg_quality,
        panorama_sh=None if panorama is None else [float(x) for x in panorama.sh],
        panorama_sh_rgb=None if panorama is None else np.asarray(panorama.sh_rgb, float).tolist(),
        panorama_dominant_direction=None
        if panorama is None
        else [float(x) for x in panorama.dominant_direction],
        exports=layouts,
        probe=None if probe is None else probe_to_wire(probe, probe_mips),
    )


def probe_to_wire(probe: ProbeResult, mips: bool) -> ProbeCube:
    """A pipeline ProbeResult as Result.probe carries it: its point (world, metres), level 0
    (the radiance) or every GGX-prefiltered level, and each level's perceptual roughness."""
    cube = probe.mips if mips else probe.mirror
    return ProbeCube(
        point_world=[float(x) for x in probe.point_world],
        levels=list(cube.levels),
        roughness=[float(r) for r in cube.roughness],
    )


def encode_error(error: Error) -> list:
    """The parts of an Error; never raises. An Error that cannot be encoded (a seq outside
    0..2^63-1, an over-long text) is replaced by an `internal` one that can."""
    try:
        return encode(error)
    except Exception as exc:  # noqa: BLE001 - the fallback below always encodes
        seq = error.seq if isinstance(error.seq, int) and 0 <= error.seq <= MAX_SEQ else None
        log.error("an Error could not be encoded (%s); sent as internal", exc)
        return encode(
            Error(
                code="internal",
                seq=seq,
                message=f"the server failed to report an error ({type(exc).__name__})",
            )
        )


@dataclass
class Reply:
    """What a worker hands back to the server's I/O thread: a frame's reply, encoded (a
    Result, or the Error in `error`)."""

    session: Session
    job: Job
    parts: list
    finish_time_mono: float  # time.monotonic(), seconds
    error: Error | None = None
    worker_s: float = 0.0  # seconds the frame held its worker (the scheduler's share)


def reply_to(session: Session, job: Job, outcome: FrameOutcome) -> Reply:
    """The encoded reply of a frame's outcome: its Result (the session's counters counted
    first: the Result reports itself processed), or its Error."""
    if isinstance(outcome, Rejected):
        return error_reply(session, job, outcome.error)
    finish_wall = time.time()
    counters = session.queue.count_processed()
    used = outcome.panorama
    try:
        message = result_message(
            outcome.result,
            seq=job.seq,
            counters=(counters.received, counters.processed, counters.dropped),
            receive_time_wall=job.receive_time_wall,
            finish_time_wall=finish_wall,
            composite=outcome.composite,
            composite_codec=outcome.composite_codec,
            jpeg_quality=outcome.jpeg_quality,
            panorama=None if used is None else used.light,
            exports=session.config.exports,
            extra_timings_ms=None if used is None else used.timings_ms,
            extra_diagnostics=None if used is None else used.diagnostics,
            probe=outcome.probe,
            probe_mips=session.config.probe is not None and session.config.probe.mips,
        )
        return Reply(session, job, encode(message), time.monotonic())
    except Exception as exc:  # noqa: BLE001 - e.g. a non-finite estimate
        return error_reply(
            session,
            job,
            Error(
                code="internal",
                seq=job.seq,
                message=f"the server could not send the Result of this frame ({exc})",
            ),
        )


def error_reply(session: Session, job: Job, error: Error) -> Reply:
    """The encoded Error reply of frame `job` (logged, counted as failed)."""
    if error.code == "internal":
        log.error("session %s: frame %d failed: %s", session.name, job.seq, error.message)
    else:
        log.info("session %s: frame %d rejected: %s", session.name, job.seq, error.message)
    session.queue.count_failed()
    return Reply(session, job, encode_error(error), time.monotonic(), error)


ERROR_LOG_LINES_PER_S = 20  # log lines about Errors, to and from peers (a flood is summarised)


class ErrorLog:
    """The log lines about Errors sent to peers and reported by them: at most `lines_per_s` a
    second together; then one line says how many the second left out (a hostile flood does
    not flood the log). A peer's text is escaped onto one line (server/logtext.py). Times:
    time.monotonic(), seconds."""

    def __init__(self, lines_per_s: int = ERROR_LOG_LINES_PER_S):
        self.lines_per_s = lines_per_s
        self._second = 0  # int(time) of the lines counted below
        self._count = 0
        self._suppressed = 0

    def sent(self, identity: bytes, error: Error, now: float) -> None:
        """Log an Error sent to peer `identity`, unless this second has had its lines."""
        if self._allow(now):
            log.info(
                "error to %s: %s%s: %s",
                identity.hex(),
                error.code,
                f" ({printable(error.field, 128)})" if error.field else "",
                printable(error.message, 512),
            )

    def reported(self, identity: bytes, error: Error, now: float) -> None:
        """Log an Error a client reported (its code, field and text are the peer's own),
        unless this second has had its lines."""
        if self._allow(now):
            log.info(
                "client %s reported an error: %s%s: %s",
                identity.hex(),
                printable(error.code, 64),
                f" ({printable(error.field, 128)})" if error.field else "",
                printable(error.message),
            )

    def _allow(self, now: float) -> bool:
        """Whether this second may have one more line (else it is counted as left out)."""
        self.flush(now)
        self._count += 1
        if self._count > self.lines_per_s:
            self._suppressed += 1
            return False
        return True

    def flush(self, now: float) -> None:
        """A new second: log how many lines the last one left out, count afresh."""
        second = int(now)
        if second != self._second:
            if self._suppressed:
                log.info("%d more error line(s) not logged (to or from peers)", self._suppressed)
            self._second, self._count, self._suppressed = second, 0, 0
