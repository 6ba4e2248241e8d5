"""The reflection probe (issue 33): cube layout, prefiltering, the room grid, the stage's
fallbacks, and mirror / glossy shading (pipeline/probe*.py).

Scenes are built here in NumPy: a camera looking along one world axis at a flat wall whose
colour and depth are exact per pixel, fused into the probe's grid by the real code."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import SMALL

from arlight.core.camera import PinholeCamera
from arlight.pipeline import probe_cube, sh
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.probe import (
    INSIDE,
    SUN_SHARE_MAX,
    DistantLight,
    ProbeSettings,
    ProbeStage,
    hanning,
    parse_point,
    split_dominant,
)
from arlight.pipeline.probe_grid import RoomGrid
from arlight.pipeline.probe_shading import Glossiness, glossiness_of, shade
from arlight.pipeline.virtual_gbuffer import VirtualRaycaster
from arlight.pipeline.virtual_scene import (
    Material,
    VirtualScene,
    box_mesh,
    object_from_open3d,
    sphere_mesh,
)
from arlight.sources.synthetic import make_sequence

CAMERA = PinholeCamera(160, 120, 120.0, 120.0, 79.5, 59.5)
RED = np.array([0.8, 0.05, 0.05])
GREY_RADIANCE = 0.2
AXES = np.eye(3)
FACE_OF = {(0, 1): 0, (0, -1): 1, (1, 1): 2, (1, -1): 3, (2, 1): 4, (2, -1): 5}


def grey_light() -> DistantLight:
    """A constant distant radiance GREY_RADIANCE (band 0 only)."""
    coeffs = np.zeros(16)
    coeffs[0] = GREY_RADIANCE / sh.sh_basis(np.array([0.0, 0.0, 1.0]), 1)[0]
    return DistantLight(coeffs)


def looking_along(direction: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """world_from_cam (OpenCV axes) at eye with its optical axis along direction."""
    z = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, np.cross(z, x), z, eye
    return pose


def wall_frame(distance_m: float, colour=RED) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) of a wall facing the camera at distance_m along its axis, and its
    linear colour (H, W, 3)."""
    depth = np.full((CAMERA.height, CAMERA.width), distance_m, np.float32)
    return depth, np.broadcast_to(np.asarray(colour, np.float32), (*depth.shape, 3)).copy()


def wall_probe(axis: int, sign: int, size: int = 32, wall_m: float = 1.0):
    """A probe at the origin after one frame of a camera 0.5 m behind it looking along
    sign * axis at a red wall wall_m beyond the origin."""
    direction = sign * AXES[axis]
    pose = looking_along(direction, -0.5 * direction)
    stage = ProbeStage(ProbeSettings(size=size), CAMERA)
    stage.fuse(np.zeros(3), *wall_frame(wall_m + 0.5), pose)
    return stage, stage.probe(np.zeros(3), pose, grey_light())


# ------------------------------------------------------------------ the cube's layout
class TestCubeLayout:
    def test_texel_centres_read_back_their_own_texel(self):
        rng = np.random.default_rng(0)
        radiance = rng.random((6, 32, 32, 3)).astype(np.float32)
        cube = probe_cube.CubeMips([radiance], np.zeros(1))
        dirs = probe_cube.texel_directions(32).reshape(-1, 3)
        got = probe_cube.sample(cube, dirs, 0.0)
        np.testing.assert_allclose(got, radiance.reshape(-1, 3), atol=1e-5)

    def test_kernel_matches_the_numpy_oracle(self):
        rng = np.random.default_rng(1)
        cube = probe_cube.prefilter(rng.random((6, 32, 32, 3)).astype(np.float32))
        dirs = rng.normal(size=(500, 3))
        for level in range(len(cube.levels)):
            np.testing.assert_allclose(
                probe_cube.sample(cube, dirs, float(level)),
                probe_cube.sample_numpy(cube, dirs, level),
                atol=1e-5,
            )

    @pytest.mark.parametrize("axis", [0, 1, 2])
    @pytest.mark.parametrize("sign", [1, -1])
    def test_a_direction_reads_the_face_of_its_major_axis(self, axis, sign):
        faces = np.broadcast_to(np.arange(6, dtype=np.float32)[:, None, None, None], (6, 32, 32, 3))
        cube = probe_cube.CubeMips([np.ascontiguousarray(faces)], np.zeros(1))
        d = sign * AXES[axis] + 0.3 * AXES[(axis + 1) % 3] - 0.2 * AXES[(axis + 2) % 3]
        assert probe_cube.sample(cube, d[None], 0.0)[0, 0] == FACE_OF[(axis, sign)]

    @pytest.mark.parametrize("size", [16, 48, 512, 32.0, True])
    def test_sizes_out_of_range_are_refused(self, size):
        with pytest.raises(ValueError, match="probe_size"):
            ProbeSettings(size=size)

    @pytest.mark.parametrize("size", [16, 48, 512])
    def test_the_config_refuses_sizes_naming_the_key(self, size):
        with pytest.raises(ValueError, match=r"--set probe_size"):
            Config.from_preset("full", probe_size=size)


# ------------------------------------------------------------------ prefiltering
class TestPrefilter:
    def test_a_constant_radiance_stays_constant_at_every_level(self):
        cube = probe_cube.prefilter(np.full((6, 64, 64, 3), 0.5, np.float32))
        assert len(cube.levels) == 5 and [lv.shape[1] for lv in cube.levels] == [64, 32, 16, 8, 4]
        for level in cube.levels:
            np.testing.assert_allclose(level, 0.5, rtol=1e-4)

    def test_a_bright_spot_spreads_as_roughness_grows(self):
        """A spot about +x: each rougher level's peak is lower and its lobe wider (the
        radiance-weighted mean angle from +x grows)."""
        radiance = np.zeros((6, 64, 64, 3), np.float32)
        radiance[0, 28:36, 28:36] = 100.0
        cube = probe_cube.prefilter(radiance)
        peaks, widths = [], []
        for level in cube.levels:
            dirs = probe_cube.texel_directions(level.shape[1]).reshape(-1, 3)
            value = level[..., 0].reshape(-1).astype(np.float64)
            angle = np.arccos(np.clip(dirs[:, 0], -1.0, 1.0))
            peaks.append(value.max())
            widths.append(float((value * angle).sum() / value.sum()))
        assert all(a > b for a, b in zip(peaks, peaks[1:], strict=False))
        assert all(a < b for a, b in zip(widths, widths[1:], strict=False))

    def test_env_brdf_is_a_reflectance(self):
        rng = np.random.default_rng(2)
        f0 = rng.random((200, 3))
        ab = probe_cube.env_brdf(f0, rng.random(200), rng.random(200))
        assert np.all(ab >= 0.0) and np.all(ab <= 1.0 + 1e-6)
        mirror = probe_cube.env_brdf(np.ones((3, 3)), np.zeros(3), np.array([1.0, 0.5, 0.1]))
        np.testing.assert_allclose(mirror, 1.0, atol=0.02)


# ------------------------------------------------------------------ the room grid
class TestRoomGrid:
    def test_march_finds_the_first_surface_cell_as_fine_stepping_does(self):
        rng = np.random.default_rng(3)
        grid = RoomGrid(np.zeros(3), cells=24, cell_m=0.1)
        grid.weight[rng.random(grid.weight.shape) < 0.01] = 1.0
        grid.invalidate()
        origins = rng.uniform(-1.0, 1.0, (300, 3))
        dirs = rng.normal(size=(300, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        t, _ = grid.march(origins, dirs)
        steps = np.arange(0.0, 5.0, 0.0005)
        for o, d, got in zip(origins, dirs, t, strict=True):
            cells = np.floor((o + steps[:, None] * d - grid.origin) / grid.cell_m).astype(int)
            inside = np.all((cells >= 0) & (cells < grid.cells), axis=1)
            c = np.clip(cells, 0, grid.cells - 1)
            solid = inside & (grid.weight[c[:, 0], c[:, 1], c[:, 2]] > 0)
            if grid.occupied(o):
                assert got == 0.0
            elif solid.any():
                assert abs(got - steps[np.argmax(solid)]) < 0.002
            else:
                assert np.isinf(got)

    def test_a_surface_that_moved_away_is_carved_in_the_next_frame(self):
        pose = looking_along(AXES[0], np.array([-0.5, 0.0, 0.0]))
        grid = RoomGrid(np.zeros(3), cells=80, cell_m=0.04)
        grid.update(*wall_frame(1.0), pose, CAMERA)  # a wall at x = 0.5
        t, _ = grid.march(np.zeros(3), AXES[:1])
        assert abs(t[0] - 0.5) < 0.05
        grid.update(*wall_frame(1.8), pose, CAMERA)  # it moved back to x = 1.3
        t, _ = grid.march(np.zeros(3), AXES[:1])
        assert abs(t[0] - 1.3) < 0.05

    def test_what_the_camera_turned_away_from_is_remembered(self):
        grid = RoomGrid(np.zeros(3), cells=80, cell_m=0.04)
        grid.update(*wall_frame(1.0), looking_along(AXES[0], -0.5 * AXES[0]), CAMERA)
        grid.update(*wall_frame(1.0), looking_along(-AXES[0], 0.5 * AXES[0]), CAMERA)
        t, rgb = grid.march(np.zeros(3), np.array([[1.0, 0, 0], [-1.0, 0, 0]]))
        assert np.all(np.abs(t - 0.5) < 0.05)
        np.testing.assert_allclose(rgb, [RED, RED], atol=1e-5)


# ------------------------------------------------------------------ the probe
class TestProbeDirections:
    @pytest.mark.parametrize("axis", [0, 1, 2])
    @pytest.mark.parametrize("sign", [1, -1])
    def test_a_red_wall_on_one_side_shows_in_that_face(self, axis, sign):
        """The issue's check: a red wall on the +x side of the probe shows in the +x face
        (and every other axis likewise); the opposite face sees the distant grey."""
        _, probe = wall_probe(axis, sign)
        level0 = probe.mips.levels[0]
        face, opposite = FACE_OF[(axis, sign)], FACE_OF[(axis, -sign)]
        centre = level0[face, 12:20, 12:20]
        np.testing.assert_allclose(centre, np.broadcast_to(RED, centre.shape), atol=1e-5)
        np.testing.assert_allclose(level0[opposite], GREY_RADIANCE, rtol=1e-3)
        assert probe.diagnostics["fallback"] is None and 0.0 < probe.hit_fraction < 0.5

    def test_the_room_off_gives_the_distant_light_alone(self):
        pose = looking_along(AXES[0], -0.5 * AXES[0])
        stage = ProbeStage(ProbeSettings(size=32, room=False), CAMERA)
        stage.fuse(np.zeros(3), *wall_frame(1.5), pose)
        probe = stage.probe(np.zeros(3), pose, grey_light())
        np.testing.assert_allclose(probe.mips.levels[0], GREY_RADIANCE, rtol=1e-3)
        assert probe.grid is None and probe.hit_fraction == 0.0


class TestRegrid:
    def test_a_point_that_moves_off_the_grid_gets_a_new_grid_about_it(self):
        pose = looking_along(AXES[0], -0.5 * AXES[0])
        stage = ProbeStage(ProbeSettings(size=32, cells=40, cell_m=0.05), CAMERA)
        notes = stage.fuse(np.zeros(3), *wall_frame(1.5), pose)
        assert notes["regridded"] is False
        near = np.array([0.4, 0.0, 0.0])  # within a quarter of the 2 m grid: kept
        assert stage.fuse(near, *wall_frame(1.5), pose)["regridded"] is False
        far = np.array([0.0, 0.0, 3.0])
        notes = stage.fuse(far, *wall_frame(1.5), pose)
        assert notes["regridded"] is True
        assert stage.grid is not None and np.allclose(stage.grid.centre, far)


class TestSunDisc:
    def test_a_delta_plus_ambient_splits_back_into_its_parts(self):
        towards = np.array([0.3, 0.8, -0.52])
        towards /= np.linalg.norm(towards)
        coeffs = sh.directional_light(towards, 2.0, 4)
        coeffs[0] += 1.0  # ambient
        direction, intensity, rest = split_dominant(coeffs)
        assert np.degrees(np.arccos(np.clip(direction @ towards, -1, 1))) < 0.5
        assert intensity == pytest.approx(2.0, rel=1e-6)
        np.testing.assert_allclose(rest[1:], 0.0, atol=1e-9)  # what is left is the ambient
        assert rest[0] == pytest.approx(1.0)

    def test_the_disc_takes_at_most_its_share_of_band_0(self):
        coeffs = sh.directional_light(np.array([0.0, 1.0, 0.0]), 2.0, 4)  # a bare delta
        _, intensity, rest = split_dominant(coeffs)
        y0 = sh.sh_basis(np.array([0.0, 1.0, 0.0]), 1)[0]
        assert intensity == pytest.approx(SUN_SHARE_MAX * coeffs[0] / y0)
        assert rest[0] == pytest.approx((1.0 - SUN_SHARE_MAX) * coeffs[0])

    def test_the_probe_draws_the_disc_where_the_light_is_and_keeps_its_energy(self):
        towards = np.array([0.0, 1.0, 0.0])
        coeffs = sh.directional_light(towards, 2.0, 4)
        coeffs[0] += 1.0
        stage = ProbeStage(ProbeSettings(size=64, sun=True), CAMERA)
        pose = looking_along(AXES[0], -0.5 * AXES[0])
        stage.fuse(np.zeros(3), *wall_frame(1.5), pose)
        probe = stage.probe(np.zeros(3), pose, DistantLight(coeffs))
        top = probe_cube.sample(probe.mips, towards[None], 0.0)[0, 0]
        side = probe_cube.sample(probe.mips, np.array([[0.0, 0.0, -1.0]]), 0.0)[0, 0]
        assert top > 100.0 * side > 0.0
        omega = probe_cube.texel_solid_angles(64)
        texels = probe.mips.levels[0][..., 0]
        plain = np.maximum(sh.sh_basis(probe_cube.texel_directions(64), 4) @ coeffs, 0.0)
        # over the directions that miss the wall, the disc and the rest hold the SH's energy
        sky = probe_cube.texel_directions(64)[..., 0] < 0.5
        assert np.sum((texels * omega)[sky]) == pytest.approx(
            np.sum((plain * omega)[sky]), rel=0.05
        )
        assert probe.diagnostics["sun_world"] == [0.0, 1.0, 0.0]
        # the objects' own surfaces are lit by the light as given, not its remainder
        assert np.array_equal(probe.distant.sh, coeffs)


class TestWindow:
    def test_hanning_keeps_band_0_and_shrinks_the_clamped_lobes(self):
        coeffs = sh.directional_light(np.array([0.0, 1.0, 0.0]), 2.0, 4)
        smooth = hanning(coeffs)
        assert smooth[0] == coeffs[0]
        np.testing.assert_allclose(smooth[1:4], coeffs[1:4] * (1 + math.cos(math.pi / 4)) / 2)
        dirs = probe_cube.texel_directions(32).reshape(-1, 3)
        raw = sh.sh_basis(dirs, 4) @ coeffs
        windowed = sh.sh_basis(dirs, 4) @ smooth
        assert windowed.min() > raw.min()  # less negative: fewer black holes once clamped


class TestPanorama:
    def test_misses_see_a_streamed_panoramas_map_instead_of_the_sh(self):
        """A session lit by its panorama: directions that leave the room read the HDR map
        (its own frame turned by map_from_world), not the SH."""
        from arlight.pipeline.glossy import mip_pyramid
        from arlight.pipeline.rendering import EnvironmentMap

        hdr = np.full((32, 64, 3), 0.1, np.float32)
        hdr[:16] = (2.0, 1.0, 0.5)  # the upper half of the map bright and warm
        turn = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # map up = world down
        env = EnvironmentMap(mip_pyramid(hdr), turn)
        pose = looking_along(AXES[0], -0.5 * AXES[0])
        stage = ProbeStage(ProbeSettings(size=32), CAMERA)
        stage.fuse(np.zeros(3), *wall_frame(1.5), pose)
        probe = stage.probe(np.zeros(3), pose, DistantLight(np.zeros(16), environment=env))
        down = probe_cube.sample(probe.mips, np.array([[0.0, -1.0, 0.0]]), 0.0)[0]
        up = probe_cube.sample(probe.mips, np.array([[0.0, 1.0, 0.0]]), 0.0)[0]
        np.testing.assert_allclose(down, [2.0, 1.0, 0.5], rtol=1e-3)
        np.testing.assert_allclose(up, 0.1, rtol=1e-3)


class TestProbeBadInput:
    def test_a_point_inside_real_geometry_falls_back_to_the_distant_light(self):
        stage, _ = wall_probe(0, 1)
        inside = np.array([1.0 + 0.01, 0.0, 0.0])  # in the wall's cells
        pose = looking_along(AXES[0], -0.5 * AXES[0])
        probe = stage.probe(inside, pose, grey_light())
        assert probe.diagnostics["fallback"] == INSIDE
        np.testing.assert_allclose(probe.mips.levels[0], GREY_RADIANCE, rtol=1e-3)

    def test_a_point_behind_the_camera_is_kept_and_flagged(self):
        stage, _ = wall_probe(0, 1)
        behind = np.array([-1.0, 0.0, 0.0])
        probe = stage.probe(behind, looking_along(AXES[0], -0.5 * AXES[0]), grey_light())
        assert probe.diagnostics["behind_camera"] is True
        assert probe.diagnostics["fallback"] is None
        # it still sees the wall in front of the camera, 2 m away along +x
        assert probe.mips.levels[0][0, 14:18, 14:18, 0].min() == pytest.approx(RED[0], abs=1e-5)

    @pytest.mark.parametrize("text", ["1,2", "a,b,c", "1,2,nan", ""])
    def test_a_bad_probe_point_names_the_flag(self, text):
        with pytest.raises(ValueError, match="--probe-at"):
            parse_point(text)
        assert np.array_equal(parse_point("1,-2,0.5"), [1.0, -2.0, 0.5])


# ------------------------------------------------------------------ shading
def mirror_pixel_towards_plus_x() -> tuple[np.ndarray, np.ndarray]:
    """(normal, view) of a pixel whose mirror direction is +x (view along +z)."""
    view = np.array([[0.0, 0.0, 1.0]])
    normal = np.array([[1.0, 0.0, -1.0]]) / math.sqrt(2.0)
    return normal, view


class TestShading:
    def test_a_mirror_reflects_the_red_wall_times_its_albedo(self):
        _, probe = wall_probe(0, 1, size=64)
        normal, view = mirror_pixel_towards_plus_x()
        looks = [glossiness_of(Material((0.9, 0.9, 0.9), mirror=True))]
        got = shade(
            probe, looks, np.zeros(1, int), np.zeros((1, 3)), normal, view, np.ones((1, 3)), None
        )
        np.testing.assert_allclose(got[0], 0.9 * RED, rtol=1e-3)

    def test_a_pixel_off_the_probe_point_sees_the_wall_along_its_own_ray(self):
        """Parallax: a wall at x = 1 red above y = 0.15 and blue below; a mirror pixel 0.3 m
        above the probe point reflecting +x meets the wall at y = 0.3 (red), where the probe
        centre's own +x direction sees blue."""
        pose = looking_along(AXES[0], -0.5 * AXES[0])
        depth, colour = wall_frame(1.5)
        rows = np.arange(CAMERA.height)
        y_world = (rows - CAMERA.cy) / CAMERA.fy * 1.5  # this camera's image y is world +y
        colour[y_world < 0.15] = (0.05, 0.05, 0.8)
        stage = ProbeStage(ProbeSettings(size=64), CAMERA)
        stage.fuse(np.zeros(3), depth, colour, pose)
        probe = stage.probe(np.zeros(3), pose, grey_light())
        assert probe_cube.sample(probe.mips, AXES[:1], 0.0)[0, 2] > 0.5  # the centre: blue
        normal, view = mirror_pixel_towards_plus_x()
        looks = [glossiness_of(Material((1.0, 1.0, 1.0), mirror=True))]
        point = np.array([[0.0, 0.3, 0.0]])
        got = shade(probe, looks, np.zeros(1, int), point, normal, view, np.ones((1, 3)), None)
        np.testing.assert_allclose(got[0], RED, atol=0.05)

    def test_the_object_itself_occludes_its_reflection(self):
        """A virtual box on +x, between the mirror pixel and the wall: the reflection is the
        box's Lambertian radiance under the distant light, not the red wall."""
        _, probe = wall_probe(0, 1, size=64)
        pose = np.eye(4)
        pose[:3, 3] = [0.3, -0.1, -0.1]
        box = object_from_open3d("box", box_mesh((0.1, 0.2, 0.2)), pose, Material((0.5,) * 3))
        ball = object_from_open3d(
            "ball", sphere_mesh(0.05), np.eye(4), Material((0.9,) * 3, mirror=True)
        )
        scene = VirtualScene((ball, box))
        looks = [glossiness_of(o.material) for o in scene.objects]
        normal, view = mirror_pixel_towards_plus_x()
        got = shade(
            probe,
            looks,
            np.zeros(1, int),
            np.zeros((1, 3)),
            normal,
            view,
            np.ones((1, 3)),
            VirtualRaycaster(scene),
        )
        grey = 0.9 * 0.5 * GREY_RADIANCE  # albedo 0.9 x box albedo / pi x pi x radiance
        np.testing.assert_allclose(got[0], grey, rtol=0.02)

    def test_the_diffuse_part_of_a_glossy_object_is_lit_as_the_diffuse_renderer_lights_it(self):
        """In a black room under no light, a glossy dielectric shows exactly its diffuse
        part: albedo / pi x the irradiance the diffuse renderer gives it, times the
        principled BSDF's diffuse Fresnel weight at this view (a 45-degree pixel)."""
        stage = ProbeStage(ProbeSettings(size=32), CAMERA)
        pose = looking_along(AXES[0], -0.5 * AXES[0])
        stage.fuse(np.zeros(3), *wall_frame(1.5, colour=(0.0, 0.0, 0.0)), pose)
        probe = stage.probe(np.zeros(3), pose, DistantLight(np.zeros(16)))
        looks = [glossiness_of(Material((0.45, 0.45, 0.45), roughness=0.3))]
        normal, view = mirror_pixel_towards_plus_x()
        e = np.array([[0.7, 0.8, 0.9]])
        got = shade(probe, looks, np.zeros(1, int), np.zeros((1, 3)), normal, view, e, None)
        weight = (1.0 - 0.5 * (1.0 - math.sqrt(0.5)) ** 5) * (1.0 - 1.0 / 42.0)
        np.testing.assert_allclose(got[0], 0.45 / math.pi * e[0] * weight, rtol=1e-9)

    def test_materials(self):
        assert glossiness_of(Material()).kind == 0  # the default: diffuse, left alone
        assert glossiness_of(Material(mirror=True)).kind == 1
        glossy = glossiness_of(Material((0.5, 0.5, 0.5), roughness=0.1))
        assert glossy.kind == 2 and np.allclose(glossy.f0, 0.04)
        metal = glossiness_of(Material((0.9, 0.6, 0.2), roughness=1.0, metalness=1.0))
        assert metal.kind == 2 and np.allclose(metal.f0, [0.9, 0.6, 0.2])
        assert np.allclose(metal.diffuse_rgb, 0.0)
        assert isinstance(glossy, Glossiness)


# ------------------------------------------------------------------ in the pipeline
@pytest.fixture(scope="module")
def tiny_sequence():
    return make_sequence(num_frames=2, width=160, height=120, sensor_noise=False)


def ball_in_view(sequence, material: Material) -> VirtualScene:
    frame = sequence.frames[0]
    centre = frame.pose[:3, 3] + 1.2 * frame.pose[:3, 2]
    pose = np.eye(4)
    pose[:3, 3] = centre
    return VirtualScene((object_from_open3d("ball", sphere_mesh(0.15), pose, material),))


class TestPipeline:
    def test_a_mirror_object_gets_a_probe_stage_and_its_notes(self, tiny_sequence):
        scene = ball_in_view(tiny_sequence, Material((0.9,) * 3, mirror=True))
        pipe = Pipeline(Config.from_preset("full", **SMALL), tiny_sequence.camera, scene)
        result = pipe.process(tiny_sequence.frames[0])
        assert result.timings_ms["Probe"] > 0.0
        notes = result.diagnostics["probe"]
        assert notes["size"] == 64 and notes["memory"] == "frames"
        assert pipe.last_probe is not None and pipe.last_probe.mips.size == 64

    def test_mirrors_alone_leave_the_mips_unmade_and_read_what_the_mips_hold(self, tiny_sequence):
        scene = ball_in_view(tiny_sequence, Material((0.9,) * 3, mirror=True))
        pipe = Pipeline(Config.from_preset("full", **SMALL), tiny_sequence.camera, scene)
        pipe.process(tiny_sequence.frames[0])
        probe = pipe.last_probe
        assert probe is not None and "mips" not in vars(probe)  # not prefiltered
        dirs = np.random.default_rng(3).normal(size=(500, 3))
        np.testing.assert_array_equal(
            probe_cube.sample(probe.mirror, dirs), probe_cube.sample(probe.mips, dirs)
        )
        assert len(probe.mips.levels) == probe_cube.num_levels(64)

    def test_a_glossy_object_makes_the_mips(self, tiny_sequence):
        scene = ball_in_view(tiny_sequence, Material((0.9,) * 3, roughness=0.3, metalness=1.0))
        pipe = Pipeline(Config.from_preset("full", **SMALL), tiny_sequence.camera, scene)
        pipe.process(tiny_sequence.frames[0])
        assert pipe.last_probe is not None and "mips" in vars(pipe.last_probe)

    def test_a_diffuse_object_is_rendered_as_before(self, tiny_sequence):
        scene = ball_in_view(tiny_sequence, Material((0.6,) * 3))
        results = []
        for probe in (True, False):
            pipe = Pipeline(
                Config.from_preset("full", **SMALL, probe=probe), tiny_sequence.camera, scene
            )
            results.append(pipe.process(tiny_sequence.frames[0]))
        assert "probe" not in results[0].diagnostics
        assert results[0].timings_ms["Probe"] < 1.0
        assert np.array_equal(results[0].composite, results[1].composite)

    def test_without_a_volume_the_probe_holds_the_current_frame_only(self, tiny_sequence):
        scene = ball_in_view(tiny_sequence, Material((0.9,) * 3, mirror=True))
        config = Config.from_preset("full", **SMALL, use_volume=False)
        pipe = Pipeline(config, tiny_sequence.camera, scene)
        result = pipe.process(tiny_sequence.frames[0])
        assert result.diagnostics["probe"]["memory"] == "current_frame"
