"""Built-in synthetic scene: ground truth, poses, image and depth formation, determinism."""

import math

import numpy as np
import pytest

from arlight.core.camera import PinholeCamera
from arlight.core.checks import depth_metres
from arlight.evaluation import angular_error_deg
from arlight.pipeline import sh
from arlight.sources import synthetic


def _world_points(seq, i):
    """World points (H, W, 3) of frame i's clean depth (sky pixels land on the camera)."""
    pose = seq.frames[i].pose
    cam_points = seq.camera.unproject(seq.depth_gt[i]).astype(np.float64)
    return cam_points @ pose[:3, :3].T + pose[:3, 3]


@pytest.fixture(scope="module")
def clean():
    return synthetic.make_sequence(num_frames=4, width=320, height=240, seed=3, sensor_noise=False)


@pytest.fixture(scope="module")
def noisy():
    return synthetic.make_sequence(num_frames=3, width=320, height=240, seed=3)


class TestGroundTruth:
    def test_dominant_direction_is_that_of_the_sh(self, clean):
        for i, pose in enumerate(f.pose for f in clean.frames):
            world = sh.dominant_direction(clean.sh_world[i])
            np.testing.assert_allclose(clean.dominant_direction_world[i], world, atol=1e-12)
            np.testing.assert_allclose(
                clean.dominant_direction_camera[i], pose[:3, :3].T @ world, atol=1e-12
            )

    def test_luminance_sh_is_weighted_sum_of_channels(self, clean):
        np.testing.assert_allclose(
            clean.sh_world[0], synthetic.LUMINANCE_RGB @ clean.sh_rgb_world[0], atol=1e-12
        )
        assert clean.sh_world[0].shape == (16,)

    def test_quadratic_closed_form_matches_quadrature(self):
        rng = np.random.default_rng(5)
        q = rng.normal(size=(3, 3))
        q = q + q.T
        a, b = 0.7, rng.normal(size=3)

        def f(d):
            return a + d @ b + np.einsum("ki,ij,kj->k", d, q, d)

        numeric = sh.project(f, 4, samples=60000)
        np.testing.assert_allclose(synthetic._quadratic_sh(a, b, q), numeric, atol=2e-4)

    def test_sky_sh_matches_numerical_projection(self):
        light = synthetic.make_lighting(1.1, math.radians(40.0))
        numeric = sh.project(light.sky_radiance, 4, samples=60000)
        np.testing.assert_allclose(light.sky_sh_rgb(), numeric, atol=2e-4)

    def test_environment_is_sky_plus_delta_sun(self):
        light = synthetic.make_lighting(0.4, math.radians(35.0))
        sun = light.sh_rgb() - light.sky_sh_rgb()
        expected = np.outer(light.sun_rgb, sh.directional_light(light.sun_direction, 1.0, 4))
        np.testing.assert_allclose(sun, expected, atol=1e-12)

    def test_sky_is_positive_brighter_up_and_dark_below(self):
        light = synthetic.make_lighting(2.0, math.radians(45.0))
        dirs = sh.fibonacci_sphere(5000)
        lum = light.sky_radiance(dirs) @ synthetic.LUMINANCE_RGB
        assert lum.min() > 0
        up = light.sky_radiance(np.array([[0.0, 1.0, 0.0]])) @ synthetic.LUMINANCE_RGB
        horizon = light.sky_radiance(np.array([[1.0, 0.0, 0.0]])) @ synthetic.LUMINANCE_RGB
        assert up[0] > horizon[0] > lum[dirs[:, 1] < -0.9].max()

    @pytest.mark.parametrize("seed", [0, 1, 2, 7])
    def test_dominant_direction_between_sun_and_zenith(self, seed):
        seq = synthetic.make_sequence(
            num_frames=1, width=8, height=6, seed=seed, sensor_noise=False
        )
        dom, sun = seq.dominant_direction_world[0], seq.sun_direction_world[0]
        up = np.array([0.0, 1.0, 0.0])
        assert angular_error_deg(dom, sun) < 15.0
        assert angular_error_deg(dom, up) < angular_error_deg(sun, up)
        assert (
            abs(
                angular_error_deg(dom, sun)
                + angular_error_deg(dom, up)
                - angular_error_deg(sun, up)
            )
            < 0.5
        )
        elevation = math.degrees(math.asin(sun[1]))
        assert 25.0 <= elevation <= 60.0

    def test_rendered_ground_follows_the_shading_equation(self, clean):
        """Clean radiance of sunlit ground = albedo / pi (E_sun s_y + AO E_sky(up))."""
        i = 0
        light = synthetic.Lighting(sun_direction=clean.sun_direction_world[i])
        pose = clean.frames[i].pose
        radiance, depth = synthetic.render_frame(clean.camera, pose, light)
        points = _world_points(clean, i).reshape(-1, 3)
        ground = (depth.reshape(-1) > 0) & (np.abs(points[:, 1]) < 1e-4)
        pts = points[ground].T.astype(np.float32)
        normals = np.zeros_like(pts)
        normals[1] = 1.0
        visible = synthetic.sun_visibility(pts, normals, light.sun_direction) > 0
        ray_len = np.linalg.norm(pts.T - pose[:3, 3], axis=1)
        albedo = synthetic.ground_albedo(pts, ray_len.astype(np.float32))
        ao = synthetic.ambient_occlusion(pts, normals)
        e_sun = light.sun_rgb[:, None] * light.sun_direction[1] * visible
        e_sky = light.sky_irradiance(np.array([[0.0, 1.0, 0.0]]))[0][:, None] * ao
        expected = albedo / math.pi * (e_sun + e_sky)
        got = radiance.reshape(-1, 3)[ground].T
        assert visible.sum() > 1000 and (~visible).sum() > 100
        np.testing.assert_allclose(got, expected, rtol=2e-3, atol=1e-5)

    def test_sky_pixels_show_sky_radiance_and_have_no_depth(self, clean):
        i = 0
        light = synthetic.Lighting(sun_direction=clean.sun_direction_world[i])
        radiance, depth = synthetic.render_frame(clean.camera, clean.frames[i].pose, light)
        rays = clean.camera.ray_directions().reshape(-1, 3) @ clean.frames[i].pose[:3, :3].T
        sky = rays[:, 1] >= 0
        assert sky.sum() > 100  # a strip of sky above the horizon
        assert np.all(depth.reshape(-1)[sky] == 0)
        np.testing.assert_allclose(
            radiance.reshape(-1, 3)[sky], light.sky_radiance(rays[sky]), rtol=1e-5
        )


class TestPoses:
    def test_rigid_and_looking_down_at_the_scene(self, clean):
        for frame in clean.frames:
            pose = frame.pose
            r = pose[:3, :3]
            np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
            assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
            np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])
            assert r[1, 1] < -0.8  # camera y (down) points along world -Y
            assert r[1, 2] < 0  # looking downwards
            assert r[1, 0] == pytest.approx(0.0, abs=1e-12)  # no roll
            eye = pose[:3, 3]
            assert 1.8 <= math.hypot(eye[0], eye[2]) <= 2.2
            assert 1.0 <= eye[1] <= 1.4

    def test_world_origin_projects_near_the_image_centre(self, clean):
        cam = clean.camera
        for frame in clean.frames:
            pose = frame.pose
            p_cam = pose[:3, :3].T @ (np.zeros(3) - pose[:3, 3])
            uv, z = cam.project(p_cam)
            assert z > 0
            assert abs(uv[0] - cam.cx) < 0.05 * cam.width
            assert abs(uv[1] - cam.cy) < 0.15 * cam.height

    def test_orbit_sweeps_60_to_90_degrees(self):
        seq = synthetic.make_sequence(num_frames=5, width=16, height=12, sensor_noise=False)
        first, last = seq.frames[0].pose[:3, 3], seq.frames[-1].pose[:3, 3]
        sweep = angular_error_deg([first[0], first[2]], [last[0], last[2]])
        assert 60.0 <= sweep <= 90.0

    def test_timestamps_at_30_hz_from_1000_s(self, clean):
        stamps = [f.timestamp for f in clean.frames]
        np.testing.assert_allclose(stamps, 1000.0 + np.arange(len(clean)) / 30.0)


class TestImage:
    def test_shadowed_ground_is_darker_than_lit_ground_nearby(self, clean):
        for i in (0, len(clean) - 1):
            points = _world_points(clean, i).reshape(-1, 3)
            near = (clean.depth_gt[i].reshape(-1) > 0) & (np.abs(points[:, 1]) < 1e-4)
            near &= np.hypot(points[:, 0], points[:, 2]) < 1.0
            pts = points[near].T.astype(np.float32)
            normals = np.zeros_like(pts)
            normals[1] = 1.0
            lit = synthetic.sun_visibility(pts, normals, clean.sun_direction_world[i]) > 0
            grey = clean.frames[i].color.reshape(-1, 3)[near].astype(float) @ [
                0.2126,
                0.7152,
                0.0722,
            ]
            assert (~lit).sum() > 300, "no visible sun shadow on the ground"
            assert np.median(grey[~lit]) < 0.8 * np.median(grey[lit])

    def test_shadow_behind_each_sphere(self, clean):
        """The ground point on the line from the sun through a sphere's centre is darker than
        sunlit ground beside it, wherever both are in view."""
        compared = 0
        up = np.array([[0.0], [1.0], [0.0]], np.float32)
        for i in range(len(clean)):
            s = clean.sun_direction_world[i]
            side = np.cross(s, [0.0, 1.0, 0.0])
            side /= np.linalg.norm(side)
            for sphere in synthetic.SCENE_OBJECTS:
                if not isinstance(sphere, synthetic.Sphere):
                    continue
                c = np.asarray(sphere.centre)
                shadow = c - s * c[1] / s[1]
                for offset in (0.4, -0.4, 0.6, -0.6):
                    lit = shadow + offset * side
                    if synthetic.sun_visibility(lit[:, None].astype(np.float32), up, s)[0]:
                        break
                shade = [self._pixel(clean, i, p) for p in (shadow, lit)]
                if None in shade:
                    continue  # hidden behind an object in this view
                assert shade[0] < 0.8 * shade[1]
                compared += 1
        assert compared >= 2

    @staticmethod
    def _pixel(seq, i, point):
        """Mean colour of the pixel showing world `point`, None if out of view or hidden."""
        pose = seq.frames[i].pose
        uv, z = seq.camera.project(pose[:3, :3].T @ (point - pose[:3, 3]))
        u, v = int(round(uv[0])), int(round(uv[1]))
        if not (0 <= u < seq.camera.width and 0 <= v < seq.camera.height):
            return None
        seen = _world_points(seq, i)[v, u]
        if z <= 0 or np.linalg.norm(seen - point) > 0.03:
            return None
        return seq.frames[i].color[v, u].astype(float).mean()

    def test_exposure_mid_grey_ground_and_little_clipping(self, noisy):
        for i, frame in enumerate(noisy.frames):
            points = _world_points(noisy, i).reshape(-1, 3)
            ground = (noisy.depth_gt[i].reshape(-1) > 0) & (np.abs(points[:, 1]) < 1e-4)
            grey = frame.color.reshape(-1, 3).astype(float).mean(axis=1)
            assert 90 <= np.median(grey[ground]) <= 140  # sRGB(0.18) = 118
            assert (frame.color == 255).any(axis=-1).mean() <= 0.02

    def test_coloured_object_present(self, clean):
        color = clean.frames[0].color.astype(int)
        reddish = (color[..., 0] - color[..., 2] > 60).mean()
        assert reddish > 0.002

    def test_color_noise_level(self, noisy):
        clean_seq = synthetic.make_sequence(
            num_frames=1, width=320, height=240, seed=3, sensor_noise=False
        )
        diff = noisy.frames[0].color.astype(float) - clean_seq.frames[0].color.astype(float)
        assert 1.2 < diff.std() < 1.9


class TestDepth:
    def test_clean_ground_depth_matches_plane_intersection(self, clean):
        cam = clean.camera
        rays_cam = cam.ray_directions().reshape(-1, 3).astype(np.float64)
        for i, frame in enumerate(clean.frames):
            pose = frame.pose
            rays = rays_cam @ pose[:3, :3].T
            with np.errstate(divide="ignore"):
                t_plane = np.where(rays[:, 1] < 0, -pose[1, 3] / rays[:, 1], np.inf)
            z_plane = t_plane * rays_cam[:, 2]
            depth = clean.depth_gt[i].reshape(-1).astype(np.float64)
            np.testing.assert_array_equal(frame.depth, clean.depth_gt[i])
            assert np.all(depth[rays[:, 1] >= 0] == 0)
            on_ground = np.abs(depth - z_plane) < 1e-3
            assert on_ground.mean() > 0.6
            objects = (depth > 0) & ~on_ground
            assert 0.01 < objects.mean() < 0.3
            assert np.all(depth[objects] < z_plane[objects])  # objects occlude the ground
            points = _world_points(clean, i).reshape(-1, 3)
            assert np.all(points[objects, 1] > 1e-4)

    def test_sensor_depth_kinect_like(self, noisy):
        for i, frame in enumerate(noisy.frames):
            # the sensor's integers at 5000 units per metre, metres as the pipeline makes them
            assert frame.depth.dtype == np.uint16 and frame.depth_scale == synthetic.DEPTH_SCALE
            d, gt = depth_metres(frame.depth, frame.depth_scale), noisy.depth_gt[i]
            assert d.dtype == np.float32 and d.shape == gt.shape
            valid = d > 0
            assert np.all((d[valid] >= 0.4) & (d[valid] <= 4.0))
            np.testing.assert_allclose(d[valid] * 5000, np.rint(d[valid] * 5000), atol=2e-3)
            in_range = (gt >= 0.45) & (gt <= 3.9)
            missing = (~valid & in_range).sum() / in_range.sum()
            assert 0.005 < missing < 0.06
            err = (d - gt)[valid & in_range]
            sigma = 0.0012 + 0.0019 * (gt[valid & in_range] - 0.4) ** 2
            assert 0.8 < np.std(err / sigma) < 1.25
            assert np.all(d[gt == 0] == 0)


class TestSequence:
    def test_deterministic(self):
        a = synthetic.make_sequence(num_frames=2, width=80, height=60, seed=11)
        b = synthetic.make_sequence(num_frames=2, width=80, height=60, seed=11)
        c = synthetic.make_sequence(num_frames=2, width=80, height=60, seed=12)
        for fa, fb, fc in zip(a.frames, b.frames, c.frames, strict=True):
            np.testing.assert_array_equal(fa.color, fb.color)
            np.testing.assert_array_equal(fa.depth, fb.depth)
            np.testing.assert_array_equal(fa.pose, fb.pose)
            assert not np.array_equal(fa.color, fc.color)
        np.testing.assert_array_equal(a.sh_world, b.sh_world)
        assert a.exposure == b.exposure

    def test_light_change(self):
        seq = synthetic.make_sequence(
            num_frames=6, width=32, height=24, seed=4, sensor_noise=False, light_change_frame=3
        )
        dom = seq.dominant_direction_world
        for i in (1, 2):
            np.testing.assert_array_equal(dom[i], dom[0])
        for i in (4, 5):
            np.testing.assert_array_equal(dom[i], dom[3])
        assert angular_error_deg(dom[2], dom[3]) > 20.0
        s0, s1 = seq.sun_direction_world[0], seq.sun_direction_world[3]
        azimuth = angular_error_deg([s0[0], s0[2]], [s1[0], s1[2]])
        assert azimuth >= 60.0
        assert s0[1] == pytest.approx(s1[1])
        steady = synthetic.make_sequence(
            num_frames=6, width=32, height=24, seed=4, sensor_noise=False
        )
        np.testing.assert_array_equal(steady.frames[2].color, seq.frames[2].color)
        assert not np.array_equal(steady.frames[3].color, seq.frames[3].color)

    def test_tiny_sequence(self):
        seq = synthetic.make_sequence(num_frames=3, width=32, height=24)
        assert len(seq) == 3
        assert seq.camera == PinholeCamera.kinect_v1(32, 24)
        for frame in seq.frames:
            assert frame.color.shape == (24, 32, 3) and frame.color.dtype == np.uint8
            assert frame.depth.shape == (24, 32) and frame.depth.dtype == np.uint16
            assert frame.depth_scale == 5000.0
            depth = depth_metres(frame.depth, frame.depth_scale)
            assert depth.shape == (24, 32) and depth.dtype == np.float32
            assert frame.pose.shape == (4, 4)
        assert seq.exposure > 0
        for field in (
            seq.sh_world,
            seq.dominant_direction_world,
            seq.dominant_direction_camera,
            seq.sun_direction_world,
        ):
            assert len(field) == 3 and all(np.all(np.isfinite(x)) for x in field)

    def test_single_frame(self):
        seq = synthetic.make_sequence(num_frames=1, width=4, height=3, sensor_noise=False)
        assert len(seq) == 1

    @pytest.mark.parametrize(
        "kwargs",
        [
            {"num_frames": 0},
            {"width": 0},
            {"height": -1},
            {"num_frames": 4, "light_change_frame": 4},
            {"light_change_frame": -1},
        ],
    )
    def test_bad_arguments(self, kwargs):
        with pytest.raises(ValueError):
            synthetic.make_sequence(**kwargs)
