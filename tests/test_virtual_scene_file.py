"""Tests of the virtual-scene file loader (arlight.sources.virtual_scene_file): the shared data
sets' ar/virtual_scene.json (skipped without ../shared/data), our own format with primitives,
anchors and meshes written by Open3D to tmp_path, and every bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from conftest import DATA, needs_data

from arlight.pipeline.virtual_scene import MAX_TRIANGLES, Anchor, SceneError
from arlight.sources import virtual_scene_file
from arlight.sources.virtual_scene_file import load_virtual_scene

SHARED_SCENES = [
    DATA / "synthetic" / seq / "ar" / "virtual_scene.json"
    for seq in ("dev_a_static_venice", "dev_d_indoor_warehouse")
]

data_driven = [pytest.mark.data, needs_data(DATA)]

EYE = np.eye(4).tolist()


def write_scene(folder: Path, objects: list, name: str = "scene.json", **top) -> Path:
    path = folder / name
    path.write_text(json.dumps({"objects": objects, **top}))
    return path


def face_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (vertices[triangles[:, i]].astype(np.float64) for i in range(3))
    n = np.cross(b - a, c - a)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


@pytest.mark.parametrize("path", SHARED_SCENES, ids=lambda p: p.parts[-3])
class TestSharedScenes:
    pytestmark = data_driven

    def test_objects_match_the_files_facts(self, path: Path):
        doc = json.loads(path.read_text())
        scene = load_virtual_scene(path)
        assert [o.name for o in scene.objects] == [o["name"] for o in doc["objects"]]
        for obj, spec in zip(scene.objects, doc["objects"], strict=True):
            facts = spec["mesh_facts"]
            assert len(obj.triangles) == facts["triangles"]
            assert len(obj.vertices) == facts["vertices"]
            np.testing.assert_allclose(obj.vertices.min(axis=0), facts["bbox_min"], atol=1e-6)
            np.testing.assert_allclose(obj.vertices.max(axis=0), facts["bbox_max"], atol=1e-6)
            assert obj.material.albedo == tuple(spec["albedo_rgb"])
            np.testing.assert_array_equal(obj.world_from_object, spec["world_from_object"])
            assert obj.anchor is None

    def test_world_and_cam0_differ_by_world_from_cam0(self, path: Path):
        world_from_cam0 = np.array(json.loads(path.read_text())["world_from_cam0"])
        world = load_virtual_scene(path, frame="world")
        cam0 = load_virtual_scene(path, frame="cam0")
        for w, c in zip(world.objects, cam0.objects, strict=True):
            assert not np.allclose(w.world_from_object, c.world_from_object)
            # the file prints 7 decimals
            np.testing.assert_allclose(
                world_from_cam0 @ c.world_from_object, w.world_from_object, atol=2e-6
            )
            np.testing.assert_array_equal(w.vertices, c.vertices)

    def test_arch_keeps_its_flat_normals_and_sphere_its_smooth_ones(self, path: Path):
        sphere, arch = load_virtual_scene(path).objects
        # every arch triangle's three vertex normals are its face normal
        n = face_normals(arch.vertices, arch.triangles)
        np.testing.assert_allclose(
            arch.normals[arch.triangles], np.repeat(n[:, None, :], 3, axis=1), atol=1e-6
        )
        # sphere: shared vertices, radial normals about the centre one radius up
        radial = sphere.vertices - np.array([0.0, 0.18, 0.0], np.float32)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        np.testing.assert_allclose(sphere.normals, radial, atol=1e-4)


class TestOwnFormat:
    def test_primitives_with_sizes(self, tmp_path: Path):
        path = write_scene(
            tmp_path,
            [
                {
                    "name": "ball",
                    "primitive": {"shape": "sphere", "radius_m": 0.2},
                    "world_from_object": EYE,
                },
                {
                    "name": "crate",
                    "primitive": {"shape": "box", "size_m": [0.1, 0.2, 0.3]},
                    "world_from_object": EYE,
                },
                {
                    "name": "ring",
                    "primitive": {"shape": "torus", "ring_radius_m": 0.3, "tube_radius_m": 0.05},
                    "world_from_object": EYE,
                },
                {"name": "default", "primitive": {"shape": "sphere"}, "world_from_object": EYE},
            ],
        )
        ball, crate, ring, default = load_virtual_scene(path).objects
        extent = {
            o.name: o.vertices.max(axis=0) - o.vertices.min(axis=0)
            for o in (ball, crate, ring, default)
        }
        np.testing.assert_allclose(extent["ball"], [0.4, 0.4, 0.4], atol=1e-3)
        np.testing.assert_allclose(extent["crate"], [0.1, 0.2, 0.3], atol=1e-6)
        np.testing.assert_allclose(extent["ring"], [0.7, 0.7, 0.1], atol=1e-3)
        np.testing.assert_allclose(extent["default"], [0.2, 0.2, 0.2], atol=1e-3)
        assert ball.material.albedo == (0.7, 0.7, 0.7)  # the Material default

    def test_pose_scale_and_material(self, tmp_path: Path):
        pose = np.eye(4)
        pose[:3, :3] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]
        pose[:3, 3] = [1.0, 0.0, -2.0]
        path = write_scene(
            tmp_path,
            [
                {
                    "name": "big",
                    "primitive": {"shape": "box", "size_m": [0.1, 0.1, 0.1]},
                    "world_from_object": pose.tolist(),
                    "scale": 2.5,
                    "material": {
                        "albedo": [0.1, 0.2, 0.3],
                        "roughness": 0.4,
                        "metalness": 1.0,
                        "mirror": True,
                    },
                },
                {
                    "name": "flat_albedo",
                    "primitive": {"shape": "sphere"},
                    "world_from_object": EYE,
                    "albedo_rgb": [0.5, 0.25, 0.0],
                },
            ],
        )
        big, flat = load_virtual_scene(path).objects
        np.testing.assert_allclose(big.world_from_object, pose @ np.diag([2.5, 2.5, 2.5, 1]))
        m = big.material
        assert (m.albedo, m.roughness, m.metalness, m.mirror) == ((0.1, 0.2, 0.3), 0.4, 1.0, True)
        assert flat.material.albedo == (0.5, 0.25, 0.0)

    def test_anchors(self, tmp_path: Path):
        path = write_scene(
            tmp_path,
            [
                {
                    "name": "at_pixel",
                    "primitive": {"shape": "sphere"},
                    "anchor": {"pixel": [100, 200.5], "yaw_deg": 30},
                    "scale": 2.0,
                },
                {"name": "at_centre", "primitive": {"shape": "sphere"}, "anchor": {"pixel": None}},
                {"name": "placed", "primitive": {"shape": "sphere"}, "world_from_object": EYE},
            ],
        )
        scene = load_virtual_scene(path)
        at_pixel, at_centre, placed = scene.objects
        assert at_pixel.anchor.pixel == (100.0, 200.5) and at_pixel.anchor.yaw_deg == 30.0
        np.testing.assert_allclose(at_pixel.world_from_object, np.diag([2.0, 2.0, 2.0, 1.0]))
        assert at_centre.anchor.pixel is None and at_centre.anchor.yaw_deg == 0.0
        assert placed.anchor is None and scene.anchored
        # an anchor needs no pose key, in either frame
        path = write_scene(
            tmp_path, [{"name": "a", "primitive": {"shape": "sphere"}, "anchor": {}}]
        )
        assert load_virtual_scene(path, frame="cam0").objects[0].anchor == Anchor()

    def test_cam0_pose_in_our_format(self, tmp_path: Path):
        pose = np.eye(4)
        pose[:3, 3] = [0.0, 0.5, 2.0]
        path = write_scene(
            tmp_path,
            [
                {
                    "name": "s",
                    "primitive": {"shape": "sphere"},
                    "world_from_object": EYE,
                    "cam0_from_object": pose.tolist(),
                }
            ],
        )
        np.testing.assert_array_equal(
            load_virtual_scene(path, "cam0").objects[0].world_from_object, pose
        )
        np.testing.assert_array_equal(
            load_virtual_scene(path, "world").objects[0].world_from_object, np.eye(4)
        )

    def test_toml_equals_json(self, tmp_path: Path):
        (tmp_path / "scene.toml").write_text(
            '[[objects]]\nname = "ball"\nworld_from_object = '
            "[[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n"
            '[objects.primitive]\nshape = "sphere"\nradius_m = 0.15\n'
            "[objects.material]\nalbedo = [0.2, 0.3, 0.4]\n"
            '[[objects]]\nname = "ring"\nanchor = { yaw_deg = 45 }\n'
            '[objects.primitive]\nshape = "torus"\n'
        )
        ball_pose = np.eye(4)
        ball_pose[0, 3] = 0.5
        json_path = write_scene(
            tmp_path,
            [
                {
                    "name": "ball",
                    "world_from_object": ball_pose.tolist(),
                    "primitive": {"shape": "sphere", "radius_m": 0.15},
                    "material": {"albedo": [0.2, 0.3, 0.4]},
                },
                {"name": "ring", "anchor": {"yaw_deg": 45}, "primitive": {"shape": "torus"}},
            ],
        )
        for a, b in zip(
            load_virtual_scene(tmp_path / "scene.toml").objects,
            load_virtual_scene(json_path).objects,
            strict=True,
        ):
            assert a.name == b.name and a.material == b.material and a.anchor == b.anchor
            np.testing.assert_array_equal(a.world_from_object, b.world_from_object)
            np.testing.assert_array_equal(a.vertices, b.vertices)


def write_mesh(path: Path, mesh: o3d.geometry.TriangleMesh) -> Path:
    """`mesh` written by Open3D; GLB through the tensor writer (the legacy one's GLB keeps
    its buffer as a data URI that Open3D's own reader rejects)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".glb":
        ok = o3d.t.io.write_triangle_mesh(str(path), o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    else:
        ok = o3d.io.write_triangle_mesh(str(path), mesh)
    assert ok
    return path


class TestMeshFiles:
    @pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb", ".gltf"])
    def test_smooth_mesh_round_trip(self, tmp_path: Path, suffix: str):
        mesh = o3d.geometry.TriangleMesh.create_sphere(0.25, resolution=10)
        # exactly radial normals: Open3D's computed ones differ from them by up to 0.05
        mesh.vertex_normals = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) / 0.25)
        write_mesh(tmp_path / "meshes" / f"ball{suffix}", mesh)
        path = write_scene(
            tmp_path, [{"name": "ball", "mesh": f"meshes/ball{suffix}", "world_from_object": EYE}]
        )
        obj = load_virtual_scene(path).objects[0]
        assert len(obj.triangles) == len(mesh.triangles)
        np.testing.assert_allclose(
            obj.vertices.min(axis=0), np.asarray(mesh.vertices).min(0), atol=1e-6
        )
        np.testing.assert_allclose(
            obj.vertices.max(axis=0), np.asarray(mesh.vertices).max(0), atol=1e-6
        )
        # the file's smooth normals kept, not recomputed
        radial = obj.vertices / np.linalg.norm(obj.vertices, axis=1, keepdims=True)
        np.testing.assert_allclose(obj.normals, radial, atol=1e-5)

    @pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb", ".gltf"])
    def test_flat_mesh_keeps_face_normals(self, tmp_path: Path, suffix: str):
        box = o3d.geometry.TriangleMesh.create_box(0.2, 0.3, 0.4)
        v = np.asarray(box.vertices)[np.asarray(box.triangles)].reshape(-1, 3)
        flat = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(v),
            o3d.utility.Vector3iVector(np.arange(len(v)).reshape(-1, 3)),
        )
        flat.compute_triangle_normals()
        flat.vertex_normals = o3d.utility.Vector3dVector(
            np.repeat(np.asarray(flat.triangle_normals), 3, axis=0)
        )
        write_mesh(tmp_path / f"box{suffix}", flat)
        obj = load_virtual_scene(
            write_scene(
                tmp_path, [{"name": "box", "mesh": f"box{suffix}", "world_from_object": EYE}]
            )
        ).objects[0]
        assert len(obj.triangles) == 12
        n = face_normals(obj.vertices, obj.triangles)
        np.testing.assert_allclose(
            obj.normals[obj.triangles], np.repeat(n[:, None, :], 3, axis=1), atol=1e-6
        )

    @pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
    def test_missing_normals_are_computed(self, tmp_path: Path, suffix: str):
        mesh = o3d.geometry.TriangleMesh.create_sphere(0.25, resolution=10)
        assert not mesh.has_vertex_normals()
        write_mesh(tmp_path / f"ball{suffix}", mesh)
        obj = load_virtual_scene(
            write_scene(
                tmp_path, [{"name": "ball", "mesh": f"ball{suffix}", "world_from_object": EYE}]
            )
        ).objects[0]
        np.testing.assert_allclose(np.linalg.norm(obj.normals, axis=1), 1.0, atol=1e-5)
        radial = obj.vertices / np.linalg.norm(obj.vertices, axis=1, keepdims=True)
        assert np.all(np.sum(obj.normals * radial, axis=1) > 0.9)  # outward


def box_ply(path: Path) -> Path:
    mesh = o3d.geometry.TriangleMesh.create_box(0.2, 0.2, 0.2)
    mesh.compute_vertex_normals()
    return write_mesh(path, mesh)


def obj_scene(tmp_path: Path, **changes) -> Path:
    """A valid one-object scene ("thing", a box PLY) with keys changed (None: removed)."""
    box_ply(tmp_path / "thing.ply")
    obj = {"name": "thing", "mesh": "thing.ply", "world_from_object": EYE}
    obj.update(changes)
    return write_scene(tmp_path, [{k: v for k, v in obj.items() if v is not None}])


def raw_scene(tmp_path: Path, text: str) -> Path:
    box_ply(tmp_path / "thing.ply")
    (tmp_path / "scene.json").write_text(text)
    return tmp_path / "scene.json"


def rotation_pose(diag) -> list:
    return np.diag([*diag, 1.0]).tolist()


# (case id, changes to the valid object, fragment the message must hold)
OBJECT_CASES = [
    ("missing_mesh_file", {"mesh": "nowhere.ply"}, "not found"),
    ("bad_suffix", {"mesh": "thing.stl"}, ".ply, .obj, .glb, .gltf"),
    ("mesh_not_a_string", {"mesh": 3}, "file path"),
    ("mesh_and_primitive", {"primitive": {"shape": "sphere"}}, "exactly one of"),
    ("neither_mesh_nor_primitive", {"mesh": None}, "exactly one of"),
    ("no_pose_no_anchor", {"world_from_object": None}, "needs a pose"),
    ("pose_and_anchor", {"anchor": {"pixel": None}}, "not both"),
    ("anchor_not_object", {"world_from_object": None, "anchor": [1, 2]}, '"anchor" must be'),
    (
        "anchor_unknown_key",
        {"world_from_object": None, "anchor": {"px": [1, 2]}},
        "valid keys: pixel, yaw_deg",
    ),
    (
        "anchor_pixel_shape",
        {"world_from_object": None, "anchor": {"pixel": [1, 2, 3]}},
        "anchor pixel must be numbers of shape 2",
    ),
    ("anchor_yaw_nan", {"world_from_object": None, "anchor": {"yaw_deg": float("nan")}}, "finite"),
    ("pose_shape", {"world_from_object": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "shape 4x4"),
    ("pose_ragged", {"world_from_object": [[1, 0, 0, 0]] * 3 + [[0, 0, 1]]}, "shape 4x4"),
    ("pose_string", {"world_from_object": [["1", 0, 0, 0]] + EYE[1:]}, "shape 4x4"),
    ("pose_bool", {"world_from_object": [[True, 0, 0, 0]] + EYE[1:]}, "shape 4x4"),
    ("pose_nan", {"world_from_object": [[float("nan"), 0, 0, 0]] + EYE[1:]}, "finite"),
    ("pose_inf", {"world_from_object": [[float("inf"), 0, 0, 0]] + EYE[1:]}, "finite"),
    ("pose_mirror", {"world_from_object": rotation_pose([-1, 1, 1])}, "det <= 0"),
    ("pose_non_uniform_scale", {"world_from_object": rotation_pose([1, 2, 1])}, "uniform scale"),
    ("pose_last_row", {"world_from_object": EYE[:3] + [[0.5, 0, 0, 1]]}, "uniform scale"),
    ("scale_zero", {"scale": 0}, '"scale" must be > 0'),
    ("scale_string", {"scale": "2"}, "scale must be a number"),
    ("unknown_key", {"colour": [1, 0, 0]}, "unknown key(s) colour; valid keys: name, mesh"),
    ("material_unknown_key", {"material": {"shine": 1}}, "valid keys: albedo, roughness"),
    ("material_not_object", {"material": [0.5, 0.5, 0.5]}, '"material" must be'),
    ("albedo_out_of_range", {"material": {"albedo": [1.2, 0.5, 0.5]}}, "[0, 1]"),
    ("albedo_rgb_negative", {"albedo_rgb": [-0.1, 0.5, 0.5]}, "[0, 1]"),
    ("albedo_twice", {"albedo_rgb": [0.5] * 3, "material": {"albedo": [0.5] * 3}}, "albedo once"),
    ("albedo_two_values", {"albedo_rgb": [0.5, 0.5]}, "albedo must be numbers of shape 3"),
    ("roughness_out_of_range", {"material": {"roughness": 1.5}}, "roughness must be in"),
    ("mirror_not_bool", {"material": {"mirror": 1}}, "true or false"),
    (
        "primitive_unknown_shape",
        {"mesh": None, "primitive": {"shape": "cone"}},
        "sphere, box, torus",
    ),
    (
        "primitive_unknown_key",
        {"mesh": None, "primitive": {"shape": "sphere", "radius": 1}},
        "valid keys: shape, radius_m",
    ),
    (
        "primitive_negative_size",
        {"mesh": None, "primitive": {"shape": "sphere", "radius_m": -0.1}},
        "> 0",
    ),
    (
        "primitive_box_size_shape",
        {"mesh": None, "primitive": {"shape": "box", "size_m": [0.1, 0.1]}},
        "size_m must be numbers of shape 3",
    ),
]


class TestBadInput:
    @pytest.mark.parametrize(
        "changes, fragment", [c[1:] for c in OBJECT_CASES], ids=[c[0] for c in OBJECT_CASES]
    )
    def test_bad_object(self, tmp_path: Path, changes: dict, fragment: str):
        path = obj_scene(tmp_path, **changes)
        with pytest.raises(SceneError) as info:
            load_virtual_scene(path)
        message = str(info.value)
        assert str(path) in message and "'thing'" in message
        assert fragment in message
        assert info.value.__suppress_context__  # raised `from None`: no chained traceback

    def test_other_frame_names_the_option(self, tmp_path: Path):
        with pytest.raises(SceneError, match="'thing'.*--scene-frame world"):
            load_virtual_scene(obj_scene(tmp_path), frame="cam0")
        path = obj_scene(tmp_path, world_from_object=None, cam0_from_object=EYE)
        with pytest.raises(SceneError, match="'thing'.*--scene-frame cam0"):
            load_virtual_scene(path, frame="world")

    def test_bad_frame(self, tmp_path: Path):
        with pytest.raises(SceneError, match="--scene-frame must be world or cam0"):
            load_virtual_scene(obj_scene(tmp_path), frame="camera")

    @pytest.mark.parametrize("content", [b"\x00\x01not a mesh", b"", b"ply\nformat ascii 1.0\n"])
    def test_broken_ply(self, tmp_path: Path, content: bytes, capfd):
        path = obj_scene(tmp_path)
        (tmp_path / "thing.ply").write_bytes(content)
        before = o3d.utility.get_verbosity_level()
        with pytest.raises(SceneError, match=r"'thing'.*holds no triangles"):
            load_virtual_scene(path)
        assert "Open3D WARNING" not in capfd.readouterr().out  # silenced during the read
        assert o3d.utility.get_verbosity_level() == before  # and restored

    @pytest.mark.parametrize("fraction", [0.5, 0.97], ids=["in_vertices", "in_faces"])
    def test_truncated_ply(self, tmp_path: Path, fraction: float):
        path = obj_scene(tmp_path)
        data = (tmp_path / "thing.ply").read_bytes()
        (tmp_path / "thing.ply").write_bytes(data[: int(len(data) * fraction)])
        with pytest.raises(SceneError, match=r"'thing'.*(truncated|no triangles)"):
            load_virtual_scene(path)

    def test_point_cloud_is_not_a_mesh(self, tmp_path: Path):
        path = obj_scene(tmp_path)
        o3d.io.write_point_cloud(
            str(tmp_path / "thing.ply"),
            o3d.geometry.PointCloud(
                o3d.utility.Vector3dVector(np.random.default_rng(0).random((10, 3)))
            ),
        )
        with pytest.raises(SceneError, match="'thing'.*no triangles"):
            load_virtual_scene(path)

    @pytest.mark.parametrize(
        "text, fragment",
        [
            ("this is not obj\n", "no triangles"),
            ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "no triangles"),  # index out of range
            ("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "not all finite"),
        ],
        ids=["garbage", "index_out_of_range", "nan_vertex"],
    )
    def test_broken_obj(self, tmp_path: Path, text: str, fragment: str):
        (tmp_path / "thing.obj").write_text(text)
        path = write_scene(
            tmp_path, [{"name": "thing", "mesh": "thing.obj", "world_from_object": EYE}]
        )
        with pytest.raises(SceneError, match=f"'thing'.*{fragment}"):
            load_virtual_scene(path)

    def test_huge_ply_rejected_from_its_header(self, tmp_path: Path):
        """Millions of faces announced: refused before Open3D builds the arrays."""
        path = obj_scene(tmp_path)
        (tmp_path / "thing.ply").write_bytes(
            b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
            b"property float y\nproperty float z\n"
            + f"element face {MAX_TRIANGLES + 1}\n".encode()
            + b"property list uchar int vertex_indices\nend_header\n"
        )
        with pytest.raises(SceneError, match=f"'thing': {MAX_TRIANGLES + 1} triangles.*simplify"):
            load_virtual_scene(path)

    def test_triangle_budget_over_the_whole_scene(self, tmp_path: Path, monkeypatch):
        monkeypatch.setattr(virtual_scene_file, "MAX_TRIANGLES", 20)  # box: 12 triangles
        box_ply(tmp_path / "thing.ply")
        o3d.io.write_triangle_mesh(
            str(tmp_path / "ball.obj"), o3d.geometry.TriangleMesh.create_box()
        )
        path = write_scene(
            tmp_path,
            [
                {"name": "first", "mesh": "thing.ply", "world_from_object": EYE},
                {"name": "second", "mesh": "ball.obj", "world_from_object": EYE},
            ],
        )
        with pytest.raises(SceneError, match=r"'second': 12 triangles.*\(8 left"):
            load_virtual_scene(path)

    def test_triangle_budget_counts_primitives(self, tmp_path: Path, monkeypatch):
        monkeypatch.setattr(virtual_scene_file, "MAX_TRIANGLES", 3000)  # a sphere: 2208
        ball = {"primitive": {"shape": "sphere"}, "world_from_object": EYE}
        path = write_scene(tmp_path, [{"name": "first", **ball}, {"name": "second", **ball}])
        with pytest.raises(SceneError, match=r"'second': 2208 triangles.*\(792 left"):
            load_virtual_scene(path)

    def test_duplicate_names(self, tmp_path: Path):
        obj = {"name": "twin", "primitive": {"shape": "sphere"}, "world_from_object": EYE}
        path = write_scene(tmp_path, [obj, dict(obj)])
        with pytest.raises(SceneError, match=r"'twin'.*objects\[0\] and objects\[1\]"):
            load_virtual_scene(path)

    @pytest.mark.parametrize(
        "objects, fragment",
        [
            ([{"primitive": {"shape": "sphere"}, "world_from_object": EYE}], r"objects\[0\]"),
            ([{"name": "", "primitive": {"shape": "sphere"}}], r"objects\[0\]"),
            ([7], r"objects\[0\]"),
            ([], "non-empty list"),
            ({"name": "x"}, "non-empty list"),
        ],
        ids=["no_name", "empty_name", "not_an_object", "empty", "not_a_list"],
    )
    def test_bad_object_list(self, tmp_path: Path, objects, fragment: str):
        with pytest.raises(SceneError, match=fragment):
            load_virtual_scene(write_scene(tmp_path, objects))

    def test_unknown_top_level_key(self, tmp_path: Path):
        path = write_scene(tmp_path, [], lights=[])
        with pytest.raises(SceneError, match="unknown key.*lights; valid keys: objects"):
            load_virtual_scene(path)

    def test_malformed_json_names_line_and_column(self, tmp_path: Path):
        path = raw_scene(tmp_path, '{"objects": [\n  {"name": "thing",,}\n]}')
        with pytest.raises(SceneError, match=r"not valid JSON: .* at line 2, column 20"):
            load_virtual_scene(path)

    def test_malformed_toml(self, tmp_path: Path):
        (tmp_path / "scene.toml").write_text('[[objects]]\nname = "thing\n')
        with pytest.raises(SceneError, match=r"scene.toml is not valid TOML: .*line 2"):
            load_virtual_scene(tmp_path / "scene.toml")

    def test_missing_scene_file_and_bad_suffix(self, tmp_path: Path):
        with pytest.raises(SceneError, match="nowhere.json not found"):
            load_virtual_scene(tmp_path / "nowhere.json")
        (tmp_path / "scene.yaml").write_text("objects: []")
        with pytest.raises(SceneError, match=r"must end in \.json or \.toml"):
            load_virtual_scene(tmp_path / "scene.yaml")

    def test_not_an_object_at_the_top(self, tmp_path: Path):
        with pytest.raises(SceneError, match="top level"):
            load_virtual_scene(raw_scene(tmp_path, "[1, 2]"))

    def test_dataset_layout_ignores_descriptive_keys_but_checks_the_rest(self, tmp_path: Path):
        obj = {
            "name": "thing",
            "mesh": "thing.ply",
            "world_from_object": EYE,
            "mesh_facts": {"triangles": 12},
            "bsdf": "Lambertian",
        }
        box_ply(tmp_path / "thing.ply")
        path = write_scene(tmp_path, [obj], world_from_cam0=EYE, sequence="x")
        assert load_virtual_scene(path).objects[0].name == "thing"
        with pytest.raises(SceneError, match="'thing'.*--scene-frame world"):
            load_virtual_scene(path, frame="cam0")
