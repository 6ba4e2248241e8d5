"""The estimated light in each target engine's own numbers (issue 18, item 1).

Input everywhere: ``sh_world``, radiance SH in this project's convention (pipeline/sh.py:
real, orthonormal, WITHOUT the Condon-Shortley phase, index ``sh_index(l, m) = l(l+1)+m``),
either (n,) luminance (the same value is written to R, G and B) or (3, n) linear RGB, with
n = bands**2 >= 9 (bands 0..2 are exported; Filament's text keeps all bands given); and
``engine_from_world``, the 3x3 orthogonal matrix taking world directions to the engine's
axes (``None``: the world already is the engine's frame). It may be a reflection (det -1)
for a left-handed engine (Unity): SH bands are closed under any orthogonal map. Ready-made
frame changes from an OpenCV-style frame (x right, y down, z forward):
``sh.GL_FROM_CV`` (x right, y up, z backward: OpenGL, ARCore, WebXR, three.js, glTF,
Filament; right-handed, +y up) and :data:`UNITY_FROM_CV` (x right, y up, z forward:
Unity, left-handed, +y up). For a world frame that is not a camera's, compose:
``GL_FROM_CV @ R_cam_world`` etc.

Symbols below: c_lm our radiance coefficients in the engine's axes; E_lm = A_l c_lm the
irradiance (Ramamoorthi-Hanrahan, A = pi, 2 pi/3, pi/4; ``sh.irradiance_from_radiance``);
K = (0.282095, 0.488603, 0.488603, 0.488603, 1.092548, 1.092548, 0.315392, 1.092548,
0.546274) the constants of the basis polynomials (1, y, z, x, xy, yz, 3z^2-1, xz, x^2-y^2);
"CS" the Condon-Shortley phase, (-1)^m on odd m (``sh.toggle_condon_shortley``).

| target | basis | stores | layout |
|---|---|---|---|
| ARCore | CS | c_lm (radiance) | 27 floats, RGB interleaved per coefficient |
| WebXR / three.js | no CS | c_lm (radiance) | 27 floats, RGB interleaved per coefficient |
| glTF EXT_lights_image_based | CS | E_lm (irradiance) | 9 x [r, g, b] |
| Unity SphericalHarmonicsL2 | no CS | E_lm K_lm / pi | [channel][9] |
| Filament / cmgen text | CS | c_lm (radiance) | one "(r, g, b); // Llm" line per coefficient |

Each exporter's docstring names its source and what the engine's shader computes of it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple, Protocol

import numpy as np
import numpy.typing as npt

from . import sh
from .color import LUMA

# Unity's axes from an OpenCV-style frame: x right, y up, z forward (left-handed): y flips.
UNITY_FROM_CV = np.diag([1.0, -1.0, 1.0])

# Polynomial constants of the real SH basis, bands 0..2, index sh_index(l, m), no CS phase.
BASIS_CONSTANTS = np.array(
    [
        0.5 / math.sqrt(math.pi),
        *(3 * [math.sqrt(3.0 / (4.0 * math.pi))]),
        0.5 * math.sqrt(15.0 / math.pi),
        0.5 * math.sqrt(15.0 / math.pi),
        0.25 * math.sqrt(5.0 / math.pi),
        0.5 * math.sqrt(15.0 / math.pi),
        0.25 * math.sqrt(15.0 / math.pi),
    ]
)


class ExportError(ValueError):
    """Light or frame that an exporter refuses: what was expected and what came."""


class SourceLike(Protocol):
    """A compact source the main light can be (a `core.frames.CompactLight`, a MainSource)."""

    @property
    def direction_world(self) -> npt.ArrayLike: ...
    @property
    def intensity(self) -> float: ...
    @property
    def rgb(self) -> npt.ArrayLike | None: ...


class MainSource(NamedTuple):
    """A compact source as a Result carries it (main_source_from_wire): direction_world (3,)
    unit towards it, world frame; intensity: its integrated radiance (the irradiance on a
    surface facing it, the SH's units); rgb: the same per linear R, G, B, or None."""

    direction_world: npt.ArrayLike
    intensity: float
    rgb: npt.ArrayLike | None = None


def main_source_from_wire(
    compact_sources: Sequence[Mapping[str, Any]] | None,
) -> MainSource | None:
    """The first of a Result's `compact_sources` (the one its dominant direction names) as a
    MainSource; None when the Result has none."""
    if not compact_sources:
        return None
    first = compact_sources[0]
    return MainSource(first["direction_world"], float(first["intensity"]), first["rgb"])


def _engine_sh(
    sh_world: np.ndarray, engine_from_world: np.ndarray | None, keep_bands: bool = False
) -> np.ndarray:
    """(3, n) radiance SH in the engine's axes, our basis; bands 0..2 unless `keep_bands`.

    The one check of the exporters' inputs (shape, finite, orthogonal frame change).
    """
    c = np.asarray(sh_world, dtype=np.float64)
    if c.ndim == 1:
        c = np.repeat(c[None], 3, axis=0)
    if c.ndim != 2 or c.shape[0] != 3:
        raise ExportError(f"sh_world must have shape (n,) or (3, n), got {c.shape}")
    try:
        bands = sh.bands_of(c.shape[1])
    except ValueError as err:
        raise ExportError(str(err)) from None
    if bands < 3:
        raise ExportError(f"sh_world needs at least 3 bands (9 coefficients), got {c.shape[1]}")
    if not np.all(np.isfinite(c)):
        raise ExportError("sh_world has non-finite values")
    if not keep_bands:
        c = c[:, :9]
    if engine_from_world is None:
        return c
    r = np.asarray(engine_from_world, dtype=np.float64)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6):
        raise ExportError(
            f"engine_from_world must be an orthogonal 3x3 matrix, got shape "
            f"{r.shape}{'' if r.shape != (3, 3) else ' (not orthogonal)'}"
        )
    return sh.rotate(c, r)


def _engine_direction(
    direction_world: npt.ArrayLike, engine_from_world: np.ndarray | None
) -> np.ndarray:
    """Unit (3,) direction in the engine's axes; zeros for a zero direction (no light)."""
    d = np.asarray(direction_world, dtype=np.float64)
    if d.shape != (3,) or not np.all(np.isfinite(d)):
        raise ExportError(f"direction_world must be 3 finite floats, got shape {d.shape}")
    if engine_from_world is not None:
        d = np.asarray(engine_from_world, dtype=np.float64) @ d
    n = float(np.linalg.norm(d))
    return d / n if n > 1e-12 else np.zeros(3)


def engine_sh(
    sh_world: np.ndarray, engine_from_world: np.ndarray | None, keep_bands: bool = False
) -> np.ndarray:
    """(3, n) radiance SH in the engine's axes, our basis (no CS phase); bands 0..2 unless
    `keep_bands`. ExportError for a bad light or frame change (what the exporters check)."""
    return _engine_sh(sh_world, engine_from_world, keep_bands)


def _floats(a: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(a).reshape(-1)]


def to_arcore(sh_world: np.ndarray, engine_from_world: np.ndarray | None = None) -> list[float]:
    """ARCore ``LightEstimate.acquireEnvironmentalHdrAmbientSphericalHarmonics()``: 27 floats.

    Source: ARCore's hello_ar sample, ``HelloArRenderer.kt`` (``sphericalHarmonicFactors``
    {0.282095, -0.325735, 0.325735, -0.325735, 0.273137, -0.273137, 0.078848, -0.273137,
    0.136569}, taken from Filament's SH annex) and its ``environmental_hdr.frag``
    (``sh[0] + sh[1]*n.y + sh[2]*n.z + sh[3]*n.x + sh[4]*n.y*n.x + sh[5]*n.y*n.z +
    sh[6]*(3 n.z^2 - 1) + sh[7]*n.z*n.x + sh[8]*(n.x^2 - n.y^2)``, n the world normal).
    The factors are A_l K_lm / pi with the CS sign, so the numbers are:

    - basis: real SH WITH the Condon-Shortley phase (our odd-m coefficients negated);
    - units: radiance c_lm, no pi factor, not convolved; the sample's shader then gives
      E(n) / pi, the diffuse light for albedo 1;
    - order: l(l+1)+m, bands 0..2; layout [R0, G0, B0, R1, G1, B1, ..., R8, G8, B8];
    - frame: ARCore's world (right-handed, +y up against gravity, OpenGL axes):
      ``engine_from_world`` = e.g. ``sh.GL_FROM_CV @ R_cam_world``.
    """
    c = sh.toggle_condon_shortley(_engine_sh(sh_world, engine_from_world))
    return _floats(c.T)


def to_webxr(sh_world: np.ndarray, engine_from_world: np.ndarray | None = None) -> list[float]:
    """WebXR ``XRLightEstimate.sphericalHarmonicsCoefficients`` as three.js reads it: 27 floats.

    Sources: WebXR Lighting Estimation API Level 1 (MDN: "27 elements ... every 3 elements
    defining red, green, and blue components for each coefficient", in the light probe's
    ``probeSpace``); three.js ``WebXRLightProbe`` / ``XREstimatedLight`` passing it to
    ``LightProbe.sh.fromArray``, and ``src/math/SphericalHarmonics3.js``: ``getAt``
    (radiance, constants 0.282095, 0.488603 y z x, 1.092548 xy yz xz, 0.315392 (3z^2-1),
    0.546274 (x^2-y^2), all positive) and ``getIrradianceAt`` / the shader's
    ``shGetIrradianceAt`` (the same times pi, 2 pi/3, pi/4: true irradiance E(n), which the
    material multiplies by BRDF_Lambert = albedo / pi).

    - basis: real SH without the CS phase (ours); units: radiance c_lm, no pi factor;
    - order: l(l+1)+m, bands 0..2; layout [R0, G0, B0, ..., R8, G8, B8];
    - frame: the reference space (right-handed, +y up, OpenGL axes).
    """
    return _floats(_engine_sh(sh_world, engine_from_world).T)


def to_gltf_ibl(sh_world: np.ndarray, engine_from_world: np.ndarray | None = None) -> dict:
    """One light of glTF ``EXT_lights_image_based`` without its specular images (the Result's
    layout; the complete, loadable light with them is pipeline/gltf_asset.py's .glb).

    Sources: the extension's README (KhronosGroup/glTF, extensions/2.0/Vendor/
    EXT_lights_image_based: "spherical harmonic coefficients for irradiance up to l=2 ...
    a 9x3 array", ``rotation`` a quaternion, ``intensity`` a multiplier) and its reference
    loader, Babylon.js ``EXT_lights_image_based.ts``: ``SphericalHarmonics.FromArray``,
    ``scaleInPlace(intensity)``, ``convertIrradianceToLambertianRadiance`` (x 1/pi), on
    ``sphericalPolynomial.ts``' basis ``SH3ylmBasisConstants`` (odd m negative: the CS phase)
    times (1, y, z, x, xy, yz, 3z^2-1, xz, x^2-y^2).

    - basis: real SH WITH the CS phase; units: irradiance E_lm = A_l c_lm (the loader
      divides by pi for the Lambertian radiance);
    - order: l(l+1)+m; layout ``irradianceCoefficients`` = 9 x [r, g, b];
    - frame: glTF's (right-handed, +y up, +z the asset's front); the frame change is
      applied to the coefficients, so ``rotation`` is the identity [0, 0, 0, 1] (x, y, z, w).
    """
    e = sh.toggle_condon_shortley(
        sh.irradiance_from_radiance(_engine_sh(sh_world, engine_from_world))
    )
    return {
        "intensity": 1.0,
        "rotation": [0.0, 0.0, 0.0, 1.0],
        "irradianceCoefficients": [_floats(e[:, i]) for i in range(9)],
    }


def to_unity(
    sh_world: np.ndarray, engine_from_world: np.ndarray | None = None
) -> list[list[float]]:
    """Unity ``UnityEngine.Rendering.SphericalHarmonicsL2``: ``sh[channel][coefficient]``.

    Sources: Unity's built-in packing of SphericalHarmonicsL2 into ``unity_SHAr/Ag/Ab``
    = (sh[3], sh[1], sh[2], sh[0] - sh[6]), ``unity_SHBr/Bg/Bb`` = (sh[4], sh[5], 3 sh[6],
    sh[7]), ``unity_SHC`` = (sh[r,8], sh[g,8], sh[b,8]) (as in Unity's forum answer and
    keijiro's LightProbeUtility, and pema99/SHTools ``GetShaderCoefficients``), evaluated by
    ``SHEvalLinearL0L1`` (dot(SHA, (n, 1))) + ``SHEvalLinearL2`` (dot(SHB, n.xyzz * n.yzzx)
    + SHC (n.x^2 - n.y^2)) of UnityCG.cginc / ShaderLibrary; and pema99/SHTools
    ``RawCoefficientsToUnityConvention``: the stored value is the coefficient times its basis
    constant divided by pi.

    - basis: polynomial coefficients, no CS phase: sh[i] = E_lm K_lm / pi, so
      ShadeSH9(n) = E(n) / pi (the diffuse light for albedo 1, Unity's materials multiply
      by albedo with no 1/pi); consistent with ``SphericalHarmonicsL2.AddDirectionalLight``
      (Y_lm(d) A_l K_lm x colour x intensity, as shivaduke28/shader-sh re-derives it) for a
      Unity light intensity = our delta light's integrated radiance / pi;
    - units: irradiance / pi; order: l(l+1)+m (1: y, 2: z, 3: x); layout 3 x 9, [r, g, b][i];
    - frame: Unity's world (LEFT-handed, +y up, +z forward): from an OpenCV-style frame
      ``UNITY_FROM_CV @ R_cam_world`` (a reflection, det -1).
    """
    e = sh.irradiance_from_radiance(_engine_sh(sh_world, engine_from_world))
    u = e * BASIS_CONSTANTS / math.pi
    return [_floats(u[ch]) for ch in range(3)]


def to_filament_text(sh_world: np.ndarray, engine_from_world: np.ndarray | None = None) -> str:
    """Filament's SH text as ``cmgen --sh-output=FILE`` writes it, for
    ``IndirectLight.Builder().radiance(bands, sh)``.

    Sources: Filament ``tools/cmgen`` (output of ``cmgen --sh=N --sh-output``, measured
    against ours in benchmarks/ibl_cmgen.py and docs/results/ibl.md, "Agreement with
    Filament's cmgen": cmgen = ours with odd m negated); ``IndirectLight::Builder::radiance()``
    convolves to irradiance (A_l) and pre-scales as cmgen's ``CubemapSH::
    preprocessSHForShader`` does, by A[i] / pi with A = (1/(2 sqrt(pi)), -sqrt(3)/(2 sqrt(pi)),
    sqrt(3)/(2 sqrt(pi)), -sqrt(3)/(2 sqrt(pi)), sqrt(15)/(2 sqrt(pi)), -sqrt(15)/(2 sqrt(pi)),
    sqrt(5)/(4 sqrt(pi)), -sqrt(15)/(2 sqrt(pi)), sqrt(15)/(4 sqrt(pi))), the CS-signed K:
    together the factors of ARCore's sample; ``light_indirect.fs``
    ``Irradiance_SphericalHarmonics`` evaluates sh[0] + sh[1] n.y + sh[2] n.z + sh[3] n.x +
    sh[4] n.y n.x + sh[5] n.y n.z + sh[6] (3 n.z^2 - 1) + sh[7] n.z n.x + sh[8] (n.x^2 - n.y^2)
    = E(n) / pi.

    - basis: real SH WITH the CS phase; units: radiance c_lm (cmgen without
      ``--sh-irradiance``); every band of ``sh_world`` is written (cmgen ``--sh=bands``);
    - order: l(l+1)+m; layout: one line per coefficient ``( r,  g,  b); // Llm``;
    - frame: Filament's world (right-handed, +y up, OpenGL axes).
    """
    c = sh.toggle_condon_shortley(_engine_sh(sh_world, engine_from_world, keep_bands=True))
    lines = []
    for l in range(sh.bands_of(c.shape[1])):
        for m in range(-l, l + 1):
            r, g, b = c[:, sh.sh_index(l, m)]
            lines.append(f"({r: .15f}, {g: .15f}, {b: .15f}); // L{l}{m}")
    return "\n".join(lines) + "\n"


def main_light(
    sh_world: np.ndarray,
    engine_from_world: np.ndarray | None = None,
    direction_world: npt.ArrayLike | None = None,
    source: SourceLike | None = None,
) -> dict[str, list[float]]:
    """The main directional light for ARCore ``getEnvironmentalHdrMainLightDirection`` /
    ``...MainLightIntensity`` and WebXR ``XRLightEstimate.primaryLightDirection`` /
    ``primaryLightIntensity``.

    Sources: MDN / WebXR Lighting Estimation API Level 1, ``primaryLightDirection``: "the
    direction to the primary light source from the probeSpace", default (0, 1, 0) "a light
    shining straight down from above"; ARCore's ``LightEstimate`` reference (the same default,
    world space); hello_ar passes both to its shader as the light's direction and colour.

    - direction: unit vector TOWARDS the light in the engine's frame: ``direction_world``
      (the Result's ``dominant_direction_world``, the light above the horizon of the surface
      the scene stands on: one notion of "the light" across outputs) after the frame change;
      without it ``sh.dominant_direction`` of the luminance (whole sphere); (0, 1, 0) when it
      vanishes, as the engines' own default;
    - intensity: linear RGB, the integrated radiance of the delta light along it that best
      fits each channel (``sh.intensity_along``, Sloan's extraction): the irradiance on a
      surface facing the light, in this project's units (no engine calibration);
    - with a compact ``source`` (the Result's first ``compact_sources`` entry): its direction
      (equal to the Result's dominant direction) and its intensity, the same quantity (the
      irradiance on a surface facing it): its ``rgb``, else its luminance ``intensity``
      times the colour of the SH's extraction along it (scaled to luminance 1);
    - layout: {"direction": [x, y, z], "intensity": [r, g, b]}.
    """
    c = _engine_sh(sh_world, engine_from_world)
    if source is not None:  # 2.8 deg from the sun, not 35: docs/results/compact-exports.md
        direction = _engine_direction(source.direction_world, engine_from_world)
        if np.any(direction):
            return {"direction": _floats(direction), "intensity": _source_rgb(source, c, direction)}
    if direction_world is None:
        direction = sh.dominant_direction(LUMA @ c)
    else:
        direction = _engine_direction(direction_world, engine_from_world)
    if not np.any(direction):
        return {"direction": [0.0, 1.0, 0.0], "intensity": [0.0, 0.0, 0.0]}
    return {
        "direction": _floats(direction),
        "intensity": [sh.intensity_along(c[ch], direction) for ch in range(3)],
    }


def _source_rgb(source: SourceLike, c: np.ndarray, direction: np.ndarray) -> list[float]:
    """A compact source's linear RGB intensity (>= 0): its own rgb, else its luminance
    times the chromaticity of the SH `c` (3, n) along unit `direction` (engine frame)."""
    if source.rgb is not None:
        rgb = np.asarray(source.rgb, dtype=np.float64)
        if rgb.shape != (3,) or not np.all(np.isfinite(rgb)):
            raise ExportError(f"source rgb must be 3 finite floats, got shape {rgb.shape}")
        return _floats(np.maximum(rgb, 0.0))
    k = float(source.intensity)
    if not math.isfinite(k):
        raise ExportError(f"source intensity must be finite, got {k}")
    along = np.array([sh.intensity_along(c[ch], direction) for ch in range(3)])
    lum = float(LUMA @ along)
    colour = along / lum if lum > 1e-12 else np.ones(3)
    return _floats(max(k, 0.0) * colour)


# --------------------------------------------------------------- the reflection probe's cube

# How each engine's cube textures are read (issue 33, item 3): the frame its sampler looks
# the OpenGL face table (4.6, table 8.19: faces +X, -X, +Y, -Y, +Z, -Z, rows from the top)
# up in, from the engine's own axes. Filament samples `samplerCubemap`s with the world
# direction as it is (filament/src/materials/skybox.mat: texture(skybox, eyeDirection);
# the IBL's prefiltered cube likewise), ARCore's environmental HDR cube map is OpenGL's, so
# both read the table in their own (right-handed, +y up) axes; three.js samples a
# `CubeTexture` at (flipEnvMap x, y, z) with flipEnvMap = -1 (the RenderMan cube maps,
# left-handed: WebGLBackground / envmap_fragment; not for render targets), which
# `PMREMGenerator.fromCubemap` reads the same way: its faces are the table in mirrored axes.
# Checked against each engine's lookup in tests/test_probe_engines.py (three.js rendered).
CUBE_LOOKUP_FROM_ENGINE = {
    "filament": np.eye(3),
    "arcore": np.eye(3),
    "threejs": np.diag([-1.0, 1.0, 1.0]),
}


class CubeLike(Protocol):
    """A cube map with mip levels (`probe_cube.CubeMips`, or a Result's `ProbeCube`)."""

    @property
    def levels(self) -> list[np.ndarray]: ...
    @property
    def roughness(self) -> Any: ...


def probe_faces(
    probe: CubeLike, engine_from_world: np.ndarray | None, engine: str
) -> list[np.ndarray]:
    """The reflection probe's cube map as `engine` loads it (CUBE_LOOKUP_FROM_ENGINE):
    per level, (6, n, n, 3) float32 faces in the order +X, -X, +Y, -Y, +Z, -Z (three.js:
    `CubeTexture` images px, nx, py, ny, pz, nz; Filament: `Texture::setImage` with face
    offsets in that order; first row the top), linear radiance (the probe's units), each
    texel the probe's radiance along the world direction it stands for in the engine's
    axes. probe: levels of (6, n, n, 3) in WORLD axes (the pipeline's CubeMips or a Result's
    probe); engine_from_world: 3x3 orthogonal (e.g. sh.GL_FROM_CV @ R^T for the camera
    frame with OpenGL's axes, as the other layouts; None: the world is the engine's frame).
    An axis-aligned frame change moves texels exactly; any other is sampled bilinearly at
    each level (probe_cube.sample)."""
    from . import probe_cube

    if engine not in CUBE_LOOKUP_FROM_ENGINE:
        raise ExportError(
            f"no cube map convention for {engine!r}; choose one of "
            f"{', '.join(CUBE_LOOKUP_FROM_ENGINE)}"
        )
    r = np.eye(3) if engine_from_world is None else np.asarray(engine_from_world, np.float64)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6):
        raise ExportError(f"engine_from_world must be an orthogonal 3x3, got {r.tolist()}")
    lookup_from_world = CUBE_LOOKUP_FROM_ENGINE[engine] @ r
    levels = [np.asarray(lv, np.float32) for lv in probe.levels]
    for k, lv in enumerate(levels):
        n = levels[0].shape[1] >> k
        if lv.shape != (6, n, n, 3):
            raise ExportError(f"probe level {k} must have shape (6, {n}, {n}, 3), got {lv.shape}")
    cube = probe_cube.CubeMips(levels, np.zeros(len(levels)))
    out = []
    for k, lv in enumerate(levels):
        n = lv.shape[1]
        # the world direction of each of the engine's texels: lookup -> world is the transpose
        world = probe_cube.texel_directions(n).reshape(-1, 3) @ lookup_from_world
        texels = probe_cube.sample(cube, world, float(k))
        out.append(np.asarray(texels, np.float32).reshape(6, n, n, 3))
    return out


# the layouts by name (`--export`, the protocol's EXPORT_LAYOUTS); main_light: ARCore's main
# light / WebXR's primary light, beside the SH of "arcore" or "webxr"
EXPORTERS = {
    "arcore": to_arcore,
    "webxr": to_webxr,
    "gltf": to_gltf_ibl,
    "unity": to_unity,
    "filament": to_filament_text,
    "main_light": main_light,
}


def camera_exports(
    sh_world: npt.ArrayLike,
    world_from_cam: npt.ArrayLike,
    names: list[str] | tuple[str, ...],
    direction_world: npt.ArrayLike | None = None,
    source: SourceLike | None = None,
) -> dict:
    """The light of one frame in each named layout (EXPORTERS), in the CAMERA frame with the
    engine's axes (OpenGL's x right, y up, z back: sh.GL_FROM_CV; Unity's left-handed
    UNITY_FROM_CV): an app turns it into its own world with its camera pose.
    sh_world: (n,) luminance or (3, n) RGB world-frame radiance SH; world_from_cam (4, 4);
    direction_world: the Result's dominant_direction_world (unit, world), the main light's
    direction (None: the SH's own, whole sphere); source: the frame's first compact source
    (FrameResult.compact_sources[0], or main_source_from_wire of a Result's), which the main
    light then is (direction and intensity; None: none was kept)."""
    cam_from_world = np.asarray(world_from_cam, np.float64)[:3, :3].T
    out: dict[str, object] = {}
    for name in names:
        axes = UNITY_FROM_CV if name == "unity" else sh.GL_FROM_CV
        light = np.asarray(sh_world, np.float64)
        if name == "main_light":
            out[name] = main_light(light, axes @ cam_from_world, direction_world, source)
        else:
            out[name] = EXPORTERS[name](light, axes @ cam_from_world)
    return out
