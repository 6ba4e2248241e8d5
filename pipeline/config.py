"""Pipeline parameters: one frozen dataclass per stage, composed into `Config`, with presets.

Defaults follow section 6.1 of the image-space illumination paper (seeds/000): 640x480,
a 2 m workspace at 256 voxels per side, 4 SH bands, D': k=20, lambda_I=7, lambda_D=5 cm;
D'': k=8, lambda_I=7; D''': k=2. Units: metres, seconds, radians; intensities in 8-bit
grey levels (0..255) as in the paper.

Each stage takes only its own object (`VolumeParams`, `AuxBufferParams`, `FilterParams`,
`TransferParams`, `EstimationParams`, `TemporalParams`); each checks all its fields when
made, with a message naming the `--set` key. Users keep one flat namespace of keys
(`Config.from_preset("fast", rt_directions=128)`, `config.replace(visibility=False)`, the
CLI's `--set KEY=VALUE`, a session's overrides): `FLAT_KEYS` maps each key to its
(stage, field). One alias converts a unit: `change_reset_deg` (degrees, as users think of
an angle) sets `TemporalParams.change_reset_rad`.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any


class _StrEnum(str, Enum):
    """An option's string values as an Enum: members print and format as their value."""

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, spec: str) -> str:
        return format(str(self.value), spec)


class Preset(_StrEnum):
    FULL = "full"  # the paper's "Ours" (its composite on a 2x2 grid: decision 0049)
    FAST = "fast"  # its "OursFast": 4x4 image-space sub-sampling of the radiance transfer
    MOBILE = "mobile"  # its 64^3 volume, no D''', sub-sampled transfer
    CUSTOM = "custom"  # made by hand, not from a preset


class VisibilityRamp(_StrEnum):
    """The threshold c of K = min(c, 1 - t.w) / c (eq. 8)."""

    PAPER = "paper"  # c = chi, eq. 8 as printed
    HALF = "half"  # c = 1 - chi: K ramps over half the angle between neighbouring directions


class RtMethod(_StrEnum):
    """How RadTransfer decides visibility V(x, w)."""

    SSDO = "ssdo"  # image space: SSDO samples against G_r and the aux buffers (eq. 6-9)
    RAYCAST = "raycast"  # object space: rays against the reconstructed mesh (GR12/GR14)


class DiffMode(_StrEnum):
    """How the differential rendering applies the virtual objects' shading change to I_c."""

    RATIO = "ratio"  # I_c R'_d / R_d: exact for a Lambertian surface under the same light
    PAPER = "paper"  # eq. 13: I_c (1 + T(R'_d) - T(R_d)), Reinhard T keyed on each buffer
    PASTE = "paste"  # the baseline: objects shaded by the light, pasted; no shadows, no bounce


class SegmentFeatures(_StrEnum):
    INVARIANT = "invariant"  # log chromaticity across the Planckian locus (sun/sky robust)
    CHROMA = "chroma"  # rg chromaticity (sensitive to sun/sky colour)


PRESETS = tuple(p.value for p in Preset if p is not Preset.CUSTOM)
REFERENCE_WIDTH = 640  # image width (pixels) at which the pixel windows are given
MIN_WORK_WIDTH = 64  # the narrowest work image (work_width) the pipeline is tested at
MAX_WINDOW = 64  # depth-filter windows (a CUDA thread's median scratch: 64 * 64 floats)


# ------------------------------------------------------------------ field checks
def _hint(key: str, kind: str) -> str:
    return f"(--set {key}={kind})"


def _check_bool(obj: Any, key: str) -> None:
    value = getattr(obj, key)
    if not isinstance(value, bool):
        raise ValueError(f"{key} must be true or false {_hint(key, 'true|false')}, got {value!r}")


def _check_int(obj: Any, key: str, low: int | None = None, high: int | None = None) -> None:
    value = getattr(obj, key)
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{key} must be an integer {_hint(key, 'N')}, got {value!r}")
    value = int(value)
    if low is not None and high is not None and not low <= value <= high:
        raise ValueError(f"{key} must be in {low}..{high} {_hint(key, 'N')}, got {value}")
    if low is not None and value < low:
        raise ValueError(f"{key} must be >= {low} {_hint(key, 'N')}, got {value}")
    if high is not None and value > high:
        raise ValueError(f"{key} must be <= {high} {_hint(key, 'N')}, got {value}")
    object.__setattr__(obj, key, int(value))


def _check_float(
    obj: Any,
    key: str,
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
) -> None:
    value = getattr(obj, key)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{key} must be a number {_hint(key, 'X')}, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{key} must be finite {_hint(key, 'X')}, got {v}")
    if low is not None and (v < low or (low_open and v == low)):
        rel = ">" if low_open else ">="
        raise ValueError(f"{key} must be {rel} {low:g} {_hint(key, 'X')}, got {v:g}")
    if high is not None and v > high:
        raise ValueError(f"{key} must be <= {high:g} {_hint(key, 'X')}, got {v:g}")
    object.__setattr__(obj, key, v)


def _check_enum(obj: Any, key: str, kind: type[Enum]) -> None:
    value = getattr(obj, key)
    try:
        object.__setattr__(obj, key, kind(value))
    except ValueError:
        choices = "|".join(m.value for m in kind)
        raise ValueError(
            f"{key} must be one of {choices} {_hint(key, choices)}, got {value!r}"
        ) from None


# ------------------------------------------------------------------ stage parameters
@dataclass(frozen=True)
class VolumeParams:
    """Reconstruct / Surface: the TSDF volume V (Open3D tensor VoxelBlockGrid), tracking."""

    volume_size_m: float = 2.0  # workspace edge; voxel size = volume_size_m / volume_resolution
    volume_resolution: int = 256
    block_resolution: int = 8  # voxels per block edge
    # the hash map's initial capacity (blocks; it grows when full): memory is held for this
    # many from the start (8 x 8 x 8 voxels x 8 bytes each: 10000 = 39 MB); the 15 shared
    # sequences end with 7400 (median) allocated where there is surface
    block_count: int = 10000
    depth_min_m: float = 0.1
    depth_max_m: float = 4.0
    sdf_trunc_voxels: float = 4.0  # TSDF truncation, in voxels
    tracking_depth_diff_m: float = 0.07  # ICP correspondence gate
    use_volume: bool = True  # False: skip the volume; D_v is then empty (image-space only)
    # Surface: V ray cast through every s-th pixel (s x s fewer rays), interpolated back
    # where the surface is smooth; only while the cast keeps 320 columns. 2 against 1 on the
    # 15 shared sequences (all frames, upper-hemisphere median of the per-sequence medians):
    # full 13.5 -> 12.8, fast 14.2 -> 14.2, mobile 20.0 -> 19.7 degrees; Surface -60 %
    surface_subsample: int = 2

    def __post_init__(self) -> None:
        _check_float(self, "volume_size_m", 0.0, low_open=True)
        _check_int(self, "volume_resolution", 8)
        _check_int(self, "block_resolution", 1)
        _check_int(self, "block_count", 1)
        _check_float(self, "depth_min_m", 0.0)
        _check_float(self, "depth_max_m", self.depth_min_m, low_open=True)
        _check_float(self, "sdf_trunc_voxels", 0.0, low_open=True)
        _check_float(self, "tracking_depth_diff_m", 0.0, low_open=True)
        _check_bool(self, "use_volume")
        _check_int(self, "surface_subsample", 1, 8)

    @property
    def voxel_size_m(self) -> float:
        return self.volume_size_m / self.volume_resolution


@dataclass(frozen=True)
class AuxBufferParams:
    """Auxiliary orthographic geometry buffers (section 5.1)."""

    aux_buffers: bool = True
    aux_resolution: int = 128  # pixels per side of each orthographic buffer
    aux_extent_m: float = 4.0  # side of the square each buffer covers, metres
    aux_update_interval: int = 5  # re-render the auxiliary buffers every n frames

    def __post_init__(self) -> None:
        _check_bool(self, "aux_buffers")
        _check_int(self, "aux_resolution", 1)
        _check_float(self, "aux_extent_m", 0.0, low_open=True)
        _check_int(self, "aux_update_interval", 1)

    @property
    def pixel_size_m(self) -> float:
        return self.aux_extent_m / self.aux_resolution


@dataclass(frozen=True)
class FilterParams:
    """DynGeo: the depth filter chain D' (eq. 1-3), D'' (eq. 4), D''' (eq. 5), normals."""

    merge: bool = True  # D' (eq. 1-3); False: the raw depth passes on as D'
    merge_window: int = 20  # k
    merge_intensity_threshold: float = 7.0  # lambda_I, grey levels
    merge_depth_threshold_m: float = 0.05  # lambda_D
    smooth: bool = True  # D'' (eq. 4); False: D' passes on as D''
    smooth_window: int = 8  # k
    smooth_intensity_threshold: float = 7.0  # lambda_I
    smooth_subsample: int = 5  # the k x k window is sub-sampled to this many per side
    denoise: bool = True
    denoise_window: int = 2  # k
    normal_window: int = 15  # box window (pixels) over depth before normals (1 = raw depth)
    # the filter chain runs on the work image reduced by the whole factor that keeps it at
    # least this wide, and its depth is enlarged back (0: at the work image's own size);
    # normals and points stay at the work resolution. 320 makes `full` 16 % faster at the
    # same error held out by map but less steady on real 7-Scenes frames: opt-in
    # (docs/decisions/0046-filter-width.md)
    filter_width: int = 0

    def __post_init__(self) -> None:
        for key in ("merge_window", "smooth_window", "smooth_subsample", "denoise_window"):
            _check_int(self, key, 1, MAX_WINDOW)
        _check_int(self, "filter_width", 0)
        if 0 < self.filter_width < MIN_WORK_WIDTH:
            raise ValueError(
                f"filter_width must be 0 (the work image's size) or at least {MIN_WORK_WIDTH} "
                f"pixels {_hint('filter_width', 'N')}, got {self.filter_width}"
            )
        for key in (
            "merge_intensity_threshold",
            "merge_depth_threshold_m",
            "smooth_intensity_threshold",
        ):
            _check_float(self, key, 0.0)
        for key in ("merge", "smooth", "denoise"):
            _check_bool(self, key)
        _check_int(self, "normal_window", 1)

    def at_width(self, width: int) -> FilterParams:
        """These windows for an image `width` pixels wide: they are given in pixels of a
        REFERENCE_WIDTH image (the paper's 640x480) and keep their footprint on the scene at
        other sizes (rounded, at least 1; the sample counts stay). At 320x240 the unscaled
        windows cost 15 degrees on the built-in scene
        (docs/decisions/0041-work-resolution.md)."""
        if width == REFERENCE_WIDTH:
            return self
        scale = width / REFERENCE_WIDTH

        def scaled(window: int) -> int:
            return int(min(MAX_WINDOW, max(1, round(window * scale))))

        return dataclasses.replace(
            self,
            merge_window=scaled(self.merge_window),
            smooth_window=scaled(self.smooth_window),
            denoise_window=scaled(self.denoise_window),
            normal_window=max(1, round(self.normal_window * scale)),
        )


@dataclass(frozen=True)
class TransferParams:
    """RadTransfer: image-space SSDO radiance transfer into SH (section 5.1, eq. 6-9), or
    object-space ray casting as a comparator (rt_method "raycast")."""

    # "ssdo": the paper's image-space visibility; "raycast": rays of length rt_radius_m
    # against the volume's mesh (or the depth image's) in the same directions
    # (pipeline/object_space_transfer.py); both give the same kind of transfer
    rt_method: RtMethod = RtMethod.SSDO
    sh_bands: int = 4  # L: L*L coefficients (the light estimate solves for as many)
    rt_directions: int = 64  # N jittered directions on the sphere
    rt_radius_m: float = 0.5  # largest sample displacement along a direction
    rt_thickness_m: float = 0.3  # a sample further than this behind a surface is not occluded
    rt_steps: int = 1  # samples along each direction (1 = the paper's single SSDO sample)
    rt_visibility_ramp: VisibilityRamp = VisibilityRamp.PAPER
    # image-space sub-sampling (fast: 4), in pixels of the input image (a frame analysed at
    # half its size, work_width, steps half as many of its own pixels)
    rt_subsample: int = 1
    rt_upsample: bool = True  # sub-sampled transfer interpolated back to every pixel
    # sub-sampled and up-sampled: pixels the grid cannot interpolate (an invalid grid point
    # beside them, or grid transfers differing by more than this, relative) get their own
    # transfer (radiance_transfer.interpolated_samples); 0: off
    rt_refine_spread: float = 0.0
    visibility: bool = True  # False: K = 1 everywhere (the no-visibility baseline)
    # blocked directions bring the occluder's own (observed) light, as in SSDO's one-bounce
    # indirect term; its unknown scale (mean albedo / pi) is solved with the light
    rt_bounce: bool = True
    # the support plane (floor, table) hides the distant light below its horizon: those
    # directions see the lit ground (its observed luminance, through the bounce term).
    # Physically right but off: with the below-horizon prior it then needs, the shared GT
    # set gave full medians a 37, b 3.6, c 22, d 24, e 14 (off: 4.2, 7.7, 7.0, 4.3, 5.2)
    rt_horizon: bool = False
    # the unoccluded part of each transfer vector made exact (a control variate: the exact
    # clamped-cosine SH of the pixel's normal minus the N directions' estimate of it), so
    # only blocked directions keep the sampling error; one direction set serves every
    # pixel, so that error is a bias that bends the shading a light is fitted to. No
    # parameter. On the 15 shared sequences (full, median of the per-sequence medians,
    # upper field): 13.3 -> 12.2 degrees at regularization 1e-2
    # (docs/decisions/0001-exact-unoccluded-transfer.md)
    rt_exact_unoccluded: bool = True

    def __post_init__(self) -> None:
        _check_enum(self, "rt_method", RtMethod)
        _check_int(self, "sh_bands", 1, 12)
        _check_int(self, "rt_directions", 4)
        _check_float(self, "rt_radius_m", 0.0, low_open=True)
        _check_float(self, "rt_thickness_m", 0.0, low_open=True)
        _check_int(self, "rt_steps", 1)
        _check_enum(self, "rt_visibility_ramp", VisibilityRamp)
        _check_int(self, "rt_subsample", 1)
        _check_float(self, "rt_refine_spread", 0.0)
        for key in ("rt_upsample", "visibility", "rt_bounce", "rt_horizon", "rt_exact_unoccluded"):
            _check_bool(self, key)


@dataclass(frozen=True)
class EstimationParams:
    """LightEst: regularised, robust least squares T l = I_c (section 5.2, unnumbered)."""

    # Tikhonov weight, relative to the mean diagonal of T^T T, times (l(l+1))^2 per band.
    # It damps what the normals leave unconstrained, and biases what they do constrain
    # towards an ambient light (too high an elevation). 4e-3 with 8 Huber passes
    # (docs/decisions/0002-regularisation-4e-3.md); 2e-3 since the alternation runs to its
    # fixed point, chosen held out by map over 22 maps (decision 0052)
    regularization: float = 2e-3
    min_samples: int = 200  # fewer valid pixels: no estimate (confidence 0)
    # larger sets of usable pixels are randomly sub-sampled: 30000 (50000 until 2026-12-04) in
    # every preset but mobile, held out by map: docs/decisions/0044-fewer-fit-samples.md
    light_max_samples: int = 30000
    # fit only the sampled pixels within this many metres of the point the camera looks at
    # (pipeline/fit_region.py; 0 = every pixel); 1.0 in `full` and `fast` (decisions 0063,
    # 0064)
    fit_radius_m: float = 0.0
    # with fit_radius_m, search the compact sources on every sampled pixel (a second fit of
    # the SH there), not only on those near the look-at point: a sun's shadows fall
    # anywhere. On in `full` and `fast` (docs/decisions/0064-sources-over-the-whole-view.md)
    fit_radius_sources_everywhere: bool = False
    # that second fit's most samples (0: light_max_samples); 10000 in `full` and `fast`:
    # 5000 leaves too few pixel pairs across a shadow's edge for the source's confidence
    fit_radius_sources_samples: int = 0
    # where that second fit's direction lies within this many degrees of the near fit's,
    # the second fit's SH is the one reported (0 = never; held out by map it lost: 0064)
    fit_radius_agree_deg: float = 0.0
    # share of that second fit's SH in the reported one where the two fits' directions
    # agree: (1 - s) near + s whole, s = fit_radius_blend * max(0, 1 - their angle /
    # fit_radius_blend_deg) (0 = the near fit alone); 0.5 in `fast`, off in `full`,
    # where it lost held out (docs/decisions/0067-the-two-fits-blended.md)
    fit_radius_blend: float = 0.0
    fit_radius_blend_deg: float = 45.0
    # weight of the prior holding radiance below the horizon of the surface the scene stands
    # on to that of a lit ground (0 = off); always on with rt_horizon (no pixel sees there),
    # otherwise only when the light comes out below that horizon
    horizon_prior: float = 0.1
    horizon_ground_albedo: float = 0.3  # of the prior's ground glow
    # weight of the light prior learned from HDR maps (pipeline/light_prior.py), relative to
    # the mean diagonal of T^T T (0 = off); docs/decisions/light-prior.md
    light_prior: float = 0.0
    # maps left out of that prior, comma-separated names (leave-one-map-out evaluation)
    light_prior_exclude: str = ""
    # albedo alternation (and re-weighting) passes, 0 = plain least squares; held out by
    # map, 24 converge where 8 stopped short (docs/decisions/0052-no-huber-24-passes.md)
    robust_iterations: int = 24
    # Huber's threshold in robust standard deviations for re-weighting the pixels (0 = off;
    # 1.345 until decision 0052: held out by map the fit is better without it)
    robust_threshold: float = 0.0
    albedo_segments: bool = True  # one unknown albedo per material segment (beyond the paper)
    segment_features: SegmentFeatures = SegmentFeatures.INVARIANT
    segment_illuminant_weight: float = 4.0  # "invariant": weight of the sun/sky colour axis
    segment_split_ground: bool = True  # the support plane's pixels never share a segment
    # the segmentation runs at 1/segment_scale of the input's size: 160x120 of 640x480, in
    # every preset (docs/decisions/0050-segments-at-160x120.md)
    segment_scale: int = 4
    # the segments' graph threshold and smallest size, times the defaults
    # (segmentation.SEGMENT_K, SEGMENT_MIN_SIZE_PX): below 1 finer segments, more albedos;
    # `fast` 0.5 (docs/decisions/0059-finer-segments-in-fast.md)
    segment_coarseness: float = 1.0
    estimate_rgb: bool = False  # also solve one SH per linear RGB channel
    # compact sources (a sun, a lamp) fitted beside the SH from the shadows the reconstruction
    # casts (pipeline/compact_light.py): at most this many (0 = off; 2: a second searched on
    # what the first leaves, experimental). On in `full` and `fast` (decisions 0061, 0062),
    # off in `mobile`
    compact_sources: int = 0
    # of the SH fit's residual its shadow must explain: 0.08, chosen leaving maps out over
    # the fit of decision 0052 (0.03 in decision 0035; docs/decisions/0054-compact-gain-0.08.md)
    compact_min_gain: float = 0.08
    compact_min_contrast: float = 0.0  # its gain over its mirrored direction's (0 = off)
    # ln step the image must show across its shadow's edge (0 = off: held out by map it did
    # not beat a gain threshold alone, docs/decisions/0043-shadow-edge.md)
    compact_min_edge_step: float = 0.0
    # degrees above the support plane's horizon a kept source must stand: lower ones were
    # rooms' walls and windows; chosen leaving maps out
    # (docs/decisions/0061-compact-sources-in-full.md)
    compact_min_elevation_deg: float = 20.0
    # directions tested over the upper hemisphere (then refined from 8 degrees down), and
    # fitted pixels whose shadows are tested per direction: 64 and 2000 find the source as
    # well as 256 and 4000 held out by map (docs/decisions/0055-compact-search-64-2000.md)
    compact_candidates: int = 64
    compact_search_samples: int = 2000
    # the full search on one frame in this many, the frames between refining the last best
    # direction (1 = every frame; compact_stage.CompactLightStage): the same accuracy held
    # out by map at 20-30 ms less a frame (docs/decisions/0056-compact-tracking.md)
    compact_search_interval: int = 5
    compact_render: bool = True  # draw them with hard shadows both ways (pipeline/sun_shadows.py)
    # test their shadows against the volume's mesh (rebuilt every aux_update_interval fused
    # frames, 0.1-0.5 s each time) instead of the current frame's depth mesh, 160 points
    # wide: held out by map the depth mesh finds the sources better
    # (docs/decisions/0060-compact-depth-mesh.md)
    compact_volume_mesh: bool = False
    # with the volume's mesh, test against the current frame's depth mesh too (no gain:
    # decision 0035)
    compact_depth_mesh: bool = False

    def __post_init__(self) -> None:
        _check_float(self, "regularization", 0.0)
        _check_int(self, "min_samples", 1)
        if (
            isinstance(self.light_max_samples, numbers.Integral)
            and not isinstance(self.light_max_samples, bool)
            and self.light_max_samples < self.min_samples
        ):
            raise ValueError(
                f"light_max_samples must be >= min_samples ({self.min_samples}) "
                f"{_hint('light_max_samples', 'N')}, got {self.light_max_samples}"
            )
        _check_int(self, "light_max_samples", 1)
        _check_float(self, "horizon_prior", 0.0)
        _check_float(self, "horizon_ground_albedo", 0.0, 1.0)
        _check_float(self, "light_prior", 0.0)
        if not isinstance(self.light_prior_exclude, str):
            raise ValueError(
                "light_prior_exclude must be map names separated by commas "
                f"{_hint('light_prior_exclude', 'NAME,NAME')}"
            )
        _check_float(self, "fit_radius_m", 0.0)
        _check_bool(self, "fit_radius_sources_everywhere")
        _check_int(self, "fit_radius_sources_samples", 0)
        _check_float(self, "fit_radius_agree_deg", 0.0, 180.0)
        _check_float(self, "fit_radius_blend", 0.0, 1.0)
        _check_float(self, "fit_radius_blend_deg", 1.0, 180.0)
        _check_int(self, "robust_iterations", 0)
        _check_float(self, "robust_threshold", 0.0)
        _check_bool(self, "albedo_segments")
        _check_enum(self, "segment_features", SegmentFeatures)
        _check_float(self, "segment_illuminant_weight", 0.0)
        _check_bool(self, "segment_split_ground")
        _check_int(self, "segment_scale", 1, 16)
        _check_float(self, "segment_coarseness", 0.0, 100.0, low_open=True)
        _check_bool(self, "estimate_rgb")
        _check_int(self, "compact_sources", 0, 2)
        _check_float(self, "compact_min_gain", 0.0)
        _check_float(self, "compact_min_contrast", 0.0, 1.0)
        _check_float(self, "compact_min_edge_step", 0.0)
        _check_float(self, "compact_min_elevation_deg", 0.0, 90.0)
        _check_int(self, "compact_candidates", 8, 4096)
        _check_int(self, "compact_search_samples", 100)
        _check_int(self, "compact_search_interval", 1, 1000)
        _check_bool(self, "compact_render")
        _check_bool(self, "compact_volume_mesh")
        _check_bool(self, "compact_depth_mesh")


@dataclass(frozen=True)
class TemporalParams:
    """The temporal filter of the world-frame SH (exponential, reset on a light change)."""

    temporal_half_life_frames: float = 2.0  # light changes pass in ~3 frames; 0: no filter
    # a jump of the dominant direction larger than this resets the filter (35 degrees)
    change_reset_rad: float = math.radians(35.0)

    def __post_init__(self) -> None:
        _check_float(self, "temporal_half_life_frames", 0.0)
        _check_float(self, "change_reset_rad", 0.0, math.pi, low_open=True)


@dataclass(frozen=True)
class ReuseParams:
    """A camera held still (pipeline/still.py): the volume's work (fusion, ray cast,
    auxiliary buffers) and, while the depth image is unchanged too, the filtered geometry
    and the radiance transfer are reused from the frame they were last made for; the light
    estimate always runs on the new image. Never triggers on a moving camera."""

    still_reuse_frames: int = 10  # at most this many frames in a row reuse (0: never)
    still_translation_m: float = 0.005  # the camera moved less than this since ...
    still_rotation_deg: float = 0.5  # ... and turned less than this
    still_depth_change: float = 0.02  # share of 8x8-pixel depth blocks allowed to change

    def __post_init__(self) -> None:
        _check_int(self, "still_reuse_frames", 0)
        _check_float(self, "still_translation_m", 0.0)
        _check_float(self, "still_rotation_deg", 0.0, 180.0)
        _check_float(self, "still_depth_change", 0.0, 1.0)


@dataclass(frozen=True)
class RenderParams:
    """Rendering: differential rendering of the virtual objects (section 5.4, eq. 10-15).

    The shading of real and real + virtual is computed only around the objects (within
    rt_radius_m of their bounding spheres, where a sample can meet them), with the SSDO
    transfer of RadTransfer's directions."""

    render_mode: DiffMode = DiffMode.RATIO
    # image-space sub-sampling of the differential buffers (fast: 4, the paper's OursFast);
    # full at 2: Rendering in half the time, as close to path-traced truth under the
    # estimated light (docs/decisions/0049-full-render-subsample.md)
    render_subsample: int = 2
    render_blur_radius_px: int = 4  # Gaussian radius of the up-sampling (the paper: 8 at 4x4)
    # render_subsample 1: Gaussian radius against the sampling noise of the shadows (0: none);
    # 2 raised PSNR and SSIM on dev_a and dev_d alike (true light, affected: 31.2 -> 31.5 and
    # 29.4 -> 29.7 dB; shadow SSIM 0.866 -> 0.892 and 0.805 -> 0.824)
    render_denoise_px: int = 2
    # samples along each direction; 2 beat 1 and 4 against path-traced truth on dev_a and
    # dev_d alike (ground-truth light, affected pixels: a 30.9 / 31.2 / 29.0 dB for 1 / 2 / 4)
    render_steps: int = 2
    render_indirect: bool = True  # one-bounce light between real and virtual (eq. 10-12, 14)
    # the real scene's mean albedo: the light estimate knows albedo x light only, so a
    # virtual albedo is shaded relative to this. 0.34: chosen on AR pairs of 19 maps, held
    # out by map (virtual objects +1.9 dB and the affected region +1.3 dB under the
    # estimated light against 0.48, which 6 maps had given; docs/decisions/0051-real-albedo-0.34.md)
    render_real_albedo: float = 0.34
    tone_key: float = 0.18  # render_mode "paper": Reinhard's key value a
    # the reflection probe (pipeline/probe.py, docs/results/probe.md): mirror and glossy
    # objects (mirror, metalness > 0 or roughness < 1) reflect a cube map of the room at the
    # objects' centre (false: they are shaded Lambertian, as before the probe)
    probe: bool = True
    probe_room: bool = True  # directions see the fused room (false: the distant light alone)
    # the light's dominant part drawn as a 2-degree disc in the probe (probe.py): on mirror
    # spheres against path-traced truth 15.4 -> 14.9 dB under the estimated light, 13.7 ->
    # 12.0 under the true one (docs/results/probe.md): off
    probe_sun: bool = False
    # the SH that directions leaving the room see, Hanning-windowed against its ringing: on
    # 6 mirror sequences it was not chosen on, +2.0 dB under the true light, -0.0 under the
    # estimated one (docs/results/probe.md)
    probe_sh_window: bool = True
    probe_size: int = 64  # texels a face, a power of two in 32..256
    probe_cells: int = 120  # the room grid: cells per side ...
    probe_cell_m: float = 0.04  # ... of this size (metres): 4.8 m across, 28 MB

    def __post_init__(self) -> None:
        _check_bool(self, "probe")
        _check_bool(self, "probe_room")
        _check_bool(self, "probe_sun")
        _check_bool(self, "probe_sh_window")
        _check_int(self, "probe_size", 32, 256)
        if self.probe_size & (self.probe_size - 1):
            raise ValueError(
                f"probe_size must be a power of two (32, 64, 128 or 256) "
                f"{_hint('probe_size', 'N')}, got {self.probe_size}"
            )
        _check_int(self, "probe_cells", 16, 400)
        _check_float(self, "probe_cell_m", 0.005, 1.0)
        _check_enum(self, "render_mode", DiffMode)
        _check_int(self, "render_subsample", 1)
        _check_int(self, "render_blur_radius_px", 0)
        _check_int(self, "render_denoise_px", 0)
        _check_int(self, "render_steps", 1)
        _check_bool(self, "render_indirect")
        _check_float(self, "render_real_albedo", 0.0, 1.0, low_open=True)
        _check_float(self, "tone_key", 0.0, low_open=True)


STAGE_TYPES: dict[str, type] = {
    "volume": VolumeParams,
    "aux": AuxBufferParams,
    "filter": FilterParams,
    "transfer": TransferParams,
    "estimation": EstimationParams,
    "temporal": TemporalParams,
    "reuse": ReuseParams,
    "render": RenderParams,
}


# ------------------------------------------------------------------ flat keys
def _flat_table() -> dict[str, tuple[str | None, str]]:
    table: dict[str, tuple[str | None, str]] = {
        key: (None, key) for key in ("device", "seed", "work_width")
    }
    for stage, cls in STAGE_TYPES.items():
        for f in dataclasses.fields(cls):
            table[f.name] = (stage, f.name)
    return table


# flat key -> (stage attribute of Config or None for Config's own field, field name)
FLAT_KEYS: dict[str, tuple[str | None, str]] = _flat_table()
# flat keys in another unit: key -> (the canonical key, conversion to its unit, the alias's
# own range (low excluded, high included), checked before converting so the message speaks
# the user's unit)
FLAT_ALIASES: dict[str, tuple[str, Callable[[float], float], tuple[float, float]]] = {
    "change_reset_deg": ("change_reset_rad", math.radians, (0.0, 180.0)),
}


def _valid_keys_text() -> str:
    return ", ".join(sorted([*FLAT_KEYS, *FLAT_ALIASES]))


def _flat_overrides(changes: dict[str, Any]) -> dict[str, Any]:
    """Aliases converted to their canonical keys; unknown keys refused (listing the valid)."""
    unknown = sorted(set(changes) - set(FLAT_KEYS) - set(FLAT_ALIASES))
    if unknown:
        raise ValueError(
            f"unknown config key(s): {', '.join(unknown)}; valid keys: {_valid_keys_text()}"
        )
    out = {}
    for key, value in changes.items():
        if key in FLAT_ALIASES:
            canonical, convert, (low, high) = FLAT_ALIASES[key]
            if canonical in changes:
                raise ValueError(f"give {key} or {canonical}, not both")
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ValueError(f"{key} must be a number {_hint(key, 'X')}, got {value!r}")
            if not low < float(value) <= high:
                raise ValueError(
                    f"{key} must be in ({low:g}, {high:g}] {_hint(key, 'X')}, got {value!r}"
                )
            value = convert(float(value))
            key = canonical
        out[key] = value
    return out


def _preset_overrides(preset: Preset) -> dict[str, Any]:
    if preset is Preset.FAST:
        # analysed at 320 pixels wide, a 128^3 volume (each held out by map over the shared
        # set and the corpus: docs/decisions/0041-work-resolution.md)
        return {
            "rt_subsample": 4,
            "render_subsample": 4,
            "render_blur_radius_px": 8,
            "work_width": 320,
            "volume_resolution": 128,
            # the light fitted to 20000 pixels: 10 % of the frame's time, the same error held
            # out by map (docs/decisions/0045-fast-fit-samples.md)
            "light_max_samples": 20000,
            # finer material segments: better held out by map in `fast` (not in `full`) and
            # on real 7-Scenes frames (docs/decisions/0059-finer-segments-in-fast.md)
            "segment_coarseness": 0.5,
            # compact sources as in `full`: held out by map 16.5 -> 12.2 degrees median
            # over 22 maps, at about 30 ms a frame (docs/decisions/0062-compact-sources-in-fast.md)
            "compact_sources": 1,
            # the light fitted to the pixels within 1 m of the look-at point: held out by map
            # 12.2 / 15.5 -> 11.6 / 12.7 degrees median / mean over 22 maps
            # (docs/decisions/0063-fit-near-the-look-at-point.md)
            "fit_radius_m": 1.0,
            # the compact sources searched over the whole view all the same, on a second fit
            # of 10000 pixels: held out by map 11.6 / 12.7 -> 10.3 / 12.3 degrees median / mean
            # (docs/decisions/0064-sources-over-the-whole-view.md)
            "fit_radius_sources_everywhere": True,
            "fit_radius_sources_samples": 10000,
            # the two fits blended where their directions agree: held out by map 10.3 / 12.2
            # -> 9.5 / 12.2 degrees median / mean (docs/decisions/0067-the-two-fits-blended.md)
            "fit_radius_blend": 0.5,
        }
    if preset is Preset.MOBILE:
        # and, speed first, the light fitted to at most 10000 pixels (measured together with
        # the quarter-resolution segments every preset now has; all frames: median 20.1 ->
        # 19.1 and 20.1, p90 32.8 -> 34.1 and 33.2)
        # and its 25 cm blocks need a smaller hash map to start with (it grows when full):
        # 16 MB held from the start, every error as with 40000 blocks (156 MB)
        # (`arlight bench ... --presets mobile --sweep block_count=40000,4000`)
        # and analysed at 320 pixels wide as fast (docs/decisions/0041-work-resolution.md)
        return {
            "work_width": 320,
            "volume_resolution": 64,
            "denoise": False,
            "rt_subsample": 4,
            "render_subsample": 4,
            "render_blur_radius_px": 8,
            "light_max_samples": 10000,
            "block_count": 4000,
        }
    # compact sources beside the SH (a sun, a lamp, where their shadows say so): held out by
    # map 16.1 -> 11.2 degrees median over 22 maps, at about 35 ms a frame
    # (docs/decisions/0061-compact-sources-in-full.md); `mobile` keeps the SH alone.
    # The SH fitted within 1 m of the look-at point, the sources searched over the whole
    # view: over 22 maps 11.2 / 17.0 -> 10.5 / 13.0 degrees median / mean (13.0 / 14.1 held
    # out with the radius chosen per fold), 7-Scenes 11.7 -> 6.4
    # (docs/decisions/0064-sources-over-the-whole-view.md)
    if preset is Preset.FULL:
        return {
            "compact_sources": 1,
            "fit_radius_m": 1.0,
            "fit_radius_sources_everywhere": True,
            "fit_radius_sources_samples": 10000,
        }
    return {}


@dataclass(frozen=True)
class Config:
    """Every pipeline parameter: the stage objects plus the preset, the device and the seed.

    Make one with `Config.from_preset(name, **flat_keys)`; change one with
    `config.replace(**flat_keys)` (keys: `FLAT_KEYS`, `FLAT_ALIASES`).
    """

    preset: Preset = Preset.FULL
    device: str = "CPU:0"  # Open3D device for the volume ("CPU:0" or "CUDA:0")
    seed: int = 0  # seeds every random choice: same frames -> same results
    # the frame is analysed (Reconstruct .. LightEst, the probe) reduced by the largest
    # whole factor that keeps it at least work_width pixels wide (0: at its own size); the
    # composite is drawn at the input's (pipeline/work_resolution.py; fast: 320)
    work_width: int = 0
    volume: VolumeParams = field(default_factory=VolumeParams)
    aux: AuxBufferParams = field(default_factory=AuxBufferParams)
    filter: FilterParams = field(default_factory=FilterParams)
    transfer: TransferParams = field(default_factory=TransferParams)
    estimation: EstimationParams = field(default_factory=EstimationParams)
    temporal: TemporalParams = field(default_factory=TemporalParams)
    reuse: ReuseParams = field(default_factory=ReuseParams)
    render: RenderParams = field(default_factory=RenderParams)

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "preset", Preset(self.preset))
        except ValueError:
            raise ValueError(
                f"preset must be one of {', '.join(p.value for p in Preset)}, got {self.preset!r}"
            ) from None
        if not isinstance(self.device, str) or not self.device.startswith(("CPU:", "CUDA:")):
            raise ValueError(
                f"device must be 'CPU:0' or 'CUDA:0' (--device CPU:0, or "
                f"--set device=CPU:0), got {self.device!r}"
            )
        _check_int(self, "seed", 0)
        _check_int(self, "work_width", 0)
        if 0 < self.work_width < MIN_WORK_WIDTH:
            raise ValueError(
                f"work_width must be 0 (the input's size) or at least {MIN_WORK_WIDTH} "
                f"pixels {_hint('work_width', 'N')}, got {self.work_width}"
            )
        for stage, cls in STAGE_TYPES.items():
            if not isinstance(getattr(self, stage), cls):
                raise TypeError(
                    f"Config.{stage} must be a {cls.__name__}, got "
                    f"{type(getattr(self, stage)).__name__}"
                )

    @classmethod
    def from_preset(cls, name: str = "full", **overrides: Any) -> Config:
        """A preset ('full' = paper's Ours, 'fast' = OursFast, 'mobile') with flat overrides."""
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
        changes = _flat_overrides(overrides)  # checked before the preset's own values
        preset = Preset(name)
        return cls(preset=preset).replace(**{**_preset_overrides(preset), **changes})

    def replace(self, **changes: Any) -> Config:
        """A copy with flat keys changed (e.g. `replace(rt_directions=128, seed=1)`)."""
        changes = _flat_overrides(changes)
        top: dict[str, Any] = {}
        per_stage: dict[str, dict[str, Any]] = {}
        for key, value in changes.items():
            stage, name = FLAT_KEYS[key]
            if stage is None:
                top[name] = value
            else:
                per_stage.setdefault(stage, {})[name] = value
        stages = {
            stage: dataclasses.replace(getattr(self, stage), **values)
            for stage, values in per_stage.items()
        }
        return dataclasses.replace(self, **top, **stages)

    def flat(self) -> dict[str, Any]:
        """Every flat key and its value (enums as their strings), e.g. for a report."""
        out: dict[str, Any] = {"preset": self.preset.value}
        for key, (stage, name) in FLAT_KEYS.items():
            value = getattr(self if stage is None else getattr(self, stage), name)
            out[key] = value.value if isinstance(value, Enum) else value
        return out

    @staticmethod
    def parse_flat_value(key: str, text: str) -> Any:
        """The value of flat key `key` from command-line text (bool: true/false/1/0/on/off);
        ValueError naming the key (unknown keys list the valid ones)."""
        types = Config.flat_key_types()
        if key not in types:
            raise ValueError(f"unknown config key {key!r}; keys: {', '.join(sorted(types))}")
        kind = types[key]
        try:
            if kind is bool:
                if text.lower() not in ("true", "false", "1", "0", "on", "off"):
                    raise ValueError(text)
                return text.lower() in ("true", "1", "on")
            return kind(text)
        except ValueError:
            what = {bool: "true or false", int: "an integer", float: "a number"}.get(
                kind, kind.__name__
            )
            raise ValueError(f"{key} expects {what}, got {text!r}") from None

    @staticmethod
    def flat_key_types() -> dict[str, type]:
        """Flat key -> bool, int, float or str (Enum options are given as their strings);
        what a command line needs to parse `--set KEY=VALUE`."""
        defaults = Config().flat()
        types: dict[str, type] = {
            key: type(value) for key, value in defaults.items() if key != "preset"
        }
        types.update({alias: float for alias in FLAT_ALIASES})
        return types
