"""Differential rendering (section 5.4 of seeds/000; pipeline/rendering.py) on analytic scenes.

The scene, built here in NumPy rather than rendered: a camera 1 m from the world origin
looking down at 45 degrees onto the ground plane y = 0 (world +Y up; depth and normals
exact per pixel), a grey ground whose colour is the Lambertian shading of the known light
(so the frame is self-consistent), and a virtual sphere standing on the origin. The light
is a delta from 35 degrees above the horizon on the +X or -X side (4 SH bands) plus a small
constant ambient radiance. `DifferentialRenderer` is driven directly with `RenderInputs`
(no auxiliary buffers, no support plane), except in the Pipeline tests at the end.

What is proved: the shadow falls where the light puts it and moves with the light; real
geometry in front hides the object; nothing virtual -> the input bit for bit, and pixels
outside the recomputed region are the input; virtual pixels are shaded albedo / pi * E;
bad objects give a clear SceneError or a finite frame; the fast path and the paste baseline
keep those properties; an anchored object is placed on the support plane under its pixel.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import cv2
import numpy as np
import pytest
from conftest import SMALL

from arlight.core.camera import PinholeCamera
from arlight.evaluation import angular_error_deg
from arlight.pipeline import rendering, sh
from arlight.pipeline import virtual_scene as vs
from arlight.pipeline.color import luminance, srgb_to_linear
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.rendering import (
    DifferentialRenderer,
    RenderInputs,
    RenderOutput,
    encode_where,
    linear_to_srgb_u8,
)
from arlight.pipeline.virtual_gbuffer import VirtualRaycaster
from arlight.pipeline.virtual_scene import (
    Anchor,
    Material,
    SceneError,
    VirtualObject,
    VirtualScene,
    object_from_open3d,
    sphere_mesh,
)
from arlight.sources.synthetic import make_sequence

WIDTH, HEIGHT = 160, 120
SPHERE_RADIUS_M = 0.1
SPHERE_ALBEDO = 0.6
GROUND_ALBEDO = 0.5
LIGHT_ELEVATION_DEG = 35.0
LIGHT_INTENSITY = 2.0  # integrated radiance of the delta (the irradiance it gives, facing it)
AMBIENT_RADIANCE = 0.1  # constant over the sphere: band 0 only
UP = np.array([0.0, 1.0, 0.0])


# ------------------------------------------------------------------ the analytic scene
@dataclasses.dataclass
class GroundView:
    """A camera over the ground plane y = 0. depth_m (H, W) float32 exact, 0 above the
    horizon; normals_cam (H, W, 3) the plane's up in the camera frame; rays_world (H, W, 3)
    the pixel rays in the world frame, scaled to unit camera z (so t along them is depth);
    eye (3,) the camera centre, world."""

    camera: PinholeCamera
    world_from_cam: np.ndarray
    depth_m: np.ndarray
    normals_cam: np.ndarray
    rays_world: np.ndarray

    @property
    def eye(self) -> np.ndarray:
        return self.world_from_cam[:3, 3]

    def points_world(self) -> np.ndarray:
        """(H, W, 3) the ground point seen at each pixel (garbage where depth is 0)."""
        return self.eye + self.depth_m[..., None].astype(np.float64) * self.rays_world

    def project(self, point_world) -> tuple[np.ndarray, float]:
        """((u, v), camera z in metres) of a world point."""
        rot, eye = self.world_from_cam[:3, :3], self.eye
        p = rot.T @ (np.asarray(point_world, np.float64) - eye)
        c = self.camera
        return np.array([c.fx * p[0] / p[2] + c.cx, c.fy * p[1] / p[2] + c.cy]), float(p[2])


def look_at(eye, target) -> np.ndarray:
    """world_from_cam (OpenCV axes: x right, y down, z forward) at eye looking at target,
    the image's up along world +Y."""
    eye = np.asarray(eye, np.float64)
    forward = np.asarray(target, np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, UP)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(forward, right), forward, eye
    return m


def ground_view(
    width: int = WIDTH, height: int = HEIGHT, distance_m: float = 1.0, tilt_deg: float = 45.0
) -> GroundView:
    """Kinect-v1 intrinsics, camera distance_m from the origin in the y-z plane, tilt_deg
    above the ground, looking at the origin."""
    camera = PinholeCamera.kinect_v1(width, height)
    tilt = math.radians(tilt_deg)
    pose = look_at([0.0, distance_m * math.sin(tilt), distance_m * math.cos(tilt)], [0, 0, 0])
    uu, vv = np.meshgrid(np.arange(width), np.arange(height))
    rays_cam = np.stack(
        [(uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy, np.ones(uu.shape)], axis=-1
    )
    rays_world = rays_cam @ pose[:3, :3].T
    t = -pose[1, 3] / np.where(rays_world[..., 1] < 0, rays_world[..., 1], -1e-300)
    depth = np.where(rays_world[..., 1] < 0, t, 0.0).astype(np.float32)
    normals = np.broadcast_to(pose[:3, :3].T @ UP, (height, width, 3)).astype(np.float32)
    normals = np.where(depth[..., None] > 0, normals, 0.0).astype(np.float32)
    return GroundView(camera, pose, depth, normals, rays_world)


def light_direction(side: int, elevation_deg: float = LIGHT_ELEVATION_DEG) -> np.ndarray:
    """Unit world direction towards the light, on the +X (side 1) or -X (side -1) side."""
    e = math.radians(elevation_deg)
    return np.array([side * math.cos(e), math.sin(e), 0.0])


def light_sh(
    direction: np.ndarray, intensity: float = LIGHT_INTENSITY, ambient: float = AMBIENT_RADIANCE
) -> np.ndarray:
    """(16,) world-frame radiance SH: the delta (4 bands) plus a constant ambient radiance."""
    coeffs = sh.directional_light(direction, intensity, 4)
    coeffs[0] += ambient / sh.sh_basis(UP, 1)[0]  # constant radiance `ambient`
    return coeffs


def irradiance(coeffs: np.ndarray, normals_world: np.ndarray) -> np.ndarray:
    """(K,) analytic irradiance of the band-limited light on normals (K, 3), no occlusion."""
    return np.atleast_1d(
        sh.evaluate(sh.irradiance_from_radiance(coeffs), np.atleast_2d(normals_world))
    )


def frame_inputs(view: GroundView, coeffs: np.ndarray) -> RenderInputs:
    """The frame of the grey ground under the light: GROUND_ALBEDO / pi * E(up), in sRGB."""
    h, w = view.depth_m.shape
    ground = GROUND_ALBEDO / math.pi * float(irradiance(coeffs, UP)[0])
    color = linear_to_srgb_u8(np.full((h, w, 3), ground))
    return RenderInputs(
        color,
        srgb_to_linear(color),
        view.depth_m,
        view.normals_cam,
        view.world_from_cam,
        [],
        None,
        coeffs,
    )


def sphere(
    name: str = "ball",
    radius_m: float = SPHERE_RADIUS_M,
    base_world=(0.0, 0.0, 0.0),
    albedo: float = SPHERE_ALBEDO,
) -> VirtualObject:
    """A virtual UV sphere whose lowest point is at base_world."""
    pose = np.eye(4)
    pose[:3, 3] = base_world
    return object_from_open3d(name, sphere_mesh(radius_m), pose, Material((albedo,) * 3))


def render(
    view: GroundView,
    coeffs: np.ndarray,
    objects,
    inputs: RenderInputs | None = None,
    **config_changes,
) -> tuple[RenderInputs, RenderOutput, DifferentialRenderer]:
    """One render of `objects` into the ground frame (or `inputs`), with flat config keys."""
    renderer = DifferentialRenderer(
        VirtualScene(tuple(objects)), view.camera, Config().replace(**config_changes)
    )
    inputs = inputs if inputs is not None else frame_inputs(view, coeffs)
    return inputs, renderer.render(inputs), renderer


def darkened(inputs: RenderInputs, out: RenderOutput, fraction: float = 0.1) -> np.ndarray:
    """(H, W) bool: real (non-virtual) pixels whose linear luminance fell by > fraction."""
    before = luminance(inputs.color_linear)
    after = luminance(srgb_to_linear(out.composite))
    return ~out.virtual_mask & (after < (1.0 - fraction) * before)


def centroid(mask: np.ndarray) -> np.ndarray:
    v, u = np.nonzero(mask)
    return np.array([u.mean(), v.mean()])


def shadow_prediction(
    view: GroundView, direction: np.ndarray, n_directions: int
) -> tuple[np.ndarray, float]:
    """((u, v) of the shadow's centre, tolerance in pixels) for the sphere on the origin.

    Centre: the sphere's centre projected along -direction onto y = 0, then into the image.
    Tolerance, in metres on the ground, converted with f / z at that point:
    * SSDO shadows from N discrete directions: the light's lobe is only seen through the
      pattern's directions, up to half their mean spacing, delta = sqrt(4 pi / N) / 2, from
      where it is (12.7 deg for N = 64). An elevation error delta moves the centre R cot(e)
      by R delta / sin(e)^2 along the light's azimuth (0.67 R at 35 deg).
    * The sphere itself hides the part of the shadow next to its base (those pixels are
      virtual, not counted), pulling the visible centroid away from it: at most R / 2.
    Measured over pattern seeds 0-5 at 160x120: 1.6-8.4 px against a tolerance of 15.4 px.
    A shadow that ignored the light's direction (a blob around the base) is 1.43 R = 18.7 px
    from the centre, and the mirror test below separates the two sides by ~37 px.
    """
    r = SPHERE_RADIUS_M
    centre = np.array([0.0, r, 0.0])
    on_ground = centre - r / direction[1] * direction
    uv, z = view.project(on_ground)
    delta = 0.5 * math.sqrt(4.0 * math.pi / n_directions)
    elevation = math.asin(direction[1])
    tolerance_m = r * delta / math.sin(elevation) ** 2 + 0.5 * r
    return uv, view.camera.fx * tolerance_m / z


def analytic_sphere_hit(view: GroundView, centre, radius_m: float) -> np.ndarray:
    """(H, W) depth of the first hit of each pixel ray on the exact sphere (inf: none)."""
    oc = view.eye - np.asarray(centre, np.float64)
    d = view.rays_world
    a = np.einsum("hwi,hwi->hw", d, d)
    b = d @ oc
    c = oc @ oc - radius_m**2
    disc = b * b - a * c
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where((disc > 0) & (t > 0), t, np.inf)


def within_reach(view: GroundView, renderer: DifferentialRenderer) -> np.ndarray:
    """(H, W) bool: ground pixels within rt_radius_m (+ 1 cm for the mesh) of the sphere
    standing on the origin, where a transfer sample can meet it."""
    centre = np.array([0.0, SPHERE_RADIUS_M, 0.0])
    distance = np.linalg.norm(view.points_world() - centre, axis=-1) - SPHERE_RADIUS_M
    return (view.depth_m > 0) & (distance <= renderer.config.transfer.rt_radius_m + 0.01)


@pytest.fixture(scope="module")
def view() -> GroundView:
    return ground_view()


@pytest.fixture(scope="module")
def lit_from_plus_x(view):
    """(inputs, output, renderer) of the sphere on the origin lit from the +X side."""
    coeffs = light_sh(light_direction(+1))
    return render(view, coeffs, [sphere()])


# ------------------------------------------------------------------ 1. shadow position
class TestShadowPosition:
    @pytest.mark.parametrize("side", [+1, -1])
    def test_shadow_centroid_where_the_light_puts_it(self, view, side):
        """The centroid of the ground pixels darkened by > 10 % lies within the derived
        tolerance of the projected shadow centre (see shadow_prediction)."""
        direction = light_direction(side)
        inputs, out, renderer = render(view, light_sh(direction), [sphere()])
        dark = darkened(inputs, out)
        assert dark.sum() > 100  # a shadow of some size: R = 13 px, so ~500 px
        expected, tolerance = shadow_prediction(
            view, direction, renderer.config.transfer.rt_directions
        )
        assert np.linalg.norm(centroid(dark) - expected) < tolerance

    def test_light_from_the_other_side_moves_the_shadow_to_the_other_side(self, view):
        """Mirroring the light about the x = 0 plane (which the camera looks along) moves
        the shadow from the left of the sphere's base to its right, each by more than half
        the predicted offset: fails if shadows ignore the light's direction."""
        base_u = view.project([0.0, 0.0, 0.0])[0][0]
        found = {}
        for side in (+1, -1):
            direction = light_direction(side)
            inputs, out, renderer = render(view, light_sh(direction), [sphere()])
            found[side] = centroid(darkened(inputs, out))[0]
            predicted = shadow_prediction(view, direction, renderer.config.transfer.rt_directions)[
                0
            ][0]
            offset = predicted - base_u
            assert (found[side] - base_u) / offset > 0.5
        assert found[+1] < base_u < found[-1]


def test_encode_where_is_the_gathered_encoding_in_place():
    """encode_where writes linear_to_srgb_u8 of the chosen pixels into a view of the
    composite, and nothing else (NaN -> 0, clipped at 0 and 1)."""
    rng = np.random.default_rng(0)
    linear = rng.random((30, 40, 3)) * 1.2 - 0.1
    linear[5, 5, 1] = np.nan
    where = rng.random((30, 40)) < 0.6
    composite = np.full((50, 60, 3), 7, np.uint8)
    expected = composite.copy()
    expected[10:40, 5:45][where] = linear_to_srgb_u8(linear[where])
    encode_where(linear, where, composite[10:40, 5:45])
    np.testing.assert_array_equal(composite, expected)
    assert composite[15, 10, 1] == 0 and np.any(composite != 7)


def test_encode_scaled_where_is_numpys_sum_encoded_in_place():
    """encode_scaled_where writes the codes of linear * ratio + delta (float64, as numpy
    makes it) at the chosen pixels of a view, from float32 colours, and nothing else."""
    from arlight.pipeline.srgb_encoding import encode_scaled_where

    rng = np.random.default_rng(1)
    linear = rng.random((30, 40, 3)).astype(np.float32)
    ratio = rng.uniform(0.3, 1.5, (30, 40))
    delta = rng.normal(0.0, 0.02, (30, 40, 3))
    where = rng.random((30, 40)) < 0.6
    composite = np.full((50, 60, 3), 7, np.uint8)
    expected = composite.copy()
    summed = linear.astype(np.float64) * ratio[..., None] + delta
    expected[10:40, 5:45][where] = linear_to_srgb_u8(summed[where])
    encode_scaled_where(linear, ratio, delta, where, composite[10:40, 5:45])
    np.testing.assert_array_equal(composite, expected)
    assert np.any(composite != 7)


# ------------------------------------------------------------------ 2. real occluder
class TestRealOccluder:
    @pytest.mark.parametrize("subsample, blur, levels", [(1, 2, 0), (2, 4, 1), (4, 8, 0)])
    def test_hand_in_front_hides_the_covered_part_of_the_sphere(
        self, view, subsample, blur, levels
    ):
        """A real 'hand' (a patch 0.5 m from the camera, facing it) over the left half of
        the sphere's pixels: no pixel of it is virtual, and it keeps its input colour bit
        for bit (the sphere is 0.4 m behind it and the light comes from the camera's side of
        it, so nothing there changes); the uncovered half of the sphere is still rendered.
        Also on full's 2x2 and fast's 4x4 grids, whose up-sampling must not carry the
        ground's shadow across the hand's edge (before the depth test it changed 7 % and
        18 % of the hand's pixels, by up to 5 levels): at most `levels` on 1 % of them."""
        coeffs = light_sh(light_direction(+1))
        grid = {"render_subsample": subsample, "render_blur_radius_px": blur}
        _, bare, _ = render(view, coeffs, [sphere()], **grid)
        rows, cols = np.nonzero(bare.virtual_mask)
        hand = np.zeros(view.depth_m.shape, bool)
        base_u = int(round(view.project([0.0, SPHERE_RADIUS_M, 0.0])[0][0]))
        hand[rows.min() - 5 : rows.max() + 6, cols.min() - 5 : base_u] = True
        inputs = frame_inputs(view, coeffs)
        depth = inputs.depth_m.copy()
        depth[hand] = 0.5
        normals = inputs.normals_cam.copy()
        normals[hand] = (0.0, 0.0, -1.0)
        color = inputs.color.copy()
        color[hand] = (190, 140, 110)
        inputs = dataclasses.replace(
            inputs,
            color=color,
            color_linear=srgb_to_linear(color),
            depth_m=depth,
            normals_cam=normals,
        )
        _, out, _ = render(view, coeffs, [sphere()], inputs=inputs, **grid)
        assert not np.any(out.virtual_mask[hand])
        change = np.abs(out.composite[hand].astype(int) - color[hand]).max(axis=1)
        assert change.max() <= levels and np.mean(change > 0) <= 0.01
        uncovered = bare.virtual_mask & ~hand
        assert uncovered.sum() > 0.3 * bare.virtual_mask.sum()
        np.testing.assert_array_equal(out.virtual_mask, uncovered)
        assert np.any(out.composite[uncovered] != color[uncovered])


# ------------------------------------------------------------------ 3. nothing virtual
@pytest.fixture(scope="module")
def tiny_sequence():
    return make_sequence(num_frames=3, width=160, height=120, sensor_noise=False)


class TestNothingToRender:
    @pytest.mark.parametrize("scene", [None, VirtualScene()], ids=["none", "empty"])
    def test_pipeline_without_objects_leaves_the_input(self, tiny_sequence, scene):
        """No scene, or an empty one: the Rendering stage costs nothing and FrameResult's
        composite is None, which means the input frame."""
        pipe = Pipeline(Config.from_preset("full", **SMALL), tiny_sequence.camera, scene)
        result = pipe.process(tiny_sequence.frames[0])
        assert result.composite is None
        assert pipe.last_render is None
        assert result.timings_ms["Rendering"] == 0.0

    @pytest.mark.parametrize("behind_m", [2.0, 0.15], ids=["far", "within-reach"])
    def test_object_behind_the_camera_leaves_the_input_bit_for_bit(self, view, behind_m):
        """A sphere behind the camera (far, or so close that its sample reach straddles the
        image plane and the whole image is examined): nothing is virtual, nothing changes."""
        coeffs = light_sh(light_direction(+1))
        back = view.eye - behind_m * view.world_from_cam[:3, 2]
        inputs, out, _ = render(view, coeffs, [sphere(base_world=back - [0, 0.1, 0])])
        assert np.array_equal(out.composite, inputs.color)
        assert not out.virtual_mask.any() and not out.region.any()

    def test_pipeline_with_an_object_out_of_view_composites_the_input(self, tiny_sequence):
        """End to end: an object placed far behind the first camera gives a composite equal
        to the input frame."""
        frame = tiny_sequence.frames[0]
        back = frame.pose[:3, 3] - 3.0 * frame.pose[:3, 2]
        scene = VirtualScene((sphere(base_world=back),))
        pipe = Pipeline(Config.from_preset("full", **SMALL), tiny_sequence.camera, scene)
        result = pipe.process(frame)
        assert result.composite is not None
        assert np.array_equal(result.composite, frame.color)

    def test_pixels_outside_the_region_are_the_input(self, view):
        """In a render at every pixel (the paper's Ours), every pixel outside
        RenderOutput.region is the input bit for bit, the region is a minority of the frame,
        and it holds only virtual pixels and real ones within rt_radius_m of the object (1 cm
        slack for the mesh). The grids: TestFastPath."""
        inputs, out, renderer = render(
            view, light_sh(light_direction(+1)), [sphere()], render_subsample=1
        )
        outside = ~out.region
        assert outside.sum() > 0.5 * outside.size
        assert np.array_equal(out.composite[outside], inputs.color[outside])
        assert not np.any(out.region & ~out.virtual_mask & ~within_reach(view, renderer))


# ------------------------------------------------------------------ 4. virtual pixels
class TestVirtualPixels:
    @staticmethod
    def _world_normals(out: RenderOutput, inputs: RenderInputs) -> np.ndarray:
        return out.gbuffer.normals_cam.astype(np.float64) @ inputs.world_from_cam[:3, :3].T

    def test_lit_side_brighter_than_shadowed_side(self, lit_from_plus_x):
        """Sphere pixels facing the light (n . l > 0.5) are over twice as bright as those
        facing away (n . l < -0.5). Analytically the ratio is ~7 (0.34 vs 0.047 linear);
        the far side also gets the lit ground's bounce (eq. 14), so 2 leaves room."""
        inputs, out, _ = lit_from_plus_x
        n = self._world_normals(out, inputs)
        facing = n @ light_direction(+1)
        value = srgb_to_linear(out.composite).mean(axis=2)
        lit = out.virtual_mask & (facing > 0.5)
        away = out.virtual_mask & (facing < -0.5)
        assert lit.sum() > 50 and away.sum() > 10
        assert value[lit].mean() > 2.0 * value[away].mean()

    def test_top_of_the_sphere_is_albedo_over_pi_times_irradiance(self, lit_from_plus_x):
        """Pixels facing up (within 20 deg) see nothing above them: their colour is
        albedo / pi * E(n), the exact clamped-cosine irradiance, within 1 % (8-bit rounding:
        half a step of sRGB near 0.27 linear is 0.8 %). The renderer's 64 directions alone
        miss it by several per cent (4.4 % here, asserted below): the unoccluded part of the
        virtual pixels' transfer is made exact (`unoccluded_quadrature_error`)."""
        inputs, out, renderer = lit_from_plus_x
        n = self._world_normals(out, inputs)
        top = out.virtual_mask & (n[..., 1] > math.cos(math.radians(20)))
        assert top.sum() >= 20
        measured = srgb_to_linear(out.composite)[top].mean(axis=0)
        normals = n[top]
        analytic = SPHERE_ALBEDO / math.pi * irradiance(inputs.light_sh, normals).mean()
        np.testing.assert_allclose(measured, analytic, rtol=0.01)
        dirs = renderer.pattern.directions @ inputs.world_from_cam[:3, :3].T
        basis = sh.sh_basis(dirs, 4) * (4.0 * math.pi / len(dirs))
        quadrature = (
            SPHERE_ALBEDO
            / math.pi
            * np.mean(np.maximum(normals @ dirs.T, 0.0) @ basis @ inputs.light_sh)
        )
        assert abs(quadrature - analytic) / analytic > 0.03


# ------------------------------------------------------------------ 5. bad input
class TestBadInput:
    def test_camera_inside_the_object_gives_a_finite_frame(self, view):
        """The camera centre inside a sphere: every pixel shows its inside, no exception and
        no NaN / inf arithmetic on the way (RuntimeWarnings turned into errors)."""
        coeffs = light_sh(light_direction(+1))
        radius = 0.3
        obj = sphere(radius_m=radius, base_world=view.eye - [0.0, radius, 0.0])
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            inputs, out, _ = render(view, coeffs, [obj])
        assert out.composite.shape == inputs.color.shape
        assert out.composite.dtype == np.uint8
        assert out.virtual_mask.all()

    def test_object_sunk_into_the_ground_shows_only_above_it(self, view):
        """A sphere with its centre on the ground: a pixel is virtual exactly where the ray
        meets the sphere above the ground. Compared where the exact sphere decides it by
        more than 1 cm along the ray (the mesh lies within ~1 mm inside the sphere; the
        depth test's contact bias is 5 mm); the undecided rim is a small minority."""
        coeffs = light_sh(light_direction(+1))
        r = SPHERE_RADIUS_M
        _, out, _ = render(view, coeffs, [sphere(base_world=(0.0, -r, 0.0))])
        t_sphere = analytic_sphere_hit(view, (0.0, 0.0, 0.0), r)
        t_sphere_inner = analytic_sphere_hit(view, (0.0, 0.0, 0.0), r - 0.002)
        ground = view.depth_m.astype(np.float64)
        above = t_sphere_inner < ground - 0.01
        hidden = t_sphere > ground + 0.01  # includes no hit at all (inf)
        assert above.sum() > 100
        assert out.virtual_mask[above].all()
        assert not out.virtual_mask[hidden].any()
        undecided = ~above & ~hidden
        assert undecided.sum() < 0.3 * above.sum()

    def test_too_many_triangles_in_an_object_is_refused_naming_it(self, monkeypatch):
        """MAX_TRIANGLES (lowered here, instead of allocating millions): a SceneError that
        names the object and says to simplify the mesh."""
        mesh = sphere_mesh(0.1)
        monkeypatch.setattr(vs, "MAX_TRIANGLES", len(mesh.triangles) - 1)
        with pytest.raises(SceneError, match="'huge'.*triangles.*simplify"):
            object_from_open3d("huge", mesh, np.eye(4))

    def test_too_many_triangles_in_the_scene_is_refused(self, monkeypatch):
        """Objects each under MAX_TRIANGLES but over it together: SceneError."""
        n = len(sphere_mesh(0.1).triangles)
        monkeypatch.setattr(vs, "MAX_TRIANGLES", n + n // 2)
        a = object_from_open3d("a", sphere_mesh(0.1), np.eye(4))
        b = object_from_open3d("b", sphere_mesh(0.1), np.eye(4))
        with pytest.raises(SceneError, match="triangles.*simplify"):
            VirtualScene((a, b))

    def test_nan_vertices_are_refused_naming_the_object(self):
        good = sphere("nan_ball")
        vertices = good.vertices.copy()
        vertices[3, 1] = np.nan
        with pytest.raises(SceneError, match="'nan_ball'.*finite"):
            dataclasses.replace(good, vertices=vertices)


# ------------------------------------------------------------------ 6. fast path
class TestFastPath:
    @pytest.mark.parametrize("subsample, blur", [(2, 4), (4, 8)])  # full's and fast's grids
    def test_subsampled_shadow_within_tolerance_and_input_outside_region(
        self, view, subsample, blur
    ):
        """render_subsample 2 (full) and 4 (OursFast): the shadow centroid keeps the
        tolerance of the per-pixel render, and pixels outside the region are still the input
        bit for bit."""
        direction = light_direction(+1)
        inputs, out, renderer = render(
            view,
            light_sh(direction),
            [sphere()],
            render_subsample=subsample,
            render_blur_radius_px=blur,
        )
        expected, tolerance = shadow_prediction(
            view, direction, renderer.config.transfer.rt_directions
        )
        assert np.linalg.norm(centroid(darkened(inputs, out)) - expected) < tolerance
        outside = ~out.region
        assert np.array_equal(out.composite[outside], inputs.color[outside])
        # the region: the pixels within reach of the object, grown by the up-sampling's
        # support (bicubic: 2 grid cells of `step` px) and the Gaussian's radius
        p = renderer.config.render
        grow = 2 * p.render_subsample + p.render_blur_radius_px + 1
        near = within_reach(view, renderer) | out.virtual_mask
        kernel = np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)
        allowed = cv2.dilate(near.astype(np.uint8), kernel).astype(bool)
        assert not np.any(out.region & ~allowed)
        assert outside.sum() > 0.2 * outside.size


# ------------------------------------------------------------------ 7. paste baseline
class TestPaste:
    def test_paste_changes_only_virtual_pixels(self, view):
        """render_mode paste: no real pixel changes (no shadow), the region is the object,
        and the object is shaded by the unshadowed light: albedo / pi * E(n) exactly (to
        the 8-bit rounding), E the analytic SH irradiance."""
        coeffs = light_sh(light_direction(+1))
        inputs, out, _ = render(view, coeffs, [sphere()], render_mode="paste")
        real = ~out.virtual_mask
        assert out.virtual_mask.sum() > 100
        assert np.array_equal(out.composite[real], inputs.color[real])
        np.testing.assert_array_equal(out.region, out.virtual_mask)
        n = (
            out.gbuffer.normals_cam[out.virtual_mask].astype(np.float64)
            @ inputs.world_from_cam[:3, :3].T
        )
        expected = linear_to_srgb_u8(
            SPHERE_ALBEDO / math.pi * np.maximum(irradiance(coeffs, n), 0.0)
        )
        diff = out.composite[out.virtual_mask].astype(int) - expected[:, None].astype(int)
        assert np.abs(diff).max() <= 1


# ------------------------------------------------------------------ 8. anchored object
class TestAnchoredInPipeline:
    ANCHOR_PIXEL = (40.0, 100.0)  # on the ground, left of the objects in frame 0

    def test_anchored_object_is_placed_under_its_pixel(self, tiny_sequence):
        """The object waits for a support plane, is placed on the first frame that shows
        one, stands on the true ground (y = 0) under the anchor pixel of that frame's true
        pose (within the plane fit's error), upright, and stays put while the camera moves,
        rendered around its projection."""
        seq = tiny_sequence
        obj = object_from_open3d(
            "anchored",
            sphere_mesh(0.08),
            np.eye(4),
            Material((0.6, 0.6, 0.6)),
            Anchor(self.ANCHOR_PIXEL),
        )
        pipe = Pipeline(Config.from_preset("full", **SMALL), seq.camera, VirtualScene((obj,)))
        assert pipe.scene.anchored
        poses = []
        for frame in seq.frames:
            result = pipe.process(frame)
            assert not pipe.scene.anchored
            assert result.composite is not None
            poses.append(pipe.scene.objects[0].world_from_object.copy())
            inputs, out = pipe.last_render
            assert out.virtual_mask.sum() > 20
            # the object's pixels surround the projection of its centre in this frame
            centre = poses[-1] @ np.array([0.0, 0.08, 0.0, 1.0])
            cam = np.linalg.inv(frame.pose) @ centre
            uv = np.array(
                [
                    seq.camera.fx * cam[0] / cam[2] + seq.camera.cx,
                    seq.camera.fy * cam[1] / cam[2] + seq.camera.cy,
                ]
            )
            assert np.linalg.norm(centroid(out.virtual_mask) - uv) < 3.0
        for later in poses[1:]:
            np.testing.assert_array_equal(later, poses[0])
        base = poses[0][:3, 3]
        assert abs(base[1]) < 0.02  # on the ground y = 0
        assert angular_error_deg(poses[0][:3, 1], UP) < 3.0
        # the true ground point under the anchor pixel in frame 0
        pose0 = seq.frames[0].pose
        u, v = self.ANCHOR_PIXEL
        cam = seq.camera
        ray = pose0[:3, :3] @ np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0])
        truth = pose0[:3, 3] - pose0[1, 3] / ray[1] * ray
        assert np.linalg.norm(base - truth) < 0.03
        cam_base = np.linalg.inv(pose0) @ np.r_[base, 1.0]
        uv = np.array(
            [
                cam.fx * cam_base[0] / cam_base[2] + cam.cx,
                cam.fy * cam_base[1] / cam_base[2] + cam.cy,
            ]
        )
        assert np.linalg.norm(uv - self.ANCHOR_PIXEL) < 1.0

    def test_anchor_above_the_horizon_waits(self, tiny_sequence):
        """An anchor pixel in the sky never meets the plane: the object stays anchored and
        nothing is rendered (composite None), frame after frame."""
        obj = object_from_open3d("sky", sphere_mesh(0.08), np.eye(4), anchor=Anchor((80.0, 2.0)))
        pipe = Pipeline(
            Config.from_preset("full", **SMALL), tiny_sequence.camera, VirtualScene((obj,))
        )
        for frame in tiny_sequence.frames[:2]:
            assert pipe.process(frame).composite is None
            assert pipe.scene.anchored


# ------------------------------------------------------------------ known defects
class TestVirtualOccluderOnlyRemovesDirectLight:
    def test_ground_never_brighter_without_indirect_light(self, view):
        """With the one-bounce term off, adding a virtual object can only take light away
        from a real surface: no real pixel ends brighter than the input (1 LSB slack)."""
        coeffs = light_sh(light_direction(+1))
        inputs, out, _ = render(view, coeffs, [sphere()], render_indirect=False)
        real = ~out.virtual_mask
        gain = out.composite[real].astype(int) - inputs.color[real].astype(int)
        assert gain.max() <= 1


# ------------------------------------------------------------------ reflections of a panorama
class TestEnvironmentReflections:
    """A session lit by its 360-degree panorama: mirror and glossy objects reflect its HDR
    map (`RenderInputs.environment`), diffuse ones are as before."""

    @staticmethod
    def _environment(rotation: np.ndarray | None = None):
        """A 128 x 64 map: dark grey, a bright patch around world +X (rows 24-40, the
        columns of azimuth 90 degrees +-22)."""
        from arlight.pipeline.glossy import mip_pyramid
        from arlight.pipeline.rendering import EnvironmentMap

        hdr = np.full((64, 128, 3), 0.05, np.float32)
        hdr[24:40, 24:40] = (4.0, 3.0, 2.0)  # u = atan2(x, -z) / 2 pi: +X at column 32
        return hdr, EnvironmentMap(mip_pyramid(hdr), np.eye(3) if rotation is None else rotation)

    @pytest.mark.parametrize("turn_deg", [0.0, 90.0])
    def test_mirror_sphere_shows_the_map_along_the_mirrored_view(self, view, turn_deg):
        """Each mirror pixel is albedo x the map along the view direction mirrored about its
        normal, taken into the map's frame by map_from_world (a map turned 90 degrees about
        +y: a transposed or ignored rotation would show the patch elsewhere)."""
        from arlight.pipeline import equirect

        a = math.radians(turn_deg)
        turn = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        hdr, env = self._environment(turn)
        coeffs = light_sh(light_direction(+1))
        mirror_ball = object_from_open3d(
            "mirror",
            sphere_mesh(SPHERE_RADIUS_M),
            np.eye(4),
            Material((0.9, 0.9, 0.9), mirror=True),
        )
        inputs = dataclasses.replace(frame_inputs(view, coeffs), environment=env)
        _, out, _ = render(view, coeffs, [mirror_ball], inputs)
        vs_, us_ = np.nonzero(out.virtual_mask)
        assert len(vs_) > 100
        rays = np.stack(
            [
                (us_ - view.camera.cx) / view.camera.fx,
                (vs_ - view.camera.cy) / view.camera.fy,
                np.ones(len(us_)),
            ],
            1,
        )
        rays = rays @ view.world_from_cam[:3, :3].T
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        n = out.gbuffer.normals_cam[vs_, us_].astype(np.float64) @ view.world_from_cam[:3, :3].T
        r = rays - 2 * np.sum(rays * n, axis=1, keepdims=True) * n
        expected = 0.9 * equirect.sample_bilinear(hdr, r @ turn.T)  # albedo x the map
        got = srgb_to_linear(out.composite)[vs_, us_]
        assert (expected.min(axis=1) > 1.0).sum() > 5  # the patch, white in the 8-bit frame
        assert (expected.max(axis=1) < 0.1).sum() > 50  # the dark rest of the map
        np.testing.assert_allclose(got, np.clip(expected, 0, 1), atol=0.01)

    def test_a_mirror_pays_no_transfer_and_shows_the_same(self, view, monkeypatch):
        """Under a panorama, a mirror shows none of its diffuse light: the renderer skips its
        pixels' SSDO transfer (the diffuse sphere beside it keeps its own), and the
        composite is the one that computing them all gives."""
        _, env = self._environment()
        coeffs = light_sh(light_direction(+1))
        objects = [
            object_from_open3d(
                "mirror",
                sphere_mesh(SPHERE_RADIUS_M),
                np.eye(4),
                Material((0.9, 0.9, 0.9), mirror=True),
            ),
            sphere("matte", base_world=(0.25, 0.0, 0.0)),
        ]
        inputs = dataclasses.replace(frame_inputs(view, coeffs), environment=env)
        listed = []
        real_transfer = rendering.transfer_at_pixels

        def counting(*args, **kwargs):
            listed.append(len(args[7]))  # pixels_u
            return real_transfer(*args, **kwargs)

        monkeypatch.setattr(rendering, "transfer_at_pixels", counting)
        _, skipping, _ = render(view, coeffs, objects, inputs)
        index = skipping.gbuffer.object_index
        mirror = skipping.virtual_mask & (index == 0)
        matte = skipping.virtual_mask & (index == 1)
        assert mirror.sum() > 100 and matte.sum() > 100
        assert listed == [int(matte.sum())]
        monkeypatch.setattr(
            rendering.DifferentialRenderer,
            "_diffuse_shown",
            lambda self, frame, g, vs, us: np.ones(len(vs), bool),
        )
        _, every, _ = render(view, coeffs, objects, inputs)
        assert listed[-1] == int(skipping.virtual_mask.sum())
        np.testing.assert_array_equal(skipping.composite, every.composite)

    def test_diffuse_objects_ignore_the_environment(self, view):
        _, env = self._environment()
        coeffs = light_sh(light_direction(+1))
        plain = frame_inputs(view, coeffs)
        _, without, _ = render(view, coeffs, [sphere()], plain)
        _, with_env, _ = render(
            view, coeffs, [sphere()], dataclasses.replace(plain, environment=env)
        )
        np.testing.assert_array_equal(without.composite, with_env.composite)


class TestWithinReach:
    """`rendering.within_reach` (not this module's helper of that name) gives the
    brute-force answer with fewer distance queries."""

    @staticmethod
    def _scene_and_points():
        # a sphere of radius 0.2 m centred on the origin, its distance as the renderer asks it
        raycaster = VirtualRaycaster(
            VirtualScene((sphere(radius_m=0.2, base_world=(0.0, -0.2, 0.0)),))
        )
        # a 120 x 160 grid of ground points 4 mm apart with a 0.3 m step in height halfway
        # (a depth edge: neighbours far apart in 3D)
        v, u = np.mgrid[0:120, 0:160]
        points = np.stack(
            [(u - 80) * 0.004, np.where(u < 80, -0.25, 0.05), (v - 60) * 0.004], axis=-1
        ).astype(np.float64)
        calls = []

        def distance(p):
            calls.append(len(p))
            return raycaster.distance_to_objects(p)

        return points, distance, calls

    @pytest.mark.parametrize("reach", [0.02, 0.05, 0.1])
    def test_same_answer_as_every_point_with_fewer_queries(self, reach):
        points, distance, calls = self._scene_and_points()
        candidates = np.ones(points.shape[:2], bool)
        candidates[::7, ::5] = False  # holes: some tiles lose their anchor
        brute = distance(points[candidates]) <= reach
        calls.clear()
        fast = rendering.within_reach(points, candidates, distance, reach)
        np.testing.assert_array_equal(fast, brute)
        assert 0 < brute.sum() < len(brute)  # the boundary crosses the grid
        assert sum(calls) < 0.5 * len(brute)
