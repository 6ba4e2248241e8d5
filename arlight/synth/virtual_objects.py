"""The virtual objects of the AR pairs: the shared set's sphere and arch, placed at the anchor.

A sphere (radius 0.18 m) and an arch (0.4 m wide, 0.3 m high, 0.12 m deep, 0.09 m posts and
lintel), both scaled by the layout's `virtual_scale` (0.3 on a table top), standing on the
support surface either side of the anchor, across the cameras' view. The sphere carries the
sequence's virtual material (``diffuse``, ``glossy0.1``, ``glossy0.3`` or ``mirror``); the arch
stays diffuse, so every pair holds a diffuse object too.
"""

from __future__ import annotations

import math

import numpy as np

from arlight.synth.layouts import UP, VIRTUAL_SPHERE_RADIUS_M, Layout, Shape, pose_matrix
from arlight.synth.materials import Material
from arlight.synth.meshes import TriangleMesh, arch, translated, uv_sphere

VIRTUAL_MATERIALS = ("diffuse", "glossy0.1", "glossy0.3", "mirror")
SPHERE_ALBEDO = (0.45, 0.45, 0.45)
ARCH_ALBEDO = (0.62, 0.2, 0.06)
ARCH_SIZE_M = {"width": 0.4, "height": 0.3, "depth": 0.12, "post": 0.09}


def sphere_material(kind: str) -> Material:
    if kind not in VIRTUAL_MATERIALS:
        raise ValueError(f"--virtual-material {kind!r}: choose from {', '.join(VIRTUAL_MATERIALS)}")
    if kind == "mirror":
        return Material("grey", (0.9, 0.9, 0.9), mirror=True)
    if kind.startswith("glossy"):
        return Material("grey", SPHERE_ALBEDO, roughness=float(kind[len("glossy") :]))
    return Material("grey", SPHERE_ALBEDO)


def virtual_shapes(layout: Layout, material_kind: str) -> tuple[list[Shape], list[dict]]:
    """The two objects as Shapes (world frame) and their scene-file entries
    (name, mesh file, world_from_object with the origin at the base centre, material)."""
    s = layout.virtual_scale
    side = np.cross(UP, layout.view_direction)
    yaw = math.degrees(math.atan2(side[0], side[2])) - 90.0  # the arch's span across the view
    base_sphere = layout.anchor_world + side * 0.22 * s
    base_arch = layout.anchor_world - side * 0.25 * s
    sphere_mat = sphere_material(material_kind)
    radius = VIRTUAL_SPHERE_RADIUS_M * s
    arch_params = {k: v * s for k, v in ARCH_SIZE_M.items()}
    shapes = [
        Shape(
            "virtual_sphere",
            "sphere",
            {"radius": radius},
            pose_matrix(0, base_sphere + UP * radius),
            sphere_mat,
        ),
        Shape(
            "virtual_arch",
            "arch",
            arch_params,
            pose_matrix(yaw, base_arch),
            Material("grey", ARCH_ALBEDO),
        ),
    ]
    entries = []
    for shape, base, mesh, y in (
        (shapes[0], base_sphere, "virtual_sphere.ply", 0.0),
        (shapes[1], base_arch, "virtual_arch.ply", yaw),
    ):
        world_from_object = pose_matrix(y, base) @ np.diag([s, s, s, 1.0])
        m = shape.material
        material: dict = {"albedo": list(m.albedo_rgb)}
        if m.mirror:
            material["mirror"] = True
        elif m.roughness is not None:
            material.update(roughness=m.roughness, metalness=m.metalness)
        entries.append(
            {
                "name": shape.name,
                "mesh": mesh,
                "material": material,
                "world_from_object": np.round(world_from_object, 7).tolist(),
            }
        )
    return shapes, entries


def object_meshes() -> dict[str, TriangleMesh]:
    """The meshes in their object frames (metres, origin at the base centre, +y up), unscaled."""
    return {
        "virtual_sphere.ply": translated(
            uv_sphere(VIRTUAL_SPHERE_RADIUS_M), (0, VIRTUAL_SPHERE_RADIUS_M, 0)
        ),
        "virtual_arch.ply": arch(*ARCH_SIZE_M.values()),
    }
