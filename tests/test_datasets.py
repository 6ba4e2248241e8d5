"""Tests of the data set readers (arlight.sources): real recorded data (skipped without
../shared/data) and tiny folders written to tmp_path for every bad-input case."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import DATA, needs_data
from scipy.spatial.transform import Rotation

from arlight.core.camera import PinholeCamera
from arlight.core.checks import depth_metres
from arlight.sources.depth_encodings import (
    NYU_DEPTH_SCALE,
    decode_depth,
    metres_to_units,
    read_depth,
)
from arlight.sources.errors import DatasetError
from arlight.sources.image_pair import open_pair
from arlight.sources.images import read_color
from arlight.sources.registration import register_depth
from arlight.sources.rgbd_sequence import RgbdSequence
from arlight.sources.sequence import open_sequence
from arlight.sources.seven_scenes import SEVEN_SCENES_COLOR_FROM_DEPTH, SEVEN_SCENES_DEPTH_SCALE
from arlight.sources.tum import quaternion_to_matrix

REAL = DATA / "real"
SYNTH = DATA / "synthetic"

data_driven = [pytest.mark.data, needs_data(DATA)]


def metres(frame) -> np.ndarray:
    """The frame's depth in metres, as the pipeline computes it."""
    return depth_metres(frame.depth, frame.depth_scale)


def check_frame(frame, camera: PinholeCamera, min_m: float = 0.05, max_m: float = 15.0) -> None:
    h, w = camera.height, camera.width
    assert frame.color.shape == (h, w, 3) and frame.color.dtype == np.uint8
    # sources yield the sensor's integers and their units per metre
    assert frame.depth.shape == (h, w) and frame.depth.dtype == np.uint16
    assert frame.depth_scale is not None and frame.depth_scale > 0
    depth = metres(frame)
    assert depth.shape == (h, w) and depth.dtype == np.float32
    assert np.all(np.isfinite(depth))
    valid = depth[depth > 0]
    assert valid.size > 0.3 * h * w
    assert valid.min() >= min_m and valid.max() <= max_m
    assert 0.3 <= float(np.median(valid)) <= 10.0
    assert isinstance(frame.timestamp, float)


def check_rigid(pose: np.ndarray, atol: float = 1e-5) -> None:
    assert pose.shape == (4, 4) and pose.dtype == np.float64
    r = pose[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=atol)
    assert abs(np.linalg.det(r) - 1.0) < atol
    np.testing.assert_array_equal(pose[3], [0.0, 0.0, 0.0, 1.0])


def first_data_line(path: Path) -> list[float]:
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            return [float(x) for x in line.split()]
    raise AssertionError(f"{path} has no data line")


# --------------------------------------------------------------------------- real data


class TestTumSynthetic:
    pytestmark = data_driven
    folder = SYNTH / "dev_a_static_venice"

    def test_frames_camera_and_depth(self):
        seq = open_sequence(self.folder)
        assert isinstance(seq, RgbdSequence)
        assert seq.format == "tum" and seq.name == "dev_a_static_venice"
        assert len(seq) == 16 and len(seq.frames) == 16
        assert seq.camera == PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
        assert seq.has_poses and not seq.poses_attached
        frames = list(seq)
        assert len(frames) == 16
        for f in frames[::5]:
            check_frame(f, seq.camera, min_m=0.4 - 1e-3, max_m=4.0 + 1e-3)  # its README's range
            assert f.pose is None
        assert frames[0].timestamp == pytest.approx(1000.0)
        assert frames[15].timestamp == pytest.approx(1000.5)

    def test_color_is_rgb_and_depth_scale_5000(self):
        f = open_sequence(self.folder).frame(0)
        bgr = cv2.imread(str(self.folder / "rgb" / "000000.png"), cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(f.color, bgr[..., ::-1])
        raw = cv2.imread(str(self.folder / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_allclose(metres(f), raw.astype(np.float32) / 5000.0, rtol=1e-6)
        # the stored integers themselves, untouched
        assert f.depth_scale == 5000.0
        np.testing.assert_array_equal(f.depth, raw)

    def test_poses_match_groundtruth(self):
        seq = open_sequence(self.folder, use_poses=True)
        assert seq.poses_attached and len(seq) == 16
        pose = seq.frame(0).pose
        check_rigid(pose)
        t, tx, ty, tz, qx, qy, qz, qw = first_data_line(self.folder / "groundtruth.txt")
        np.testing.assert_allclose(pose[:3, 3], [tx, ty, tz])
        np.testing.assert_allclose(
            pose[:3, :3], Rotation.from_quat([qx, qy, qz, qw]).as_matrix(), atol=1e-6
        )
        assert seq.frame(0, with_pose=False).pose is None
        for f in seq.frames[1::7]:
            check_rigid(f.pose)

    def test_max_frames_and_slices(self):
        seq = open_sequence(self.folder, max_frames=3)
        assert len(seq) == 3
        assert len(seq.frames[1:]) == 2
        assert seq.frames[-1].timestamp == pytest.approx(1000.0 + 2 / 30, abs=1e-5)
        with pytest.raises(IndexError):
            seq.frame(3)


class TestTumCorner:
    pytestmark = data_driven
    folder = REAL / "corner_18frames"

    def test_loads_with_kinect_defaults(self, caplog):
        with caplog.at_level(logging.WARNING, logger="arlight.sources"):
            seq = open_sequence(self.folder)
        assert "camera.json" in caplog.text
        # 18 image pairs on disk; one (1628069034.423709) is in neither depth.txt nor
        # associations.txt, so the dataset's own index pairs 17
        assert len(seq) == 17
        assert seq.camera == PinholeCamera.kinect_v1(640, 480)
        assert not seq.has_poses
        f = seq.frame(0)
        depth = metres(f)
        assert f.color.shape == (480, 640, 3) and depth.dtype == np.float32
        assert 0.3 <= float(np.median(depth[depth > 0])) <= 10.0

    def test_associations_with_depth_column_first(self):
        # corner's associations.txt lists depth before rgb: colour must still be colour
        seq = open_sequence(self.folder)
        f = seq.frame(0)
        bgr = cv2.imread(str(self.folder / "rgb" / "1628069033.660061.png"), cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(f.color, bgr[..., ::-1])

    def test_65535_becomes_missing(self):
        seq = open_sequence(self.folder)
        raw = cv2.imread(str(self.folder / "depth" / "1628069033.660061.png"), cv2.IMREAD_UNCHANGED)
        saturated = raw == 65535
        assert saturated.mean() > 0.01
        depth = metres(seq.frame(0))
        assert np.all(depth[saturated] == 0)
        ok = ~saturated
        np.testing.assert_allclose(depth[ok], raw[ok] / 5000.0, rtol=1e-6)

    def test_use_poses_without_groundtruth(self):
        with pytest.raises(DatasetError, match="groundtruth.txt"):
            open_sequence(self.folder, use_poses=True)


class TestRedwood:
    pytestmark = data_driven
    folder = REAL / "icl_nuim_livingroom"

    def test_loads(self):
        seq = open_sequence(self.folder)
        assert seq.format == "redwood" and len(seq) == 5
        assert seq.camera == PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
        for i, f in enumerate(seq):
            check_frame(f, seq.camera)
            assert f.timestamp == pytest.approx(i / 30.0)
            assert f.pose is None
        raw = cv2.imread(str(self.folder / "depth" / "00002.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_allclose(metres(seq.frame(2)), raw / 1000.0, rtol=1e-6)
        assert seq.frame(2).depth_scale == 1000.0
        np.testing.assert_array_equal(seq.frame(2).depth, raw)

    def test_poses_match_trajectory_log(self):
        seq = open_sequence(self.folder, use_poses=True)
        lines = (self.folder / "trajectory.log").read_text().splitlines()
        expected = np.array([[float(x) for x in ln.split()] for ln in lines[1:5]])
        for f in seq:
            check_rigid(f.pose)
        np.testing.assert_allclose(seq.frame(0).pose, expected)


class TestSevenScenes:
    pytestmark = data_driven
    folder = REAL / "7scenes_redkitchen"

    def test_loads_registered_to_colour(self):
        seq = open_sequence(self.folder)
        assert seq.format == "7scenes" and len(seq) == 100
        assert seq.camera == PinholeCamera(640, 480, 525.0, 525.0, 320.0, 240.0)
        assert seq.has_poses
        f = seq.frame(0)
        check_frame(f, seq.camera)
        assert f.timestamp == 0.0 and seq.frame(30).timestamp == pytest.approx(1.0)
        assert any("registered" in n for n in seq.notes)

    def test_65535_and_zero_are_missing(self):
        raw = cv2.imread(str(self.folder / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
        raw[:10, :10] = 65535
        depth = depth_metres(*decode_depth(raw, "mm"))
        assert np.all(depth[:10, :10] == 0)

    def test_registration_aligns_depth_edges_with_colour_edges(self):
        # Depth discontinuities must sit closer to colour edges after reprojection into the
        # colour camera than in the raw depth image (measured: ~10 px raw, ~5 px registered).
        depth_cam = PinholeCamera(640, 480, 585.0, 585.0, 320.0, 240.0)
        seq = open_sequence(self.folder)
        raw_d, reg_d = [], []
        for i in (0, 40, 80):
            gray = cv2.cvtColor(seq.frame(i).color, cv2.COLOR_RGB2GRAY)
            edges = cv2.Canny(gray, 50, 150)
            dist = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)
            raw = depth_metres(*read_depth(self.folder / f"frame-{i:06d}.depth.png", "mm"))
            for depth, out in ((raw, raw_d), (metres(seq.frame(i)), reg_d)):
                jump = (
                    (np.abs(np.diff(depth, axis=1)) > 0.1)
                    & (depth[:, 1:] > 0)
                    & (depth[:, :-1] > 0)
                )
                ys, xs = np.nonzero(jump)
                out.append(np.median(dist[ys, xs]))
        assert np.mean(reg_d) < 0.7 * np.mean(raw_d)
        # and the registration is the documented one, quantised at the stated scale
        assert seq.frame(0).depth_scale == SEVEN_SCENES_DEPTH_SCALE == 5000.0
        registered = register_depth(
            depth_metres(*read_depth(self.folder / "frame-000000.depth.png", "mm")),
            depth_cam,
            seq.camera,
            SEVEN_SCENES_COLOR_FROM_DEPTH,
        )
        np.testing.assert_allclose(
            metres(seq.frame(0)),
            depth_metres(
                metres_to_units(registered, SEVEN_SCENES_DEPTH_SCALE), SEVEN_SCENES_DEPTH_SCALE
            ),
        )
        # which is within half a step (0.1 mm) of the reprojected depth
        both = (registered > 0) & (metres(seq.frame(0)) > 0)
        assert np.abs(metres(seq.frame(0)) - registered)[both].max() <= 0.5 / 5000 + 1e-6

    def test_poses(self):
        seq = open_sequence(self.folder, use_poses=True, max_frames=5)
        assert len(seq) == 5
        world_from_depth = np.loadtxt(self.folder / "frame-000000.pose.txt")
        pose = seq.frame(0).pose
        check_rigid(pose, atol=1e-3)  # KinectFusion's own poses are orthonormal to ~2e-4
        # the file's pose is the depth camera's; frames are in the colour camera
        np.testing.assert_allclose(
            pose @ SEVEN_SCENES_COLOR_FROM_DEPTH, world_from_depth, atol=1e-9
        )
        assert np.linalg.norm(pose[:3, 3] - world_from_depth[:3, 3]) < 0.05

    def test_scene_folder_with_one_seq(self, tmp_path):
        (tmp_path / "seq-01").symlink_to(self.folder, target_is_directory=True)
        seq = open_sequence(tmp_path, max_frames=2)
        assert seq.format == "7scenes" and seq.name == "seq-01" and len(seq) == 2


class TestSingleFrames:
    pytestmark = data_driven
    folder = REAL / "single_frames"

    @pytest.mark.parametrize(
        "prefix,color_ext,depth_ext,encoding",
        [
            ("TUM", "png", "png", "tum"),
            ("SUN", "jpg", "png", "sun"),
            ("NYU", "ppm", "pgm", "nyu"),
        ],
    )
    def test_each_encoding_is_plausible(self, prefix, color_ext, depth_ext, encoding):
        color = self.folder / f"{prefix}_color.{color_ext}"
        depth = self.folder / f"{prefix}_depth.{depth_ext}"
        seq = open_pair(color, depth, encoding)
        assert seq.format == "pair" and len(seq) == 1 and not seq.has_poses
        assert seq.name == prefix
        f = seq.frame(0)
        check_frame(f, seq.camera, min_m=0.3, max_m=10.0)
        assert f.pose is None and f.timestamp == 0.0
        # the colour file alone finds its partner and infers the encoding from the prefix
        auto = open_sequence(color).frame(0)
        np.testing.assert_array_equal(auto.depth, f.depth)
        assert auto.depth_scale == f.depth_scale

    def test_nyu_missing_and_formula(self):
        raw = cv2.imread(str(self.folder / "NYU_depth.pgm"), cv2.IMREAD_UNCHANGED).byteswap()
        frame = open_pair(
            self.folder / "NYU_color.ppm", self.folder / "NYU_depth.pgm", "nyu"
        ).frame(0)
        assert frame.depth.dtype == np.uint16 and frame.depth_scale == NYU_DEPTH_SCALE == 5000.0
        depth = metres(frame)
        missing = raw == 2047
        assert missing.mean() > 0.01 and np.all(depth[missing] == 0)
        ok = ~missing
        # disparity is not linear in depth: the reader quantises the formula's metres at
        # NYU_DEPTH_SCALE units per metre
        formula = 351.3 / (1092.5 - raw[ok].astype(np.float64))
        np.testing.assert_allclose(depth[ok], np.rint(formula * 5000.0) / 5000.0, rtol=1e-5)
        assert np.abs(depth[ok] - formula).max() <= 0.5 / 5000 + 1e-6

    def test_wrong_encoding_is_implausible(self):
        # the SUN file read as plain millimetres gives nonsense depth: the encoding matters
        f = open_pair(self.folder / "SUN_color.jpg", self.folder / "SUN_depth.png", "mm").frame(0)
        depth = metres(f)
        assert np.median(depth[depth > 0]) > 10.0

    def test_folder_with_several_pairs_lists_them(self):
        with pytest.raises(DatasetError, match="TUM_color.png") as err:
            open_sequence(self.folder)
        assert "3 colour + depth pairs" in str(err.value)

    def test_folder_with_one_pair(self, tmp_path):
        for name in ("TUM_color.png", "TUM_depth.png"):
            (tmp_path / name).symlink_to(self.folder / name)
        seq = open_sequence(tmp_path)
        assert seq.format == "pair" and seq.depth_encoding == "tum"
        with pytest.raises(DatasetError, match="no camera poses"):
            open_sequence(tmp_path, use_poses=True)


# --------------------------------------------------------------------------- tiny folders


def write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if image.ndim == 3:
        image = image[..., ::-1]  # RGB -> BGR for OpenCV
    assert cv2.imwrite(str(path), image)


def color_image(h: int = 6, w: int = 8, value: tuple[int, int, int] = (200, 100, 50)) -> np.ndarray:
    return np.broadcast_to(np.array(value, np.uint8), (h, w, 3)).copy()


def depth_image(h: int = 6, w: int = 8, metres: float = 1.5, scale: float = 5000.0) -> np.ndarray:
    return np.full((h, w), int(round(metres * scale)), np.uint16)


def make_tum(
    folder: Path, n: int = 3, assoc: bool = True, gt: bool = True, camera_json: str | None = None
) -> Path:
    rgb_lines, depth_lines, assoc_lines = ["# color"], ["# depth"], []
    for i in range(n):
        t = 100.0 + i / 30.0
        write_png(folder / "rgb" / f"{i}.png", color_image(value=(10 * i, 100, 50)))
        write_png(folder / "depth" / f"{i}.png", depth_image(metres=1.0 + i))
        rgb_lines.append(f"{t:.6f} rgb/{i}.png")
        depth_lines.append(f"{t + 0.01:.6f} depth/{i}.png")
        assoc_lines.append(f"{t:.6f} rgb/{i}.png {t + 0.01:.6f} depth/{i}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if assoc:
        (folder / "associations.txt").write_text("\n".join(assoc_lines) + "\n")
    if gt:
        rows = ["# timestamp tx ty tz qx qy qz qw"]
        for i in range(n):
            rows.append(f"{100.0 + i / 30.0 + 0.003:.6f} {i} 2 3 0 0 0.7071068 0.7071068")
        (folder / "groundtruth.txt").write_text("\n".join(rows) + "\n")
    if camera_json is not None:
        (folder / "camera.json").write_text(camera_json)
    return folder


class TestTinyTum:
    def test_associates_by_timestamp_without_associations(self, tmp_path):
        folder = make_tum(tmp_path, n=3, assoc=False)
        # a colour image with no depth within 0.02 s is skipped
        with open(folder / "rgb.txt", "a") as fh:
            fh.write("200.0 rgb/0.png\n")
        seq = open_sequence(folder, use_poses=True)
        assert len(seq) == 3
        f = seq.frame(2)
        assert f.color[0, 0].tolist() == [20, 100, 50]
        np.testing.assert_allclose(metres(f), 3.0)
        assert f.timestamp == pytest.approx(100.0 + 2 / 30.0)
        np.testing.assert_allclose(f.pose[:3, 3], [2, 2, 3])
        np.testing.assert_allclose(f.pose[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)
        assert any("within 0.02 s" in n for n in seq.notes)

    def test_camera_json_and_depth_scale(self, tmp_path):
        folder = make_tum(
            tmp_path,
            camera_json='{"fx": 10, "fy": 11, "cx": 3.5, "cy": 2.5, '
            '"width": 8, "height": 6, "depth_scale": 1000}',
        )
        seq = open_sequence(folder)
        assert seq.camera == PinholeCamera(8, 6, 10.0, 11.0, 3.5, 2.5)
        np.testing.assert_allclose(metres(seq.frame(0)), 5.0)  # 5000 units at 1000 / m
        assert seq.frame(0).depth_scale == 1000.0

    def test_pose_too_far_in_time_drops_frame(self, tmp_path):
        folder = make_tum(tmp_path, n=3)
        gt = folder / "groundtruth.txt"
        lines = gt.read_text().splitlines()
        gt.write_text("\n".join(lines[:2]) + "\n")  # one pose: frame 2 is 0.064 s away
        seq = open_sequence(folder, use_poses=True)
        assert len(seq) == 2
        assert len(open_sequence(folder)) == 3

    def test_listed_but_absent_files_are_skipped(self, tmp_path):
        folder = make_tum(tmp_path, n=3)
        (folder / "rgb" / "1.png").unlink()
        seq = open_sequence(folder)
        assert len(seq) == 2
        assert any("absent" in n for n in seq.notes)


class TestBadInput:
    def test_missing_folder(self, tmp_path):
        with pytest.raises(DatasetError, match="no such file or folder"):
            open_sequence(tmp_path / "nope")

    def test_unknown_folder_lists_what_was_looked_for(self, tmp_path):
        (tmp_path / "notes.txt").write_text("hello")
        with pytest.raises(DatasetError) as err:
            open_sequence(tmp_path)
        msg = str(err.value)
        for looked_for in ("TUM", "rgb.txt", "Redwood", "7-Scenes", "colour + depth"):
            assert looked_for in msg

    def test_unreadable_color(self, tmp_path):
        folder = make_tum(tmp_path, n=2)
        (folder / "rgb" / "0.png").write_bytes(b"not a png")
        with pytest.raises(DatasetError, match=r"0\.png.*cannot decode"):
            open_sequence(folder)

    def test_unreadable_later_frame_fails_on_access(self, tmp_path):
        folder = make_tum(tmp_path, n=2)
        (folder / "depth" / "1.png").write_bytes(b"")
        seq = open_sequence(folder)
        with pytest.raises(DatasetError, match=r"1\.png"):
            seq.frame(1)

    def test_all_listed_files_missing_is_empty(self, tmp_path):
        folder = make_tum(tmp_path, n=2)
        for p in (folder / "rgb").iterdir():
            p.unlink()
        with pytest.raises(DatasetError, match="empty sequence"):
            open_sequence(folder)

    def test_empty_lists(self, tmp_path):
        (tmp_path / "rgb.txt").write_text("# nothing\n")
        (tmp_path / "depth.txt").write_text("# nothing\n")
        with pytest.raises(DatasetError, match="empty sequence"):
            open_sequence(tmp_path)

    def test_only_rgb_txt(self, tmp_path):
        (tmp_path / "rgb.txt").write_text("1.0 rgb/0.png\n")
        with pytest.raises(DatasetError, match="depth.txt"):
            open_sequence(tmp_path)

    def test_sizes_differ(self, tmp_path):
        folder = make_tum(tmp_path, n=1)
        write_png(folder / "depth" / "0.png", depth_image(h=5, w=7))
        with pytest.raises(DatasetError, match=r"8x6.*7x5"):
            open_sequence(folder)

    def test_camera_size_differs_from_images(self, tmp_path):
        folder = make_tum(
            tmp_path,
            n=1,
            camera_json='{"fx": 10, "fy": 10, "cx": 3, "cy": 2, "width": 640, "height": 480}',
        )
        with pytest.raises(DatasetError, match=r"8x6.*640x480"):
            open_sequence(folder)

    def test_bad_camera_json(self, tmp_path):
        folder = make_tum(tmp_path, n=1, camera_json='{"fx": 10, "fy": 10, "cx": 3, "cy": 2}')
        with pytest.raises(DatasetError, match=r"camera.json.*'width'"):
            open_sequence(folder)

    def test_depth_not_uint16(self, tmp_path):
        folder = make_tum(tmp_path, n=1)
        write_png(folder / "depth" / "0.png", np.full((6, 8), 7, np.uint8))
        with pytest.raises(DatasetError, match="uint16"):
            open_sequence(folder)

    def test_malformed_lines(self, tmp_path):
        folder = make_tum(tmp_path, n=2)
        (folder / "associations.txt").write_text("1.0 rgb/0.png\n")
        with pytest.raises(DatasetError, match=r"associations.txt, line 1"):
            open_sequence(folder)
        folder = make_tum(tmp_path / "b", n=2)
        (folder / "groundtruth.txt").write_text("100.0 0 0 0 0 0 0 0\n")
        with pytest.raises(DatasetError, match=r"groundtruth.txt, line 1"):
            open_sequence(folder, use_poses=True)
        assert len(open_sequence(folder)) == 2  # poses not asked for: not read

    def test_arguments(self, tmp_path):
        folder = make_tum(tmp_path, n=1)
        with pytest.raises(DatasetError, match="unknown depth encoding 'cm'"):
            open_sequence(folder, depth_encoding="cm")
        with pytest.raises(DatasetError, match="--max-frames"):
            open_sequence(folder, max_frames=0)

    def test_redwood_empty_and_missing_poses(self, tmp_path):
        (tmp_path / "color").mkdir()
        (tmp_path / "depth").mkdir()
        with pytest.raises(DatasetError, match="empty sequence"):
            open_sequence(tmp_path)
        write_png(tmp_path / "color" / "00000.png", color_image())
        write_png(tmp_path / "depth" / "00000.png", depth_image(scale=1000.0))
        seq = open_sequence(tmp_path)
        assert seq.format == "redwood" and len(seq) == 1
        np.testing.assert_allclose(metres(seq.frame(0)), 1.5)
        with pytest.raises(DatasetError, match="trajectory.log"):
            open_sequence(tmp_path, use_poses=True)
        (tmp_path / "trajectory.log").write_text("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n")
        with pytest.raises(DatasetError, match="multiple of 5"):
            open_sequence(tmp_path, use_poses=True)
        (tmp_path / "camera_intrinsic.json").write_text('{"width": 8, "height": 6}')
        with pytest.raises(DatasetError, match="intrinsic_matrix"):
            open_sequence(tmp_path)

    def test_seven_scenes_bad_pose_and_several_sequences(self, tmp_path):
        seq_dir = tmp_path / "seq-01"
        write_png(seq_dir / "frame-000000.color.png", color_image(48, 64))
        write_png(seq_dir / "frame-000000.depth.png", depth_image(48, 64, scale=1000.0))
        (seq_dir / "frame-000000.pose.txt").write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
        seq = open_sequence(seq_dir)
        assert seq.format == "7scenes" and seq.camera.width == 64
        assert any("camera-intrinsics.txt" in n for n in seq.notes)
        with pytest.raises(DatasetError, match=r"pose.txt.*not a rigid"):
            open_sequence(seq_dir, use_poses=True)
        (tmp_path / "seq-02").symlink_to(seq_dir, target_is_directory=True)
        with pytest.raises(DatasetError, match="2 7-Scenes sequences"):
            open_sequence(tmp_path)

    def test_pair_errors(self, tmp_path):
        write_png(tmp_path / "a_color.png", color_image())
        write_png(tmp_path / "a_depth.png", depth_image())
        with pytest.raises(DatasetError, match="--depth-encoding"):
            open_pair(tmp_path / "a_color.png", tmp_path / "a_depth.png", None)
        with pytest.raises(DatasetError, match="--depth-encoding"):
            open_sequence(tmp_path / "a_color.png")
        seq = open_sequence(tmp_path / "a_color.png", depth_encoding="mm")
        np.testing.assert_allclose(metres(seq.frame(0)), 7.5)
        write_png(tmp_path / "b_color.png", color_image())
        with pytest.raises(DatasetError, match="no depth partner"):
            open_sequence(tmp_path / "b_color.png", depth_encoding="mm")
        write_png(tmp_path / "c.png", color_image())
        with pytest.raises(DatasetError, match="--depth FILE"):
            open_sequence(tmp_path / "c.png", depth_encoding="mm")
        with pytest.raises(DatasetError, match="does not exist"):
            open_pair(
                tmp_path / "a_color.png",
                tmp_path / "nope.png",
                "mm",
                camera=PinholeCamera.kinect_v1(8, 6),
            )
        with pytest.raises(DatasetError, match="not raw Kinect disparity"):
            open_pair(tmp_path / "a_color.png", tmp_path / "a_depth.png", "nyu")


# --------------------------------------------------------------------------- decoding


class TestDecodeDepth:
    def test_tum_and_mm(self):
        raw = np.array([[0, 5000, 65535]], np.uint16)
        np.testing.assert_allclose(depth_metres(*decode_depth(raw, "tum")), [[0.0, 1.0, 0.0]])
        np.testing.assert_allclose(depth_metres(*decode_depth(raw, "mm")), [[0.0, 5.0, 0.0]])
        units, scale = decode_depth(raw, "tum")
        assert units.dtype == np.uint16 and units.tolist() == [[0, 5000, 0]] and scale == 5000.0
        assert decode_depth(raw, "mm", units_per_metre=2000.0)[1] == 2000.0

    def test_sun_bit_rotation(self):
        mm = np.array([0, 1234, 8191, 9870], np.uint32)
        stored = (((mm << 3) | (mm >> 13)) & 0xFFFF).astype(np.uint16)
        np.testing.assert_allclose(
            depth_metres(*decode_depth(stored[None], "sun"))[0], mm / 1000.0, rtol=1e-6
        )
        units, scale = decode_depth(stored[None], "sun")
        assert units[0].tolist() == mm.tolist() and scale == 1000.0  # the millimetre integers

    def test_nyu(self):
        disparity = np.array([[2047, 1092, 1200, 1000, 300]], np.uint16)
        expected = [0.0, 0.0, 0.0, 351.3 / 92.5, 351.3 / 792.5]  # missing, >10 m, negative
        # quantised at NYU_DEPTH_SCALE units per metre (disparity is not linear in depth)
        expected = np.rint(np.array(expected) * NYU_DEPTH_SCALE) / NYU_DEPTH_SCALE
        np.testing.assert_allclose(
            depth_metres(*decode_depth(disparity.byteswap(), "nyu")), [expected], rtol=1e-6
        )
        np.testing.assert_allclose(
            depth_metres(*decode_depth(disparity, "nyu")), [expected], rtol=1e-6
        )
        assert decode_depth(disparity, "nyu")[1] == NYU_DEPTH_SCALE

    def test_metres_to_units_edges(self):
        depth = np.array([[0.0, np.nan, -1.0, np.inf], [1.0, 1.00009, 13.1, 20.0]], np.float32)
        units = metres_to_units(depth, 5000.0)
        assert units.dtype == np.uint16
        assert units.tolist() == [[0, 0, 0, 0], [5000, 5000, 65500, 0]]

    def test_quaternion_to_matrix(self):
        q = [0.1, -0.2, 0.3, 0.9]  # x, y, z, w as TUM writes them; not unit length
        np.testing.assert_allclose(
            quaternion_to_matrix(*q), Rotation.from_quat(q).as_matrix(), atol=1e-12
        )
        np.testing.assert_allclose(
            quaternion_to_matrix(0, 0, 0.7071068, 0.7071068),
            [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
            atol=1e-6,
        )
        with pytest.raises(ValueError, match="no direction"):
            quaternion_to_matrix(0, 0, 0, 0)

    def test_read_color_converts_grey_and_bgr(self, tmp_path):
        write_png(tmp_path / "g.png", np.full((2, 3), 9, np.uint8))
        assert read_color(tmp_path / "g.png").shape == (2, 3, 3)
        write_png(tmp_path / "c.png", color_image(2, 3, (1, 2, 3)))
        assert read_color(tmp_path / "c.png")[0, 0].tolist() == [1, 2, 3]


class TestRegisterDepth:
    def test_identity_is_exact(self):
        cam = PinholeCamera(8, 6, 5.0, 5.0, 3.5, 2.5)
        depth = np.linspace(0.5, 3.0, 48, dtype=np.float32).reshape(6, 8)
        depth[2, 3] = 0.0
        np.testing.assert_allclose(register_depth(depth, cam, cam, np.eye(4)), depth, rtol=1e-6)

    def test_nearest_surface_wins(self):
        # a depth camera with twice the focal length: pixel pairs land on one colour pixel
        depth_cam = PinholeCamera(8, 1, 10.0, 10.0, 3.5, 0.0)
        color_cam = PinholeCamera(4, 1, 5.0, 5.0, 1.5, 0.0)
        depth = np.array([[2.0, 1.0, 3.0, 4.0, 1.5, 0.0, 2.0, 2.5]], np.float32)
        out = register_depth(depth, depth_cam, color_cam, np.eye(4))
        np.testing.assert_allclose(out, [[1.0, 3.0, 1.5, 2.0]])

    def test_translation_shifts(self):
        cam = PinholeCamera(8, 1, 10.0, 10.0, 3.5, 0.0)
        depth = np.full((1, 8), 2.0, np.float32)
        m = np.eye(4)
        m[0, 3] = 0.2  # 0.2 m to the right at 2 m, f = 10 px: 1 px
        out = register_depth(depth, cam, cam, m)
        assert out[0, 0] == 0.0 and np.all(out[0, 1:] == 2.0)


class TestPackage:
    def test_sources_never_import_client_or_server(self):
        """The dependency direction: client -> sources -> pipeline, protocols."""
        import subprocess
        import sys

        code = (
            "import sys, arlight.sources.source\n"
            "bad = sorted(m for m in sys.modules\n"
            "             if m.startswith(('arlight.client', 'arlight.server')))\n"
            "print(bad); sys.exit(1 if bad else 0)"
        )
        done = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=120
        )
        assert done.returncode == 0, done.stdout + done.stderr
