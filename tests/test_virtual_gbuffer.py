"""The virtual objects' depth in an auxiliary buffer: rays cast only near the objects."""

import numpy as np
from scipy.spatial.transform import Rotation

from arlight.pipeline.virtual_gbuffer import VirtualRaycaster, texel_origins
from arlight.pipeline.virtual_scene import demo_scene

RESOLUTION = 128
PIXEL_M = 4.0 / RESOLUTION


def _every_texel(raycaster: VirtualRaycaster, world_from_buffer: np.ndarray) -> np.ndarray:
    """The same buffer with a ray from every texel (what the rectangle must not change)."""
    origins = texel_origins(world_from_buffer, RESOLUTION, PIXEL_M)
    along = np.broadcast_to(world_from_buffer[:3, 2], origins.shape)
    t = raycaster._cast(origins, along)["t_hit"].numpy()
    return np.where(np.isfinite(t), t, 0.0).astype(np.float32).reshape(RESOLUTION, RESOLUTION)


def test_only_rays_near_the_objects_and_the_same_depth():
    raycaster = VirtualRaycaster(demo_scene())
    rng = np.random.default_rng(0)
    seen = 0
    for i in range(24):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.random(random_state=i).as_matrix()
        pose[:3, 3] = rng.normal(0.0, 1.5, 3)
        got = raycaster.orthographic_depth(pose, RESOLUTION, PIXEL_M)
        np.testing.assert_array_equal(got, _every_texel(raycaster, pose))
        seen += bool((got > 0).any())
    assert 5 <= seen < 24  # objects in some buffers, none in others


def test_objects_behind_the_image_plane_are_not_seen():
    raycaster = VirtualRaycaster(demo_scene())
    pose = np.eye(4)
    pose[2, 3] = 5.0  # the plane 5 m above the objects along +z, looking further +z
    assert not raycaster.orthographic_depth(pose, RESOLUTION, PIXEL_M).any()
    pose[2, 3] = -5.0  # 5 m below them, looking up at them
    assert raycaster.orthographic_depth(pose, RESOLUTION, PIXEL_M).any()
