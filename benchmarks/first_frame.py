"""Is JIT compilation kept off the request path? The first frame of a fresh process against
its tenth, and what numba's kernel cache did.

In a fresh Python process (as a new server or `arlight estimate` is) it builds a Pipeline for
the built-in 640x480 scene and times each of 12 frames; numba's cache debugging
(NUMBA_DEBUG_CACHE) says for each kernel whether it was loaded from the cache written at
install (`scripts/bootstrap.sh` runs `python -m arlight.warmup`) or compiled now. Prints per
frame the total and per-stage milliseconds, the first-to-tenth ratio (the issue's bound: at
most 2x), and the kernels loaded and compiled.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/first_frame.py [--preset fast]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

CHILD = r"""
import json, time
from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.runtime import configure_process
from arlight.sources.synthetic import make_sequence
configure_process()
scene = make_sequence(num_frames=12, width=640, height=480)
pipeline = Pipeline(Config.from_preset(PRESET), scene.camera)
rows = []
for frame in scene.frames:
    t0 = time.perf_counter()
    result = pipeline.process(frame)
    rows.append({"total": 1e3 * (time.perf_counter() - t0), **result.timings_ms})
print("ROWS " + json.dumps(rows))
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="fast")
    args = parser.parse_args(argv)
    env = dict(os.environ, NUMBA_DEBUG_CACHE="1")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    proc = subprocess.run(
        [sys.executable, "-c", CHILD.replace("PRESET", repr(args.preset))],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if proc.returncode != 0:
        print(proc.stderr[-3000:], file=sys.stderr)
        return 1
    lines = proc.stdout.splitlines()
    rows = json.loads(next(x for x in lines if x.startswith("ROWS "))[5:])
    loaded = sorted(
        {
            x.split("'")[1].rsplit("/", 1)[-1].split("-")[0]
            for x in lines
            if x.startswith("[cache] data loaded")
        }
    )
    saved = sorted(
        {
            x.split("'")[1].rsplit("/", 1)[-1].split("-")[0]
            for x in lines
            if x.startswith("[cache] data saved")
        }
    )
    stages = [k for k in rows[0] if k != "total"]
    print("| frame | total ms | " + " | ".join(stages) + " |")
    print("|---|---|" + "---|" * len(stages))
    for i, r in enumerate(rows):
        print(f"| {i + 1} | {r['total']:.0f} | " + " | ".join(f"{r[s]:.0f}" for s in stages) + " |")
    ratio = rows[0]["total"] / rows[9]["total"]
    print(f"\nfirst / tenth frame: {ratio:.2f}x (bound 2x: {'met' if ratio <= 2 else 'MISSED'})")
    print(f"kernels loaded from the cache: {', '.join(loaded) or 'none'}")
    print(f"kernels compiled in this process: {', '.join(saved) or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
