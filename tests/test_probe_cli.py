"""`arlight estimate --probe-out DIR [--probe-at X,Y,Z]`: each frame's reflection probe as
OpenEXR cube maps with their mips (issue 33, item 3), and its bad input exiting 2 with the
flag named."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli

from arlight.pipeline.environment_map import CUBE_FACES
from arlight.sources.exr import read_exr

SMALL = ["--set", "volume_resolution=64", "--set", "aux_resolution=32"]


def test_probe_out_writes_every_face_and_mip_level(tmp_path, capsys):
    out = tmp_path / "probes"
    code, text = run_cli(
        ["estimate", "--max-frames", "2", "--probe-out", str(out), "--probe-at", "0,0,1.5"] + SMALL,
        capsys,
    )
    assert code == 0, text
    assert "wrote 2 reflection probes" in text
    info = json.loads((out / "000001.json").read_text())
    assert info["faces"] == list(CUBE_FACES)
    assert [lv["size"] for lv in info["levels"]] == [64, 32, 16, 8, 4]
    assert info["levels"][0]["roughness"] == 0.0 and info["levels"][-1]["roughness"] == 1.0
    assert info["point_world"] == [0.0, 0.0, 1.5]
    for level, entry in enumerate(info["levels"]):
        for face in CUBE_FACES:
            image = read_exr(out / f"000001_{face}_m{level}.exr")
            assert image.shape == (entry["size"], entry["size"], 3)
            assert np.all(np.isfinite(image)) and image.min() >= 0.0
    # the synthetic scene lies in front of the first camera (+z): the probe sees it there
    assert info["diagnostics"]["hit_fraction"] > 0.0


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["--probe-out", "{d}", "--probe-at", "1,2"], "--probe-at"),
        (["--probe-out", "{d}", "--probe-at", "1,2,x"], "--probe-at"),
        (["--probe-out", "{d}"], "--probe-at X,Y,Z or a --scene"),
        (["--probe-out", "{d}", "--probe-at", "0,0,1", "--set", "probe_size=48"], "probe_size"),
        (["--probe-out", "{d}", "--probe-at", "0,0,1", "--set", "probe_size=512"], "probe_size"),
        (["--probe-out", "{d}", "--probe-at", "0,0,1", "--set", "probe=false"], "probe=false"),
    ],
)
def test_bad_probe_input_exits_2_naming_the_flag(tmp_path, capsys, argv, named):
    code, text = run_cli(
        ["estimate", "--max-frames", "1"] + [a.format(d=tmp_path / "p") for a in argv], capsys
    )
    assert code == 2, text
    assert named in text
    assert "Traceback" not in text
