"""The reflection probe on the wire (SPEC.md section 4, "hello: the reflection probe" and
"result: the reflection probe"): Hello `config.probe` asks for it (`ProbeRequest`), Result
`probe` carries the frame's cube map (`ProbeCube`).

The cube: six square faces per mip level, +X, -X, +Y, -Y, +Z, -Z along the session's world
axes, each face's rows top to bottom and columns left to right in OpenGL's cube-map
orientation (table 8.19, `face_directions`); texels linear RGB radiance in the units of the
Result's `sh`. On the wire every texel is one little-endian uint32 in RGB9E5 (OpenGL's
GL_RGB9_E5 / UNSIGNED_INT_5_9_9_9_REV: 9-bit mantissas in bits 0-8, 9-17, 18-26 for R, G,
B, a shared 5-bit exponent, bias 15, in bits 27-31), levels one after another, and the whole
run of texels one zstd frame with its content size. Why this codec (about a quarter of
float16's bytes after zstd, loaded by GPUs as it is): docs/results/probe.md, "On the wire".

Nothing here knows the pipeline: the sizes below are the probe's (pipeline/probe_cube.py),
checked equal by tests/test_probe_wire.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zstandard

from .errors import ProtocolError
from .fields import FieldReader, float_list, read_float, read_floats, to_plain, type_name
from .images import ImageParts

PROBE_SIZE_MIN = 32  # texels a face of level 0 (a power of two)
PROBE_SIZE_MAX = 256
PROBE_LAST_LEVEL = 4  # texels a face of the roughest level: the chain 256 ... 4 has 7 levels
PROBE_ENCODINGS = ("rgb9e5",)
PROBE_POINT_MAX_M = 1.0e4  # |coordinate| of a probe point, metres
PROBE_ZSTD_LEVEL = 3  # 0.5 ms / 1.6 ms at 64 / 128 texels with mips (docs/results/probe.md)
BYTES_PER_TEXEL = 4
RGB9E5_MAX = 65408.0  # (2^9 - 1) / 2^9 * 2^(31 - 15): the largest value RGB9E5 holds

_REQUEST_KEYS = ("size", "point_world", "mips")


def num_levels(size: int) -> int:
    """Levels of a full chain: size, size / 2, ... down to PROBE_LAST_LEVEL texels a face."""
    return int(round(math.log2(size / PROBE_LAST_LEVEL))) + 1


def probe_bytes(size: int, levels: int) -> int:
    """Decoded bytes of a cube of `levels` levels from `size` texels a face (RGB9E5)."""
    return BYTES_PER_TEXEL * 6 * sum((size >> k) ** 2 for k in range(levels))


MAX_PROBE_BYTES = probe_bytes(PROBE_SIZE_MAX, num_levels(PROBE_SIZE_MAX))  # 2 097 024


def _read_size(v: Any, name: str) -> int:
    if type(v) is not int or not PROBE_SIZE_MIN <= v <= PROBE_SIZE_MAX or v & (v - 1):
        raise ProtocolError(
            "bad_field",
            f"expected a power of two in {PROBE_SIZE_MIN}..{PROBE_SIZE_MAX} texels a face, "
            f"got {v!r}",
            name,
        )
    return v


def _read_point(v: Any, name: str) -> list[float]:
    point = read_floats(v, name, 3)
    for i, x in enumerate(point):
        read_float(x, f"{name}[{i}]", -PROBE_POINT_MAX_M, PROBE_POINT_MAX_M)
    return point


# ------------------------------------------------------------------------------ the Hello


@dataclass(frozen=True)
class ProbeRequest:
    """Hello `config.probe`: the session's Results carry a reflection probe.

    size: texels a face of level 0, a power of two in 32..256; point_world: (x, y, z)
    metres, world frame, where the probe is made (None: the centre of the virtual scene's
    objects, which the session must then have); mips: every GGX-prefiltered level down to 4
    texels a face (False: level 0 only, the radiance itself)."""

    size: int = 64
    point_world: tuple[float, float, float] | None = None
    mips: bool = False

    def _pack(self, name: str) -> dict:
        return {
            "size": _read_size(to_plain(self.size), f"{name}.size"),
            "point_world": None
            if self.point_world is None
            else _read_point(
                float_list(list(self.point_world), f"{name}.point_world"), f"{name}.point_world"
            ),
            "mips": to_plain(self.mips),
        }

    @classmethod
    def _unpack(cls, m: FieldReader) -> ProbeRequest:
        size = _read_size(m.raw("size"), m.f("size"))
        raw = m.raw("point_world", nullable=True)
        point = None if raw is None else tuple(_read_point(raw, m.f("point_world")))
        mips = m.bool("mips")
        m.done()
        return cls(size, point, mips)  # type: ignore[arg-type]

    @property
    def levels(self) -> int:
        """Levels each Result carries."""
        return num_levels(self.size) if self.mips else 1

    @property
    def max_bytes(self) -> int:
        """Decoded bytes of each Result's cube (the compressed part is at most this plus
        zstd's frame overhead)."""
        return probe_bytes(self.size, self.levels)


# ----------------------------------------------------------------------------- the codec


def rgb9e5_encode(radiance: np.ndarray) -> np.ndarray:
    """(..., 3) linear RGB -> (...,) little-endian uint32 RGB9E5 (EXT_texture_shared_exponent:
    each channel clamped to 0..RGB9E5_MAX, NaN to 0, the exponent of the largest, mantissas
    rounded to nearest). float32 arithmetic: exact for the powers of two involved."""
    shape = np.shape(radiance)[:-1]
    v = np.array(radiance, np.float32, copy=True).reshape(-1, 3)
    v[~(v >= 0.0)] = 0.0  # negative and NaN
    np.minimum(v, np.float32(RGB9E5_MAX), out=v)
    peak = v.max(axis=1)
    # floor(log2(peak)) from the float32's exponent bits; max(-B - 1, .) + 1 + B
    exp = np.maximum((peak.view(np.uint32) >> 23).astype(np.int32) - 127, -16) + 16
    inv = ((151 - exp) << 23).astype(np.uint32).view(np.float32)  # 2^(24 - exp) = 1 / step
    bump = np.floor(peak * inv + np.float32(0.5)) >= 512  # the largest mantissa rounds up
    exp += bump
    inv = np.where(bump, inv * np.float32(0.5), inv)
    q = np.floor(v * inv[:, None] + np.float32(0.5)).astype(np.uint32)
    np.minimum(q, 511, out=q)
    packed = q[:, 0] | (q[:, 1] << 9) | (q[:, 2] << 18) | (exp.astype(np.uint32) << 27)
    return packed.astype("<u4").reshape(shape)


def rgb9e5_decode(packed: np.ndarray) -> np.ndarray:
    """(...,) uint32 RGB9E5 -> (..., 3) float32 linear RGB: mantissa x 2^(exponent - 24)."""
    p = np.asarray(packed, np.uint32)
    scale = np.ldexp(1.0, (p >> 27).astype(np.int64) - 24)
    rgb = np.stack([p & 511, (p >> 9) & 511, (p >> 18) & 511], axis=-1).astype(np.float64)
    return (rgb * scale[..., None]).astype(np.float32)


def face_directions(size: int) -> np.ndarray:
    """(6, size, size, 3) unit world directions of every texel centre, as SPEC.md writes
    them: face order +X, -X, +Y, -Y, +Z, -Z; texel (column i, row j) has sc = 2 (i + 0.5) /
    size - 1, tc = 2 (j + 0.5) / size - 1 and direction +X (1, -tc, -sc), -X (-1, -tc, sc),
    +Y (sc, 1, tc), -Y (sc, -1, -tc), +Z (sc, -tc, 1), -Z (-sc, -tc, -1)."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    tc, sc = np.meshgrid(c, c, indexing="ij")  # tc down the rows, sc along a row
    one = np.ones_like(sc)
    faces = [
        (one, -tc, -sc),
        (-one, -tc, sc),
        (sc, one, tc),
        (sc, -one, -tc),
        (sc, -tc, one),
        (-sc, -tc, -one),
    ]
    d = np.stack([np.stack(f, axis=-1) for f in faces])
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------- the Result


@dataclass(eq=False)
class ProbeCube:
    """Result `probe`: one frame's reflection probe.

    point_world: (3,) metres, world frame; levels: list of (6, n_k, n_k, 3) float32 linear
    RGB radiance (the units of `sh`), n_k = size >> k, faces +X, -X, +Y, -Y, +Z, -Z in the
    world's axes, OpenGL orientation (`face_directions`); roughness: per level, the GGX
    perceptual roughness it is prefiltered for (level 0: 0, the radiance itself). On the
    wire each texel is RGB9E5 (`rgb9e5_encode`): decoding gives the texels rounded to 9
    bits of the brightest channel."""

    point_world: list[float]
    levels: list[np.ndarray]
    roughness: list[float] = field(default_factory=lambda: [0.0])
    encoding: str = "rgb9e5"

    @property
    def size(self) -> int:
        return int(self.levels[0].shape[1])

    def __eq__(self, other: object) -> bool:
        """Equal point, roughness, encoding and texels (every level, exactly)."""
        if not isinstance(other, ProbeCube):
            return NotImplemented
        return (
            list(self.point_world) == list(other.point_world)
            and list(self.roughness) == list(other.roughness)
            and self.encoding == other.encoding
            and len(self.levels) == len(other.levels)
            and all(np.array_equal(a, b) for a, b in zip(self.levels, other.levels, strict=True))
        )

    __hash__ = None  # type: ignore[assignment]  # mutable, compared by value

    def _pack(self, parts: list, name: str) -> dict:
        if not self.levels:
            raise ProtocolError("bad_field", "a probe has at least level 0", f"{name}.levels")
        size = _read_size(int(self.levels[0].shape[1]), f"{name}.size")
        count = _read_level_count(len(self.levels), size, f"{name}.levels")
        roughness = _read_roughness(to_plain(list(self.roughness)), count, f"{name}.roughness")
        texels = []
        for k, level in enumerate(self.levels):
            a = np.asarray(level)
            n = size >> k
            if a.shape != (6, n, n, 3):
                raise ProtocolError(
                    "bad_field",
                    f"level {k} must have shape (6, {n}, {n}, 3), got {a.shape}",
                    f"{name}.levels",
                )
            texels.append(rgb9e5_encode(a).reshape(-1))
        raw = np.concatenate(texels).astype("<u4").tobytes()
        payload = zstandard.ZstdCompressor(
            level=PROBE_ZSTD_LEVEL, write_content_size=True
        ).compress(raw)
        out = {
            "point_world": _read_point(
                float_list(list(self.point_world), f"{name}.point_world"), f"{name}.point_world"
            ),
            "size": size,
            "levels": count,
            "roughness": roughness,
            "encoding": _read_encoding(self.encoding, f"{name}.encoding"),
            "buffer": len(parts),
        }
        parts.append(payload)
        return out

    @classmethod
    def _unpack(cls, m: FieldReader, images: ImageParts) -> PendingProbe:
        """The header's probe map checked; its texels are decoded by PendingProbe.cube()
        once every header field is (SPEC.md section 6: payloads last)."""
        point = _read_point(m.raw("point_world"), m.f("point_world"))
        size = _read_size(m.raw("size"), m.f("size"))
        count = _read_level_count(m.raw("levels"), size, m.f("levels"))
        roughness = _read_roughness(m.raw("roughness"), count, m.f("roughness"))
        encoding = _read_encoding(m.raw("encoding"), m.f("encoding"))
        payload = images.part(m, "buffer")
        m.done()
        decode = payload is not None and images.decoding
        return PendingProbe(cls(point, [], roughness, encoding), size, count, payload, decode)


def probe_summary(probe: ProbeCube | None) -> dict | None:
    """What an output record says of a Result's probe, never its texels: None when it
    carried none, else its size (texels a face of level 0), levels, roughness per level
    and point (world, metres)."""
    if probe is None:
        return None
    return {
        "size": int(probe.size),
        "levels": len(probe.levels),
        "roughness": [float(r) for r in probe.roughness],
        "point_world": [float(x) for x in probe.point_world],
    }


@dataclass
class PendingProbe:
    """A Result's probe read from the header, its payload not yet decoded."""

    header: ProbeCube
    size: int
    count: int
    payload: Any
    decode: bool
    name: str = "result.probe.buffer"

    def cube(self) -> ProbeCube:
        """The ProbeCube with its levels (none when the message is only validated)."""
        if not self.decode:
            return self.header
        flat = _decompress(self.payload, probe_bytes(self.size, self.count), self.name)
        levels, start = [], 0
        for k in range(self.count):
            n = self.size >> k
            levels.append(rgb9e5_decode(flat[start : start + 6 * n * n]).reshape(6, n, n, 3))
            start += 6 * n * n
        h = self.header
        return ProbeCube(h.point_world, levels, h.roughness, h.encoding)


def _read_level_count(v: Any, size: int, name: str) -> int:
    full = num_levels(size)
    if type(v) is not int or not 1 <= v <= full:
        raise ProtocolError(
            "bad_field",
            f"expected 1..{full} levels for {size} texels a face (down to "
            f"{PROBE_LAST_LEVEL}), got {v!r}",
            name,
        )
    return v


def _read_roughness(v: Any, count: int, name: str) -> list[float]:
    values = read_floats(v, name, count)
    for i, x in enumerate(values):
        read_float(x, f"{name}[{i}]", 0.0, 1.0)
    if values[0] != 0.0 or any(b <= a for a, b in zip(values, values[1:], strict=False)):
        raise ProtocolError("bad_field", f"expected 0 first, then increasing, got {values}", name)
    return values


def _read_encoding(v: Any, name: str) -> str:
    if type(v) is not str or v not in PROBE_ENCODINGS:
        shown = repr(v[:64]) if type(v) is str else type_name(v)
        raise ProtocolError(
            "bad_codec", f"expected one of {', '.join(PROBE_ENCODINGS)}, got {shown}", name
        )
    return v


def _decompress(payload: Any, expected: int, name: str) -> np.ndarray:
    """The texels of a probe's part: one zstd frame declaring exactly `expected` bytes."""
    data = bytes(payload)
    try:
        size = zstandard.frame_content_size(data)
    except zstandard.ZstdError as exc:
        raise ProtocolError("decode_failed", f"not a zstd frame: {exc}", name) from None
    if size != expected:
        what = "no content size" if size < 0 else f"content size {size} bytes"
        raise ProtocolError(
            "decode_failed", f"zstd frame declares {what}, the probe {expected} bytes", name
        )
    dobj = zstandard.ZstdDecompressor().decompressobj()
    try:
        raw = dobj.decompress(data)  # bounded by the declared (checked) content size
    except zstandard.ZstdError as exc:
        raise ProtocolError("decode_failed", f"zstd: {exc}", name) from None
    if not dobj.eof or dobj.unused_data or len(raw) != expected:
        raise ProtocolError(
            "decode_failed",
            "zstd payload is truncated, has trailing bytes or does not decode to exactly "
            "one frame of the declared size",
            name,
        )
    return np.frombuffer(raw, dtype="<u4")


__all__ = [
    "MAX_PROBE_BYTES",
    "PROBE_ENCODINGS",
    "PROBE_SIZE_MAX",
    "PROBE_SIZE_MIN",
    "ProbeCube",
    "ProbeRequest",
    "face_directions",
    "num_levels",
    "probe_bytes",
    "rgb9e5_decode",
    "rgb9e5_encode",
]
