"""Glossy and mirror virtual objects lit by the reflection probe (issue 33, item 2).

Materials (`virtual_scene.Material`, glTF's metallic-roughness reading, as the synth's
Mitsuba `principled` truth): `mirror` is a perfect conductor of reflectance `albedo`;
otherwise an object with `metalness` > 0 or `roughness` < 1 is glossy: F0 = 0.04 (1 - m) +
albedo m, a GGX lobe of perceptual roughness r (alpha = r^2), and a diffuse part (1 - m)
albedo lit exactly as the diffuse renderer lights it (SSDO transfer and the estimated light,
`rendering`), weighted by the principled BSDF's diffuse Fresnel factors
(`principled_diffuse_weight`: 0.976 facing the camera, 0.49 at its silhouette). Objects with
roughness 1 and metalness 0 (the default) are left to the diffuse renderer: nothing changes
for them.

Per pixel, with view direction v (camera to surface, world), normal n and mirror direction
r = v - 2 (v.n) n:
- parallax: r is followed through the probe's room grid from the surface point; where it
  meets the room at h, the probe is read along h - probe point (the direction in which the
  probe saw that surface), else along r (a distant direction is the same from anywhere);
- self-occlusion: r is also cast against the virtual objects; where one is met before the
  room, the reflection is that surface's Lambertian radiance under the distant light
  (albedo / pi times the SH irradiance at its normal: no shadow, no second bounce);
- radiance: mirror: albedo L(r, level 0); glossy: (1 - m) albedo / pi E w + L(r, level of
  r) (F0 A + B) (split sum, `probe_cube.env_brdf`; w the diffuse weight above).
The occlusion test follows the mirror direction only, also for a glossy lobe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from arlight.pipeline import probe_cube, sh
from arlight.pipeline.probe import ProbeResult
from arlight.pipeline.virtual_gbuffer import VirtualRaycaster
from arlight.pipeline.virtual_scene import Material

DIELECTRIC_F0 = 0.04  # glTF's and Mitsuba principled's (specular 0.5) reflectance at normal
SURFACE_OFFSET_M = 1e-3  # reflected rays start this far off the surface


@dataclass(frozen=True)
class Glossiness:
    """What the probe shading does with one Material: kind 0 none (diffuse renderer), 1
    mirror, 2 glossy; diffuse_rgb: the Lambertian part's albedo; f0 (3,); roughness
    (perceptual, 0..1)."""

    kind: int
    diffuse_rgb: np.ndarray
    f0: np.ndarray
    roughness: float


def glossiness_of(material: Material) -> Glossiness:
    """The Glossiness of a Material (see the module text)."""
    albedo = np.asarray(material.albedo, np.float64)
    if material.mirror:
        return Glossiness(1, np.zeros(3), albedo, 0.0)
    m = float(np.clip(material.metalness, 0.0, 1.0))
    r = float(np.clip(material.roughness, 0.0, 1.0))
    if m <= 0.0 and r >= 1.0:
        return Glossiness(0, albedo, np.zeros(3), 1.0)
    f0 = DIELECTRIC_F0 * (1.0 - m) + albedo * m
    return Glossiness(2, (1.0 - m) * albedo, f0, r)


def is_reflective(material: Material) -> bool:
    """Whether the probe shades this material (a mirror, metallic or not fully rough)."""
    return glossiness_of(material).kind != 0


def shade(
    probe: ProbeResult,
    looks: list[Glossiness],
    object_index: np.ndarray,
    points_world: np.ndarray,
    normals_world: np.ndarray,
    view_world: np.ndarray,
    irradiance_rgb: np.ndarray,
    raycaster: VirtualRaycaster | None,
) -> np.ndarray:
    """(K, 3) linear radiance of K virtual pixels of reflective objects.

    looks: per scene object; object_index (K,); points_world (K, 3) metres; normals_world
    (K, 3) unit, facing the camera; view_world (K, 3) unit, camera to point; irradiance_rgb
    (K, 3): the diffuse renderer's irradiance at each pixel (its e_v, so that
    albedo / pi * irradiance is what it would show)."""
    k = len(object_index)
    out = np.zeros((k, 3))
    if k == 0:
        return out
    n = np.asarray(normals_world, np.float64)
    v = np.asarray(view_world, np.float64)
    cos_nv = np.sum(n * v, axis=1, keepdims=True)
    r = v - 2.0 * cos_nv * n
    r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12)
    start = np.asarray(points_world, np.float64) + SURFACE_OFFSET_M * n
    lookup = r.copy()
    t_room = np.full(k, np.inf)
    if probe.grid is not None:
        t_room, _ = probe.grid.march(start, r)
        hit = np.isfinite(t_room)
        towards = start[hit] + t_room[hit, None] * r[hit] - probe.point_world
        lookup[hit] = towards / np.maximum(np.linalg.norm(towards, axis=1, keepdims=True), 1e-9)
    kinds = np.array([g.kind for g in looks])[object_index]
    rough = np.array([g.roughness for g in looks])[object_index]
    f0 = np.stack([g.f0 for g in looks])[object_index]
    diffuse = np.stack([g.diffuse_rgb for g in looks])[object_index]
    # mirrors read level 0 alone, so a scene of mirrors never makes the prefiltered levels
    cube = probe.mirror if np.all(kinds == 1) else probe.mips
    lods = cube.lod_of(np.where(kinds == 1, 0.0, rough))
    seen = probe_cube.sample(cube, lookup, lods).astype(np.float64)
    if raycaster is not None:
        t_virtual, other, other_n = raycaster.first_hits(start, r)
        blocked = np.isfinite(t_virtual) & (t_virtual < t_room)
        if np.any(blocked):
            seen[blocked] = _lambertian(probe, looks, other[blocked], other_n[blocked], r[blocked])
    spec = np.where(
        (kinds == 1)[:, None],
        f0,
        probe_cube.env_brdf(f0, rough, np.abs(cos_nv[:, 0])),
    )
    weight = np.where(kinds == 2, principled_diffuse_weight(np.abs(cos_nv[:, 0])), 1.0)
    return diffuse / math.pi * irradiance_rgb * weight[:, None] + spec * seen


def principled_diffuse_weight(n_dot_v: np.ndarray) -> np.ndarray:
    """The Disney / principled diffuse lobe's Fresnel factors (Burley 2012, as Mitsuba's
    `principled`): (1 - 0.5 F(v)) times the mean over cosine-weighted incoming directions
    of (1 - 0.5 F(l)), 1 - 1/42, with F(x) = (1 - cos x)^5; the retro-reflection term
    (rough surfaces at grazing angles) is left out."""
    return (1.0 - 0.5 * (1.0 - np.clip(n_dot_v, 0.0, 1.0)) ** 5) * (1.0 - 1.0 / 42.0)


def _lambertian(
    probe: ProbeResult,
    looks: list[Glossiness],
    index: np.ndarray,
    normals: np.ndarray,
    ray: np.ndarray,
) -> np.ndarray:
    """Radiance of virtual surfaces seen along `ray`: albedo / pi x the distant light's
    irradiance at their normal (turned towards the ray's origin)."""
    nn = np.where(np.sum(normals * ray, axis=1, keepdims=True) > 0, -normals, normals)
    albedo = np.stack([g.diffuse_rgb + g.f0 for g in looks])[index]
    e = np.maximum(sh.irradiance_at(probe.distant.sh, nn), 0.0)
    return albedo / math.pi * e[:, None] * np.asarray(probe.distant.rgb, np.float64)


__all__ = [
    "DIELECTRIC_F0",
    "Glossiness",
    "glossiness_of",
    "is_reflective",
    "principled_diffuse_weight",
    "shade",
]
