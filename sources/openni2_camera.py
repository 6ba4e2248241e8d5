"""OpenNI2 cameras (PrimeSense, Asus Xtion, Orbbec Astra, Kinect through a driver) and
recorded `.oni` files, through the OpenNI2 runtime (Debian `libopenni2-0`) and the
`openni` binding (pip extra `arlight[openni2]`; docs/guides/cameras.md says why this binding).

`open_openni2(spec)` opens `openni2` (the first device), `openni2:URI` (a device URI as
`Device.enumerate_uris()` lists them, or an .oni file) or `FILE.oni`, and returns a Source:
depth registered to colour (image registration DEPTH_TO_COLOR) where the device supports it,
mirroring off, depth and colour synchronised, intrinsics from the colour stream's fields of
view (`pinhole_from_fov`), timestamps from the device's microsecond clock mapped to host wall
time. A file plays through the same path, frame by frame (no repeat), and ends the stream.
"""

from __future__ import annotations

import atexit
import ctypes.util
import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from arlight.protocols import CameraCalibration
from arlight.sources.camera import (
    CameraError,
    CameraSpec,
    DeviceClock,
    FrameCounter,
    camera_stream,
    import_library,
    no_device_message,
    pinhole_from_fov,
)
from arlight.sources.source import Source, SourceFrame

log = logging.getLogger(__name__)

# where Debian/Ubuntu put the runtime (libopenni2-0 ships only the versioned name)
SYSTEM_LIBRARY_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib/arm-linux-gnueabihf",
    "/usr/lib",
    "/usr/local/lib",
)
LIBRARY_NAMES = ("libOpenNI2.so", "libOpenNI2.so.0")

# depth pixel format name -> depth_scale (units per metre)
DEPTH_FORMATS = {"ONI_PIXEL_FORMAT_DEPTH_1_MM": 1000.0, "ONI_PIXEL_FORMAT_DEPTH_100_UM": 10000.0}
COLOR_FORMATS = ("ONI_PIXEL_FORMAT_RGB888", "ONI_PIXEL_FORMAT_YUYV", "ONI_PIXEL_FORMAT_YUV422")

# what a device that reports no field of view is assumed to have (PS1080-class sensors,
# about 58 x 45 degrees); used with a note, never silently
NOMINAL_FOV_DEG = (58.0, 45.0)

READ_TIMEOUT_S = 2.0  # a live device silent this long is gone
DUMMY_URIS = ("Dummy", "Oz", "PingPong")  # the runtime's own test driver (DummyDevice)
DUMMY_STOP_GRACE_S = 0.5
FILE_CLOSE_GRACE_S = 0.2
PERMISSIONS = (
    "the udev rules (Debian's libopenni2-0 installs /lib/udev/rules.d/"
    "60-libopenni2-0.rules; then replug) or run as a user in the plugdev group"
)


def find_runtime() -> str | None:
    """The path of libOpenNI2 to load: $OPENNI2_REDIST64 / $OPENNI2_REDIST first, then the
    system's (ldconfig, then the usual folders); None if there is none."""
    dirs = [os.environ[v] for v in ("OPENNI2_REDIST64", "OPENNI2_REDIST") if os.environ.get(v)]
    dirs += list(SYSTEM_LIBRARY_DIRS)
    for d in dirs:
        for name in LIBRARY_NAMES:
            path = Path(d) / name
            if path.is_file():
                return str(path)
    found = ctypes.util.find_library("OpenNI2")
    return found if found and os.path.isabs(found) else None


def initialize():
    """The `openni.openni2` module with the runtime initialised (once per process).

    The binding's own initialize() looks only for the unversioned libOpenNI2.so (a -dev
    package's link); the runtime found by find_runtime() is loaded explicitly instead.
    """
    import_library("openni2")
    from openni import _openni2 as c_api
    from openni import openni2

    if openni2.is_initialized():
        return openni2
    path = find_runtime()
    if path is None:
        raise CameraError(
            "SOURCE openni2: the OpenNI2 runtime (libOpenNI2.so) is not "
            "installed; on Debian/Ubuntu: apt-get install libopenni2-0 (or set "
            "OPENNI2_REDIST64 to the folder of a vendor's OpenNI2 redist)"
        )
    try:
        c_api.load_dll(path)
        openni2.loaded_dll_directory = os.path.dirname(path)
        openni2.initialize()
    except Exception as exc:  # the binding raises its own InitializationError or OSError
        raise CameraError(
            f"SOURCE openni2: the OpenNI2 runtime {path} cannot be initialised: {exc}"
        ) from None
    return openni2


def depth_from_buffer(buffer, width: int, height: int, stride_bytes: int) -> np.ndarray:
    """(H, W) uint16 depth, a copy, from a frame buffer of rows stride_bytes apart."""
    data = np.frombuffer(buffer, np.uint8)
    if stride_bytes < 2 * width or data.size < stride_bytes * (height - 1) + 2 * width:
        raise CameraError(
            f"a {width}x{height} depth frame with a stride of {stride_bytes} "
            f"bytes needs at least {stride_bytes * (height - 1) + 2 * width} "
            f"bytes, the frame has {data.size}"
        )
    rows = np.lib.stride_tricks.as_strided(data, (height, 2 * width), (stride_bytes, 1))
    return np.ascontiguousarray(rows).view("<u2").astype(np.uint16, copy=False)


def color_from_buffer(
    buffer, width: int, height: int, stride_bytes: int, pixel_format: str
) -> np.ndarray:
    """(H, W, 3) uint8 RGB, a copy, from an RGB888, YUYV or YUV422 (UYVY) frame buffer."""
    import cv2

    bytes_per_pixel = 3 if pixel_format == "ONI_PIXEL_FORMAT_RGB888" else 2
    if pixel_format not in COLOR_FORMATS:
        raise CameraError(
            f"colour pixel format {pixel_format} is not supported; expected "
            f"one of {', '.join(COLOR_FORMATS)}"
        )
    data = np.frombuffer(buffer, np.uint8)
    row = bytes_per_pixel * width
    if stride_bytes < row or data.size < stride_bytes * (height - 1) + row:
        raise CameraError(
            f"a {width}x{height} {pixel_format} frame with a stride of "
            f"{stride_bytes} bytes is larger than its {data.size} bytes"
        )
    rows = np.ascontiguousarray(
        np.lib.stride_tricks.as_strided(data, (height, row), (stride_bytes, 1))
    )
    if bytes_per_pixel == 3:
        return rows.reshape(height, width, 3)
    code = (
        cv2.COLOR_YUV2RGB_YUYV
        if pixel_format == "ONI_PIXEL_FORMAT_YUYV"
        else cv2.COLOR_YUV2RGB_UYVY
    )
    return cv2.cvtColor(rows.reshape(height, width, 2), code)


def _format_name(pixel_format) -> str:
    """ "ONI_PIXEL_FORMAT_RGB888" for the binding's enum value (a ctypes CEnum) or an int."""
    values = getattr(type(pixel_format), "_values_", None)
    if values is not None:
        return values.get(int(pixel_format), str(int(pixel_format)))
    return str(pixel_format)


def _mode_text(mode) -> str:
    return (
        f"{mode.resolutionX}x{mode.resolutionY}@{mode.fps} "
        f"{_format_name(mode.pixelFormat).replace('ONI_PIXEL_FORMAT_', '')}"
    )


def choose_mode(
    modes: list, size: tuple[int, int], fps: float, formats, what: str, source: str = "openni2"
):
    """The video mode among `modes` with this size, frame rate and one of `formats` (in
    their order of preference); CameraError listing the modes there are."""
    for fmt in formats:
        for mode in modes:
            if (
                (mode.resolutionX, mode.resolutionY) == tuple(size)
                and abs(mode.fps - fps) < 0.5
                and _format_name(mode.pixelFormat) == fmt
            ):
                return mode
    listed = ", ".join(_mode_text(m) for m in modes) or "none"
    raise CameraError(
        f"SOURCE {source}: the {what} stream has no {size[0]}x{size[1]} mode at "
        f"{fps:g} Hz in "
        f"a supported format; its modes: {listed}; choose one with --size WxH "
        "and --fps F"
    )


class _OpenNI2Camera:
    """One opened device (or file) with its depth and colour streams started."""

    def __init__(self, openni2, spec: CameraSpec):
        self.openni2 = openni2
        self.spec = spec
        self.notes: list[str] = []
        self.device = self._open_device()
        self.is_file = bool(self.device.is_file())
        # the depth and colour streams (openni2.VideoStream: the binding has no types) once
        # set up, None after close
        self.depth: Any = None
        self.color: Any = None
        self.started = False  # the streams start with the first read, not at open
        self.fps = spec.fps
        self.frames_read = 0
        self.clock = DeviceClock(live=not self.is_file)
        self.counter = FrameCounter()
        try:
            self._setup()
        except Exception:
            self.close()
            raise

    def _open_device(self):
        openni2, spec = self.openni2, self.spec
        uri = spec.device
        if uri is not None and uri.lower().endswith(".oni"):
            if not Path(uri).is_file():
                raise CameraError(f"SOURCE {spec.text}: no such .oni file")
        else:
            uris = [u.decode(errors="replace") for u in openni2.Device.enumerate_uris()]
            if uri is None and not uris:
                raise CameraError(
                    no_device_message(spec, "OpenNI2 devices on USB", uris, PERMISSIONS)
                )
        try:
            return openni2.Device(None if uri is None else uri.encode())
        except Exception as exc:  # OpenNIError: no such URI, busy, no permission
            if uri is not None and uri.lower().endswith(".oni"):
                raise CameraError(
                    f"SOURCE {spec.text}: the OpenNI2 runtime cannot play this file: {exc}"
                ) from None
            raise CameraError(
                no_device_message(spec, f"OpenNI2 device URIs ({exc})", uris, PERMISSIONS)
            ) from None

    def _setup(self) -> None:
        openni2, spec, device = self.openni2, self.spec, self.device
        if not device.has_sensor(openni2.SENSOR_DEPTH) or not device.has_sensor(
            openni2.SENSOR_COLOR
        ):
            raise CameraError(
                f"SOURCE {spec.text}: the device needs a depth and a colour "
                "sensor (IR-only devices are not RGB-D)"
            )
        self.depth = device.create_depth_stream()
        self.color = device.create_color_stream()
        if self.is_file:
            device.playback.set_repeat_enabled(False)
            self.frames_in_file = self.depth.get_number_of_frames()
        else:
            self.frames_in_file = None
            for stream, formats, what in (
                (self.depth, tuple(DEPTH_FORMATS), "depth"),
                (self.color, COLOR_FORMATS, "colour"),
            ):
                modes = stream.get_sensor_info().videoModes
                mode = choose_mode(modes, spec.size, spec.fps, formats, what, spec.text)
                current = stream.get_video_mode()
                if _mode_text(current) != _mode_text(mode):
                    stream.set_video_mode(mode)
        depth_mode, color_mode = self.depth.get_video_mode(), self.color.get_video_mode()
        self.width, self.height = color_mode.resolutionX, color_mode.resolutionY
        if (depth_mode.resolutionX, depth_mode.resolutionY) != (self.width, self.height):
            raise CameraError(
                f"SOURCE {spec.text}: depth {_mode_text(depth_mode)} and colour "
                f"{_mode_text(color_mode)} differ in size; registration needs "
                "one size (--size WxH)"
            )
        depth_format = _format_name(depth_mode.pixelFormat)
        if depth_format not in DEPTH_FORMATS:
            raise CameraError(
                f"SOURCE {spec.text}: depth pixel format {depth_format}; "
                f"supported: {', '.join(DEPTH_FORMATS)}"
            )
        self.depth_scale = DEPTH_FORMATS[depth_format]
        self.color_format = _format_name(color_mode.pixelFormat)
        self.fps = float(color_mode.fps or spec.fps)
        self.registered = self._register()
        for stream, what in ((self.depth, "depth"), (self.color, "colour")):
            self._try(
                lambda s=stream: s.set_mirroring_enabled(False),
                f"mirroring of the {what} stream cannot be switched off",
            )
        self._try(
            lambda: device.set_depth_color_sync_enabled(True),
            "depth/colour frame sync cannot be enabled",
        )
        self.fx, self.fy, self.cx, self.cy = self._intrinsics()

    def _try(self, action, note: str) -> bool:
        try:
            action()
            return True
        except Exception as exc:  # OpenNIError: the driver does not implement it
            if not self.is_file:
                self.notes.append(f"{note} ({exc})")
            return False

    def _register(self) -> bool:
        openni2, device = self.openni2, self.device
        if self.is_file:
            self.notes.append("an .oni recording keeps the registration it was recorded with")
            return False
        mode = openni2.IMAGE_REGISTRATION_DEPTH_TO_COLOR
        if device.is_image_registration_mode_supported(mode) and self._try(
            lambda: device.set_image_registration_mode(mode), "depth-to-colour registration failed"
        ):
            return True
        self.notes.append(
            "the device cannot register depth to colour: depth stays in the "
            "depth camera's geometry and the colour image is not aligned to it"
        )
        return False

    def _intrinsics(self) -> tuple[float, float, float, float]:
        """From the fields of view of the stream whose geometry the depth image has."""
        stream = self.color if self.registered or self.is_file else self.depth
        try:
            hfov, vfov = stream.get_horizontal_fov(), stream.get_vertical_fov()
        except Exception as exc:  # OpenNIError: not reported by this driver / file
            hfov, vfov = (math.radians(a) for a in NOMINAL_FOV_DEG)
            self.notes.append(
                f"the device reports no field of view ({exc}); the intrinsics "
                f"assume {NOMINAL_FOV_DEG[0]:g} x {NOMINAL_FOV_DEG[1]:g} degrees"
            )
        return pinhole_from_fov(self.width, self.height, hfov, vfov)

    def read(self) -> SourceFrame | None:
        """The next pair, or None at the end of a file; TimeoutError if a device went quiet."""
        if not self.started:
            self.depth.start()
            self.color.start()
            self.started = True
        pair = []
        for stream, what in ((self.depth, "depth"), (self.color, "colour")):
            if self.openni2.wait_for_any_stream([stream], READ_TIMEOUT_S) is None:
                if self.is_file and (
                    not self.frames_in_file or self.frames_read >= self.frames_in_file
                ):
                    return None
                if self.is_file:
                    raise TimeoutError(
                        f"the OpenNI2 player gave {self.frames_read} of the "
                        f"file's {self.frames_in_file} frames, then no {what} "
                        f"frame for {READ_TIMEOUT_S:g} s"
                    )
                raise TimeoutError(f"no {what} frame for {READ_TIMEOUT_S:g} s")
            pair.append(stream.read_frame())
        d, c = pair
        self.counter.see(int(d.frameIndex))
        depth = depth_from_buffer(d.get_buffer_as_uint8(), d.width, d.height, d.stride)
        color = color_from_buffer(
            c.get_buffer_as_uint8(), c.width, c.height, c.stride, self.color_format
        )
        stamp = self.clock.to_host(d.timestamp * 1e-6)
        self.frames_read += 1
        return SourceFrame(stamp, color, depth)

    def close(self) -> None:
        """Streams stopped, then destroyed, then the device (the runtime crashes the other
        way round). A driver may raise one more frame after stop() (the runtime's own
        DummyDevice does: its frame thread is not joined), so destroying waits a little
        over two frame periods. Errors are logged: the device may be gone already."""
        streams = [s for s in (self.depth, self.color) if s is not None]
        self.depth = self.color = None
        if self.started:
            for stream in streams:
                _quietly(stream.stop, "stopping an OpenNI2 stream")
            # the dummy's late frame may come a scheduler delay later on a loaded machine
            dummy = (self.spec.device or "") in DUMMY_URIS
            time.sleep(DUMMY_STOP_GRACE_S if dummy else 2.5 / max(self.fps, 1.0))
        for stream in streams:
            _quietly(stream.close, "closing an OpenNI2 stream")
        if self.device is not None:
            _quietly(self.device.close, "closing the OpenNI2 device")
            self.device = None
            if self.is_file:  # the file player crashed the runtime's shutdown in about 1
                time.sleep(FILE_CLOSE_GRACE_S)  # of 30 runs right after close (0 of 30 so)


def _quietly(action, what: str) -> None:
    try:
        action()
    except Exception as exc:  # OpenNIError from a device that is gone
        log.debug("%s: %s", what, exc)


def open_openni2(spec: CameraSpec, max_frames: int | None = None) -> Source:
    """A Source streaming an OpenNI2 device or .oni file (see the module docstring)."""
    openni2 = initialize()
    cam = _OpenNI2Camera(openni2, spec)
    atexit.register(cam.close)  # a source never streamed: closed before the runtime unloads
    info = cam.device.get_device_info()
    label = [b.decode(errors="replace").strip() for b in (info.vendor, info.name)]
    name = (
        Path(spec.device).stem
        if cam.is_file and spec.device
        else "-".join(["openni2", *[part for part in label if part]])
    )
    n = (
        cam.frames_in_file
        if cam.is_file and cam.frames_in_file and cam.frames_in_file > 0
        else None
    )
    if max_frames is not None:
        n = max_frames if n is None else min(n, max_frames)
    from openni.utils import OpenNIError

    lost = (TimeoutError, OpenNIError)

    def read():
        if cam.is_file and cam.frames_in_file and cam.frames_read >= cam.frames_in_file:
            return None  # every frame of the file has been read
        return cam.read()

    frames = camera_stream(spec, read, cam.close, lost, n, cam.counter)

    calibration = CameraCalibration(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    notes = list(cam.notes)
    for note in notes:
        log.warning("SOURCE %s: %s", spec.text, note)
    return Source(name, calibration, cam.depth_scale, n or 0, frames, notes)
