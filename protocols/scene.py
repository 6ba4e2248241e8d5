"""The virtual scene a capture Hello may carry (SessionConfig.scene; SPEC.md section 4,
"hello: the virtual scene"): plain arrays and materials, no pipeline type."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import ProtocolError
from .fields import (
    FieldReader,
    float_list,
    pose_to_wire,
    read_floats,
    to_plain,
    type_name,
)
from .images import ImageParts

# Hello.config.scene (SPEC.md section 4, "hello: the virtual scene"): objects sent inline.
# The limits are the pipeline's (arlight.pipeline.virtual_scene MAX_OBJECTS, MAX_TRIANGLES;
# protocols does not import the pipeline, tests/test_protocols_scene.py holds them equal). The
# bytes are bounded by the message limit (max_message_bytes), as every part is.
SCENE_MAX_OBJECTS = 64
SCENE_MAX_TRIANGLES = 2_000_000  # all objects together
SCENE_MAX_NAME = 64  # characters of an object's name
_SCENE_BUFFERS = ("vertices", "triangles", "normals")  # one part each, objects in order
_XYZ_BYTES = 12  # one vertex or normal (3 float32), or one triangle (3 uint32)
_F32 = np.dtype("<f4")
_U32 = np.dtype("<u4")


@dataclass(frozen=True)
class SceneAnchorSpec:
    """Stand the object on the support plane under `pixel` (u, v), pixels, or under the
    view's centre when None; yaw_deg: turn about the plane's up direction, degrees."""

    pixel: tuple[float, float] | None = None
    yaw_deg: float = 0.0


@dataclass(frozen=True, eq=False)
class SceneObjectSpec:
    """One virtual object as the wire carries it: plain arrays, no pipeline type (the server
    makes a `pipeline.virtual_scene.VirtualObject` of it).

    vertices: (N, 3) float32, object frame, metres; triangles: (M, 3) uint32 indices into
    vertices; normals: (N, 3) float32 unit vertex normals. Exactly one of world_from_object
    ((4, 4) float64, p_world = M [p_object, 1], rotation times a uniform scale plus a
    translation) and anchor. Material as `pipeline.virtual_scene.Material`: albedo linear RGB
    in [0, 1], roughness and metalness in [0, 1], mirror. Equality compares the arrays' values.
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    world_from_object: np.ndarray | None = None
    anchor: SceneAnchorSpec | None = None
    albedo: tuple[float, float, float] = (0.7, 0.7, 0.7)
    roughness: float = 1.0
    metalness: float = 0.0
    mirror: bool = False

    __hash__ = None  # type: ignore[assignment]  # holds arrays

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SceneObjectSpec):
            return NotImplemented
        scalars = ("name", "anchor", "albedo", "roughness", "metalness", "mirror")
        if any(getattr(self, k) != getattr(other, k) for k in scalars):
            return False
        if (self.world_from_object is None) != (other.world_from_object is None):
            return False
        arrays = ("vertices", "triangles", "normals") + (
            () if self.world_from_object is None else ("world_from_object",)
        )
        return all(np.array_equal(getattr(self, k), getattr(other, k)) for k in arrays)

    def _pack(self, name: str) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
        """The object's map and its three arrays as little-endian (N, 3) / (M, 3) arrays."""
        vertices = _xyz_array(self.vertices, _F32, f"{name}.vertices")
        triangles = _xyz_array(self.triangles, _U32, f"{name}.triangles")
        normals = _xyz_array(self.normals, _F32, f"{name}.normals")
        pose = None
        if self.world_from_object is not None:
            pose = pose_to_wire(self.world_from_object, f"{name}.world_from_object")
            pose = [x for row in pose for x in row]
        anchor = None
        if self.anchor is not None:
            anchor = {
                "pixel": None
                if self.anchor.pixel is None
                else float_list(self.anchor.pixel, f"{name}.anchor.pixel"),
                "yaw_deg": to_plain(self.anchor.yaw_deg),
            }
        out = {
            "name": self.name,
            "vertex_count": len(vertices),
            "triangle_count": len(triangles),
            "world_from_object": pose,
            "anchor": anchor,
            "albedo": float_list(self.albedo, f"{name}.albedo"),
            "roughness": to_plain(self.roughness),
            "metalness": to_plain(self.metalness),
            "mirror": to_plain(self.mirror),
        }
        return out, vertices, triangles, normals


def _xyz_array(a: Any, dtype: np.dtype, name: str) -> np.ndarray:
    """An (n, 3) array of numbers as contiguous `dtype` (encode side); uint32 only from
    integers in range, so no index wraps."""
    arr = np.asarray(a)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ProtocolError("bad_field", f"expected shape (n, 3), got {arr.shape}", name)
    if dtype.kind == "u":
        if arr.dtype.kind not in "iu":
            raise ProtocolError("bad_field", f"expected integers, got {arr.dtype}", name)
        if arr.size and (arr.min() < 0 or arr.max() > np.iinfo(np.uint32).max):
            raise ProtocolError(
                "bad_field", f"indices must lie in 0..2^32-1, got {arr.min()}..{arr.max()}", name
            )
    elif arr.dtype.kind not in "fiu":
        raise ProtocolError("bad_field", f"expected numbers, got {arr.dtype}", name)
    return np.ascontiguousarray(arr, dtype=dtype)


@dataclass(frozen=True)
class SceneSpec:
    """The virtual scene a capture client sends in its Hello (SessionConfig.scene): at most
    SCENE_MAX_OBJECTS objects with unique names, SCENE_MAX_TRIANGLES triangles in all."""

    objects: tuple[SceneObjectSpec, ...] = ()

    def _pack(self, parts: list, name: str) -> dict:
        packed = [obj._pack(f"{name}.objects[{i}]") for i, obj in enumerate(self.objects)]
        out: dict[str, Any] = {}
        columns = {
            "vertices": [p[1] for p in packed],
            "triangles": [p[2] for p in packed],
            "normals": [p[3] for p in packed],
        }
        for key in _SCENE_BUFFERS:
            arrays = columns[key]
            joined = (
                arrays[0]
                if len(arrays) == 1
                else np.concatenate(
                    arrays or [np.empty((0, 3), _U32 if key == "triangles" else _F32)]
                )
            )
            out[key] = len(parts)
            parts.append(joined.reshape(-1).view(np.uint8).data)  # a memoryview, zero-copy
        out["objects"] = [p[0] for p in packed]
        return out

    @classmethod
    def _unpack(cls, m: FieldReader, images: ImageParts) -> SceneSpec:
        buffers = {key: images.part(m, key) for key in _SCENE_BUFFERS}
        raw = m.raw("objects")
        where = m.f("objects")
        if type(raw) is not list:
            raise ProtocolError(
                "bad_field", f"expected an array of objects, got {type_name(raw)}", where
            )
        if len(raw) > SCENE_MAX_OBJECTS:
            raise ProtocolError(
                "bad_field", f"{len(raw)} objects, at most {SCENE_MAX_OBJECTS}", where
            )
        fields, names = [], set()
        vertices_total = triangles_total = 0
        for i, o in enumerate(raw):
            om = FieldReader(o, f"{where}[{i}]")
            f = _scene_object_fields(om)
            if f["name"] in names:
                raise ProtocolError(
                    "bad_field", f"object name {f['name']!r} is used twice", om.f("name")
                )
            names.add(f["name"])
            triangles_total += f["triangle_count"]
            if triangles_total > SCENE_MAX_TRIANGLES:
                raise ProtocolError(
                    "bad_field",
                    f"objects 0..{i} have {triangles_total} triangles together, "
                    f"at most {SCENE_MAX_TRIANGLES} in a scene; simplify the meshes",
                    om.f("triangle_count"),
                )
            f["offsets"] = (vertices_total, triangles_total - f["triangle_count"])
            vertices_total += f["vertex_count"]
            fields.append(f)
        m.done()
        if images.parts is None:  # descriptors only: no arrays to check
            return cls()
        given = {key: buf for key, buf in buffers.items() if buf is not None}  # all, with parts
        counts = {
            "vertices": vertices_total,
            "triangles": triangles_total,
            "normals": vertices_total,
        }
        for key, buf in given.items():
            if len(buf) != counts[key] * _XYZ_BYTES:
                what = "triangle_count" if key == "triangles" else "vertex_count"
                raise ProtocolError(
                    "bad_field",
                    f"the part holds {len(buf)} bytes; the objects' {what}s "
                    f"({counts[key]} in all, {_XYZ_BYTES} bytes each) need "
                    f"{counts[key] * _XYZ_BYTES}",
                    m.f(key),
                )
        vertices = np.frombuffer(given["vertices"], _F32).reshape(-1, 3)
        triangles = np.frombuffer(given["triangles"], _U32).reshape(-1, 3)
        normals = np.frombuffer(given["normals"], _F32).reshape(-1, 3)
        objects = []
        for i, f in enumerate(fields):
            name = f"{where}[{i}]"
            v0, t0 = f.pop("offsets")
            nv, nt = f.pop("vertex_count"), f.pop("triangle_count")
            v, n = vertices[v0 : v0 + nv], normals[v0 : v0 + nv]
            t = triangles[t0 : t0 + nt]
            for key, arr in (("vertices", v), ("normals", n)):
                if not np.isfinite(arr).all():
                    raise ProtocolError("bad_field", "not all finite", f"{name}.{key}")
            if t.max() >= nv:
                raise ProtocolError(
                    "bad_field",
                    f"triangle index {int(t.max())} is outside 0..{nv - 1} (vertex_count {nv})",
                    f"{name}.triangles",
                )
            if images.decoding:  # own, aligned, native-order copies: the parts are freed
                v, t, n = v.astype(np.float32), t.astype(np.uint32), n.astype(np.float32)
            objects.append(SceneObjectSpec(vertices=v, triangles=t, normals=n, **f))
        return cls(tuple(objects))


def _scene_object_fields(om: FieldReader) -> dict:
    """One object's header fields, checked (its arrays are checked against the parts)."""
    name = om.str("name", SCENE_MAX_NAME)
    if not name:
        raise ProtocolError("bad_field", "must not be empty", om.f("name"))
    vertex_count = om.int("vertex_count", 3)
    triangle_count = om.int("triangle_count", 1, SCENE_MAX_TRIANGLES)
    pose = om.raw("world_from_object", nullable=True)
    if pose is not None:
        values = read_floats(pose, om.f("world_from_object"), 16)
        if values[12:] != [0.0, 0.0, 0.0, 1.0]:
            raise ProtocolError(
                "bad_field",
                f"the last row must be 0, 0, 0, 1, got {values[12:]}",
                om.f("world_from_object"),
            )
        pose = np.array(values, dtype=np.float64).reshape(4, 4)
    am = om.map("anchor", nullable=True)
    anchor = None
    if am is not None:
        pixel = am.raw("pixel", nullable=True)
        pixel = None if pixel is None else tuple(read_floats(pixel, am.f("pixel"), 2))
        anchor = SceneAnchorSpec(pixel, am.float("yaw_deg"))
        am.done()
    if (pose is None) == (anchor is None):
        raise ProtocolError(
            "bad_field",
            "give exactly one of world_from_object and anchor, got "
            + ("both" if anchor is not None else "neither"),
            om.f("anchor" if anchor is not None else "world_from_object"),
        )
    albedo = om.floats("albedo", 3)
    for k, a in enumerate(albedo):
        if not 0.0 <= a <= 1.0:
            raise ProtocolError(
                "bad_field", f"{a} is outside 0..1 (linear RGB)", f"{om.f('albedo')}[{k}]"
            )
    out = dict(
        name=name,
        vertex_count=vertex_count,
        triangle_count=triangle_count,
        world_from_object=pose,
        anchor=anchor,
        albedo=tuple(albedo),
        roughness=om.float("roughness", 0.0, 1.0),
        metalness=om.float("metalness", 0.0, 1.0),
        mirror=om.bool("mirror"),
    )
    om.done()
    return out


# Hello.config.exports / Result.exports (SPEC.md section 4, "engine layouts"): optional.
