"""TUM RGB-D folders (format "tum").

Layout: rgb.txt + depth.txt and/or associations.txt (`timestamp path` lines), depth as uint16
PNG at 5000 units per metre (or `depth_scale` in an optional camera.json, which also gives
fx, fy, cx, cy, width, height; without it Kinect v1 defaults are used and a warning logged).
The depth integers are kept as stored (65535 = invalid -> 0), with that depth_scale.
Without associations.txt, colour and depth are paired by nearest timestamp (<= 0.02 s).
Frames listed in the text files whose image files are absent are skipped with a warning
(excerpts of long sequences keep the full lists). Poses: groundtruth.txt
(`timestamp tx ty tz qx qy qz qw`, camera-to-world), nearest timestamp within 0.05 s.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from arlight.core.camera import PinholeCamera
from arlight.sources.depth_encodings import UNITS_PER_METRE
from arlight.sources.errors import DatasetError
from arlight.sources.rgbd_sequence import (
    FrameRecord,
    RgbdSequence,
    build_sequence,
    default_camera,
    note,
)

TUM_ASSOCIATION_MAX_DT_S = 0.02
TUM_POSE_MAX_DT_S = 0.05

#: (t_rgb, rgb path, t_depth, depth path), paths relative to the folder
Pair = tuple[float, str, float, str]


def is_tum_folder(folder: Path) -> bool:
    return any((folder / name).is_file() for name in ("associations.txt", "rgb.txt", "depth.txt"))


def open_tum(
    folder: Path, depth_encoding: str | None, use_poses: bool, max_frames: int | None
) -> RgbdSequence:
    """Open a TUM RGB-D folder (module docstring); depth_encoding overrides "tum"."""
    notes: list[str] = []
    pairs, listed_in = _listed_pairs(folder, notes)
    if not pairs:
        raise DatasetError(
            f"{folder}: empty sequence: no colour + depth pair listed in {listed_in} has both "
            "image files present"
        )
    pairs.sort(key=lambda p: p[0])
    camera, units = _camera(folder, folder / pairs[0][1], notes)
    encoding = "tum"
    if depth_encoding is not None:
        encoding, units = depth_encoding, None
    elif units is None:
        units = UNITS_PER_METRE["tum"]
    gt_path = folder / "groundtruth.txt"
    records = [FrameRecord(folder / c, folder / d, t) for t, c, _, d in pairs]
    if use_poses:
        if not gt_path.is_file():
            raise DatasetError(
                f"{folder}: --poses groundtruth, but there is no "
                "groundtruth.txt; track instead (--poses track)"
            )
        records = _with_groundtruth(records, gt_path, notes)
    return build_sequence(
        folder.name,
        "tum",
        folder,
        records,
        camera,
        encoding,
        units,
        gt_path.is_file(),
        use_poses,
        max_frames,
        notes,
    )


# --------------------------------------------------------------------------- pairing


def _listed_pairs(folder: Path, notes: list[str]) -> tuple[list[Pair], str]:
    """The colour + depth pairs the folder lists whose files exist, and where they were listed."""
    assoc_path = folder / "associations.txt"
    if not assoc_path.is_file():
        return _pairs_by_timestamp(folder, notes), "rgb.txt/depth.txt"
    pairs = _read_associations(folder, assoc_path)
    present = [p for p in pairs if (folder / p[1]).is_file() and (folder / p[3]).is_file()]
    if len(present) < len(pairs):
        note(
            notes,
            f"{folder}: {len(pairs) - len(present)} of {len(pairs)} pairs listed in "
            f"{assoc_path.name} have absent image files; skipped",
        )
    return present, assoc_path.name


def _read_associations(folder: Path, assoc_path: Path) -> list[Pair]:
    rgb_path = folder / "rgb.txt"
    rgb_names = {n for _, n in _read_timed_list(rgb_path)} if rgb_path.is_file() else set()
    pairs = []
    for n, f in _read_table(assoc_path, 4, "t_rgb rgb/x.png t_depth depth/x.png"):
        t1, f1 = _float_field(f[0], assoc_path, n), f[1]
        t2, f2 = _float_field(f[2], assoc_path, n), f[3]
        # TUM's associate.py writes whichever list it was given first: tell them apart
        swapped = (f2 in rgb_names and f1 not in rgb_names) or (
            not rgb_names and "depth" in f1.lower() and "depth" not in f2.lower()
        )
        pairs.append((t2, f2, t1, f1) if swapped else (t1, f1, t2, f2))
    return pairs


def _pairs_by_timestamp(folder: Path, notes: list[str]) -> list[Pair]:
    rgb_path, depth_path = folder / "rgb.txt", folder / "depth.txt"
    if not (rgb_path.is_file() and depth_path.is_file()):
        have = rgb_path.name if rgb_path.is_file() else depth_path.name
        raise DatasetError(
            f"{folder}: TUM RGB-D layout needs associations.txt or both rgb.txt and "
            f"depth.txt, found only {have}"
        )
    listed = _read_timed_list(rgb_path)
    rgb = [(t, n) for t, n in listed if (folder / n).is_file()]
    depth = [(t, n) for t, n in _read_timed_list(depth_path) if (folder / n).is_file()]
    if len(rgb) < len(listed):
        note(
            notes,
            f"{folder}: {len(listed) - len(rgb)} of {len(listed)} images listed in "
            "rgb.txt are absent; skipped",
        )
    pairs = _associate(rgb, depth, TUM_ASSOCIATION_MAX_DT_S)
    if rgb and len(pairs) < len(rgb):
        note(
            notes,
            f"{folder}: {len(rgb) - len(pairs)} colour images have no depth "
            f"image within {TUM_ASSOCIATION_MAX_DT_S} s; skipped",
        )
    return pairs


def _associate(
    rgb: list[tuple[float, str]], depth: list[tuple[float, str]], max_dt: float
) -> list[Pair]:
    """One-to-one nearest-timestamp pairs (|dt| <= max_dt), closest pairs first."""
    if not rgb or not depth:
        return []
    t_rgb = np.array([t for t, _ in rgb])
    t_depth = np.array([t for t, _ in depth])
    order = np.argsort(t_depth)
    t_sorted = t_depth[order]
    candidates = []
    for i, t in enumerate(t_rgb):
        k = int(np.searchsorted(t_sorted, t))
        for j in (k - 1, k):
            if 0 <= j < len(t_sorted) and abs(t_sorted[j] - t) <= max_dt:
                candidates.append((abs(t_sorted[j] - t), i, int(order[j])))
    used_rgb: set[int] = set()
    used_depth: set[int] = set()
    pairs = []
    for _, i, j in sorted(candidates):
        if i in used_rgb or j in used_depth:
            continue
        used_rgb.add(i)
        used_depth.add(j)
        pairs.append((rgb[i][0], rgb[i][1], depth[j][0], depth[j][1]))
    pairs.sort(key=lambda p: p[0])
    return pairs


# --------------------------------------------------------------------------- text files


def _read_table(path: Path, min_cols: int, layout: str) -> list[tuple[int, list[str]]]:
    """Non-comment rows (line number, fields) of a whitespace (or comma) separated text file."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc})") from exc
    rows = []
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) < min_cols:
            raise DatasetError(f"{path}, line {n}: expected '{layout}', got {line!r}")
        rows.append((n, fields))
    return rows


def _float_field(value: str, path: Path, n: int) -> float:
    try:
        x = float(value)
    except ValueError:
        x = float("nan")
    if not np.isfinite(x):
        raise DatasetError(f"{path}, line {n}: {value!r} is not a finite number")
    return x


def _read_timed_list(path: Path) -> list[tuple[float, str]]:
    return [
        (_float_field(f[0], path, n), f[1]) for n, f in _read_table(path, 2, "timestamp filename")
    ]


# --------------------------------------------------------------------------- camera


def _camera(
    folder: Path, first_color: Path, notes: list[str]
) -> tuple[PinholeCamera, float | None]:
    """The colour camera and camera.json's depth_scale (None: not given)."""
    camera_json = folder / "camera.json"
    if camera_json.is_file():
        return _read_camera_json(camera_json)
    return default_camera(first_color, notes, f"{folder}: no camera.json"), None


def _read_camera_json(path: Path) -> tuple[PinholeCamera, float | None]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot read camera JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object with fx, fy, cx, cy, width, height")
    values = {}
    for key in ("fx", "fy", "cx", "cy", "width", "height"):
        if key not in data:
            raise DatasetError(
                f"{path}: missing {key!r}; camera.json needs fx, fy, cx, cy, width, height "
                "(and optionally depth_scale, units per metre)"
            )
        if not isinstance(data[key], (int, float)) or isinstance(data[key], bool):
            raise DatasetError(f"{path}: {key!r} must be a number, got {data[key]!r}")
        values[key] = data[key]
    try:
        camera = PinholeCamera(
            int(values["width"]),
            int(values["height"]),
            float(values["fx"]),
            float(values["fy"]),
            float(values["cx"]),
            float(values["cy"]),
        )
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}") from exc
    scale = data.get("depth_scale")
    if scale is not None:
        if (
            not isinstance(scale, (int, float))
            or isinstance(scale, bool)
            or not np.isfinite(scale)
            or scale <= 0
        ):
            raise DatasetError(
                f"{path}: depth_scale must be a number > 0 (units per metre), got {scale!r}"
            )
        scale = float(scale)
    return camera, scale


# --------------------------------------------------------------------------- poses


def quaternion_to_matrix(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """3x3 rotation from a Hamilton quaternion in TUM's (x, y, z, w) order, normalised first.

    ValueError for a zero (or non-finite) quaternion, which has no direction.
    """
    q = np.array([qx, qy, qz, qw], dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-8:
        raise ValueError(f"quaternion {q.tolist()} has no direction")
    return Rotation.from_quat(q).as_matrix()  # scalar last, as TUM writes it


def _read_tum_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and world_from_cam (N, 4, 4), sorted by time."""
    rows = _read_table(path, 8, "timestamp tx ty tz qx qy qz qw")
    times, poses = [], []
    for n, f in rows:
        v = [_float_field(x, path, n) for x in f[:8]]
        try:
            r = quaternion_to_matrix(*v[4:8])
        except ValueError as exc:
            raise DatasetError(f"{path}, line {n}: {exc}") from exc
        m = np.eye(4)
        m[:3, :3] = r
        m[:3, 3] = v[1:4]
        times.append(v[0])
        poses.append(m)
    if not times:
        raise DatasetError(f"{path}: holds no poses")
    order = np.argsort(times)
    return np.asarray(times)[order], np.asarray(poses)[order]


def _nearest_pose(
    times: np.ndarray, poses: np.ndarray, t: float, max_dt: float
) -> np.ndarray | None:
    k = int(np.searchsorted(times, t))
    best = None
    for j in (k - 1, k):
        if 0 <= j < len(times) and abs(times[j] - t) <= max_dt:
            if best is None or abs(times[j] - t) < abs(times[best] - t):
                best = j
    return None if best is None else poses[best]


def _with_groundtruth(
    records: list[FrameRecord], gt_path: Path, notes: list[str]
) -> list[FrameRecord]:
    """The records with a pose within TUM_POSE_MAX_DT_S, each carrying it."""
    times, poses = _read_tum_groundtruth(gt_path)
    with_pose = []
    for rec in records:
        pose = _nearest_pose(times, poses, rec.timestamp_s, TUM_POSE_MAX_DT_S)
        if pose is not None:
            with_pose.append(FrameRecord(rec.color_path, rec.depth_path, rec.timestamp_s, pose))
    if len(with_pose) < len(records):
        note(
            notes,
            f"{gt_path}: {len(records) - len(with_pose)} of {len(records)} frames "
            f"have no pose within {TUM_POSE_MAX_DT_S} s; skipped",
        )
    if not with_pose:
        raise DatasetError(
            f"{gt_path}: no pose lies within {TUM_POSE_MAX_DT_S} s of any "
            "frame's timestamp; check that the timestamps share a clock"
        )
    return with_pose
