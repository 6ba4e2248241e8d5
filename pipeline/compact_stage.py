"""The compact sources as a session keeps them: what a frame's shadows are tested against
(the reconstruction, and the current depth image's mesh), and when to search the whole
hemisphere and when to follow the last source found (compact_light.py holds the model and
the search)."""

from __future__ import annotations

import numpy as np

from arlight.pipeline.compact_light import CompactFit, ShadowTester, fit_compact_source

DEPTH_MESH_STRIDE = 2  # the current frame's depth mesh at every 2nd pixel (a quarter)


def occluders(
    volume_scene, points_cam: np.ndarray, pose: np.ndarray, with_depth: bool
) -> list[tuple[object, np.ndarray]]:
    """(scene, world_from_scene) pairs the shadows are tested against: the reconstruction
    (`volume_scene`: the volume's mesh, world frame, or a depth mesh, camera frame) and,
    with_depth, the current frame's depth mesh too (moving things the volume has not
    fused, or has smeared)."""
    from arlight.pipeline.object_space_transfer import OcclusionScene, depth_mesh

    out = [(volume_scene, np.eye(4) if volume_scene.in_world else pose)]
    if with_depth and volume_scene.in_world:
        step = DEPTH_MESH_STRIDE
        out.append((OcclusionScene(depth_mesh(points_cam[::step, ::step])), pose))
    return out


# a tracked frame whose best direction explains less than this part of the gain of the
# source the last full search kept starts a full search at once (the light changed)
TRACK_KEEP_GAIN = 0.5


class CompactLightStage:
    """Per session: compact sources beside each frame's SH fit, against the current depth
    image's mesh at every `depth_stride`-th pixel (made each frame, a few ms); or, with
    `depth_stride` None, against the volume's mesh (rebuilt as object_space_transfer's scene
    is: every `update_interval` fused frames, 0.1-0.5 s each time), else the depth image's.

    With `search_interval` N > 1 the full search (the grid of candidates, the radius) runs
    on one frame in N; the frames between refine the last best direction within 7 degrees
    and keep its radius (a sun moves 0.25 degrees a minute), and search in full at once
    where the last search kept a source and the tracked direction's gain falls below
    TRACK_KEEP_GAIN of its gain (a light that moved or went out; one that appears waits for
    the next full search)."""

    def __init__(
        self,
        update_interval: int,
        scenes=None,
        search_interval: int = 5,
        depth_stride: int | None = None,
    ):
        """scenes: an ObjectSpaceTransfer whose cached scene to share (the session's
        rt_method raycast one), else one of this stage's own (volume's mesh only)."""
        from arlight.pipeline.object_space_transfer import ObjectSpaceTransfer

        self._scenes = scenes if scenes is not None else ObjectSpaceTransfer(update_interval)
        self.depth_stride = None if depth_stride is None else max(1, int(depth_stride))
        self.search_interval = max(1, int(search_interval))
        self._searched: CompactFit | None = None  # the last full search's fit
        self._last: CompactFit | None = None
        self._since_search = 0
        self.searches = 0  # full searches run (the rest tracked)
        self.last_searched = False  # whether the last frame's fit was a full search

    def occluder(self, points_cam: np.ndarray, volume):
        """The reconstruction as an OcclusionScene (see the class docstring); points_cam:
        (H, W, 3) the frame's filtered geometry (camera frame)."""
        if self.depth_stride is not None:
            from arlight.pipeline.object_space_transfer import OcclusionScene, depth_mesh

            step = self.depth_stride
            return OcclusionScene(depth_mesh(np.ascontiguousarray(points_cam[::step, ::step])))
        return self._scenes.scene(points_cam, volume)

    def fit_against(
        self,
        occluder,
        fit_state,
        points_cam: np.ndarray,
        normals_cam: np.ndarray,
        pixel_v: np.ndarray,
        pixel_u: np.ndarray,
        pose: np.ndarray,
        up_world: np.ndarray | None,
        options: dict,
        seed: int = 0,
        with_depth: bool = False,
    ) -> tuple[CompactFit, int]:
        """(the fit, rays cast) for an estimate's FitState against an occluder taken earlier
        (`occluder`, e.g. right after the frame's fusion, the volume having fused the next
        frame since: Pipeline.process_overlapped); it reads no volume. points_cam,
        normals_cam: (H, W, 3) the frame's filtered geometry (camera frame); pixel_v,
        pixel_u: the fitted samples' pixels (FitState.rows index them); pose: world_from_cam
        (4, 4); with_depth: test against the current frame's depth mesh as well
        (`occluders`)."""
        scenes = occluders(occluder, points_cam, pose, with_depth)
        v, u = pixel_v[fit_state.rows], pixel_u[fit_state.rows]
        rot, origin = pose[:3, :3], pose[:3, 3]
        points = points_cam[v, u].astype(np.float64) @ rot.T + origin
        normals = normals_cam[v, u].astype(np.float64) @ rot.T
        tester = ShadowTester(scenes, points, normals)

        def fit(track: CompactFit | None) -> CompactFit:
            return fit_compact_source(
                fit_state.design,
                fit_state.albedo,
                fit_state.weights,
                fit_state.lum,
                fit_state.rgb,
                fit_state.penalty,
                fit_state.bands,
                tester,
                up_world,
                seed=seed,
                track=track,
                **options,
            )

        searched = self._searched
        tracking = (
            searched is not None
            and self._last is not None
            and self._since_search < self.search_interval - 1
        )
        result = fit(self._last) if tracking else None
        lost = (
            searched is not None
            and bool(searched.sources)
            and result is not None
            and result.gain < TRACK_KEEP_GAIN * searched.gain
        )
        if result is None or lost:
            result = fit(None)
            self._searched, self._since_search = result, 0
            self.searches += 1
            self.last_searched = True
        else:
            self._since_search += 1
            self.last_searched = False
        self._last = result
        return result, tester.rays
