"""Compile the Numba kernels once, at set-up, so that no user's first frame waits for it.

`python -m arlight.warmup` (run by scripts/bootstrap.sh after installing) pushes two small
frames of the built-in scene, with the demo's virtual objects, through the pipeline with
every preset and through the depth codecs, and the 360 path's mirror / glossy / diffuse
lookups (`pipeline/glossy.py`) over a small map. Numba writes what it compiles to its on-disk
cache (`cache=True` on every kernel: `__pycache__/*.nbi`, `*.nbc` beside the sources), which
later processes load in milliseconds.
The image size does not matter to the cache: kernels are compiled per argument type.
"""

from __future__ import annotations

import sys
import time

WARMUP_SIZE = (64, 48)  # pixels; small, so the frames themselves cost nothing


def warm_up() -> float:
    """Compile (or load) every kernel the presets use; returns the seconds it took."""
    import numpy as np

    from arlight.pipeline.config import PRESETS, Config
    from arlight.pipeline.pipeline import Pipeline
    from arlight.pipeline.runtime import configure_process
    from arlight.pipeline.virtual_scene import demo_scene
    from arlight.protocols import decode_depth, encode_depth
    from arlight.sources.synthetic import make_sequence

    configure_process()
    t0 = time.perf_counter()
    scene = make_sequence(num_frames=2, width=WARMUP_SIZE[0], height=WARMUP_SIZE[1])
    for preset in PRESETS:
        # with the demo's objects, so the renderer's kernels compile here too
        pipeline = Pipeline(Config.from_preset(preset), scene.camera, demo_scene(WARMUP_SIZE))
        for frame in scene.frames:
            pipeline.process(frame)
    depth = np.asarray(scene.frames[0].depth, dtype=np.uint16)
    decode_depth(*encode_depth(depth, "rvl"))
    _warm_up_glossy()
    return time.perf_counter() - t0


def _warm_up_glossy() -> None:
    """The kernels of `arlight ibl --render`: glossy, specular (mirror + glossy), lookup."""
    import numpy as np

    from arlight.pipeline import glossy

    pyramid = glossy.mip_pyramid(np.ones((8, 16, 3), np.float32))
    dirs = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    glossy.glossy(pyramid, dirs, 0.2)
    glossy.specular(pyramid, dirs, np.array([1, 2]), np.array([0.0, 48.0]))
    glossy.lookup(pyramid.levels[0], dirs)


def main() -> int:
    print(
        "arlight: compiling the kernels once (cached for every later run)...",
        file=sys.stderr,
        flush=True,
    )
    seconds = warm_up()
    print(f"arlight: kernels ready ({seconds:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
