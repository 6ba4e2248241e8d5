"""Ground truth and the accuracy metrics that `arlight bench` reports.

Ground truth per frame (`FrameTruth`) comes from a sequence folder's `lighting_gt.json`
(../shared/data/synthetic: Sloan's SH basis WITH the Condon-Shortley phase, converted here)
or from the built-in scene (`scene_truth`). Two references: the whole sphere, and the upper
hemisphere only (world y > 0: the light that can reach a scene standing on the ground).
Where the distant-light assumption fails (a room, a light close by), a file says
`"truth_reference": "probe"` and each frame's `probe` object (same fields, same conventions)
is the reference instead: the light at the scene, not the environment map's. Each frame
also names the environment map that lit it (`env_map`) and its sequence's layout, so that
`arlight bench` can group errors by map and hold maps out.

Metrics, each a number per frame:
- `angular_error_deg`: between unit directions towards the light (the paper's evaluation).
- `sh_error`: relative L2 distance of the estimated radiance SH from the truth after the best
  common scale (exposure and albedo make the absolute scale unknowable), over the bands both
  have. 0 = same shape, 1 = no better than zero.
- `shading_error`: the same for the diffuse shading (irradiance) the two lights give on the
  frame's observed normals: what a virtual Lambertian object would look like.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from arlight.pipeline import sh

GT_FILE = "lighting_gt.json"


# the shared set's categories (no "layout" key there) and the layout each stands for
CATEGORY_LAYOUTS = {
    "a_static": "static",
    "b_dynamic_object": "dynamic",
    "c_light_change": "light_change",
    "d_indoor_env": "indoor",
    "e_few_normals": "few_normals",
}
PROBE_FIELDS = ("dominant_dir_upper_camera", "dominant_dir_camera", "sh_lum_upper_world")


class GroundTruthError(ValueError):
    """A lighting_gt.json that cannot be scored against (names the file and the frame)."""


@dataclass(frozen=True)
class FrameTruth:
    """The true light of one frame.

    dominant_camera / dominant_upper_camera: (3,) unit, towards the light, camera frame, of
    the whole sphere and of the upper hemisphere. sh_upper_world: (16,) luminance radiance SH
    of the upper hemisphere (zero below), world frame, arlight's basis (no phase); None when
    unknown. All three are the light probe's where the file's truth_reference is "probe".
    env_map: name of the environment map that lit this frame (e.g. "venice_sunset_1k"), None
    when unknown (the built-in scene). layout: the sequence's scene layout ("static", "room",
    ...; from its "category" where the file has no "layout"), None when unknown.
    reference: "distant" (the environment map's own fields) or "probe". sun_camera: (3,)
    unit, towards the built-in scene's sun, camera frame (what a kept compact source is:
    where the sky outshines the sun, the first moment above stands apart from it); None
    where the truth names no single sun.
    """

    dominant_camera: np.ndarray
    dominant_upper_camera: np.ndarray
    sh_upper_world: np.ndarray | None
    env_map: str | None = None
    layout: str | None = None
    reference: str = "distant"
    sun_camera: np.ndarray | None = None


def has_ground_truth(folder: str | Path) -> bool:
    return (Path(folder) / GT_FILE).is_file()


def layout_of(data: dict) -> str | None:
    """A lighting_gt.json's layout: its "layout", else derived from its "category"
    ("a_static" -> "static", "b_dynamic_object" -> "dynamic", an unknown "x_name" -> "name"),
    else None."""
    if data.get("layout"):
        return str(data["layout"])
    category = data.get("category")
    if not category:
        return None
    category = str(category)
    if category in CATEGORY_LAYOUTS:
        return CATEGORY_LAYOUTS[category]
    head, _, rest = category.partition("_")
    return rest if len(head) == 1 and rest else category


def load_ground_truth(folder: str | Path) -> list[FrameTruth]:
    """Per-frame truth of a sequence folder, in frame order (lighting_gt.json).

    With `"truth_reference": "probe"` every frame must carry a `probe` object with
    PROBE_FIELDS; GroundTruthError names the first frame that does not.
    """
    path = Path(folder) / GT_FILE
    data = json.loads(path.read_text())
    reference = str(data.get("truth_reference", "distant"))
    if reference not in ("distant", "probe"):
        raise GroundTruthError(
            f"{path}: truth_reference {reference!r} is neither 'distant' nor 'probe'"
        )
    layout = layout_of(data)
    truths = []
    for k, f in enumerate(data["frames"]):
        source = f
        if reference == "probe":
            source = f.get("probe")
            missing = (
                list(PROBE_FIELDS)
                if not isinstance(source, dict)
                else [name for name in PROBE_FIELDS if name not in source]
            )
            if missing:
                raise GroundTruthError(
                    f"{path}: truth_reference is 'probe' but frame {f.get('index', k)} has "
                    f"no probe {', '.join(missing)} (expected frames[i]['probe'] with "
                    f"{', '.join(PROBE_FIELDS)})"
                )
        upper_sh = source.get("sh_lum_upper_world")
        env_map = f.get("env_map")
        truths.append(
            FrameTruth(
                dominant_camera=np.asarray(source["dominant_dir_camera"], float),
                dominant_upper_camera=np.asarray(
                    source.get("dominant_dir_upper_camera", source["dominant_dir_camera"]), float
                ),
                sh_upper_world=(
                    None
                    if upper_sh is None
                    else sh.toggle_condon_shortley(np.asarray(upper_sh, float))
                ),
                env_map=None if env_map is None else str(env_map),
                layout=layout,
                reference=reference,
            )
        )
    return truths


def scene_truth(scene) -> list[FrameTruth]:
    """Per-frame truth of the built-in scene (`arlight.sources.synthetic.SyntheticSequence`).

    Its upper hemisphere is the sky above the horizon plus the sun (always above it),
    projected by quadrature on 20000 directions.
    """
    from arlight.sources.synthetic import LUMINANCE_RGB, Lighting

    dirs = sh.fibonacci_sphere(20000)
    up = dirs[dirs[:, 1] > 0]
    solid_angle = np.full(len(up), 4.0 * math.pi / len(dirs))
    truths = []
    for frame, sun, whole in zip(
        scene.frames, scene.sun_direction_world, scene.sh_world, strict=True
    ):
        lighting = Lighting(sun_direction=np.asarray(sun, float))
        sky = lighting.sky_radiance(up) @ LUMINANCE_RGB
        upper = sh.project_samples(up, sky, solid_angle, 4) + sh.directional_light(
            lighting.sun_direction, float(LUMINANCE_RGB @ lighting.sun_rgb), 4
        )
        cam_from_world = np.asarray(frame.pose, float)[:3, :3].T
        truths.append(
            FrameTruth(
                dominant_camera=cam_from_world @ sh.dominant_direction(whole),
                dominant_upper_camera=cam_from_world @ sh.dominant_direction(upper),
                sh_upper_world=upper,
                sun_camera=cam_from_world @ lighting.sun_direction,
            )
        )
    return truths


def angular_error_deg(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Degrees between two directions; 180 when the estimate is zero (no estimate)."""
    a, b = np.asarray(estimate, float), np.asarray(truth, float)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return 180.0
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def _scaled_distance(estimate: np.ndarray, truth: np.ndarray) -> float:
    """min over s >= 0 of |s estimate - truth| / |truth|; 1 when the estimate is zero."""
    t_norm = float(np.linalg.norm(truth))
    if t_norm == 0:
        return float("nan")
    e_sq = float(estimate @ estimate)
    s = max(float(estimate @ truth) / e_sq, 0.0) if e_sq > 0 else 0.0
    return float(np.linalg.norm(s * estimate - truth)) / t_norm


def sh_error(estimate_world: np.ndarray, truth_world: np.ndarray) -> float:
    """Scale-free relative L2 error of radiance SH over the bands both have (world frame)."""
    n = min(len(estimate_world), len(truth_world))
    return _scaled_distance(
        np.asarray(estimate_world, float)[:n], np.asarray(truth_world, float)[:n]
    )


def shading_error(
    estimate_world: np.ndarray, truth_world: np.ndarray, normals_world: np.ndarray
) -> float:
    """Scale-free relative RMS error of the irradiance on unit normals (N, 3), world frame."""
    normals = np.asarray(normals_world, float).reshape(-1, 3)
    if len(normals) == 0:
        return float("nan")
    n = min(len(estimate_world), len(truth_world))
    est = sh.evaluate(sh.irradiance_from_radiance(np.asarray(estimate_world, float)[:n]), normals)
    gt = sh.evaluate(sh.irradiance_from_radiance(np.asarray(truth_world, float)[:n]), normals)
    return _scaled_distance(est, gt)
