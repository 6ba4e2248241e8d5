"""The virtual scene a Hello carries (SceneSpec): round trips bit for bit, bounds, and the
hostile scenes refused with the right code."""

from __future__ import annotations

import math
import struct

import numpy as np
from conftest import as_bytes, calibration, expect, tamper

from arlight.protocols import (
    DEFAULT_MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    SCENE_MAX_OBJECTS,
    SCENE_MAX_TRIANGLES,
    Hello,
    SceneAnchorSpec,
    SceneObjectSpec,
    SceneSpec,
    SessionConfig,
    decode,
    encode,
    peek_header,
)

# --------------------------------------------------------------------------- virtual scene


def scene_object(name: str = "obj", nv: int = 5, nt: int = 4, seed: int = 0, **kw):
    rng = np.random.default_rng(seed)
    args = dict(
        vertices=rng.standard_normal((nv, 3)).astype(np.float32),
        triangles=rng.integers(0, nv, (nt, 3)).astype(np.uint32),
        normals=rng.standard_normal((nv, 3)).astype(np.float32),
        world_from_object=np.diag([2.0, 2.0, 2.0, 1.0]),
    )
    args.update(kw)
    return SceneObjectSpec(name, **args)


def scene_hello(scene: SceneSpec | None, **config) -> Hello:
    return Hello(
        PROTOCOL_VERSION, SessionConfig("s", calibration=calibration(), scene=scene, **config)
    )


def bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint32)


class TestScene:
    """Hello.config.scene: the virtual scene inline (SPEC.md section 4, "scene")."""

    def test_round_trip_is_bit_exact(self):
        odd = scene_object(
            "odd",
            6,
            3,
            seed=1,
            world_from_object=None,
            anchor=SceneAnchorSpec((320.5, 400.25), -15.0),
        )
        odd.vertices[0] = (-0.0, np.float32(1e-42), np.finfo(np.float32).max)  # -0, subnormal
        msg = scene_hello(
            SceneSpec(
                (
                    scene_object("a"),
                    odd,
                    scene_object(
                        "centre",
                        3,
                        1,
                        seed=2,
                        world_from_object=None,
                        anchor=SceneAnchorSpec(None, 0.0),
                        albedo=(1.0, 0.0, 0.5),
                        roughness=0.25,
                        metalness=1.0,
                        mirror=True,
                    ),
                )
            )
        )
        parts = encode(msg)
        back = decode(as_bytes(parts))
        assert back == msg
        for got, sent in zip(back.config.scene.objects, msg.config.scene.objects, strict=True):
            assert got.vertices.dtype == got.normals.dtype == np.float32
            assert got.triangles.dtype == np.uint32
            for key in ("vertices", "normals", "triangles"):
                np.testing.assert_array_equal(bits(getattr(got, key)), bits(getattr(sent, key)))
        header = peek_header(parts)
        assert header["buffers"] == [(5 + 6 + 3) * 12, (4 + 3 + 1) * 12, (5 + 6 + 3) * 12]
        assert list(header["config"]["scene"]) == ["vertices", "triangles", "normals", "objects"]
        assert list(header["config"]["scene"]["objects"][0]) == [
            "name",
            "vertex_count",
            "triangle_count",
            "world_from_object",
            "anchor",
            "albedo",
            "roughness",
            "metalness",
            "mirror",
        ]

    def test_decoded_arrays_are_owned_copies(self):
        parts = as_bytes(encode(scene_hello(SceneSpec((scene_object(),)))))
        obj = decode(parts).config.scene.objects[0]
        assert obj.vertices.flags.owndata and obj.vertices.flags.writeable

    def test_no_scene_is_the_hello_of_before(self):
        """Absent `scene` key = no scene (older v2 clients, the Go client); nil accepted too;
        the encoder omits the key, so a Hello without a scene is byte for byte unchanged
        (the golden `hello` vector pins it)."""
        parts = encode(scene_hello(None))
        assert "scene" not in peek_header(parts)["config"] and len(parts) == 1
        assert decode(parts).config.scene is None
        nil = tamper(parts, lambda h: h["config"].update(scene=None))
        assert decode(nil).config.scene is None
        empty = decode(as_bytes(encode(scene_hello(SceneSpec()))))
        assert empty.config.scene == SceneSpec()

    def test_limits_are_the_pipelines(self):
        from arlight.pipeline import virtual_scene

        assert SCENE_MAX_OBJECTS == virtual_scene.MAX_OBJECTS
        assert SCENE_MAX_TRIANGLES == virtual_scene.MAX_TRIANGLES

    def test_two_million_triangles_fit_the_default_message_limit(self):
        """2M triangles with 1M vertices (a closed mesh: N ~ M / 2): 48 MB of parts, under the
        default 64 MiB; the same scene against a 32 MiB limit is too_large."""
        n, m = 1_000_000, SCENE_MAX_TRIANGLES
        obj = SceneObjectSpec(
            "big",
            np.zeros((n, 3), np.float32),
            np.zeros((m, 3), np.uint32),
            np.zeros((n, 3), np.float32),
            np.eye(4),
        )
        parts = encode(scene_hello(SceneSpec((obj,))))
        assert sum(len(memoryview(p)) for p in parts) < DEFAULT_MAX_MESSAGE_BYTES
        assert decode(parts).config.scene.objects[0].triangles.shape == (m, 3)
        expect("too_large", decode, parts, max_message_bytes=32 * 2**20)
        expect("too_large", encode, scene_hello(SceneSpec((obj,))), max_message_bytes=32 * 2**20)

    def test_encode_refuses_what_decode_would(self):
        def refused(field, **kw):
            expect(
                "bad_field",
                encode,
                scene_hello(SceneSpec((scene_object(**kw),))),
                field=f"hello.config.scene.objects[0].{field}",
            )

        refused("triangles", triangles=-np.ones((2, 3), np.int32))
        refused("triangles", triangles=np.zeros((2, 3), np.float32))
        refused("triangles", triangles=np.full((2, 3), 5, np.uint32))  # nv = 5
        refused("vertices", vertices=np.zeros((5, 2), np.float32))
        refused("normals", normals=np.full((5, 3), np.nan, np.float32))
        refused("world_from_object[0]", world_from_object=np.full((4, 4), np.inf))
        refused("world_from_object", world_from_object=None)
        refused("anchor", anchor=SceneAnchorSpec())
        refused("albedo[1]", albedo=(0.5, 1.5, 0.5))
        expect(
            "bad_field",
            encode,
            scene_hello(SceneSpec((scene_object(),)), virtual_scene="demo"),
            field="hello.config.scene",
        )

    def test_hostile_scenes_are_refused_naming_the_field(self):
        parts = as_bytes(
            encode(scene_hello(SceneSpec((scene_object("a"), scene_object("b", 3, 1, seed=1)))))
        )
        s = "hello.config.scene"
        o0, o1 = f"{s}.objects[0]", f"{s}.objects[1]"

        def obj(i, **kw):
            return lambda h: h["config"]["scene"]["objects"][i].update(**kw)

        def part(i, data):
            return [*parts[:i], data, *parts[i + 1 :]]

        def fix_buffers(p):
            return tamper(p, lambda h: h.update(buffers=[len(x) for x in p[1:]]))

        cases = [
            # byte lengths: not what the counts say, not a multiple of 12
            (fix_buffers(part(1, parts[1][:-12])), f"{s}.vertices"),
            (fix_buffers(part(2, parts[2] + b"\0" * 6)), f"{s}.triangles"),
            (fix_buffers(part(3, parts[3] + b"\0" * 12)), f"{s}.normals"),
            (tamper(parts, obj(1, vertex_count=4)), f"{s}.vertices"),
            (tamper(parts, obj(0, triangle_count=5)), f"{s}.triangles"),
            # counts and limits
            (tamper(parts, obj(1, vertex_count=2)), f"{o1}.vertex_count"),
            (tamper(parts, obj(0, triangle_count=0)), f"{o0}.triangle_count"),
            (tamper(parts, obj(1, triangle_count=SCENE_MAX_TRIANGLES)), f"{o1}.triangle_count"),
            (
                tamper(
                    parts,
                    lambda h: h["config"]["scene"].update(
                        objects=h["config"]["scene"]["objects"] * 33
                    ),
                ),
                f"{s}.objects",
            ),
            # the pose, the anchor, the material, the name
            (
                tamper(parts, obj(0, world_from_object=[math.nan] + [0.0] * 15)),
                f"{o0}.world_from_object[0]",
            ),
            (tamper(parts, obj(0, world_from_object=[1.0] * 16)), f"{o0}.world_from_object"),
            (
                tamper(parts, obj(0, world_from_object=[[1.0] * 4] * 4)),  # 16 flat numbers
                f"{o0}.world_from_object",
            ),
            (tamper(parts, obj(0, anchor={"pixel": None, "yaw_deg": 0.0})), f"{o0}.anchor"),
            (tamper(parts, obj(0, world_from_object=None)), f"{o0}.world_from_object"),
            (
                tamper(parts, obj(0, world_from_object=None, anchor={"pixel": [1.0]})),
                f"{o0}.anchor.pixel",
            ),
            (
                tamper(
                    parts,
                    obj(
                        0, world_from_object=None, anchor={"pixel": None, "yaw_deg": 0.0, "roll": 1}
                    ),
                ),
                f"{o0}.anchor.roll",
            ),
            (tamper(parts, obj(0, albedo=[0.5, 0.5])), f"{o0}.albedo"),
            (tamper(parts, obj(0, roughness=-0.5)), f"{o0}.roughness"),
            (tamper(parts, obj(0, mirror=1)), f"{o0}.mirror"),
            (tamper(parts, obj(1, name="a")), f"{o1}.name"),
            (tamper(parts, obj(1, name="")), f"{o1}.name"),
            (tamper(parts, obj(1, colour=[1, 2, 3])), f"{o1}.colour"),
            # the parts: indices in range and each used once
            (tamper(parts, lambda h: h["config"]["scene"].update(normals=0)), f"{s}.normals"),
            (tamper(parts, lambda h: h["config"]["scene"].update(vertices=3)), f"{s}.vertices"),
            (tamper(parts, lambda h: h["config"]["scene"].pop("normals")), f"{s}.normals"),
            (tamper(parts, lambda h: h["config"].update(virtual_scene="demo")), s),
            (tamper(parts, lambda h: h["config"].update(scene=[])), s),
        ]
        # values in the parts: non-finite vertices or normals, an index out of range
        nan = bytearray(parts[1])
        nan[12 * 5 + 4 : 12 * 5 + 8] = struct.pack("<f", math.nan)  # object 1's first vertex
        cases.append((part(1, bytes(nan)), f"{o1}.vertices"))
        inf = bytearray(parts[3])
        inf[0:4] = struct.pack("<f", math.inf)
        cases.append((part(3, bytes(inf)), f"{o0}.normals"))
        out = bytearray(parts[2])
        out[12 * 4 : 12 * 4 + 4] = struct.pack("<I", 3)  # object 1 has 3 vertices
        cases.append((part(2, bytes(out)), f"{o1}.triangles"))
        for hostile, field in cases:
            expect("bad_field", decode, hostile, field=field)
        expect("malformed", decode, parts[:-1])
        expect("malformed", decode, fix_buffers([*parts, b"\0" * 12]), field="hello.buffers")
