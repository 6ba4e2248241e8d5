"""Open recorded RGB-D data of any supported layout: `open_sequence(path)`.

Detects the layout and returns an `RgbdSequence` (arlight.sources.rgbd_sequence): a camera
and a lazy, indexable list of FrameInput frames, depth as the sensor's uint16 with its
depth_scale. Layouts, one module each:

- "tum": TUM RGB-D folder (arlight.sources.tum);
- "redwood": Open3D / Redwood reconstruction-system folder (arlight.sources.redwood);
- "7scenes": Microsoft 7-Scenes sequence or scene folder, depth reprojected into the colour
  camera (arlight.sources.seven_scenes);
- "pair": one colour + one depth image (arlight.sources.image_pair).

Bad input raises `DatasetError` (a ValueError) naming the file or folder and what to do.
"""

from __future__ import annotations

from pathlib import Path

from arlight.sources.depth_encodings import check_encoding
from arlight.sources.errors import DatasetError
from arlight.sources.image_pair import (
    open_pair,
    pairs_in_folder,
    partner_of_color_file,
    without_poses,
)
from arlight.sources.redwood import open_redwood, redwood_color_dir
from arlight.sources.rgbd_sequence import RgbdSequence
from arlight.sources.seven_scenes import open_seven_scenes, seven_scenes_folder
from arlight.sources.tum import is_tum_folder, open_tum

_LOOKED_FOR = (
    "TUM RGB-D (rgb.txt + depth.txt, or associations.txt); "
    "Open3D/Redwood (color/ or image/ and depth/ subfolders); "
    "7-Scenes (frame-NNNNNN.depth.png + frame-NNNNNN.color.png|jpg, or one seq-XX subfolder); "
    "a single colour + depth image pair (one *color*|*rgb* and one *depth* image file)"
)


def open_sequence(
    path: str | Path,
    *,
    depth_encoding: str | None = None,
    use_poses: bool = False,
    max_frames: int | None = None,
) -> RgbdSequence:
    """Open recorded RGB-D data, detecting its layout (see the module docstring).

    path: a sequence folder, a 7-Scenes scene folder with one seq-XX, a folder holding one
    colour + depth pair, or a colour image file with a *depth* partner beside it.
    depth_encoding: override the layout's depth encoding ("tum", "mm", "sun", "nyu").
    use_poses: attach the data set's camera-to-world poses to the frames (DatasetError if it
    has none); frames with no pose are dropped with a warning. False leaves pose None.
    max_frames: keep only the first max_frames frames.
    """
    path = Path(path)
    if depth_encoding is not None:
        check_encoding(depth_encoding)
    if max_frames is not None and max_frames < 1:
        raise DatasetError(f"--max-frames must be >= 1, got {max_frames}")
    if not path.exists():
        raise DatasetError(
            f"{path}: no such file or folder; pass a recorded RGB-D sequence folder ({_LOOKED_FOR})"
        )
    try:
        return _open_detected(path, depth_encoding, use_poses, max_frames)
    except OSError as exc:  # unreadable folders, broken links, permissions
        raise DatasetError(
            f"{path}: cannot read ({exc}); check the path and its permissions"
        ) from exc


def _open_detected(
    path: Path, depth_encoding: str | None, use_poses: bool, max_frames: int | None
) -> RgbdSequence:
    if path.is_file():
        color_path, depth_path = partner_of_color_file(path)
        return without_poses(open_pair(color_path, depth_path, depth_encoding), use_poses)
    if is_tum_folder(path):
        return open_tum(path, depth_encoding, use_poses, max_frames)
    seven = seven_scenes_folder(path)
    if seven is not None:
        return open_seven_scenes(seven, depth_encoding, use_poses, max_frames)
    color_dir = redwood_color_dir(path)
    if color_dir is not None and (path / "depth").is_dir():
        return open_redwood(path, color_dir, depth_encoding, use_poses, max_frames)
    pairs = pairs_in_folder(path)
    if len(pairs) == 1:
        return without_poses(open_pair(pairs[0][0], pairs[0][1], depth_encoding), use_poses)
    if len(pairs) > 1:
        listing = "; ".join(f"{c.name} + {d.name}" for c, d in pairs)
        raise DatasetError(
            f"{path}: holds {len(pairs)} colour + depth pairs ({listing}); pass one colour "
            "image file instead of the folder (its *depth* partner is found beside it)"
        )
    raise DatasetError(f"{path}: not a recognised RGB-D data set. Looked for: {_LOOKED_FOR}")
