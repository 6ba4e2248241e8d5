"""The ground-truth generator (`arlight synth`): truth, files, the corpus, bad input.

The tiny renders (32x24 pixels, 2 frames, 4 samples per pixel) run in CI with the real
Mitsuba 3 (the test extra); the comparison with the shared sequences reads ../shared/data
and skips without it.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import DATA, needs_data, run_cli

from arlight.cli import EXIT_BAD_INPUT, main
from arlight.evaluation import angular_error_deg
from arlight.pipeline import sh
from arlight.synth import environment as env
from arlight.synth import meshes
from arlight.synth.corpus import coverage, load_definition, make_definition
from arlight.synth.layouts import LAYOUTS, build_layout

needs_shared_sequences = needs_data(DATA / "synthetic")
mitsuba = pytest.importorskip("mitsuba", reason="the synth extra (Mitsuba 3) is not installed")

PATCH_DIR_MAP = np.array([0.6, 0.55, -0.58])  # the bright patch, the map's own frame
ROTATION_DEG = 30.0


def write_patch_map(path: Path, height: int = 64) -> np.ndarray:
    """A dim uniform map with one bright patch towards PATCH_DIR_MAP; returns the map."""
    width = 2 * height
    rgb = np.full((height, width, 3), 0.002, np.float32)
    dirs, _ = env.texel_directions(height, width)
    d = PATCH_DIR_MAP / np.linalg.norm(PATCH_DIR_MAP)
    rgb[dirs @ d > math.cos(math.radians(6))] = 200.0
    cv2.imwrite(str(path), rgb[..., ::-1])
    return rgb


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny static sequence under the patch map, with an AR pair at frame 1."""
    root = tmp_path_factory.mktemp("synth")
    write_patch_map(root / "patch.hdr")
    seq = root / "tiny_static"
    code = main(
        [
            "synth",
            "--map",
            str(root / "patch.hdr"),
            "--rotation",
            str(ROTATION_DEG),
            "--layout",
            "static",
            "--frames",
            "2",
            "--size",
            "32x24",
            "--spp",
            "4",
            "--ar-frames",
            "1",
            "--out",
            str(seq),
        ]
    )
    assert code == 0
    return seq


class TestTruth:
    def test_patch_direction_in_lighting_gt(self, tiny):
        gt = json.loads((tiny / "lighting_gt.json").read_text())
        want = env.rotation_y(ROTATION_DEG) @ (PATCH_DIR_MAP / np.linalg.norm(PATCH_DIR_MAP))
        for frame in gt["frames"]:
            got = np.asarray(frame["dominant_dir_upper_world"])
            assert angular_error_deg(got, want) < 1.0
            # the same direction through the pipeline's own SH code (file basis -> ours)
            ours = sh.toggle_condon_shortley(np.asarray(frame["sh_lum_upper_world"]))
            assert angular_error_deg(sh.dominant_direction(ours), want) < 1.0

    def test_camera_frame_is_the_pose_applied(self, tiny):
        gt = json.loads((tiny / "lighting_gt.json").read_text())
        rows = [
            line.split()
            for line in (tiny / "groundtruth.txt").read_text().splitlines()
            if not line.startswith("#")
        ]
        from scipy.spatial.transform import Rotation

        for frame, row in zip(gt["frames"], rows, strict=True):
            r_wc = Rotation.from_quat([float(x) for x in row[4:8]]).as_matrix()
            world = np.asarray(frame["dominant_dir_upper_world"])
            assert angular_error_deg(r_wc.T @ world, frame["dominant_dir_upper_camera"]) < 1e-3

    def test_mitsuba_sees_the_patch_where_the_truth_puts_it(self, tiny):
        """The probe is path-traced by Mitsuba's emitter; its upper-hemisphere light must
        point where the texel truth does (a wrong rotation convention would miss by 60 deg)."""
        gt = json.loads((tiny / "lighting_gt.json").read_text())
        for frame in gt["frames"]:
            assert (
                angular_error_deg(
                    frame["probe"]["dominant_dir_upper_world"], frame["dominant_dir_upper_world"]
                )
                < 5.0
            )

    @needs_shared_sequences
    @pytest.mark.data
    def test_same_truth_as_the_shared_sequences(self):
        """Same map, rotation and pose as a shared frame -> the same truth within 1 degree."""
        from scipy.spatial.transform import Rotation

        for name in ("dev_a_static_venice", "dev_c_lightswitch_forest_kiara"):
            folder = DATA / "synthetic" / name
            gt = json.loads((folder / "lighting_gt.json").read_text())
            rows = [
                line.split()
                for line in (folder / "groundtruth.txt").read_text().splitlines()
                if not line.startswith("#")
            ]
            for frame in gt["frames"][::8]:
                radiance = env.load_map(DATA / "hdri" / f"{frame['env_map']}.hdr")
                truth = env.environment_truth(radiance, frame["env_rotation_deg"])
                r_wc = Rotation.from_quat([float(x) for x in rows[frame["index"]][4:8]]).as_matrix()
                upper = env.dominant(truth.sh_lum_upper_world)
                whole = env.dominant(truth.sh_lum_world)
                assert angular_error_deg(upper, frame["dominant_dir_upper_world"]) < 1.0
                assert angular_error_deg(whole, frame["dominant_dir_world"]) < 1.0
                assert angular_error_deg(r_wc.T @ upper, frame["dominant_dir_upper_camera"]) < 1.0
                np.testing.assert_allclose(
                    env.to_file_convention(truth.sh_lum_world),
                    frame["sh_lum_world"],
                    atol=0.01 * abs(frame["sh_lum_world"][0]),
                )

    def test_compact_region_of_a_coloured_sun(self):
        """A warm disc on a blue sky: the region holds the disc, its colour is the disc's
        (rgb / power has luminance 1), and its power is the disc's integrated luminance."""
        from arlight.pipeline.color import LUMA

        h, w = 64, 128
        radiance = np.zeros((h, w, 3), np.float32)
        radiance[..., 2] = 0.2  # sky, blue
        dirs, solid = env.texel_directions(h, w)
        sun = np.array([0.0, math.sin(math.radians(40)), -math.cos(math.radians(40))])
        disc = dirs @ sun > math.cos(math.radians(3.0))
        radiance[disc] = (50.0, 35.0, 20.0)
        region = env.brightest_compact_region(radiance, 0.0)
        assert angular_error_deg(region.direction, sun) < 2.0
        colour = region.rgb / region.power
        assert abs(float(LUMA @ colour) - 1.0) < 1e-9
        np.testing.assert_allclose(colour / colour[0], (1.0, 0.7, 0.4), rtol=1e-6)
        weights = np.repeat(solid[:, None], w, axis=1)[disc]
        expected = float(np.sum(weights) * (LUMA @ np.array((50.0, 35.0, 20.0))))
        assert abs(region.power - expected) < 1e-3 * expected

    def test_compact_regions_of_two_lamps(self):
        """Two lamps 60 degrees apart: both are found, the brighter first, each at its
        disc; a share above the dimmer one's keeps only the first; the first region is the
        brightest_compact_region."""
        h, w = 64, 128
        radiance = np.full((h, w, 3), 0.05, np.float32)
        dirs, _ = env.texel_directions(h, w)
        lamps = []
        for elevation, azimuth, level in ((40.0, 0.0, 60.0), (30.0, 60.0, 20.0)):
            e, a = math.radians(elevation), math.radians(azimuth)
            lamp = np.array([math.cos(e) * math.sin(a), math.sin(e), -math.cos(e) * math.cos(a)])
            radiance[dirs @ lamp > math.cos(math.radians(3.0))] = level
            lamps.append(lamp)
        regions = env.compact_regions(radiance, 0.0, 4, 0.05)
        assert len(regions) == 2
        for region, lamp in zip(regions, lamps, strict=True):
            assert angular_error_deg(region.direction, lamp) < 2.0
        assert regions[0].power > 2.5 * regions[1].power
        first = env.brightest_compact_region(radiance, 0.0)
        np.testing.assert_allclose(first.direction, regions[0].direction)
        assert first.share == regions[0].share
        only = env.compact_regions(radiance, 0.0, 4, regions[1].share + 0.01)
        assert len(only) == 1


class TestFiles:
    def test_layout_of_the_shared_set(self, tiny):
        for item in (
            "rgb/000000.png",
            "depth/000001.png",
            "depth_gt/000000.png",
            "rgb.txt",
            "depth.txt",
            "associations.txt",
            "groundtruth.txt",
            "camera.json",
            "lighting_gt.json",
            "ar/real/000001.png",
            "ar/real_virtual/000001.png",
            "ar/mask_virtual/000001.png",
            "ar/mask_affected/000001.png",
            "ar/virtual_scene.json",
            "ar/virtual_sphere.ply",
            "ar/virtual_arch.ply",
        ):
            assert (tiny / item).is_file(), item
        camera = json.loads((tiny / "camera.json").read_text())
        assert (camera["width"], camera["height"], camera["depth_scale"]) == (32, 24, 5000.0)
        assert camera["fx"] == pytest.approx(525.0 * 32 / 640)
        depth = cv2.imread(str(tiny / "depth_gt" / "000000.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16 and depth.shape == (24, 32) and depth.max() > 0

    def test_albedo_file_is_the_intrinsic_image(self, tiny):
        """albedo/: 16-bit linear RGB, 0 where the environment is seen, a reflectance
        (0.02-0.9, the generator's range) on the surfaces."""
        for i in (0, 1):
            albedo = cv2.imread(str(tiny / "albedo" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
            depth = cv2.imread(str(tiny / "depth_gt" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
            assert albedo.dtype == np.uint16 and albedo.shape == (24, 32, 3)
            a = albedo.astype(np.float64) / 65535
            # a pixel's albedo averages its footprint, the depth is its centre's: test
            # pixels whose neighbours agree
            environment = cv2.erode((depth == 0).astype(np.uint8), np.ones((3, 3))) > 0
            assert environment.any() and np.all(a[environment] == 0.0)
            inner = cv2.erode((depth > 0).astype(np.uint8), np.ones((3, 3))) > 0
            assert inner.mean() > 0.3
            assert np.all((a[inner] > 0.015) & (a[inner] < 0.91))

    def test_albedo_is_each_surface_material(self, tmp_path):
        """Every untextured surface in view shows its material's albedo (the aov renders the
        reflectance the path tracer shades with, per pixel, under any light)."""
        from arlight.synth import render

        write_patch_map(tmp_path / "patch.hdr")
        layout = build_layout("static", 2, 2)  # three plain materials in view at 64x48
        shapes = layout.shapes_at(0)
        camera = render.Camera(64, 48, 525.0 * 64 / 640, 525.0 * 64 / 640)
        scene = render.SceneRenderer(shapes, tmp_path / "patch.hdr", 0.0)
        try:
            albedo = scene.render_albedo(camera, layout.poses[0], seed=0)
        finally:
            scene.close()
        _, ids = render.GeometryCaster(shapes).cast(camera, layout.poses[0])
        environment = cv2.erode((ids < 0).astype(np.uint8), np.ones((3, 3))) > 0
        assert environment.any() and np.all(albedo[environment] == 0.0)
        checked = 0
        for k, shape in enumerate(shapes):
            inner = cv2.erode((ids == k).astype(np.uint8), np.ones((3, 3))) > 0
            if shape.material.textured or inner.sum() < 5:
                continue
            np.testing.assert_allclose(
                np.median(albedo[inner], axis=0), shape.material.albedo_rgb, atol=0.01
            )
            checked += 1
        assert checked == 3

    def test_depth_is_the_rendered_geometry(self, tiny):
        """Pixels the clean depth says hit nothing show the environment (no depth)."""
        depth = cv2.imread(str(tiny / "depth_gt" / "000000.png"), cv2.IMREAD_UNCHANGED)
        gt = json.loads((tiny / "lighting_gt.json").read_text())
        assert gt["truth_reference"] == "distant" and gt["layout"] == "static"
        assert (depth > 0).mean() > 0.5  # a camera looking down at the ground

    def test_loads_with_arlight_estimate(self, tiny, tmp_path, capsys):
        out = tmp_path / "r.jsonl"
        code, text = run_cli(
            [
                "estimate",
                str(tiny),
                "--poses",
                "groundtruth",
                "--preset",
                "fast",
                "--out",
                str(out),
            ],
            capsys,
        )
        assert code == 0, text
        assert len(out.read_text().splitlines()) == 2

    def test_virtual_scene_loads(self, tiny):
        from arlight.sources.virtual_scene_file import load_virtual_scene

        scene = load_virtual_scene(tiny / "ar" / "virtual_scene.json")
        assert [o.name for o in scene.objects] == ["virtual_sphere", "virtual_arch"]

    def test_resumes_and_skips_what_is_complete(self, tiny, capsys):
        before = (tiny / "lighting_gt.json").stat().st_mtime_ns
        code, text = run_cli(
            [
                "synth",
                "--map",
                str(tiny.parent / "patch.hdr"),
                "--out",
                str(tiny),
                "--frames",
                "2",
                "--size",
                "32x24",
                "--spp",
                "4",
            ],
            capsys,
        )
        assert code == 0 and "complete already" in text
        assert (tiny / "lighting_gt.json").stat().st_mtime_ns == before


class TestBadInput:
    def test_missing_map(self, tmp_path, capsys):
        code, text = run_cli(
            ["synth", "--map", str(tmp_path / "nope.hdr"), "--out", str(tmp_path / "s")], capsys
        )
        assert code == EXIT_BAD_INPUT and "--map" in text and "no such file" in text

    def test_map_not_two_to_one(self, tmp_path, capsys):
        cv2.imwrite(str(tmp_path / "square.hdr"), np.ones((16, 16, 3), np.float32))
        code, text = run_cli(
            ["synth", "--map", str(tmp_path / "square.hdr"), "--out", str(tmp_path / "s")], capsys
        )
        assert code == EXIT_BAD_INPUT and "--map" in text and "twice the height" in text

    def test_unknown_layout(self, tmp_path, capsys):
        code, text = run_cli(
            ["synth", "--map", "x.hdr", "--layout", "castle", "--out", str(tmp_path / "s")], capsys
        )
        assert code == EXIT_BAD_INPUT and "--layout" in text

    def test_negative_seed(self, tmp_path, capsys):
        write_patch_map(tmp_path / "p.hdr", 8)
        code, text = run_cli(
            [
                "synth",
                "--map",
                str(tmp_path / "p.hdr"),
                "--seed",
                "-3",
                "--out",
                str(tmp_path / "s"),
            ],
            capsys,
        )
        assert code == EXIT_BAD_INPUT and "--seed" in text and "Traceback" not in text

    def test_more_rotations_than_maps(self, tmp_path, capsys):
        code, text = run_cli(
            [
                "synth",
                "--map",
                "x.hdr",
                "--rotation",
                "1",
                "--rotation",
                "2",
                "--out",
                str(tmp_path / "s"),
            ],
            capsys,
        )
        assert code == EXIT_BAD_INPUT and "--rotation" in text

    @pytest.mark.parametrize("doc", ['{"sequences": [{"name": "x"}]}', "[1]", "{not json"])
    def test_broken_corpus_definition(self, tmp_path, capsys, doc):
        (tmp_path / "c.json").write_text(doc)
        code, text = run_cli(
            ["synth", "--corpus", str(tmp_path / "c.json"), "--out", str(tmp_path / "out")], capsys
        )
        assert code == EXIT_BAD_INPUT and "--corpus" in text and "Traceback" not in text

    def test_extra_not_installed(self, tmp_path, capsys, monkeypatch):
        write_patch_map(tmp_path / "p.hdr", 8)
        monkeypatch.setitem(sys.modules, "mitsuba", None)  # import mitsuba -> ImportError
        code, text = run_cli(
            [
                "synth",
                "--map",
                str(tmp_path / "p.hdr"),
                "--out",
                str(tmp_path / "s"),
                "--size",
                "8x8",
            ],
            capsys,
        )
        assert code == EXIT_BAD_INPUT and "arlight[synth]" in text
        assert "Traceback" not in text


class TestCorpus:
    def test_committed_definition_is_the_generated_one(self):
        assert load_definition() == json.loads(json.dumps(make_definition()))

    def test_rules(self):
        definition = load_definition()
        cover = coverage(definition)
        assert len(definition["sequences"]) >= 60
        assert len(cover["sequences_per_map"]) == 26
        assert min(cover["sequences_per_map"].values()) >= 2
        assert set(cover["maps_per_layout"]) == set(LAYOUTS)
        assert min(cover["maps_per_layout"].values()) >= 8

    @needs_shared_sequences
    @pytest.mark.data
    def test_every_map_is_a_shared_map(self):
        for name in load_definition()["maps"]:
            assert (DATA / "hdri" / f"{name}_1k.hdr").is_file(), name


class TestGeometry:
    @pytest.mark.parametrize(
        "mesh",
        [
            meshes.box((0.2, 0.3, 0.1)),
            meshes.uv_sphere(0.3),
            meshes.cylinder(0.1, 0.4),
            meshes.arch(),
        ],
        ids=["box", "sphere", "cylinder", "arch"],
    )
    def test_faces_wind_outwards(self, mesh):
        v = mesh.vertices[mesh.faces]
        face_normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        vertex_normal = mesh.normals[mesh.faces].mean(axis=1)
        assert np.all(np.einsum("ij,ij->i", face_normal, vertex_normal) > 0)

    @pytest.mark.parametrize("name", LAYOUTS)
    def test_layouts_are_deterministic_and_leave_room_for_the_objects(self, name):
        a, b = build_layout(name, 5, 6), build_layout(name, 5, 6)
        assert [s.describe() for s in a.shapes] == [s.describe() for s in b.shapes]
        assert np.allclose(np.stack(a.poses), np.stack(b.poses))
        for shape in a.shapes:  # no real object within the anchor's reach
            if shape.kind in ("sphere", "box", "cylinder") and shape.name.startswith("obj"):
                d = np.linalg.norm((shape.world_from_shape[:3, 3] - a.anchor_world)[[0, 2]])
                assert d > 0.1 * a.virtual_scale
