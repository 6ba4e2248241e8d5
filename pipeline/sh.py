"""Real spherical harmonics: the one place where the convention is written out.

Convention (docs/architecture.md, "Conventions"): real, orthonormal over the unit sphere,
WITHOUT the Condon-Shortley phase, index ``i = l*(l+1) + m`` for band ``l`` and order
``m = -l..l``::

    Y_l,m  = sqrt(2) K_l^m P_l^m(z) cos(m phi)        m > 0
    Y_l,0  =         K_l^0 P_l^0(z)
    Y_l,-m = sqrt(2) K_l^m P_l^m(z) sin(m phi)        m > 0
    K_l^m  = sqrt((2l + 1) / (4 pi) * (l - m)! / (l + m)!)

with P_l^m the associated Legendre functions without the (-1)^m factor and
(x, y, z) = (sin theta cos phi, sin theta sin phi, cos theta). The first bands read
Y_0,0 = 0.282095, Y_1,-1 = 0.488603 y, Y_1,0 = 0.488603 z, Y_1,1 = 0.488603 x,
Y_2,-2 = 1.092548 xy, Y_2,-1 = 1.092548 yz, Y_2,0 = 0.315392 (3z^2 - 1),
Y_2,1 = 1.092548 xz, Y_2,2 = 0.546274 (x^2 - y^2).

Sloan's tables (and ``../shared/data/synthetic``) carry the phase: their odd-m coefficients
(indices 1, 3, 5, 7, 9, 11, 13, 15, ...) have the opposite sign; see
:func:`toggle_condon_shortley`.

Coefficients describe a function on directions of whatever frame the directions are given
in (world or camera); :func:`rotation_matrix` moves them between frames. ``sh`` values in
arlight are *radiance* (the light arriving from a direction, per steradian);
:func:`irradiance_from_radiance` is the Ramamoorthi-Hanrahan convolution to irradiance.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

SQRT2 = math.sqrt(2.0)
Y1_SCALE = math.sqrt(3.0 / (4.0 * math.pi))  # 0.488603: Y_1,m = Y1_SCALE * (y, z, x)


def num_coefficients(bands: int) -> int:
    """Number of coefficients of `bands` bands (l = 0..bands-1): bands**2."""
    return bands * bands


def bands_of(num_coeffs: int) -> int:
    """Inverse of :func:`num_coefficients`; raises ValueError if not a square."""
    bands = math.isqrt(int(num_coeffs))
    if bands * bands != num_coeffs or bands < 1:
        raise ValueError(f"an SH vector has bands**2 coefficients, got {num_coeffs}")
    return bands


def sh_index(l: int, m: int) -> int:
    """Flat index of (l, m)."""
    return l * (l + 1) + m


def _normalisation(l: int, m: int) -> float:
    return math.sqrt(
        (2 * l + 1) / (4.0 * math.pi) * math.exp(math.lgamma(l - m + 1) - math.lgamma(l + m + 1))
    )


def sh_basis(directions: np.ndarray, bands: int) -> np.ndarray:
    """All basis functions at unit `directions` (..., 3) -> (..., bands**2) float64.

    Stable for any number of bands: the Legendre part is the standard three-term recurrence
    on z and the azimuthal part is Re/Im of (x + i y)^m, so no atan2 and no pole problems.
    Directions are normalised here; zero vectors give Y_0,0 only.
    """
    if bands < 1:
        raise ValueError(f"bands must be >= 1, got {bands}")
    d = np.asarray(directions, dtype=np.float64)
    if d.shape[-1] != 3:
        raise ValueError(f"directions must have shape (..., 3), got {d.shape}")
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    d = np.divide(d, norm, out=np.zeros_like(d), where=norm > 0)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = np.empty(d.shape[:-1] + (bands * bands,), dtype=np.float64)

    # reduced Legendre  Pbar_l^m(z) = P_l^m(z) / sin^m(theta), no Condon-Shortley phase
    xy_pow_re = np.ones_like(x)  # Re (x + i y)^m
    xy_pow_im = np.zeros_like(x)  # Im (x + i y)^m
    p_mm = np.ones_like(z)  # Pbar_m^m = (2m - 1)!!
    for m in range(bands):
        if m > 0:
            p_mm = p_mm * (2 * m - 1)
            xy_pow_re, xy_pow_im = xy_pow_re * x - xy_pow_im * y, xy_pow_re * y + xy_pow_im * x
        p_prev, p_cur = None, p_mm
        for l in range(m, bands):
            if l == m + 1:
                p_prev, p_cur = p_cur, z * (2 * m + 1) * p_mm
            elif l > m + 1:
                p_prev, p_cur = p_cur, ((2 * l - 1) * z * p_cur - (l + m - 1) * p_prev) / (l - m)
            k = _normalisation(l, m)
            if m == 0:
                out[..., sh_index(l, 0)] = k * p_cur
            else:
                out[..., sh_index(l, m)] = SQRT2 * k * p_cur * xy_pow_re
                out[..., sh_index(l, -m)] = SQRT2 * k * p_cur * xy_pow_im
    return out


def evaluate(coeffs: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Value of the SH expansion `coeffs` (..., n) at `directions` (K, 3) -> (..., K)."""
    c = np.asarray(coeffs, dtype=np.float64)
    basis = sh_basis(directions, bands_of(c.shape[-1]))
    return c @ basis.reshape(-1, c.shape[-1]).T


def fibonacci_sphere(n: int) -> np.ndarray:
    """`n` near-uniform unit directions (n, 3) on the sphere (equal solid angle 4 pi / n)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def project(function, bands: int, samples: int = 20000) -> np.ndarray:
    """Coefficients of `function(directions (K, 3)) -> (K,) or (K, C)` by quadrature.

    Returns (bands**2,) or (C, bands**2).
    """
    dirs = fibonacci_sphere(samples)
    values = np.asarray(function(dirs), dtype=np.float64)
    basis = sh_basis(dirs, bands) * (4.0 * math.pi / samples)
    return (values.T @ basis) if values.ndim > 1 else values @ basis


def project_samples(
    directions: np.ndarray, values: np.ndarray, solid_angles: np.ndarray, bands: int
) -> np.ndarray:
    """Coefficients from samples of a function: sum_k values_k Y(d_k) solid_angle_k."""
    basis = sh_basis(directions, bands).reshape(-1, bands * bands)
    w = np.asarray(solid_angles, dtype=np.float64).reshape(-1)
    v = np.asarray(values, dtype=np.float64).reshape(w.shape[0], -1)
    coeffs = (v * w[:, None]).T @ basis
    return coeffs[0] if v.shape[1] == 1 else coeffs


def directional_light(direction: np.ndarray, intensity: float, bands: int) -> np.ndarray:
    """Coefficients of a delta light of integrated radiance `intensity` from unit `direction`."""
    return intensity * sh_basis(np.asarray(direction, dtype=np.float64), bands)


def dominant_direction(coeffs: np.ndarray) -> np.ndarray:
    """Unit vector towards the light, normalize(c[3], c[1], c[2]) = normalize(c_1,1, c_1,-1, c_1,0).

    This is the direction of the radiance-weighted mean direction, integral L(w) w dw.
    Returns zeros when the first band is zero or absent.
    """
    c = np.asarray(coeffs, dtype=np.float64)
    if c.shape[-1] < 4:
        return np.zeros(3)
    v = np.array([c[..., 3], c[..., 1], c[..., 2]], dtype=np.float64).T
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 1e-300)


_MOMENT_SAMPLES = 8192  # directions of the quadrature below the horizon (< 0.5 degree)


@lru_cache(maxsize=16)
def _moment_quadrature(bands: int) -> tuple[np.ndarray, np.ndarray]:
    """Fixed directions (K, 3) and their SH basis times the solid angle (K, bands^2)."""
    dirs = fibonacci_sphere(_MOMENT_SAMPLES)
    return dirs, sh_basis(dirs, bands) * (4.0 * math.pi / _MOMENT_SAMPLES)


def above_horizon_direction(coeffs: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Unit vector towards the light that reaches a scene standing on a surface facing `up`.

    An estimate fitted to what a scene shows is the light its surfaces receive, and below
    the horizon of the ground they stand on that is the ground's glow, not the sky: the
    direction of the first moment, integral L(w) w dw, is pulled down by it. This takes it
    out as a uniform glow of the expansion's mean radiance below the horizon, G:
    normalize(integral L(w) w dw + G pi up) (pi up = the moment of a unit uniform hemisphere),
    the moment of the light above the horizon alone, as the ground truth's `*_upper_*` fields
    define it. On those fields' own SH (bands 0..3) it is within 6 degrees of their direction
    (the moment of the band-limited hemisphere itself is up to 11 off: its ringing below the
    horizon is not uniform). `up`: unit, frame of `coeffs`. Zeros when the moment vanishes.
    """
    c = np.asarray(coeffs, dtype=np.float64)
    if c.shape[-1] < 4 or not np.any(c[1:4]):
        return np.zeros(3)  # no band 1: no direction, not "up"
    dirs, weighted_basis = _moment_quadrature(bands_of(c.shape[-1]))
    up = np.asarray(up, dtype=np.float64)
    radiance_dw = weighted_basis @ c  # L(w_k) dw_k
    glow = float(radiance_dw[dirs @ up < 0.0].sum()) / (2.0 * math.pi)
    moment = radiance_dw @ dirs + glow * math.pi * up
    n = float(np.linalg.norm(moment))
    return moment / n if n > 1e-300 else np.zeros(3)


def intensity_along(coeffs: np.ndarray, direction: np.ndarray) -> float:
    """Integrated radiance of the delta light along unit `direction` that best fits `coeffs`:
    argmin_I |c - I Y(d)|^2 = (c . Y(d)) / |Y(d)|^2 (Sloan's extraction), clipped at 0."""
    c = np.asarray(coeffs, dtype=np.float64)
    if not np.any(direction):
        return 0.0
    y = sh_basis(np.asarray(direction, dtype=np.float64), bands_of(c.shape[-1]))
    return max(0.0, float(c @ y / (y @ y)))


def dominant_light(coeffs: np.ndarray) -> tuple[np.ndarray, float]:
    """Dominant direction and the intensity of the delta light along it that best fits `coeffs`.

    Intensity = argmin_I |c - I Y(d)|^2 = (c . Y(d)) / |Y(d)|^2 (Sloan's extraction), clipped
    at 0 so a dark dominant lobe never gives negative intensity.
    """
    d = dominant_direction(coeffs)
    return d, intensity_along(coeffs, d)


def toggle_condon_shortley(coeffs: np.ndarray) -> np.ndarray:
    """Convert between the bases with and without the Condon-Shortley phase (odd m negated)."""
    c = np.array(coeffs, dtype=np.float64, copy=True)
    bands = bands_of(c.shape[-1])
    for l in range(bands):
        for m in range(-l, l + 1):
            if m % 2:
                c[..., sh_index(l, m)] *= -1.0
    return c


def rotation_matrix(rotation: np.ndarray, bands: int) -> np.ndarray:
    """(n, n) matrix M with M @ c = coefficients of f(R^T w), i.e. the function rotated by R.

    With R = R_world_cam (camera-to-world rotation), M maps camera-frame coefficients to
    world-frame coefficients. Built band by band by fitting the rotated band-l functions on
    a fixed quadrature set (exact: each band is closed under rotation).
    """
    r = np.asarray(rotation, dtype=np.float64)[:3, :3]
    n = bands * bands
    dirs = fibonacci_sphere(max(64, 4 * n))
    basis = sh_basis(dirs, bands)
    basis_rot = sh_basis(dirs @ r, bands)  # Y(R^T d) for every row d
    m = np.zeros((n, n))
    for l in range(bands):
        s = slice(l * l, (l + 1) * (l + 1))
        m[s, s] = np.linalg.lstsq(basis[:, s], basis_rot[:, s], rcond=None)[0]
    return m


def rotate(coeffs: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Coefficients of the function rotated by the 3x3 rotation (see :func:`rotation_matrix`)."""
    c = np.asarray(coeffs, dtype=np.float64)
    return c @ rotation_matrix(rotation, bands_of(c.shape[-1])).T


def lambert_band_factors(bands: int) -> np.ndarray:
    """A_l of the clamped-cosine kernel: E_lm = A_l L_lm (Ramamoorthi and Hanrahan 2001).

    A_0 = pi, A_1 = 2 pi / 3, A_l = 0 for odd l > 1, and for even l
    A_l = 2 pi (-1)^(l/2 - 1) / ((l + 2)(l - 1)) * l! / (2^l ((l/2)!)^2).
    """
    a = np.zeros(bands)
    for l in range(bands):
        if l == 0:
            a[l] = math.pi
        elif l == 1:
            a[l] = 2.0 * math.pi / 3.0
        elif l % 2 == 0:
            a[l] = (
                2.0
                * math.pi
                * (-1) ** (l // 2 - 1)
                / ((l + 2) * (l - 1))
                * math.factorial(l)
                / (2**l * math.factorial(l // 2) ** 2)
            )
    return a


def irradiance_from_radiance(coeffs: np.ndarray) -> np.ndarray:
    """Irradiance E(n) = integral L(w) max(0, n.w) dw as SH, from radiance SH (any leading dims)."""
    c = np.asarray(coeffs, dtype=np.float64)
    bands = bands_of(c.shape[-1])
    per_coeff = np.repeat(lambert_band_factors(bands), [2 * l + 1 for l in range(bands)])
    return c * per_coeff


@lru_cache(maxsize=1)
def _quadratic_weights() -> np.ndarray:
    """(9, 10) the first nine basis functions as weights of the monomials x^2, y^2, z^2, xy,
    yz, zx, x, y, z, 1: exact on the unit sphere (each is a polynomial of degree <= 2)."""
    d = fibonacci_sphere(64)
    return np.linalg.lstsq(_monomials(d), sh_basis(d, 3), rcond=None)[0].T


def _monomials(d: np.ndarray) -> np.ndarray:
    """(K, 10) the monomials of `_quadratic_weights` at directions d (K, 3)."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return np.stack([x * x, y * y, z * z, x * y, y * z, z * x, x, y, z, np.ones_like(x)], 1)


def irradiance_at(radiance: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(K,) irradiance E(n) of the radiance SH `radiance` (n >= 1 coefficients) at unit
    `normals` (K, 3; normalised here): `evaluate(irradiance_from_radiance(radiance),
    normals)` in a fraction of its time. The clamped cosine leaves band 3 at zero, so up to
    4 bands E is a quadratic form in n (Ramamoorthi and Hanrahan 2001): ten multiply-adds
    a normal, no basis built."""
    c = np.asarray(radiance, np.float64)
    if len(c) > 16:  # band 4 and up: the cosine keeps the even ones
        return evaluate(irradiance_from_radiance(c), np.asarray(normals, np.float64))
    e = irradiance_from_radiance(c[:9])
    w = e @ _quadratic_weights()[: len(e)]  # (10,) the monomials' weights
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.sqrt(np.einsum("ij,ij->i", n, n)), 1e-300)[:, None]
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    return (
        x * (w[0] * x + w[3] * y + w[5] * z + w[6])
        + y * (w[1] * y + w[4] * z + w[7])
        + z * (w[2] * z + w[8])
        + w[9]
    )


# OpenCV camera axes (x right, y down, z forward) -> OpenGL/ARCore/ARKit camera axes
# (x right, y up, z backward): a rotation by pi about x.
GL_FROM_CV = np.diag([1.0, -1.0, -1.0])


def _first_three_bands(sh_rgb: np.ndarray, rotation: np.ndarray | None) -> np.ndarray:
    """(3, 9) bands 0..2 of (3, n >= 9) RGB coefficients, optionally rotated."""
    c = np.asarray(sh_rgb, dtype=np.float64)
    if c.ndim != 2 or c.shape[0] != 3 or c.shape[1] < 9:
        raise ValueError(f"sh_rgb must have shape (3, >=9), got {c.shape}")
    c = c[:, :9]
    return rotate(c, rotation) if rotation is not None else c


def to_arcore_27(sh_rgb: np.ndarray, rotation: np.ndarray | None = None) -> list[float]:
    """ARCore `environmentalHdrAmbientSphericalHarmonics` layout: 27 floats.

    sh_rgb: (3, n >= 9) radiance SH per linear RGB channel (this module's basis, no phase).
    Output: bands 0..2 in ARCore's basis, which carries the Condon-Shortley phase (hello_ar's
    HelloArRenderer.kt factors -0.325735 on y and x): our odd-m coefficients negated,
    interleaved by colour [R0, G0, B0, R1, G1, B1, ..., R8, G8, B8], raw radiance (not
    convolved, no pi factors), order i = l(l+1)+m. ARCore's frame is OpenGL's (y up): pass
    `rotation` (3x3) to rotate the light into that frame first, e.g. ``GL_FROM_CV @
    R_cam_world``. The same numbers as `pipeline.engine_export.to_arcore`, which documents
    and tests the convention.
    """
    c = toggle_condon_shortley(_first_three_bands(sh_rgb, rotation))
    return [float(v) for v in c.T.reshape(-1)]


def to_planar_27(sh_rgb: np.ndarray, rotation: np.ndarray | None = None) -> list[float]:
    """Planar layout of this module's own coefficients: 27 floats [R0..R8, G0..G8, B0..B8].

    Our basis (no Condon-Shortley phase), order l(l+1)+m, raw radiance, optional frame
    rotation as :func:`to_arcore_27`. Not an engine's layout as such: WebXR interleaves RGB
    per coefficient, see `pipeline.engine_export` for each engine's numbers.
    """
    return [float(v) for v in _first_three_bands(sh_rgb, rotation).reshape(-1)]
