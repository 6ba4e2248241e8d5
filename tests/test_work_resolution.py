"""The work resolution (`work_width`): the reduced frame, camera and geometry, and the pipeline
analysing a frame at half resolution while drawing its composite at the input's."""

import numpy as np
import pytest
from conftest import SMALL

from arlight.core.camera import PinholeCamera
from arlight.core.checks import depth_metres
from arlight.pipeline.color import intensity_from_rgb, srgb_to_linear
from arlight.pipeline.config import Config, FilterParams
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.work_resolution import (
    enlarge_geometry,
    reduce_depth,
    reduce_frame,
    work_scale,
)
from arlight.sources.synthetic import make_sequence


class TestReduceDepth:
    def test_agreeing_blocks_are_averaged(self):
        depth = np.array([[1.00, 1.02, 2.0, 2.0], [1.01, 1.01, 2.0, 2.0]], np.float32)
        out = reduce_depth(depth, 2)
        np.testing.assert_allclose(out, [[1.01, 2.0]], rtol=1e-6)

    def test_a_depth_edge_keeps_the_foreground(self):
        depth = np.array([[1.0, 3.0], [1.0, 3.0]], np.float32)
        assert reduce_depth(depth, 2)[0, 0] == pytest.approx(1.0)

    def test_holes_do_not_count_and_an_empty_block_stays_empty(self):
        depth = np.array([[0.0, 2.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0]], np.float32)
        np.testing.assert_array_equal(reduce_depth(depth, 2), [[2.0, 0.0]])

    def test_odd_sizes_round_up(self):
        depth = np.ones((5, 7), np.float32)
        out = reduce_depth(depth, 2)
        assert out.shape == (3, 4) and np.all(out == 1.0)


def test_reduced_camera_sees_the_block_centre():
    """Work pixel (i, j) is the centre of its block: its ray is the mean input ray."""
    camera = PinholeCamera.kinect_v1(64, 48)
    small = camera.reduced(2)
    assert (small.width, small.height) == (32, 24)
    rays_full = camera.ray_directions()
    rays_small = small.ray_directions()
    block = rays_full[4:6, 10:12].reshape(-1, 3)
    block = block / block[:, 2:3]
    centre = block.mean(axis=0)
    ray = rays_small[2, 5] / rays_small[2, 5, 2]
    np.testing.assert_allclose(ray, centre, atol=1e-9)


def test_reduced_frame_averages_linear_colour():
    color = np.zeros((4, 4, 3), np.uint8)
    color[:, ::2] = 255  # alternate black and white columns
    work = reduce_frame(color, srgb_to_linear(color), np.ones((4, 4), np.float32), 2)
    assert work.color_linear.shape == (2, 2, 3)
    np.testing.assert_allclose(work.color_linear, 0.5, atol=1e-6)  # linear light, not sRGB


def test_enlarged_geometry_has_the_input_shape():
    depth = np.full((3, 4), 2.0, np.float32)
    normals = np.zeros((3, 4, 3), np.float32)
    normals[..., 2] = -1.0
    d, n = enlarge_geometry(depth, normals, 2, (5, 7))
    assert d.shape == (5, 7) and n.shape == (5, 7, 3)
    assert np.all(d == 2.0) and np.all(n[..., 2] == -1.0)


def test_windows_keep_their_footprint():
    """Pixel windows are given at 640 pixels wide and scale with the image."""
    params = FilterParams()
    assert params.at_width(640) is params
    half = params.at_width(320)
    assert (half.merge_window, half.smooth_window, half.normal_window) == (10, 4, 8)
    assert params.at_width(40).denoise_window == 1  # never below one pixel


@pytest.fixture(scope="module")
def scene_160():
    return make_sequence(num_frames=3, width=160, height=120, sensor_noise=False)


def test_pipeline_at_half_resolution(scene_160):
    """work_width 80 (half of 160): a result like the full-resolution one's (the same
    scene, lit the same), the transfer's samples on the 80x60 work image."""
    results = {}
    for scale in (1, 2):
        config = Config.from_preset("full", work_width=160 // scale, **SMALL)
        pipeline = Pipeline(config, scene_160.camera)
        for frame in scene_160.frames:
            results[scale] = pipeline.process(frame)
        if scale == 2:
            assert pipeline.work_scale == 2 and pipeline.work_camera.width == 80
            assert pipeline._volume.camera.width == 80
    a, b = (results[s].dominant_direction_world for s in (1, 2))
    angle = np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0)))
    assert angle < 10.0, f"half resolution turned the light by {angle:.1f} degrees"
    assert results[2].confidence.samples > 1000


def test_work_width_rules():
    assert work_scale(640, 320) == 2 and work_scale(320, 320) == 1 and work_scale(1280, 320) == 4
    assert work_scale(480, 320) == 1 and work_scale(640, 0) == 1
    with pytest.raises(ValueError, match="work_width"):
        Config.from_preset("fast", work_width=10)


def test_fast_steps_the_same_grid_at_half_resolution():
    """rt_subsample is in input pixels: fast (4) steps 2 work pixels at 640x480."""
    pipeline = Pipeline(Config.from_preset("fast", **SMALL), PinholeCamera.kinect_v1(640, 480))
    assert pipeline.work_scale == 2 and pipeline._transfer_params.rt_subsample == 2


def test_depth_filter_at_half_width(scene_160):
    """filter_width 80 on a 160x120 work image: the filter runs at 80x60 and its depth comes
    back at 160x120, on smooth surfaces within millimetres of the filter run at full size."""
    frame = scene_160.frames[0]
    depths = {}
    for width in (0, 80):
        config = Config.from_preset("full", filter_width=width, **SMALL)
        pipeline = Pipeline(config, scene_160.camera)
        intensity = intensity_from_rgb(frame.color)
        depths[width] = pipeline._filtered_depth(
            depth_metres(frame.depth, frame.depth_scale), None, intensity
        )
    full, half = depths[0], depths[80]
    assert half.shape == full.shape == frame.depth.shape
    both = (full > 0) & (half > 0)
    assert both.mean() > 0.9 * (full > 0).mean()
    assert np.median(np.abs(full[both] - half[both])) < 0.003


def test_filter_width_rules():
    with pytest.raises(ValueError, match="filter_width"):
        FilterParams(filter_width=10)
    assert FilterParams(filter_width=320).filter_width == 320


def _segments_of(pipeline: Pipeline, linear: np.ndarray, depth: np.ndarray) -> int:
    """How many material segments `pipeline` draws on a frame (linear colour, metres at the
    input's size), reduced to its work image as the pipeline reduces it."""
    from types import SimpleNamespace

    from arlight.pipeline.work_resolution import reduce_image

    s = pipeline.work_scale
    shape = (-(-depth.shape[0] // s), -(-depth.shape[1] // s))
    geometry = SimpleNamespace(depth_m=reduce_depth(depth, s), plane=None)
    return len(np.unique(pipeline._segments(reduce_image(linear, shape), geometry)))


@pytest.fixture
def kitchen_frame(shared_data):
    """(camera, linear colour, depth in metres) of the first real 7-Scenes frame."""
    from arlight.sources.sequence import open_sequence

    folder = shared_data / "real" / "7scenes_redkitchen"
    if not folder.exists():
        pytest.skip(f"no 7-Scenes frames at {folder}")
    seq = open_sequence(folder)
    frame = seq.frame(0)
    return (
        seq.camera,
        srgb_to_linear(frame.color),
        depth_metres(frame.depth, frame.depth_scale),
    )


def test_a_reduced_work_image_draws_the_segments_of_the_full_one(kitchen_frame):
    """The material segments' graph threshold and smallest segment are in input pixels: on a
    real 7-Scenes frame (many materials) the segments of the frame analysed at 320x240 are
    as fine as at 640x480 (107 segments against 109). Before, they were 4x larger in area
    (22 against 109), and `fast` wandered 30 degrees over the 100 frames instead of 13
    (decision 0058)."""
    camera, linear, depth = kitchen_frame
    counts = {}
    for work_width in (0, 320):
        pipeline = Pipeline(Config.from_preset("full", work_width=work_width), camera)
        counts[pipeline.work_scale] = _segments_of(pipeline, linear, depth)
    assert counts[2] >= 0.7 * counts[1], counts


def test_fast_draws_finer_segments_than_full(kitchen_frame):
    """`fast` sets segment_coarseness 0.5 (decision 0059): on the real 7-Scenes frame its
    segments are finer than `full`'s, both analysed at the input's size."""
    camera, linear, depth = kitchen_frame
    counts = {
        preset: _segments_of(
            Pipeline(Config.from_preset(preset, work_width=0), camera), linear, depth
        )
        for preset in ("full", "fast")
    }
    assert counts["fast"] > 1.5 * counts["full"], counts
    with pytest.raises(ValueError, match="--set segment_coarseness"):
        Config.from_preset("fast", segment_coarseness=0)
