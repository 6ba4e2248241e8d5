"""The front page's picture: a composite beside the trade plot (docs/images/front.png).

    .venv/bin/arlight estimate ../shared/data/synthetic/dev_a_static_venice --poses groundtruth \
        --max-frames 4 --preset fast --composite-out /tmp/comp \
        --scene ../shared/data/synthetic/dev_a_static_venice/ar/virtual_scene.json
    .venv/bin/python docs/make_front_picture.py /tmp/comp/000003.png docs/images/trade.png

Both images are scaled to one height and saved with a 256-colour palette (small enough for
the repository: under 300 KB).
"""

from __future__ import annotations

import sys
from pathlib import Path

from PIL import Image

HEIGHT_PX = 400
GAP_PX = 12


def main(composite: str, plot: str, out: str = "docs/images/front.png") -> None:
    left, right = (Image.open(p).convert("RGB") for p in (composite, plot))
    left, right = (
        im.resize((round(im.width * HEIGHT_PX / im.height), HEIGHT_PX), Image.Resampling.LANCZOS)
        for im in (left, right)
    )
    canvas = Image.new("RGB", (left.width + GAP_PX + right.width, HEIGHT_PX), "white")
    canvas.paste(left, (0, 0))
    canvas.paste(right, (left.width + GAP_PX, 0))
    canvas.quantize(colors=256, dither=Image.Dither.FLOYDSTEINBERG).save(out, optimize=True)
    print(f"{out}: {canvas.width}x{canvas.height}, {Path(out).stat().st_size // 1024} KB")


if __name__ == "__main__":
    main(*sys.argv[1:])
