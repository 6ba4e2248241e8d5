"""The session a capture or display client asks for: Hello and its SessionConfig (SPEC.md
section 4, "hello"), with the camera calibration and the panorama light. The virtual scene is
in scene.py, the engine layout names in layouts.py."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from arlight.core.checks import RIGID_TOLERANCE, CheckError, check_rigid

from .codecs import MAX_IMAGE_SIDE
from .errors import ProtocolError
from .fields import (
    KEY_RE,
    MODES,
    NAME_RE,
    ROLES,
    FieldReader,
    float_list,
    read_str,
    read_token,
    to_plain,
    type_name,
)
from .images import ImageParts
from .layouts import read_export_names
from .probe import ProbeRequest
from .scene import SceneSpec


@dataclass(frozen=True)
class CameraCalibration:
    """Pinhole intrinsics in pixels (Foxglove CameraCalibration; K = [fx 0 cx; 0 fy cy; 0 0 1])."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: str = ""  # "", "plumb_bob", "rational_polynomial", ...
    D: tuple[float, ...] = ()

    def _pack(self) -> dict:
        return {
            "width": to_plain(self.width),
            "height": to_plain(self.height),
            "K": to_plain([self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]),
            "distortion_model": self.distortion_model,
            "D": to_plain(list(self.D)),
        }

    @classmethod
    def _unpack(cls, m: FieldReader) -> CameraCalibration:
        width = m.int("width", 1, MAX_IMAGE_SIDE)
        height = m.int("height", 1, MAX_IMAGE_SIDE)
        k = m.floats("K", 9)
        if k[1] != 0 or k[3] != 0 or k[6] != 0 or k[7] != 0 or k[8] != 1:
            raise ProtocolError(
                "bad_field", "K must be [fx, 0, cx, 0, fy, cy, 0, 0, 1] (no skew)", m.f("K")
            )
        if not (k[0] > 0 and k[4] > 0):
            raise ProtocolError(
                "bad_field", f"focal lengths must be > 0, got {k[0]}, {k[4]}", m.f("K")
            )
        model = m.str("distortion_model", 64)
        d = m.floats("D", max_len=16)
        m.done()
        return cls(width, height, k[0], k[4], k[2], k[5], model, tuple(d))


# Hello.config.panorama (SPEC.md section 4, "hello: the panorama light"): optional.
LIGHT_SOURCES = ("rgbd", "panorama")
_IDENTITY_3X3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class PanoramaConfig:
    """How a session lights with the Frames' 360-degree panoramas.

    operator: the inverse tone mapping operator (the server's names, pipeline/inverse_tone.py;
    None: the server's default). light_source: which light renders the virtual objects when
    a frame has both RGB-D and a panorama, "rgbd" (the estimate) or "panorama".
    panorama_from_world: 3 x 3 rotation, row-major, d_panorama = R d_world (directions); the
    panorama's light in the world frame is its SH rotated by R^T. Identity by default.
    """

    operator: str | None = None
    light_source: str = "rgbd"
    panorama_from_world: tuple[float, ...] = _IDENTITY_3X3

    def _pack(self, name: str) -> dict:
        rotation = float_list(self.panorama_from_world, f"{name}.panorama_from_world")
        rotation = np.asarray(rotation, dtype=np.float64).reshape(-1).tolist()
        return {
            "operator": self.operator,
            "light_source": self.light_source,
            "panorama_from_world": rotation,
        }

    @classmethod
    def _unpack(cls, m: FieldReader) -> PanoramaConfig:
        operator = m.str("operator", 64, NAME_RE, nullable=True)
        light_source = m.str("light_source", 32, choices=LIGHT_SOURCES)
        values = m.floats("panorama_from_world", 9)
        rows = [values[0:3] + [0.0], values[3:6] + [0.0], values[6:9] + [0.0], [0.0, 0.0, 0.0, 1.0]]
        try:
            check_rigid(rows, m.f("panorama_from_world"), RIGID_TOLERANCE)
        except CheckError:
            raise ProtocolError(
                "bad_field",
                f"not a rotation (orthonormal rows, determinant +1, each within "
                f"{RIGID_TOLERANCE:g}): {values}",
                m.f("panorama_from_world"),
            ) from None
        m.done()
        return cls(operator, light_source, tuple(values))


@dataclass
class SessionConfig:
    session: str  # session name, [A-Za-z0-9_.-]{1,64}
    client_name: str = ""
    role: str = "capture"  # "capture" | "display"
    calibration: CameraCalibration | None = None  # required for role capture
    depth_scale: float = 1000.0  # depth units per metre on the wire (TUM: 5000)
    preset: str = "full"
    overrides: dict[str, bool | int | float | str] = dataclasses.field(default_factory=dict)
    virtual_scene: str | None = None
    mode: str = "live"  # "live" | "lossless"
    want_composite: bool = False
    scene: SceneSpec | None = None  # the virtual scene itself (not with virtual_scene)
    # the panorama light (optional key); with calibration None: a panorama-only session
    panorama: PanoramaConfig | None = None
    # engine layouts (EXPORT_LAYOUTS) every Result of the session carries (optional key,
    # capture Hellos only); () = none
    exports: tuple[str, ...] = ()
    # a reflection probe in every Result (optional key, capture Hellos only; SPEC.md "hello:
    # the reflection probe"); None = none
    probe: ProbeRequest | None = None
    # the session token (optional key, SPEC.md "session tokens"): a display's proof that it
    # may watch the session; a capture client's token for a new session or proof for resuming
    token: str | None = None

    def _pack(self, parts: list) -> dict:
        out = {
            "session": self.session,
            "client_name": self.client_name,
            "role": self.role,
            "calibration": None if self.calibration is None else self.calibration._pack(),
            "depth_scale": to_plain(self.depth_scale),
            "preset": self.preset,
            "overrides": to_plain(self.overrides),
            "virtual_scene": self.virtual_scene,
            "mode": self.mode,
            "want_composite": to_plain(self.want_composite),
        }
        if self.scene is not None:  # optional key: absent when there is no scene
            out["scene"] = self.scene._pack(parts, "hello.config.scene")
        if self.panorama is not None:  # optional key: absent when the session has none
            out["panorama"] = self.panorama._pack("hello.config.panorama")
        if self.exports:  # optional key: absent when the session asks for no layout
            out["exports"] = list(read_export_names(list(self.exports), "hello.config.exports"))
            _exports_role(self.role, "hello.config.exports")
        if self.probe is not None:  # optional key: absent when the session asks for none
            out["probe"] = self.probe._pack("hello.config.probe")
            _probe_role(self.role, "hello.config.probe")
        if self.token is not None:  # optional key: absent when the client has no token
            out["token"] = read_token(self.token, "hello.config.token")
        return out

    @classmethod
    def _unpack(cls, c: FieldReader, images: ImageParts) -> SessionConfig:
        session = c.str("session", 64, NAME_RE)
        client_name = c.str("client_name", 128)
        role = c.str("role", choices=ROLES)
        cal = c.map("calibration", nullable=True)
        calibration = None if cal is None else CameraCalibration._unpack(cal)
        panorama = None
        if "panorama" in c.d:  # optional key (SPEC.md section 2): absent = nil
            pm = c.map("panorama", nullable=True)
            panorama = None if pm is None else PanoramaConfig._unpack(pm)
        if role == "capture" and calibration is None and panorama is None:
            raise ProtocolError(
                "bad_field",
                "required for role capture (nil only for a "
                "panorama-only session: give config.panorama)",
                c.f("calibration"),
            )
        depth_scale = c.float("depth_scale", 1e-6, 1e9)
        preset = c.str("preset", 64, NAME_RE)
        overrides = _read_overrides(c.raw("overrides"), c.f("overrides"))
        virtual_scene = c.str("virtual_scene", 1024, nullable=True)
        mode = c.str("mode", choices=MODES)
        want_composite = c.bool("want_composite")
        scene = None
        if "scene" in c.d:  # the one optional key (SPEC.md section 2): absent = nil
            sm = c.map("scene", nullable=True)
            scene = None if sm is None else SceneSpec._unpack(sm, images)
        if scene is not None and virtual_scene is not None:
            raise ProtocolError(
                "bad_field",
                f"give virtual_scene (a built-in scene name, here "
                f"{virtual_scene[:64]!r}) or scene (the scene itself), not both",
                c.f("scene"),
            )
        exports: tuple[str, ...] = ()
        if "exports" in c.d:  # optional key: absent = nil = none
            exports = read_export_names(c.raw("exports", nullable=True), c.f("exports"))
            if exports:
                _exports_role(role, c.f("exports"))
        probe = None
        if "probe" in c.d:  # optional key: absent = nil = none
            pm = c.map("probe", nullable=True)
            probe = None if pm is None else ProbeRequest._unpack(pm)
            if probe is not None:
                _probe_role(role, c.f("probe"))
        token = None
        if "token" in c.d:  # optional key (SPEC.md section 2): absent = nil
            raw = c.raw("token", nullable=True)
            token = None if raw is None else read_token(raw, c.f("token"))
        c.done()
        return cls(
            session,
            client_name,
            role,
            calibration,
            depth_scale,
            preset,
            overrides,
            virtual_scene,
            mode,
            want_composite,
            scene,
            panorama,
            exports,
            probe,
            token,
        )


def _exports_role(role: str, name: str) -> None:
    """The layouts are the session's: the capture client's Hello chooses them."""
    if role != "capture":
        raise ProtocolError(
            "bad_field",
            "only a capture Hello chooses the session's engine "
            "layouts (a display receives them in every Result, or computes "
            "its own: arlight display --export)",
            name,
        )


def _probe_role(role: str, name: str) -> None:
    """The probe is the session's: the capture client's Hello asks for it."""
    if role != "capture":
        raise ProtocolError(
            "bad_field",
            "only a capture Hello asks for the session's reflection probe (a display "
            "receives it in every Result)",
            name,
        )


def _read_overrides(v: Any, name: str) -> dict[str, bool | int | float | str]:
    """Config overrides: <= 256 entries, name -> bool, int, finite float or str <= 4096."""
    if type(v) is not dict:
        raise ProtocolError("bad_field", f"expected a map, got {type_name(v)}", name)
    if len(v) > 256:
        raise ProtocolError("bad_field", f"{len(v)} entries, at most 256", name)
    out: dict[str, bool | int | float | str] = {}
    for k, x in v.items():
        key = read_str(k, f"{name} key", 64, KEY_RE)
        if type(x) not in (bool, int, float, str):
            raise ProtocolError(
                "bad_field",
                f"expected bool, int, float or string, got {type_name(x)}",
                f"{name}.{key}",
            )
        if type(x) is float and not math.isfinite(x):
            raise ProtocolError("bad_field", f"{x} is not finite", f"{name}.{key}")
        if type(x) is str and len(x) > 4096:
            raise ProtocolError("bad_field", "string longer than 4096 characters", f"{name}.{key}")
        out[key] = x
    return out


@dataclass
class Hello:
    TYPE: ClassVar[str] = "hello"
    protocol_version: int
    config: SessionConfig

    def _pack(self, parts: list) -> dict:
        return {"config": self.config._pack(parts)}

    @classmethod
    def _unpack(cls, h: FieldReader, v: int, images: ImageParts) -> Hello:
        return cls(v, SessionConfig._unpack(h.map("config"), images))
