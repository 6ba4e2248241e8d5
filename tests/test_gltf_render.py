"""The .glb rendered by Babylon.js in headless Chromium (WebGL on SwiftShader): the white
sphere it carries, lit by nothing but the file's EXT_lights_image_based light, is brightest
towards arlight's light and as bright there as arlight's irradiance says (issue 34 item 1).

Skipped, saying why, without Chromium or without Babylon's browser builds (`babylonjs`,
`babylonjs-loaders`: scripts/node_test_deps.sh, or $ARLIGHT_NODE_MODULES).
"""

from __future__ import annotations

import functools
import http.server
import json
import math
import shutil
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
from browser_support import chromium_or_skip
from node_support import node_modules_or_skip

from arlight.pipeline import gltf_asset as ga
from arlight.pipeline import sh

LIGHT_GL = np.array([0.3, 0.6, 0.74]) / np.linalg.norm([0.3, 0.6, 0.74])  # seen from +z
SIZE = 256  # canvas pixels

PAGE = """<!doctype html><html><body style="margin:0;background:#000">
<canvas id="c" width="%(size)d" height="%(size)d"></canvas><pre id="out">pending</pre>
<script src="babylon.js"></script><script src="babylonjs.loaders.min.js"></script>
<script>
// Babylon's default scene (left-handed; %(handed)s), a nearly orthographic camera on the
// asset's front (+z in glTF's axes) looking at the sphere: glTF's +x to the right, +y up
const out = document.getElementById("out");
try {
  const engine = new BABYLON.Engine(document.getElementById("c"), false,
                                    { preserveDrawingBuffer: true });
  const scene = new BABYLON.Scene(engine);
  scene.useRightHandedSystem = %(right_handed)s;
  scene.clearColor = new BABYLON.Color4(0, 0, 0, 1);
  const camera = new BABYLON.FreeCamera("cam", new BABYLON.Vector3(0, 0, 40), scene);
  camera.setTarget(BABYLON.Vector3.Zero());
  camera.fov = 2 * Math.atan(1.1 / 40);
  BABYLON.SceneLoader.AppendAsync("", "light.glb", scene).then(() => {
    scene.executeWhenReady(async () => {
      scene.render(); scene.render();
      const px = await engine.readPixels(0, 0, %(size)d, %(size)d);
      out.textContent = JSON.stringify({
        environment: scene.environmentTexture ? scene.environmentTexture.name : null,
        lights: scene.lights.length,
        pixels: Array.from(px),
      });
    });
  }).catch((e) => { out.textContent = "error " + e; });
} catch (e) { out.textContent = "error " + e; }
</script></body></html>
"""


def _serve(folder: Path) -> tuple[http.server.ThreadingHTTPServer, str]:
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, format: str, *args) -> None:  # noqa: A002 - the base's name
            pass

    handler = functools.partial(Quiet, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}/page.html"


def _render(tmp_path: Path, glb: bytes, right_handed: bool = False) -> dict:
    executable = chromium_or_skip()
    modules = node_modules_or_skip(
        "Babylon.js render test",
        "babylonjs/babylon.js",
        "babylonjs-loaders/babylonjs.loaders.min.js",
    )
    site = tmp_path / "site"
    site.mkdir()
    shutil.copy(modules / "babylonjs" / "babylon.js", site)
    shutil.copy(modules / "babylonjs-loaders" / "babylonjs.loaders.min.js", site)
    (site / "light.glb").write_bytes(glb)
    handed = "useRightHandedSystem" if right_handed else "as the Sandbox loads glTF"
    page = PAGE % {"size": SIZE, "right_handed": str(right_handed).lower(), "handed": handed}
    (site / "page.html").write_text(page)
    server, url = _serve(site)
    try:
        run = subprocess.run(
            [
                executable,
                "--headless=new",
                "--no-sandbox",
                "--enable-unsafe-swiftshader",
                "--use-angle=swiftshader",
                f"--user-data-dir={tmp_path / 'profile'}",
                "--virtual-time-budget=30000",
                "--dump-dom",
                url,
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        server.shutdown()
    text = run.stdout.split('<pre id="out">', 1)[-1].split("</pre>", 1)[0]
    if not text.startswith("{"):
        pytest.fail(f"the page said {text[:500]!r}; chromium: {run.stderr[-2000:]}")
    return json.loads(text.replace("&quot;", '"'))


def _shading(got: dict) -> tuple[np.ndarray, np.ndarray]:
    """(normals (N, 3) in glTF's axes, linear values (N,)) of the sphere's pixels within
    0.77 of its radius (off the rim, where Fresnel brightens the specular)."""
    rgba = np.asarray(got["pixels"], np.float64).reshape(SIZE, SIZE, 4)[::-1]  # top row first
    grey = rgba[..., :3].mean(axis=-1)
    on_sphere = grey > 8
    ys, xs = np.nonzero(on_sphere)
    cx, cy = xs.mean(), ys.mean()
    radius = math.sqrt(on_sphere.sum() / math.pi)
    nx, ny = (xs - cx) / radius, -(ys - cy) / radius
    inner = nx**2 + ny**2 < 0.6
    nz = np.sqrt(np.clip(1.0 - nx**2 - ny**2, 0.0, 1.0))
    normals = np.stack([nx, ny, nz], axis=1)[inner]
    return normals, (grey[ys, xs][inner] / 255.0) ** 2.2  # Babylon's gamma 2.2 output


def _light() -> np.ndarray:
    """A sun towards LIGHT_GL (glTF's axes) over a uniform sky of radiance 0.1."""
    sun = sh.directional_light(LIGHT_GL, 0.6, 4)
    sun[0] += 0.1 * 2.0 * math.sqrt(math.pi)
    return sun


def _lambert(normals: np.ndarray, light: np.ndarray) -> np.ndarray:
    """E(n) / pi of the light's bands 0..2: a white Lambertian surface, as Babylon shades."""
    return sh.sh_basis(normals, 3) @ sh.irradiance_from_radiance(light)[:9] / math.pi


def test_babylon_renders_the_sphere_lit_as_arlight_says(tmp_path):
    """Babylon's default scene: pixel by pixel the sphere is E(n) / pi of arlight's light
    (its loader's convertIrradianceToLambertianRadiance; plus a little specular, F0 0.04),
    brightest towards the light."""
    got = _render(tmp_path, ga.glb_bytes(*ga.light_asset(_light())))
    assert got["environment"] == "arlight estimate" and got["lights"] == 0
    normals, shade = _shading(got)
    want = _lambert(normals, _light())
    assert np.corrcoef(shade, want)[0, 1] > 0.98
    assert np.median(shade / want) == pytest.approx(1.0, abs=0.15)
    brightest = normals[int(np.argmax(shade))]
    error = math.degrees(math.acos(float(np.clip(brightest @ LIGHT_GL, -1.0, 1.0))))
    assert error < 10.0, (brightest, error)


def test_a_right_handed_babylon_scene_turns_the_light(tmp_path):
    """What decision 0040 records: with `useRightHandedSystem` Babylon reads the same file's
    light turned 180 degrees about +y (it flips the environment's z, and no root node turns
    the asset); in glTF's own axes (no mirror) the default scene showed it mirrored in x."""
    got = _render(tmp_path, ga.glb_bytes(*ga.light_asset(_light())), right_handed=True)
    normals, shade = _shading(got)
    turned = np.diag([-1.0, 1.0, -1.0])
    assert np.corrcoef(shade, _lambert(normals @ turned, _light()))[0, 1] > 0.98
    assert np.corrcoef(shade, _lambert(normals, _light()))[0, 1] < 0.5
