"""Per-session budgets: what one frame may cost in time and one session in memory.

A capture Hello's settings (image size, preset, overrides, virtual objects) are priced by a
coarse cost model before the session is made; a Hello whose frames could not meet the
server's per-frame deadline, or whose session would not fit its memory budget, is refused
(Error `over_budget`) naming the setting that costs most. The server's memory is then
bounded by `max_sessions` x `session_memory_bytes` (plus the process's own, about 0.5 GB).

The model is an order of magnitude, not a prediction: each stage's time is the stage's
measured time for the `full` preset at 640 x 480 on the development machine (2 shared cores;
`REFERENCE_STAGE_MS`), scaled by the ratio of the work its settings ask for to the
reference's (pixels, window areas, directions, samples, iterations, ...). It refuses what is
far out of reach (robust_iterations 10^6, a 4096^2 image on a small budget); what it lets
through and still runs long is abandoned at the deadline between stages and between the
light estimate's robust iterations (server/worker.py, `Deadline`); nothing else
is interrupted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.pipeline.config import Config, RtMethod
from arlight.pipeline.pipeline import CANDIDATES_PER_SAMPLE, transfer_pixels
from arlight.protocols import SessionConfig

REFERENCE_PIXELS = 640 * 480
REFERENCE_FIT_SAMPLES = 50000  # light_max_samples of the reference (decision 0044 lowered it)
# ms per stage, `full` preset, 640 x 480 synthetic frames, warm, 1 Open3D thread, on the
# 2-core development machine (benchmarks: `arlight bench`); Rendering: the demo scene
REFERENCE_STAGE_MS = {
    "Input": 6.0,
    "Reconstruct": 95.0,
    "Surface": 175.0,
    "DynGeo": 200.0,
    "RadTransfer": 330.0,
    "LightEst": 135.0,
    "Rendering": 400.0,
    # the reflection probe at 64 texels a face, with a mirror sphere (docs/results/probe.md,
    # "Cost": fuse 12 + probe 24 ms under load); scaled by (size / 64)^2 but its grid's part
    "Probe": 40.0,
}
PROBE_REFERENCE_SIZE = 64
PROBE_FIXED_SHARE = 0.3  # the grid's fusion, whatever the size (docs/results/probe.md, "Cost")
BYTES_PER_PIXEL = 450  # a frame's buffers while it is processed (a 2048^2 frame: 1.9 GB)
BYTES_PER_VOXEL = 8  # tsdf + weight, float32 (pipeline/volume.py)
AUX_BYTES_PER_PIXEL = 6 * 32  # six orthographic buffers: depth, normals, colour
SAMPLE_BYTES_PER_COEFFICIENT = 8 * 6  # float64 design matrix and its weighted copies
# a panorama's light (pipeline/ibl.py lighting_from_ldr: 36 bytes per pixel at its peak,
# measured with tracemalloc at 1024..4096 wide) plus the decoded image
PANORAMA_BYTES_PER_PIXEL = 40
PROBE_BYTES_PER_CELL = 16  # the probe's room grid: colour (3) and weight, float32
# the probe's cube: float32 RGB texels of every level (4/3 of level 0) and, when a Hello asks
# for it, its RGB9E5 copy for the Result (4 bytes a texel, before zstd)
PROBE_BYTES_PER_TEXEL = 12 * 4 / 3 + 4 * 4 / 3


# The virtual scene's geometry (issue 39, item 2): Open3D's ray casting (Embree) builds a BVH
# of the scene's triangles, then each ray tests the triangles of the leaves it passes. A
# leaf cannot be split where triangles share a place: 2 M triangles all at [0, 0, 0] cost
# 35-47 s a frame at 160 x 120 (priced by the object count at 0.002 s). Measured on the
# development machine (docs/reliability.md): 2 M small scattered triangles, BVH built and
# 160 x 120 rays cast in 2.0 s (1 us a triangle); 80 000 triangles sharing one centroid,
# 19 200 rays, 19 s (13 ns a ray-triangle test).
RENDER_S_PER_TRIANGLE = 1e-6
RENDER_S_PER_TEST = 13e-9
CELLS_PER_SIDE = 4096  # the grid `densest_cell` counts centroids in, along an object's extent
HASH_BINS = 2**22


def densest_cell(vertices: np.ndarray, triangles: np.ndarray) -> int:
    """The most triangles whose centroids fall in one cell of a grid of CELLS_PER_SIDE cells
    along the object's largest extent (its vertices' bounding box, object frame): about the
    triangles one ray may have to test where they crowd. vertices: (N, 3), triangles: (M, 3)
    indices into them (checked)."""
    if len(triangles) == 0:
        return 0
    v = np.asarray(vertices, dtype=np.float32)
    t = np.asarray(triangles)
    centroids = v[t[:, 0]] + v[t[:, 1]] + v[t[:, 2]]  # x 3: the grid scales with them
    lo = centroids.min(axis=0)
    extent = 3.0 * float(np.max(v.max(axis=0) - v.min(axis=0)))
    cell = max(extent / CELLS_PER_SIDE, 1e-12)
    q = np.minimum(((centroids - lo) / cell).astype(np.int64), CELLS_PER_SIDE)
    keys = (q[:, 0] * (CELLS_PER_SIDE + 1) + q[:, 1]) * (CELLS_PER_SIDE + 1) + q[:, 2]
    # counted in 2^22 bins (a hash of the cell: cells sharing a bin add up, so the figure
    # errs high, by a few at 2 M triangles), no sort
    return int(np.bincount(keys % HASH_BINS, minlength=1).max())


@dataclass(frozen=True)
class SceneLoad:
    """What a session's virtual scene asks of the ray caster: its triangles, and the sum over
    its objects of their densest cell (`densest_cell`: they may overlap where placed)."""

    triangles: int = 0
    crowded: int = 0

    @classmethod
    def of(cls, objects: list[tuple[np.ndarray, np.ndarray]]) -> SceneLoad:
        """objects: (vertices, triangles) of each object."""
        return cls(sum(len(t) for _, t in objects), sum(densest_cell(v, t) for v, t in objects))


class BudgetError(ValueError):
    """A session over a budget; `setting` names the override key (or `calibration`)."""

    def __init__(self, setting: str, message: str):
        super().__init__(message)
        self.setting = setting


@dataclass(frozen=True)
class SessionCost:
    """A session's modelled cost: seconds per frame by stage, bytes by item; the volume's
    bytes per voxel block and the bytes its growth may reach within the budget."""

    stage_s: dict[str, float]
    memory_bytes: dict[str, float]
    bytes_per_block: int
    volume_limit_bytes: float

    @property
    def frame_s(self) -> float:
        return sum(self.stage_s.values())

    @property
    def session_bytes(self) -> float:
        return sum(self.memory_bytes.values())


@dataclass(frozen=True)
class SessionBudget:
    """The server's limits per frame (seconds, in the pipeline) and per session (bytes)."""

    frame_deadline_s: float = 60.0
    session_memory_bytes: int = 1024 * 2**20

    def check(
        self,
        config: SessionConfig,
        pipeline: Config,
        camera: PinholeCamera | None,
        objects: int = 0,
        scene: SceneLoad | None = None,
    ) -> SessionCost:
        """The session's cost; SessionSetupError (code over_budget) naming the setting that
        costs most when it is over either budget."""
        from arlight.server.session import SessionSetupError

        try:
            return check_cost(pipeline, camera, objects, self, scene, config.probe is not None)
        except BudgetError as exc:
            keys = set(config.overrides or {})
            field = (
                "scene"
                if exc.setting == "scene"
                else "probe.size"
                if exc.setting == "probe_size" and config.probe is not None
                else "calibration"
                if exc.setting == "calibration" or camera is None
                else f"overrides.{exc.setting}"
                if exc.setting in keys
                else "preset"
            )
            raise SessionSetupError(field, str(exc), code="over_budget") from None


def probe_made(c: Config, objects: int, probe: bool) -> bool:
    """Whether a session makes a reflection probe each frame (priced for any object: the
    model does not read materials) or a Hello asked for one."""
    return c.render.probe and (objects > 0 or probe)


def _factors(
    c: Config, pixels: float, objects: int, probe: bool = False
) -> dict[str, dict[str, float]]:
    """Per stage: setting -> its ratio of work to the reference (the product scales the
    stage's reference time). probe: the Hello asked for a reflection probe."""
    v, f, t, e, r, a = c.volume, c.filter, c.transfer, c.estimation, c.render, c.aux
    # the configuration REFERENCE_STAGE_MS were measured with (`full` fitted 50000 pixels
    # then, rendered at every pixel and segmented at 320x240: decisions 0044, 0049 and 0050)
    ref = Config().replace(
        light_max_samples=REFERENCE_FIT_SAMPLES,
        render_subsample=1,
        render_blur_radius_px=8,
        segment_scale=2,
    )
    px = pixels / REFERENCE_PIXELS

    def window(k: int) -> float:
        return (2 * k + 1) ** 2

    ref_filter = (
        window(ref.filter.merge_window)
        + ref.filter.smooth_subsample**2
        + window(ref.filter.denoise_window)
    )
    filt = (
        window(f.merge_window)
        + f.smooth_subsample**2
        + (window(f.denoise_window) if f.denoise else 0.0)
    )
    # ray-cast steps through the volume: depth range over the voxel size
    steps = v.depth_max_m / v.voxel_size_m
    ref_steps = ref.volume.depth_max_m / ref.volume.voxel_size_m
    aux = a.aux_resolution**2 / a.aux_update_interval if a.aux_buffers else 0.0
    ref_aux = ref.aux.aux_resolution**2 / ref.aux.aux_update_interval
    # RadTransfer: at the sampled pixels (rt_subsample 1) or on the sub-sampled grid; the
    # reference drew 1.25 x its fit's pixels (decision 0047 lowered that)
    ref_samples = min(REFERENCE_PIXELS, CANDIDATES_PER_SAMPLE * ref.estimation.light_max_samples)
    samples = min(pixels, transfer_pixels(c)) if t.rt_subsample == 1 else pixels / t.rt_subsample**2
    coefficients = t.sh_bands**2 * (4 if e.estimate_rgb else 1)
    ref_coefficients = ref.transfer.sh_bands**2
    fit_samples = min(pixels, e.light_max_samples)
    ref_fit = min(REFERENCE_PIXELS, ref.estimation.light_max_samples)
    # compact sources (pipeline/compact_light.py): rays for candidates x search pixels plus
    # the normal equations over every fitted pixel; 158 ms at 256 x 4000 and 50 000 pixels
    # against LightEst's 80 ms idle (docs/decisions/0035-compact-sources.md): 2x the stage
    compact = (
        2.0
        * (
            0.7 * e.compact_candidates / 256 * min(e.compact_search_samples, fit_samples) / 4000
            + 0.3 * fit_samples / ref_fit
        )
        if e.compact_sources > 0
        else 0.0
    )
    render = 0.0 if objects == 0 else 1.0
    blur = max(1, r.render_blur_radius_px + r.render_denoise_px)
    ref_blur = ref.render.render_blur_radius_px + ref.render.render_denoise_px
    use_volume = 1.0 if v.use_volume else 0.05
    return {
        "Input": {"calibration": px},
        "Reconstruct": {"calibration": px, "use_volume": use_volume},
        "Surface": {
            "calibration": px
            / (v.surface_subsample / ref.volume.surface_subsample) ** 2
            * use_volume,
            "depth_max_m": 0.5 * steps / ref_steps + 0.5 * aux / ref_aux,
        },
        "DynGeo": {"calibration": px, "merge_window": filt / ref_filter},
        "RadTransfer": {
            "calibration": samples / ref_samples,
            "rt_directions": t.rt_directions / ref.transfer.rt_directions,
            "rt_steps": t.rt_steps
            / ref.transfer.rt_steps
            * (4.0 if t.rt_method is RtMethod.RAYCAST else 1.0),
        },
        # half the stage is the fit (iterations x samples x coefficients^2), half the
        # per-pixel material segmentation
        "LightEst": {
            "robust_iterations": 0.5
            * (e.robust_iterations + 1)
            / (ref.estimation.robust_iterations + 1)
            * fit_samples
            / ref_fit
            * (coefficients / ref_coefficients) ** 2
            + 0.5 * px / (e.segment_scale / ref.estimation.segment_scale) ** 2
            + compact
        },
        "Rendering": {
            "calibration": render * px / r.render_subsample**2 * max(1.0, objects / 2),
            "rt_directions": t.rt_directions / ref.transfer.rt_directions,
            "render_steps": 0.5 * r.render_steps / ref.render.render_steps + 0.5 * blur / ref_blur,
        },
        "Probe": {
            "probe_size": (
                PROBE_FIXED_SHARE
                + (1.0 - PROBE_FIXED_SHARE) * (r.probe_size / PROBE_REFERENCE_SIZE) ** 2
                if probe_made(c, objects, probe)
                else 0.0
            )
        },
    }


# the override keys behind each factor (named in a refusal: the one the session changed)
_FACTOR_KEYS = {
    "depth_max_m": (
        "depth_max_m",
        "volume_resolution",
        "volume_size_m",
        "aux_resolution",
        "aux_update_interval",
    ),
    "merge_window": ("merge_window", "denoise_window", "smooth_subsample"),
    "robust_iterations": (
        "robust_iterations",
        "light_max_samples",
        "sh_bands",
        "estimate_rgb",
        "segment_scale",
        "compact_candidates",
        "compact_search_samples",
        "compact_sources",
    ),
    "rt_steps": ("rt_steps", "rt_method"),
    "render_steps": ("render_steps", "render_blur_radius_px", "render_denoise_px"),
    "calibration": (
        "calibration",
        "light_max_samples",
        "rt_subsample",
        "surface_subsample",
        "render_subsample",
    ),
}


def _setting(factor: str, c: Config) -> str:
    """The flat key a refusal names for a factor: the first of its keys set away from the
    default (the preset's value counts as set), else the factor's own name."""
    defaults = Config().flat()
    values = c.flat()
    for key in _FACTOR_KEYS.get(factor, (factor,)):
        if key in values and values[key] != defaults[key]:
            return key
    return factor


def check_cost(
    c: Config,
    camera: PinholeCamera | None,
    objects: int,
    budget: SessionBudget,
    scene: SceneLoad | None = None,
    probe: bool = False,
) -> SessionCost:
    """The modelled cost of a session; BudgetError naming the costliest setting when a
    frame would take longer than the deadline or the session need more than its memory.
    scene: the virtual scene's geometry (its BVH and crowded triangles add to Rendering);
    probe: the Hello asked for a reflection probe in every Result (`config.probe`)."""
    pixels = 0.0 if camera is None else float(camera.width * camera.height)
    stage_s: dict[str, float] = {}
    blame: dict[str, str] = {}
    for stage, factors in _factors(c, pixels, objects, probe).items():
        stage_s[stage] = REFERENCE_STAGE_MS[stage] / 1e3 * math.prod(factors.values())
        blame[stage] = max(factors, key=lambda k: factors[k])
    if scene is not None and objects and scene.triangles:
        rays = pixels / c.render.render_subsample**2
        geometry_s = (
            scene.triangles * RENDER_S_PER_TRIANGLE + rays * scene.crowded * RENDER_S_PER_TEST
        )
        if geometry_s > stage_s["Rendering"]:
            blame["Rendering"] = "scene"
        stage_s["Rendering"] += geometry_s
    if camera is None:  # panorama-only: no RGB-D pipeline
        stage_s = dict.fromkeys(stage_s, 0.0)
    total = sum(stage_s.values())
    if total > budget.frame_deadline_s:
        stage = max(stage_s, key=lambda k: stage_s[k])
        setting = "scene" if blame[stage] == "scene" else _setting(blame[stage], c)
        value = "" if setting in ("calibration", "scene") else f"={c.flat().get(setting)!r}"
        size = "" if camera is None else f" at {camera.width} x {camera.height}"
        advice = (
            f"lower {setting} or choose a cheaper preset"
            if setting != "scene" or scene is None
            else f"the scene's {scene.triangles} triangles crowd up to {scene.crowded} in "
            "one place: simplify the meshes, remove degenerate or duplicated triangles"
        )
        raise BudgetError(
            setting,
            (
                f"{setting}{value}: a frame{size} would take about {total:.2g} s "
                f"({stage} {stage_s[stage]:.2g} s, by the server's cost model), over the "
                f"per-frame deadline of {budget.frame_deadline_s:g} s (`arlight serve "
                f"--frame-deadline`); {advice}"
            ),
        )
    v = c.volume
    block = v.block_resolution**3 * BYTES_PER_VOXEL
    memory = {
        "calibration": pixels * BYTES_PER_PIXEL,
        "block_count": float(v.block_count * block) if v.use_volume and camera else 0.0,
        "aux_resolution": (
            c.aux.aux_resolution**2 * AUX_BYTES_PER_PIXEL if c.aux.aux_buffers and camera else 0.0
        ),
        "light_max_samples": (
            min(pixels, transfer_pixels(c)) * c.transfer.sh_bands**2 * SAMPLE_BYTES_PER_COEFFICIENT
        ),
        # the reflection probe's room grid (pipeline/probe_grid.py: linear RGB and a weight,
        # float32, per cell), held while virtual objects may reflect (priced for any object)
        "probe_cells": (
            c.render.probe_cells**3 * PROBE_BYTES_PER_CELL
            if probe_made(c, objects, probe) and c.render.probe_room and camera
            else 0.0
        ),
        # the probe's cube (and its copy for the wire), while the session makes one
        "probe_size": (
            6 * c.render.probe_size**2 * PROBE_BYTES_PER_TEXEL
            if probe_made(c, objects, probe) and camera
            else 0.0
        ),
    }
    need = sum(memory.values())
    if need > budget.session_memory_bytes:
        item = max(memory, key=lambda k: memory[k])
        setting = item if item != "block_count" else _setting_of_volume(c)
        value = "" if setting == "calibration" else f"={c.flat().get(setting)!r}"
        size = "" if camera is None else f" ({camera.width} x {camera.height})"
        raise BudgetError(
            setting,
            (
                f"{setting}{value}: the session would need about {need / 2**20:.0f} MiB{size} "
                f"({item} {memory[item] / 2**20:.0f} MiB, by the server's cost model), over the "
                f"per-session memory budget of {budget.session_memory_bytes / 2**20:.0f} MiB "
                f"(`arlight serve --session-memory-mb`); lower {setting}"
            ),
        )
    volume_limit = budget.session_memory_bytes - need + memory["block_count"]
    return SessionCost(stage_s, memory, block, volume_limit)


def _setting_of_volume(c: Config) -> str:
    defaults = Config()
    if c.volume.block_resolution != defaults.volume.block_resolution:
        return "block_resolution"
    return "block_count"
