"""A single colour image + depth image pair (format "pair").

`open_pair(color_path, depth_path, encoding)`, or `open_sequence` on a colour image whose
name holds color/colour/rgb/image with a partner holding depth instead, or on a folder
holding exactly one such pair. Depth encodings: see `depth_encodings.DEPTH_ENCODINGS`; without
one, a TUM_/SUN_/NYU_ file-name prefix names it. NYU raw depth is in the depth camera's frame
(not registered to colour), like 7-Scenes; it is not reprojected here (no calibration ships
with the frame).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from arlight.core.camera import PinholeCamera
from arlight.sources.depth_encodings import DEPTH_ENCODINGS, check_encoding
from arlight.sources.errors import DatasetError
from arlight.sources.images import IMAGE_EXTS, check_decodable, is_image
from arlight.sources.rgbd_sequence import (
    FrameRecord,
    RgbdSequence,
    build_sequence,
    default_camera,
    note,
)

COLOR_TOKENS = ("color", "colour", "rgb", "image")
_ENCODING_PREFIXES = {"tum": "tum", "sun": "sun", "nyu": "nyu"}


def open_pair(
    color_path: str | Path,
    depth_path: str | Path,
    depth_encoding: str | None,
    camera: PinholeCamera | None = None,
) -> RgbdSequence:
    """A one-frame sequence (format "pair", timestamp 0, no pose) from a colour + depth image.

    depth_encoding: one of DEPTH_ENCODINGS; None infers it from a TUM_/SUN_/NYU_ file-name
    prefix (DatasetError when there is none). camera: intrinsics of the colour image; None
    uses Kinect v1 defaults scaled to the image width (with a warning).
    """
    color_path, depth_path = Path(color_path), Path(depth_path)
    check_decodable(color_path, "colour image")  # before anything is said about the depth
    check_decodable(depth_path, "depth image")
    notes: list[str] = []
    if depth_encoding is None:
        depth_encoding = _infer_encoding(color_path, depth_path)
        note(
            notes,
            f"depth encoding {depth_encoding!r} inferred from the file name "
            f"{depth_path.name}; --depth-encoding overrides it",
            logging.INFO,
        )
    check_encoding(depth_encoding)
    if camera is None:
        camera = default_camera(color_path, notes, f"{color_path}: no intrinsics given")
    if depth_encoding == "nyu":
        note(
            notes,
            f"{depth_path}: NYU raw depth is in the depth camera's frame, not "
            "registered to colour (misaligned by a few pixels)",
            logging.INFO,
        )
    record = FrameRecord(color_path, depth_path, 0.0)
    name = _common_prefix_name(color_path, depth_path)
    return build_sequence(
        name,
        "pair",
        color_path,
        [record],
        camera,
        depth_encoding,
        None,
        has_poses=False,
        use_poses=False,
        max_frames=None,
        notes=notes,
    )


def without_poses(seq: RgbdSequence, use_poses: bool) -> RgbdSequence:
    """`seq`, or DatasetError when poses were asked for: a single pair has none."""
    if use_poses:
        raise DatasetError(
            f"{seq.source}: a single colour + depth pair has no camera poses, so "
            "--poses groundtruth cannot be used; track instead (--poses track)"
        )
    return seq


def partner_of_color_file(path: Path) -> tuple[Path, Path]:
    """The depth image beside a colour image file: its name with color/colour/rgb -> depth."""
    if not is_image(path):
        raise DatasetError(
            f"{path}: not an image file ({', '.join(IMAGE_EXTS)}); pass a sequence folder or "
            "a colour image"
        )
    lower = path.stem.lower()
    for token in COLOR_TOKENS:
        i = lower.rfind(token)
        if i < 0:
            continue
        stem = path.stem[:i] + "depth" + path.stem[i + len(token) :]
        tried = [path.with_name(stem + ext) for ext in (".png", ".pgm", ".tif", ".tiff")]
        for candidate in tried:
            if candidate.is_file():
                return path, candidate
        raise DatasetError(
            f"{path}: found no depth partner (looked for {', '.join(p.name for p in tried)}); "
            "name the depth image with --depth FILE --depth-encoding E"
        )
    raise DatasetError(
        f"{path}: a single image is opened as a colour + depth pair, but its name holds none "
        f"of {', '.join(COLOR_TOKENS)} to find the depth partner by; name the depth image "
        "with --depth FILE --depth-encoding E"
    )


def pairs_in_folder(folder: Path) -> list[tuple[Path, Path]]:
    """Every (colour, depth partner) image pair directly in `folder`."""
    pairs = []
    for p in sorted(folder.iterdir()):
        if (
            is_image(p)
            and any(t in p.stem.lower() for t in COLOR_TOKENS)
            and ("depth" not in p.stem.lower())
        ):
            try:
                pairs.append(partner_of_color_file(p))
            except DatasetError:
                continue
    return pairs


def _infer_encoding(color_path: Path, depth_path: Path) -> str:
    for p in (depth_path, color_path):
        match = re.match(r"([A-Za-z]+)[_\-.]", p.name)
        if match and match.group(1).lower() in _ENCODING_PREFIXES:
            return _ENCODING_PREFIXES[match.group(1).lower()]
    described = "; ".join(f"{k}: {v}" for k, v in DEPTH_ENCODINGS.items())
    raise DatasetError(
        f"{depth_path}: cannot tell how this depth image is encoded; name it with "
        f"--depth-encoding {'|'.join(DEPTH_ENCODINGS)} ({described})"
    )


def _common_prefix_name(a: Path, b: Path) -> str:
    prefix = ""
    for x, y in zip(a.stem, b.stem, strict=False):
        if x != y:
            break
        prefix += x
    prefix = prefix.rstrip("_-. ")
    return prefix or a.stem
