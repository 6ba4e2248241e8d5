"""Intel RealSense cameras through pyrealsense2 (pip extra `arlight[realsense]`).

`open_realsense(spec)` opens `realsense` (the first device) or `realsense:SERIAL` and returns
a Source: depth (z16) and colour (rgb8) at spec.size and spec.fps, depth aligned to colour
(`rs.align(rs.stream.color)`), depth units from the depth sensor (`get_depth_scale()`,
metres per unit: 0.001 -> depth_scale 1000), intrinsics of the colour stream, timestamps in
host wall time (librealsense's global time domain, milliseconds, is already the host's;
a hardware-clock domain is mapped by `DeviceClock`).
"""

from __future__ import annotations

import logging

import numpy as np

from arlight.protocols import CameraCalibration
from arlight.sources.camera import (
    CameraError,
    CameraSpec,
    DeviceClock,
    FrameCounter,
    camera_stream,
    depth_units_per_metre,
    import_library,
    no_device_message,
)
from arlight.sources.source import Source, SourceFrame

log = logging.getLogger(__name__)

READ_TIMEOUT_MS = 2000  # a device silent this long is gone
PERMISSIONS = (
    "the udev rules (librealsense's 99-realsense-libusb.rules in "
    "/etc/udev/rules.d, then replug) and a USB 3 port"
)


def find_serial(rs, spec: CameraSpec) -> str:
    """The serial number to open; CameraError naming the devices found if it is absent."""
    serials = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
    if spec.device is None and serials:
        return serials[0]
    if spec.device is not None and spec.device in serials:
        return spec.device
    raise CameraError(
        no_device_message(
            spec,
            "Intel RealSense devices on USB (rs.context().query_devices())",
            serials,
            PERMISSIONS,
        )
    )


def calibration_from_intrinsics(intrinsics) -> tuple[CameraCalibration, list[str]]:
    """The wire calibration of an rs.intrinsics (pixels), and a note if it has distortion
    coefficients the wire does not carry (D4xx colour streams usually have none)."""
    calibration = CameraCalibration(
        int(intrinsics.width),
        int(intrinsics.height),
        float(intrinsics.fx),
        float(intrinsics.fy),
        float(intrinsics.ppx),
        float(intrinsics.ppy),
    )
    coeffs = [float(c) for c in intrinsics.coeffs]
    notes = (
        []
        if not any(abs(c) > 1e-9 for c in coeffs)
        else [f"the colour stream has {intrinsics.model} distortion {coeffs}, not corrected"]
    )
    return calibration, notes


def timestamp_s(rs, frame, clock: DeviceClock) -> float:
    """A frame's time in host wall seconds: global / system time domains are host
    milliseconds already; the hardware clock is mapped through `clock`."""
    stamp_s = frame.get_timestamp() * 1e-3
    if frame.get_frame_timestamp_domain() == rs.timestamp_domain.hardware_clock:
        return clock.to_host(stamp_s)
    return stamp_s


def rgbd_of(frameset) -> tuple[np.ndarray, np.ndarray]:
    """(colour (H, W, 3) uint8 RGB, depth (H, W) uint16) copies of an aligned frameset."""
    color = np.asanyarray(frameset.get_color_frame().get_data())
    depth = np.asanyarray(frameset.get_depth_frame().get_data())
    if color.ndim != 3 or color.dtype != np.uint8 or depth.dtype != np.uint16:
        raise CameraError(
            f"RealSense frames of {color.dtype}{color.shape} / "
            f"{depth.dtype}{depth.shape}; expected rgb8 and z16"
        )
    return np.array(color), np.array(depth)


def rgbd_reader(rs, wait, counter: FrameCounter, clock: DeviceClock | None = None):
    """read() -> the next SourceFrame: wait() gives a frameset (depth + colour; the
    pipeline's wait_for_frames, which raises RuntimeError once the device is gone), whose
    depth `rs.align` reprojects into the colour camera."""
    align = rs.align(rs.stream.color)
    clock = DeviceClock(live=True) if clock is None else clock

    def read() -> SourceFrame:
        aligned = align.process(wait())
        color_frame = aligned.get_color_frame()
        counter.see(int(color_frame.get_frame_number()))
        color, depth = rgbd_of(aligned)
        return SourceFrame(timestamp_s(rs, color_frame, clock), color, depth)

    return read


def open_realsense(spec: CameraSpec, max_frames: int | None = None) -> Source:
    """A Source streaming an Intel RealSense camera (see the module docstring)."""
    rs = import_library("realsense")
    serial = find_serial(rs, spec)
    config = rs.config()
    config.enable_device(serial)
    width, height = spec.size
    config.enable_stream(rs.stream.depth, width, height, rs.format.z16, int(spec.fps))
    config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, int(spec.fps))
    pipeline = rs.pipeline()
    try:
        profile = pipeline.start(config)
    except RuntimeError as exc:
        raise CameraError(
            f"SOURCE {spec.text}: device {serial} cannot stream depth and "
            f"colour at {width}x{height} @ {spec.fps:g} Hz ({exc}); choose "
            "another --size / --fps, check " + PERMISSIONS
        ) from None
    try:
        depth_scale = depth_units_per_metre(
            profile.get_device().first_depth_sensor().get_depth_scale()
        )
        color_profile = profile.get_stream(rs.stream.color).as_video_stream_profile()
        calibration, notes = calibration_from_intrinsics(color_profile.get_intrinsics())
    except BaseException:
        pipeline.stop()
        raise
    counter = FrameCounter()
    read = rgbd_reader(rs, lambda: pipeline.wait_for_frames(READ_TIMEOUT_MS), counter)
    frames = camera_stream(spec, read, pipeline.stop, (RuntimeError,), max_frames, counter)

    for note in notes:
        log.warning("SOURCE %s: %s", spec.text, note)
    return Source(f"realsense-{serial}", calibration, depth_scale, max_frames or 0, frames, notes)
