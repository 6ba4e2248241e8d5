"""Reading image files of recorded data: colour as RGB, any image undecoded."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from arlight.sources.errors import DatasetError

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")


def is_image(path: Path) -> bool:
    """An existing file with an image extension (IMAGE_EXTS)."""
    return path.is_file() and path.suffix.lower() in IMAGE_EXTS


def check_decodable(path: Path, what: str) -> None:
    """DatasetError unless `path` exists and starts like an image OpenCV can decode."""
    if not path.is_file():
        raise DatasetError(f"{path}: {what} file does not exist")
    if not cv2.haveImageReader(str(path)):
        raise DatasetError(
            f"{path}: not an image OpenCV can decode (the {what} must be a "
            "PNG, JPEG, PPM/PGM, BMP or TIFF file)"
        )


def read_image(path: Path, flags: int, what: str) -> np.ndarray:
    """The image at `path` decoded by OpenCV with `flags`; DatasetError naming `what`."""
    if not path.is_file():
        raise DatasetError(f"{path}: {what} file does not exist")
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read the {what} file ({exc})") from exc
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise DatasetError(
            f"{path}: OpenCV cannot decode this {what} file (empty, truncated or not an image); "
            "replace it or remove the frame"
        )
    return image


def read_color(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB from an image file (grey is expanded, alpha dropped)."""
    bgr = read_image(Path(path), cv2.IMREAD_COLOR, "colour image")
    return np.ascontiguousarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
