"""Scene layouts of the generator: geometry, materials, camera path, anchor, from a seed.

World frame as in ``../shared/data/synthetic``: right-handed, metres, +Y up, ground y = 0.
Camera poses are camera-to-world 4x4 with OpenCV axes. Every layout is built from its seed
alone (NumPy's PCG64), so a corpus entry (layout, seed, frames) fixes the scene exactly.

Layouts (:data:`LAYOUTS`): the shared set's five categories and what users meet beyond it:

- ``static``: 3-5 objects on a ground, a camera orbiting 1.8-2.4 m away;
- ``dynamic``: the same, and a ball rolls across the view and leaves it;
- ``light_change``: the same, and the light changes half-way (the corpus entry's second map);
- ``indoor``: the same objects seen from 2.6-3.2 m under an indoor map;
- ``few_normals``: one big box on the ground (ill-conditioned: few normal orientations);
- ``room``: floor, four walls and a ceiling; the environment reaches in only through two
  windows and a skylight (the distant-light assumption fails: judge against the probe);
- ``textured``: wood, fabric, paint and checker at realistic albedos;
- ``tabletop``: small objects on a table, a camera 0.6-0.9 m away.

The anchor is the point on the support surface (ground or table top) where virtual objects
stand; the probe (the radiance arriving there) sits one virtual-sphere radius above it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from arlight.sources.synthetic import look_at
from arlight.synth import meshes
from arlight.synth.materials import Material, ground_material, random_material

LAYOUTS = (
    "static",
    "dynamic",
    "light_change",
    "indoor",
    "few_normals",
    "room",
    "textured",
    "tabletop",
)
CATEGORY = {
    "static": "a_static",
    "dynamic": "b_dynamic_object",
    "light_change": "c_light_change",
    "indoor": "d_indoor_env",
    "few_normals": "e_few_normals",
    "room": "f_room",
    "textured": "g_textured",
    "tabletop": "h_tabletop",
}
DESCRIPTION = {
    "static": "static scene, static light",
    "dynamic": "an object moves through the view and leaves it",
    "light_change": "lighting changes from a given frame on (env map rotated and/or switched)",
    "indoor": "static scene under an indoor map, seen from farther away",
    "few_normals": "almost only one plane and one box visible (few normal orientations)",
    "room": "a closed room: the environment enters only through two windows and a skylight",
    "textured": "wood, fabric, paint and checker materials at realistic albedos",
    "tabletop": "small objects on a table at close range",
}
VIRTUAL_SPHERE_RADIUS_M = 0.18  # the shared set's virtual sphere (ar/virtual_sphere.ply)
GROUND_SIZE_M = 30.0
UP = np.array([0.0, 1.0, 0.0])


class LayoutError(ValueError):
    """An unknown layout or unusable layout parameters."""


@dataclass(frozen=True)
class Shape:
    """One surface: kind (plane, box, sphere, cylinder, arch), its parameters in metres, its
    pose world_from_shape (4x4: box and sphere centre, cylinder and arch base centre, plane
    centre),
    and its material."""

    name: str
    kind: str
    params: dict
    world_from_shape: np.ndarray
    material: Material

    def mesh(self) -> meshes.TriangleMesh:
        """The triangle mesh in the world frame."""
        p = self.params
        local = {
            "plane": lambda: meshes.quad(*p["size_m"]),
            "box": lambda: meshes.box(p["half_extents"]),
            "sphere": lambda: meshes.uv_sphere(p["radius"]),
            "cylinder": lambda: meshes.cylinder(p["radius"], p["height"]),
            "arch": lambda: meshes.arch(p["width"], p["height"], p["depth"], p["post"]),
        }[self.kind]()
        return local.transformed(self.world_from_shape)

    def describe(self) -> dict:
        m = self.world_from_shape
        out = {
            "name": self.name,
            "type": self.kind,
            "centre": [round(float(x), 5) for x in m[:3, 3]],
            "yaw_deg": round(math.degrees(math.atan2(m[0, 2], m[0, 0])) % 360, 3),
        }
        out.update(
            {
                k: (
                    np.round(v, 5).tolist()
                    if isinstance(v, (list, tuple, np.ndarray))
                    else round(float(v), 5)
                )
                for k, v in self.params.items()
            }
        )
        out["material"] = self.material.describe()
        return out


@dataclass(frozen=True)
class Layout:
    """A scene and its camera path. `moving[i]`: the moving object at frame i (None: none)."""

    name: str
    seed: int
    shapes: tuple[Shape, ...]
    poses: tuple[np.ndarray, ...]
    anchor_world: np.ndarray
    virtual_scale: float
    view_direction: np.ndarray  # horizontal unit vector from the cameras towards the anchor
    moving: tuple[Shape | None, ...] = field(default=())
    distant_light_holds: bool = True

    @property
    def category(self) -> str:
        return CATEGORY[self.name]

    def shapes_at(self, frame: int) -> list[Shape]:
        extra = self.moving[frame] if self.moving else None
        return list(self.shapes) + ([extra] if extra is not None else [])

    @property
    def probe_world(self) -> np.ndarray:
        """Where the anchor-probe truth is taken: one virtual-sphere radius above the anchor."""
        return self.anchor_world + UP * VIRTUAL_SPHERE_RADIUS_M * self.virtual_scale


def pose_matrix(yaw_deg: float, position) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    m = np.eye(4)
    m[:3, :3] = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    m[:3, 3] = position
    return m


def _orbit(
    rng,
    n: int,
    radius: tuple[float, float],
    height: tuple[float, float],
    target: np.ndarray,
    sweep_deg: tuple[float, float],
) -> tuple[list, float]:
    """Camera poses on an arc about `target` (radius, height drawn from the ranges; a little
    bob and breathing so the path is not a perfect circle) and the arc's middle azimuth."""
    r, h = rng.uniform(*radius), rng.uniform(*height)
    sweep = math.radians(rng.uniform(*sweep_deg)) * rng.choice([-1, 1])
    start = rng.uniform(0, 2 * math.pi)
    poses = []
    for i in range(n):
        s = i / max(1, n - 1)
        phi = start + sweep * s
        rr = r * (1 + 0.05 * math.sin(2 * math.pi * s))
        eye = target + [
            rr * math.sin(phi),
            h + 0.05 * math.sin(3 * math.pi * s),
            rr * math.cos(phi),
        ]
        poses.append(look_at(eye, target))
    return poses, start + sweep / 2


def _scatter(
    rng,
    count: int,
    keep_out: list[tuple[np.ndarray, float]],
    extent: float,
    scale: float,
    kinds: tuple[str, ...],
    base_y: float = 0.0,
    name_prefix: str = "obj",
) -> list[Shape]:
    """`count` objects (sphere, box, cylinder) standing at y = base_y within `extent` of the
    origin, footprints apart from each other and from the discs in `keep_out`."""
    shapes: list[Shape] = []
    taken = list(keep_out)
    for k in range(count * 30):
        if len(shapes) == count:
            break
        kind = (
            ("sphere", "box", "cylinder")[len(shapes) % 3]
            if k < count
            else str(rng.choice(["sphere", "box", "cylinder"]))
        )
        xz = rng.uniform(-extent, extent, 2)
        size = rng.uniform(0.08, 0.2) * scale
        centre = np.array([xz[0], 0.0, xz[1]])
        if any(np.linalg.norm(centre[[0, 2]] - c[[0, 2]]) < size * 1.5 + r for c, r in taken):
            continue
        taken.append((centre, size * 1.5))
        material = random_material(rng, kinds, seed=int(rng.integers(1 << 30)))
        name = f"{name_prefix}{len(shapes):02d}_{kind}"
        yaw = float(rng.uniform(0, 360))
        if kind == "sphere":
            shapes.append(
                Shape(
                    name,
                    "sphere",
                    {"radius": size},
                    pose_matrix(0, centre + [0, base_y + size, 0]),
                    material,
                )
            )
        elif kind == "box":
            half = (size, rng.uniform(0.6, 1.6) * size, rng.uniform(0.5, 1.0) * size)
            shapes.append(
                Shape(
                    name,
                    "box",
                    {"half_extents": half},
                    pose_matrix(yaw, centre + [0, base_y + half[1], 0]),
                    material,
                )
            )
        else:
            shapes.append(
                Shape(
                    name,
                    "cylinder",
                    {"radius": size * 0.6, "height": rng.uniform(1.2, 3.0) * size},
                    pose_matrix(yaw, centre + [0, base_y, 0]),
                    material,
                )
            )
    return shapes


def _ground(rng, seed: int, kinds=("noise", "checker", "grey"), size=GROUND_SIZE_M) -> Shape:
    return Shape(
        "ground", "plane", {"size_m": [size, size]}, np.eye(4), ground_material(rng, seed, kinds)
    )


def _anchor(
    mid_azimuth: float, distance: float, base_y: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """A point `distance` from the scene centre towards the middle camera, and the
    horizontal direction the cameras look along there."""
    towards_camera = np.array([math.sin(mid_azimuth), 0.0, math.cos(mid_azimuth)])
    return towards_camera * distance + [0, base_y, 0], -towards_camera


OBJECT_KINDS = ("grey", "colour", "checker", "noise")
TEXTURED_KINDS = ("wood", "fabric", "paint", "checker")


def build_layout(name: str, seed: int, num_frames: int) -> Layout:
    """The layout `name` (LAYOUTS) drawn from `seed`, with `num_frames` camera poses."""
    if name not in LAYOUTS:
        raise LayoutError(f"--layout {name!r} is not a layout; choose from {', '.join(LAYOUTS)}")
    if num_frames < 1:
        raise LayoutError(f"--frames must be >= 1, got {num_frames}")
    rng = np.random.default_rng(seed)
    builder = {"few_normals": _few_normals, "room": _room, "tabletop": _tabletop}.get(
        name, _objects_on_ground
    )
    return builder(name, seed, num_frames, rng)


def _objects_on_ground(name: str, seed: int, n: int, rng) -> Layout:
    far = name == "indoor"
    target = np.array([0.0, 0.15, 0.0])
    poses, mid = _orbit(
        rng,
        n,
        (2.6, 3.2) if far else (1.8, 2.4),
        (1.3, 1.8) if far else (0.8, 1.4),
        target,
        (45, 75),
    )
    anchor, view = _anchor(mid, 0.45)
    kinds = TEXTURED_KINDS if name == "textured" else OBJECT_KINDS
    ground_kinds = ("wood",) if name == "textured" else ("noise", "checker", "grey")
    shapes = [_ground(rng, seed, ground_kinds)]
    shapes += _scatter(rng, int(rng.integers(3, 6)), [(anchor, 0.45)], 0.65, 1.0, kinds)
    moving: tuple = ()
    if name == "dynamic":
        moving = _rolling_ball(rng, n, poses, anchor, view)
    return Layout(name, seed, tuple(shapes), tuple(poses), anchor, 1.0, view, moving)


def _rolling_ball(rng, n: int, poses, anchor: np.ndarray, view: np.ndarray) -> tuple:
    """A ball rolling across the view in front of the scene; gone in the last quarter."""
    radius = float(rng.uniform(0.12, 0.18))
    side = np.cross(UP, view)
    material = random_material(rng, ("colour", "checker"), seed=int(rng.integers(1 << 30)))
    centre = anchor - view * 0.35
    visible = max(1, n - max(1, n // 4))
    out: list[Shape | None] = []
    for i in range(n):
        if i >= visible:
            out.append(None)
            continue
        s = -1.1 + 2.2 * i / max(1, visible - 1)
        p = centre + side * s + UP * radius
        out.append(Shape("moving_ball", "sphere", {"radius": radius}, pose_matrix(0, p), material))
    return tuple(out)


def _few_normals(name: str, seed: int, n: int, rng) -> Layout:
    half = (rng.uniform(0.25, 0.35), rng.uniform(0.18, 0.3), rng.uniform(0.22, 0.32))
    target = np.array([0.0, 0.15, 0.0])
    poses, mid = _orbit(rng, n, (1.8, 2.3), (0.9, 1.3), target, (30, 50))
    anchor, view = _anchor(mid + rng.choice([-0.6, 0.6]), 0.75)
    box = Shape(
        "big_box",
        "box",
        {"half_extents": half},
        pose_matrix(rng.uniform(0, 360), [0, half[1], 0]),
        random_material(rng, ("grey", "colour"), seed=int(rng.integers(1 << 30))),
    )
    return Layout(name, seed, (_ground(rng, seed), box), tuple(poses), anchor, 1.0, view)


ROOM_HALF_M = 2.5
ROOM_HEIGHT_M = 2.6
WALL_M = 0.1


def _wall_with_opening(
    name: str,
    length: float,
    height: float,
    opening: tuple | None,
    world_from_wall: np.ndarray,
    material: Material,
) -> list[Shape]:
    """A wall slab in its own frame (x along it, y up from 0, z through it), with a
    rectangular opening (x0, x1, y0, y1) cut out as four slabs around it."""
    if opening is None:
        rects = [(-length / 2, length / 2, 0.0, height)]
    else:
        x0, x1, y0, y1 = opening
        rects = [
            (-length / 2, x0, 0.0, height),
            (x1, length / 2, 0.0, height),
            (x0, x1, 0.0, y0),
            (x0, x1, y1, height),
        ]
    out = []
    for k, (a, b, c, d) in enumerate(rects):
        if b - a < 1e-3 or d - c < 1e-3:
            continue
        local = np.eye(4)
        local[:3, 3] = [(a + b) / 2, (c + d) / 2, 0.0]
        out.append(
            Shape(
                f"{name}_{k}",
                "box",
                {"half_extents": ((b - a) / 2, (d - c) / 2, WALL_M / 2)},
                world_from_wall @ local,
                material,
            )
        )
    return out


def _room(name: str, seed: int, n: int, rng) -> Layout:
    paint = random_material(rng, ("paint",), seed=int(rng.integers(1 << 30)))
    shapes = [_ground(rng, seed, ("wood", "noise"))]
    window_walls = rng.choice(4, 2, replace=False)
    for k in range(4):
        yaw = 90.0 * k
        world = pose_matrix(yaw, [0, 0, 0]) @ pose_matrix(0, [0, 0, -(ROOM_HALF_M + WALL_M / 2)])
        opening = None
        if k in window_walls:
            w, h = rng.uniform(1.2, 1.8), rng.uniform(1.0, 1.3)
            x = rng.uniform(-ROOM_HALF_M + w / 2 + 0.3, ROOM_HALF_M - w / 2 - 0.3)
            sill = rng.uniform(0.8, 1.0)
            opening = (x - w / 2, x + w / 2, sill, sill + h)
        shapes += _wall_with_opening(
            f"wall{k}", 2 * ROOM_HALF_M + 2 * WALL_M, ROOM_HEIGHT_M, opening, world, paint
        )
    # the ceiling: a wall slab laid flat (its x along world x, its y along world z, its z
    # down), with a skylight
    span = 2 * ROOM_HALF_M + 2 * WALL_M
    size = rng.uniform(0.9, 1.3)
    cx, cz = rng.uniform(-1.0, 1.0, 2)
    world_from_ceiling = np.array(
        [[1, 0, 0, 0], [0, 0, -1, ROOM_HEIGHT_M + WALL_M / 2], [0, 1, 0, -span / 2], [0, 0, 0, 1.0]]
    )
    skylight = (cx - size / 2, cx + size / 2, cz + span / 2 - size / 2, cz + span / 2 + size / 2)
    shapes += _wall_with_opening("ceiling", span, span, skylight, world_from_ceiling, paint)
    target = np.array([0.0, 0.2, 0.0])
    poses, mid = _orbit(rng, n, (1.6, 2.0), (0.9, 1.3), target, (45, 75))
    anchor, view = _anchor(mid, 0.45)
    shapes += _scatter(rng, int(rng.integers(3, 5)), [(anchor, 0.45)], 0.65, 1.0, OBJECT_KINDS)
    return Layout(
        name, seed, tuple(shapes), tuple(poses), anchor, 1.0, view, distant_light_holds=False
    )


TABLE_HEIGHT_M = 0.74
TABLE_TOP_M = (0.6, 0.02, 0.4)  # half extents of the top


def _tabletop(name: str, seed: int, n: int, rng) -> Layout:
    wood = random_material(rng, ("wood", "paint"), seed=int(rng.integers(1 << 30)))
    top_y = TABLE_HEIGHT_M
    shapes = [
        _ground(rng, seed),
        Shape(
            "table_top",
            "box",
            {"half_extents": TABLE_TOP_M},
            pose_matrix(0, [0, top_y - TABLE_TOP_M[1], 0]),
            wood,
        ),
    ]
    for k, (sx, sz) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
        leg = Shape(
            f"table_leg{k}",
            "cylinder",
            {"radius": 0.025, "height": top_y - 2 * TABLE_TOP_M[1]},
            pose_matrix(0, [sx * (TABLE_TOP_M[0] - 0.06), 0, sz * (TABLE_TOP_M[2] - 0.06)]),
            wood,
        )
        shapes.append(leg)
    target = np.array([0.0, top_y + 0.04, 0.0])
    poses, mid = _orbit(rng, n, (0.6, 0.8), (0.3, 0.45), target, (35, 60))
    anchor, view = _anchor(mid, 0.14, base_y=top_y)
    objects = _scatter(
        rng,
        int(rng.integers(3, 5)),
        [(anchor - [0, top_y, 0], 0.14)],
        0.25,
        0.35,
        OBJECT_KINDS + ("wood", "fabric"),
        base_y=top_y,
    )
    return Layout(name, seed, tuple(shapes + objects), tuple(poses), anchor, 0.3, view)
