"""The estimated light as a glTF 2.0 binary asset (.glb) that engines load (issue 34, item 1).

One ``EXT_lights_image_based`` light, complete per the extension's ``light.schema.json``
(KhronosGroup/glTF, extensions/2.0/Vendor/EXT_lights_image_based/schema: required
``irradianceCoefficients`` 9 x 3, ``specularImages`` N x 6 image indices, ``specularImageSize``;
``rotation`` items in [0, 1], no other keys), referenced by the scene, beside a unit-radius
white Lambertian sphere (metallic 0, roughness 1) to see it on; optionally the main light as
a ``KHR_lights_punctual`` directional light.

- irradiance: ``engine_export.to_gltf_ibl`` (CS phase, E_lm = A_l c_lm, bands 0..2);
- specular: a cube map of the radiance, six faces per mip (+X, -X, +Y, -Y, +Z, -Z, OpenGL's
  table 8.19 orientation, the first image row the top), mip k prefiltered with GGX for
  perceptual roughness k / (N - 1) (the extension: "mip levels evenly map to roughness values
  from 0 to 1"), ``probe_cube``'s split-sum prefilter (Karis 2013, filtered importance
  sampling). Its source: the session's reflection probe (``ProbeResult.mips``, the room as
  seen from the probe's point) when given, resampled into the engine's axes; else the SH
  light itself, every band, evaluated on a SPECULAR_SIZE cube and prefiltered, so the
  specular images carry the same distant light as the irradiance (band-limited: mip 0 is
  not a sharp mirror);
- images: 4-channel PNG in Babylon.js's RGBD packing, the extension's HDR format: the
  linear radiance v is stored as rgb = (v D)^(1/2.2), alpha = D, D = min(1, floor(255 /
  max(v)) / 255) >= 1/255 (Babylon ``helperFunctions`` ``toRGBD``/``fromRGBD``:
  v = rgb^2.2 / alpha), so values up to 255 fit; units: the SH's radiance units;
- frame: the asset's geometry (the sphere, the main light's node) in glTF's axes
  (right-handed, +y up, +z the front): ``engine_from_world`` as in engine_export; the
  light's coefficients and cube faces in those axes mirrored in x (FILE_FROM_GLTF), the
  frame Babylon.js, the extension's reference loader, reads them in for its default
  (left-handed) scene, whose glTF root node turns the asset by (x, y, z) -> (-x, y, z) and
  leaves the environment as it is; in a right-handed Babylon scene
  (``useRightHandedSystem``) the light shows turned 180 degrees about +y (decision 0040,
  measured in tests/test_gltf_render.py); ``rotation`` the identity.
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from arlight.pipeline import probe_cube, sh
from arlight.pipeline.engine_export import engine_sh, main_light, to_gltf_ibl
from arlight.pipeline.environment_map import CUBE_FACES, cube_face_directions

# the light's axes in the file from glTF's: x mirrored (docs/decisions/0040-gltf-light-axes.md)
FILE_FROM_GLTF = np.diag([-1.0, 1.0, 1.0])
SPECULAR_SIZE = 64  # texels a face of mip 0 when made from the SH (mips 64, 32, 16, 8, 4)
RGBD_MAX = 255.0  # the largest radiance RGBD packs (Babylon's rgbdMaxRange)
SPHERE_SEGMENTS = (48, 24)  # longitude, latitude
_FLOAT, _UINT16 = 5126, 5123  # glTF accessor component types
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def rgbd_encode(radiance: np.ndarray) -> np.ndarray:
    """(..., 3) linear radiance -> (..., 4) uint8 RGBA in Babylon's RGBD packing (module
    text); values above RGBD_MAX clip."""
    v = np.maximum(np.asarray(radiance, np.float64), 0.0)
    peak = np.maximum(v.max(axis=-1, keepdims=True), 1e-7)
    d = np.clip(np.floor(np.maximum(RGBD_MAX / peak, 1.0)) / 255.0, 0.0, 1.0)
    rgb = np.clip((v * d) ** (1.0 / 2.2), 0.0, 1.0)
    return np.round(np.concatenate([rgb, d], axis=-1) * 255.0).astype(np.uint8)


def rgbd_decode(rgba: np.ndarray) -> np.ndarray:
    """(..., 4) uint8 RGBD -> (..., 3) float64 linear radiance (Babylon's ``fromRGBD``)."""
    x = np.asarray(rgba, np.float64) / 255.0
    return x[..., :3] ** 2.2 / np.maximum(x[..., 3:], 1.0 / 255.0)


def specular_mips(
    sh_engine: np.ndarray,
    probe: probe_cube.CubeMips | None = None,
    engine_from_world: np.ndarray | None = None,
) -> probe_cube.CubeMips:
    """The GGX-prefiltered radiance cube in the engine's axes: of the probe (world axes,
    resampled level by level at each texel's world direction) when given, else of the (3, n)
    engine-frame radiance SH ``sh_engine`` (every band)."""
    if probe is None:
        c = np.asarray(sh_engine, np.float64)
        faces = [
            np.maximum(
                sh.sh_basis(cube_face_directions(f, SPECULAR_SIZE), sh.bands_of(c.shape[1])) @ c.T,
                0.0,
            ).astype(np.float32)
            for f in CUBE_FACES
        ]
        return probe_cube.prefilter(np.stack(faces))
    r = np.eye(3) if engine_from_world is None else np.asarray(engine_from_world, np.float64)
    levels = []
    for k, n in enumerate(probe.sizes):
        dirs_world = probe_cube.texel_directions(int(n)).reshape(-1, 3) @ r  # R^T d_engine
        texels = probe_cube.sample(probe, dirs_world, float(k))
        levels.append(np.asarray(texels, np.float32).reshape(6, int(n), int(n), 3))
    return probe_cube.CubeMips(levels, probe.roughness)


def _quaternion_z_to(d: np.ndarray) -> list[float]:
    """Unit quaternion (x, y, z, w) turning +z onto unit d (a directional light shines
    along its node's -z, so from d towards the origin)."""
    z = np.array([0.0, 0.0, 1.0])
    c = float(np.clip(z @ d, -1.0, 1.0))
    if c < -1.0 + 1e-9:
        return [1.0, 0.0, 0.0, 0.0]  # half a turn about x
    axis = np.cross(z, d)
    w = math.sqrt((1.0 + c) / 2.0)
    xyz = axis / (2.0 * w)
    return [float(xyz[0]), float(xyz[1]), float(xyz[2]), float(w)]


def _sphere() -> tuple[np.ndarray, np.ndarray]:
    """Unit UV sphere: (V, 3) float32 positions (= normals), (T * 3,) uint16 indices."""
    n_lon, n_lat = SPHERE_SEGMENTS
    theta = np.linspace(0.0, math.pi, n_lat + 1)
    phi = np.linspace(0.0, 2.0 * math.pi, n_lon + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)], -1).reshape(-1, 3)
    idx = []
    for i in range(n_lat):
        for j in range(n_lon):
            a, b = i * (n_lon + 1) + j, (i + 1) * (n_lon + 1) + j
            idx += [a, b, a + 1, a + 1, b, b + 1]  # counter-clockwise seen from outside
    return v.astype(np.float32), np.asarray(idx, np.uint16)


class _Bin:
    """The GLB's binary chunk: buffer views appended 4-byte aligned."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []

    def add(self, payload: bytes, target: int | None = None) -> int:
        self.data += b"\0" * (-len(self.data) % 4)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(payload)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        self.data += payload
        return len(self.views) - 1


def light_asset(
    sh_world: npt.ArrayLike,
    engine_from_world: np.ndarray | None = None,
    probe: probe_cube.CubeMips | None = None,
    direction_world: npt.ArrayLike | None = None,
    with_main_light: bool = False,
) -> tuple[dict, bytes]:
    """(glTF JSON, binary chunk) of the light: sh_world (n,) luminance or (3, n) RGB radiance
    SH (world frame, n >= 9); probe: the reflection probe's mips (world axes) or None;
    with_main_light: also a KHR_lights_punctual directional light along direction_world
    (the Result's dominant direction; engine_export.main_light), which lights the sphere a
    second time on top of the image-based light (for engines' shadows)."""
    gltf_from_world = np.eye(3) if engine_from_world is None else engine_from_world
    file_from_world = FILE_FROM_GLTF @ np.asarray(gltf_from_world, np.float64)
    c = engine_sh(np.asarray(sh_world, np.float64), file_from_world, keep_bands=True)
    ibl = to_gltf_ibl(c)  # already in the file's axes
    mips = specular_mips(c, probe, file_from_world)
    buf = _Bin()
    images, spec = [], []
    for level in mips.levels:
        row = []
        for face in level:
            ok, png = cv2.imencode(".png", cv2.cvtColor(rgbd_encode(face), cv2.COLOR_RGBA2BGRA))
            if not ok:
                raise ValueError("OpenCV could not encode a PNG")
            images.append({"bufferView": buf.add(png.tobytes()), "mimeType": "image/png"})
            row.append(len(images) - 1)
        spec.append(row)
    positions, indices = _sphere()
    pos_view = buf.add(positions.tobytes(), _ARRAY_BUFFER)
    idx_view = buf.add(indices.tobytes(), _ELEMENT_ARRAY_BUFFER)
    gltf: dict = {
        "asset": {"version": "2.0", "generator": "arlight"},
        "extensionsUsed": ["EXT_lights_image_based"],
        "extensions": {
            "EXT_lights_image_based": {
                "lights": [
                    {
                        "name": "arlight estimate",
                        **ibl,
                        "specularImageSize": int(mips.size),
                        "specularImages": spec,
                    }
                ]
            }
        },
        "scene": 0,
        "scenes": [{"nodes": [0], "extensions": {"EXT_lights_image_based": {"light": 0}}}],
        "nodes": [{"name": "sphere", "mesh": 0}],
        "meshes": [
            {
                "name": "sphere",
                "primitives": [
                    {"attributes": {"POSITION": 0, "NORMAL": 0}, "indices": 1, "material": 0}
                ],
            }
        ],
        "materials": [
            {
                "name": "white diffuse",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 1.0,
                },
            }
        ],
        "accessors": [
            {
                "bufferView": pos_view,
                "componentType": _FLOAT,
                "count": len(positions),
                "type": "VEC3",
                "min": [-1.0, -1.0, -1.0],
                "max": [1.0, 1.0, 1.0],
            },
            {
                "bufferView": idx_view,
                "componentType": _UINT16,
                "count": len(indices),
                "type": "SCALAR",
            },
        ],
        "images": images,
    }
    if with_main_light:
        light = main_light(np.asarray(sh_world, np.float64), engine_from_world, direction_world)
        rgb = np.asarray(light["intensity"])
        peak = float(rgb.max())
        gltf["extensionsUsed"].append("KHR_lights_punctual")
        gltf["extensions"]["KHR_lights_punctual"] = {
            "lights": [
                {
                    "name": "main light",
                    "type": "directional",
                    "color": [float(x) for x in (rgb / peak if peak > 0 else np.ones(3))],
                    "intensity": peak,
                }
            ]
        }
        gltf["nodes"].append(
            {
                "name": "main light",
                "rotation": _quaternion_z_to(np.asarray(light["direction"])),
                "extensions": {"KHR_lights_punctual": {"light": 0}},
            }
        )
        gltf["scenes"][0]["nodes"].append(1)
    buf.data += b"\0" * (-len(buf.data) % 4)
    gltf["bufferViews"] = buf.views
    gltf["buffers"] = [{"byteLength": len(buf.data)}]
    return gltf, bytes(buf.data)


def glb_bytes(gltf: dict, binary: bytes) -> bytes:
    """The GLB container (glTF 2.0 section 4.4): header, JSON chunk, BIN chunk."""
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return (
        struct.pack("<4sII", b"glTF", 2, total)
        + struct.pack("<I4s", len(text), b"JSON")
        + text
        + struct.pack("<I4s", len(binary), b"BIN\0")
        + binary
    )


def read_glb(data: bytes) -> tuple[dict, bytes]:
    """(JSON, BIN chunk) of a GLB; ValueError for anything else."""
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2 or total != len(data):
        raise ValueError(f"not a glTF 2.0 GLB of {len(data)} bytes")
    n, kind = struct.unpack_from("<I4s", data, 12)
    if kind != b"JSON":
        raise ValueError("the first GLB chunk is not JSON")
    gltf = json.loads(data[20 : 20 + n])
    m, kind = struct.unpack_from("<I4s", data, 20 + n)
    if kind != b"BIN\0":
        raise ValueError("the second GLB chunk is not BIN")
    return gltf, data[28 + n : 28 + n + m]


def write_glb(path: str | Path, *args, **kwargs) -> Path:
    """light_asset(*args, **kwargs) written to `path` (.glb)."""
    path = Path(path)
    path.write_bytes(glb_bytes(*light_asset(*args, **kwargs)))
    return path
