"""Surface materials of generated scenes: realistic linear albedos and procedural textures.

A material is either uniform (``grey``, ``colour``, ``paint``) or textured over the shape's
uv coordinates: ``checker`` (two colours), ``noise`` (smooth value noise, +-15 %), ``wood``
(rings warped by noise), ``fabric`` (a fine weave). Textures are (T, T, 3) float32 linear
albedo, made from the material's seed alone. Albedos follow measured ranges (white paint
0.7-0.85, wood 0.15-0.45, fabric 0.1-0.6, concrete 0.25-0.4): no surface above 0.9.
Virtual objects' materials add ``roughness`` (glossy), ``metalness`` and ``mirror``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

TEXTURE_SIZE = 256
KINDS = ("grey", "colour", "paint", "checker", "noise", "wood", "fabric")


@dataclass(frozen=True)
class Material:
    """kind (KINDS); albedo_rgb: mean linear albedo; colours: the texture's base colours;
    repeats: texture tiles per uv unit (planes' uvs are metres); seed: the texture's noise."""

    kind: str
    albedo_rgb: tuple[float, float, float]
    colours: tuple[tuple[float, float, float], ...] = ()  # linear RGB
    repeats: float = 1.0
    seed: int = 0
    roughness: float | None = None  # virtual objects: GGX roughness (None: Lambertian)
    metalness: float = 0.0
    mirror: bool = False

    @property
    def textured(self) -> bool:
        return self.kind in ("checker", "noise", "wood", "fabric")

    def describe(self) -> dict:
        """The JSON description written into lighting_gt.json's scene_objects."""
        out: dict = {"kind": self.kind, "albedo_rgb": [round(x, 4) for x in self.albedo_rgb]}
        if self.colours:
            out["colours"] = [[round(x, 4) for x in c] for c in self.colours]
        if self.textured:
            out["repeats_per_uv_unit"] = self.repeats
        if self.mirror:
            out["mirror"] = True
        elif self.roughness is not None:
            out.update(roughness=self.roughness, metalness=self.metalness)
        return out

    def texture(self) -> np.ndarray:
        """(T, T, 3) float32 linear albedo of a textured material."""
        rng = np.random.default_rng(self.seed)
        t = TEXTURE_SIZE
        c = [np.asarray(x, np.float32) for x in self.colours] or [np.asarray(self.albedo_rgb)]
        if self.kind == "checker":
            i = np.arange(t) * 2 // t
            mask = (i[:, None] + i[None, :]) % 2 == 0
            return np.where(mask[..., None], c[0], c[1]).astype(np.float32)
        noise = _value_noise(rng, t, cells=8)
        if self.kind == "noise":
            base = c[0] if len(c) == 1 else c[0] * (1 - noise[..., None]) + c[1] * noise[..., None]
            return np.clip(
                base * (0.85 + 0.3 * _value_noise(rng, t, 16))[..., None], 0, 0.9
            ).astype(np.float32)
        y, x = np.mgrid[0:t, 0:t] / t
        if self.kind == "wood":
            rings = 0.5 + 0.5 * np.sin(2 * math.pi * (6 * x + 2.5 * noise))
            grain = _value_noise(rng, t, 64)
            k = (0.7 * rings + 0.3 * grain)[..., None]
            return np.clip(c[0] * (1 - k) + c[1] * k, 0, 0.9).astype(np.float32)
        # fabric: threads across and along, each row and column a little different
        warp = 0.5 + 0.5 * np.sin(2 * math.pi * 32 * x)
        weft = 0.5 + 0.5 * np.sin(2 * math.pi * 32 * y)
        k = (0.35 * warp * weft + 0.2 * noise)[..., None]
        return np.clip(c[0] * (0.85 + k), 0, 0.9).astype(np.float32)


def _value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """(size, size) smooth tileable noise in [0, 1]: a random grid up-sampled bicubically."""
    grid = rng.random((cells, cells)).astype(np.float32)
    tiled = np.tile(grid, (3, 3))
    big = cv2.resize(tiled, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)
    out = big[size : 2 * size, size : 2 * size]
    return (out - out.min()) / max(float(np.ptp(out)), 1e-6)


RGB = tuple[float, float, float]


def _triple(values) -> RGB:
    """Three floats (a linear RGB colour) from any sequence of three numbers."""
    r, g, b = (float(x) for x in values)
    return r, g, b


def _rgb(
    rng: np.random.Generator, low: float, high: float, saturation: float
) -> tuple[float, float, float]:
    """A colour of mean albedo in [low, high] and the given saturation (0 = grey)."""
    hue = rng.random()
    rgb = np.array([0.5 + 0.5 * math.cos(2 * math.pi * (hue + k / 3)) for k in range(3)])
    rgb = (1 - saturation) + saturation * rgb
    rgb *= rng.uniform(low, high) / rgb.mean()
    return _triple(np.clip(rgb, 0.02, 0.9))


def random_material(rng: np.random.Generator, kinds: tuple[str, ...], seed: int) -> Material:
    """One material of a kind drawn from `kinds`, at realistic albedo."""
    kind = str(rng.choice(kinds))
    if kind == "grey":
        grey = float(rng.uniform(0.2, 0.7))
        return Material("grey", (grey, grey, grey))
    if kind in ("colour", "paint"):
        low, high = (0.5, 0.8) if kind == "paint" else (0.15, 0.6)
        return Material(kind, _rgb(rng, low, high, float(rng.uniform(0.2, 0.8))))
    if kind == "wood":
        light = np.array([0.45, 0.30, 0.17]) * rng.uniform(0.7, 1.1)
        dark = light * rng.uniform(0.45, 0.65)
        colours = (_triple(light), _triple(dark))
        return Material(
            "wood", _triple((light + dark) / 2), colours, float(rng.uniform(1, 3)), seed
        )
    if kind == "fabric":
        c = _rgb(rng, 0.1, 0.55, float(rng.uniform(0.3, 0.9)))
        return Material("fabric", c, (c,), float(rng.uniform(1, 2)), seed)
    a, b = _rgb(rng, 0.1, 0.7, 0.7), _rgb(rng, 0.4, 0.8, 0.0)
    if kind == "checker":
        return Material(
            "checker", _triple(np.add(a, b) / 2), (a, b), float(rng.choice([2.0, 4.0])), seed
        )
    return Material("noise", _triple(np.add(a, b) / 2), (a, b), 1.0, seed)


def ground_material(
    rng: np.random.Generator, seed: int, kinds=("noise", "checker", "grey")
) -> Material:
    """A ground (concrete, tiles, earth): albedo 0.2-0.45, textured over metres."""
    kind = str(rng.choice(kinds))
    if kind == "wood":
        return random_material(rng, ("wood",), seed)
    a = _rgb(rng, 0.25, 0.42, 0.15)
    if kind == "checker":
        b = _triple(np.multiply(a, 0.75))
        return Material("checker", _triple(np.add(a, b) / 2), (a, b), 1.0, seed)
    if kind == "grey":
        g = float(np.mean(a))
        return Material("grey", (g, g, g))
    b = _triple(np.multiply(a, 0.85))
    return Material("noise", _triple(np.add(a, b) / 2), (a, b), 0.5, seed)
