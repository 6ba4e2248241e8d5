"""Microsoft 7-Scenes sequences (format "7scenes").

Layout: a sequence folder (frame-NNNNNN.color.png|jpg, frame-NNNNNN.depth.png in mm with
65535 = invalid, frame-NNNNNN.pose.txt camera-to-world, camera-intrinsics.txt) or a scene
folder holding exactly one seq-XX subfolder.

7-Scenes depth is NOT registered to colour: it comes from the Kinect's depth camera
(fx = fy = 585), the colour from its RGB camera (fx = fy = 525, about 2.5 cm to the side).
We reproject every depth pixel into the colour camera (z-buffered nearest-pixel splat) with
the generic Kinect v1 depth-to-colour calibration the 7-Scenes community uses
(`SEVEN_SCENES_COLOR_FROM_DEPTH`, the LIRIS calibration also used by DSAC*/ACE's "calibrated
depth"). It is not this device's own calibration (none was published), so expect residual
misalignment of a few pixels at depth edges. The reprojected depth is no longer the stored
millimetres: it is quantised again to uint16 at `SEVEN_SCENES_DEPTH_SCALE` = 5000 units per
metre (0.2 mm steps, so at most 0.1 mm from the reprojected value; depth beyond 13.1 m
becomes missing). The returned camera is the colour camera, and so are the poses:
world_from_color = world_from_depth (the file's KinectFusion pose, tracked with the depth
camera) @ inv(SEVEN_SCENES_COLOR_FROM_DEPTH), so fused depth stays consistent (the world
frame is the file's).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np

from arlight.core.camera import PinholeCamera
from arlight.core.checks import check_rigid
from arlight.sources.errors import DatasetError, dataset_errors
from arlight.sources.images import read_color, read_image
from arlight.sources.registration import DepthRegistration
from arlight.sources.rgbd_sequence import FrameRecord, RgbdSequence, build_sequence, note

SEVEN_SCENES_FPS = 30.0
#: Units per metre of the depth once reprojected into the colour camera.
SEVEN_SCENES_DEPTH_SCALE = 5000.0
#: 7-Scenes depth camera defaults (used when camera-intrinsics.txt is absent), 640x480.
SEVEN_SCENES_DEPTH_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
#: 7-Scenes colour camera (focal length as published with the data set), at 640x480.
SEVEN_SCENES_COLOR_FOCAL_PX = 525.0
#: color_from_depth 4x4 (metres): generic Kinect v1 calibration (LIRIS), as used for
#: 7-Scenes' "calibrated depth" in DSAC* and ACE. Depth camera -> colour camera.
SEVEN_SCENES_COLOR_FROM_DEPTH = np.array(
    [
        [
            9.9996518012567637e-01,
            2.6765126468950343e-03,
            -7.9041012313000904e-03,
            -2.5558943178152542e-02,
        ],
        [
            -2.7409311281316700e-03,
            9.9996302803027592e-01,
            -8.1504520778013286e-03,
            1.0109636268061706e-04,
        ],
        [
            7.8819942130445332e-03,
            8.1718328771890631e-03,
            9.9993554558014031e-01,
            2.0318321729487039e-03,
        ],
        [0.0, 0.0, 0.0, 1.0],
    ]
)

_SEVEN_DEPTH = re.compile(r"^frame-(\d+)\.depth\.png$")

#: (frame number, colour path, depth path, pose path)
_Files = tuple[int, Path, Path, Path]


def seven_scenes_folder(folder: Path) -> Path | None:
    """The 7-Scenes sequence folder at or (one seq-XX) below `folder`, or None."""
    if any(_SEVEN_DEPTH.match(p.name) for p in folder.glob("frame-*.depth.png")):
        return folder
    seqs = sorted(p for p in folder.glob("seq-*") if p.is_dir())
    seqs = [s for s in seqs if any(s.glob("frame-*.depth.png"))]
    if len(seqs) == 1:
        return seqs[0]
    if len(seqs) > 1:
        raise DatasetError(
            f"{folder}: holds {len(seqs)} 7-Scenes sequences "
            f"({', '.join(s.name for s in seqs)}); pass one of them, e.g. {seqs[0]}"
        )
    return None


def open_seven_scenes(
    folder: Path, depth_encoding: str | None, use_poses: bool, max_frames: int | None
) -> RgbdSequence:
    """Open a 7-Scenes sequence folder (module docstring); depth_encoding overrides "mm"."""
    notes: list[str] = []
    files = _frame_files(folder, notes)
    depth_camera, camera = _cameras(folder, files[0], notes)
    registration = DepthRegistration(
        depth_camera, SEVEN_SCENES_COLOR_FROM_DEPTH, SEVEN_SCENES_DEPTH_SCALE
    )
    note(
        notes,
        "7-Scenes depth is not registered to colour: reprojected into the colour "
        f"camera (fx = fy = {camera.fx:g}) with a generic Kinect v1 depth-to-colour "
        "calibration (poses moved to the colour camera too) and quantised at "
        f"{SEVEN_SCENES_DEPTH_SCALE:g} units per metre; expect a few pixels of "
        "residual misalignment at depth edges",
        logging.INFO,
    )
    has_poses = all(f[3].is_file() for f in files)
    if use_poses:
        if max_frames is not None:  # read only the poses that will be used
            files = files[:max_frames]
        records = _records_with_poses(folder, files, notes)
    else:
        records = [FrameRecord(c, d, n / SEVEN_SCENES_FPS) for n, c, d, _ in files]
    return build_sequence(
        folder.name,
        "7scenes",
        folder,
        records,
        camera,
        depth_encoding or "mm",
        None,
        has_poses,
        use_poses,
        max_frames,
        notes,
        registration,
    )


def _frame_files(folder: Path, notes: list[str]) -> list[_Files]:
    """Every frame whose depth has a colour image beside it, by frame number."""
    files = []
    missing_color = 0
    for p in folder.glob("frame-*.depth.png"):
        match = _SEVEN_DEPTH.match(p.name)
        if not match:
            continue
        stem = f"frame-{match.group(1)}"
        color = next(
            (
                folder / f"{stem}.color{ext}"
                for ext in (".png", ".jpg")
                if (folder / f"{stem}.color{ext}").is_file()
            ),
            None,
        )
        if color is None:
            missing_color += 1
            continue
        files.append((int(match.group(1)), color, p, folder / f"{stem}.pose.txt"))
    files.sort(key=lambda f: f[0])
    if missing_color:
        note(
            notes,
            f"{folder}: {missing_color} depth images have no frame-NNNNNN.color.png|jpg; skipped",
        )
    if not files:
        raise DatasetError(
            f"{folder}: empty sequence: no frame-NNNNNN.depth.png has a "
            "frame-NNNNNN.color.png|jpg beside it"
        )
    return files


def _cameras(folder: Path, first: _Files, notes: list[str]) -> tuple[PinholeCamera, PinholeCamera]:
    """(depth camera, colour camera), at the sizes of the first frame's images."""
    intr = folder / "camera-intrinsics.txt"
    first_depth = read_image(first[2], cv2.IMREAD_UNCHANGED, "depth image")
    dh, dw = first_depth.shape[:2]
    if intr.is_file():
        try:
            k = np.loadtxt(intr, dtype=np.float64)
            if k.shape != (3, 3):
                raise ValueError(f"shape {k.shape}, expected 3x3")
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{intr}: cannot read a 3x3 intrinsic matrix ({exc})") from exc
    else:  # defaults are for 640x480: scale them to the depth image
        s = dw / 640.0
        k = SEVEN_SCENES_DEPTH_K * np.array([[s, 1.0, s], [1.0, s, s], [1.0, 1.0, 1.0]])
        note(
            notes,
            f"{folder}: no camera-intrinsics.txt; using the 7-Scenes depth camera "
            "defaults fx = fy = 585, cx = 320, cy = 240 (at 640x480, scaled)",
        )
    try:
        depth_camera = PinholeCamera.from_matrix(k, dw, dh)
    except ValueError as exc:
        raise DatasetError(f"{intr}: {exc}") from exc
    ch, cw = read_color(first[1]).shape[:2]
    f = SEVEN_SCENES_COLOR_FOCAL_PX * cw / 640.0
    return depth_camera, PinholeCamera(cw, ch, f, f, cw / 2.0, ch / 2.0)


def _records_with_poses(folder: Path, files: list[_Files], notes: list[str]) -> list[FrameRecord]:
    """Records of the frames with a pose.txt, each pose moved to the colour camera."""
    if not any(f[3].is_file() for f in files):
        raise DatasetError(
            f"{folder}: --poses groundtruth, but there are no "
            "frame-NNNNNN.pose.txt files; track instead (--poses track)"
        )
    # the files hold world_from_depth-camera; the frames are in the colour camera
    depth_from_color = np.linalg.inv(SEVEN_SCENES_COLOR_FROM_DEPTH)
    records = [
        FrameRecord(c, d, n / SEVEN_SCENES_FPS, _read_pose_file(p) @ depth_from_color)
        for n, c, d, p in files
        if p.is_file()
    ]
    if len(records) < len(files):
        note(notes, f"{folder}: {len(files) - len(records)} frames have no pose.txt; skipped")
    return records


def _read_pose_file(path: Path) -> np.ndarray:
    """world_from_depth-camera (4, 4) from a frame-NNNNNN.pose.txt."""
    try:
        m = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot read a 4x4 pose matrix ({exc})") from exc
    with dataset_errors("a pose.txt holds a camera-to-world rigid transform"):
        return check_rigid(m, str(path))
