"""The moderngl G-buffer of benchmarks/gbuffer_renderers.py agrees with Open3D's ray casting.

Both sample the same triangles at the pixel centres, so they should agree to float rounding:
measured at 640x480 (llvmpipe), IoU 1.0, depth 0.0001 mm, normals 0.001 degrees. The bounds
below are loose for other GL drivers yet tight enough to catch a projection off by half a
pixel (a one-pixel shift of cx gives IoU 0.981, depth 0.6 mm, normals 1.1 degrees) or a
flipped image. Skipped where moderngl or an EGL context is not available.
"""

import numpy as np
import pytest

from arlight.core.camera import PinholeCamera
from arlight.pipeline.virtual_gbuffer import VirtualRaycaster
from benchmarks.gbuffer_renderers import (
    GLGBufferRenderer,
    agreement,
    bench_scene,
    camera_pose,
    gl_context,
)


@pytest.fixture(scope="module")
def ctx():
    pytest.importorskip("moderngl")
    context, why = gl_context()
    if context is None:
        pytest.skip(f"no moderngl EGL context: {why}")
    yield context
    context.release()


@pytest.mark.parametrize("with_torus", [False, True])
def test_moderngl_gbuffer_matches_open3d(ctx, with_torus):
    scene = bench_scene(5000, with_torus=with_torus)
    camera = PinholeCamera.kinect_v1(640, 480)
    pose = camera_pose(7)
    expected = VirtualRaycaster(scene).camera_gbuffer(camera, pose)
    renderer = GLGBufferRenderer(scene, ctx)
    try:
        got = renderer.camera_gbuffer(camera, pose)
    finally:
        renderer.release()
    assert got.depth_m.shape == (480, 640) and got.normals_cam.shape == (480, 640, 3)
    assert got.object_index.dtype == np.int32
    a = agreement(expected, got)
    assert min(a["pixels_hit"]) > 20000  # the objects are in view
    assert a["iou"] > 0.995
    assert a["depth_mm_median"] < 0.1
    assert a["normal_deg_median"] < 0.2
    assert a["same_object"] > 0.999
    np.testing.assert_array_equal(got.depth_m[~got.hit], 0.0)
    both = got.hit & expected.hit
    np.testing.assert_array_equal(got.albedo[both], expected.albedo[both])
