"""depthai and RealSense cameras (sources/depthai_camera.py, sources/realsense_camera.py).

Everything that runs without a device runs against the installed libraries' host-side types
(ImgFrame, ImgTransformation, CalibrationHandler, rs.intrinsics, librealsense's
software_device); opening real hardware is marked `hardware` and skipped without it. The
spec, the frame loop and OpenNI2 are tests/test_cameras.py.
"""

from __future__ import annotations

import datetime
import importlib.util
import time

import numpy as np
import pytest

from arlight.sources.camera import (
    CameraSpec,
    DeviceClock,
    FrameCounter,
    camera_frames,
)


def _has(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


# --------------------------------------------------------------------------- depthai

needs_depthai = pytest.mark.skipif(
    not _has("depthai"), reason="depthai: pip install 'arlight[depthai]'"
)


def _depthai_devices() -> list:
    if not _has("depthai"):
        return []
    import depthai as dai

    return list(dai.Device.getAllAvailableDevices())


@needs_depthai
class TestDepthai:
    def test_color_frames_come_out_rgb(self):
        import depthai as dai

        from arlight.sources.depthai_camera import color_from_imgframe

        rgb = np.zeros((4, 6, 3), np.uint8)
        rgb[..., 0] = 200  # red
        for kind, data in (
            (dai.ImgFrame.Type.RGB888i, rgb),
            (dai.ImgFrame.Type.BGR888i, rgb[..., ::-1]),
        ):
            frame = dai.ImgFrame()
            frame.setType(kind)
            frame.setWidth(6)
            frame.setHeight(4)
            frame.setData(np.ascontiguousarray(data).reshape(-1))
            np.testing.assert_array_equal(color_from_imgframe(dai, frame), rgb)

    def test_depth_frame_is_uint16_mm(self):
        import depthai as dai

        from arlight.sources.depthai_camera import depth_from_imgframe

        depth = (np.arange(12, dtype=np.uint16) * 250).reshape(3, 4)
        frame = dai.ImgFrame()
        frame.setType(dai.ImgFrame.Type.RAW16)
        frame.setWidth(4)
        frame.setHeight(3)
        frame.setData(depth.view(np.uint8).reshape(-1))
        np.testing.assert_array_equal(depth_from_imgframe(frame), depth)

    def test_intrinsics_follow_the_isp_scaling(self):
        """1920x1080 calibration as a 640x480 output in depthai's CROP resize mode: scaled
        by 4/9 to 853x480, then 106 columns cropped on the left."""
        import depthai as dai

        from arlight.sources.depthai_camera import intrinsics_of

        k = [[1500.0, 0.0, 950.0], [0.0, 1500.0, 530.0], [0.0, 0.0, 1.0]]
        transformation = dai.ImgTransformation(1920, 1080, k)
        transformation.addScale(4 / 9, 4 / 9)
        transformation.addCrop(106, 0, 640, 480)
        frame = dai.ImgFrame()
        frame.setTransformation(transformation)
        fx, fy, cx, cy = intrinsics_of(frame)
        assert (fx, fy) == pytest.approx((1500 * 4 / 9, 1500 * 4 / 9), rel=1e-6)
        assert (cx, cy) == pytest.approx((950 * 4 / 9 - 106, 530 * 4 / 9), rel=1e-6)

    def test_distortion_is_reported(self):
        import depthai as dai

        from arlight.sources.depthai_camera import distortion_notes

        k = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]
        frame = dai.ImgFrame()
        frame.setTransformation(dai.ImgTransformation(640, 480, k))
        assert distortion_notes(frame) == []
        frame.setTransformation(
            dai.ImgTransformation(
                640, 480, k, dai.CameraModel.Perspective, [-0.12, 0.05] + [0.0] * 12
            )
        )
        assert "lens distortion (-0.12, 0.05" in distortion_notes(frame)[0]

    def test_imu_extrinsics_from_the_calibration(self):
        import depthai as dai

        from arlight.sources.depthai_camera import camera_from_imu

        calibration = dai.CalibrationHandler()
        rotation = [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
        calibration.setImuExtrinsics(dai.CameraBoardSocket.CAM_A, rotation, [1.0, 2.0, 0.0])
        # no data for the camera yet: the IMU is linked to nothing, so no gravity
        assert camera_from_imu(calibration, dai.CameraBoardSocket.CAM_A) is None
        calibration.setCameraIntrinsics(
            dai.CameraBoardSocket.CAM_A, [[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]], 1920, 1080
        )
        np.testing.assert_allclose(
            camera_from_imu(calibration, dai.CameraBoardSocket.CAM_A), rotation
        )

    def test_reader_over_a_depthai_queue_then_the_queue_closes(self, caplog):
        """The read path over depthai's own MessageQueue of Sync MessageGroups, as the device
        fills it; then the queue closes, as it does when the device goes away."""
        import depthai as dai

        from arlight.sources.depthai_camera import lost_errors, rgbd_reader

        queue = dai.MessageQueue("rgbd", 8, False)
        for seq in (3, 4, 6):
            color = dai.ImgFrame()
            color.setType(dai.ImgFrame.Type.RGB888i)
            color.setWidth(4)
            color.setHeight(2)
            color.setData(np.full(2 * 4 * 3, seq, np.uint8))
            color.setSequenceNum(seq)
            color.setTimestamp(datetime.timedelta(seconds=100.0 + seq / 30))
            depth = dai.ImgFrame()
            depth.setType(dai.ImgFrame.Type.RAW16)
            depth.setWidth(4)
            depth.setHeight(2)
            depth.setData(np.full(8, 1000 + seq, np.uint16).view(np.uint8))
            group = dai.MessageGroup()
            group["color"], group["depth"] = color, depth
            queue.send(group)
        counter, closed = FrameCounter(), []
        read = rgbd_reader(dai, queue, counter, wall_offset_s=1.7e9)
        frames = camera_frames(
            CameraSpec("depthai", "X"),
            read,
            lambda: closed.append(1),
            lost_errors(dai),
            None,
            counter,
        )
        got = [next(frames) for _ in range(3)]
        assert [int(f.color[0, 0, 0]) for f in got] == [3, 4, 6]
        assert [int(f.depth[1, 3]) for f in got] == [1003, 1004, 1006]
        assert got[0].depth.dtype == np.uint16 and got[0].gravity is None
        assert got[0].timestamp == pytest.approx(1.7e9 + 100.1)
        queue.close()
        assert list(frames) == [] and closed == [1]
        assert counter.skipped == 1  # seq 5 never came
        assert "camera lost after 3 frame(s) (MessageQueue was closed)" in caplog.text

    def test_gravity_from_the_newest_imu_report(self):
        """IMUData through depthai's own queue: the newest accelerometer report, rotated into
        the colour camera; an empty queue gives None."""
        import depthai as dai

        from arlight.sources.depthai_camera import latest_gravity

        queue = dai.MessageQueue("imu", 8, False)
        rotation = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
        for reading in ((0.0, 9.8, 0.0), (9.81, 0.0, 0.0)):  # the older one is superseded
            report = dai.IMUReportAccelerometer()
            report.x, report.y, report.z = reading
            packet = dai.IMUPacket()
            packet.acceleroMeter = report
            data = dai.IMUData()
            data.packets = [packet]
            queue.send(data)
        np.testing.assert_allclose(latest_gravity(queue, rotation), [0.0, 0.0, -1.0], atol=1e-12)
        assert latest_gravity(queue, rotation) is None  # nothing new
        assert latest_gravity(None, rotation) is None

    def test_timestamps_are_host_steady_clock(self):
        import depthai as dai

        frame = dai.ImgFrame()
        frame.setTimestamp(datetime.timedelta(seconds=12.5))
        assert frame.getTimestamp().total_seconds() == 12.5

    def test_the_graph_needs_a_device(self):
        """Why building the pipeline is a hardware test: depthai v3 refuses device nodes on
        a pipeline without a device (Pipeline(False) is host only)."""
        import depthai as dai

        with pytest.raises(RuntimeError, match="host only"):
            dai.Pipeline(False).create(dai.node.Camera)

    @pytest.mark.skipif(bool(_depthai_devices()), reason="a depthai device is attached")
    def test_no_device_is_a_clear_error(self, capsys):
        from arlight.cli import main

        assert main(["stream", "depthai", "--server", "tcp://127.0.0.1:9"]) == 2  # no raise
        err = capsys.readouterr().err
        assert "no depthai camera" in err and "udev" in err
        assert "getAllAvailableDevices" in err

    @pytest.mark.hardware
    @pytest.mark.skipif(not _depthai_devices(), reason="no depthai (OAK) device attached")
    def test_device_streams_aligned_rgbd(self):
        from arlight.sources.source import open_source

        source = open_source("depthai", max_frames=3)
        assert (source.calibration.width, source.calibration.height) == (640, 480)
        assert source.depth_scale == 1000.0
        frames = list(source.frames())
        assert len(frames) == 3
        assert frames[0].depth.shape == (480, 640) and frames[0].color.shape == (480, 640, 3)
        assert abs(frames[0].timestamp - time.time()) < 5


# --------------------------------------------------------------------------- RealSense

needs_realsense = pytest.mark.skipif(
    not _has("pyrealsense2"), reason="pyrealsense2: pip install 'arlight[realsense]'"
)


def _realsense_devices() -> int:
    if not _has("pyrealsense2"):
        return 0
    import pyrealsense2 as rs

    return len(rs.context().query_devices())


@needs_realsense
class TestRealSense:
    def test_calibration_from_intrinsics(self):
        import pyrealsense2 as rs

        from arlight.sources.realsense_camera import calibration_from_intrinsics

        intrinsics = rs.intrinsics()
        intrinsics.width, intrinsics.height = 640, 480
        intrinsics.fx, intrinsics.fy, intrinsics.ppx, intrinsics.ppy = 615.2, 615.9, 318.4, 241.7
        intrinsics.model = rs.distortion.inverse_brown_conrady
        intrinsics.coeffs = [0.0] * 5
        calibration, notes = calibration_from_intrinsics(intrinsics)
        assert (calibration.fx, calibration.fy, calibration.cx, calibration.cy) == pytest.approx(
            (615.2, 615.9, 318.4, 241.7)
        )
        assert notes == []
        # the library's own projection agrees with the pinhole the wire carries
        u, v = rs.rs2_project_point_to_pixel(intrinsics, [0.1, -0.2, 1.5])
        assert (u, v) == pytest.approx(
            (615.2 * 0.1 / 1.5 + 318.4, -615.9 * 0.2 / 1.5 + 241.7), abs=1e-3
        )
        intrinsics.coeffs = [0.1, 0.0, 0.0, 0.0, 0.0]
        assert "distortion" in calibration_from_intrinsics(intrinsics)[1][0]

    def test_reader_aligns_software_device_frames(self, caplog):
        """The read path on frames from librealsense's own software_device (no hardware):
        depth at 8x6 is aligned by rs.align into a 16x12 colour camera, timestamps of the
        hardware clock are mapped to host time, a dropped frame number is counted, and the
        RuntimeError a stopped device raises ends the stream."""
        import pyrealsense2 as rs

        from arlight.sources.realsense_camera import rgbd_reader

        def intrinsics(w, h, f):
            i = rs.intrinsics()
            i.width, i.height, i.fx, i.fy, i.ppx, i.ppy = w, h, f, f, w / 2, h / 2
            i.model, i.coeffs = rs.distortion.none, [0.0] * 5
            return i

        def stream(kind, uid, w, h, fmt, bpp, f):
            s = rs.video_stream()
            s.type, s.index, s.uid, s.width, s.height = kind, 0, uid, w, h
            s.fps, s.bpp, s.fmt, s.intrinsics = 30, bpp, fmt, intrinsics(w, h, f)
            return s

        device = rs.software_device()
        depth_sensor, color_sensor = device.add_sensor("Depth"), device.add_sensor("Color")
        depth_profile = depth_sensor.add_video_stream(
            stream(rs.stream.depth, 0, 8, 6, rs.format.z16, 2, 8.0)
        )
        color_profile = color_sensor.add_video_stream(
            stream(rs.stream.color, 1, 16, 12, rs.format.rgb8, 3, 16.0)
        )
        same_place = rs.extrinsics()
        same_place.rotation, same_place.translation = [1, 0, 0, 0, 1, 0, 0, 0, 1], [0, 0, 0]
        depth_profile.register_extrinsics_to(color_profile, same_place)
        depth_queue, color_queue = rs.frame_queue(10, True), rs.frame_queue(10, True)
        depth_sensor.open(depth_profile)
        color_sensor.open(color_profile)
        depth_sensor.start(depth_queue)
        color_sensor.start(color_queue)
        held, framesets = [], rs.frame_queue(10, True)

        def pair(frame, source):  # two frames -> one frameset, as the pipeline's syncer does
            held.append(frame)
            if len(held) == 2:
                source.frame_ready(source.allocate_composite_frame(held[:]))
                held.clear()

        block = rs.processing_block(pair)
        block.start(framesets)
        depth = np.full((6, 8), 1500, np.uint16)
        color = np.zeros((12, 16, 3), np.uint8)
        color[..., 1] = 200
        for number in (0, 1, 3):
            for sensor, profile, pixels, bpp, width in (
                (depth_sensor, depth_profile, depth, 2, 8),
                (color_sensor, color_profile, color, 3, 16),
            ):
                f = rs.software_video_frame()
                f.pixels, f.bpp, f.stride = pixels, bpp, bpp * width
                f.timestamp, f.domain = 5000.0 + 33.0 * number, rs.timestamp_domain.hardware_clock
                f.frame_number, f.profile = number, profile.as_video_stream_profile()
                f.depth_units = 0.001
                sensor.on_video_frame(f)
        for _ in range(3):
            block.invoke(depth_queue.wait_for_frame(2000))
            block.invoke(color_queue.wait_for_frame(2000))

        def wait():
            frameset = framesets.poll_for_frame()
            if not frameset:
                raise RuntimeError("Frame didn't arrive within 2000")
            return frameset.as_frameset()

        # the frames were all made at once, so a live clock (least delay) would see them
        # arrive faster than their stamps: the fixed clock keeps their spacing
        counter, clock, closed = FrameCounter(), DeviceClock(live=False), []
        read = rgbd_reader(rs, wait, counter, clock)
        got = list(
            camera_frames(
                CameraSpec("realsense", "SW"),
                read,
                lambda: closed.append(1),
                (RuntimeError,),
                None,
                counter,
            )
        )
        for sensor in (depth_sensor, color_sensor):
            sensor.stop()
            sensor.close()
        assert len(got) == 3 and closed == [1]
        assert got[0].depth.shape == (12, 16) and got[0].depth.dtype == np.uint16
        assert got[0].depth[6, 8] == 1500  # depth reprojected into the colour camera
        assert got[0].color.shape == (12, 16, 3) and got[0].color[0, 0].tolist() == [0, 200, 0]
        stamps = [f.timestamp for f in got]
        assert abs(stamps[0] - time.time()) < 60  # host wall time, not the device's 5 s
        np.testing.assert_allclose(np.diff(stamps), [0.033, 0.066], atol=1e-6)
        assert counter.skipped == 1
        assert "camera lost after 3 frame(s) (Frame didn't arrive within 2000)" in caplog.text

    @pytest.mark.skipif(_realsense_devices() > 0, reason="a RealSense device is attached")
    def test_no_device_is_a_clear_error(self, capsys, tmp_path):
        from arlight.cli import main

        assert main(["record", "realsense:123456", "--out", str(tmp_path / "x.mcap")]) == 2
        err = capsys.readouterr().err
        assert "no realsense camera (device '123456'" in err and "udev" in err

    @pytest.mark.hardware
    @pytest.mark.skipif(_realsense_devices() == 0, reason="no RealSense device attached")
    def test_device_streams_aligned_rgbd(self):
        from arlight.sources.source import open_source

        source = open_source("realsense", max_frames=3)
        assert source.depth_scale > 0
        frames = list(source.frames())
        assert len(frames) == 3 and frames[0].depth.shape == frames[0].color.shape[:2]
