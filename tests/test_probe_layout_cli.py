"""`arlight estimate --probe-out DIR --probe-layout ENGINE` (issue 33, item 3): the probe's
faces as three.js or Filament load them, in the frame's camera frame with OpenGL's axes,
equal to `engine_export.probe_faces` of the world-axes faces; a layout without --probe-out
exits 2 naming the flag."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli

from arlight.pipeline import probe_cube, sh
from arlight.pipeline.engine_export import probe_faces
from arlight.pipeline.environment_map import CUBE_FACES
from arlight.sources.exr import read_exr

SMALL = ["--set", "volume_resolution=64", "--set", "aux_resolution=32", "--set", "probe_size=32"]


def _levels(folder, stem: str = "000000") -> list[np.ndarray]:
    info = json.loads((folder / f"{stem}.json").read_text())
    return [
        np.stack([read_exr(folder / f"{stem}_{f}_m{k}.exr") for f in CUBE_FACES])
        for k in range(len(info["levels"]))
    ]


@pytest.mark.parametrize("layout", ["threejs", "filament"])
def test_engine_layouts_are_probe_faces_of_the_world_faces(tmp_path, capsys, layout):
    base = ["estimate", "--max-frames", "1", "--probe-at", "0,0,1.5", "--poses", "groundtruth"]
    world, engine = tmp_path / "world", tmp_path / layout
    code, text = run_cli(base + ["--probe-out", str(world)] + SMALL, capsys)
    assert code == 0, text
    code, text = run_cli(
        base + ["--probe-out", str(engine), "--probe-layout", layout] + SMALL, capsys
    )
    assert code == 0, text
    info = json.loads((engine / "000000.json").read_text())
    assert info["layout"] == layout and layout in info["convention"]
    from arlight.sources.synthetic import make_sequence

    first = make_sequence(num_frames=1).frames[0].pose  # --poses groundtruth: the world's
    got = _levels(engine)
    mips = probe_cube.CubeMips(_levels(world), np.zeros(len(got)))
    want = probe_faces(mips, sh.GL_FROM_CV @ first[:3, :3].T, layout)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, rtol=2e-3, atol=1e-3)  # EXR half floats


def test_a_layout_without_probe_out_exits_2(capsys):
    code, text = run_cli(["estimate", "--max-frames", "1", "--probe-layout", "threejs"], capsys)
    assert code == 2 and "--probe-out" in text and "Traceback" not in text
