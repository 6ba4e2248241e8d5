"""The reflection probe in a .glb's EXT_lights_image_based specular images, rendered by
Babylon.js (the extension's reference loader) in headless Chromium (issue 33, item 3): a
mirror sphere lit by nothing but the file's light reflects, on its right, top and centre,
what the probe holds along glTF's +x, +y and +z (the axes the asset says its light is in).

Skipped, saying why, without Chromium or Babylon's browser builds (tests/test_gltf_render.py
has the page and the harness)."""

from __future__ import annotations

import math

import numpy as np
from test_gltf_render import SIZE, _render

from arlight.pipeline import gltf_asset as ga
from arlight.pipeline import probe_cube

COS_45 = math.cos(math.radians(45.0))


def _coloured_axes(d: np.ndarray) -> np.ndarray:
    """Red within 45 degrees of +x, green of +y, blue of +z, dark grey elsewhere."""
    out = np.full(d.shape, 0.05)
    for axis in range(3):
        near = d[..., axis] > COS_45
        out[near] = np.eye(3)[axis]
    return out


def _mirror_probe_glb() -> bytes:
    size = 64
    levels = [
        _coloured_axes(probe_cube.texel_directions(size >> k)).astype(np.float32)
        for k in range(probe_cube.num_levels(size))
    ]
    probe = probe_cube.CubeMips(levels, probe_cube.level_roughness(len(levels)))
    light = np.zeros((3, 16))
    light[:, 0] = 0.05 * 2.0 * math.sqrt(math.pi)  # a dim uniform irradiance
    gltf, binary = ga.light_asset(light, None, probe=probe)  # world = glTF's axes
    gltf["materials"][0] = {
        "name": "mirror",
        "pbrMetallicRoughness": {
            "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
            "metallicFactor": 1.0,
            "roughnessFactor": 0.0,
        },
    }
    return ga.glb_bytes(gltf, binary)


def test_a_mirror_sphere_reflects_the_probe_along_gltfs_axes(tmp_path):
    got = _render(tmp_path, _mirror_probe_glb())
    assert got["environment"] == "arlight estimate"
    rgba = np.asarray(got["pixels"], np.float64).reshape(SIZE, SIZE, 4)[::-1]  # top row first
    lit = rgba[..., :3].max(axis=-1) > 4
    ys, xs = np.nonzero(lit)
    cx, cy = xs.mean(), ys.mean()
    radius = math.sqrt(lit.sum() / math.pi)

    def seen(nx: float, ny: float) -> np.ndarray:
        """The mean colour about the pixel whose normal is (nx, ny, +z) (glTF's axes; +x to
        the right, +y up, the camera on +z)."""
        x, y = int(round(cx + nx * radius)), int(round(cy - ny * radius))
        return rgba[y - 2 : y + 3, x - 2 : x + 3, :3].reshape(-1, 3).mean(axis=0)

    # a mirror at normal n seen from +z reflects r = 2 (n.z) n - z: the centre +z, the
    # normal 45 degrees right +x, 45 degrees up +y, 45 degrees left -x
    s = math.sin(math.radians(45.0))
    centre, right, top, left = seen(0.0, 0.0), seen(s, 0.0), seen(0.0, s), seen(-s, 0.0)
    assert np.argmax(centre) == 2 and centre[2] > 3 * max(centre[:2]), centre
    assert np.argmax(right) == 0 and right[0] > 3 * max(right[1:]), right
    assert np.argmax(top) == 1 and top[1] > 3 * max(top[0], top[2]), top
    assert left.max() < 0.5 * right[0], left
