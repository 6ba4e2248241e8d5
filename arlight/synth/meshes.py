"""Triangle meshes of the generator's shapes, with normals and texture coordinates.

Every shape the generator renders is a triangle mesh built here, so Mitsuba (colour) and
Open3D (depth, masks) see exactly the same surfaces. Vertices are (N, 3) float32 metres in
the shape's own frame; normals (N, 3) unit; uvs (N, 2) in [0, 1] (a plane's uvs are in
metres so textures tile by size); faces (M, 3) int32, counter-clockwise seen from outside.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class TriangleMesh:
    """vertices (N, 3) m, normals (N, 3), uvs (N, 2), faces (M, 3) int32."""

    vertices: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    faces: np.ndarray

    def transformed(self, world_from_shape: np.ndarray) -> TriangleMesh:
        """The mesh in the world frame (4x4 rigid or scaled transform)."""
        m = np.asarray(world_from_shape, float)
        linear = m[:3, :3]
        normal_matrix = np.linalg.inv(linear).T
        normals = self.normals @ normal_matrix.T
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        if np.linalg.det(linear) < 0:
            faces = self.faces[:, ::-1]
        else:
            faces = self.faces
        return TriangleMesh(
            (self.vertices @ linear.T + m[:3, 3]).astype(np.float32),
            normals.astype(np.float32),
            self.uvs,
            faces,
        )


def _mesh(vertices, normals, uvs, faces) -> TriangleMesh:
    return TriangleMesh(
        np.asarray(vertices, np.float32),
        np.asarray(normals, np.float32),
        np.asarray(uvs, np.float32),
        np.asarray(faces, np.int32),
    )


def merge(meshes: list[TriangleMesh]) -> TriangleMesh:
    """One mesh holding all of `meshes` (same frame)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return _mesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.normals for m in meshes]),
        np.concatenate([m.uvs for m in meshes]),
        np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]),
    )


def quad(width_m: float, depth_m: float) -> TriangleMesh:
    """A horizontal rectangle at y = 0 centred on the origin, normal +y, uvs in metres."""
    hx, hz = width_m / 2, depth_m / 2
    v = [[-hx, 0, -hz], [hx, 0, -hz], [hx, 0, hz], [-hx, 0, hz]]
    uv = [[0, 0], [width_m, 0], [width_m, depth_m], [0, depth_m]]
    return _mesh(v, [[0, 1, 0]] * 4, uv, [[0, 2, 1], [0, 3, 2]])


def box(half_extents: tuple[float, float, float]) -> TriangleMesh:
    """An axis-aligned box centred on the origin, flat faces, uvs [0, 1] per face."""
    h = np.asarray(half_extents, float)
    verts: list[np.ndarray] = []
    norms: list[np.ndarray] = []
    uvs: list[list[float]] = []
    faces: list[list[int]] = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            u_axis, v_axis = [a for a in range(3) if a != axis]
            u = np.zeros(3)
            u[u_axis] = 1.0
            v = np.cross(n, u)  # (u, v, n) right-handed: faces wind outwards
            base = len(verts)
            for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = n * h + su * u * h + sv * v * h
                verts.append(p)
                norms.append(n)
                uvs.append([(su + 1) / 2, (sv + 1) / 2])
            faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return _mesh(verts, norms, uvs, faces)


def uv_sphere(radius_m: float, rings: int = 48, segments: int = 96) -> TriangleMesh:
    """A sphere centred on the origin, smooth radial normals, uv = (longitude, latitude)."""
    theta = np.linspace(0.0, math.pi, rings + 1)
    phi = np.linspace(0.0, 2 * math.pi, segments + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    n = np.stack([np.sin(t) * np.cos(p), np.cos(t), -np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    uv = np.stack([p / (2 * math.pi), t / math.pi], -1).reshape(-1, 2)
    idx = np.arange((rings + 1) * (segments + 1)).reshape(rings + 1, segments + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    # drop the degenerate triangles at the poles
    area = np.linalg.norm(
        np.cross(n[faces[:, 1]] - n[faces[:, 0]], n[faces[:, 2]] - n[faces[:, 0]]), axis=1
    )
    return _mesh(n * radius_m, n, uv, faces[area > 1e-12])


def cylinder(radius_m: float, height_m: float, segments: int = 64) -> TriangleMesh:
    """An upright closed cylinder, base centre at the origin, smooth side, flat caps."""
    phi = np.linspace(0.0, 2 * math.pi, segments + 1)
    ring = np.stack([np.cos(phi), np.zeros_like(phi), -np.sin(phi)], -1)
    side_v = np.concatenate([ring * radius_m, ring * radius_m + [0, height_m, 0]])
    side_n = np.concatenate([ring, ring])
    side_uv = np.concatenate(
        [
            np.stack([phi / (2 * math.pi), np.zeros_like(phi)], -1),
            np.stack([phi / (2 * math.pi), np.ones_like(phi)], -1),
        ]
    )
    k = segments + 1
    i = np.arange(segments)
    side_f = np.concatenate(
        [np.stack([i, i + 1, i + k], 1), np.stack([i + 1, i + k + 1, i + k], 1)]
    )
    parts = [_mesh(side_v, side_n, side_uv, side_f)]
    for y, sign in ((0.0, -1.0), (height_m, 1.0)):
        centre = [[0, y, 0]]
        rim = ring[:-1] * radius_m + [0, y, 0]
        v = np.concatenate([centre, rim])
        uv = np.concatenate([[[0.5, 0.5]], 0.5 + 0.5 * ring[:-1][:, [0, 2]]])
        j = np.arange(segments)
        f = np.stack([np.zeros(segments, int), 1 + j, 1 + (j + 1) % segments], 1)
        if sign < 0:
            f = f[:, ::-1]
        parts.append(_mesh(v, [[0, sign, 0]] * len(v), uv, f))
    return merge(parts)


def translated(mesh: TriangleMesh, offset) -> TriangleMesh:
    m = np.eye(4)
    m[:3, 3] = offset
    return mesh.transformed(m)


def arch(
    width_m: float = 0.4, height_m: float = 0.3, depth_m: float = 0.12, post_m: float = 0.09
) -> TriangleMesh:
    """Two posts and a lintel (non-convex), base centre at the origin, +y up, flat faces."""
    post_h = height_m - post_m
    post = box((post_m / 2, post_h / 2, depth_m / 2))
    lintel = box((width_m / 2, post_m / 2, depth_m / 2))
    x = width_m / 2 - post_m / 2
    return merge(
        [
            translated(post, (-x, post_h / 2, 0)),
            translated(post, (x, post_h / 2, 0)),
            translated(lintel, (0, post_h + post_m / 2, 0)),
        ]
    )


def write_ply(mesh: TriangleMesh, path: str | Path, with_uv: bool = True) -> None:
    """Binary little-endian PLY: float x y z nx ny nz [u v], uchar-count int faces."""
    fields = [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("nx", "<f4"),
        ("ny", "<f4"),
        ("nz", "<f4"),
    ] + ([("u", "<f4"), ("v", "<f4")] if with_uv else [])
    vert = np.empty(len(mesh.vertices), dtype=fields)
    for k, name in enumerate("xyz"):
        vert[name] = mesh.vertices[:, k]
        vert["n" + name] = mesh.normals[:, k]
    if with_uv:
        vert["u"], vert["v"] = mesh.uvs[:, 0], mesh.uvs[:, 1]
    face = np.empty(len(mesh.faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, mesh.faces
    props = "".join(f"property float {name}\n" for name, _ in fields)
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vert)}\n{props}"
        f"element face {len(face)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vert.tobytes())
        f.write(face.tobytes())
