"""The worker step (server/worker.py): a received frame in, a typed outcome out, no socket.

`run_frame(job, compute)` never raises; a processed frame's FrameResult is the one the
pipeline (here a stand-in step) returned, not edited; what a panorama adds travels beside it
and is merged only into the Result (server/results.py).
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from streaming_support import identity_step

from arlight.core.frames import FrameResult, RenderLight
from arlight.protocols import (
    CameraCalibration,
    ErrorField,
    Frame,
    Heartbeat,
    PanoramaConfig,
    SessionConfig,
    encode,
)
from arlight.server.budget import SessionBudget
from arlight.server.frame_queue import Job
from arlight.server.results import result_message
from arlight.server.session import Session
from arlight.server.worker import Deadline, FrameAbandoned, Processed, Rejected, run_frame

W, H = 64, 48


def session(step=None, budget=None, cancel=None, **config) -> Session:
    base = dict(
        session="w",
        role="capture",
        calibration=CameraCalibration(W, H, 50.0, 50.0, W / 2, H / 2),
        mode="lossless",
    )
    base.update(config)
    return Session(
        SessionConfig(**base),
        credits=4,
        max_pixels=2**22,
        max_message_bytes=2**26,
        process=step or identity_step(),
        budget=budget,
        cancel=cancel,
    )


def frame_job(
    seq: int = 0, width: int = W, panorama: np.ndarray | None = None, rgbd: bool = True
) -> Job:
    color = np.full((H, width, 3), 40 + seq, np.uint8) if rgbd else None
    depth = np.full((H, width), 1500, np.uint16) if rgbd else None
    parts = encode(Frame(seq, 1.0 + seq, color, depth, None, panorama, "png", "zstd"))
    return Job(seq, [bytes(memoryview(p)) for p in parts], time.time(), time.monotonic())


def sky(width: int = 128) -> np.ndarray:
    """A 2:1 LDR panorama, bright at the top."""
    rows = np.linspace(255, 20, width // 2).astype(np.uint8)
    return np.repeat(rows[:, None, None], width, axis=1).repeat(3, axis=2)


class TestProcessed:
    def test_the_result_is_the_steps_untouched(self):
        returned: list[FrameResult] = []
        step = identity_step()

        def record(frame, s, render_light, deadline):
            returned.append(step(frame, s, render_light, deadline))
            return returned[-1]

        out = run_frame(frame_job(3), session(record).compute)
        assert isinstance(out, Processed)
        assert out.result is returned[0]
        assert out.result.timings_ms == {"Identity": 0.0} and out.result.diagnostics == {}
        assert out.result.sh[0] == pytest.approx(43)  # the frame's own colour
        assert out.composite is None and out.panorama is None
        assert out.composite_codec == "png"

    def test_a_composite_is_the_input_frame_without_a_scene(self):
        out = run_frame(frame_job(), session(want_composite=True).compute)
        assert isinstance(out, Processed)
        assert out.composite is not None and np.all(out.composite == 40)

    def test_a_panorama_lights_the_step_and_its_extras_stay_beside_the_result(self):
        seen = []
        step = identity_step()

        def record(frame, s, render_light, deadline):
            seen.append(render_light)
            return step(frame, s, render_light, deadline)

        s = session(record, panorama=PanoramaConfig(light_source="panorama"))
        out = run_frame(frame_job(panorama=sky()), s.compute)
        assert isinstance(out, Processed), out
        assert isinstance(seen[0], RenderLight) and seen[0].environment is None
        assert out.result.diagnostics == {}  # not edited
        assert out.result.timings_ms == {"Identity": 0.0}
        assert out.panorama is not None and out.panorama.light_source == "panorama"
        assert set(out.panorama.timings_ms) >= {"PanoramaSH", "PanoramaInverseTone"}
        message = result_message(
            out.result,
            seq=0,
            counters=(1, 1, 0),
            receive_time_wall=1.0,
            finish_time_wall=2.0,
            panorama=out.panorama.light,
            extra_timings_ms=out.panorama.timings_ms,
            extra_diagnostics=out.panorama.diagnostics,
        )
        assert list(message.timings_ms)[0] == "Identity"  # the pipeline's stages first
        assert message.diagnostics == {
            "light_source": "panorama",
            "panorama_operator": s.setup.panorama_light.params.operator,
        }

    def test_a_panorama_only_frame_needs_no_pipeline(self):
        calls = []
        s = session(
            lambda frame, *_: calls.append(frame), panorama=PanoramaConfig(), calibration=None
        )
        out = run_frame(frame_job(panorama=sky(), rgbd=False), s.compute)
        assert isinstance(out, Processed) and not calls
        assert out.result.confidence.samples > 0
        assert out.panorama is not None and out.panorama.light_source == "panorama"


class TestRejected:
    def test_another_message_than_a_frame(self):
        parts = [bytes(memoryview(p)) for p in encode(Heartbeat(1.0))]
        out = run_frame(Job(0, parts, 0.0, 0.0), session().compute)
        assert isinstance(out, Rejected) and out.error.code == "bad_state"

    def test_garbage_parts(self):
        out = run_frame(Job(5, [b"\xc1"], 0.0, 0.0), session().compute)
        assert isinstance(out, Rejected) and out.error.code == "malformed"
        assert out.error.seq == 5

    def test_an_image_at_another_size_than_the_calibration(self):
        out = run_frame(frame_job(width=W * 2), session().compute)
        assert isinstance(out, Rejected)
        assert out.error.code == "bad_field" and out.error.field == "frame.color"

    def test_a_failing_step_becomes_an_internal_error(self):
        def boom(frame, s, render_light, deadline):
            raise RuntimeError("kaput")

        out = run_frame(frame_job(7), session(boom).compute)
        assert isinstance(out, Rejected) and out.error.code == "internal"
        assert out.error.seq == 7 and "kaput" in out.error.message


class TestDeadline:
    def test_a_checkpoint_past_the_deadline_abandons_the_frame(self):
        def slow(frame, s, render_light, deadline):
            time.sleep(0.1)
            deadline("LightEst")
            return identity_step()(frame, s, render_light, deadline)

        # `fast`: its model cost at 64 x 48 is under the 0.05 s deadline (`full`'s is not)
        s = session(slow, budget=SessionBudget(frame_deadline_s=0.05), preset="fast")
        out = run_frame(frame_job(), s.compute)
        assert isinstance(out, Rejected) and out.error.code == "deadline"
        assert "LightEst" in out.error.message

    def test_a_stopping_server_abandons_it_retryable(self):
        cancel = threading.Event()
        cancel.set()

        def step(frame, s, render_light, deadline):
            deadline("DynGeo")
            return identity_step()(frame, s, render_light, deadline)

        out = run_frame(frame_job(), session(step, cancel=cancel).compute)
        assert isinstance(out, Rejected) and out.error.retryable
        assert out.error.field == ErrorField.SHUTDOWN

    def test_the_deadline_object(self):
        deadline = Deadline(limit_s=0.0)
        time.sleep(0.01)
        with pytest.raises(FrameAbandoned) as info:
            deadline("Rendering")
        assert info.value.reason == "deadline" and info.value.stage == "Rendering"
        Deadline()("Rendering")  # no limit, no cancel: never raises
