"""Volume V, G_v = (D_v, N_v), frame-to-model tracking and auxiliary buffers (real Open3D).

The scene is analytic (a room corner: floor, back wall, left wall, a box and a sphere) and its
depth maps are ray-cast in NumPy, so every expected value is known exactly.
"""

import numpy as np
import open3d.core as o3c
import pytest
from scipy.ndimage import maximum_filter, minimum_filter
from scipy.spatial import cKDTree

from arlight.core.camera import PinholeCamera
from arlight.pipeline.aux_buffers import OrthoBuffer, aux_buffer_poses, render_orthographic
from arlight.pipeline.config import Config
from arlight.pipeline.ray_refine import REFINE_MAX_STEP_VOXELS, refine_ray_cast
from arlight.pipeline.reconstruction import SurfaceOutput, VolumeReconstruction

# ------------------------------------------------------------------ analytic scene
# World axes as the first camera's: x right, y down, z forward. Outward normals.
FLOOR_Y = 1.0  # plane y = 1, normal -y
BACK_Z = 3.0  # plane z = 3, normal -z
LEFT_X = -1.2  # plane x = -1.2, normal +x
BOX_CENTRE = np.array([0.5, 0.75, 1.8])  # on the floor
BOX_HALF = np.array([0.25, 0.25, 0.25])
SPHERE_CENTRE = np.array([-0.45, 0.8, 1.5])
SPHERE_RADIUS = 0.2


def trace_scene(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First front-facing hit of rays o + t d: t (N,) (inf = miss) and outward normals (N, 3)."""
    d = np.atleast_2d(np.asarray(directions, np.float64))
    o = np.broadcast_to(np.asarray(origins, np.float64), d.shape)
    n = len(d)
    best = np.full(n, np.inf)
    normal = np.zeros((n, 3))

    def offer(t, nrm):
        better = np.isfinite(t) & (t > 1e-9) & (t < best)
        best[better] = t[better]
        normal[better] = np.broadcast_to(nrm, (n, 3))[better]

    with np.errstate(divide="ignore", invalid="ignore"):
        # planes only from their front side
        offer(np.where(d[:, 1] > 0, (FLOOR_Y - o[:, 1]) / d[:, 1], np.inf), [0.0, -1.0, 0.0])
        offer(np.where(d[:, 2] > 0, (BACK_Z - o[:, 2]) / d[:, 2], np.inf), [0.0, 0.0, -1.0])
        offer(np.where(d[:, 0] < 0, (LEFT_X - o[:, 0]) / d[:, 0], np.inf), [1.0, 0.0, 0.0])
        lo = (BOX_CENTRE - BOX_HALF - o) / d
        hi = (BOX_CENTRE + BOX_HALF - o) / d
        t_near = np.minimum(lo, hi).max(axis=1)
        t_far = np.maximum(lo, hi).min(axis=1)
        axis = np.minimum(lo, hi).argmax(axis=1)
        box_normal = np.zeros((n, 3))
        box_normal[np.arange(n), axis] = -np.sign(d[np.arange(n), axis])
        offer(np.where(t_near <= t_far, t_near, np.inf), box_normal)
        oc = o - SPHERE_CENTRE
        b = np.sum(d * oc, axis=1)
        a = np.sum(d * d, axis=1)
        disc = b * b - a * (np.sum(oc * oc, axis=1) - SPHERE_RADIUS**2)
        t_sphere = np.where(disc > 0, (-b - np.sqrt(disc)) / a, np.inf)
        offer(t_sphere, (o + t_sphere[:, None] * d - SPHERE_CENTRE) / SPHERE_RADIUS)
    return best, normal


def render_scene(camera: PinholeCamera, world_from_cam: np.ndarray):
    """Depth (H, W) float32 along the optical axis (0 = none) and camera-frame normals."""
    rays_cam = camera.unproject(np.ones((camera.height, camera.width), np.float32))
    rays_world = rays_cam.reshape(-1, 3).astype(np.float64) @ world_from_cam[:3, :3].T
    t, normal = trace_scene(world_from_cam[:3, 3], rays_world)  # t = depth: rays have z = 1
    depth = np.where(np.isfinite(t), t, 0.0).reshape(camera.height, camera.width)
    normal_cam = (normal @ world_from_cam[:3, :3]).reshape(camera.height, camera.width, 3)
    return depth.astype(np.float32), normal_cam.astype(np.float32)


def rotation(yaw: float = 0.0, pitch: float = 0.0) -> np.ndarray:
    """Rotation about the camera's y (yaw, radians), then tilting the view down by `pitch`."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    r_yaw = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_pitch = np.array([[1, 0, 0], [0, cp, sp], [0, -sp, cp]])
    return r_yaw @ r_pitch


def make_pose(rot: np.ndarray, position) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = position
    return pose


def smooth_mask(depth: np.ndarray, normals: np.ndarray, radius: int = 2) -> np.ndarray:
    """Pixels whose (2 radius + 1)^2 neighbourhood has no depth or normal discontinuity."""
    size = 2 * radius + 1
    ok = minimum_filter(depth, size) > 0
    ok &= (maximum_filter(depth, size) - minimum_filter(depth, size)) < 0.05
    for k in range(3):
        ok &= (maximum_filter(normals[..., k], size) - minimum_filter(normals[..., k], size)) < 0.05
    return ok


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


CAMERA = PinholeCamera.kinect_v1(320, 240)
COLOR = np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8)
PITCH = np.deg2rad(20.0)
POSES = [
    make_pose(rotation(yaw=0.05 * k - 0.1, pitch=PITCH), [0.05 * k, 0.0, 0.02 * k])
    for k in range(4)
]
LIGHT = np.array([0.3, -0.9, 0.3]) / np.linalg.norm([0.3, -0.9, 0.3])


def config(**overrides) -> Config:
    return Config.from_preset("full", volume_resolution=128, **overrides)


@pytest.fixture(scope="module")
def fused():
    """Four frames fused with known poses; outputs of every frame (aux every frame)."""
    cfg = config(aux_update_interval=1)
    recon = VolumeReconstruction.from_config(cfg, CAMERA)
    outputs = []
    for pose in POSES:
        depth, _ = render_scene(CAMERA, pose)
        outputs.append(recon.process(COLOR, depth, pose, light_direction_world=LIGHT))
    return recon, outputs


# ------------------------------------------------------------------ G_v with known poses
class TestGeometryBuffer:
    def test_shapes_dtypes_and_pose(self, fused):
        _, outputs = fused
        out = outputs[-1]
        assert isinstance(out, SurfaceOutput)
        np.testing.assert_array_equal(out.pose, POSES[-1])
        assert out.depth_volume_m.shape == (CAMERA.height, CAMERA.width)
        assert out.depth_volume_m.dtype == np.float32
        assert out.normals_volume.shape == (CAMERA.height, CAMERA.width, 3)
        assert out.normals_volume.dtype == np.float32
        assert out.tracking_ok
        assert set(out.timings_ms) == {"Reconstruct", "Surface"}
        valid = out.depth_volume_m > 0
        assert np.all(out.normals_volume[~valid] == 0)
        norms = np.linalg.norm(out.normals_volume[valid], axis=-1)
        assert np.mean(np.abs(norms - 1) < 1e-3) > 0.99

    def test_depth_matches_analytic_within_voxels(self, fused):
        recon, outputs = fused
        voxel = recon.params.voxel_size_m
        truth, normals = render_scene(CAMERA, POSES[-1])
        d_v = outputs[-1].depth_volume_m
        inner = smooth_mask(truth, normals)
        assert np.mean(d_v[inner] > 0) > 0.8  # the last view is mostly covered by V
        both = inner & (d_v > 0)
        err = np.abs(d_v - truth)[both]
        assert np.percentile(err, 99) < 0.75 * voxel
        assert err.max() < 3.0 * voxel
        # no systematic offset (Open3D's nearest-sample and half-pixel biases compensated)
        assert abs(np.median((d_v - truth)[both])) < 0.1 * voxel

    def test_normals_match_analytic(self, fused):
        _, outputs = fused
        truth, normals = render_scene(CAMERA, POSES[-1])
        out = outputs[-1]
        both = smooth_mask(truth, normals) & (out.depth_volume_m > 0)
        ang = angle_deg(out.normals_volume[both], normals[both])
        assert np.median(ang) < 4.0
        assert np.percentile(ang, 90) < 10.0

    @pytest.mark.parametrize("subsample", [2, 3])
    def test_subsampled_cast_is_the_block_sample_of_the_full_one(self, fused, subsample):
        """surface_subsample s: every pixel carries the depth cast through the centre of its
        s x s block, so on smooth surfaces it is the full-resolution depth within what the
        surface slope moves over a block (a voxel here), and pixel (s i + s // 2, s j + s //
        2) sees what the full cast sees there (odd s: the same ray; Open3D's marching starts
        from a range map of the image's own size, so some rays stop a refinement step apart)."""
        recon, _ = fused
        voxel = recon.params.voxel_size_m
        truth, normals = render_scene(CAMERA, POSES[-1])
        full, _ = recon._volume.ray_cast(POSES[-1])
        sub, n_sub = recon._volume.ray_cast(POSES[-1], subsample)
        assert sub.shape == full.shape and n_sub.shape == (*full.shape, 3)
        inner = smooth_mask(truth, normals) & (full > 0) & (sub > 0)
        assert np.mean((sub > 0)[full > 0]) > 0.97
        assert np.median(np.abs(sub - full)[inner]) < 0.5 * voxel
        assert np.percentile(np.abs(sub - full)[inner], 95) < 2.0 * voxel
        if subsample % 2:
            c = subsample // 2
            centres = full[c::subsample, c::subsample]
            picked = sub[c::subsample, c::subsample]
            ok = (
                (centres > 0)
                & (picked > 0)
                & smooth_mask(truth, normals)[c::subsample, c::subsample]
            )
            diff = np.abs(picked[ok] - centres[ok])
            assert np.mean(diff < 1e-4) > 0.5  # 70 % here: the same depth
            # the others within the full cast's own error (its p99 against truth: 0.3 voxel)
            assert np.percentile(diff, 99) < 0.5 * voxel

    def test_first_frame_already_gives_depth(self, fused):
        _, outputs = fused
        truth, _ = render_scene(CAMERA, POSES[0])
        assert np.mean(outputs[0].depth_volume_m[truth > 0] > 0) > 0.8


@pytest.fixture(scope="module")
def ray_cast(fused):
    """Open3D's ray cast of the fused scene into the last view, as refine_ray_cast takes it."""
    recon, _ = fused
    grid, c, pose = recon.voxel_grid, recon.params, POSES[-1]
    hashmap = grid.hashmap()
    blocks = hashmap.key_tensor()[hashmap.active_buf_indices().to(o3c.int64)]
    result = grid.ray_cast(
        blocks,
        o3c.Tensor(CAMERA.matrix),
        o3c.Tensor(np.linalg.inv(pose)),
        CAMERA.width,
        CAMERA.height,
        ["depth", "index", "mask", "interp_ratio"],
        1.0,
        c.depth_min_m,
        c.depth_max_m,
        3.0,
        c.sdf_trunc_voxels,
    )
    return (
        result["depth"].numpy()[..., 0],
        grid.attribute("tsdf").numpy().reshape(-1),
        result["index"].numpy(),
        result["mask"].numpy(),
        result["interp_ratio"].numpy(),
        pose,
        CAMERA,
        c.voxel_size_m,
    )


class TestRefineRayCast:
    """The Numba refinement of Open3D's ray cast against a plain NumPy oracle."""

    @staticmethod
    def reference(raw, source, index, mask, ratio, pose, camera, voxel):
        depth = np.zeros(raw.shape, np.float32)
        normals = np.zeros(raw.shape + (3,), np.float32)
        hit = raw > 0
        v, u = np.nonzero(hit)
        t = raw[hit].astype(np.float64)
        m = mask[hit]
        r = ratio[hit].astype(np.float64)
        values = np.where(m, source[index[hit]], 0.0).reshape(-1, 2, 2, 2)  # [n, dz, dy, dx]
        fx, fy, fz = (
            r[:, [1, 3, 5, 7]].sum(1),
            r[:, [2, 3, 6, 7]].sum(1),
            r[:, [4, 5, 6, 7]].sum(1),
        )
        wx, wy, wz = (np.stack([1 - f, f], axis=1) for f in (fx, fy, fz))
        phi = np.sum(r * values.reshape(-1, 8), axis=1)
        grad = np.stack(
            [
                np.einsum("nzy,nz,ny->n", values[..., 1] - values[..., 0], wz, wy),
                np.einsum("nzx,nz,nx->n", values[:, :, 1] - values[:, :, 0], wz, wx),
                np.einsum("nyx,ny,nx->n", values[:, 1] - values[:, 0], wy, wx),
            ],
            axis=1,
        )
        rays = (
            np.stack(
                [(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(t)], axis=1
            )
            @ pose[:3, :3].T
        )
        slope = np.sum(grad * rays, axis=1) / voxel
        with np.errstate(divide="ignore", invalid="ignore"):
            step = -phi / slope
        ok = m.all(axis=1) & (slope < 0) & (np.abs(step) <= REFINE_MAX_STEP_VOXELS * voxel)
        t[ok] += step[ok]
        depth[hit] = t
        norm = np.linalg.norm(grad, axis=1, keepdims=True)
        normals[hit] = np.where(norm > 0, grad @ pose[:3, :3] / np.maximum(norm, 1e-30), 0.0)
        return depth, normals

    def test_matches_numpy_reference(self, ray_cast):
        depth, normals = refine_ray_cast(*ray_cast)
        ref_depth, ref_normals = self.reference(*ray_cast)
        np.testing.assert_allclose(depth, ref_depth, atol=1e-5)
        np.testing.assert_allclose(normals, ref_normals, atol=1e-4)

    def test_removes_the_ray_casters_bias(self, ray_cast):
        raw, voxel = ray_cast[0], ray_cast[-1]
        depth, _ = refine_ray_cast(*ray_cast)
        truth, normals = render_scene(CAMERA, POSES[-1])
        both = smooth_mask(truth, normals) & (raw > 0)
        raw_err, err = (np.abs(d - truth)[both] for d in (raw, depth))
        assert np.percentile(err, 90) < 0.5 * np.percentile(raw_err, 90)
        assert np.percentile(err, 90) < 0.25 * voxel

    def test_no_hit_stays_empty(self, ray_cast):
        raw = np.zeros_like(ray_cast[0])
        raw[0, 0] = np.nan
        depth, normals = refine_ray_cast(raw, *ray_cast[1:])
        assert not depth.any() and not normals.any()


# ------------------------------------------------------------------ tracking
class TestTracking:
    @staticmethod
    def true_poses(n: int = 5) -> list[np.ndarray]:
        return [
            make_pose(
                rotation(yaw=np.deg2rad(0.6) * k, pitch=PITCH + np.deg2rad(0.3) * k),
                [0.01 * k, -0.005 * k, 0.01 * k],
            )
            for k in range(n)
        ]

    def test_relative_poses_match_truth(self):
        recon = VolumeReconstruction.from_config(config(aux_buffers=False), CAMERA)
        truth = self.true_poses()
        first_inv = np.linalg.inv(truth[0])
        for k, pose in enumerate(truth):
            depth, _ = render_scene(CAMERA, pose)
            out = recon.process(COLOR, depth, None)
            assert out.tracking_ok
            if k == 0:
                np.testing.assert_array_equal(out.pose, np.eye(4))
            err = np.linalg.inv(first_inv @ pose) @ out.pose
            assert np.linalg.norm(err[:3, 3]) < 0.01, k
            cos_angle = np.clip((np.trace(err[:3, :3]) - 1) / 2, -1.0, 1.0)
            assert np.degrees(np.arccos(cos_angle)) < 1.0, k

    def test_unrelated_frame_fails_and_keeps_pose(self):
        recon = VolumeReconstruction.from_config(config(aux_buffers=False), CAMERA)
        truth = self.true_poses(2)
        for pose in truth:
            out = recon.process(COLOR, render_scene(CAMERA, pose)[0], None)
        pose_before, blocks_before = out.pose.copy(), recon.num_blocks
        wall = np.full((CAMERA.height, CAMERA.width), 0.4, np.float32)  # something else
        out = recon.process(COLOR, wall, None)
        assert not out.tracking_ok
        np.testing.assert_array_equal(out.pose, pose_before)
        assert recon.num_blocks == blocks_before  # not fused at a wrong pose
        # the next good frame is tracked again against the unchanged model
        out = recon.process(COLOR, render_scene(CAMERA, truth[-1])[0], None)
        assert out.tracking_ok
        np.testing.assert_allclose(out.pose, pose_before, atol=5e-3)

    def test_failures_say_why(self):
        recon = VolumeReconstruction.from_config(config(aux_buffers=False), CAMERA)
        for pose in self.true_poses(2):
            out = recon.process(COLOR, render_scene(CAMERA, pose)[0], None)
        assert out.tracking.ok and out.tracking.reason == ""
        wall = np.full((CAMERA.height, CAMERA.width), 0.4, np.float32)
        out = recon.process(COLOR, wall, None)
        assert not out.tracking.ok and not out.tracking_ok
        assert out.tracking.reason  # ICP error text, too few inliers or an implausible jump
        empty = recon.process(COLOR, np.zeros_like(wall), None)
        assert "too little depth" in empty.tracking.reason
        assert empty.tracking.to_dict() == {"ok": False, "reason": empty.tracking.reason}

    def test_missing_depth_while_tracking_keeps_pose_and_model(self):
        recon = VolumeReconstruction.from_config(config(aux_buffers=False), CAMERA)
        pose = self.true_poses(1)[0]
        recon.process(COLOR, render_scene(CAMERA, pose)[0], None)
        out = recon.process(COLOR, np.zeros((CAMERA.height, CAMERA.width), np.float32), None)
        assert not out.tracking_ok
        np.testing.assert_array_equal(out.pose, np.eye(4))
        assert np.mean(out.depth_volume_m > 0) > 0.5  # D_v still shows V


# ------------------------------------------------------------------ auxiliary buffers
class TestAuxBufferPoses:
    def test_axes_and_planes_as_documented(self):
        cam_pose = make_pose(rotation(yaw=0.3, pitch=0.2), [0.1, -0.2, 0.3])
        rot, position = cam_pose[:3, :3], cam_pose[:3, 3]
        ex, ey, ez = rot.T
        poses = aux_buffer_poses(cam_pose, 1.5, 4.0, LIGHT)
        assert list(poses) == ["left", "right", "top", "light"]
        centre = position + 1.5 * ez
        expected = {
            "left": (-ez, ey, ex),
            "right": (ez, ey, -ex),
            "top": (ex, -ez, ey),
            "light": (None, None, -LIGHT),
        }
        for name, t in poses.items():
            np.testing.assert_allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-12)
            assert np.linalg.det(t[:3, :3]) == pytest.approx(1.0)
            for axis, want in enumerate(expected[name]):
                if want is not None:
                    np.testing.assert_allclose(t[:3, axis], want, atol=1e-12)
            # image plane centre: half the extent back from the centre, against the view
            np.testing.assert_allclose(t[:3, 3], centre - 2.0 * t[:3, 2], atol=1e-12)

    def test_pixel_convention(self):
        world_from_buffer = make_pose(rotation(yaw=0.4), [1.0, 2.0, 3.0])
        buf = OrthoBuffer(world_from_buffer, np.zeros((5, 5), np.float32), 0.1, "top")
        local = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 2.0], [0.0, -0.2, 1.0]])
        world = local @ world_from_buffer[:3, :3].T + world_from_buffer[:3, 3]
        uv, depth = buf.project(world)
        np.testing.assert_allclose(uv, [[2, 2], [3, 2], [2, 0]], atol=1e-9)
        np.testing.assert_allclose(depth, [0.0, 2.0, 1.0], atol=1e-9)


class TestAuxBuffers:
    def buffers(self, out) -> dict[str, OrthoBuffer]:
        return {b.name: b for b in out.aux_buffers}

    def test_names_sizes_and_light(self, fused):
        recon, outputs = fused
        bufs = self.buffers(outputs[-1])
        assert list(bufs) == ["left", "right", "top", "light"]
        res = recon.aux_params.aux_resolution
        for b in bufs.values():
            assert b.depth_m.shape == (res, res) and b.depth_m.dtype == np.float32
            assert b.pixel_size_m == pytest.approx(recon.aux_params.aux_extent_m / res)
            assert np.all(b.depth_m >= 0) and np.all(b.depth_m <= recon.aux_params.aux_extent_m)
        np.testing.assert_allclose(bufs["light"].world_from_buffer[:3, 2], -LIGHT, atol=1e-12)

    def test_box_top_at_the_right_depth_in_top_buffer(self, fused):
        recon, outputs = fused
        top = self.buffers(outputs[-1])["top"]
        # points on the box top, away from its edges (seen by the camera from above)
        s = np.linspace(-0.15, 0.15, 7)
        gx, gz = np.meshgrid(BOX_CENTRE[0] + s, BOX_CENTRE[2] + s)
        points = np.stack(
            [gx.ravel(), np.full(gx.size, BOX_CENTRE[1] - BOX_HALF[1]), gz.ravel()], axis=-1
        )
        uv, depth = top.project(points)
        u, v = np.rint(uv).astype(int).T
        stored = top.depth_m[v, u]
        assert np.all(stored > 0)
        # the box top is tilted in the buffer by the camera pitch: one pixel spans this depth
        slope = top.pixel_size_m * np.tan(PITCH)
        np.testing.assert_allclose(stored, depth, atol=2 * recon.params.voxel_size_m + slope)

    def test_floor_seen_from_above_matches_analytic(self, fused):
        recon, outputs = fused
        top = self.buffers(outputs[-1])["top"]
        res = top.resolution
        grid = (np.arange(res) - (res - 1) / 2) * top.pixel_size_m
        x, y = np.meshgrid(grid, grid)
        local = np.stack([x, y, np.zeros_like(x)], axis=-1).reshape(-1, 3)
        t = top.world_from_buffer
        t_hit, _ = trace_scene(local @ t[:3, :3].T + t[:3, 3], np.tile(t[:3, 2], (res * res, 1)))
        truth = t_hit.reshape(res, res)
        valid = top.depth_m > 0
        assert valid.mean() > 0.1
        err = np.abs(top.depth_m - truth)[valid]
        slope = top.pixel_size_m * np.tan(PITCH)
        assert np.median(err) < recon.params.voxel_size_m
        # where V knew the first surface (most pixels), it is where the scene has it
        assert np.mean(err < 2 * recon.params.voxel_size_m + slope) > 0.9

    def test_wall_seen_from_behind_is_transparent(self, fused):
        recon, outputs = fused
        bufs = self.buffers(outputs[-1])
        tol = 2 * recon.params.voxel_size_m

        def on_left_wall(b: OrthoBuffer) -> int:
            res = b.resolution
            grid = (np.arange(res) - (res - 1) / 2) * b.pixel_size_m
            x, y = np.meshgrid(grid, grid)
            local = np.stack([x, y, b.depth_m], axis=-1)[b.depth_m > 0]
            world = local @ b.world_from_buffer[:3, :3].T + b.world_from_buffer[:3, 3]
            on_wall = np.abs(world[:, 0] - LEFT_X) < tol
            off_edges = (world[:, 1] < FLOOR_Y - tol) & (world[:, 2] < BACK_Z - tol)
            return int(np.sum(on_wall & off_edges))

        # the left wall faces +x: the right buffer sees it, the left buffer looks through it
        assert on_left_wall(bufs["right"]) > 50
        assert on_left_wall(bufs["left"]) == 0

    def test_cached_between_updates(self):
        recon = VolumeReconstruction.from_config(config(aux_update_interval=3), CAMERA)
        outs = [recon.process(COLOR, render_scene(CAMERA, p)[0], p) for p in POSES]
        first = [b.world_from_buffer for b in outs[0].aux_buffers]
        for out in outs[1:3]:
            for b, t in zip(out.aux_buffers, first, strict=True):
                assert np.array_equal(b.world_from_buffer, t)  # still the frame-0 buffers
        assert not np.array_equal(outs[3].aux_buffers[0].world_from_buffer, first[0])
        assert [b.name for b in outs[0].aux_buffers] == ["left", "right", "top"]

    def test_disabled(self):
        recon = VolumeReconstruction.from_config(config(aux_buffers=False), CAMERA)
        out = recon.process(COLOR, render_scene(CAMERA, POSES[0])[0], POSES[0], LIGHT)
        assert out.aux_buffers == []


class TestRenderOrthographic:
    def test_known_points_and_z_buffer(self):
        points = np.array(
            [
                [0.0, 0.0, 1.0],  # centre pixel (2, 2)
                [0.0, 0.0, 0.5],  # same pixel, nearer: wins
                [0.1, -0.2, 2.0],  # pixel u = 3, v = 0
                [0.0, 0.0, -1.0],  # behind the image plane: ignored
                [0.3, 0.0, 1.0],  # outside the image: ignored
                [-0.2, 0.2, 9.0],  # beyond max depth: ignored
            ]
        )
        depth = render_orthographic(points, np.eye(4), 5, 0.1, max_depth_m=5.0)
        expected = np.zeros((5, 5), np.float32)
        expected[2, 2] = 0.5
        expected[0, 3] = 2.0
        np.testing.assert_array_equal(depth, expected)

    def test_moved_buffer(self):
        world_from_buffer = make_pose(rotation(yaw=np.pi / 2), [1.0, 0.0, 0.0])  # looks +x
        depth = render_orthographic(np.array([[3.0, 0.0, 0.0]]), world_from_buffer, 3, 0.5)
        assert depth[1, 1] == pytest.approx(2.0)
        assert np.count_nonzero(depth) == 1


class TestSurfacePoints:
    def test_stride_one_equals_open3d_extraction(self, fused):
        recon, _ = fused
        points, gradients = recon.surface_points(1)
        threshold = min(recon.frames_integrated, 3.0)
        oracle = recon.voxel_grid.extract_point_cloud(threshold - 1e-3)
        expected = oracle.point.positions.numpy()
        assert len(points) == len(expected) > 1000
        order = np.lexsort(points.T)
        np.testing.assert_allclose(points[order], expected[np.lexsort(expected.T)], atol=1e-5)
        # gradients point to free space, as Open3D's normals do
        g = gradients / np.linalg.norm(gradients, axis=1, keepdims=True)
        _, nearest = cKDTree(expected).query(points)
        assert np.median(np.sum(g * oracle.point.normals.numpy()[nearest], axis=1)) > 0.95

    def test_coarser_stride_stays_on_the_surface(self, fused):
        recon, _ = fused
        fine, _ = recon.surface_points(1)
        coarse, _ = recon.surface_points(2)
        dist, _ = cKDTree(fine).query(coarse)
        assert len(coarse) < len(fine) / 2
        assert np.percentile(dist, 99) < recon.params.voxel_size_m

    def test_stride_must_divide_block(self, fused):
        recon, _ = fused
        with pytest.raises(ValueError, match="stride"):
            recon.surface_points(3)


class TestDeterminism:
    def test_same_frames_same_results(self):
        """The same frames give the same results, tracking included (docs/architecture.md)."""
        runs = []
        for _ in range(2):
            recon = VolumeReconstruction.from_config(config(aux_update_interval=2), CAMERA)
            runs.append(
                [recon.process(COLOR, render_scene(CAMERA, p)[0], None, LIGHT) for p in POSES]
            )
        for a, b in zip(*runs, strict=True):
            np.testing.assert_array_equal(a.pose, b.pose)
            np.testing.assert_array_equal(a.depth_volume_m, b.depth_volume_m)
            np.testing.assert_array_equal(a.normals_volume, b.normals_volume)
            for x, y in zip(a.aux_buffers, b.aux_buffers, strict=True):
                np.testing.assert_array_equal(x.depth_m, y.depth_m)


# ------------------------------------------------------------------ robustness
class TestBadInput:
    @pytest.mark.parametrize("fill", [0.0, np.nan])
    def test_missing_depth_gives_empty_surface(self, fill):
        recon = VolumeReconstruction.from_config(config(), CAMERA)
        depth = np.full((CAMERA.height, CAMERA.width), fill, np.float32)
        for pose in (None, None, POSES[0]):
            out = recon.process(COLOR, depth, pose, LIGHT)
            assert np.all(out.depth_volume_m == 0)
            assert np.all(out.normals_volume == 0)
            assert all(np.all(b.depth_m == 0) for b in out.aux_buffers)
        assert recon.num_blocks == 0

    def test_out_of_range_and_inf_depth_ignored(self):
        recon = VolumeReconstruction.from_config(config(), CAMERA)
        depth = np.full((CAMERA.height, CAMERA.width), 9.0, np.float32)  # beyond depth_max
        depth[:, :10] = np.inf
        depth[:, 10:20] = 0.05  # nearer than depth_min
        out = recon.process(COLOR, depth, None)
        assert np.all(out.depth_volume_m == 0)

    def test_first_valid_frame_after_empty_ones_starts_the_map(self):
        recon = VolumeReconstruction.from_config(config(aux_buffers=False), CAMERA)
        recon.process(COLOR, np.zeros((CAMERA.height, CAMERA.width), np.float32), None)
        out = recon.process(COLOR, render_scene(CAMERA, POSES[0])[0], None)
        assert out.tracking_ok
        assert np.mean(out.depth_volume_m > 0) > 0.5

    @pytest.mark.parametrize(
        "field, kwargs, match",
        [
            ("depth", {"depth_m": np.zeros((10, 10), np.float32)}, "depth_m"),
            ("depth", {"depth_m": np.zeros((CAMERA.height, CAMERA.width), np.uint16)}, "depth_m"),
            ("color", {"color_rgb_u8": np.zeros((CAMERA.height, CAMERA.width, 3))}, "color_rgb_u8"),
            ("color", {"color_rgb_u8": np.zeros((10, 10, 3), np.uint8)}, "color_rgb_u8"),
            ("pose", {"pose": np.eye(3)}, "pose"),
            ("pose", {"pose": np.full((4, 4), np.nan)}, "pose"),
            ("light", {"light_direction_world": np.zeros(3)}, "light_direction_world"),
        ],
    )
    def test_invalid_arguments_raise(self, field, kwargs, match):
        recon = VolumeReconstruction.from_config(config(), CAMERA)
        args = {
            "color_rgb_u8": COLOR,
            "depth_m": np.zeros((CAMERA.height, CAMERA.width), np.float32),
            "pose": None,
        }
        args.update(kwargs)
        with pytest.raises(ValueError, match=match):
            recon.process(**args)

    @pytest.mark.parametrize("size", [(100, 75), (81, 61), (320, 240)])
    def test_image_borders_reach_the_volume(self, size):
        """Open3D samples every 4th pixel to allocate blocks and reads its ray-casting range
        map past its end for sizes that are not multiples of 8 (holes, or a hang); the last
        rows and columns must still get D_v."""
        camera = PinholeCamera.kinect_v1(*size)
        recon = VolumeReconstruction.from_config(config(aux_buffers=False), camera)
        plane = np.full((size[1], size[0]), 1.5, np.float32)  # facing the camera
        for _ in range(2):
            out = recon.process(np.zeros((size[1], size[0], 3), np.uint8), plane, np.eye(4))
        valid = out.depth_volume_m > 0
        assert valid[1:-1, 1:-1].mean() > 0.95
        assert valid[-3:-1, 1:-1].mean() > 0.9 and valid[1:-1, -3:-1].mean() > 0.9
        assert np.abs(out.depth_volume_m[valid] - 1.5).max() < 0.25 * recon.params.voxel_size_m

    def test_without_volume(self):
        recon = VolumeReconstruction.from_config(config(use_volume=False), CAMERA)
        out = recon.process(COLOR, render_scene(CAMERA, POSES[1])[0], POSES[1])
        np.testing.assert_array_equal(out.pose, POSES[1])
        assert np.all(out.depth_volume_m == 0) and out.aux_buffers == []

    @pytest.mark.skipif(o3c.cuda.is_available(), reason="CUDA is available here")
    def test_cuda_requested_without_cuda(self):
        with pytest.raises(RuntimeError, match="CUDA"):
            VolumeReconstruction.from_config(config(device="CUDA:0"), CAMERA)


@pytest.mark.skipif(not o3c.cuda.is_available(), reason="needs Open3D with a CUDA device")
class TestCuda:
    def test_cuda_matches_cpu(self):
        outs = {}
        for device in ("CPU:0", "CUDA:0"):
            recon = VolumeReconstruction.from_config(config(device=device), CAMERA)
            for pose in POSES[:2]:
                outs[device] = recon.process(COLOR, render_scene(CAMERA, pose)[0], pose)
        cpu, gpu = outs["CPU:0"], outs["CUDA:0"]
        both = (cpu.depth_volume_m > 0) & (gpu.depth_volume_m > 0)
        assert np.mean(both) > 0.5
        assert np.percentile(np.abs(cpu.depth_volume_m - gpu.depth_volume_m)[both], 99) < 1e-3
        for a, b in zip(cpu.aux_buffers, gpu.aux_buffers, strict=True):
            assert np.mean(np.abs(a.depth_m - b.depth_m) < 1e-3) > 0.99


def test_unique_block_keys_matches_numpy_rows_including_negative_and_far_blocks():
    """The packed-key unique gives np.unique(axis=0)'s rows and order, for coordinates of
    both signs up to the packing's limit (+-2^20 blocks)."""
    from arlight.pipeline.volume import unique_block_keys

    rng = np.random.default_rng(3)
    keys = rng.integers(-50, 50, (5000, 3)).astype(np.int32)
    keys[:10] = [[(1 << 20) - 1, -(1 << 20), 0]] * 10  # repeated, at the limits
    np.testing.assert_array_equal(unique_block_keys(keys), np.unique(keys, axis=0))
    assert unique_block_keys(keys).dtype == np.int32


@pytest.mark.parametrize(
    ("width", "asked", "used"), [(80, 2, 1), (320, 2, 1), (640, 2, 2), (1280, 4, 4), (960, 4, 3)]
)
def test_surface_subsample_keeps_the_cast_320_columns_wide(width, asked, used):
    from arlight.pipeline.reconstruction import surface_subsample

    camera = PinholeCamera.kinect_v1(width, width * 3 // 4)
    assert (
        surface_subsample(Config.from_preset("fast", surface_subsample=asked).volume, camera)
        == used
    )


def test_upsample_depth_interpolates_smooth_surfaces_and_keeps_edges():
    """A plane tilted in depth comes back bilinear (exact for a linear field between the
    coarse samples); across a 1 m step each pixel keeps its own block's depth."""
    from arlight.pipeline.volume import upsample_depth

    coarse = np.tile(np.linspace(2.0, 2.3, 8, dtype=np.float32), (6, 1))
    full = upsample_depth(coarse, 2, (12, 16))
    x = (np.arange(16) + 0.5) / 2 - 0.5
    expected = np.interp(np.clip(x, 0, 7), np.arange(8), coarse[0])
    np.testing.assert_allclose(full[5], expected, atol=1e-6)
    step = np.full((6, 8), 2.0, np.float32)
    step[:, 4:] = 3.0
    out = upsample_depth(step, 2, (12, 16))
    assert set(np.unique(out).tolist()) == {2.0, 3.0}  # nothing in between
    np.testing.assert_array_equal(out[:, :8], 2.0)
    hole = step.copy()
    hole[2, 2] = 0.0
    assert upsample_depth(hole, 2, (12, 16))[4, 4] == 0.0  # its own block: missing


@pytest.mark.parametrize("seed", range(12))
def test_upsample_depth_kernel_equals_its_numpy_oracle(seed):
    """The parallel pass gives the NumPy expressions' float32 values bit for bit: smooth
    ramps, random depths with holes, factors 1-4, shapes not a multiple of the factor."""
    from arlight.pipeline.volume import upsample_depth, upsample_depth_numpy

    rng = np.random.default_rng(seed)
    factor = int(rng.integers(1, 5))
    hc, wc = (int(n) for n in rng.integers(1, 40, 2))
    if seed % 2:
        coarse = (1.0 + np.cumsum(np.full((hc, wc), 0.004), axis=1)).astype(np.float32)
    else:
        coarse = (rng.random((hc, wc)) * 3.0 + 0.5).astype(np.float32)
    coarse[rng.random((hc, wc)) < 0.1] = 0.0
    shape = (hc * factor - int(rng.integers(0, factor)), wc * factor - int(rng.integers(0, factor)))
    np.testing.assert_array_equal(
        upsample_depth(coarse, factor, shape), upsample_depth_numpy(coarse, factor, shape)
    )
