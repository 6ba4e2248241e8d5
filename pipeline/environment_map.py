"""HDR environment maps from SH light, for engines that take textures rather than SH.

An SH radiance expansion (the project's basis, `pipeline/sh.py`) evaluated per texel and
clamped at 0 (a band-limited light rings negative):

* equirectangular: (H, W = 2 H, 3) in the frame of the SH, +y up, the mapping of
  `pipeline/equirect.py` (direction d at column u = atan2(d.x, -d.z) / 2 pi, row v =
  acos(d.y) / pi, row 0 at the top), the one `arlight ibl --exr` writes;
* cubemap (from SH, or from an equirectangular map): six (S, S, 3) faces in the OpenGL
  convention (the OpenGL 4.6 specification,
  table 8.19, "Selection of cube map images"): face +X, -X, +Y, -Y, +Z, -Z; texel (s, t)
  with s, t in [0, 1] from the left and from the TOP row looks along the major axis with
  sc, tc of that table (e.g. +X: direction (1, -tc, -sc) for sc, tc in [-1, 1]); the SH
  frame's axes are the cube's axes.

Units are the SH's (radiance); write them with `sources/exr.write_exr` (half float).
"""

from __future__ import annotations

import numpy as np

from arlight.pipeline import equirect, sh

CUBE_FACES = ("px", "nx", "py", "ny", "pz", "nz")


def _radiance_at(sh_rgb: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(..., 3) float32 radiance of (3, n) RGB SH (or (n,) luminance, grey) at unit
    directions (..., 3), clamped at 0."""
    c = np.asarray(sh_rgb, np.float64)
    c = np.broadcast_to(c, (3, c.shape[-1])) if c.ndim == 1 else c
    if c.ndim != 2 or c.shape[0] != 3:
        raise ValueError(f"SH must be (n,) or (3, n), got shape {np.shape(sh_rgb)}")
    basis = sh.sh_basis(directions, sh.bands_of(c.shape[1]))
    return np.maximum(basis @ c.T, 0.0).astype(np.float32)


def equirect_from_sh(sh_rgb: np.ndarray, width: int = 256) -> np.ndarray:
    """(width / 2, width, 3) float32 equirectangular radiance map of the SH light."""
    if width < 2 or width % 2:
        raise ValueError(f"width must be an even number of pixels >= 2, got {width}")
    return _radiance_at(sh_rgb, equirect.pixel_directions(width // 2, width))


def cube_face_directions(face: str, size: int) -> np.ndarray:
    """(size, size, 3) unit directions of a cube face's texel centres (OpenGL table 8.19:
    s left to right, t top to bottom)."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    sc, tc = np.meshgrid(c, c)  # sc along a row, tc down the rows
    one = np.ones_like(sc)
    d = {
        "px": (one, -tc, -sc),
        "nx": (-one, -tc, sc),
        "py": (sc, one, tc),
        "ny": (sc, -one, -tc),
        "pz": (sc, -tc, one),
        "nz": (-sc, -tc, -one),
    }[face]
    v = np.stack(d, axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def cubemap_from_sh(sh_rgb: np.ndarray, size: int = 64) -> dict[str, np.ndarray]:
    """The six faces (CUBE_FACES order) as (size, size, 3) float32 radiance."""
    if size < 1:
        raise ValueError(f"size must be >= 1 pixel, got {size}")
    return {f: _radiance_at(sh_rgb, cube_face_directions(f, size)) for f in CUBE_FACES}


def cubemap_from_equirect(hdr: np.ndarray, size: int = 128) -> dict[str, np.ndarray]:
    """The six faces (CUBE_FACES order, (size, size, 3) float32) of an equirectangular map
    (`equirect`'s mapping), bilinear lookups at the texel centres' directions."""
    if size < 1:
        raise ValueError(f"size must be >= 1 pixel, got {size}")
    image = equirect.check_equirect(np.asarray(hdr, np.float32), "hdr")
    return {
        f: equirect.sample_bilinear(image, cube_face_directions(f, size)).astype(np.float32)
        for f in CUBE_FACES
    }
