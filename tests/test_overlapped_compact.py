"""Pipeline.process_overlapped with compact sources on: the back half reads no volume (the
compact sources' occluder is taken in the front half, after the frame's fusion), so the
frames overlap and give `process`'s results (docs/decisions/0042-overlapped-frames.md)."""

import numpy as np
from conftest import SMALL

from arlight.core.frames import FrameResult
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.virtual_scene import demo_scene
from arlight.sources.synthetic import make_sequence


def _assert_same(a: FrameResult, b: FrameResult) -> None:
    """Bit for bit: the SH, the compact sources, what the compact stage said, the composite."""
    np.testing.assert_array_equal(a.sh, b.sh)
    assert len(a.compact_sources) == len(b.compact_sources), a.timestamp
    for x, y in zip(a.compact_sources, b.compact_sources, strict=True):
        np.testing.assert_array_equal(x.direction_world, y.direction_world)
        assert x.intensity == y.intensity
    assert a.diagnostics["compact"] == b.diagnostics["compact"], a.timestamp
    assert (a.composite is None) == (b.composite is None)
    if a.composite is not None:
        np.testing.assert_array_equal(a.composite, b.composite)


def test_with_compact_sources_overlapped_frames_equal_the_serial_ones():
    """Without auxiliary buffers nothing the front half reads comes from the back half (the
    "light" buffer's lag, 0042, is the one difference otherwise): the results are the same
    bit for bit. The occluder is rebuilt every other fused frame, so a back half that read
    the volume would see the next frame's fusion (its sources then differ)."""
    seq = make_sequence(num_frames=5, width=160, height=120)
    config = Config.from_preset(
        "fast", compact_sources=1, aux_buffers=False, aux_update_interval=2, **SMALL
    )
    serial_pipeline = Pipeline(config, seq.camera, demo_scene())
    serial = [serial_pipeline.process(f) for f in seq.frames]
    overlapped = list(Pipeline(config, seq.camera, demo_scene()).process_overlapped(seq.frames))
    assert [r.timestamp for r in overlapped] == [f.timestamp for f in seq.frames]
    for a, b in zip(serial, overlapped, strict=True):
        _assert_same(a, b)
    # what is compared is there: a source kept and drawn on the composite
    assert any(r.compact_sources and r.composite is not None for r in serial)
