"""The data messages (SPEC.md section 4): Frame (capture client -> server: colour, depth, pose,
panorama) and Result (server -> clients: the lighting of one processed frame)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from arlight.core.contracts import Confidence, Diagnostics
from arlight.core.frames import CompactLight

from .codecs import (
    DEFAULT_COLOR_CODEC,
    DEFAULT_DEPTH_CODEC,
    DEFAULT_JPEG_QUALITY,
    encode_color,
    encode_depth,
)
from .diagnostics import read_diagnostics
from .errors import ProtocolError
from .fields import (
    FieldReader,
    float_list,
    pose_to_wire,
    read_float,
    read_floats,
    read_plain_map,
    read_pose,
    to_plain,
    type_name,
)
from .images import ImageParts, add_image
from .layouts import read_exports
from .probe import ProbeCube

# a light direction on the wire (SPEC.md section 4, "result: directions"): a unit vector, its
# norm within this of 1 (the reference server rotates it by the frame's pose, rigid within
# 1e-3), or exactly [0, 0, 0]: no direction
DIRECTION_NORM_TOLERANCE = 0.01

# Result.compact_sources (SPEC.md section 4, "result: compact sources"): 1..4 maps with these
# keys, in this order; absent = none
MAX_COMPACT_SOURCES = 4
COMPACT_SOURCE_KEYS = (
    "direction_world",
    "direction_camera",
    "intensity",
    "rgb",
    "angular_radius_deg",
    "share",
)


@dataclass
class Frame:
    TYPE: ClassVar[str] = "frame"
    seq: int  # >= 0, per session, increasing
    timestamp: float  # capture time, sender clock, seconds
    color: np.ndarray | None  # (H, W, 3) uint8 RGB; None with depth: a panorama-only frame
    depth: np.ndarray | None  # (H, W) uint16, SessionConfig.depth_scale units per metre,
    # 0 = missing; None together with color (then panorama is required)
    pose: np.ndarray | None = None  # (4, 4) float64 camera-to-world
    panorama: np.ndarray | None = None  # (h, w, 3) uint8 RGB equirectangular
    color_codec: str = DEFAULT_COLOR_CODEC  # also used for the panorama
    depth_codec: str = DEFAULT_DEPTH_CODEC
    jpeg_quality: int = DEFAULT_JPEG_QUALITY

    def _pack(self, parts: list) -> dict:
        nm = "frame"
        color, depth = self.color, self.depth
        if isinstance(color, np.ndarray) and isinstance(depth, np.ndarray):
            if color.shape[:2] != depth.shape[:2]:
                raise ProtocolError(
                    "bad_field",
                    f"depth shape {depth.shape} and colour shape {color.shape} must agree in "
                    "(H, W)",
                    f"{nm}.depth",
                )
        out: dict[str, Any] = {
            "seq": to_plain(self.seq),
            "timestamp": to_plain(self.timestamp),
            "pose": None if self.pose is None else pose_to_wire(self.pose, f"{nm}.pose"),
        }
        if (color is None) != (depth is None):
            missing = "color" if color is None else "depth"
            raise ProtocolError(
                "bad_field",
                "give both colour and depth, or neither (a panorama-only frame)",
                f"{nm}.{missing}",
            )
        if color is None and self.panorama is None:
            raise ProtocolError(
                "bad_field",
                "a frame without colour and depth must carry a panorama",
                f"{nm}.panorama",
            )
        out["color"] = (
            None
            if color is None
            else add_image(
                parts,
                *encode_color(color, self.color_codec, self.jpeg_quality, field=f"{nm}.color"),
            )
        )
        out["depth"] = (
            None
            if depth is None
            else add_image(parts, *encode_depth(depth, self.depth_codec, field=f"{nm}.depth"))
        )
        out["panorama"] = (
            None
            if self.panorama is None
            else add_image(
                parts,
                *encode_color(
                    self.panorama, self.color_codec, self.jpeg_quality, field=f"{nm}.panorama"
                ),
            )
        )
        return out

    @classmethod
    def _unpack(cls, h: FieldReader, v: int, images: ImageParts) -> Frame:
        seq = h.int("seq")
        timestamp = h.float("timestamp")
        pose = h.raw("pose", nullable=True)
        pose = None if pose is None else read_pose(pose, h.f("pose"))
        dc = images.descriptor(h, "color", depth=False, nullable=True)
        dd = images.descriptor(h, "depth", depth=True, nullable=True)
        dp = images.descriptor(h, "panorama", depth=False, nullable=True)
        if (dc is None) != (dd is None):
            raise ProtocolError(
                "bad_field",
                "give both colour and depth, or neither (a panorama-only frame)",
                h.f("color" if dc is None else "depth"),
            )
        if dc is None and dp is None:
            raise ProtocolError(
                "bad_field",
                "a frame without colour and depth must carry a panorama",
                h.f("panorama"),
            )
        if dc is not None and (dc[2], dc[3]) != (dd[2], dd[3]):
            raise ProtocolError(
                "bad_field",
                f"depth is {dd[2]} x {dd[3]}, colour {dc[2]} x {dc[3]}: they must agree",
                h.f("depth"),
            )
        h.done()
        images.done(h.name)
        color = images.decode(dc)
        depth = images.decode(dd)
        panorama = images.decode(dp)
        first = dc if dc is not None else dp  # the colour codec: of the colour, else panorama
        quality = first[0].get("quality", DEFAULT_JPEG_QUALITY)
        depth_codec = DEFAULT_DEPTH_CODEC if dd is None else dd[1]
        return cls(seq, timestamp, color, depth, pose, panorama, first[1], depth_codec, quality)


@dataclass(kw_only=True)
class Result:
    """The lighting of one processed frame (server -> capture and display clients).

    Built with keywords only. `diagnostics`: a bounded map of plain values (str, bool, int,
    float, nil, arrays of numbers, maps of these; SPEC.md "diagnostics"), e.g. the pipeline's
    `{"tracking": {"ok": True, "reason": ""}}`; anything else is refused by encode().

    `confidence`: a `Confidence` (arlight.core.contracts), the type the pipeline makes. A plain
    map is accepted too (the wire carries any map of plain values, SPEC.md "result"): it is
    read with `Confidence.from_dict` and kept as it came, so that it goes out unchanged
    (`confidence_map`); decode() builds every Result that way.
    """

    TYPE: ClassVar[str] = "result"
    seq: int
    timestamp: float  # the frame's capture timestamp, sender clock, seconds
    sh: list[float]  # radiance SH, luminance, world frame, L^2 coefficients
    sh_camera: list[float] | None = None  # the same light in this frame's camera frame
    sh_rgb: list[list[float]] | None = None  # 3 x L^2, world frame
    dominant_direction_camera: list[float]  # unit vector towards the light
    dominant_direction_world: list[float]
    intensity: float
    # the compact sources kept beside the SH (optional key: absent = none): 1..4 maps with
    # COMPACT_SOURCE_KEYS (read_compact_sources; `compact_sources_to_wire` of CompactLights)
    compact_sources: list[dict[str, Any]] | None = None
    confidence: Confidence
    pose: list[list[float]]  # 4 x 4 camera-to-world
    timings_ms: dict[str, float]
    diagnostics: Diagnostics = dataclasses.field(default_factory=Diagnostics)
    frames_received: int  # session counters so far
    frames_processed: int
    frames_dropped: int
    server_receive_time: float  # server wall clock, seconds
    server_finish_time: float
    composite: np.ndarray | None = None  # (H, W, 3) uint8 RGB
    composite_codec: str = "jpeg"
    jpeg_quality: int = DEFAULT_JPEG_QUALITY
    # the frame's panorama light (optional keys, all three or none: absent = no panorama),
    # in the PANORAMA's frame (+y up, u = atan2(x, -z) / 2 pi), radiance of the HDR map
    panorama_sh: list[float] | None = None  # luminance, L^2 coefficients
    panorama_sh_rgb: list[list[float]] | None = None  # 3 x L^2, linear R, G, B
    panorama_dominant_direction: list[float] | None = None  # unit, towards the light
    # the light in the engine layouts the session's Hello asked for (optional key: absent
    # when it asked for none): layout name -> numbers, CAMERA frame with the engine's axes
    exports: dict | None = None
    # the frame's reflection probe, when the session's Hello asked for one (optional key:
    # absent otherwise, and for a frame that made none): SPEC.md "result: the reflection probe"
    probe: ProbeCube | None = None

    def __post_init__(self) -> None:
        self._confidence_map: tuple[Confidence, dict] | None = None
        given: Any = self.confidence
        if isinstance(given, Mapping):  # as the wire carries it: read, and kept as it came
            plain = to_plain(dict(given))
            self.confidence = Confidence.from_dict(plain)
            self._confidence_map = (self.confidence, plain)

    @property
    def confidence_map(self) -> Any:
        """Result.confidence as the wire carries it: the map this Result was built or
        decoded from (while `confidence` is still the Confidence read from it), else
        `confidence.to_dict()`."""
        kept = self._confidence_map
        if kept is not None and kept[0] is self.confidence:
            return kept[1]
        if isinstance(self.confidence, Confidence):
            return self.confidence.to_dict()
        return self.confidence  # neither a Confidence nor a map: encode() refuses it

    def _pack(self, parts: list) -> dict:
        out = {
            "seq": to_plain(self.seq),
            "timestamp": to_plain(self.timestamp),
            "sh": float_list(self.sh, "result.sh"),
            "sh_camera": None
            if self.sh_camera is None
            else float_list(self.sh_camera, "result.sh_camera"),
            "sh_rgb": None if self.sh_rgb is None else float_list(self.sh_rgb, "result.sh_rgb"),
            "dominant_direction_camera": float_list(
                self.dominant_direction_camera, "result.dominant_direction_camera"
            ),
            "dominant_direction_world": float_list(
                self.dominant_direction_world, "result.dominant_direction_world"
            ),
            "intensity": to_plain(self.intensity),
        }
        if self.compact_sources is not None:  # optional key: absent when none was kept
            out["compact_sources"] = read_compact_sources(
                to_plain(self.compact_sources), "result.compact_sources"
            )
        out |= {
            "confidence": to_plain(self.confidence_map),
            "pose": pose_to_wire(self.pose, "result.pose"),
            "timings_ms": to_plain(self.timings_ms),
            "diagnostics": to_plain(self.diagnostics),
            "frames_received": to_plain(self.frames_received),
            "frames_processed": to_plain(self.frames_processed),
            "frames_dropped": to_plain(self.frames_dropped),
            "server_receive_time": to_plain(self.server_receive_time),
            "server_finish_time": to_plain(self.server_finish_time),
        }
        given = [
            self.panorama_sh is not None,
            self.panorama_sh_rgb is not None,
            self.panorama_dominant_direction is not None,
        ]
        if any(given) and not all(given):
            missing = [k for k, g in zip(_PANORAMA_RESULT_KEYS, given, strict=True) if not g]
            raise ProtocolError(
                "bad_field",
                "give panorama_sh, panorama_sh_rgb and "
                "panorama_dominant_direction together, or none",
                f"result.{missing[0]}",
            )
        if all(given):  # optional keys: absent when the frame had no panorama
            out["panorama_sh"] = float_list(self.panorama_sh, "result.panorama_sh")
            out["panorama_sh_rgb"] = float_list(self.panorama_sh_rgb, "result.panorama_sh_rgb")
            out["panorama_dominant_direction"] = float_list(
                self.panorama_dominant_direction, "result.panorama_dominant_direction"
            )
        if self.exports is not None:  # optional key: absent when the session asked for none
            out["exports"] = read_exports(to_plain(self.exports), "result.exports")
        if self.probe is not None:  # optional key: absent when the frame carries none
            out["probe"] = self.probe._pack(parts, "result.probe")
        out["composite"] = None
        if self.composite is not None:
            out["composite"] = add_image(
                parts,
                *encode_color(
                    self.composite,
                    self.composite_codec,
                    self.jpeg_quality,
                    field="result.composite",
                ),
            )
        return out

    @classmethod
    def _unpack(cls, h: FieldReader, v: int, images: ImageParts) -> Result:
        seq = h.int("seq")
        timestamp = h.float("timestamp")
        sh = h.floats("sh", max_len=1024)
        bands = math.isqrt(len(sh))
        if not sh or bands * bands != len(sh):
            raise ProtocolError(
                "bad_field", f"{len(sh)} coefficients is not L^2 for L >= 1", h.f("sh")
            )
        sh_camera = h.raw("sh_camera", nullable=True)
        if sh_camera is not None:
            sh_camera = read_floats(sh_camera, h.f("sh_camera"), len(sh))
        sh_rgb = h.raw("sh_rgb", nullable=True)
        if sh_rgb is not None:
            if type(sh_rgb) is not list or len(sh_rgb) != 3:
                raise ProtocolError(
                    "bad_field", "expected 3 arrays (R, G, B) of L^2 numbers", h.f("sh_rgb")
                )
            sh_rgb = [
                read_floats(c, f"{h.f('sh_rgb')}[{i}]", len(sh)) for i, c in enumerate(sh_rgb)
            ]
        fields: dict[str, Any] = dict(
            seq=seq,
            timestamp=timestamp,
            sh=sh,
            sh_camera=sh_camera,
            sh_rgb=sh_rgb,
            dominant_direction_camera=read_direction(
                h.raw("dominant_direction_camera"), h.f("dominant_direction_camera")
            ),
            dominant_direction_world=read_direction(
                h.raw("dominant_direction_world"), h.f("dominant_direction_world")
            ),
            intensity=h.float("intensity"),
            compact_sources=read_compact_sources(h.raw("compact_sources"), h.f("compact_sources"))
            if "compact_sources" in h.d  # optional key: absent = no compact source
            else None,
            confidence=read_plain_map(h.raw("confidence"), h.f("confidence"), 0, 64),
            pose=read_pose(h.raw("pose"), h.f("pose")).tolist(),
        )
        if any(fields["dominant_direction_camera"]) != any(fields["dominant_direction_world"]):
            raise ProtocolError(
                "bad_field",
                "one dominant direction is [0, 0, 0] and the other "
                "is not: a light has a direction in both frames or in neither",
                h.f("dominant_direction_camera"),
            )
        timings = read_plain_map(h.raw("timings_ms"), h.f("timings_ms"), 0, 64)
        fields["timings_ms"] = {
            k: read_float(x, f"{h.f('timings_ms')}.{k}", 0.0) for k, x in timings.items()
        }
        fields["diagnostics"] = read_diagnostics(h.raw("diagnostics"), h.f("diagnostics"))
        for key in ("frames_received", "frames_processed", "frames_dropped"):
            fields[key] = h.int(key)
        for key in ("server_receive_time", "server_finish_time"):
            fields[key] = h.float(key)
        fields.update(_read_panorama_light(h))
        if "exports" in h.d:  # optional key: absent = the session asked for no layout
            fields["exports"] = read_exports(h.raw("exports"), h.f("exports"))
        probe = None
        if "probe" in h.d:  # optional key: absent = no probe this frame
            probe = ProbeCube._unpack(h.map("probe"), images)
        dc = images.descriptor(h, "composite", depth=False, nullable=True)
        h.done()
        images.done(h.name)
        if probe is not None:
            fields["probe"] = probe.cube()
        if dc is not None:
            fields.update(
                composite=images.decode(dc),
                composite_codec=dc[1],
                jpeg_quality=dc[0].get("quality", DEFAULT_JPEG_QUALITY),
            )
        return cls(**fields)


_PANORAMA_RESULT_KEYS = ("panorama_sh", "panorama_sh_rgb", "panorama_dominant_direction")


def _read_panorama_light(h: FieldReader) -> dict:
    """Result's optional panorama keys: all three or none (SPEC.md, "result")."""
    present = [k in h.d for k in _PANORAMA_RESULT_KEYS]
    if not any(present):
        return {}
    if not all(present):
        missing = _PANORAMA_RESULT_KEYS[present.index(False)]
        raise ProtocolError(
            "bad_field", "missing (the panorama keys come all three or none)", h.f(missing)
        )
    coeffs = h.floats("panorama_sh", max_len=1024)
    bands = math.isqrt(len(coeffs))
    if not coeffs or bands * bands != len(coeffs):
        raise ProtocolError(
            "bad_field", f"{len(coeffs)} coefficients is not L^2 for L >= 1", h.f("panorama_sh")
        )
    rgb = h.raw("panorama_sh_rgb")
    if type(rgb) is not list or len(rgb) != 3:
        raise ProtocolError(
            "bad_field", "expected 3 arrays (R, G, B) of L^2 numbers", h.f("panorama_sh_rgb")
        )
    rgb = [read_floats(c, f"{h.f('panorama_sh_rgb')}[{i}]", len(coeffs)) for i, c in enumerate(rgb)]
    direction = read_direction(
        h.raw("panorama_dominant_direction"), h.f("panorama_dominant_direction")
    )
    return {"panorama_sh": coeffs, "panorama_sh_rgb": rgb, "panorama_dominant_direction": direction}


def read_direction(v: Any, name: str) -> list[float]:
    """A direction towards the light: 3 numbers, a unit vector (norm within
    DIRECTION_NORM_TOLERANCE of 1) or exactly [0, 0, 0], no direction (SPEC.md section 4,
    "result: directions")."""
    d = read_floats(v, name, 3)
    if not any(d):
        return d
    norm = math.sqrt(sum(x * x for x in d))
    if abs(norm - 1.0) > DIRECTION_NORM_TOLERANCE:
        raise ProtocolError(
            "bad_field",
            f"norm {norm:.6g}: expected a unit vector (within "
            f"{DIRECTION_NORM_TOLERANCE:g}) or [0, 0, 0] for no direction",
            name,
        )
    return d


def read_compact_sources(v: Any, name: str) -> list[dict[str, Any]]:
    """Result.compact_sources (SPEC.md section 4, "result: compact sources"): an array of
    1..MAX_COMPACT_SOURCES maps, each with exactly COMPACT_SOURCE_KEYS: two unit directions,
    intensity >= 0, rgb 3 numbers >= 0 or nil, angular_radius_deg 0..90, share 0..1 (all
    finite). Returns the maps in that key order; bad_field naming e.g.
    `result.compact_sources[0].share` otherwise."""
    if type(v) is not list or not 1 <= len(v) <= MAX_COMPACT_SOURCES:
        got = f"{len(v)} entries" if type(v) is list else type_name(v)
        raise ProtocolError(
            "bad_field",
            f"expected an array of 1..{MAX_COMPACT_SOURCES} maps (none: omit the key), got {got}",
            name,
        )
    out = []
    for i, x in enumerate(v):
        h = FieldReader(x, f"{name}[{i}]")
        source: dict[str, Any] = {
            "direction_world": _read_unit(h.raw("direction_world"), h.f("direction_world")),
            "direction_camera": _read_unit(h.raw("direction_camera"), h.f("direction_camera")),
            "intensity": h.float("intensity", 0.0),
        }
        rgb = h.raw("rgb", nullable=True)
        if rgb is not None:
            rgb = read_floats(rgb, h.f("rgb"), 3)
            for j, c in enumerate(rgb):
                read_float(c, f"{h.f('rgb')}[{j}]", 0.0)
        source["rgb"] = rgb
        source["angular_radius_deg"] = h.float("angular_radius_deg", 0.0, 90.0)
        source["share"] = h.float("share", 0.0, 1.0)
        h.done()
        out.append(source)
    return out


def _read_unit(v: Any, name: str) -> list[float]:
    """A compact source's direction: a unit vector (read_direction's tolerance), never
    [0, 0, 0] (a source always has a direction)."""
    d = read_direction(v, name)
    if not any(d):
        raise ProtocolError("bad_field", "[0, 0, 0]: a compact source has a direction", name)
    return d


def compact_sources_to_wire(lights: Sequence[CompactLight]) -> list[dict[str, Any]] | None:
    """The pipeline's CompactLights (FrameResult.compact_sources) as Result.compact_sources
    takes them: plain maps in COMPACT_SOURCE_KEYS order, None when there is none (the
    optional key is then omitted). At most MAX_COMPACT_SOURCES (encode refuses more)."""
    if not lights:
        return None
    return [
        {
            "direction_world": [float(x) for x in s.direction_world],
            "direction_camera": [float(x) for x in s.direction_camera],
            "intensity": float(s.intensity),
            "rgb": None if s.rgb is None else [float(x) for x in s.rgb],
            "angular_radius_deg": float(s.angular_radius_deg),
            "share": float(s.share),
        }
        for s in lights
    ]
