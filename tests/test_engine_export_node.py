"""The `webxr` and `main_light` layouts in three.js itself (issue 34, item 4), run in node
where node and the `three` package are installed (scripts/node_test_deps.sh), else skipped
with the reason.

three.js r187 reads XRLightEstimate.sphericalHarmonicsCoefficients with
`LightProbe.sh.fromArray` and the primary light as a `DirectionalLight` whose position,
relative to its target, points towards the light. The test hands it a Result's layouts (a
sun, a sky and a glowing ground, the Result's direction the light above the horizon) and
checks what three.js computes: `SphericalHarmonics3.getIrradianceAt` equals the irradiance
of our SH in the engine's axes (1 %), and the DirectionalLight points within 5 degrees of
the Result's direction, where the whole sphere's moment (the old main light) is 29 off.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from node_support import node_modules_or_skip

from arlight.evaluation import angular_error_deg
from arlight.pipeline import sh
from arlight.pipeline.engine_export import camera_exports

SCRIPT = r"""
import * as THREE from "three";
import fs from "node:fs";
const input = JSON.parse(fs.readFileSync(0, "utf8"));
const probe = new THREE.LightProbe();
probe.sh.fromArray(input.webxr);
const target = new THREE.Vector3();
const irradiance = input.normals.map(([x, y, z]) => {
  probe.sh.getIrradianceAt(new THREE.Vector3(x, y, z), target);
  return [target.x, target.y, target.z];
});
const sun = new THREE.DirectionalLight(0xffffff, 1.0);
sun.position.fromArray(input.main_light.direction);  // as the WebXR samples set it
sun.target.position.set(0, 0, 0);
const towards = sun.position.clone().sub(sun.target.position).normalize();
console.log(JSON.stringify({ irradiance, towards: towards.toArray(), revision: THREE.REVISION }));
"""


def _three_or_skip() -> tuple[str, Path]:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (apt-get install nodejs): three.js conformance")
    modules = node_modules_or_skip("three.js conformance", "three/package.json")
    return node, modules


UP_CV = np.array([0.0, -1.0, 0.0])
SUN_CV = np.array([0.6, -0.5, 0.62]) / np.linalg.norm([0.6, -0.5, 0.62])


def test_threejs_light_probe_and_main_light():
    node, modules = _three_or_skip()
    # a Result: world = a posed camera's, a sun over a sky and a ground glowing below
    light = (
        sh.directional_light(SUN_CV, 3.0, 4)
        + sh.project(lambda d: 0.3 * (d @ UP_CV > 0), 4)
        + sh.project(lambda d: 0.6 * (d @ UP_CV < 0), 4)
    )
    reported = sh.above_horizon_direction(light, UP_CV)
    rgb = np.stack([light, 0.9 * light, 0.8 * light])
    pose = np.eye(4)
    exports = camera_exports(rgb, pose, ["webxr", "main_light"], reported)
    normals = sh.fibonacci_sphere(2000)
    script = modules.parent / f".arlight_three_{os.getpid()}.mjs"  # resolves node_modules
    script.write_text(SCRIPT)
    try:
        run = subprocess.run(
            [node, str(script)],
            input=json.dumps({**exports, "normals": normals.tolist()}),
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        script.unlink()
    assert run.returncode == 0, run.stderr[-3000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    # three.js's own irradiance = ours, in OpenGL axes (bands 0..2)
    ours = (
        sh.sh_basis(normals, 3)
        @ sh.irradiance_from_radiance(sh.rotate(rgb, sh.GL_FROM_CV)[:, :9]).T
    )
    theirs = np.asarray(got["irradiance"])
    np.testing.assert_allclose(theirs, ours, rtol=0.01, atol=0.01 * np.abs(ours).max())
    # the main light three.js builds points at the Result's light
    want = sh.GL_FROM_CV @ reported
    assert angular_error_deg(np.asarray(got["towards"]), want) < 5.0
    assert angular_error_deg(sh.dominant_direction(light), reported) > 20.0  # the old one
