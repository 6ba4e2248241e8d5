"""The reflection probe's files on the command line (issue 33, item 3): `--probe-out DIR`
writes a probe as OpenEXR cube faces, every level, and a JSON beside them (`arlight
estimate`, from the pipeline's probe; `arlight stream`, from each Result's), and
`probe_record` says in a `--out` line what came and where it went, without the texels."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from arlight.protocols.probe import probe_summary

PROBE_LAYOUTS = ("world", "filament", "threejs")

PROBE_LAYOUT_HELP = (
    "the --probe-out faces' frame and convention: 'world' (default) the session's "
    "world axes, OpenGL's cube-map orientation; 'filament' (also ARCore, OpenGL) and "
    "'threejs' (CubeTexture / PMREMGenerator, which read cube maps mirrored in x) the "
    "frame's camera frame with OpenGL's axes, as --export and --gltf "
    "(pipeline/engine_export.py probe_faces)"
)

FACES_PATTERN = "_<face>_m<level>.exr"  # after the stem: NNNNNN_px_m0.exr ...


def write_probe_files(
    stem: str | Path,
    cube: Any,
    point_world: Sequence[float],
    layout: str = "world",
    pose: Any = None,
    diagnostics: dict | None = None,
) -> None:
    """STEM_<face>_m<level>.exr for every face and level of a probe and STEM.json: the
    point (world, metres), each level's size (texels a face) and perceptual roughness
    (GGX, alpha = roughness^2), the faces' order, frame and convention, the diagnostics.

    cube: its `levels`, (6, n_k, n_k, 3) linear radiance, faces +X, -X, +Y, -Y, +Z, -Z in
    world axes, OpenGL's cube-map orientation, and `roughness` per level (the pipeline's
    CubeMips or a Result's ProbeCube); point_world: (3,) metres;
    layout: "world" (those faces as they are) or an engine of engine_export.probe_faces
    ("filament", "threejs") in the camera frame of `pose` (4 x 4 camera-to-world) with
    OpenGL's axes. Faces are half-float OpenEXR (sources/exr.py)."""
    from arlight.pipeline import sh
    from arlight.pipeline.environment_map import CUBE_FACES
    from arlight.sources.exr import write_exr

    if layout == "world":
        faces_per_level = [np.asarray(lv, np.float32) for lv in cube.levels]
        convention = (
            "OpenGL cube map (table 8.19), world axes of the session, linear radiance in the "
            "camera's linear image units"
        )
    else:
        from arlight.pipeline.engine_export import probe_faces

        engine_from_world = sh.GL_FROM_CV @ np.asarray(pose, np.float64)[:3, :3].T
        faces_per_level = probe_faces(cube, engine_from_world, layout)
        convention = (
            f"{layout}: the faces as {layout} loads them (pipeline/engine_export.py "
            "probe_faces), this frame's camera frame with OpenGL's axes (x right, y up, z "
            "back), linear radiance in the camera's linear image units"
        )
    for level, faces in enumerate(faces_per_level):
        for face, image in zip(CUBE_FACES, faces, strict=True):
            write_exr(f"{stem}_{face}_m{level}.exr", image)
    info = {
        "point_world": [float(x) for x in point_world],
        "faces": list(CUBE_FACES),
        "layout": layout,
        "convention": convention,
        "levels": [
            {"size": int(np.shape(lv)[1]), "roughness": float(r)}
            for lv, r in zip(cube.levels, cube.roughness, strict=True)
        ],
        "diagnostics": diagnostics or {},
    }
    Path(f"{stem}.json").write_text(json.dumps(info, indent=1))


def probe_record(probe, stem: str | Path | None, layout: str = "world") -> dict | None:
    """A `--out` line's `probe`: None when the Result carried none, else its size (texels a
    face of level 0), levels, roughness per level, point (world, metres) and, when
    --probe-out wrote it, `files` (the JSON and the faces' name pattern) and their layout;
    never the texels."""
    summary = probe_summary(probe)
    if summary is None:
        return None
    return {
        **summary,
        "files": None
        if stem is None
        else {"json": f"{stem}.json", "faces": f"{stem}{FACES_PATTERN}", "layout": layout},
    }
