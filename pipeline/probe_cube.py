"""Cube maps of linear HDR radiance with GGX-prefiltered mips (the reflection probe's texture).

Layout: six (n, n, 3) float32 faces per level in the order and orientation of
`environment_map` (OpenGL 4.6 table 8.19: +X, -X, +Y, -Y, +Z, -Z; texel (s, t) from the left
and from the top row), the cube's axes the frame of the directions given (the probe's: the
session's world frame). Level k is n / 2^k texels a face and holds the radiance prefiltered
for perceptual roughness r_k = k / (L - 1) (GGX, alpha = r^2, the glTF / Filament / Mitsuba
`principled` convention): level 0 is the radiance itself (a mirror), the last level (4 texels)
r = 1. A lookup for roughness r reads level r (L - 1), linearly between the two levels about
it, bilinearly inside a face (clamped at the face's edges).

Prefiltering is the split-sum approximation (Karis 2013, "Real Shading in Unreal Engine 4"):
each texel of level k is the GGX lobe of alpha_k about its own direction (N = V = R), the
NdotL-weighted mean of `PREFILTER_SAMPLES` importance-sampled directions (a Hammersley set),
each read from the radiance's own box-filtered mip chain at the level whose texel matches the
sample's solid angle (filtered importance sampling, Krivanek and Colbert 2008), so few samples
give a smooth result. The view-dependent other half is `env_brdf` (Karis' analytic fit for
mobile). Why split-sum rather than seed 001's 36-sample rings about each pixel's mirror
direction: the mips are what engines load (glTF EXT_lights_image_based specular images,
Filament's and three.js' prefiltered cube maps), so the texture we export is the one we
render with, and a pixel costs one trilinear lookup instead of 36 (decision 0034).

Per-texel logic is written once as ``register_jitable`` functions driven by
``@njit(parallel=True)`` loops; `sample_numpy` is the plain NumPy oracle of `sample`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numba
import numpy as np
from numba.extending import register_jitable

from arlight.pipeline.environment_map import CUBE_FACES, cube_face_directions

SIZE_MIN = 32  # texels a face (the range: ARCore's 16 is what users find too coarse)
SIZE_MAX = 256
LAST_LEVEL_TEXELS = 4  # the roughest level's face size
PREFILTER_SAMPLES = 32  # GGX samples per prefiltered texel (filtered importance sampling)


def check_size(size: int, field: str = "probe_size") -> int:
    """`size` as an int, a power of two in SIZE_MIN..SIZE_MAX; ValueError naming `field`."""
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)):
        raise ValueError(f"{field} must be an integer, got {size!r}")
    s = int(size)
    if not SIZE_MIN <= s <= SIZE_MAX or s & (s - 1):
        raise ValueError(
            f"{field} must be a power of two in {SIZE_MIN}..{SIZE_MAX} texels a face, got {s}"
        )
    return s


def num_levels(size: int) -> int:
    """Mip levels of a `size`-texel cube: size, size / 2, ... down to LAST_LEVEL_TEXELS."""
    return int(round(math.log2(check_size(size) / LAST_LEVEL_TEXELS))) + 1


def level_roughness(levels: int) -> np.ndarray:
    """(levels,) perceptual roughness of each level: k / (levels - 1)."""
    return np.linspace(0.0, 1.0, levels)


def texel_directions(size: int) -> np.ndarray:
    """(6, size, size, 3) unit directions of every texel centre (CUBE_FACES order)."""
    return _texel_directions(int(size)).copy()


@functools.cache
def _texel_directions(size: int) -> np.ndarray:
    return np.stack([cube_face_directions(f, size) for f in CUBE_FACES]).astype(np.float64)


@functools.cache
def texel_solid_angles(size: int) -> np.ndarray:
    """(6, size, size) exact solid angle (sr) of every texel (they sum to 4 pi)."""
    edges = np.linspace(-1.0, 1.0, size + 1)
    a, b = np.meshgrid(edges, edges)  # corners: a along a row, b down the rows

    def corner(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))

    c = corner(a, b)
    face = c[1:, 1:] - c[:-1, 1:] - c[1:, :-1] + c[:-1, :-1]
    return np.broadcast_to(np.abs(face), (6, size, size))


@dataclass
class CubeMips:
    """A cube map's levels packed for the kernels.

    levels: list of (6, n_k, n_k, 3) float32; data: every level's texels one after another,
    (sum 6 n_k^2, 3) float32; offsets (L,) int64 first row of each level in data; sizes (L,)
    int64 n_k; roughness (L,) float64 perceptual roughness each level is prefiltered for.
    """

    levels: list[np.ndarray]
    roughness: np.ndarray

    def __post_init__(self) -> None:
        self.sizes = np.array([lv.shape[1] for lv in self.levels], np.int64)
        counts = np.array([lv.shape[0] * lv.shape[1] * lv.shape[2] for lv in self.levels])
        self.offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self.data = np.ascontiguousarray(
            np.concatenate([lv.reshape(-1, 3) for lv in self.levels]), np.float32
        )

    @property
    def size(self) -> int:
        return int(self.sizes[0])

    def lod_of(self, roughness: np.ndarray) -> np.ndarray:
        """Fractional level of perceptual roughness (clipped to 0..1)."""
        return np.clip(np.asarray(roughness, np.float64), 0.0, 1.0) * (len(self.levels) - 1)


# --------------------------------------------------------------------------- per-texel logic


@register_jitable
def _face_st(x, y, z):
    """(face, s, t) of a direction, s and t in [0, 1] (OpenGL table 8.19)."""
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        ma = ax
        if x > 0:
            face, sc, tc = 0, -z, -y
        else:
            face, sc, tc = 1, z, -y
    elif ay >= az:
        ma = ay
        if y > 0:
            face, sc, tc = 2, x, z
        else:
            face, sc, tc = 3, x, -z
    else:
        ma = az
        if z > 0:
            face, sc, tc = 4, x, -y
        else:
            face, sc, tc = 5, -x, -y
    ma = max(ma, 1e-30)
    return face, 0.5 * (sc / ma + 1.0), 0.5 * (tc / ma + 1.0)


@register_jitable
def _bilinear(data, offset, n, face, s, t):
    """(r, g, b) bilinear in one face of an n-texel level (clamped at the face's edges)."""
    fx = min(max(s * n - 0.5, 0.0), n - 1.0)
    fy = min(max(t * n - 0.5, 0.0), n - 1.0)
    x0 = min(int(fx), n - 1)
    y0 = min(int(fy), n - 1)
    x1 = min(x0 + 1, n - 1)
    y1 = min(y0 + 1, n - 1)
    ax = fx - x0
    ay = fy - y0
    base = offset + face * n * n
    i00 = base + y0 * n + x0
    i01 = base + y0 * n + x1
    i10 = base + y1 * n + x0
    i11 = base + y1 * n + x1
    w00 = (1.0 - ax) * (1.0 - ay)
    w01 = ax * (1.0 - ay)
    w10 = (1.0 - ax) * ay
    w11 = ax * ay
    r = w00 * data[i00, 0] + w01 * data[i01, 0] + w10 * data[i10, 0] + w11 * data[i11, 0]
    g = w00 * data[i00, 1] + w01 * data[i01, 1] + w10 * data[i10, 1] + w11 * data[i11, 1]
    b = w00 * data[i00, 2] + w01 * data[i01, 2] + w10 * data[i10, 2] + w11 * data[i11, 2]
    return r, g, b


@register_jitable
def _trilinear(data, offsets, sizes, x, y, z, lod):
    """(r, g, b) at a direction and fractional level (clamped to the levels held)."""
    last = sizes.shape[0] - 1
    lod = min(max(lod, 0.0), float(last))
    k0 = min(int(lod), last)
    k1 = min(k0 + 1, last)
    a = lod - k0
    face, s, t = _face_st(x, y, z)
    r0, g0, b0 = _bilinear(data, offsets[k0], sizes[k0], face, s, t)
    if a <= 0.0 or k1 == k0:
        return r0, g0, b0
    r1, g1, b1 = _bilinear(data, offsets[k1], sizes[k1], face, s, t)
    return r0 + a * (r1 - r0), g0 + a * (g1 - g0), b0 + a * (b1 - b0)


@numba.njit(parallel=True, cache=True)
def _sample_kernel(data, offsets, sizes, directions, lods, out):
    for i in numba.prange(directions.shape[0]):
        r, g, b = _trilinear(
            data, offsets, sizes, directions[i, 0], directions[i, 1], directions[i, 2], lods[i]
        )
        out[i, 0] = r
        out[i, 1] = g
        out[i, 2] = b


def sample(cube: CubeMips, directions: np.ndarray, lods: np.ndarray | float = 0.0) -> np.ndarray:
    """(K, 3) float32 radiance along directions (K, 3) (any length, not zero) at fractional
    levels lods (K,) or one for all."""
    d = np.ascontiguousarray(np.asarray(directions, np.float64).reshape(-1, 3))
    lod = np.ascontiguousarray(np.broadcast_to(np.asarray(lods, np.float64), (len(d),)))
    out = np.zeros((len(d), 3), np.float32)
    if len(d):
        _sample_kernel(cube.data, cube.offsets, cube.sizes, d, lod, out)
    return out


def sample_numpy(cube: CubeMips, directions: np.ndarray, lod: int = 0) -> np.ndarray:
    """The oracle of `sample` at a whole level: the same lookup in plain NumPy."""
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    level = cube.levels[lod].astype(np.float64)
    n = level.shape[1]
    a = np.abs(d)
    major = np.argmax(a, axis=1)  # ties as the kernel: x before y before z
    x, y, z = d.T
    pos = d[np.arange(len(d)), major] > 0
    face = 2 * major + (~pos)
    sc = np.select(
        [face == 0, face == 1, face == 2, face == 3, face == 4], [-z, z, x, x, x], default=-x
    )
    tc = np.select(
        [face == 0, face == 1, face == 2, face == 3, face == 4], [-y, -y, z, -z, -y], default=-y
    )
    ma = a[np.arange(len(d)), major]
    fx = np.clip((0.5 * (sc / ma + 1.0)) * n - 0.5, 0.0, n - 1.0)
    fy = np.clip((0.5 * (tc / ma + 1.0)) * n - 0.5, 0.0, n - 1.0)
    x0, y0 = np.minimum(fx.astype(int), n - 1), np.minimum(fy.astype(int), n - 1)
    x1, y1 = np.minimum(x0 + 1, n - 1), np.minimum(y0 + 1, n - 1)
    ax, ay = (fx - x0)[:, None], (fy - y0)[:, None]
    return (
        level[face, y0, x0] * (1 - ax) * (1 - ay)
        + level[face, y0, x1] * ax * (1 - ay)
        + level[face, y1, x0] * (1 - ax) * ay
        + level[face, y1, x1] * ax * ay
    )


# --------------------------------------------------------------------------- prefiltering


def box_chain(radiance: np.ndarray) -> CubeMips:
    """The radiance (6, n, n, 3) and its 2x2 box-filtered levels down to 1 texel a face (the
    source of filtered importance sampling; texels of a face weigh alike)."""
    levels = [np.ascontiguousarray(radiance, np.float32)]
    while levels[-1].shape[1] > 1:
        lv = levels[-1]
        n = lv.shape[1] // 2
        levels.append(lv.reshape(6, n, 2, n, 2, 3).mean(axis=(2, 4)).astype(np.float32))
    return CubeMips(levels, np.zeros(len(levels)))


def _hammersley(count: int) -> np.ndarray:
    """(count, 2) the Hammersley set: (i / count, radical inverse of i in base 2)."""
    i = np.arange(count, dtype=np.uint32)
    bits = i.copy()
    bits = ((bits << 16) | (bits >> 16)) & 0xFFFFFFFF
    bits = ((bits & 0x55555555) << 1) | ((bits & 0xAAAAAAAA) >> 1)
    bits = ((bits & 0x33333333) << 2) | ((bits & 0xCCCCCCCC) >> 2)
    bits = ((bits & 0x0F0F0F0F) << 4) | ((bits & 0xF0F0F0F0) >> 4)
    bits = ((bits & 0x00FF00FF) << 8) | ((bits & 0xFF00FF00) >> 8)
    return np.stack([i / count, bits.astype(np.float64) / 2.0**32], axis=1)


def ggx_lobe_samples(alpha: float, count: int = PREFILTER_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Half-vectors of the GGX lobe about +z (Hammersley, importance-sampled D(h) cos):
    (count, 3) unit h in the lobe's frame and (count,) D(h) / 4 (the pdf of the mirrored
    direction l = 2 (v.h) h - v for v = n = +z)."""
    u = _hammersley(count)
    a2 = max(alpha * alpha, 1e-12)
    cos_t = np.sqrt((1.0 - u[:, 1]) / (1.0 + (a2 - 1.0) * u[:, 1]))
    sin_t = np.sqrt(1.0 - cos_t * cos_t)
    phi = 2.0 * math.pi * u[:, 0]
    h = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)
    denom = cos_t * cos_t * (a2 - 1.0) + 1.0
    d = a2 / (math.pi * denom * denom)
    return h, d / 4.0


@numba.njit(parallel=True, cache=True)
def _prefilter_kernel(data, offsets, sizes, dirs, lobe, halfs, lods, out):
    """out[i]: the NdotL-weighted mean over the samples of lobe[i] about dirs[i] (N = V):
    half-vectors halfs[lobe[i], j], each read at level lods[lobe[i], j]."""
    count = halfs.shape[1]
    for i in numba.prange(dirs.shape[0]):
        q = lobe[i]
        nx, ny, nz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        # a frame about n: t1, t2
        if abs(nz) < 0.999:
            ux, uy, uz = 0.0, 0.0, 1.0
        else:
            ux, uy, uz = 1.0, 0.0, 0.0
        t1x, t1y, t1z = uy * nz - uz * ny, uz * nx - ux * nz, ux * ny - uy * nx
        norm = math.sqrt(t1x * t1x + t1y * t1y + t1z * t1z)
        t1x, t1y, t1z = t1x / norm, t1y / norm, t1z / norm
        t2x, t2y, t2z = ny * t1z - nz * t1y, nz * t1x - nx * t1z, nx * t1y - ny * t1x
        r = g = b = 0.0
        wsum = 0.0
        for j in range(count):
            hx = halfs[q, j, 0] * t1x + halfs[q, j, 1] * t2x + halfs[q, j, 2] * nx
            hy = halfs[q, j, 0] * t1y + halfs[q, j, 1] * t2y + halfs[q, j, 2] * ny
            hz = halfs[q, j, 0] * t1z + halfs[q, j, 1] * t2z + halfs[q, j, 2] * nz
            vh = nx * hx + ny * hy + nz * hz
            lx, ly, lz = 2.0 * vh * hx - nx, 2.0 * vh * hy - ny, 2.0 * vh * hz - nz
            nl = nx * lx + ny * ly + nz * lz
            if nl <= 0.0:
                continue
            sr, sg, sb = _trilinear(data, offsets, sizes, lx, ly, lz, lods[q, j])
            r += nl * sr
            g += nl * sg
            b += nl * sb
            wsum += nl
        if wsum > 0.0:
            out[i, 0] = r / wsum
            out[i, 1] = g / wsum
            out[i, 2] = b / wsum


@functools.cache
def _prefilter_plan(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """What `prefilter` of an n-texel cube reads, made once per size: every level's texel
    directions one after another, each texel's level - 1, per level the lobe's half-vectors
    and each sample's source level, and the levels' sizes."""
    levels = num_levels(n)
    rough = level_roughness(levels)
    texel_solid = 4.0 * math.pi / (6.0 * n * n)
    dirs, lobe, halfs, lods, sizes = [], [], [], [], []
    for k in range(1, levels):
        d = _texel_directions(n >> k).reshape(-1, 3)
        dirs.append(d)
        sizes.append(n >> k)
        lobe.append(np.full(len(d), k - 1, np.int64))
        h, pdf = ggx_lobe_samples(float(rough[k] ** 2))
        halfs.append(h)
        # filtered importance sampling: each sample read at the level whose texel is its
        # solid angle 1 / (count pdf), plus one (Karis' bias against aliasing)
        omega = 1.0 / (len(pdf) * np.maximum(pdf, 1e-12))
        lods.append(0.5 * np.log2(np.maximum(omega / texel_solid, 1.0)) + 1.0)
    return np.concatenate(dirs), np.concatenate(lobe), np.stack(halfs), np.stack(lods), sizes


def prefilter(radiance: np.ndarray) -> CubeMips:
    """The GGX-prefiltered mips (see the module text) of a (6, n, n, 3) radiance cube."""
    n = check_size(radiance.shape[1], "cube face size")
    rough = level_roughness(num_levels(n))
    source = box_chain(radiance)
    all_dirs, lobe, halfs, lods, sizes = _prefilter_plan(n)
    out = np.zeros((len(all_dirs), 3), np.float32)
    # one launch for every level (a launch per level cost more than the small levels' work)
    _prefilter_kernel(source.data, source.offsets, source.sizes, all_dirs, lobe, halfs, lods, out)
    out_levels = [source.levels[0]]
    start = 0
    for size in sizes:
        count = 6 * size * size
        out_levels.append(out[start : start + count].reshape(6, size, size, 3))
        start += count
    return CubeMips(out_levels, rough)


def env_brdf(f0: np.ndarray, roughness: np.ndarray, n_dot_v: np.ndarray) -> np.ndarray:
    """The split sum's second factor, F0 A + B (Karis' analytic fit, "Physically Based Shading
    on Mobile", 2014): f0 (K, 3), roughness (K,) perceptual, n_dot_v (K,) -> (K, 3)."""
    r = np.asarray(roughness, np.float64)[:, None]
    nv = np.clip(np.asarray(n_dot_v, np.float64), 0.0, 1.0)[:, None]
    c0 = np.array([-1.0, -0.0275, -0.572, 0.022])
    c1 = np.array([1.0, 0.0425, 1.04, -0.04])
    q = r * c0 + c1
    a004 = np.minimum(q[:, 0:1] ** 2, np.exp2(-9.28 * nv)) * q[:, 0:1] + q[:, 1:2]
    scale = -1.04 * a004 + q[:, 2:3]
    bias = 1.04 * a004 + q[:, 3:4]
    return np.asarray(f0, np.float64) * scale + bias


__all__ = [
    "SIZE_MAX",
    "SIZE_MIN",
    "CubeMips",
    "check_size",
    "env_brdf",
    "ggx_lobe_samples",
    "level_roughness",
    "num_levels",
    "prefilter",
    "sample",
    "sample_numpy",
    "texel_directions",
]
