"""The reflection probe's cube map in the engines' own conventions (issue 33, item 3):
`engine_export.probe_faces` for Filament / ARCore (OpenGL's cube-map table in the engine's
axes) and three.js (`CubeTexture`, read with x mirrored), each checked with that engine's
lookup: a red wall on the probe's +x lands where the engine looks along its +x. three.js
itself renders the faces in headless Chromium when it is there (skipped, saying why, else).
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

from arlight.pipeline import probe_cube, sh
from arlight.pipeline.engine_export import ExportError, probe_faces

SIZE = 32


def _probe(radiance_of) -> probe_cube.CubeMips:
    """A probe (world axes) whose level k holds radiance_of(directions) at its texels."""
    levels = [
        radiance_of(probe_cube.texel_directions(SIZE >> k)).astype(np.float32)
        for k in range(probe_cube.num_levels(SIZE))
    ]
    return probe_cube.CubeMips(levels, probe_cube.level_roughness(len(levels)))


def _red_wall(d: np.ndarray) -> np.ndarray:
    """Red where a direction points within 45 degrees of world +x, grey elsewhere."""
    wall = (d[..., 0] > math.cos(math.radians(45.0)))[..., None]
    return np.where(wall, [1.0, 0.0, 0.0], [0.2, 0.2, 0.2])


def _smooth(d: np.ndarray) -> np.ndarray:
    """A field with no symmetry: every direction its own colour."""
    return np.stack([1.0 + d[..., 0], 1.0 + 0.5 * d[..., 1], 1.5 + d[..., 2] * d[..., 0]], -1)


# Each engine's lookup of a direction d (its own axes) in the faces it was given, as its
# shader reads them: OpenGL's table (probe_cube.sample_numpy) at Filament's direction as it
# is (skybox.mat: texture(skybox, eyeDirection)) and at three.js's (flipEnvMap * x, y, z),
# flipEnvMap = -1 for a CubeTexture (WebGLBackground, envmap_fragment).
ENGINE_LOOKUP = {
    "filament": np.diag([1.0, 1.0, 1.0]),
    "arcore": np.diag([1.0, 1.0, 1.0]),
    "threejs": np.diag([-1.0, 1.0, 1.0]),
}


def _engine_reads(faces: list[np.ndarray], engine: str, d_engine: np.ndarray) -> np.ndarray:
    cube = probe_cube.CubeMips(faces[:1], np.zeros(1))
    return probe_cube.sample_numpy(cube, np.asarray(d_engine, float) @ ENGINE_LOOKUP[engine].T)


class TestFaces:
    @pytest.mark.parametrize("engine, slot", [("filament", 0), ("arcore", 0), ("threejs", 1)])
    def test_a_red_wall_on_plus_x_is_where_the_engine_looks_along_plus_x(self, engine, slot):
        """World = engine axes: Filament / ARCore keep it in their +X face; three.js needs it
        in the `nx` image, which its mirrored lookup reads along +x."""
        faces = probe_faces(_probe(_red_wall), None, engine)
        assert _engine_reads(faces, engine, np.array([[1.0, 0.0, 0.0]])).tolist() == [
            [1.0, 0.0, 0.0]
        ]
        assert _engine_reads(faces, engine, np.array([[-1.0, 0.0, 0.0]]))[0, 0] == pytest.approx(
            0.2
        )
        red = faces[0][..., 0] > 0.5 + faces[0][..., 1]
        # the wall's 45-degree cone covers the face but its corners (54.7 degrees out)
        assert red[slot].mean() > 0.75 and red[slot ^ 1].mean() == 0.0
        assert red[slot, SIZE // 2, SIZE // 2] and red.sum() == red[slot].sum()

    @pytest.mark.parametrize("engine", ["filament", "threejs"])
    def test_a_posed_camera_frame_with_opengl_axes(self, engine):
        """The layouts' frame (camera frame, OpenGL axes: GL_FROM_CV R^T): every direction
        the engine looks along reads the probe's radiance along the same direction in the
        world, at every level (bilinear, so within the field's change over a texel)."""
        angle = math.radians(35.0)
        c, s = math.cos(angle), math.sin(angle)
        rotation = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ np.array(
            [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
        )
        engine_from_world = sh.GL_FROM_CV @ rotation.T
        probe = _probe(_smooth)
        faces = probe_faces(probe, engine_from_world, engine)
        assert [f.shape for f in faces] == [lv.shape for lv in probe.levels]
        d_engine = sh.fibonacci_sphere(400)
        want = _smooth(d_engine @ engine_from_world)  # world = R_e^T d
        got = _engine_reads(faces, engine, d_engine)
        assert np.abs(got - want).max() < 0.1
        # a mirror image would be far off
        wrong = _engine_reads(faces, "threejs" if engine == "filament" else "filament", d_engine)
        assert np.abs(wrong - want).max() > 0.5

    def test_an_axis_aligned_change_moves_texels_exactly(self):
        probe = _probe(_smooth)
        faces = probe_faces(probe, np.diag([1.0, -1.0, -1.0]), "filament")
        # engine +Y (world -y) is world's -Y face turned: every texel a texel of the probe
        for level, src in zip(faces, probe.levels, strict=True):
            assert np.isin(level[2], src[3]).all()

    def test_refusals(self):
        with pytest.raises(ExportError, match="unity"):
            probe_faces(_probe(_smooth), None, "unity")
        with pytest.raises(ExportError, match="orthogonal"):
            probe_faces(_probe(_smooth), np.eye(3) * 2.0, "filament")


# ------------------------------------------------------------------ three.js itself, rendered

PAGE = """<!doctype html><html><body style="margin:0">
<pre id="out">pending</pre>
<script type="importmap">{"imports": {"three": "./three.module.js"}}</script>
<script type="module">
import * as THREE from "three";
const out = document.getElementById("out");
try {
  const input = await (await fetch("faces.json")).json();
  const renderer = new THREE.WebGLRenderer({ preserveDrawingBuffer: true });
  renderer.setSize(%(px)d, %(px)d);
  renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
  renderer.toneMapping = THREE.NoToneMapping;
  document.body.appendChild(renderer.domElement);
  const n = input.size;
  const images = input.faces.map((rgb) => {  // px, nx, py, ny, pz, nz; first row the top
    const data = new Uint8Array(n * n * 4);
    for (let i = 0; i < n * n; i++) {
      data.set([rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2], 255], 4 * i);
    }
    const t = new THREE.DataTexture(data, n, n);
    return t;
  });
  const cube = new THREE.CubeTexture(images);
  cube.colorSpace = THREE.NoColorSpace;
  cube.generateMipmaps = false;
  cube.minFilter = THREE.NearestFilter;
  cube.magFilter = THREE.NearestFilter;
  cube.needsUpdate = true;
  const scene = new THREE.Scene();
  const camera = new THREE.PerspectiveCamera(2, 1, 0.1, 10);
  const gl = renderer.getContext();
  const read = () => {
    const px = new Uint8Array(4);
    gl.readPixels(%(half)d, %(half)d, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    return Array.from(px.slice(0, 3));
  };
  const look = (d) => {
    camera.position.set(0, 0, 0);
    camera.up.set(0, 1, 0);
    if (Math.abs(d[1]) > 0.99 * Math.hypot(...d)) camera.up.set(0, 0, 1);
    camera.lookAt(d[0], d[1], d[2]);
    camera.updateMatrixWorld();
    renderer.render(scene, camera);
    return read();
  };
  scene.background = cube;
  const background = input.directions.map(look);
  const pmrem = new THREE.PMREMGenerator(renderer);
  scene.background = pmrem.fromCubemap(cube).texture;
  const prefiltered = input.directions.map(look);
  out.textContent = JSON.stringify({ background, prefiltered, revision: THREE.REVISION });
} catch (e) { out.textContent = "error " + e + " " + e.stack; }
</script></body></html>
"""
CANVAS_PX = 8


def _serve(folder: Path) -> tuple[http.server.ThreadingHTTPServer, str]:
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, format: str, *args) -> None:  # noqa: A002 - the base's name
            pass

    handler = functools.partial(Quiet, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}/page.html"


def test_threejs_shows_each_direction_what_the_probe_holds(tmp_path):
    """three.js r187 in headless Chromium: the faces `probe_faces(..., "threejs")` as a
    `CubeTexture` background, and through `PMREMGenerator.fromCubemap`, show along each
    engine direction the probe's colour for that direction: the six axes and four oblique
    directions (which pin the faces' orientation, not just their order)."""
    executable = chromium_or_skip()
    modules = node_modules_or_skip(
        "three.js cube-map render", "three/build/three.module.js", "three/build/three.core.js"
    )
    site = tmp_path / "site"
    site.mkdir()
    for name in ("three.module.js", "three.core.js"):
        shutil.copy(modules / "three" / "build" / name, site)

    def colour(d: np.ndarray) -> np.ndarray:  # engine axes = world axes here
        return np.clip(0.5 + 0.5 * d / np.linalg.norm(d, axis=-1, keepdims=True), 0.0, 1.0)

    probe = _probe(colour)
    faces = probe_faces(probe, None, "threejs")[0]
    directions = np.array(
        [
            [1, 0, 0],
            [-1, 0, 0],
            [0, 1, 0],
            [0, -1, 0],
            [0, 0, 1],
            [0, 0, -1],
            [0.8, 0.5, 0.3],
            [-0.3, 0.4, 0.85],
            [0.2, -0.9, -0.35],
            [-0.7, -0.2, -0.6],
        ],
        float,
    )
    payload = {
        "size": SIZE,
        "faces": [np.round(f * 255).astype(int).reshape(-1).tolist() for f in faces],
        "directions": directions.tolist(),
    }
    (site / "faces.json").write_text(json.dumps(payload))
    (site / "page.html").write_text(PAGE % {"px": CANVAS_PX, "half": CANVAS_PX // 2})
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
    got = json.loads(text.replace("&quot;", '"'))
    want = colour(directions) * 255.0
    background = np.asarray(got["background"], float)
    assert np.abs(background - want).max() < 8.0, (background, want)
    # PMREM's sharpest level is blurred a little and stored in half floats
    prefiltered = np.asarray(got["prefiltered"], float)
    assert np.abs(prefiltered - want).max() < 20.0, (prefiltered, want)
    # the OpenGL faces as they are (no mirror) would show +x's colour at -x
    plain = probe_faces(probe, None, "filament")[0]
    assert not np.allclose(plain, faces)
