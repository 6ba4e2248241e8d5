"""The streaming server over real loopback sockets with a virtual scene: the scene a Hello
sends reaches the session's pipeline, bad scenes are refused, composites are right."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from streaming_support import SMALL, RawPeer, flat_source, identity_step, run_with_timeout
from streaming_support import calibrated as _calibrated
from streaming_support import edit_header as _edit
from streaming_support import frame_parts as _frame_parts
from streaming_support import hello_parts as _hello_parts

from arlight.client.capture import StreamError, StreamOptions, stream
from arlight.protocols import Error, Result, SceneObjectSpec, SceneSpec, Welcome
from arlight.sources.source import sequence_source
from arlight.sources.synthetic import make_sequence

# --------------------------------------------------------------------------- virtual scene


def _scene_object(name: str = "tri", **kw) -> SceneObjectSpec:
    args = dict(
        vertices=np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], np.float32),
        triangles=np.array([[0, 1, 2]], np.uint32),
        normals=np.array([[0, 0, -1]] * 3, np.float32),
        world_from_object=np.eye(4),
    )
    args.update(kw)
    return SceneObjectSpec(name, **args)


def _scene_hello(scene: SceneSpec | None = None, session: str = "scene", **config) -> list:
    return [
        bytes(memoryview(p))
        for p in _hello_parts(
            **_calibrated(
                session=session,
                scene=SceneSpec((_scene_object(),)) if scene is None else scene,
                **config,
            )
        )
    ]


def _replace_part(parts: list[bytes], i: int, data: bytes) -> list[bytes]:
    parts = [*parts[:i], data, *parts[i + 1 :]]
    return _edit(parts, lambda h: h.update(buffers=[len(p) for p in parts[1:]]))


def _object_edit(**fields):
    return lambda h: h["config"]["scene"]["objects"][0].update(**fields)


def _assert_same_object(got, sent, vertices=None) -> None:
    """A pipeline VirtualObject made by the server equals the client's, bit for bit."""
    assert got.name == sent.name and got.material == sent.material
    assert got.anchor == sent.anchor
    want = sent.vertices if vertices is None else vertices
    np.testing.assert_array_equal(got.vertices.view(np.uint32), want.view(np.uint32))
    np.testing.assert_array_equal(got.normals.view(np.uint32), sent.normals.view(np.uint32))
    np.testing.assert_array_equal(got.triangles, sent.triangles)


# (name, Hello parts, expected field prefix)
BAD_SCENES = [
    (
        "vertices part one vertex short",
        _replace_part(_scene_hello(), 1, _scene_hello()[1][:-12]),
        "hello.config.scene.vertices",
    ),
    (
        "triangles part not whole triangles",
        _replace_part(_scene_hello(), 2, _scene_hello()[2] + b"\0\0"),
        "hello.config.scene.triangles",
    ),
    (
        "too many triangles",
        _edit(_scene_hello(), _object_edit(triangle_count=2_000_001)),
        "hello.config.scene.objects[0].triangle_count",
    ),
    (
        "triangle index out of range",
        _replace_part(_scene_hello(), 2, np.array([[0, 1, 3]], "<u4").tobytes()),
        "hello.config.scene.objects[0].triangles",
    ),
    (
        "NaN pose",
        _edit(_scene_hello(), _object_edit(world_from_object=[math.nan] * 16)),
        "hello.config.scene.objects[0].world_from_object",
    ),
    (
        "pose and anchor",
        _edit(_scene_hello(), _object_edit(anchor={"pixel": [32.0, 24.0], "yaw_deg": 0.0})),
        "hello.config.scene.objects[0].anchor",
    ),
    (
        "sheared pose (the pipeline's own check)",
        _scene_hello(
            SceneSpec(
                (
                    _scene_object(
                        "sheared",
                        world_from_object=np.array(
                            [[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]
                        ),
                    ),
                )
            )
        ),
        "hello.config.scene.objects[0]",
    ),
    (
        "scene and virtual_scene",
        _edit(_scene_hello(), lambda h: h["config"].update(virtual_scene="demo")),
        "hello.config.scene",
    ),
    (
        "unknown scene name",
        [
            bytes(memoryview(p))
            for p in _hello_parts(**_calibrated(session="scene", virtual_scene="bunny.ply"))
        ],
        "hello.config.virtual_scene",
    ),
]


class TestVirtualScene:
    def test_the_sessions_pipeline_gets_the_scene_sent(self, make_server):
        """A VirtualScene in StreamOptions reaches the session's Pipeline bit for bit (an
        anchored object's scale applied to its vertices), and the real pipeline's Results
        arrive."""
        from arlight.pipeline.virtual_scene import (
            Anchor,
            Material,
            VirtualScene,
            box_mesh,
            object_from_open3d,
            sphere_mesh,
        )

        placed = object_from_open3d(
            "ball",
            sphere_mesh(0.05, 8),
            np.array([[0, 0, 1, 0.1], [0, 1, 0, 0.2], [-1, 0, 0, 1.5], [0, 0, 0, 1.0]]),
            Material((0.2, 0.4, 0.6), 0.5, 0.25, True),
        )
        anchored = object_from_open3d(
            "crate",
            box_mesh((0.1, 0.1, 0.1)),
            np.diag([2.0, 2.0, 2.0, 1.0]),
            Material(),
            Anchor((80.0, 90.0), 30.0),
        )
        scene = VirtualScene((placed, anchored))
        server = make_server()
        seq = make_sequence(num_frames=2, width=160, height=120, seed=1)
        source = sequence_source("scene", seq.camera, seq.frames)
        seen = []

        def on_result(result, _):
            seen.append((result, server.sessions["scene"].compute.pipeline.requested_scene))

        options = StreamOptions(
            server=server.connect_address,
            session="scene",
            mode="lossless",
            rate="max",
            preset="fast",
            overrides=SMALL,
            scene=scene,
        )
        summary = run_with_timeout(lambda: stream(source, options, on_result=on_result))
        assert summary.errors == [] and [r.seq for r, _ in seen] == [0, 1]
        got = seen[0][1]
        assert isinstance(got, VirtualScene) and [o.name for o in got.objects] == ["ball", "crate"]
        _assert_same_object(got.objects[0], placed)
        np.testing.assert_array_equal(got.objects[0].world_from_object, placed.world_from_object)
        _assert_same_object(
            got.objects[1], anchored, vertices=(anchored.vertices * 2.0).astype(np.float32)
        )
        np.testing.assert_array_equal(got.objects[1].world_from_object, np.eye(4))

    def test_demo_scene_by_name_and_none_without(self, make_server):
        from arlight.pipeline.virtual_scene import demo_scene

        server = make_server(process=identity_step())
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("demo-scene", virtual_scene="demo"), Welcome)
        scene = server.sessions["demo-scene"].scene
        assert [o.name for o in scene.objects] == [o.name for o in demo_scene().objects]
        plain = RawPeer(server.connect_address)
        assert isinstance(plain.hello("no-scene"), Welcome)
        assert server.sessions["no-scene"].scene is None
        peer.close()
        plain.close()

    def test_a_reconnect_with_the_same_scene_resumes_the_session(self, make_server):
        server = make_server(process=identity_step())
        first, again, other = (RawPeer(server.connect_address) for _ in range(3))
        first.send(_scene_hello())
        assert isinstance(first.receive(), Welcome)
        session = server.sessions["scene"]
        again.send(_scene_hello())  # equal arrays, other buffers: the same configuration
        assert isinstance(again.receive(), Welcome)
        assert server.sessions["scene"] is session
        moved = SceneSpec(
            (_scene_object(world_from_object=np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3)),)
        )
        other.send(_scene_hello(moved))
        error = other.receive()
        assert (error.code, error.field) == ("bad_state", "hello.config.session")
        for peer in (first, again, other):
            peer.close()

    def test_bad_scenes_are_refused_and_the_server_keeps_serving(self, make_server):
        server = make_server(process=identity_step())
        bystander = RawPeer(server.connect_address)
        assert isinstance(bystander.hello("bystander"), Welcome)
        for seq, (name, parts, field) in enumerate(BAD_SCENES):
            peer = RawPeer(server.connect_address)
            peer.send(parts)
            error = peer.receive()
            assert isinstance(error, Error), (name, error)
            assert error.code == "bad_field" and not error.retryable, (name, error)
            assert (error.field or "").startswith(field), (name, error)
            assert "scene" not in server.sessions, name  # no session was created
            if name.startswith("sheared"):
                assert "'sheared'" in error.message  # names the object
            if name == "unknown scene name":
                assert "arlight stream --scene FILE" in error.message
            peer.close()
            bystander.send(_frame_parts(seq=seq, value=seq))
            result = bystander.receive()
            assert isinstance(result, Result) and result.seq == seq
        bystander.close()
        # the refusal reaches a capture client as a clear, final StreamError
        options = StreamOptions(
            server=server.connect_address, session="named", virtual_scene="bunny.ply"
        )
        with pytest.raises(StreamError, match="unknown virtual scene name 'bunny.ply'"):
            run_with_timeout(lambda: stream(flat_source(1), options))

    @pytest.mark.parametrize("codec", ["raw", "png"])
    def test_no_scene_composite_is_the_input_bit_for_bit(self, make_server, codec):
        server = make_server(process=identity_step())
        source = flat_source(3, 64, 48, noise=True)
        display = RawPeer(server.connect_address)
        assert isinstance(display.hello("composite", role="display"), Welcome)
        results: list[Result] = []
        options = StreamOptions(
            server=server.connect_address,
            session="composite",
            mode="lossless",
            rate="max",
            color_codec=codec,
            want_composite=True,
        )
        summary = run_with_timeout(
            lambda: stream(source, options, on_result=lambda r, _: results.append(r))
        )
        assert summary.errors == [] and len(results) == 3
        shown = [display.receive() for _ in range(3)]
        for got, also, frame in zip(results, shown, source.frames(), strict=True):
            assert got.composite_codec == codec  # as the colour came: lossless stays lossless
            assert got.composite.dtype == np.uint8
            np.testing.assert_array_equal(got.composite, frame.color)
            np.testing.assert_array_equal(also.composite, frame.color)
        display.close()

    def test_with_a_scene_the_composite_is_the_pipelines(self, make_server):
        """The pipeline's composite when it makes one; the input frame while it makes none."""
        identity = identity_step()

        def rendering(frame, session, render_light, deadline):
            out = identity(frame, session, render_light, deadline)
            return (
                dataclasses.replace(out, composite=255 - frame.color)
                if frame.timestamp > 1000.02
                else out
            )  # none for the first frame

        server = make_server(process=rendering)
        results: list[Result] = []
        source = flat_source(2, 64, 48, noise=True)
        options = StreamOptions(
            server=server.connect_address,
            session="rendered",
            mode="lossless",
            rate="max",
            color_codec="png",
            want_composite=True,
            scene=_virtual_scene(),
        )
        summary = run_with_timeout(
            lambda: stream(source, options, on_result=lambda r, _: results.append(r))
        )
        assert summary.errors == []
        first, second = (frame.color for frame in source.frames())
        np.testing.assert_array_equal(results[0].composite, first)
        np.testing.assert_array_equal(results[1].composite, 255 - second)
        # the same step without a scene: the input frame, whatever the pipeline made
        results.clear()
        options = dataclasses.replace(options, session="unrendered", scene=None)
        run_with_timeout(lambda: stream(source, options, on_result=lambda r, _: results.append(r)))
        np.testing.assert_array_equal(results[1].composite, second)


def test_a_hello_that_cannot_be_sent_is_a_stream_error():
    """Refused by encode() before any socket opens: scene and virtual_scene together."""
    options = StreamOptions(
        server="tcp://127.0.0.1:9",
        session="unsendable",
        virtual_scene="demo",
        scene=_virtual_scene(),
    )
    with pytest.raises(StreamError, match=r"cannot be sent: bad_field \(hello.config.scene\)"):
        run_with_timeout(lambda: stream(flat_source(1), options), timeout_s=10)


def _virtual_scene():
    from arlight.pipeline.virtual_scene import VirtualObject, VirtualScene

    spec = _scene_object()
    return VirtualScene(
        (
            VirtualObject(
                spec.name,
                spec.vertices,
                spec.triangles.astype(np.int32),
                spec.normals,
                spec.world_from_object,
            ),
        )
    )
