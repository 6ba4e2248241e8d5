"""The light as a .glb (pipeline/gltf_asset.py, issue 34 item 1): complete per
EXT_lights_image_based's schema, images that decode to the light, and, where node and
Babylon.js are installed, Babylon's own glTF loader reading it.

The schema rules checked (KhronosGroup/glTF extensions/2.0/Vendor/EXT_lights_image_based/
schema): light.schema.json requires irradianceCoefficients (9 arrays of 3 numbers),
specularImages (>= 1 arrays of exactly 6 integer image indices >= 0) and specularImageSize
(a number >= 0); rotation is 4 numbers in [0, 1]; intensity a number; no keys but name,
rotation, intensity, irradianceCoefficients, specularImages, specularImageSize, extensions,
extras. glTF.EXT_lights_image_based: only "lights". scene.EXT_lights_image_based: "light"
required, nothing else. README: square power-of-two faces, each mip half the one before,
4-channel PNGs hold RGBD.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
from node_support import node_modules_or_skip

from arlight.pipeline import engine_export as ee
from arlight.pipeline import gltf_asset as ga
from arlight.pipeline import probe_cube, sh
from arlight.pipeline.environment_map import CUBE_FACES, cube_face_directions

LIGHT_GL = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])
LIGHT_KEYS = {
    "name",
    "rotation",
    "intensity",
    "irradianceCoefficients",
    "specularImages",
    "specularImageSize",
    "extensions",
    "extras",
}


def _light_rgb() -> np.ndarray:
    """(3, 16) radiance SH: a sun towards LIGHT_GL over a uniform sky, warm."""
    c = sh.directional_light(LIGHT_GL, 3.0, 4)
    c[0] += 0.5 * 2.0 * np.sqrt(np.pi)  # + uniform 0.5
    return np.stack([c, 0.9 * c, 0.8 * c])


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def check_ibl_schema(gltf: dict, binary: bytes) -> dict:
    """The schema's rules (module text) and the README's on the images; the light."""
    assert "EXT_lights_image_based" in gltf["extensionsUsed"]
    root = gltf["extensions"]["EXT_lights_image_based"]
    assert set(root) <= {"lights"}
    scene = gltf["scenes"][gltf["scene"]]["extensions"]["EXT_lights_image_based"]
    assert set(scene) == {"light"}
    light = root["lights"][scene["light"]]
    assert set(light) <= LIGHT_KEYS
    for key in ("irradianceCoefficients", "specularImages", "specularImageSize"):
        assert key in light, f"required {key} missing"
    coeffs = light["irradianceCoefficients"]
    assert len(coeffs) == 9 and all(len(r) == 3 and all(map(_is_number, r)) for r in coeffs)
    rotation = light.get("rotation", [0, 0, 0, 1])
    assert len(rotation) == 4 and all(_is_number(x) and 0.0 <= x <= 1.0 for x in rotation)
    assert _is_number(light.get("intensity", 1.0))
    size = light["specularImageSize"]
    assert _is_number(size) and size >= 0
    mips = light["specularImages"]
    assert len(mips) >= 1
    for k, faces in enumerate(mips):
        assert len(faces) == 6
        for index in faces:
            assert isinstance(index, int) and 0 <= index < len(gltf["images"])
            rgba = _image(gltf, binary, index)
            assert rgba.shape == (size >> k, size >> k, 4), (k, rgba.shape)
    assert size & (size - 1) == 0
    return light


def _image(gltf: dict, binary: bytes, index: int) -> np.ndarray:
    """Image `index` as (n, n, 4) uint8 RGBA."""
    image = gltf["images"][index]
    assert image["mimeType"] == "image/png"
    view = gltf["bufferViews"][image["bufferView"]]
    start = view.get("byteOffset", 0)
    png = np.frombuffer(binary[start : start + view["byteLength"]], np.uint8)
    bgra = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)
    assert bgra is not None and bgra.ndim == 3 and bgra.shape[2] == 4, "not an RGBA PNG"
    return cv2.cvtColor(bgra, cv2.COLOR_BGRA2RGBA)


class TestAsset:
    def test_complete_per_the_schema_and_a_valid_glb(self, tmp_path):
        path = ga.write_glb(tmp_path / "light.glb", _light_rgb(), with_main_light=True)
        gltf, binary = ga.read_glb(path.read_bytes())
        light = check_ibl_schema(gltf, binary)
        assert light["specularImageSize"] == ga.SPECULAR_SIZE
        assert len(light["specularImages"]) == probe_cube.num_levels(ga.SPECULAR_SIZE)
        assert gltf["buffers"][0]["byteLength"] == len(binary)
        for view in gltf["bufferViews"]:
            assert view["byteOffset"] % 4 == 0
            assert view["byteOffset"] + view["byteLength"] <= len(binary)
        np.testing.assert_allclose(  # the Result's layout in the file's axes
            light["irradianceCoefficients"],
            ee.to_gltf_ibl(_light_rgb(), ga.FILE_FROM_GLTF)["irradianceCoefficients"],
        )

    def test_the_old_light_fails_the_schema(self):
        """The Result's `gltf` layout alone (what arlight wrote before): not loadable."""
        gltf, binary = ga.light_asset(_light_rgb())
        del gltf["extensions"]["EXT_lights_image_based"]["lights"][0]["specularImages"]
        with pytest.raises(AssertionError, match="specularImages"):
            check_ibl_schema(gltf, binary)

    def test_mip0_decodes_to_the_radiance(self):
        c = _light_rgb()
        gltf, binary = ga.light_asset(c)
        light = check_ibl_schema(gltf, binary)
        for face, index in zip(CUBE_FACES, light["specularImages"][0], strict=True):
            got = ga.rgbd_decode(_image(gltf, binary, index))
            d_gltf = cube_face_directions(face, 64) @ ga.FILE_FROM_GLTF  # file -> glTF axes
            want = np.maximum(sh.sh_basis(d_gltf, 4) @ c.T, 0.0)
            # RGBD keeps 8 bits of (v D)^(1/2.2): about 1 % of the texel's peak channel
            np.testing.assert_allclose(got, want, rtol=0.03, atol=0.02 * want.max())

    def test_rough_mips_peak_towards_the_light(self):
        gltf, binary = ga.light_asset(_light_rgb())
        light = check_ibl_schema(gltf, binary)
        last = light["specularImages"][-1]
        n = light["specularImageSize"] >> (len(light["specularImages"]) - 1)
        dirs = np.concatenate([cube_face_directions(f, n).reshape(-1, 3) for f in CUBE_FACES])
        values = np.concatenate(
            [ga.rgbd_decode(_image(gltf, binary, i)).reshape(-1, 3) for i in last]
        )
        brightest = dirs[int(np.argmax(values[:, 1]))]  # the file's axes
        assert brightest @ (ga.FILE_FROM_GLTF @ LIGHT_GL) > np.cos(np.radians(30.0))  # coarse

    def test_rgbd_round_trip(self):
        v = np.array([[0.0, 0.0, 0.0], [0.01, 0.5, 1.0], [3.0, 20.0, 200.0]])
        back = ga.rgbd_decode(ga.rgbd_encode(v))
        np.testing.assert_allclose(back, v, rtol=0.03, atol=2e-3)

    @pytest.mark.parametrize(
        "axis, bright_face, dark_face",
        [(1, 3, 2), (0, 1, 0)],  # world +y (OpenCV down) -> glTF -y -> file -Y face;
        # world +x -> glTF +x -> file -X face (FILE_FROM_GLTF mirrors x)
    )
    def test_from_a_probe_resampled_into_the_file_axes(self, axis, bright_face, dark_face):
        """A probe's cube (world axes) lands in the file's axes, level by level."""
        size = 32
        levels = []
        for k in range(probe_cube.num_levels(size)):
            d = probe_cube.texel_directions(size >> k)
            levels.append(
                (np.maximum(d[..., axis : axis + 1], 0.0) * np.ones(3)).astype(np.float32)
            )
        probe = probe_cube.CubeMips(levels, probe_cube.level_roughness(len(levels)))
        gltf, binary = ga.light_asset(_light_rgb(), sh.GL_FROM_CV, probe=probe)
        light = check_ibl_schema(gltf, binary)
        assert light["specularImageSize"] == size
        faces = light["specularImages"][0]
        bright = ga.rgbd_decode(_image(gltf, binary, faces[bright_face]))
        dark = ga.rgbd_decode(_image(gltf, binary, faces[dark_face]))
        assert bright.mean() > 0.5 and dark.max() < 0.05

    def test_main_light_node_points_along_the_results_direction(self):
        d_world = np.array([0.0, -0.6, 0.8])  # OpenCV world: up and ahead
        gltf, _ = ga.light_asset(
            _light_rgb(), sh.GL_FROM_CV, direction_world=d_world, with_main_light=True
        )
        node = gltf["nodes"][1]
        x, y, z, w = node["rotation"]
        # +z of the node turned by the quaternion: the light comes from there
        z_axis = np.array([2 * (x * z + y * w), 2 * (y * z - x * w), 1 - 2 * (x * x + y * y)])
        np.testing.assert_allclose(z_axis, sh.GL_FROM_CV @ d_world, atol=1e-9)
        assert gltf["extensions"]["KHR_lights_punctual"]["lights"][0]["type"] == "directional"


# --------------------------------------------------------------------------- Babylon.js

BABYLON_SCRIPT = r"""
// Babylon.js's own glTF loader on the .glb under a NullEngine: the EXT_lights_image_based
// light is parsed (its specular images read and the irradiance SH turned into Babylon's
// spherical polynomial); print what the scene got.
const path = process.argv[2];
const fs = require("fs");
globalThis.XMLHttpRequest = globalThis.XMLHttpRequest || undefined;
(async () => {
  const core = await import("@babylonjs/core");
  await import("@babylonjs/loaders/glTF/2.0/index.js");
  const engine = new core.NullEngine();
  // a NullEngine has no WebGL context to make a raw cube texture in: an empty one stands in
  // (the loader's own code runs; only the GPU upload is left out)
  engine.createRawCubeTexture = function (data, size, format, type) {
    const t = new core.InternalTexture(this, core.InternalTextureSource.CubeRaw);
    t.isCube = true;
    t.width = t.height = t.baseWidth = t.baseHeight = size;
    t.format = format;
    t.type = type;
    t.isReady = true;
    return t;
  };
  const scene = new core.Scene(engine);
  const data = new Uint8Array(fs.readFileSync(path));
  let error = null;
  const seen = {};
  core.RawCubeTexture.prototype.updateRGBDAsync = function (imageData, polynomial, lodScale) {
    seen.mips = imageData.length;
    seen.faces = imageData.map((m) => m.length);
    seen.bytes = imageData.map((m) => m.map((f) => f.byteLength));
    seen.lodScale = lodScale;
    this.sphericalPolynomial = polynomial;
    return Promise.resolve(this);
  };
  try {
    await core.SceneLoader.AppendAsync("", data, scene, undefined, ".glb");
  } catch (e) {
    error = String(e && e.stack ? e.stack : e);
  }
  const env = scene.environmentTexture;
  const poly = env && env.sphericalPolynomial;
  const out = {
    error,
    meshes: scene.meshes.map((m) => m.name),
    environment: env ? env.name : null,
    size: env ? env.getSize().width : null,
    seen,
    harmonics: poly ? ["l00", "l1_1", "l10", "l11", "l2_2", "l2_1", "l20", "l21", "l22"].map(
      (k) => [poly.preScaledHarmonics[k].x, poly.preScaledHarmonics[k].y,
              poly.preScaledHarmonics[k].z]) : null,
  };
  console.log(JSON.stringify(out));
  engine.dispose();
})();
"""


def _babylon_or_skip() -> tuple[str, Path]:
    """node and the node_modules holding @babylonjs/core and @babylonjs/loaders, or skip."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (apt-get install nodejs): Babylon.js loader test")
    modules = node_modules_or_skip(
        "Babylon.js loader test", "@babylonjs/core/package.json", "@babylonjs/loaders/package.json"
    )
    return node, modules


def _babylon_load(node: str, modules: Path, path: Path) -> dict:
    script = modules.parent / f".arlight_babylon_{os.getpid()}.cjs"  # resolves node_modules
    script.write_text(BABYLON_SCRIPT)
    try:
        run = subprocess.run(
            [node, str(script), str(path)], capture_output=True, text=True, timeout=120
        )
    finally:
        script.unlink()
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("{")]
    assert run.returncode == 0 and lines, run.stdout[-2000:] + run.stderr[-3000:]
    return json.loads(lines[-1])


def test_babylon_loads_it(tmp_path):
    node, modules = _babylon_or_skip()
    gltf, binary = ga.light_asset(_light_rgb())
    del gltf["extensions"]["EXT_lights_image_based"]["lights"][0]["specularImages"]
    (tmp_path / "old.glb").write_bytes(ga.glb_bytes(gltf, binary))
    old = _babylon_load(node, modules, tmp_path / "old.glb")  # the TypeError
    assert old["error"] is not None and "length" in old["error"], old
    got = _babylon_load(node, modules, ga.write_glb(tmp_path / "light.glb", _light_rgb()))
    assert got["error"] is None, got["error"]
    assert "sphere" in " ".join(got["meshes"])
    assert got["environment"] == "arlight estimate" and got["size"] == ga.SPECULAR_SIZE
    assert got["seen"]["mips"] == probe_cube.num_levels(ga.SPECULAR_SIZE)
    assert got["seen"]["faces"] == [6] * got["seen"]["mips"]
    # Babylon's pre-scaled harmonics evaluate E(n) / pi directly (its shader's
    # computeEnvironmentIrradiance) in its default scene's world, where the glTF root node
    # put the asset at (-x, y, z): brightest towards the light there
    h = np.asarray(got["harmonics"])  # (9, 3), Babylon's basis with the CS phase
    normals = sh.fibonacci_sphere(4000)
    x, y, z = normals.T
    basis = np.stack(
        [np.ones_like(x), y, z, x, x * y, y * z, 3 * z * z - 1, x * z, x * x - y * y], 1
    )
    e = basis @ h[:, 1]
    assert normals[int(np.argmax(e))] @ (ga.FILE_FROM_GLTF @ LIGHT_GL) > np.cos(np.radians(5))


def test_estimate_writes_a_glb_per_frame(tmp_path, capsys):
    from conftest import run_cli

    code, text = run_cli(
        [
            "--open3d-threads",
            "1",
            "estimate",
            "synthetic",
            "--max-frames",
            "1",
            "--preset",
            "fast",
            "--gltf",
            str(tmp_path / "gltf"),
        ],
        capsys,
    )
    assert code == 0, text
    gltf, binary = ga.read_glb((tmp_path / "gltf" / "000000.glb").read_bytes())
    check_ibl_schema(gltf, binary)
