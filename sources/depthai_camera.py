"""Luxonis OAK cameras through depthai v3 (pip extra `arlight[depthai]`).

`open_depthai(spec)` opens `depthai` (the first device found) or `depthai:DEVICE_ID` (its
device id, or a name / IP address as `depthai.DeviceInfo` takes them) and returns a Source:
the colour camera (CAM_A) at spec.size and spec.fps as RGB, stereo depth from CAM_B / CAM_C
aligned to the colour camera (`StereoDepth.setDepthAlign(CAM_A)`, scaled to the colour size),
the two paired on the device by a Sync node; depth in millimetres (depth_scale 1000);
intrinsics of the colour output at that size from the device calibration (the frame's
`ImgTransformation`, which carries the ISP's scaling and cropping); timestamps from the
device clock as depthai synchronises it to the host's steady clock, mapped to wall time;
IMU gravity in the colour camera's frame on each frame (`SourceFrame.gravity`) when the
device has an IMU.
"""

from __future__ import annotations

import datetime
import logging

import numpy as np

from arlight.protocols import CameraCalibration
from arlight.sources.camera import (
    CameraError,
    CameraSpec,
    FrameCounter,
    camera_stream,
    gravity_in_camera,
    import_library,
    monotonic_to_wall_offset,
    no_device_message,
)
from arlight.sources.source import Source, SourceFrame

log = logging.getLogger(__name__)

DEPTH_SCALE = 1000.0  # StereoDepth.depth: uint16 millimetres
STEREO_SIZE = (640, 400)  # the mono cameras' output fed to StereoDepth (OV9282: 1280x800 / 2)
FIRST_FRAME_TIMEOUT_S = 10.0  # the pipeline's start-up (firmware boot is before it)
READ_TIMEOUT_S = 2.0  # a device silent this long is gone
IMU_RATE_HZ = 100
PERMISSIONS = (
    'USB permissions: echo \'SUBSYSTEM=="usb", ATTRS{idVendor}=="03e7", '
    'MODE="0666"\' | sudo tee /etc/udev/rules.d/80-movidius.rules, then '
    "sudo udevadm control --reload-rules && sudo udevadm trigger; in a container "
    "pass -v /dev/bus/usb:/dev/bus/usb --device-cgroup-rule='c 189:* rmw'"
)


def find_device(dai, spec: CameraSpec):
    """The DeviceInfo to open; CameraError (within depthai's search time) if none."""
    infos = list(dai.Device.getAllAvailableDevices())
    ids = [f"{i.getDeviceId()} ({i.name})" for i in infos]
    if spec.device is None:
        if infos:
            return infos[0]
    else:
        for info in infos:
            if spec.device in (info.getDeviceId(), info.name):
                return info
        if spec.device.count(".") == 3:  # an IP address: depthai searches it directly
            return dai.DeviceInfo(spec.device)
    raise CameraError(
        no_device_message(
            spec,
            "Luxonis OAK devices on USB and the network (depthai.Device.getAllAvailableDevices)",
            ids,
            PERMISSIONS,
        )
    )


def color_from_imgframe(dai, frame) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a colour ImgFrame (RGB888i as requested; others converted)."""
    kind = frame.getType()
    if kind == dai.ImgFrame.Type.RGB888i:
        return np.ascontiguousarray(
            np.asarray(frame.getFrame(), np.uint8).reshape(frame.getHeight(), frame.getWidth(), 3)
        )
    if kind == dai.ImgFrame.Type.BGR888i:
        bgr = np.asarray(frame.getFrame(), np.uint8).reshape(frame.getHeight(), frame.getWidth(), 3)
        return np.ascontiguousarray(bgr[..., ::-1])
    return np.ascontiguousarray(np.asarray(frame.getCvFrame())[..., ::-1])  # OpenCV's BGR


def depth_from_imgframe(frame) -> np.ndarray:
    """(H, W) uint16 millimetres of StereoDepth's depth ImgFrame (RAW16), 0 = no depth."""
    depth = np.asarray(frame.getFrame())
    if depth.dtype != np.uint16:
        raise CameraError(f"depthai depth frame of dtype {depth.dtype}; expected uint16 (RAW16)")
    return np.ascontiguousarray(depth.reshape(frame.getHeight(), frame.getWidth()))


def intrinsics_of(frame) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in pixels of an ImgFrame as it is, from its ImgTransformation (the
    device calibration carried through the ISP's scaling, cropping and padding)."""
    transformation = frame.getTransformation()
    if not transformation.isValid():
        raise CameraError(
            "the depthai colour frame carries no valid ImgTransformation "
            "(calibration) to take intrinsics from"
        )
    k = np.asarray(transformation.getIntrinsicMatrix(), np.float64)
    return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])


def distortion_notes(frame) -> list[str]:
    """A note when the frame's lens distortion is not zero: the wire's calibration is a
    pinhole, so distortion is reported, not corrected."""
    coeffs = [float(c) for c in frame.getTransformation().getDistortionCoefficients()]
    if not any(abs(c) > 1e-9 for c in coeffs):
        return []
    shown = ", ".join(f"{c:.4g}" for c in coeffs[:5])
    return [
        f"the colour output has lens distortion ({shown}, ...), not corrected: the "
        "calibration sent is a pinhole"
    ]


def camera_from_imu(calibration, socket) -> np.ndarray | None:
    """(3, 3) rotation from the IMU's axes to the camera's, from the device calibration;
    None if the calibration links no IMU to that camera."""
    try:
        matrix = np.asarray(calibration.getImuToCameraExtrinsics(socket), np.float64)
    except RuntimeError:
        return None
    return matrix[:3, :3] if matrix.shape == (4, 4) else None


def latest_gravity(queue, rotation: np.ndarray | None) -> np.ndarray | None:
    """Gravity in the camera frame from the newest accelerometer report waiting in the IMU
    queue (None without one, or while the device accelerates)."""
    if queue is None or rotation is None:
        return None
    packets = []
    for message in queue.tryGetAll():
        packets.extend(message.packets)
    if not packets:
        return None
    a = packets[-1].acceleroMeter
    return gravity_in_camera(np.array([a.x, a.y, a.z]), rotation)


def build_pipeline(dai, pipeline, spec: CameraSpec, with_imu: bool):
    """The graph on a device pipeline: colour + aligned stereo depth, synchronised, and
    optionally the accelerometer. Returns (synced RGB-D queue, IMU queue or None)."""
    socket = dai.CameraBoardSocket
    color_cam = pipeline.create(dai.node.Camera).build(socket.CAM_A)
    color = color_cam.requestOutput(
        tuple(spec.size), dai.ImgFrame.Type.RGB888i, fps=float(spec.fps)
    )
    left = pipeline.create(dai.node.Camera).build(socket.CAM_B)
    right = pipeline.create(dai.node.Camera).build(socket.CAM_C)
    stereo = pipeline.create(dai.node.StereoDepth).build(
        left.requestOutput(STEREO_SIZE, fps=float(spec.fps)),
        right.requestOutput(STEREO_SIZE, fps=float(spec.fps)),
        presetMode=dai.node.StereoDepth.PresetMode.DEFAULT,
    )
    stereo.setLeftRightCheck(True)  # needed to align depth to another camera
    stereo.setDepthAlign(socket.CAM_A)
    stereo.setOutputSize(*spec.size)
    sync = pipeline.create(dai.node.Sync)
    sync.setSyncThreshold(datetime.timedelta(seconds=0.5 / spec.fps))
    color.link(sync.inputs["color"])
    stereo.depth.link(sync.inputs["depth"])
    rgbd_queue = sync.out.createOutputQueue(maxSize=4, blocking=False)
    imu_queue = None
    if with_imu:
        imu = pipeline.create(dai.node.IMU)
        imu.enableIMUSensor(dai.IMUSensor.ACCELEROMETER_CALIBRATED, IMU_RATE_HZ)
        imu.setBatchReportThreshold(1)
        imu.setMaxBatchReports(10)
        imu_queue = imu.out.createOutputQueue(maxSize=50, blocking=False)
    return rgbd_queue, imu_queue


def _get(queue, timeout_s: float):
    """The next message, or TimeoutError after timeout_s."""
    message = queue.get(datetime.timedelta(seconds=timeout_s))
    if message is None:
        raise TimeoutError(f"no frame from the device for {timeout_s:g} s")
    return message


def lost_errors(dai) -> tuple[type[BaseException], ...]:
    """What reading a queue raises once the device is gone: RuntimeError (XLink
    communication errors), the queue's QueueException (closed), TimeoutError (_get)."""
    return (RuntimeError, TimeoutError, dai.MessageQueue.QueueException)


def rgbd_reader(
    dai,
    queue,
    counter: FrameCounter,
    imu_queue=None,
    rotation=None,
    first=None,
    wall_offset_s: float | None = None,
):
    """read() -> the next SourceFrame from a queue of Sync MessageGroups ("color": RGB888i,
    "depth": RAW16 mm), `first` (already taken from the queue) first; timestamps are the
    colour frame's host-synchronised steady-clock time plus wall_offset_s (default
    monotonic_to_wall_offset(), taken now)."""
    offset_s = monotonic_to_wall_offset() if wall_offset_s is None else wall_offset_s
    pending = [] if first is None else [first]

    def read() -> SourceFrame:
        group = pending.pop() if pending else _get(queue, READ_TIMEOUT_S)
        color, depth = group["color"], group["depth"]
        counter.see(int(color.getSequenceNum()))
        stamp = color.getTimestamp().total_seconds() + offset_s
        return SourceFrame(
            stamp,
            color_from_imgframe(dai, color),
            depth_from_imgframe(depth),
            gravity=latest_gravity(imu_queue, rotation),
        )

    return read


def open_depthai(spec: CameraSpec, max_frames: int | None = None) -> Source:
    """A Source streaming a Luxonis OAK camera (see the module docstring)."""
    dai = import_library("depthai")
    info = find_device(dai, spec)
    try:
        device = dai.Device(info)
    except RuntimeError as exc:
        raise CameraError(
            f"SOURCE {spec.text}: the device {info.getDeviceId()} cannot be "
            f"opened ({exc}); check {PERMISSIONS}"
        ) from None
    try:
        return _start(dai, device, spec, max_frames)
    except BaseException:
        device.close()
        raise


def _start(dai, device, spec: CameraSpec, max_frames: int | None) -> Source:
    sockets = set(device.getConnectedCameras())
    needed = {dai.CameraBoardSocket.CAM_A, dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C}
    if not needed <= sockets:
        raise CameraError(
            f"SOURCE {spec.text}: the device has cameras on "
            f"{sorted(str(s) for s in sockets)}; RGB-D needs colour on CAM_A "
            "and a stereo pair on CAM_B / CAM_C"
        )
    imu_type = device.getConnectedIMU()
    calibration = device.readCalibration()
    rotation = (
        camera_from_imu(calibration, dai.CameraBoardSocket.CAM_A)
        if imu_type and imu_type.upper() != "NONE"
        else None
    )
    notes = (
        []
        if rotation is not None
        else [f"no IMU gravity (IMU {imu_type or 'none'}, or no IMU-to-camera calibration)"]
    )
    pipeline = dai.Pipeline(device)
    try:
        rgbd_queue, imu_queue = build_pipeline(dai, pipeline, spec, rotation is not None)
        pipeline.start()
    except RuntimeError as exc:
        raise CameraError(
            f"SOURCE {spec.text}: the depthai pipeline cannot start at "
            f"{spec.size[0]}x{spec.size[1]} @ {spec.fps:g} Hz ({exc}); try "
            "another --size / --fps"
        ) from None
    counter = FrameCounter()
    try:
        first = _get(rgbd_queue, FIRST_FRAME_TIMEOUT_S)
    except lost_errors(dai) as exc:
        raise CameraError(
            f"SOURCE {spec.text}: the device started but sent no frame ({exc}); "
            "replug it, or check its power (a USB 3 port or a powered hub)"
        ) from None
    fx, fy, cx, cy = intrinsics_of(first["color"])
    width, height = first["color"].getWidth(), first["color"].getHeight()
    notes += distortion_notes(first["color"])
    read = rgbd_reader(dai, rgbd_queue, counter, imu_queue, rotation, first)

    def close() -> None:
        try:
            pipeline.stop()
        finally:
            device.close()

    frames = camera_stream(spec, read, close, lost_errors(dai), max_frames, counter)

    for note in notes:
        log.warning("SOURCE %s: %s", spec.text, note)
    name = f"oak-{device.getDeviceId()}"
    log.info("SOURCE %s: %s, %dx%d @ %g Hz", spec.text, name, width, height, spec.fps)
    return Source(
        name,
        CameraCalibration(width, height, fx, fy, cx, cy),
        DEPTH_SCALE,
        max_frames or 0,
        frames,
        notes,
    )
