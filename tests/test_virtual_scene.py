"""Tests of the virtual objects (arlight.pipeline.virtual_scene): the object checks, the
primitives, anchoring on the support plane, bounding spheres."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from arlight.core.camera import PinholeCamera
from arlight.core.checks import CheckError
from arlight.pipeline import virtual_scene
from arlight.pipeline.virtual_scene import (
    MAX_OBJECTS,
    PRIMITIVES,
    Anchor,
    Material,
    SceneError,
    VirtualObject,
    VirtualScene,
    demo_scene,
    object_from_open3d,
    pose_on_plane,
    resolve_anchors,
)

TETRA_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
TETRA_T = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)


def tetra(name: str = "tetra", **changes) -> VirtualObject:
    fields = dict(
        name=name,
        vertices=TETRA_V,
        triangles=TETRA_T,
        normals=TETRA_V - TETRA_V.mean(axis=0),
        world_from_object=np.eye(4),
    )
    fields.update(changes)
    return VirtualObject(**fields)


def pose(rotvec=(0.3, -0.5, 0.2), translation=(0.4, -0.1, 2.0), scale=1.0) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = scale * Rotation.from_rotvec(rotvec).as_matrix()
    m[:3, 3] = translation
    return m


class TestSceneError:
    def test_one_message_and_pickle(self):
        err = SceneError("virtual object 'x': bad")
        assert isinstance(err, CheckError) and str(err) == "virtual object 'x': bad"
        back = pickle.loads(pickle.dumps(err))
        assert type(back) is SceneError and str(back) == str(err)


NAN_V = TETRA_V.copy()
NAN_V[1, 0] = np.nan

# (case id, changes, fragment of the message)
BAD_OBJECTS = [
    ("vertices_2d", {"vertices": TETRA_V[:, :2]}, "vertices must be (N >= 3, 3)"),
    (
        "vertices_too_few",
        {"vertices": TETRA_V[:2], "normals": TETRA_V[:2]},
        "vertices must be (N >= 3, 3)",
    ),
    ("vertices_list", {"vertices": TETRA_V.tolist()}, "vertices must be"),
    ("triangles_2_columns", {"triangles": TETRA_T[:, :2]}, "triangles must be (M >= 1, 3)"),
    ("triangles_empty", {"triangles": np.zeros((0, 3), np.int32)}, "triangles must be"),
    ("normals_mismatch", {"normals": TETRA_V[:3]}, "normals must match"),
    ("vertices_nan", {"vertices": NAN_V}, "not all finite"),
    ("normals_inf", {"normals": np.full((4, 3), np.inf, np.float32)}, "not all finite"),
    ("index_too_big", {"triangles": TETRA_T + 1}, "indices must lie in 0..3"),
    ("index_negative", {"triangles": TETRA_T - 1}, "indices must lie in 0..3"),
    ("pose_3x3", {"world_from_object": np.eye(3)}, "finite 4x4"),
    ("pose_nan", {"world_from_object": np.full((4, 4), np.nan)}, "finite 4x4"),
    ("pose_mirror", {"world_from_object": np.diag([-1.0, 1, 1, 1])}, "det <= 0"),
    ("pose_zero", {"world_from_object": np.diag([0.0, 0, 0, 1])}, "det <= 0"),
    ("pose_non_uniform", {"world_from_object": np.diag([1.0, 2, 1, 1])}, "uniform scale"),
    (
        "pose_shear",
        {
            "world_from_object": np.array(
                [[1, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]
            )
        },
        "uniform scale",
    ),
    (
        "pose_last_row",
        {
            "world_from_object": np.array(
                [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.5, 0, 0, 1.0]]
            )
        },
        "uniform scale",
    ),
    ("albedo_above_1", {"material": Material((1.2, 0.5, 0.5))}, "[0, 1]"),
    ("albedo_negative", {"material": Material((0.5, -0.1, 0.5))}, "[0, 1]"),
    ("albedo_nan", {"material": Material((0.5, np.nan, 0.5))}, "[0, 1]"),
    ("albedo_two", {"material": Material((0.5, 0.5))}, "3 linear RGB"),
]


class TestCheckObject:
    def test_valid_with_rotation_and_uniform_scale(self):
        obj = tetra(world_from_object=pose(scale=2.5))
        assert virtual_scene._scale(obj) == pytest.approx(2.5)

    @pytest.mark.parametrize(
        "changes, fragment", [c[1:] for c in BAD_OBJECTS], ids=[c[0] for c in BAD_OBJECTS]
    )
    def test_bad(self, changes: dict, fragment: str):
        with pytest.raises(SceneError) as info:
            tetra("the_object", **changes)
        assert "'the_object'" in str(info.value) and fragment in str(info.value)

    def test_too_many_triangles(self, monkeypatch):
        monkeypatch.setattr(virtual_scene, "MAX_TRIANGLES", 3)
        with pytest.raises(SceneError, match="'tetra': 4 triangles, at most 3.*simplify"):
            tetra()


class TestVirtualScene:
    def test_names_unique(self):
        with pytest.raises(SceneError, match="unique"):
            VirtualScene((tetra("a"), tetra("a")))

    def test_limits(self, monkeypatch):
        with pytest.raises(SceneError, match=f"at most {MAX_OBJECTS}"):
            VirtualScene(tuple(tetra(f"t{i}") for i in range(MAX_OBJECTS + 1)))
        monkeypatch.setattr(virtual_scene, "MAX_TRIANGLES", 7)  # 4 each: one fits, two do not
        VirtualScene((tetra("a"),))
        with pytest.raises(SceneError, match="8 triangles, at most 7"):
            VirtualScene((tetra("a"), tetra("b")))

    def test_anchored_and_empty(self):
        assert not VirtualScene() and not VirtualScene().anchored
        scene = VirtualScene((tetra("a"), tetra("b", anchor=Anchor())))
        assert scene and scene.anchored
        assert scene.objects[1].placed(pose()).anchor is None


class TestPrimitives:
    @pytest.mark.parametrize("shape", sorted(PRIMITIVES))
    def test_stand_on_y0_centred(self, shape: str):
        mesh = PRIMITIVES[shape]()
        v = np.asarray(mesh.vertices)
        lo, hi = v.min(axis=0), v.max(axis=0)
        assert lo[1] == pytest.approx(0.0, abs=1e-12)
        np.testing.assert_allclose((lo + hi)[[0, 2]] / 2, 0.0, atol=1e-12)
        n = np.asarray(mesh.vertex_normals)
        assert n.shape == v.shape
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
        object_from_open3d(shape, mesh, np.eye(4))  # passes the checks

    def test_sizes(self):
        def extent(mesh):
            v = np.asarray(mesh.vertices)
            return v.max(axis=0) - v.min(axis=0)

        np.testing.assert_allclose(extent(PRIMITIVES["sphere"](0.3)), [0.6, 0.6, 0.6], atol=2e-3)
        np.testing.assert_allclose(extent(PRIMITIVES["box"]((0.1, 0.2, 0.3))), [0.1, 0.2, 0.3])
        # upright ring in the x-y plane, standing on its rim
        np.testing.assert_allclose(
            extent(PRIMITIVES["torus"](0.2, 0.05)), [0.5, 0.5, 0.1], atol=2e-3
        )

    def test_box_flat_and_sphere_radial_normals(self):
        box = object_from_open3d("box", PRIMITIVES["box"](), np.eye(4))
        a, b, c = (box.vertices[box.triangles[:, i]] for i in range(3))
        face = np.cross(b - a, c - a)
        face /= np.linalg.norm(face, axis=1, keepdims=True)
        np.testing.assert_allclose(
            box.normals[box.triangles], np.repeat(face[:, None], 3, axis=1), atol=1e-6
        )
        sphere = object_from_open3d("sphere", PRIMITIVES["sphere"](0.1), np.eye(4))
        radial = sphere.vertices - np.array([0, 0.1, 0], np.float32)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        assert np.all(np.sum(sphere.normals * radial, axis=1) > 0.99)


CAMERA = PinholeCamera.kinect_v1()
UP_CAM = np.array([0.05, -0.95, -0.3]) / np.linalg.norm([0.05, -0.95, -0.3])
OFFSET_M = 1.3  # the camera 1.3 m above the plane


def project(world_from_cam: np.ndarray, point_world: np.ndarray) -> np.ndarray:
    p = np.linalg.inv(world_from_cam) @ np.append(point_world, 1.0)
    return np.array([CAMERA.fx * p[0] / p[2] + CAMERA.cx, CAMERA.fy * p[1] / p[2] + CAMERA.cy])


class TestResolveAnchors:
    def test_anchored_object_stands_under_its_pixel(self):
        world_from_cam = pose()
        scene = VirtualScene(
            (
                tetra(
                    "px",
                    anchor=Anchor((400.0, 330.0), yaw_deg=0.0),
                    world_from_object=np.diag([2.0, 2.0, 2.0, 1.0]),
                ),
                tetra("yawed", anchor=Anchor((400.0, 330.0), yaw_deg=90.0)),
                tetra("centre", anchor=Anchor(None)),
                tetra("fixed", world_from_object=pose(translation=(5, 5, 5))),
            )
        )
        out = resolve_anchors(scene, UP_CAM, OFFSET_M, world_from_cam, CAMERA)
        px, yawed, centre, fixed = out.objects
        assert not out.anchored
        for obj, pixel in ((px, (400.0, 330.0)), (centre, (CAMERA.cx, CAMERA.cy))):
            base = obj.world_from_object[:3, 3]
            np.testing.assert_allclose(project(world_from_cam, base), pixel, atol=0.5)
            base_cam = (np.linalg.inv(world_from_cam) @ np.append(base, 1.0))[:3]
            assert UP_CAM @ base_cam + OFFSET_M == pytest.approx(0.0, abs=1e-9)  # on the plane
            # object +y along the plane's up, in the world frame
            y = obj.world_from_object[:3, 1]
            np.testing.assert_allclose(
                y / np.linalg.norm(y), world_from_cam[:3, :3] @ UP_CAM, atol=1e-9
            )
        assert virtual_scene._scale(px) == pytest.approx(2.0)  # the anchored scale kept
        # yaw turns the object about up: x axes 90 degrees apart
        x0 = px.world_from_object[:3, 0] / 2.0
        x90 = yawed.world_from_object[:3, 0]
        assert x0 @ x90 == pytest.approx(0.0, abs=1e-9)
        np.testing.assert_allclose(np.cross(x0, x90), world_from_cam[:3, :3] @ UP_CAM, atol=1e-9)
        np.testing.assert_array_equal(fixed.world_from_object, scene.objects[3].world_from_object)

    def test_ray_above_the_horizon_stays_anchored(self):
        scene = VirtualScene(
            (
                tetra("sky", anchor=Anchor((CAMERA.cx, 0.0))),
                tetra("floor", anchor=Anchor((CAMERA.cx, CAMERA.height - 1))),
            )
        )
        ray = np.array([0.0, -CAMERA.cy / CAMERA.fy, 1.0])
        assert UP_CAM @ ray > 0  # the top row looks above the horizon
        out = resolve_anchors(scene, UP_CAM, OFFSET_M, pose(), CAMERA)
        sky, floor = out.objects
        assert sky.anchor == scene.objects[0].anchor and floor.anchor is None
        assert out.anchored

    def test_pose_on_plane_is_a_rotation(self):
        up = np.array([0.1, 0.9, -0.2])
        m = pose_on_plane(np.array([1.0, 2.0, 3.0]), up, 37.0, np.array([0.0, 0.0, 1.0]))
        r = m[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
        np.testing.assert_allclose(r[:, 1], up / np.linalg.norm(up), atol=1e-12)
        # forward parallel to up: still a rotation
        m = pose_on_plane(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.0, np.array([0, 0, 2.0]))
        np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-12)

    def test_demo_scene(self):
        scene = demo_scene()
        assert [o.name for o in scene.objects] == ["sphere", "torus"] and scene.anchored


class TestGeometry:
    @pytest.mark.parametrize("scale", [1.0, 0.3, 4.0])
    def test_bounding_sphere_contains_all_vertices(self, scale: float):
        obj = object_from_open3d("torus", PRIMITIVES["torus"](), pose(scale=scale))
        centre, radius = obj.bounding_sphere()
        v = obj.world_vertices()
        assert np.linalg.norm(v - centre, axis=1).max() <= radius + 1e-12
        lo, hi = v.min(axis=0), v.max(axis=0)
        assert radius <= 0.5 * np.linalg.norm(hi - lo) + 1e-12  # no looser than the box

    def test_world_vertices_and_normals(self):
        m = pose(scale=2.0)
        obj = object_from_open3d("sphere", PRIMITIVES["sphere"](0.1), m)
        np.testing.assert_allclose(
            obj.world_vertices()[0], m[:3, :3] @ obj.vertices[0] + m[:3, 3], atol=1e-6
        )
        n = obj.world_normals()
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-9)
        expected = m[:3, :3] @ obj.normals[0] / 2.0
        np.testing.assert_allclose(n[0], expected / np.linalg.norm(expected), atol=1e-6)
