"""arlight's frames and Results as Foxglove messages (protocols/SPEC.md section 7).

One job: turn what travels on arlight's wire into the messages Foxglove's panels know, built
with Foxglove's own schema classes (`foxglove.messages`, from the `foxglove-sdk` package;
protobuf on the wire and in MCAP). The sinks that write or serve them are in
`client/foxglove_sinks.py`.

Frames of reference (Foxglove `frame_id`s):
- `camera`: the camera's optical frame, OpenCV axes (x right, y down, z forward), which is
  also Foxglove's image frame convention;
- `world`: arlight's world frame (the first camera's frame unless the source gives poses);
  `/tf` carries world_from_cam as a FrameTransform parent `world`, child `camera`.

Topics:

- `/camera/color` (from Frames): `foxglove.CompressedImage` (the JPEG/PNG as sent), or
  `RawImage` `rgb8` for raw colour;
- `/camera/depth` (Frames): `foxglove.RawImage` `16UC1` in the sensor's units, channel
  metadata `depth_scale` (units per metre);
- `/camera/calibration` (the Hello's): `foxglove.CameraCalibration` (R = I, P = [K | 0]);
- `/tf` (the Frame's or the Result's pose): `foxglove.FrameTransform` world -> camera;
- `/arlight/composite` (Results): `foxglove.CompressedImage` (JPEG);
- `/arlight/light` (Results): `foxglove.SceneUpdate`, an arrow towards the light, spheres;
- `/arlight/lighting` (Results): JSON, JSON Schema `arlight.Lighting`: SH, dominant
  direction, confidence, per-stage timings, latencies.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import cv2
import numpy as np
import numpy.typing as npt
from foxglove import messages as fm

COLOR_TOPIC = "/camera/color"
DEPTH_TOPIC = "/camera/depth"
CALIBRATION_TOPIC = "/camera/calibration"
TF_TOPIC = "/tf"
COMPOSITE_TOPIC = "/arlight/composite"
LIGHT_TOPIC = "/arlight/light"
LIGHTING_TOPIC = "/arlight/lighting"
CAMERA_FRAME = "camera"
WORLD_FRAME = "world"
# the light marker: a sphere this far in front of the first camera (world z), metres, and an
# arrow from it towards the light
MARKER_CENTRE_M = (0.0, 0.0, 1.0)
MARKER_RADIUS_M = 0.15
ARROW_LENGTH_M = 0.6

_NUMBERS = {"type": "array", "items": {"type": "number"}}
LIGHTING_SCHEMA = {
    "title": "arlight.Lighting",
    "description": "the light arlight estimated for one frame (docs/reference/output-record.md)",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "description": "the frame's capture time",
            "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
        },
        "frame": {"type": "integer", "description": "the frame's seq"},
        "sh": {
            **_NUMBERS,
            "description": "radiance SH, luminance, world frame, index "
            "l(l+1)+m, no Condon-Shortley phase",
        },
        "sh_camera": {**_NUMBERS, "description": "the same light in the camera frame"},
        "dominant_direction_world": {**_NUMBERS, "description": "unit vector towards the light"},
        "dominant_direction_camera": {**_NUMBERS, "description": "unit, OpenCV camera axes"},
        "intensity": {"type": "number"},
        "confidence": {
            "type": "object",
            "description": "samples, condition_number, bands_estimated, value (0..1), reason",
        },
        "timings_ms": {
            "type": "object",
            "description": "per pipeline stage, milliseconds",
            "additionalProperties": {"type": "number"},
        },
        "pipeline_ms": {"type": "number", "description": "sum of timings_ms"},
        "in_server_ms": {"type": "number", "description": "server receive -> finish"},
        "end_to_end_ms": {
            "type": ["number", "null"],
            "description": "capture timestamp -> display receive",
        },
        "frames_dropped": {"type": "integer"},
        "compact_sources": {
            "type": "array",
            "description": "present when a compact source (a sun, a lamp) was kept: "
            "direction_world, direction_camera, intensity, rgb, angular_radius_deg, share "
            "(protocols/SPEC.md, result: compact sources)",
            "items": {"type": "object"},
        },
    },
}


def timestamp(seconds: float) -> fm.Timestamp:
    """A Foxglove Timestamp of a time in seconds (float64, any epoch >= 0); whole seconds
    split off first, so that nanoseconds survive at Unix-epoch magnitudes."""
    whole = math.floor(float(seconds))
    nsec = int(round((float(seconds) - whole) * 1e9))
    if nsec >= 1_000_000_000:
        whole, nsec = whole + 1, nsec - 1_000_000_000
    return fm.Timestamp(sec=int(whole), nsec=nsec)


def quaternion(rotation: np.ndarray) -> fm.Quaternion:
    """The unit quaternion (x, y, z, w) of a 3x3 rotation matrix (Shepperd's method)."""
    r = np.asarray(rotation, dtype=np.float64)
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s
    n = math.sqrt(sum(c * c for c in q)) or 1.0
    return fm.Quaternion(x=q[0] / n, y=q[1] / n, z=q[2] / n, w=q[3] / n)


def x_axis_to(direction: npt.ArrayLike) -> fm.Quaternion:
    """The rotation taking +x onto `direction` (Foxglove arrows point along their +x)."""
    d = np.asarray(direction, dtype=np.float64)
    norm = float(np.linalg.norm(d))
    if not np.isfinite(norm) or norm < 1e-12:
        return fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    d = d / norm
    cos = float(np.clip(d[0], -1.0, 1.0))
    if cos < -1.0 + 1e-9:  # opposite: half a turn about z
        return fm.Quaternion(x=0.0, y=0.0, z=1.0, w=0.0)
    axis = np.array([0.0, -d[2], d[1]])  # x cross d
    half = math.acos(cos) / 2
    axis_norm = float(np.linalg.norm(axis))
    axis = axis / axis_norm if axis_norm > 1e-12 else np.array([0.0, 0.0, 1.0])
    s = math.sin(half)
    return fm.Quaternion(x=axis[0] * s, y=axis[1] * s, z=axis[2] * s, w=math.cos(half))


def color_image(
    encoded: tuple[str, bytes] | None, color: np.ndarray, stamp_s: float
) -> fm.CompressedImage | fm.RawImage:
    """The colour of a Frame: its JPEG/PNG bytes as sent (`encoded` = (format, bytes), from
    client.connection.encoded_image) as a CompressedImage, or (raw colour: encoded None) the
    decoded (H, W, 3) uint8 RGB array as RawImage rgb8."""
    if encoded is not None:
        return fm.CompressedImage(
            timestamp=timestamp(stamp_s), frame_id=CAMERA_FRAME, data=encoded[1], format=encoded[0]
        )
    return raw_rgb(color, stamp_s)


def raw_rgb(color: np.ndarray, stamp_s: float) -> fm.RawImage:
    """(H, W, 3) uint8 RGB as a RawImage rgb8 in the camera frame."""
    rgb = np.ascontiguousarray(color, dtype=np.uint8)
    h, w = rgb.shape[:2]
    return fm.RawImage(
        timestamp=timestamp(stamp_s),
        frame_id=CAMERA_FRAME,
        width=w,
        height=h,
        encoding="rgb8",
        step=3 * w,
        data=rgb.tobytes(),
    )


def depth_image(depth: np.ndarray, stamp_s: float) -> fm.RawImage:
    """(H, W) uint16 depth in the sensor's units (the session's depth_scale units per metre;
    0 = missing) as a RawImage 16UC1, little-endian, in the camera frame."""
    d = np.ascontiguousarray(depth, dtype="<u2")
    h, w = d.shape
    return fm.RawImage(
        timestamp=timestamp(stamp_s),
        frame_id=CAMERA_FRAME,
        width=w,
        height=h,
        encoding="16UC1",
        step=2 * w,
        data=d.tobytes(),
    )


def camera_calibration(calibration, stamp_s: float) -> fm.CameraCalibration:
    """A protocols CameraCalibration (pixels) as Foxglove's: K, D, R = I, P = [K | 0]."""
    c = calibration
    k = [c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0]
    p = [c.fx, 0.0, c.cx, 0.0, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return fm.CameraCalibration(
        timestamp=timestamp(stamp_s),
        frame_id=CAMERA_FRAME,
        width=int(c.width),
        height=int(c.height),
        distortion_model=c.distortion_model or "plumb_bob",
        D=[float(x) for x in c.D] or [0.0] * 5,
        K=k,
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=p,
    )


def camera_transform(world_from_cam: np.ndarray, stamp_s: float) -> fm.FrameTransform:
    """The camera pose (4x4 camera-to-world, metres) as the transform world -> camera."""
    pose = np.asarray(world_from_cam, dtype=np.float64)
    t = pose[:3, 3]
    return fm.FrameTransform(
        timestamp=timestamp(stamp_s),
        parent_frame_id=WORLD_FRAME,
        child_frame_id=CAMERA_FRAME,
        translation=fm.Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        rotation=quaternion(pose[:3, :3]),
    )


def composite_image(
    composite: np.ndarray,
    stamp_s: float,
    quality: int = 90,
    encoded: tuple[str, bytes] | None = None,
) -> fm.CompressedImage:
    """A Result's composite as a CompressedImage: its JPEG/PNG bytes as received
    (`encoded`, from client.connection.encoded_image), else the (H, W, 3) uint8 RGB array
    encoded as JPEG."""
    if encoded is not None:
        return fm.CompressedImage(
            timestamp=timestamp(stamp_s), frame_id=CAMERA_FRAME, data=encoded[1], format=encoded[0]
        )
    bgr = cv2.cvtColor(np.ascontiguousarray(composite, dtype=np.uint8), cv2.COLOR_RGB2BGR)
    ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("OpenCV could not encode the composite as JPEG")
    return fm.CompressedImage(
        timestamp=timestamp(stamp_s), frame_id=CAMERA_FRAME, data=jpeg.tobytes(), format="jpeg"
    )


def light_scene(
    direction_world: Sequence[float], confidence: float, stamp_s: float
) -> fm.SceneUpdate:
    """The estimated light in 3D (world frame): a grey sphere in front of the first camera, an
    arrow from it towards the light (brighter the more confident) and a small yellow sphere
    where the arrow ends, standing for the light."""
    d = np.asarray(direction_world, dtype=np.float64)
    n = float(np.linalg.norm(d))
    d = d / n if np.isfinite(n) and n > 1e-12 else np.zeros(3)
    c = np.asarray(MARKER_CENTRE_M)
    tip = c + d * (MARKER_RADIUS_M + ARROW_LENGTH_M)
    level = float(np.clip(confidence, 0.0, 1.0))
    stamp = timestamp(stamp_s)

    def point(p) -> fm.Vector3:
        return fm.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2]))

    identity = fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    entity = fm.SceneEntity(
        timestamp=stamp,
        frame_id=WORLD_FRAME,
        id="light",
        frame_locked=True,
        arrows=[
            fm.ArrowPrimitive(
                pose=fm.Pose(position=point(c + d * MARKER_RADIUS_M), orientation=x_axis_to(d)),
                shaft_length=ARROW_LENGTH_M * 0.75,
                shaft_diameter=0.03,
                head_length=ARROW_LENGTH_M * 0.25,
                head_diameter=0.08,
                color=fm.Color(r=1.0, g=0.6 + 0.4 * level, b=0.1, a=0.4 + 0.6 * level),
            )
        ],
        spheres=[
            fm.SpherePrimitive(
                pose=fm.Pose(position=point(c), orientation=identity),
                size=point([2 * MARKER_RADIUS_M] * 3),
                color=fm.Color(r=0.8, g=0.8, b=0.8, a=1.0),
            ),
            fm.SpherePrimitive(
                pose=fm.Pose(position=point(tip), orientation=identity),
                size=point([0.08] * 3),
                color=fm.Color(r=1.0, g=0.9, b=0.2, a=1.0),
            ),
        ],
    )
    return fm.SceneUpdate(entities=[entity])


def lighting_message(record: Mapping) -> dict:
    """The JSON lighting message of one Result, from its received record
    (protocols.received_record); keys as LIGHTING_SCHEMA."""
    stamp_s = float(record["timestamp"])
    sec = math.floor(stamp_s)
    nsec = min(int(round((stamp_s - sec) * 1e9)), 999_999_999)
    keys = (
        "sh",
        "sh_camera",
        "dominant_direction_world",
        "dominant_direction_camera",
        "intensity",
        "confidence",
        "timings_ms",
        "pipeline_ms",
        "in_server_ms",
        "end_to_end_ms",
        "frames_dropped",
    )
    return _finite(
        {
            "timestamp": {"sec": int(sec), "nsec": nsec},
            "frame": record["frame"],
            **{k: record.get(k) for k in keys},
            # only where one was kept (absent, not null, as in the Result)
            **(
                {"compact_sources": record["compact_sources"]}
                if record.get("compact_sources")
                else {}
            ),
        }
    )


def _finite(value):
    """value with every non-finite float (inf condition numbers, NaN) as None: strict JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value
