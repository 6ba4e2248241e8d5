"""Readers of recorded RGB-D data into `arlight.pipeline.frames.FrameInput` frames.

`open_sequence(path)` detects the layout and returns an `RgbdSequence`: a camera and a lazy,
indexable list of frames (frame i is read from disk when it is accessed, never cached).
`open_pair(color_path, depth_path, encoding)` wraps one colour + depth image pair.

Every frame leaves here as
    color: (H, W, 3) uint8, RGB order (OpenCV's BGR converted here, at the edge);
    depth: (H, W) float32, metres along the optical axis, 0 = missing;
    timestamp: seconds (float);
    pose: (4, 4) float64 camera-to-world (world_from_cam) or None.

Supported layouts (`RgbdSequence.format`):

- "tum": TUM RGB-D folder: rgb.txt + depth.txt and/or associations.txt, depth uint16 PNG at
  5000 units per metre (or `depth_scale` in an optional camera.json, which also gives
  fx, fy, cx, cy, width, height; without it Kinect v1 defaults are used and a warning logged).
  Without associations.txt, colour and depth are paired by nearest timestamp (<= 0.02 s).
  Frames listed in the text files whose image files are absent are skipped with a warning
  (excerpts of long sequences keep the full lists). Poses: groundtruth.txt
  (`timestamp tx ty tz qx qy qz qw`, camera-to-world), nearest timestamp within 0.05 s.
- "redwood": Open3D / Redwood reconstruction-system folder: color/ (or image/) *.jpg|*.png,
  depth/ *.png (uint16 millimetres), camera_intrinsic.json (Open3D's column-major
  `intrinsic_matrix`), optional trajectory.log (camera-to-world). Timestamps index / 30 s.
- "7scenes": Microsoft 7-Scenes sequence folder (frame-NNNNNN.color.png|jpg,
  frame-NNNNNN.depth.png in mm with 65535 = invalid, frame-NNNNNN.pose.txt camera-to-world,
  camera-intrinsics.txt) or a scene folder holding exactly one seq-XX subfolder.
  7-Scenes depth is NOT registered to colour: it comes from the Kinect's depth camera
  (fx = fy = 585), the colour from its RGB camera (fx = fy = 525, about 2.5 cm to the side).
  We reproject every depth pixel into the colour camera (z-buffered nearest-pixel splat)
  with the generic Kinect v1 depth-to-colour calibration the 7-Scenes community uses
  (`SEVEN_SCENES_COLOR_FROM_DEPTH`, the LIRIS calibration also used by DSAC*/ACE's
  "calibrated depth"). It is not this device's own calibration (none was published), so
  expect residual misalignment of a few pixels at depth edges. The returned camera is the
  colour camera, and so are the poses: world_from_color = world_from_depth (the file's
  KinectFusion pose, tracked with the depth camera) @ inv(SEVEN_SCENES_COLOR_FROM_DEPTH),
  so fused depth stays consistent (the world frame is the file's).
- "pair": one colour image + one depth image (`open_pair`, or `open_sequence` on a colour
  image whose name holds color/colour/rgb with a partner holding depth, or on a folder
  holding exactly one such pair). Depth encodings: see `DEPTH_ENCODINGS`. NYU raw depth is
  in the depth camera's frame (not registered to colour), like 7-Scenes; it is not
  reprojected here (no calibration ships with the frame).

Bad input raises `DatasetError` (a ValueError) naming the file or folder and what to do.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import overload

import cv2
import numpy as np

from arlight.pipeline.camera import PinholeCamera
from arlight.pipeline.frames import FrameInput
from arlight.pipeline.splat import splat_nearest

log = logging.getLogger(__name__)

#: Depth encodings: name -> what a stored uint16 value means.
DEPTH_ENCODINGS: dict[str, str] = {
    "tum": "uint16, metres * 5000 (TUM RGB-D); 0 and 65535 = missing",
    "mm": "uint16 millimetres (Open3D/Redwood, 7-Scenes, most sensors); 0 and 65535 = missing",
    "sun": "uint16 millimetres bit-rotated by 3 (SUN RGB-D): mm = ((v >> 3) | (v << 13)) & 0xFFFF",
    "nyu": "raw Kinect disparity (NYU Depth v2 PGM, stored little-endian): "
    "metres = 351.3 / (1092.5 - raw); raw 2047 = missing",
}
_UNITS_PER_METRE = {"tum": 5000.0, "mm": 1000.0, "sun": 1000.0}

#: Depth beyond this many metres from NYU raw disparity is treated as missing (Kinect v1 range;
#: the NYU toolbox clamps to 10 m, which would invent depth).
NYU_MAX_DEPTH_M = 10.0

TUM_ASSOCIATION_MAX_DT_S = 0.02
TUM_POSE_MAX_DT_S = 0.05
REDWOOD_FPS = 30.0
SEVEN_SCENES_FPS = 30.0

#: 7-Scenes depth camera defaults (used when camera-intrinsics.txt is absent), 640x480.
SEVEN_SCENES_DEPTH_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
#: 7-Scenes colour camera (focal length as published with the data set), at 640x480.
SEVEN_SCENES_COLOR_FOCAL_PX = 525.0
#: color_from_depth 4x4 (metres): generic Kinect v1 calibration (LIRIS), as used for
#: 7-Scenes' "calibrated depth" in DSAC* and ACE. Depth camera -> colour camera.
SEVEN_SCENES_COLOR_FROM_DEPTH = np.array([
    [9.9996518012567637e-01, 2.6765126468950343e-03, -7.9041012313000904e-03,
     -2.5558943178152542e-02],
    [-2.7409311281316700e-03, 9.9996302803027592e-01, -8.1504520778013286e-03,
     1.0109636268061706e-04],
    [7.8819942130445332e-03, 8.1718328771890631e-03, 9.9993554558014031e-01,
     2.0318321729487039e-03],
    [0.0, 0.0, 0.0, 1.0],
])

_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")
_COLOR_TOKENS = ("color", "colour", "rgb", "image")
_ENCODING_PREFIXES = {"tum": "tum", "sun": "sun", "nyu": "nyu"}

_LOOKED_FOR = (
    "TUM RGB-D (rgb.txt + depth.txt, or associations.txt); "
    "Open3D/Redwood (color/ or image/ and depth/ subfolders); "
    "7-Scenes (frame-NNNNNN.depth.png + frame-NNNNNN.color.png|jpg, or one seq-XX subfolder); "
    "a single colour + depth image pair (one *color*|*rgb* and one *depth* image file)"
)


class DatasetError(ValueError):
    """Recorded RGB-D data that cannot be read; the message names the file and what to do."""


# --------------------------------------------------------------------------- sequence


@dataclass(frozen=True)
class _FrameRecord:
    """Where one frame lives on disk. world_from_cam: (4, 4) or None."""

    color_path: Path
    depth_path: Path
    timestamp_s: float
    world_from_cam: np.ndarray | None = None


@dataclass(frozen=True)
class _Registration:
    """Reproject depth from a separate depth camera into the colour camera."""

    depth_camera: PinholeCamera
    color_from_depth: np.ndarray  # (4, 4), metres


class LazyFrames(Sequence[FrameInput]):
    """Read-only sequence of frames; each access reads (and decodes) the files again."""

    def __init__(self, load: Callable[[int, bool], FrameInput], indices: range) -> None:
        self._load = load
        self._indices = indices

    def __len__(self) -> int:
        return len(self._indices)

    @overload
    def __getitem__(self, index: int) -> FrameInput: ...

    @overload
    def __getitem__(self, index: slice) -> LazyFrames: ...

    def __getitem__(self, index: int | slice) -> FrameInput | LazyFrames:
        if isinstance(index, slice):
            return LazyFrames(self._load, self._indices[index])
        return self._load(self._indices[index], True)  # IndexError past the end

    def __repr__(self) -> str:
        return f"LazyFrames(len={len(self)})"


@dataclass
class RgbdSequence:
    """A recorded RGB-D sequence.

    name: folder (or file) name; camera: intrinsics of the colour image, which the depth is
    registered to; frames: lazy sequence of FrameInput (frame i read on access; len() works);
    format: "tum", "redwood", "7scenes" or "pair"; has_poses: the data set ships camera-to-world
    poses (groundtruth.txt / trajectory.log / every frame's pose.txt; read only when asked
    for); poses_attached: the frames carry them (open_sequence(use_poses=True));
    depth_encoding: how stored depth was decoded; source: the path opened; notes: choices
    made while opening (defaults, skipped frames, registration), also logged.
    """

    name: str
    camera: PinholeCamera
    frames: Sequence[FrameInput]
    format: str
    has_poses: bool
    poses_attached: bool = False
    depth_encoding: str = ""
    source: Path | None = None
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[FrameInput]:
        for i in range(len(self.frames)):
            yield self.frames[i]

    def frame(self, index: int, with_pose: bool = True) -> FrameInput:
        """Frame `index` (negative counts from the end); with_pose=False drops its pose."""
        frame = self.frames[index]
        return frame if with_pose else replace(frame, pose=None)


class _Loader:
    """Reads and decodes the frames of one sequence."""

    def __init__(self, records: list[_FrameRecord], camera: PinholeCamera, encoding: str,
                 units_per_metre: float | None, attach_poses: bool,
                 registration: _Registration | None = None) -> None:
        self.records = records
        self.camera = camera
        self.encoding = encoding
        self.units_per_metre = units_per_metre
        self.attach_poses = attach_poses
        self.registration = registration

    def __call__(self, index: int, with_pose: bool = True) -> FrameInput:
        rec = self.records[index]
        color = read_color(rec.color_path)
        depth_m = read_depth(rec.depth_path, self.encoding, self.units_per_metre)
        h, w = color.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise DatasetError(
                f"{rec.color_path}: colour image is {w}x{h} but the camera is "
                f"{self.camera.width}x{self.camera.height}; fix the intrinsics file or the "
                "images so that they agree")
        if self.registration is not None:
            reg = self.registration
            dh, dw = depth_m.shape
            if (dw, dh) != (reg.depth_camera.width, reg.depth_camera.height):
                raise DatasetError(
                    f"{rec.depth_path}: depth image is {dw}x{dh} but the depth camera is "
                    f"{reg.depth_camera.width}x{reg.depth_camera.height}; all depth images "
                    "of a sequence must have one size")
            depth_m = register_depth(depth_m, reg.depth_camera, self.camera, reg.color_from_depth)
        elif depth_m.shape != (h, w):
            dh, dw = depth_m.shape
            raise DatasetError(
                f"colour {rec.color_path} is {w}x{h} but depth {rec.depth_path} is {dw}x{dh}; "
                "colour and depth must have the same size (register or resize the depth first)")
        pose = None
        if with_pose and self.attach_poses and rec.world_from_cam is not None:
            pose = rec.world_from_cam.copy()
        return FrameInput(color=color, depth=depth_m, timestamp=float(rec.timestamp_s),
                          pose=pose)


def _make_sequence(name: str, fmt: str, source: Path, records: list[_FrameRecord],
                   camera: PinholeCamera, encoding: str, units_per_metre: float | None,
                   has_poses: bool, use_poses: bool, max_frames: int | None,
                   notes: list[str], registration: _Registration | None = None
                   ) -> RgbdSequence:
    if not records:
        raise DatasetError(f"{source}: the sequence has no frames")
    if max_frames is not None:
        records = records[:max_frames]
    loader = _Loader(records, camera, encoding, units_per_metre, use_poses, registration)
    seq = RgbdSequence(name=name, camera=camera, frames=LazyFrames(loader, range(len(records))),
                       format=fmt, has_poses=has_poses, poses_attached=use_poses,
                       depth_encoding=encoding, source=source, notes=notes)
    loader(0)  # read the first frame now: sizes, dtypes and codecs fail here, not later
    return seq


def _note(notes: list[str], message: str, level: int = logging.WARNING) -> None:
    notes.append(message)
    log.log(level, message)


# --------------------------------------------------------------------------- images


def _read_image(path: Path, flags: int, what: str) -> np.ndarray:
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
            "replace it or remove the frame")
    return image


def read_color(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB from an image file (grey is expanded, alpha dropped)."""
    bgr = _read_image(Path(path), cv2.IMREAD_COLOR, "colour image")
    return np.ascontiguousarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))


def read_depth(path: str | Path, encoding: str, units_per_metre: float | None = None
               ) -> np.ndarray:
    """(H, W) float32 metres (0 = missing) from a uint16 depth image in `encoding`.

    units_per_metre overrides the encoding's scale for "tum"/"mm" (e.g. camera.json).
    """
    path = Path(path)
    raw = _read_image(path, cv2.IMREAD_UNCHANGED, "depth image")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        shape = "x".join(str(s) for s in raw.shape)
        raise DatasetError(
            f"{path}: depth must be a single-channel uint16 image, got {raw.dtype} with shape "
            f"{shape}; this is not a depth map in encoding {encoding!r}")
    return decode_depth(raw, encoding, units_per_metre, source=str(path))


def decode_depth(raw: np.ndarray, encoding: str, units_per_metre: float | None = None,
                 source: str = "depth") -> np.ndarray:
    """Metres (H, W) float32, 0 = missing, from stored uint16 depth `raw` (see DEPTH_ENCODINGS)."""
    _check_encoding(encoding)
    if encoding == "nyu":
        return _decode_nyu(raw, source)
    values = raw.astype(np.uint32)
    if encoding == "sun":
        values = ((values >> 3) | (values << 13)) & 0xFFFF
    scale = units_per_metre if units_per_metre is not None else _UNITS_PER_METRE[encoding]
    depth_m = values.astype(np.float32) / np.float32(scale)
    depth_m[values == 0xFFFF] = 0.0  # saturated / invalid marker
    return depth_m


def _decode_nyu(raw: np.ndarray, source: str) -> np.ndarray:
    # NYU's PGMs are little-endian although PGM is big-endian, so a PGM reader returns the
    # bytes swapped. Raw Kinect disparity has 11 bits: pick the byte order that fits.
    swapped = raw.byteswap()
    if int(swapped.max(initial=0)) <= 2047:
        disparity = swapped
    elif int(raw.max(initial=0)) <= 2047:
        disparity = raw  # already converted to the right byte order
    else:
        raise DatasetError(
            f"{source}: values exceed 2047 in either byte order, so this is not raw Kinect "
            "disparity (NYU Depth v2 raw PGM); pick another depth_encoding")
    d = disparity.astype(np.float64)
    with np.errstate(divide="ignore"):
        depth_m = 351.3 / (1092.5 - d)
    bad = (disparity == 2047) | ~np.isfinite(depth_m) | (depth_m <= 0) | (
        depth_m > NYU_MAX_DEPTH_M)
    depth_m[bad] = 0.0
    return depth_m.astype(np.float32)


def _check_encoding(encoding: str) -> None:
    if encoding not in DEPTH_ENCODINGS:
        raise DatasetError(
            f"unknown depth_encoding {encoding!r}; use one of: {', '.join(DEPTH_ENCODINGS)}")


def register_depth(depth_m: np.ndarray, depth_camera: PinholeCamera,
                   color_camera: PinholeCamera, color_from_depth: np.ndarray) -> np.ndarray:
    """Depth (H_c, W_c) float32 metres in the colour camera from depth (H_d, W_d) metres.

    Each valid depth pixel is unprojected with depth_camera, moved by color_from_depth (4x4)
    and splatted to its nearest colour pixel; where several land, the nearest surface wins.
    Colour pixels nothing lands on are 0 (missing).
    """
    h, w = color_camera.height, color_camera.width
    valid = np.isfinite(depth_m) & (depth_m > 0)
    if not valid.any():
        return np.zeros((h, w), np.float32)
    rows, cols = np.nonzero(valid)
    z_d = depth_m[valid].astype(np.float64)
    x_d = (cols - depth_camera.cx) / depth_camera.fx * z_d
    y_d = (rows - depth_camera.cy) / depth_camera.fy * z_d
    # written out per component: (N, 3) @ (3, 3) through BLAS is slower by 10x here
    m = np.asarray(color_from_depth, dtype=np.float64)
    x = m[0, 0] * x_d + m[0, 1] * y_d + m[0, 2] * z_d + m[0, 3]
    y = m[1, 0] * x_d + m[1, 1] * y_d + m[1, 2] * z_d + m[1, 3]
    z = m[2, 0] * x_d + m[2, 1] * y_d + m[2, 2] * z_d + m[2, 3]
    with np.errstate(divide="ignore", invalid="ignore"):  # z <= 0 is dropped by the splat
        u = color_camera.fx * x / z + color_camera.cx
        v = color_camera.fy * y / z + color_camera.cy
    return splat_nearest(u, v, z, w, h)  # the nearest surface wins


# --------------------------------------------------------------------------- poses


def _check_rigid(m: np.ndarray, source: str) -> np.ndarray:
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise DatasetError(f"{source}: pose must be a finite 4x4 matrix, got {m.tolist()}")
    r = m[:3, :3]
    if (not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6)
            or not np.allclose(r.T @ r, np.eye(3), atol=1e-3)
            or abs(np.linalg.det(r) - 1.0) > 1e-3):
        raise DatasetError(
            f"{source}: pose is not a rigid camera-to-world transform (rotation not "
            "orthonormal with det 1, or last row not 0 0 0 1)")
    return m


def quaternion_to_matrix(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """3x3 rotation from a Hamilton unit quaternion (x, y, z, w); normalised first."""
    q = np.array([qx, qy, qz, qw], dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-8:
        raise ValueError(f"quaternion {q.tolist()} has no direction")
    x, y, z, w = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _read_matrix_file(path: Path) -> np.ndarray:
    try:
        m = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot read a 4x4 pose matrix ({exc})") from exc
    return _check_rigid(m, str(path))


# --------------------------------------------------------------------------- public entry


def open_sequence(path: str | Path, *, depth_encoding: str | None = None,
                  use_poses: bool = False, max_frames: int | None = None) -> RgbdSequence:
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
        _check_encoding(depth_encoding)
    if max_frames is not None and max_frames < 1:
        raise DatasetError(f"max_frames must be >= 1, got {max_frames}")
    if not path.exists():
        raise DatasetError(
            f"{path}: no such file or folder; pass a recorded RGB-D sequence folder "
            f"({_LOOKED_FOR})")
    try:
        return _open_detected(path, depth_encoding, use_poses, max_frames)
    except OSError as exc:  # unreadable folders, broken links, permissions
        raise DatasetError(f"{path}: cannot read ({exc}); check the path and its "
                           "permissions") from exc


def _open_detected(path: Path, depth_encoding: str | None, use_poses: bool,
                   max_frames: int | None) -> RgbdSequence:
    if path.is_file():
        color_path, depth_path = _partner_of_color_file(path)
        seq = open_pair(color_path, depth_path, depth_encoding)
        return _pair_checks(seq, use_poses)
    if (path / "associations.txt").is_file() or (path / "rgb.txt").is_file() or (
            path / "depth.txt").is_file():
        return _open_tum(path, depth_encoding, use_poses, max_frames)
    seven = _seven_scenes_folder(path)
    if seven is not None:
        return _open_seven_scenes(seven, depth_encoding, use_poses, max_frames)
    color_dir = _redwood_color_dir(path)
    if color_dir is not None and (path / "depth").is_dir():
        return _open_redwood(path, color_dir, depth_encoding, use_poses, max_frames)
    pairs = _pairs_in_folder(path)
    if len(pairs) == 1:
        seq = open_pair(pairs[0][0], pairs[0][1], depth_encoding)
        return _pair_checks(seq, use_poses)
    if len(pairs) > 1:
        listing = "; ".join(f"{c.name} + {d.name}" for c, d in pairs)
        raise DatasetError(
            f"{path}: holds {len(pairs)} colour + depth pairs ({listing}); pass one colour "
            "image file instead of the folder (its *depth* partner is found beside it)")
    raise DatasetError(f"{path}: not a recognised RGB-D data set. Looked for: {_LOOKED_FOR}")


def open_pair(color_path: str | Path, depth_path: str | Path, depth_encoding: str | None,
              camera: PinholeCamera | None = None) -> RgbdSequence:
    """A one-frame sequence (format "pair", timestamp 0, no pose) from a colour + depth image.

    depth_encoding: one of DEPTH_ENCODINGS; None infers it from a TUM_/SUN_/NYU_ file-name
    prefix (DatasetError when there is none). camera: intrinsics of the colour image; None
    uses Kinect v1 defaults scaled to the image width (with a warning).
    """
    color_path, depth_path = Path(color_path), Path(depth_path)
    notes: list[str] = []
    if depth_encoding is None:
        depth_encoding = _infer_encoding(color_path, depth_path)
        _note(notes, f"depth encoding {depth_encoding!r} inferred from the file name "
                     f"{depth_path.name}; pass depth_encoding to override", logging.INFO)
    _check_encoding(depth_encoding)
    if camera is None:
        color = read_color(color_path)
        h, w = color.shape[:2]
        camera = PinholeCamera.kinect_v1(w, h)
        _note(notes, f"{color_path}: no intrinsics given; using Kinect v1 defaults "
                     f"(fx = fy = {camera.fx:g}, cx = {camera.cx:g}, cy = {camera.cy:g})")
    if depth_encoding == "nyu":
        _note(notes, f"{depth_path}: NYU raw depth is in the depth camera's frame, not "
                     "registered to colour (misaligned by a few pixels)", logging.INFO)
    record = _FrameRecord(color_path, depth_path, 0.0)
    name = _common_prefix_name(color_path, depth_path)
    return _make_sequence(name, "pair", color_path, [record], camera, depth_encoding, None,
                          has_poses=False, use_poses=False, max_frames=None, notes=notes)


def _pair_checks(seq: RgbdSequence, use_poses: bool) -> RgbdSequence:
    if use_poses:
        raise DatasetError(
            f"{seq.source}: a single colour + depth pair has no camera poses; "
            "open it with use_poses=False")
    return seq


def _infer_encoding(color_path: Path, depth_path: Path) -> str:
    for p in (depth_path, color_path):
        match = re.match(r"([A-Za-z]+)[_\-.]", p.name)
        if match and match.group(1).lower() in _ENCODING_PREFIXES:
            return _ENCODING_PREFIXES[match.group(1).lower()]
    described = "; ".join(f"{k}: {v}" for k, v in DEPTH_ENCODINGS.items())
    raise DatasetError(
        f"{depth_path}: cannot tell how this depth image is encoded; pass depth_encoding= one "
        f"of {', '.join(DEPTH_ENCODINGS)} ({described})")


def _common_prefix_name(a: Path, b: Path) -> str:
    prefix = ""
    for x, y in zip(a.stem, b.stem, strict=False):
        if x != y:
            break
        prefix += x
    prefix = prefix.rstrip("_-. ")
    return prefix or a.stem


def _is_image(p: Path) -> bool:
    return p.is_file() and p.suffix.lower() in _IMAGE_EXTS


def _partner_of_color_file(path: Path) -> tuple[Path, Path]:
    """The depth image beside a colour image file: its name with color/colour/rgb -> depth."""
    if not _is_image(path):
        raise DatasetError(
            f"{path}: not an image file ({', '.join(_IMAGE_EXTS)}); pass a sequence folder or "
            "a colour image")
    lower = path.stem.lower()
    for token in _COLOR_TOKENS:
        i = lower.rfind(token)
        if i < 0:
            continue
        stem = path.stem[:i] + "depth" + path.stem[i + len(token):]
        tried = [path.with_name(stem + ext) for ext in (".png", ".pgm", ".tif", ".tiff")]
        for candidate in tried:
            if candidate.is_file():
                return path, candidate
        raise DatasetError(
            f"{path}: found no depth partner (looked for {', '.join(p.name for p in tried)}); "
            "use open_pair(color_path, depth_path, depth_encoding)")
    raise DatasetError(
        f"{path}: a single image is opened as a colour + depth pair, but its name holds none "
        f"of {', '.join(_COLOR_TOKENS)} to find the depth partner by; use "
        "open_pair(color_path, depth_path, depth_encoding)")


def _pairs_in_folder(folder: Path) -> list[tuple[Path, Path]]:
    pairs = []
    for p in sorted(folder.iterdir()):
        if _is_image(p) and any(t in p.stem.lower() for t in _COLOR_TOKENS) and (
                "depth" not in p.stem.lower()):
            try:
                pairs.append(_partner_of_color_file(p))
            except DatasetError:
                continue
    return pairs


# --------------------------------------------------------------------------- TUM


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
    return [(_float_field(f[0], path, n), f[1])
            for n, f in _read_table(path, 2, "timestamp filename")]


def _associate(rgb: list[tuple[float, str]], depth: list[tuple[float, str]], max_dt: float
               ) -> list[tuple[float, str, float, str]]:
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
                "(and optionally depth_scale, units per metre)")
        if not isinstance(data[key], (int, float)) or isinstance(data[key], bool):
            raise DatasetError(f"{path}: {key!r} must be a number, got {data[key]!r}")
        values[key] = data[key]
    try:
        camera = PinholeCamera(int(values["width"]), int(values["height"]), float(values["fx"]),
                               float(values["fy"]), float(values["cx"]), float(values["cy"]))
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}") from exc
    scale = data.get("depth_scale")
    if scale is not None:
        if (not isinstance(scale, (int, float)) or isinstance(scale, bool)
                or not np.isfinite(scale) or scale <= 0):
            raise DatasetError(f"{path}: depth_scale must be a number > 0 (units per metre), "
                               f"got {scale!r}")
        scale = float(scale)
    return camera, scale


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


def _nearest_pose(times: np.ndarray, poses: np.ndarray, t: float, max_dt: float
                  ) -> np.ndarray | None:
    k = int(np.searchsorted(times, t))
    best = None
    for j in (k - 1, k):
        if 0 <= j < len(times) and abs(times[j] - t) <= max_dt:
            if best is None or abs(times[j] - t) < abs(times[best] - t):
                best = j
    return None if best is None else poses[best]


def _open_tum(folder: Path, depth_encoding: str | None, use_poses: bool,
              max_frames: int | None) -> RgbdSequence:
    notes: list[str] = []
    assoc_path = folder / "associations.txt"
    rgb_path, depth_path = folder / "rgb.txt", folder / "depth.txt"
    if assoc_path.is_file():
        rgb_names = {n for _, n in _read_timed_list(rgb_path)} if rgb_path.is_file() else set()
        rows = _read_table(assoc_path, 4, "t_rgb rgb/x.png t_depth depth/x.png")
        pairs = []
        for n, f in rows:
            t1, f1 = _float_field(f[0], assoc_path, n), f[1]
            t2, f2 = _float_field(f[2], assoc_path, n), f[3]
            # TUM's associate.py writes whichever list it was given first: tell them apart
            swapped = (f2 in rgb_names and f1 not in rgb_names) or (
                not rgb_names and "depth" in f1.lower() and "depth" not in f2.lower())
            pairs.append((t2, f2, t1, f1) if swapped else (t1, f1, t2, f2))
        listed_in = assoc_path.name
    else:
        if not (rgb_path.is_file() and depth_path.is_file()):
            have = rgb_path.name if rgb_path.is_file() else depth_path.name
            raise DatasetError(
                f"{folder}: TUM RGB-D layout needs associations.txt or both rgb.txt and "
                f"depth.txt, found only {have}")
        rgb = _read_timed_list(rgb_path)
        depth = _read_timed_list(depth_path)
        n_rgb = len(rgb)
        rgb = [(t, n) for t, n in rgb if (folder / n).is_file()]
        depth = [(t, n) for t, n in depth if (folder / n).is_file()]
        if len(rgb) < n_rgb:
            _note(notes, f"{folder}: {n_rgb - len(rgb)} of {n_rgb} images listed in rgb.txt "
                         "are absent; skipped")
        pairs = _associate(rgb, depth, TUM_ASSOCIATION_MAX_DT_S)
        if rgb and len(pairs) < len(rgb):
            _note(notes, f"{folder}: {len(rgb) - len(pairs)} colour images have no depth "
                         f"image within {TUM_ASSOCIATION_MAX_DT_S} s; skipped")
        listed_in = "rgb.txt/depth.txt"
    n_listed = len(pairs)
    if assoc_path.is_file():
        pairs = [p for p in pairs if (folder / p[1]).is_file() and (folder / p[3]).is_file()]
        if n_listed and len(pairs) < n_listed:
            _note(notes, f"{folder}: {n_listed - len(pairs)} of {n_listed} pairs listed in "
                         f"{listed_in} have absent image files; skipped")
    if not pairs:
        raise DatasetError(
            f"{folder}: empty sequence: no colour + depth pair listed in {listed_in} has both "
            "image files present")
    pairs.sort(key=lambda p: p[0])

    camera_json = folder / "camera.json"
    units = None
    if camera_json.is_file():
        camera, units = _read_camera_json(camera_json)
    else:
        first = read_color(folder / pairs[0][1])
        camera = PinholeCamera.kinect_v1(first.shape[1], first.shape[0])
        _note(notes, f"{folder}: no camera.json; using Kinect v1 default intrinsics "
                     f"(fx = fy = {camera.fx:g}, cx = {camera.cx:g}, cy = {camera.cy:g})")
    encoding = "tum"
    if depth_encoding is not None:
        encoding, units = depth_encoding, None
    elif units is None:
        units = _UNITS_PER_METRE["tum"]

    gt_path = folder / "groundtruth.txt"
    has_poses = gt_path.is_file()
    records = [_FrameRecord(folder / c, folder / d, t) for t, c, _, d in pairs]
    if use_poses:
        if not has_poses:
            raise DatasetError(f"{folder}: use_poses=True but there is no groundtruth.txt; "
                               "open it with use_poses=False (poses are then estimated)")
        times, poses = _read_tum_groundtruth(gt_path)
        with_pose = []
        for rec in records:
            pose = _nearest_pose(times, poses, rec.timestamp_s, TUM_POSE_MAX_DT_S)
            if pose is not None:
                with_pose.append(_FrameRecord(rec.color_path, rec.depth_path,
                                              rec.timestamp_s, pose))
        if len(with_pose) < len(records):
            _note(notes, f"{gt_path}: {len(records) - len(with_pose)} of {len(records)} frames "
                         f"have no pose within {TUM_POSE_MAX_DT_S} s; skipped")
        if not with_pose:
            raise DatasetError(f"{gt_path}: no pose lies within {TUM_POSE_MAX_DT_S} s of any "
                               "frame's timestamp; check that the timestamps share a clock")
        records = with_pose
    return _make_sequence(folder.name, "tum", folder, records, camera, encoding, units,
                          has_poses, use_poses, max_frames, notes)


# --------------------------------------------------------------------------- Redwood / Open3D


def _redwood_color_dir(folder: Path) -> Path | None:
    for name in ("color", "image"):
        if (folder / name).is_dir():
            return folder / name
    return None


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
            "and a 9-value column-major intrinsic_matrix") from exc


def _read_trajectory_log(path: Path) -> list[np.ndarray]:
    """world_from_cam (4, 4) per entry of an Open3D/Redwood trajectory.log."""
    try:
        lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc})") from exc
    if len(lines) % 5:
        raise DatasetError(
            f"{path}: {len(lines)} non-empty lines is not a multiple of 5; each pose is a "
            "header line 'i j k' and 4 rows of a 4x4 matrix")
    poses = []
    for e in range(0, len(lines), 5):
        try:
            m = np.array([[float(x) for x in lines[e + r].split()] for r in range(1, 5)])
        except ValueError as exc:
            raise DatasetError(f"{path}, lines {e + 2}-{e + 5}: {exc}") from exc
        poses.append(_check_rigid(m, f"{path}, lines {e + 2}-{e + 5}"))
    return poses


def _open_redwood(folder: Path, color_dir: Path, depth_encoding: str | None, use_poses: bool,
                  max_frames: int | None) -> RgbdSequence:
    notes: list[str] = []
    depth_dir = folder / "depth"
    colors = sorted(p for p in color_dir.iterdir() if _is_image(p))
    depths = sorted(p for p in depth_dir.iterdir() if _is_image(p))
    if not colors or not depths:
        empty = color_dir if not colors else depth_dir
        raise DatasetError(f"{empty}: empty sequence: no image files in this folder")
    depth_by_stem = {p.stem: p for p in depths}
    if all(c.stem in depth_by_stem for c in colors):
        pairs = [(c, depth_by_stem[c.stem]) for c in colors]
    elif len(colors) == len(depths):
        pairs = list(zip(colors, depths, strict=True))
        _note(notes, f"{folder}: colour and depth file names differ; paired in sorted order",
              logging.INFO)
    else:
        matched = [(c, depth_by_stem[c.stem]) for c in colors if c.stem in depth_by_stem]
        if not matched:
            raise DatasetError(
                f"{folder}: {len(colors)} colour and {len(depths)} depth images share no file "
                "names; name each colour/depth pair alike (00000.jpg + 00000.png)")
        _note(notes, f"{folder}: {len(colors) - len(matched)} colour images have no depth "
                     "image of the same name; skipped")
        pairs = matched
    index_of = {c: i for i, c in enumerate(colors)}
    records = [_FrameRecord(c, d, index_of[c] / REDWOOD_FPS) for c, d in pairs]

    intr = folder / "camera_intrinsic.json"
    if intr.is_file():
        camera = _read_open3d_intrinsics(intr)
    else:
        first = read_color(pairs[0][0])
        camera = PinholeCamera.kinect_v1(first.shape[1], first.shape[0])
        _note(notes, f"{folder}: no camera_intrinsic.json; using Kinect v1 default intrinsics "
                     f"(fx = fy = {camera.fx:g}, cx = {camera.cx:g}, cy = {camera.cy:g})")

    traj = folder / "trajectory.log"
    has_poses = traj.is_file()
    if use_poses:
        if not has_poses:
            raise DatasetError(f"{folder}: use_poses=True but there is no trajectory.log; "
                               "open it with use_poses=False (poses are then estimated)")
        poses = _read_trajectory_log(traj)
        # trajectory.log entries follow the sorted colour images, as Open3D writes them
        if len(poses) != len(colors):
            _note(notes, f"{traj}: {len(poses)} poses for {len(colors)} colour images; frames "
                         "beyond the last pose are skipped")
        records = [_FrameRecord(r.color_path, r.depth_path, r.timestamp_s,
                                poses[index_of[r.color_path]])
                   for r in records if index_of[r.color_path] < len(poses)]
    encoding = depth_encoding or "mm"
    return _make_sequence(folder.name, "redwood", folder, records, camera, encoding, None,
                          has_poses, use_poses, max_frames, notes)


# --------------------------------------------------------------------------- 7-Scenes

_SEVEN_DEPTH = re.compile(r"^frame-(\d+)\.depth\.png$")


def _seven_scenes_folder(folder: Path) -> Path | None:
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
            f"({', '.join(s.name for s in seqs)}); pass one of them, e.g. {seqs[0]}")
    return None


def _open_seven_scenes(folder: Path, depth_encoding: str | None, use_poses: bool,
                       max_frames: int | None) -> RgbdSequence:
    notes: list[str] = []
    frames = []
    missing_color = 0
    for p in folder.glob("frame-*.depth.png"):
        match = _SEVEN_DEPTH.match(p.name)
        if not match:
            continue
        stem = f"frame-{match.group(1)}"
        color = next((folder / f"{stem}.color{ext}" for ext in (".png", ".jpg")
                      if (folder / f"{stem}.color{ext}").is_file()), None)
        if color is None:
            missing_color += 1
            continue
        frames.append((int(match.group(1)), color, p, folder / f"{stem}.pose.txt"))
    frames.sort(key=lambda f: f[0])
    if missing_color:
        _note(notes, f"{folder}: {missing_color} depth images have no "
                     "frame-NNNNNN.color.png|jpg; skipped")
    if not frames:
        raise DatasetError(f"{folder}: empty sequence: no frame-NNNNNN.depth.png has a "
                           "frame-NNNNNN.color.png|jpg beside it")

    intr = folder / "camera-intrinsics.txt"
    if intr.is_file():
        try:
            k = np.loadtxt(intr, dtype=np.float64)
            if k.shape != (3, 3):
                raise ValueError(f"shape {k.shape}, expected 3x3")
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{intr}: cannot read a 3x3 intrinsic matrix ({exc})") from exc
    else:
        k = None
    first_depth = _read_image(frames[0][2], cv2.IMREAD_UNCHANGED, "depth image")
    if k is None:  # defaults are for 640x480: scale them to the depth image
        s = first_depth.shape[1] / 640.0
        k = SEVEN_SCENES_DEPTH_K * np.array([[s, 1.0, s], [1.0, s, s], [1.0, 1.0, 1.0]])
        _note(notes, f"{folder}: no camera-intrinsics.txt; using the 7-Scenes depth camera "
                     "defaults fx = fy = 585, cx = 320, cy = 240 (at 640x480, scaled)")
    first_color = read_color(frames[0][1])
    try:
        depth_camera = PinholeCamera.from_matrix(k, first_depth.shape[1], first_depth.shape[0])
    except ValueError as exc:
        raise DatasetError(f"{intr}: {exc}") from exc
    ch, cw = first_color.shape[:2]
    s = cw / 640.0
    camera = PinholeCamera(cw, ch, SEVEN_SCENES_COLOR_FOCAL_PX * s,
                           SEVEN_SCENES_COLOR_FOCAL_PX * s, cw / 2.0, ch / 2.0)
    registration = _Registration(depth_camera, SEVEN_SCENES_COLOR_FROM_DEPTH)
    _note(notes, "7-Scenes depth is not registered to colour: reprojected into the colour "
                 f"camera (fx = fy = {camera.fx:g}) with a generic Kinect v1 depth-to-colour "
                 "calibration (poses moved to the colour camera too); expect a few pixels of "
                 "residual misalignment at depth edges",
          logging.INFO)

    has_poses = all(f[3].is_file() for f in frames)
    records = [_FrameRecord(c, d, n / SEVEN_SCENES_FPS) for n, c, d, _ in frames]
    if use_poses:
        if not any(f[3].is_file() for f in frames):
            raise DatasetError(f"{folder}: use_poses=True but there are no "
                               "frame-NNNNNN.pose.txt files; open it with use_poses=False")
        if max_frames is not None:  # read only the poses that will be used
            frames, records = frames[:max_frames], records[:max_frames]
        # the files hold world_from_depth-camera; the frames are in the colour camera
        depth_from_color = np.linalg.inv(SEVEN_SCENES_COLOR_FROM_DEPTH)
        kept = [_FrameRecord(r.color_path, r.depth_path, r.timestamp_s,
                             _read_matrix_file(f[3]) @ depth_from_color)
                for r, f in zip(records, frames, strict=True) if f[3].is_file()]
        if len(kept) < len(records):
            _note(notes, f"{folder}: {len(records) - len(kept)} frames have no pose.txt; skipped")
        records = kept
    encoding = depth_encoding or "mm"
    return _make_sequence(folder.name, "7scenes", folder, records, camera, encoding, None,
                          has_poses, use_poses, max_frames, notes, registration)
