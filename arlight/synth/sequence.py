"""One generated sequence: render every frame (resumable), then write the shared set's layout.

A sequence folder is written under a temporary name and renamed when complete, so a folder
with ``lighting_gt.json`` is always whole. Rendered frames are kept in ``<out>/.work/<name>/``
(one ``.npz`` per frame) until the sequence is written, so an interrupted run resumes at the
frame it stopped at. File layout and conventions: ``../shared/data/synthetic/README.md``;
what this generator adds is written into ``lighting_gt.json`` itself (``layout``,
``truth_reference`` and each frame's ``probe``), and ``albedo/``: each frame's true albedo.
"""

from __future__ import annotations

import json
import shutil
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from arlight.evaluation import angular_error_deg
from arlight.pipeline import sh
from arlight.pipeline.color import LUMA
from arlight.synth import environment as env
from arlight.synth import render, sensor
from arlight.synth.layouts import DESCRIPTION, LAYOUTS, Layout, LayoutError, build_layout
from arlight.synth.meshes import write_ply
from arlight.synth.virtual_objects import VIRTUAL_MATERIALS, object_meshes, virtual_shapes

FIRST_TIMESTAMP_S = 1000.0
FRAME_RATE_HZ = 30.0
KINECT_F_AT_640 = 525.0  # focal length in pixels at 640 wide (Kinect v1)
AFFECTED_REL_CHANGE = 0.02
AFFECTED_BLUR_SIGMA_PX = 1.5


@dataclass(frozen=True)
class LightState:
    """From frame `from_frame` on, the scene is lit by `map_name` rotated by `rotation_deg`."""

    map_name: str
    rotation_deg: float
    from_frame: int = 0


@dataclass(frozen=True)
class SequenceSpec:
    """Everything that fixes a sequence (a corpus entry, or `arlight synth` arguments)."""

    name: str
    layout: str
    seed: int
    lights: tuple[LightState, ...]
    frames: int = 8
    width: int = 640
    height: int = 480
    spp: int = 32
    max_depth: int = 4
    ar_frames: tuple[int, ...] = ()
    virtual_material: str = "diffuse"
    probe_size: int = 32  # texels a cube face side
    probe_spp: int = 64

    def check(self, map_folder: Path) -> None:
        """Raise ValueError naming the CLI flag for anything unusable."""
        if self.layout not in LAYOUTS:
            raise LayoutError(
                f"--layout {self.layout!r} is not a layout; choose from {', '.join(LAYOUTS)}"
            )
        if not 1 <= self.frames <= 10000:
            raise ValueError(f"--frames must be in 1..10000, got {self.frames}")
        if self.width < 8 or self.height < 8 or self.width > 4096 or self.height > 4096:
            raise ValueError(f"--size {self.width}x{self.height}: each side must be 8..4096")
        if not 1 <= self.spp <= 65536:
            raise ValueError(f"--spp must be in 1..65536, got {self.spp}")
        if self.seed < 0:
            raise ValueError(f"--seed must be >= 0, got {self.seed}")
        if self.virtual_material not in VIRTUAL_MATERIALS:
            raise ValueError(
                f"--virtual-material {self.virtual_material!r}: choose from "
                f"{', '.join(VIRTUAL_MATERIALS)}"
            )
        if not self.lights or self.lights[0].from_frame != 0:
            raise ValueError("--map: the first map must light frame 0")
        bad = [f for f in self.ar_frames if not 0 <= f < self.frames]
        if bad:
            raise ValueError(f"--ar-frames {bad}: frames are 0..{self.frames - 1}")
        for light in self.lights:
            env.load_map(map_path(map_folder, light.map_name))  # exists, readable, 2:1

    @property
    def fx(self) -> float:
        return KINECT_F_AT_640 * self.width / 640.0

    def light_at(self, frame: int) -> LightState:
        return [s for s in self.lights if s.from_frame <= frame][-1]


def map_path(folder: Path, name: str) -> Path:
    """The file of map `name` (a path, or a name in `folder` with or without _1k.hdr)."""
    p = Path(name)
    if p.suffix.lower() in env.MAP_SUFFIXES:
        return p if p.is_absolute() or p.exists() else folder / p
    for candidate in (folder / f"{name}.hdr", folder / f"{name}_1k.hdr", folder / f"{name}.exr"):
        if candidate.is_file():
            return candidate
    return folder / f"{name}.hdr"


def map_label(name: str) -> str:
    """The map's name as lighting_gt.json records it (file stem, e.g. venice_sunset_1k)."""
    return (
        Path(name).stem if Path(name).suffix else (name if name.endswith("_1k") else f"{name}_1k")
    )


@dataclass
class RenderStats:
    frames_rendered: int = 0
    seconds: float = 0.0
    renders: int = 0
    per_frame_s: list[float] = field(default_factory=list)


def generate(
    spec: SequenceSpec, out_root: Path, map_folder: Path, on_frame: Callable[[], None] | None = None
) -> RenderStats:
    """Render `spec` into out_root/spec.name (skipped when already complete)."""
    final = out_root / spec.name
    stats = RenderStats()
    if (final / "lighting_gt.json").is_file():
        return stats
    spec.check(map_folder)
    render.mitsuba()
    layout = build_layout(spec.layout, spec.seed, spec.frames)
    work = out_root / ".work" / spec.name
    work.mkdir(parents=True, exist_ok=True)
    camera = render.Camera(spec.width, spec.height, spec.fx, spec.fx)
    virtual, entries = virtual_shapes(layout, spec.virtual_material)
    scenes = _Scenes(map_folder, spec.max_depth)
    try:
        for i in range(spec.frames):
            file = work / f"{i:06d}.npz"
            if not file.is_file():
                t0 = time.perf_counter()
                arrays = _render_frame(spec, layout, virtual, camera, i, scenes)
                np.savez(str(work / f"{i:06d}.tmp.npz"), **arrays)  # type: ignore[arg-type]  # numpy's stub types **kwds as the allow_pickle flag
                (work / f"{i:06d}.tmp.npz").rename(file)
                stats.per_frame_s.append(time.perf_counter() - t0)
                stats.frames_rendered += 1
                stats.renders += 1 + (i in spec.ar_frames)
            if on_frame is not None:
                on_frame()
    finally:
        scenes.close()
    stats.seconds = float(sum(stats.per_frame_s))
    _write(spec, layout, entries, camera, work, final, map_folder)
    shutil.rmtree(work, ignore_errors=True)
    return stats


class _Scenes:
    """A sequence's scene states (the shapes of a frame, with or without the virtual
    objects, under one map), each loaded into Mitsuba and Open3D once and reused by every
    frame that shows it; the last few are kept (a moving object makes a state per frame)."""

    KEEP = 4

    def __init__(self, map_folder: Path, max_depth: int):
        self._maps, self._max_depth = map_folder, max_depth
        self._built: OrderedDict[tuple, tuple] = OrderedDict()

    def get(self, shapes: list, light: LightState, key: tuple) -> tuple:
        """(SceneRenderer, GeometryCaster) of `shapes` lit by `light`; `key` names the state."""
        key = (light.map_name, light.rotation_deg, *key)
        if key not in self._built:
            path = map_path(self._maps, light.map_name)
            renderer = render.SceneRenderer(shapes, path, light.rotation_deg, self._max_depth)
            self._built[key] = (renderer, render.GeometryCaster(shapes))
            while len(self._built) > self.KEEP:
                self._built.popitem(last=False)[1][0].close()
        self._built.move_to_end(key)
        return self._built[key]

    def close(self) -> None:
        for renderer, _ in self._built.values():
            renderer.close()
        self._built.clear()


def _render_frame(
    spec: SequenceSpec, layout: Layout, virtual, camera, i: int, scenes: _Scenes
) -> dict[str, np.ndarray]:
    light = spec.light_at(i)
    shapes = layout.shapes_at(i)
    seed = spec.seed * 1000 + i
    pose = layout.poses[i]
    moving = id(layout.moving[i]) if layout.moving and layout.moving[i] is not None else None
    scene, caster = scenes.get(shapes, light, (moving, False))
    radiance = scene.render(camera, pose, spec.spp, seed)
    probe = render.render_probe(
        scene, layout.probe_world, spec.probe_size, spec.probe_spp, seed * 8
    )
    depth, ids = caster.cast(camera, pose)
    albedo = scene.render_albedo(camera, pose, seed)
    out = {"radiance": radiance, "depth": depth, "ids": ids, "probe": probe, "albedo": albedo}
    if i in spec.ar_frames:
        with_virtual, caster_v = scenes.get(shapes + virtual, light, (moving, True))
        out["radiance_virtual"] = with_virtual.render(camera, pose, spec.spp, seed)
        _, ids_v = caster_v.cast(camera, pose)
        out["mask_virtual"] = ids_v >= len(shapes)
    return out


# --------------------------------------------------------------------------- writing


def _quaternion(rotation: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(rotation).as_quat()  # x y z w
    return -q if q[3] < 0 else q


def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if image.ndim == 3:
        image = image[..., ::-1]
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cannot write {path}")


def _probe_truth(cube: np.ndarray, point, world_from_cam: np.ndarray) -> dict:
    dirs, solid = render.cube_texels(cube.shape[1])
    d = dirs.reshape(-1, 3)
    w = np.broadcast_to(solid, cube.shape[:3]).reshape(-1)
    rgb = cube.reshape(-1, 3).astype(np.float64)
    sh_rgb = sh.project_samples(d, rgb, w, 4)
    lum = rgb @ LUMA
    sh_lum = sh.project_samples(d, lum, w, 4)
    up = d[:, 1] > 0
    sh_upper = sh.project_samples(d[up], lum[up], w[up], 4)
    r_cw = np.asarray(world_from_cam, float)[:3, :3].T
    dom, dom_up = env.dominant(sh_lum), env.dominant(sh_upper)
    return {
        "point_world": np.round(point, 6).tolist(),
        "sh_lum_world": env.to_file_convention(sh_lum),
        "sh_rgb_world": env.to_file_convention(sh_rgb),
        "sh_lum_upper_world": env.to_file_convention(sh_upper),
        "dominant_dir_world": np.round(dom, 6).tolist(),
        "dominant_dir_camera": np.round(r_cw @ dom, 6).tolist(),
        "dominant_dir_upper_world": np.round(dom_up, 6).tolist(),
        "dominant_dir_upper_camera": np.round(r_cw @ dom_up, 6).tolist(),
    }


CONVENTIONS = {
    "world_frame": "Right-handed, metres. +Y is up (gravity along -Y); the ground plane is y = 0.",
    "camera_frame": "OpenCV: x right, y down, z forward. groundtruth.txt stores the "
    "camera-to-world pose, quaternion qx qy qz qw (Hamilton, qw >= 0).",
    "direction_meaning": "Unit vectors from the scene towards where light arrives from.",
    "env_rotation": "The map's direction d shows column u = (atan2(d.x, -d.z) / 2 pi) mod 1, "
    "row v = acos(d.y) / pi; world direction = R_y(phi) d, phi = "
    "env_rotation_deg, R_y = [[cos, 0, sin], [0, 1, 0], [-sin, 0, cos]].",
    "radiance_units": "Linear RGB radiance as stored in the map file; images are "
    "sRGB(clip(exposure_scale * radiance, 0, 1)) plus noise.",
    "albedo": "albedo/NNNNNN.png: 16-bit RGB, linear diffuse albedo times 65535 of the first "
    "surface each pixel sees (averaged over the pixel), 0 where it sees the environment; "
    "no sRGB curve, no noise (the intrinsic image, for measuring albedo estimates).",
    "sh_basis": "Real orthonormal SH, bands 0..3, index l(l+1)+m, Sloan's polynomials WITH "
    "the Condon-Shortley phase (as ../shared/data/synthetic); negate indices 1, "
    "3, 5, 7, 9, 11, 13, 15 for the basis without it.",
    "sh_definition": "c_i = integral f(w) Y_i(w) dw over every texel of the map with exact "
    "texel solid angles; f = luminance 0.2126 R + 0.7152 G + 0.0722 B "
    "(sh_lum_*) or each linear channel (sh_rgb_world, rows R, G, B).",
    "upper": "*_upper_* fields: the radiance over world y > 0 only (the light that can reach "
    "a scene on the ground plane).",
    "dominant_dir": "normalize(integral L(w) w dw) = normalize(-c_1,1, -c_1,-1, c_1,0).",
    "probe": "probe: the radiance arriving at point_world (one virtual-sphere radius above the "
    "virtual objects' anchor), path-traced into a cube map with the scene in it "
    "(every surface, the moving object, walls), then projected to SH like the map; "
    "where truth_reference is 'probe' (the distant-light assumption fails, e.g. a "
    "closed room), judge estimates against the probe's upper fields.",
}


def _write(
    spec: SequenceSpec,
    layout: Layout,
    entries: list[dict],
    camera,
    work: Path,
    final: Path,
    map_folder: Path,
) -> None:
    frames = [dict(np.load(work / f"{i:06d}.npz")) for i in range(spec.frames)]
    exposure = sensor.choose_exposure(
        [f["radiance"] for f in frames], [f["ids"] >= 0 for f in frames]
    )
    tmp = work.parent / (final.name + ".partial")  # inside .work: never seen as a sequence
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    rng = np.random.default_rng(spec.seed)
    truths = {}
    gt_frames, assoc, rgb_list, depth_list, poses_txt = [], [], [], [], []
    visible_moving = []
    for i, f in enumerate(frames):
        light = spec.light_at(i)
        key = (light.map_name, light.rotation_deg)
        if key not in truths:
            radiance = env.load_map(map_path(map_folder, light.map_name))
            truths[key] = env.environment_truth(radiance, light.rotation_deg)
        truth = truths[key]
        ts = FIRST_TIMESTAMP_S + i / FRAME_RATE_HZ
        name = f"{i:06d}.png"
        _write_png(tmp / "rgb" / name, sensor.to_8bit(f["radiance"], exposure, rng))
        _write_png(tmp / "depth" / name, sensor.kinect_depth(f["depth"], rng))
        _write_png(tmp / "depth_gt" / name, sensor.clean_depth_16bit(f["depth"]))
        if "albedo" in f:  # frames rendered before the generator wrote it have none
            _write_png(tmp / "albedo" / name, sensor.albedo_16bit(f["albedo"]))
        pose = layout.poses[i]
        q = _quaternion(pose[:3, :3])
        poses_txt.append(
            f"{ts:.6f} "
            + " ".join(f"{x:.7f}" for x in pose[:3, 3])
            + " "
            + " ".join(f"{x:.7f}" for x in q)
        )
        rgb_list.append(f"{ts:.6f} rgb/{name}")
        depth_list.append(f"{ts:.6f} depth/{name}")
        assoc.append(f"{ts:.6f} rgb/{name} {ts:.6f} depth/{name}")
        r_cw = pose[:3, :3].T
        dom, dom_up = env.dominant(truth.sh_lum_world), env.dominant(truth.sh_lum_upper_world)
        probe = _probe_truth(f["probe"], layout.probe_world, pose)
        gt_frames.append(
            {
                "index": i,
                "timestamp": round(ts, 6),
                "rgb": f"rgb/{name}",
                "env_map": map_label(light.map_name),
                "env_rotation_deg": light.rotation_deg,
                "sh_lum_world": env.to_file_convention(truth.sh_lum_world),
                "sh_lum_camera": env.to_file_convention(
                    env.rotate_to_camera(truth.sh_lum_world, pose)
                ),
                "sh_rgb_world": env.to_file_convention(truth.sh_rgb_world),
                "dominant_dir_world": np.round(dom, 6).tolist(),
                "dominant_dir_camera": np.round(r_cw @ dom, 6).tolist(),
                "lighting_changed_at_this_frame": i > 0 and light.from_frame == i,
                "dominant_dir_upper_world": np.round(dom_up, 6).tolist(),
                "dominant_dir_upper_camera": np.round(r_cw @ dom_up, 6).tolist(),
                "sh_lum_upper_world": env.to_file_convention(truth.sh_lum_upper_world),
                "upper_vs_full_deg": round(angular_error_deg(dom, dom_up), 2),
                "probe": probe,
                "probe_vs_distant_upper_deg": round(
                    angular_error_deg(probe["dominant_dir_upper_world"], dom_up), 2
                ),
            }
        )
        if layout.moving:
            names = [s.name for s in layout.shapes_at(i)]
            visible_moving.append(
                "moving_ball" in names and bool(np.any(f["ids"] == names.index("moving_ball")))
            )
    header = "# timestamp filename\n"
    (tmp / "rgb.txt").write_text(
        "# color images\n# sequence " + spec.name + "\n" + header + "\n".join(rgb_list) + "\n"
    )
    (tmp / "depth.txt").write_text(
        "# depth images (uint16, metres * 5000)\n# sequence "
        + spec.name
        + "\n"
        + header
        + "\n".join(depth_list)
        + "\n"
    )
    (tmp / "associations.txt").write_text("\n".join(assoc) + "\n")
    (tmp / "groundtruth.txt").write_text(
        "# ground truth camera-to-world poses, OpenCV camera axes, world +Y up\n"
        "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(poses_txt) + "\n"
    )
    (tmp / "camera.json").write_text(
        json.dumps(
            {
                "fx": camera.fx,
                "fy": camera.fy,
                "cx": camera.cx,
                "cy": camera.cy,
                "width": camera.width,
                "height": camera.height,
                "depth_scale": sensor.DEPTH_SCALE,
                "distortion": [0.0] * 5,
                "pixel_centre_convention": "OpenCV: the centre of pixel (u, v) is at (u, v)",
                "depth_valid_range_m": list(sensor.DEPTH_RANGE_M),
            },
            indent=2,
        )
        + "\n"
    )
    events: dict = {"lighting_change_frames": [s.from_frame for s in spec.lights[1:]]}
    if layout.moving:
        events["dynamic_object"] = {
            "shape": "sphere",
            "frames_visible": [i for i, v in enumerate(visible_moving) if v],
            "frames_not_visible": [i for i, v in enumerate(visible_moving) if not v],
        }
    doc = {
        "sequence": spec.name,
        "set": "arlight synth",
        "category": layout.category,
        "category_description": DESCRIPTION[spec.layout],
        "layout": spec.layout,
        "num_frames": spec.frames,
        "conventions": CONVENTIONS,
        "truth_reference": "distant" if layout.distant_light_holds else "probe",
        "distant_light_holds": layout.distant_light_holds,
        "exposure_scale": exposure,
        "env_schedule": [
            {
                "from_frame": s.from_frame,
                "env_map": map_label(s.map_name),
                "env_rotation_deg": s.rotation_deg,
            }
            for s in spec.lights
        ],
        "events": events,
        "render": {
            "renderer": f"Mitsuba {render.version()} (scalar_rgb), path tracer",
            "max_depth": spec.max_depth,
            "spp": spec.spp,
            "reconstruction_filter": "gaussian",
            "scene_seed": spec.seed,
            "frame_seed": "scene_seed * 1000 + frame index",
            "probe_cube_size": spec.probe_size,
            "probe_spp": spec.probe_spp,
            "lighting": "environment map only (distant); scene Lambertian",
        },
        "spec": asdict(spec),
        "scene_objects": [s.describe() for s in layout.shapes],
        "frames": gt_frames,
    }
    if spec.ar_frames:
        _write_ar(spec, layout, entries, frames, exposure, tmp, doc)
    (tmp / "lighting_gt.json").write_text(json.dumps(doc, indent=1) + "\n")
    shutil.rmtree(final, ignore_errors=True)
    tmp.rename(final)


def _affected(real: np.ndarray, virtual: np.ndarray, mask_virtual: np.ndarray) -> np.ndarray:
    """Pixels whose linear radiance the virtual objects change by more than 2 % (after a
    Gaussian of 1.5 px against Monte Carlo noise, a 5x5 closing and opening), or that show a
    virtual object."""
    r = cv2.GaussianBlur(real, (0, 0), AFFECTED_BLUR_SIGMA_PX)
    v = cv2.GaussianBlur(virtual, (0, 0), AFFECTED_BLUR_SIGMA_PX)
    change = (np.abs(v - r) / np.maximum(r, 1e-4)).max(axis=2) > AFFECTED_REL_CHANGE
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    m = cv2.morphologyEx(change.astype(np.uint8), cv2.MORPH_CLOSE, kernel)
    m = cv2.morphologyEx(m, cv2.MORPH_OPEN, kernel).astype(bool)
    return m | mask_virtual


def _write_ar(
    spec: SequenceSpec,
    layout: Layout,
    entries: list[dict],
    frames: list[dict],
    exposure: float,
    tmp: Path,
    doc: dict,
) -> None:
    ar = tmp / "ar"
    ar.mkdir()
    for file, mesh in object_meshes().items():
        write_ply(mesh, ar / file, with_uv=False)
    cam0 = layout.poses[0]
    cam0_inv = np.linalg.inv(cam0)
    objects = []
    for e in entries:
        wfo = np.asarray(e["world_from_object"])
        objects.append({**e, "cam0_from_object": np.round(cam0_inv @ wfo, 7).tolist()})
    up_cam0 = cam0[:3, :3].T @ np.array([0.0, 1.0, 0.0])
    ar_frames = []
    for i in spec.ar_frames:
        f = frames[i]
        name = f"{i:06d}.png"
        mask_v = f["mask_virtual"].astype(bool)
        affected = _affected(f["radiance"], f["radiance_virtual"], mask_v)
        _write_png(ar / "real" / name, sensor.to_8bit(f["radiance"], exposure, None))
        _write_png(
            ar / "real_virtual" / name, sensor.to_8bit(f["radiance_virtual"], exposure, None)
        )
        _write_png(ar / "mask_virtual" / name, mask_v.astype(np.uint8) * 255)
        _write_png(ar / "mask_affected" / name, affected.astype(np.uint8) * 255)
        light = spec.light_at(i)
        ar_frames.append(
            {
                "index": i,
                "rgb": f"rgb/{name}",
                "real": f"ar/real/{name}",
                "real_virtual": f"ar/real_virtual/{name}",
                "mask_virtual": f"ar/mask_virtual/{name}",
                "mask_affected": f"ar/mask_affected/{name}",
                "env_map": map_label(light.map_name),
                "env_rotation_deg": light.rotation_deg,
                "virtual_pixels": int(mask_v.sum()),
                "affected_fraction": round(float(affected.mean()), 5),
            }
        )
    scene = {
        "sequence": spec.name,
        "set": "arlight synth",
        "description": "Differential-rendering pairs: frames rendered without (ar/real) and "
        "with (ar/real_virtual) two virtual objects on the support surface, "
        "with the same per-frame seed, plus masks of the virtual objects and "
        "of every pixel they affect (as ../shared/data/synthetic).",
        "conventions": {
            "world_from_object": "4x4 row-major, p_world = M [p_object, 1]; "
            "object frame: metres, origin at the base "
            "centre, +y up (the scale is in M)",
            "cam0_from_object": "the same pose in the OpenCV frame of frame 0",
        },
        "world_from_cam0": np.round(cam0, 7).tolist(),
        "ground_plane_cam0": {
            "normal": np.round(up_cam0, 7).tolist(),
            "d": round(float(cam0[1, 3] - layout.anchor_world[1]), 7),
        },
        "objects": objects,
        "frames_rendered": list(spec.ar_frames),
        "virtual_material": spec.virtual_material,
        "exposure_scale": exposure,
        "frames": ar_frames,
    }
    (ar / "virtual_scene.json").write_text(json.dumps(scene, indent=1) + "\n")
    doc["ar_frames"] = list(spec.ar_frames)
