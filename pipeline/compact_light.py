"""Compact light sources (a sun, a lamp) beside the SH, found from the shadows the real
scene casts at any distance.

Four bands of SH cannot hold a sun: its diffuse shading they hold well (a clamped cosine
is almost all in bands 0-2), its hard shadow not at all. The shadow is also the one part
of a sun's effect that says where it is: a surface point x with normal n sees a distant
source in direction w (world frame, unit, towards the source) only when the ray from x
towards w leaves the scene, V(x, w) = 1. The model of the light estimate (section 5.2 of
seeds/000, light_estimation.py) becomes

    I(x) = a_g(x) (T(x) l + beta B(x) + k V(x, w) max(0, n . w))

with k >= 0 the source's luminance integrated over its solid angle (the irradiance it
brings to a surface facing it, in the fit's luminance units, times pi over the albedo
scale: the same units as T l). The SH l then holds the rest of the light ("ambient").

For each candidate w on the upper hemisphere of the support plane the visibility of a
seeded subset of the fitted pixels is tested by rays against the reconstruction (the
volume's mesh, world frame; else the current depth image's mesh), k and l are solved in
closed form (one Schur complement on the SH fit's normal matrix, its albedo and robust
weights held), and the direction that explains most of the residual wins; it is refined
on finer grids. A source is kept only when it explains at least `compact_min_gain` of the
SH fit's weighted residual and enough lit and shadowed pixels face it: an overcast scene
gets none, and `CompactFit.reason` says why. What a session tests the rays against, and
when it searches in full or follows the last source: compact_stage.py.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba
import numpy as np

from arlight.core.frames import Confidence
from arlight.pipeline import sh
from arlight.pipeline.light_confidence import LOW_CONFIDENCE, MIN_FACTOR
from arlight.pipeline.sun_shadows import disc_directions, perpendicular_basis

# rays start this far above the surface (metres, along its normal) and count hits from
# this distance on: the reconstruction's mesh and the filtered depth differ by ~1 cm
RAY_OFFSET_M = 0.02
RAY_TNEAR_M = 0.01
RAY_TFAR_M = 100.0
MIN_FACING = 0.1  # n . w below this: the pixel says nothing of the source's shadow
MIN_ELEVATION_DEG = 3.0  # candidates below this elevation above the support plane: none
REFINE_STEPS_DEG = (4.0, 2.0, 1.0)
# a further source is searched at least this far from a kept one (two REGION_RADIUS_DEG of
# the truth's regions: arlight.synth.environment)
SEPARATION_DEG = 16.0


def refine_steps(candidates: int) -> tuple[float, ...]:
    """The refinement's steps (degrees) after a grid of `candidates` directions over the
    hemisphere: REFINE_STEPS_DEG, led by 8 degrees where half the grid's spacing exceeds it
    (a coarse grid's best lies up to half a spacing from the optimum)."""
    spacing_deg = math.degrees(math.sqrt(2.0 * math.pi / max(candidates, 1)))
    return ((8.0,) if spacing_deg / 2.0 > 8.0 else ()) + REFINE_STEPS_DEG


@dataclass(frozen=True)
class CompactSource:
    """A distant light of small angular size (world frame).

    direction: (3,) unit, towards the source; intensity: its luminance integrated over
    its solid angle (the irradiance on a surface facing it, the SH's units); rgb: (3,)
    the same per linear RGB channel (or None); angular_radius_deg: assumed, not measured;
    share: of the irradiance a surface facing the source receives, the source's part;
    gain: the share of the SH fit's weighted residual the source explains."""

    direction: np.ndarray
    intensity: float
    rgb: np.ndarray | None
    angular_radius_deg: float
    share: float
    gain: float

    def sh(self, bands: int) -> np.ndarray:
        """The source's luminance as SH (its projection, a delta of weight `intensity`)."""
        return sh.directional_light(self.direction, self.intensity, bands)


@dataclass(frozen=True)
class CompactFit:
    """sources: the kept sources (the brightest first); ambient: (C,) the SH fitted beside
    them (equal to the SH-only fit when none is kept); reason: why none or why this one;
    tested: candidate directions tested; rays: visibility rays cast; contrast: of the best
    direction's gain against its mirror's (module docstring), whether kept or not; nan
    where no `min_contrast` asked for it."""

    sources: tuple[CompactSource, ...]
    ambient: np.ndarray
    ambient_rgb: np.ndarray | None
    reason: str
    tested: int = 0
    rays: int = 0
    contrast: float = float("nan")
    radius_deg: float = float("nan")  # the angular radius whose soft shadow explains most
    edge_step: float = 0.0  # ln step the image shows across its shadow edge (shadow_edge)
    direction: np.ndarray | None = None  # the best direction found, kept or not (world)
    gain: float = 0.0  # the share of the residual that direction's shadow explains


def candidate_directions(up: np.ndarray | None, count: int) -> np.ndarray:
    """(K, 3) unit directions spread evenly over the hemisphere above `up` (the whole
    sphere without one), at least MIN_ELEVATION_DEG above its horizon."""
    dirs = sh.fibonacci_sphere(2 * count if up is not None else count)
    if up is None:
        return dirs
    return dirs[dirs @ up > math.sin(math.radians(MIN_ELEVATION_DEG))]


def _neighbours(direction: np.ndarray, step_deg: float) -> np.ndarray:
    """(9, 3): `direction` and 8 directions `step_deg` away around it."""
    e1, e2 = perpendicular_basis(direction)
    step = math.radians(step_deg)
    out = [direction]
    for k in range(8):
        phi = k * math.pi / 4
        d = math.cos(step) * direction + math.sin(step) * (math.cos(phi) * e1 + math.sin(phi) * e2)
        out.append(d / np.linalg.norm(d))
    return np.array(out)


# angular radii (degrees) whose soft shadows the best direction is tried with: a sun, a lamp
# nearby, a window, a bright patch of sky
RADII_DEG = (0.5, 5.0, 15.0, 30.0)
DISC_SAMPLES = 8


def _best_radius(tester, sub, rows: np.ndarray, albedo: np.ndarray, direction: np.ndarray) -> float:
    """The angular radius (RADII_DEG) of a disc of light around `direction` whose (soft)
    shadow explains most beyond its unshadowed shading, on the search rows: a true compact
    source's hard shadow wins at a small radius, a soft light's contact darkening at a
    large one."""
    gains = []
    for radius in RADII_DEG:
        dirs = disc_directions(direction, radius, DISC_SAMPLES)
        shaded = tester.shading(dirs, rows).mean(axis=1, keepdims=True)
        bare = np.maximum(tester.normals[rows] @ dirs.T, 0.0).mean(axis=1, keepdims=True)
        gains.append(
            _shadow_gain(sub, shaded * albedo[rows, None], bare * albedo[rows, None])[0][0]
        )
    return float(RADII_DEG[int(np.argmax(gains))])


class ShadowTester:
    """Visibility of distant directions from surface points, by rays against meshes.

    scenes: (scene, world_from_scene) pairs, a ray being blocked when any scene blocks it;
    scene: an object_space_transfer.OcclusionScene; world_from_scene: (4, 4) maps the
    scene's frame to the world (identity for the volume's mesh, the camera pose for a
    depth image's mesh); points, normals: (M, 3) world frame."""

    def __init__(self, scenes, points: np.ndarray, normals: np.ndarray):
        self._scenes = []
        origins = points + RAY_OFFSET_M * normals
        for scene, world_from_scene in scenes:
            rot, origin = world_from_scene[:3, :3], world_from_scene[:3, 3]
            # world -> scene: x_s = R^T (x_w - o)
            self._scenes.append((scene, rot, ((origins - origin) @ rot).astype(np.float32)))
        self.points = points
        self.normals = normals
        self.rays = 0

    def shading(self, directions: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """(M', K) V(x, w) max(0, n . w) for the rows (all when None) and directions
        (K, 3) world."""
        normals = self.normals if rows is None else self.normals[rows]
        cos = np.maximum(normals @ directions.T, 0.0)
        if not self._scenes:  # nothing blocks a ray
            return cos
        out = np.zeros_like(cos)
        if not np.any(cos > 0.0):
            return out
        rows_at = np.arange(len(normals)) if rows is None else np.asarray(rows, np.int64)
        # one batch of every (pixel, direction) pair that faces the source: Embree's cost
        # per call outweighs a few thousand rays
        blocked = []
        for scene, rot, all_origins in self._scenes:
            rays, pix, j = _facing_rays(
                all_origins, rows_at, (directions @ rot).astype(np.float32), cos
            )
            blocked.append(scene.blocked(rays, RAY_TNEAR_M, RAY_TFAR_M))
            self.rays += len(pix)
        _unblocked_into(out, cos, pix, j, np.logical_or.reduce(blocked))
        return out


@numba.njit(cache=True, nogil=True)
def _facing_rays(
    origins: np.ndarray, rows: np.ndarray, directions: np.ndarray, cos: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays of every (i, j) with cos[i, j] > 0, in np.nonzero's order: (P, 6) float32
    (origins[rows[i]], directions[j]), and each pair's i and j (P,)."""
    m, k = cos.shape
    count = 0
    for i in range(m):
        for j in range(k):
            if cos[i, j] > 0.0:
                count += 1
    rays = np.empty((count, 6), np.float32)
    pix = np.empty(count, np.int64)
    col = np.empty(count, np.int64)
    p = 0
    for i in range(m):
        row = rows[i]
        for j in range(k):
            if cos[i, j] > 0.0:
                for c in range(3):
                    rays[p, c] = origins[row, c]
                    rays[p, 3 + c] = directions[j, c]
                pix[p] = i
                col[p] = j
                p += 1
    return rays, pix, col


@numba.njit(cache=True, nogil=True)
def _unblocked_into(
    out: np.ndarray, cos: np.ndarray, pix: np.ndarray, col: np.ndarray, blocked: np.ndarray
) -> None:
    """out[pix, col] = cos there where the ray is not blocked (out is zero elsewhere)."""
    for p in range(len(pix)):
        if not blocked[p]:
            out[pix[p], col[p]] = cos[pix[p], col[p]]


@dataclass
class _System:
    """The SH fit's weighted normal equations with its albedo and weights held:
    A = a * [T | B], G = A^T W A + penalty, r = A^T W I."""

    design: np.ndarray  # (M, n) a * [T | B]
    w: np.ndarray  # (M,) robust weights
    target: np.ndarray  # (M,) or (M, 3)
    g_inv: np.ndarray  # (n, n)
    r: np.ndarray  # (n,) or (n, 3)
    sse: float  # weighted residual of the SH-only solution (luminance)


def _system(
    design: np.ndarray,
    w: np.ndarray,
    target: np.ndarray,
    penalty: np.ndarray,
    g_inv: np.ndarray | None = None,
) -> _System:
    """The penalised normal equations of I = A x for `target`; `g_inv`: their inverse
    matrix from another target with the same design, weights and penalty (reused)."""
    if g_inv is None:
        gram = design.T @ (design * w[:, None])
        scale = float(np.mean(np.diag(gram))) or 1.0
        g_inv = np.linalg.inv(gram + scale * penalty)
    r = design.T @ (w[:, None] * target if target.ndim == 2 else w * target)
    x = g_inv @ r
    lum = target if target.ndim == 1 else target[:, 0]
    xl = x if x.ndim == 1 else x[:, 0]
    sse = float(np.sum(w * (design @ xl - lum) ** 2))
    return _System(design, w, target, g_inv, r, sse)


def _scores(system: _System, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(gain, k) per column (M, K) of the model I = A x + k s, k the source column: the
    weighted residual the column takes off (relative to the SH-only fit's) and its k."""
    ws = system.w[:, None] * columns
    gs = system.design.T @ ws  # (n, K)
    h = np.sum(columns * ws, axis=0)
    target = system.target if system.target.ndim == 1 else system.target[:, 0]
    r = system.r if system.r.ndim == 1 else system.r[:, 0]
    q = ws.T @ target
    g_inv_r = system.g_inv @ r
    num = q - gs.T @ g_inv_r
    den = h - np.einsum("ik,ij,jk->k", gs, system.g_inv, gs)
    den = np.maximum(den, 1e-12 * np.maximum(h, 1e-30))
    k = num / den
    gain = np.where(k > 0.0, num * num / den, 0.0) / max(system.sse, 1e-30)
    return gain, k


def _shadow_gain(
    system: _System, shaded: np.ndarray, bare: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(gain, k) per column: what a source's shading with its shadow (`shaded`, (M, K))
    explains beyond the same shading without it (`bare`: max(0, n . w), which the SH's
    high bands and the clamp could otherwise pass off as evidence of a source where no
    shadow says so); k of the shadowed column."""
    gain, k = _scores(system, shaded)
    return gain - _scores(system, bare)[0], k


# the shadow edge's test (shadow_edge): pairs of fitted pixels this close (metres), both
# facing the source at least this much, their normals this close (cosine)
EDGE_RADIUS_M = 0.04
EDGE_MIN_FACING = 0.3
EDGE_MIN_NORMAL_COS = 0.95
EDGE_MIN_PAIRS = 20
EDGE_SAMPLES = 2000  # shadowed pixels tested at most (a seeded subset)


def shadow_edge(
    points: np.ndarray,
    normals: np.ndarray,
    albedo: np.ndarray,
    lum: np.ndarray,
    column: np.ndarray,
    direction: np.ndarray,
) -> float:
    """The step the image shows across a source's predicted shadow edge: for each fitted
    pixel in its shadow (`column`, V max(0, n . w), zero) the lit pixels of the same
    material (equal albedo) within EDGE_RADIUS_M (world) whose normals agree; the mean
    over shadowed pixels of ln(median lit luminance / its own). A real hard shadow where
    the reconstruction puts it makes a clear step (0.2-1); a boundary drawn across smooth
    shading (a soft light's contact darkening read as a shadow) about none. 0 with fewer
    than EDGE_MIN_PAIRS pixels on the edge. points, normals: (M, 3) world; direction: w
    (3,); the rest (M,). docs/decisions/0043-shadow-edge.md"""
    from scipy.spatial import cKDTree

    facing = normals @ direction > EDGE_MIN_FACING
    lit = np.nonzero(facing & (column > 0.0) & (lum > 0.0))[0]
    dark = np.nonzero(facing & (column == 0.0) & (lum > 0.0))[0]
    if len(lit) < EDGE_MIN_PAIRS or len(dark) < EDGE_MIN_PAIRS:
        return 0.0
    if len(dark) > EDGE_SAMPLES:
        dark = np.sort(np.random.default_rng(0).choice(dark, EDGE_SAMPLES, replace=False))
    log_lum = np.log(lum)
    # every (shadowed, lit) pair within EDGE_RADIUS_M at once (one tree query, no loop)
    pairs = cKDTree(points[dark]).sparse_distance_matrix(
        cKDTree(points[lit]), EDGE_RADIUS_M, output_type="ndarray"
    )
    i, j = dark[pairs["i"]], lit[pairs["j"]]
    same = (np.abs(albedo[j] - albedo[i]) <= 1e-9 * np.abs(albedo[i])) & (
        np.einsum("kc,kc->k", normals[j], normals[i]) > EDGE_MIN_NORMAL_COS
    )
    i, lit_log_lum = i[same], log_lum[j[same]]
    # the median lit ln luminance per shadowed pixel: sorted by pixel, then by value
    order = np.lexsort((lit_log_lum, i))
    i, values = i[order], lit_log_lum[order]
    shadowed, start, count = np.unique(i, return_index=True, return_counts=True)
    median = (values[start + (count - 1) // 2] + values[start + count // 2]) / 2
    steps = median.astype(np.float64) - log_lum[shadowed]
    return float(np.mean(steps)) if len(steps) >= EDGE_MIN_PAIRS else 0.0


# the ln step across a source's shadow edge that counts as a clear shadow (lit 1.65 times
# the shadowed): confidence 1 from here on (decision 0043; the ranking does not depend on it)
EDGE_STEP_FULL = 0.5


def source_confidence(conf: Confidence, edge_step: float) -> Confidence:
    """The confidence of a frame whose reported direction is a kept compact source's: how
    clear the step across its shadow's edge is, min(1, edge_step / EDGE_STEP_FULL), in
    place of the SH fit's value (which judges the normals' spread, not shadows). Over the
    kept sources of the corpus and the shared set it ranks the source's error at Spearman
    -0.51 where the SH fit's confidence reaches -0.15 (decision 0043). The other fields of
    `conf` are kept. Floored at light_confidence.MIN_FACTOR: a source is an estimate, and
    a confidence of 0 means none."""
    value = float(np.clip(edge_step / EDGE_STEP_FULL, MIN_FACTOR, 1.0))
    reason = (
        ""
        if value >= LOW_CONFIDENCE
        else (
            f"the direction is a compact source's, and the image steps by only "
            f"{max(edge_step, 0.0):.2f} across its shadow's edge ({EDGE_STEP_FULL} is a "
            "clear shadow)"
        )
    )
    return dataclasses.replace(conf, value=value, reason=reason)


def _solve_with(system: _System, column: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, k) of I = A x + k s for one column s (M,): x (n,) or (n, 3), k scalar or (3,)."""
    ws = system.w * column
    gs = system.design.T @ ws
    h = float(column @ ws)
    target = system.target
    q = ws @ target
    g_inv_r = system.g_inv @ system.r
    g_inv_gs = system.g_inv @ gs
    den = max(h - float(gs @ g_inv_gs), 1e-12 * max(h, 1e-30))
    k = (q - gs @ g_inv_r) / den
    k = np.maximum(k, 0.0)
    x = g_inv_r - (np.outer(g_inv_gs, k) if np.ndim(k) else g_inv_gs * k)
    return x, k


def fit_compact_source(
    design: np.ndarray,
    albedo: np.ndarray,
    weights: np.ndarray,
    lum: np.ndarray,
    rgb: np.ndarray | None,
    penalty: np.ndarray,
    bands: int,
    tester: ShadowTester,
    up: np.ndarray | None,
    *,
    candidates: int = 64,
    search_samples: int = 2000,
    min_gain: float = 0.05,
    min_contrast: float = 0.0,
    min_edge_step: float = 0.0,
    max_radius_deg: float = math.inf,
    min_elevation_deg: float = 0.0,
    min_pixels: int = 50,
    angular_radius_deg: float = 0.27,
    seed: int = 0,
    track: CompactFit | None = None,
    max_sources: int = 1,
    exclude: np.ndarray | None = None,
) -> CompactFit:
    """The SH fit's light split into an ambient SH and compact sources (at most
    `max_sources`).

    design: (M, n) the SH fit's columns [T | B] (n = bands^2 [+ 1]); albedo, weights: (M,)
    its per-pixel albedo and robust weights; lum: (M,) linear luminance; rgb: (M, 3) or
    None; penalty: (n, n) its regulariser (relative to the mean diagonal); tester: the
    visibility of the same M pixels (world frame). Returns the SH-only solution as ambient
    (and no source) where no direction explains `min_gain` of the residual.
    track: an earlier frame's fit whose best direction and radius to start from (the grid of
    `candidates` and the radius search are skipped; the refinement reaches 7 degrees).
    max_sources > 1: after a kept source, the search runs again on what it leaves (its
    shadowed shading a column of the fit, unpenalised), away from the kept directions
    (exclude: (E, 3) world, none within SEPARATION_DEG), and every kept source's intensity
    is solved jointly with the ambient SH (`joined`)."""
    n_sh = bands * bands
    a_design = design * albedo[:, None]
    system = _system(a_design, weights, lum, penalty)
    base = system.g_inv @ system.r
    none_rgb = None
    if rgb is not None:
        rgb_system = _system(a_design, weights, rgb, penalty, system.g_inv)
        none_rgb = (rgb_system.g_inv @ rgb_system.r)[:n_sh].T
    rng = np.random.default_rng(seed)
    m = len(lum)
    rows = np.sort(rng.choice(m, min(m, search_samples), replace=False))
    # the subset's own normal equations (the full set's would mix two sets of pixels)
    sub = _system(system.design[rows], system.w[rows], lum[rows], penalty)

    def score(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(shadow gain, k) of each direction on the search rows (`_shadow_gain`); -inf
        within SEPARATION_DEG of an excluded direction."""
        a = albedo[rows, None]
        bare = np.maximum(tester.normals[rows] @ dirs.T, 0.0)
        gain, k = _shadow_gain(sub, tester.shading(dirs, rows) * a, bare * a)
        if exclude is not None and len(exclude):
            near = (dirs @ np.asarray(exclude, np.float64).T).max(axis=1) > math.cos(
                math.radians(SEPARATION_DEG)
            )
            gain = np.where(near, -np.inf, gain)
        return gain, k

    start = None if track is None else track.direction
    steps: tuple[float, ...] = REFINE_STEPS_DEG
    if start is not None:
        best, tested = np.asarray(start, np.float64), 0
    else:
        dirs = candidate_directions(up, candidates)
        tested = len(dirs)
        if not tested:
            return CompactFit((), base[:n_sh], none_rgb, "no candidate direction", 0, tester.rays)
        gain, _ = score(dirs)
        best, steps = dirs[int(np.argmax(gain))], refine_steps(candidates)
    for step in steps:
        around = _neighbours(best, step)
        if up is not None:
            around = around[around @ up > math.sin(math.radians(MIN_ELEVATION_DEG))]
        if not len(around):
            break
        g, _ = score(around)
        tested += len(around)
        best = around[int(np.argmax(g))]
    known_radius = float("nan") if track is None or start is None else float(track.radius_deg)
    radius = (
        known_radius if np.isfinite(known_radius) else _best_radius(tester, sub, rows, albedo, best)
    )
    column = tester.shading(best[None])[:, 0]
    lit = int(np.sum(column > MIN_FACING))
    cos = tester.normals @ best
    shadowed = int(np.sum((cos > MIN_FACING) & (column == 0.0)))
    x, k = _solve_with(system, column * albedo)
    edge = shadow_edge(tester.points, tester.normals, albedo, lum, column, best)
    full_gain = float(
        _shadow_gain(system, (column * albedo)[:, None], (np.maximum(cos, 0.0) * albedo)[:, None])[
            0
        ][0]
    )
    contrast = float("nan")  # asked for only where it gates (its rays are a third of a frame's)
    if min_contrast > 0.0 and up is not None and full_gain > 0.0:
        # the same elevation on the opposite azimuth: a sun's shadows fall on one side of
        # what casts them; darkening all round (contact shadows of a soft light, what the
        # SH's transfer misses) explains about as much from either side
        mirror = 2.0 * float(best @ up) * up - best
        a = albedo[:, None]
        mirror_gain = float(
            _shadow_gain(
                system,
                tester.shading(mirror[None]) * a,
                np.maximum(tester.normals @ mirror[:, None], 0.0) * a,
            )[0][0]
        )
        contrast = 1.0 - max(mirror_gain, 0.0) / full_gain
    elevation = (
        math.degrees(math.asin(float(np.clip(best @ up, -1, 1))))
        if up is not None
        else float("nan")
    )
    where = f"elevation {elevation:.0f} deg" if up is not None else "no support plane"

    def searched(sources, ambient_sh, ambient_rgb_sh, why: str) -> CompactFit:
        """The fit with what the search measured of the best direction."""
        return CompactFit(
            sources,
            ambient_sh,
            ambient_rgb_sh,
            why,
            tested,
            tester.rays,
            contrast,
            radius,
            edge,
            best,
            full_gain,
        )

    if (
        full_gain < min_gain
        or contrast < min_contrast  # False for nan: not asked for
        or edge < min_edge_step
        or radius > max_radius_deg
        or elevation < min_elevation_deg  # False for nan: no support plane
        or lit < min_pixels
        or shadowed < min_pixels
        or float(k) <= 0.0
    ):
        mirrored = (
            f"{contrast:.0%} more than its mirror (needs {min_contrast:.0%}), "
            if np.isfinite(contrast)
            else ""
        )
        why = (
            f"none: the best direction ({where}) explains {full_gain:.1%} of the residual "
            f"(needs {min_gain:.0%}), {mirrored}a step of {edge:.2f} across its shadow's "
            f"edge (needs {min_edge_step:g}), its shadows those of a {radius:g}-degree disc "
            f"(at most {max_radius_deg:g}), an elevation of at least {min_elevation_deg:g} "
            f"deg, {lit} pixels lit and {shadowed} in its shadow "
            f"(needs {min_pixels} each)"
        )
        return searched((), base[:n_sh], none_rgb, why)
    ambient = x[:n_sh]
    k_rgb = None
    ambient_rgb = None
    if rgb is not None:
        x_rgb, k_rgb = _solve_with(rgb_system, column * albedo)
        ambient_rgb = x_rgb[:n_sh].T
        k_rgb = np.asarray(k_rgb, np.float64)
    # irradiance on a surface facing the source: the source's k, the ambient's E(best)
    ambient_irradiance = max(
        float(sh.evaluate(sh.irradiance_from_radiance(ambient), best[None])[0]), 0.0
    )
    share = float(k) / max(float(k) + ambient_irradiance, 1e-30)
    source = CompactSource(best, float(k), k_rgb, angular_radius_deg, share, full_gain)
    why = (
        f"1 compact source ({where}): it explains {full_gain:.1%} of the residual, the image "
        f"steps by {edge:.2f} across its shadow's edge, "
        f"{lit} pixels lit and {shadowed} in its shadow"
    )

    def joined(one: CompactFit, more: CompactFit) -> CompactFit:
        """`one` (a fit that kept one source) joined with `more` (the search on what it left):
        every kept source's intensity and the ambient SH solved together (the sources'
        shadowed shading as unpenalised columns); `one` alone where `more` kept none or the
        joint solution gives a source no light."""
        if not more.sources:
            return dataclasses.replace(one, reason=f"{one.reason}; no second: {more.reason}")
        sources = list(one.sources) + list(more.sources)
        n, n_sh = design.shape[1], bands * bands
        # the first source's shading is this fit's `column`; the others' are cast anew
        columns = [column * albedo] + [
            tester.shading(s.direction[None])[:, 0] * albedo for s in more.sources
        ]
        a_design = np.column_stack([design * albedo[:, None], *columns])
        wide = np.pad(penalty, ((0, len(columns)), (0, len(columns))))
        system = _system(a_design, weights, lum, wide)
        x = system.g_inv @ system.r
        if np.any(x[n:] <= 0.0):
            return dataclasses.replace(
                one, reason=f"{one.reason}; a second found, but no light left for both"
            )
        ambient = x[:n_sh]
        ambient_rgb, k_rgb = None, [None] * len(sources)
        if rgb is not None:
            rgb_system = _system(a_design, weights, rgb, wide, system.g_inv)
            x_rgb = rgb_system.g_inv @ rgb_system.r
            ambient_rgb = x_rgb[:n_sh].T
            k_rgb = [np.maximum(x_rgb[n + i], 0.0) for i in range(len(sources))]
        irradiance = sh.irradiance_from_radiance(ambient)
        joint = []
        for i, s in enumerate(sources):
            k = float(x[n + i])
            e = max(float(sh.evaluate(irradiance, s.direction[None])[0]), 0.0)
            joint.append(
                dataclasses.replace(s, intensity=k, rgb=k_rgb[i], share=k / max(k + e, 1e-30))
            )
        first = one.reason.removeprefix("1 compact source ")
        why = f"{len(joint)} compact sources: the first {first}; then {more.reason}"
        return dataclasses.replace(
            one, sources=tuple(joint), ambient=ambient, ambient_rgb=ambient_rgb, reason=why
        )

    one = searched((source,), ambient, ambient_rgb, why)
    if max_sources <= 1:
        return one
    follow = None  # a tracked frame refines the tracked fit's further sources
    if track is not None:
        if len(track.sources) < 2:
            return one  # a further source waits for the next full search
        follow = CompactFit((), track.ambient, None, "", direction=track.sources[1].direction)
    more = fit_compact_source(
        np.column_stack([design, column]),
        albedo,
        weights,
        lum,
        rgb,
        np.pad(penalty, ((0, 1), (0, 1))),
        bands,
        tester,
        up,
        candidates=candidates,
        search_samples=search_samples,
        min_gain=min_gain,
        min_contrast=min_contrast,
        min_edge_step=min_edge_step,
        max_radius_deg=max_radius_deg,
        min_elevation_deg=min_elevation_deg,
        min_pixels=min_pixels,
        angular_radius_deg=angular_radius_deg,
        seed=seed + 1,
        track=follow,
        max_sources=max_sources - 1,
        exclude=best[None] if exclude is None else np.vstack([exclude, best]),
    )
    return joined(one, more)
