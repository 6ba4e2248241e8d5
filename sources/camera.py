"""What the live camera sources share: the spec, their error, lazy imports, clocks, maths.

A camera SOURCE argument is `depthai[:DEVICE_ID]`, `openni2[:URI]`, `realsense[:SERIAL]`, or
a recorded `FILE.oni` (played by the OpenNI2 runtime through the openni2 code path). Each
camera module (`depthai_camera`, `openni2_camera`, `realsense_camera`) imports its library
only when opened, so the base install works without any of them (pyproject extras
`arlight[depthai]`, `arlight[openni2]`, `arlight[realsense]`).

Frames leave a camera as every other source's do (sources/source.py): colour (H, W, 3)
uint8 RGB, depth (H, W) uint16 registered to the colour camera in the device's own units
(`depth_scale` units per metre, 1000 for millimetres), timestamps in host wall-clock
seconds (time.time()'s clock) mapped from the device's clock.
"""

from __future__ import annotations

import importlib
import logging
import math
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # arlight.sources.source opens cameras through this module
    from arlight.sources.source import SourceFrame

log = logging.getLogger(__name__)

CAMERA_KINDS = ("depthai", "openni2", "realsense")

# the pip extra and the Python module of each camera library
EXTRAS = {
    "depthai": ("depthai", "depthai"),
    "openni2": ("openni2", "openni"),
    "realsense": ("realsense", "pyrealsense2"),
}

# what to do where a library is known not to work
UNSUPPORTED = {
    "openni": "the openni binding builds its ctypes enums in a way Python 3.13 "
    "refuses; use Python 3.10-3.12 for OpenNI2 cameras "
    "(docs/guides/cameras.md)"
}

DEVICE_LOST = "camera lost"  # the SourceFrame-free end of a camera stream, as logged


class CameraError(ValueError):
    """A camera that cannot be opened or read; the message names the SOURCE argument, what
    was looked for and what to do (exit code 2 in the CLI)."""


@dataclass(frozen=True)
class CameraSpec:
    """A parsed camera SOURCE: kind (one of CAMERA_KINDS), device (an id, URI, serial or
    .oni path; None = the first one found), size (width, height) in pixels, fps (Hz)."""

    kind: str
    device: str | None = None
    size: tuple[int, int] = (640, 480)
    fps: float = 30.0

    @property
    def text(self) -> str:
        """The SOURCE argument as the user would write it."""
        if self.kind == "openni2" and self.device and self.device.lower().endswith(".oni"):
            return self.device
        return self.kind if self.device is None else f"{self.kind}:{self.device}"


def parse_camera_spec(
    spec: str, size: tuple[int, int] = (640, 480), fps: float = 30.0
) -> CameraSpec | None:
    """The CameraSpec of a SOURCE argument, or None when it names no camera.

    "depthai", "depthai:14442C10D13EABCE00", "openni2", "openni2:FILE.oni", "realsense:8123"
    and a bare "FILE.oni" (played through OpenNI2) are cameras.
    """
    kind, sep, device = spec.partition(":")
    if kind.lower() in CAMERA_KINDS:
        return CameraSpec(kind.lower(), device if sep and device else None, size, fps)
    if spec.lower().endswith(".oni"):
        return CameraSpec("openni2", spec, size, fps)
    return None


def import_library(kind: str) -> ModuleType:
    """The camera library of `kind`, imported now; CameraError naming the extra if absent."""
    extra, module = EXTRAS[kind]
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise CameraError(
            f"SOURCE {kind}: the Python package {module!r} is not installed ({exc}); install "
            f"the camera extra: pip install 'arlight[{extra}]'"
        ) from None
    except Exception as exc:  # installed but broken here (openni on Python >= 3.13)
        version = ".".join(str(v) for v in sys.version_info[:3])
        raise CameraError(
            f"SOURCE {kind}: the Python package {module!r} is installed but cannot be imported "
            f"on Python {version} ({type(exc).__name__}: {exc}); "
            + (
                UNSUPPORTED.get(module)
                or f"reinstall it: pip install --force-reinstall 'arlight[{extra}]'"
            )
        ) from None


def no_device_message(spec: CameraSpec, looked_for: str, found: list[str], permissions: str) -> str:
    """The text of 'no such camera': what was looked for, what was found, what to do."""
    seen = f"found: {', '.join(found)}" if found else "found none"
    wanted = f"device {spec.device!r}" if spec.device else "any device"
    return (
        f"SOURCE {spec.text}: no {spec.kind} camera ({wanted}; looked for {looked_for}; "
        f"{seen}). Plug the camera in (a USB 3 port and cable for 640x480 at 30 Hz), "
        f"check {permissions}, or name another device as SOURCE {spec.kind}:ID"
    )


def open_camera(spec: CameraSpec, max_frames: int | None = None):
    """The Source of a camera (sources/source.py); CameraError if it cannot be opened."""
    if spec.kind == "depthai":
        from arlight.sources.depthai_camera import open_depthai as opener
    elif spec.kind == "openni2":
        from arlight.sources.openni2_camera import open_openni2 as opener
    else:
        from arlight.sources.realsense_camera import open_realsense as opener
    return opener(spec, max_frames=max_frames)


# --------------------------------------------------------------------------- maths


def pinhole_from_fov(
    width: int, height: int, hfov_rad: float, vfov_rad: float
) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in pixels of an image of width x height pixels whose horizontal and
    vertical fields of view are hfov_rad and vfov_rad (radians, full angles).

    The convention of OpenNI2's own coordinate converter: the optical centre is the image
    centre (W / 2, H / 2) and a point at the image edge x = 0 lies tan(hfov / 2) * Z to the
    left, so fx = (W / 2) / tan(hfov / 2).
    """
    for name, angle in (("horizontal", hfov_rad), ("vertical", vfov_rad)):
        if not (math.isfinite(angle) and 0.0 < angle < math.pi):
            raise CameraError(
                f"the camera reports a {name} field of view of {angle!r} rad; expected 0 < fov < pi"
            )
    fx = 0.5 * width / math.tan(0.5 * hfov_rad)
    fy = 0.5 * height / math.tan(0.5 * vfov_rad)
    return fx, fy, 0.5 * width, 0.5 * height


def depth_units_per_metre(metres_per_unit: float) -> float:
    """depth_scale (units per metre) of a sensor whose one depth unit is metres_per_unit
    (RealSense's depth scale, e.g. 0.001 -> 1000.0; 0.0001 -> 10000.0)."""
    if not (math.isfinite(metres_per_unit) and metres_per_unit > 0):
        raise CameraError(
            f"the camera reports a depth unit of {metres_per_unit!r} m; expected a positive number"
        )
    scale = 1.0 / metres_per_unit
    nearest = round(scale)
    return float(nearest) if abs(scale - nearest) < 1e-6 * scale else scale


def gravity_in_camera(accel_imu: np.ndarray, camera_from_imu: np.ndarray) -> np.ndarray | None:
    """The direction of gravity (unit vector, pointing down) in the camera's frame.

    accel_imu: (3,) accelerometer reading in the IMU's frame, m/s^2; at rest it measures the
    support's reaction, which points up, so gravity is its opposite. camera_from_imu: (3, 3)
    rotation or (4, 4) transform from the IMU's axes to the camera's (OpenCV: x right, y
    down, z forward). None for a reading too far from 1 g (the device is accelerating).
    """
    a = np.asarray(accel_imu, np.float64).reshape(3)
    norm = float(np.linalg.norm(a))
    if not math.isfinite(norm) or not 0.7 * 9.80665 < norm < 1.3 * 9.80665:
        return None
    rotation = np.asarray(camera_from_imu, np.float64)[:3, :3]
    down = rotation @ (-a / norm)
    return down / np.linalg.norm(down)


class DeviceClock:
    """Maps a device's clock to host wall time (time.time()'s clock, seconds).

    host = device + offset. live: the offset is the smallest (receive time - device time)
    seen so far, the frame that came with the least delay, so transport jitter does not
    enter the timestamps; a device clock that jumps backwards (a reset, a file looping)
    starts over. fixed (files): the offset of the first frame, so a recording keeps its own
    spacing however fast it is read.
    """

    def __init__(self, live: bool = True):
        self.live = live
        self.offset_s: float | None = None
        self._last_device_s: float | None = None

    def to_host(self, device_s: float, received_s: float | None = None) -> float:
        received_s = time.time() if received_s is None else received_s
        candidate = received_s - device_s
        restarted = self._last_device_s is not None and device_s < self._last_device_s
        if self.offset_s is None or restarted or (self.live and candidate < self.offset_s):
            self.offset_s = candidate
        self._last_device_s = device_s
        return device_s + self.offset_s


def monotonic_to_wall_offset() -> float:
    """time.time() - time.monotonic(): adds to a host steady-clock time (depthai's synced
    timestamps, std::chrono::steady_clock = CLOCK_MONOTONIC on Linux) to give wall time."""
    return time.time() - time.monotonic()


# --------------------------------------------------------------------------- streams


@dataclass
class FrameCounter:
    """Camera frames the client did not take in time (gaps in the device's sequence
    numbers): the device or its queue dropped them. Reported when the stream ends."""

    skipped: int = 0
    _last: int | None = field(default=None, repr=False)

    def see(self, sequence_number: int) -> None:
        if self._last is not None and sequence_number > self._last + 1:
            self.skipped += sequence_number - self._last - 1
        self._last = sequence_number


def camera_frames(
    spec: CameraSpec,
    read: Callable[[], SourceFrame | None],
    close: Callable[[], None],
    lost_errors: tuple[type[BaseException], ...],
    max_frames: int | None,
    counter: FrameCounter,
) -> Iterator[SourceFrame]:
    """The frames `read()` returns until max_frames, the end of a file (read() -> None) or
    the device going away (one of lost_errors raised): then the stream ends cleanly, with a
    warning saying why, and `close()` releases the device. The frames already yielded are
    the caller's to deliver (lossless: every one of them gets its Result)."""
    n = 0
    try:
        while max_frames is None or n < max_frames:
            try:
                frame = read()
            except lost_errors as exc:
                log.warning(
                    "SOURCE %s: %s after %d frame(s) (%s); the stream ends here, the "
                    "frames already sent are delivered",
                    spec.text,
                    DEVICE_LOST,
                    n,
                    str(exc).strip() or type(exc).__name__,
                )
                return
            if frame is None:
                log.info("SOURCE %s: end of recording after %d frame(s)", spec.text, n)
                return
            n += 1
            yield frame
    finally:
        if counter.skipped:
            log.warning(
                "SOURCE %s: %d camera frame(s) were skipped (not taken in time: in "
                "lossless mode the server sets the pace)",
                spec.text,
                counter.skipped,
            )
        try:
            close()
        except Exception as exc:  # a device already gone may refuse to stop
            log.warning("SOURCE %s: closing the camera: %s", spec.text, exc)


def camera_stream(
    spec: CameraSpec,
    read: Callable[[], SourceFrame | None],
    close: Callable[[], None],
    lost_errors: tuple[type[BaseException], ...],
    max_frames: int | None,
    counter: FrameCounter,
) -> Callable[[], Iterator[SourceFrame]]:
    """A camera Source's `frames`: `camera_frames` the first time it is called; a second call
    (a device streams once) is a CameraError saying there is no --loop."""
    started = False

    def frames() -> Iterator[SourceFrame]:
        nonlocal started
        if started:
            raise CameraError(f"SOURCE {spec.text}: a camera streams once (no --loop)")
        started = True
        return camera_frames(spec, read, close, lost_errors, max_frames, counter)

    return frames
