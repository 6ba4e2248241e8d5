"""Open3D / Redwood reconstruction-system folders (format "redwood").

Layout: color/ (or image/) *.jpg|*.png, depth/ *.png (uint16 millimetres: kept as stored at
1000 units per metre, 65535 = invalid -> 0), camera_intrinsic.json (Open3D's column-major
`intrinsic_matrix`), optional trajectory.log (camera-to-world, one 'i j k' header line and
four matrix rows per pose, in the order of the sorted colour images). Timestamps index / 30 s.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.core.checks import check_rigid
from arlight.sources.errors import DatasetError, dataset_errors
from arlight.sources.images import is_image
from arlight.sources.rgbd_sequence import (
    FrameRecord,
    RgbdSequence,
    build_sequence,
    default_camera,
    note,
)

REDWOOD_FPS = 30.0


def redwood_color_dir(folder: Path) -> Path | None:
    """The colour subfolder (color/ or image/) of a Redwood folder, or None."""
    for name in ("color", "image"):
        if (folder / name).is_dir():
            return folder / name
    return None


def open_redwood(
    folder: Path,
    color_dir: Path,
    depth_encoding: str | None,
    use_poses: bool,
    max_frames: int | None,
) -> RgbdSequence:
    """Open a Redwood folder (module docstring); depth_encoding overrides "mm"."""
    notes: list[str] = []
    colors = sorted(p for p in color_dir.iterdir() if is_image(p))
    pairs = _pairs(folder, color_dir, colors, notes)
    index_of = {c: i for i, c in enumerate(colors)}
    records = [FrameRecord(c, d, index_of[c] / REDWOOD_FPS) for c, d in pairs]

    intr = folder / "camera_intrinsic.json"
    if intr.is_file():
        camera = _read_open3d_intrinsics(intr)
    else:
        camera = default_camera(pairs[0][0], notes, f"{folder}: no camera_intrinsic.json")

    traj = folder / "trajectory.log"
    if use_poses:
        if not traj.is_file():
            raise DatasetError(
                f"{folder}: --poses groundtruth, but there is no "
                "trajectory.log; track instead (--poses track)"
            )
        poses = _read_trajectory_log(traj)
        # trajectory.log entries follow the sorted colour images, as Open3D writes them
        if len(poses) != len(colors):
            note(
                notes,
                f"{traj}: {len(poses)} poses for {len(colors)} colour images; frames "
                "beyond the last pose are skipped",
            )
        records = [
            FrameRecord(r.color_path, r.depth_path, r.timestamp_s, poses[index_of[r.color_path]])
            for r in records
            if index_of[r.color_path] < len(poses)
        ]
    return build_sequence(
        folder.name,
        "redwood",
        folder,
        records,
        camera,
        depth_encoding or "mm",
        None,
        traj.is_file(),
        use_poses,
        max_frames,
        notes,
    )


def _pairs(
    folder: Path, color_dir: Path, colors: list[Path], notes: list[str]
) -> list[tuple[Path, Path]]:
    """(colour, depth) image pairs: by file name, else in sorted order when the counts agree."""
    depth_dir = folder / "depth"
    depths = sorted(p for p in depth_dir.iterdir() if is_image(p))
    if not colors or not depths:
        empty = color_dir if not colors else depth_dir
        raise DatasetError(f"{empty}: empty sequence: no image files in this folder")
    depth_by_stem = {p.stem: p for p in depths}
    if all(c.stem in depth_by_stem for c in colors):
        return [(c, depth_by_stem[c.stem]) for c in colors]
    if len(colors) == len(depths):
        note(
            notes,
            f"{folder}: colour and depth file names differ; paired in sorted order",
            logging.INFO,
        )
        return list(zip(colors, depths, strict=True))
    matched = [(c, depth_by_stem[c.stem]) for c in colors if c.stem in depth_by_stem]
    if not matched:
        raise DatasetError(
            f"{folder}: {len(colors)} colour and {len(depths)} depth images share no file "
            "names; name each colour/depth pair alike (00000.jpg + 00000.png)"
        )
    note(
        notes,
        f"{folder}: {len(colors) - len(matched)} colour images have no depth "
        "image of the same name; skipped",
    )
    return matched


def _read_open3d_intrinsics(path: Path) -> PinholeCamera:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        width, height = int(data["width"]), int(data["height"])
        k = np.asarray(data["intrinsic_matrix"], dtype=np.float64)
        if k.size != 9:
            raise ValueError(f"intrinsic_matrix has {k.size} values, expected 9")
        k = k.reshape(3, 3).T  # Open3D stores it column-major
        return PinholeCamera.from_matrix(k, width, height)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(
            f"{path}: cannot read Open3D camera intrinsics ({exc!s}); expected width, height "
            "and a 9-value column-major intrinsic_matrix"
        ) from exc


def _read_trajectory_log(path: Path) -> list[np.ndarray]:
    """world_from_cam (4, 4) per entry of an Open3D/Redwood trajectory.log."""
    try:
        lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc})") from exc
    if len(lines) % 5:
        raise DatasetError(
            f"{path}: {len(lines)} non-empty lines is not a multiple of 5; each pose is a "
            "header line 'i j k' and 4 rows of a 4x4 matrix"
        )
    poses = []
    for e in range(0, len(lines), 5):
        where = f"{path}, lines {e + 2}-{e + 5}"
        try:
            m = np.array([[float(x) for x in lines[e + r].split()] for r in range(1, 5)])
        except ValueError as exc:
            raise DatasetError(f"{where}: {exc}") from exc
        with dataset_errors("each pose must be a camera-to-world rigid transform"):
            poses.append(check_rigid(m, where))
    return poses
