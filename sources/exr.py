"""OpenEXR files of linear RGB maps: read (HDR panoramas as input) and write (`arlight ibl --exr`).

Through the OpenEXR package (the format's reference implementation; the OpenCV wheels are
built without OpenEXR). Channels R, G, B; what is written is half float (16-bit), ZIP
compressed, scanline; values beyond half's range (65504) are clipped to it, NaN and negative
values written as 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from arlight.sources.errors import DatasetError

HALF_MAX = float(np.finfo(np.float16).max)  # 65504


def write_exr(path: str | Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) linear RGB float map as a half-float OpenEXR file."""
    import OpenEXR

    a = np.asarray(rgb, dtype=np.float32)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"write_exr: expected an (H, W, 3) RGB map, got shape {a.shape}")
    half = np.clip(np.nan_to_num(a, nan=0.0, posinf=HALF_MAX), 0.0, HALF_MAX).astype(np.float16)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    try:
        with OpenEXR.File(header, {"RGB": np.ascontiguousarray(half)}) as f:
            f.write(str(path))
    except OSError:
        raise
    except Exception as exc:  # the binding raises plain RuntimeError when it cannot write
        raise OSError(f"{path}: cannot write this OpenEXR file ({exc})") from None


def read_exr(path: str | Path) -> np.ndarray:
    """(H, W, 3) float32 linear RGB of an OpenEXR file (R, G, B channels, any pixel type)."""
    import OpenEXR

    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: file does not exist")
    try:
        with OpenEXR.File(str(p)) as f:
            channels = f.channels()
            if "RGB" in channels:
                rgb = np.array(channels["RGB"].pixels, dtype=np.float32)
            elif all(c in channels for c in "RGB"):
                rgb = np.stack(
                    [np.asarray(channels[c].pixels, dtype=np.float32) for c in "RGB"], axis=-1
                )
            else:
                raise DatasetError(
                    f"{p}: an OpenEXR panorama needs R, G and B channels, "
                    f"found {', '.join(sorted(channels)) or 'none'}"
                )
    except DatasetError:
        raise
    except Exception as exc:  # the binding raises plain RuntimeError/OSError on bad files
        raise DatasetError(f"{p}: cannot read this OpenEXR file ({exc})") from None
    if rgb.ndim == 3 and rgb.shape[2] == 4:  # RGBA
        rgb = rgb[..., :3]
    return np.ascontiguousarray(rgb)
