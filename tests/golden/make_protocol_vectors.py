"""Regenerate the golden vectors of the wire protocol: tests/golden/protocol_v2/*.bin.

Each file is a container (SPEC.md, "Container") holding one encoded message built by
vectors() below from fixed, hand-made values (8 x 6 images). tests/test_protocols_golden.py checks
that encode() still reproduces every file byte for byte (JPEG excepted: its bytes depend on
the libjpeg build, so the JPEG vector is pinned by decoding the stored file) and that
decode() of each stored file gives the message below.

The refused vectors (refused() below, tests/golden/protocol_v2/refused/*.bin and
expected.json) are messages a decoder must refuse, each with the code and field SPEC.md
section 9 names: hand-edited headers of the vectors above.

Run only after a deliberate format change (and bump PROTOCOL_VERSION if old peers can no
longer read the new bytes):

    .venv/bin/python tests/golden/make_protocol_vectors.py
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import msgpack
import numpy as np

from arlight.core.contracts import Confidence
from arlight.pipeline.sh import intensity_along
from arlight.protocols import (
    PROTOCOL_VERSION,
    Bye,
    ByeKind,
    CameraCalibration,
    Credit,
    Error,
    ErrorField,
    Frame,
    Heartbeat,
    Hello,
    PanoramaConfig,
    Result,
    SceneAnchorSpec,
    SceneObjectSpec,
    SceneSpec,
    SessionConfig,
    Welcome,
    encode,
    write_container,
)
from arlight.protocols.probe import ProbeCube, ProbeRequest

OUT = Path(__file__).resolve().parent / f"protocol_v{PROTOCOL_VERSION}"
JPEG_VECTORS = ("frame_jpeg_zstd",)  # pinned by decoding, not by re-encoding
GOLDEN_TOKEN = "golden-token_0123456789"  # 23 characters of TOKEN_RE; not a secret


def color_8x6() -> np.ndarray:
    """(6, 8, 3) uint8 RGB: a smooth gradient (JPEG-friendly), one saturated pixel."""
    y, x = np.mgrid[0:6, 0:8]
    rgb = np.stack([x * 30 + 10, y * 40 + 20, 200 - x * 10 - y * 10], axis=-1).astype(np.uint8)
    rgb[0, 0] = (255, 255, 255)
    return rgb


def depth_8x6() -> np.ndarray:
    """(6, 8) uint16 millimetres: a slanted plane with holes (0) and one 65535 pixel."""
    y, x = np.mgrid[0:6, 0:8]
    d = (1000 + 37 * x + 101 * y).astype(np.uint16)
    d[0, 0:3] = 0  # zero run at the start
    d[2, 5] = 0
    d[3, :] = 0  # a whole missing row
    d[5, 7] = 65535  # saturated / invalid marker of some sensors
    return d


def panorama_16x8() -> np.ndarray:
    y, x = np.mgrid[0:8, 0:16]
    return np.stack([x * 16, y * 32, (x + y) * 8], axis=-1).astype(np.uint8)


def pose() -> np.ndarray:
    c, s = np.cos(0.5), np.sin(0.5)
    return np.array(
        [[c, 0.0, s, 0.25], [0.0, 1.0, 0.0, -0.5], [-s, 0.0, c, 1.5], [0.0, 0.0, 0.0, 1.0]]
    )


def scene() -> SceneSpec:
    """A tetrahedron at a scaled pose and one anchored triangle (exact binary fractions)."""
    tetra = SceneObjectSpec(
        "tetra",
        np.array([[0, 0, 0], [0.25, 0, 0], [0, 0.25, 0], [0, 0, 0.25]], np.float32),
        np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.uint32),
        np.array([[-0.5, -0.5, -0.5], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32),
        world_from_object=np.array(
            [[0, 0, 2, 0.5], [0, 2, 0, -0.25], [-2, 0, 0, 1.5], [0, 0, 0, 1]], np.float64
        ),
        albedo=(0.75, 0.5, 0.25),
        roughness=0.5,
        metalness=0.0,
        mirror=False,
    )
    card = SceneObjectSpec(
        "card",
        np.array([[0, 0, 0], [0.125, 0, 0], [0, 0.125, 0]], np.float32),
        np.array([[0, 1, 2]], np.uint32),
        np.array([[0, 0, 1]] * 3, np.float32),
        anchor=SceneAnchorSpec((4.5, 3.0), 30.0),
        albedo=(1.0, 1.0, 1.0),
        roughness=0.0,
        metalness=1.0,
        mirror=True,
    )
    return SceneSpec((tetra, card))


def exports() -> dict:
    """One of each engine layout (SPEC.md, "result: engine layouts"): shapes, not physics."""
    c = [0.25 - 0.03125 * i for i in range(9)]
    return {
        "arcore": [x * k for x in c for k in (1.0, 0.5, 0.25)],
        "gltf": {
            "intensity": 1.0,
            "rotation": [0.0, 0.0, 0.0, 1.0],
            "irradianceCoefficients": [[x, x * 0.5, x * 0.25] for x in c],
        },
        "unity": [c, [x * 0.5 for x in c], [x * 0.25 for x in c]],
        "filament": "( 0.250000000000000,  0.125000000000000,  0.062500000000000); // L00\n",
        "main_light": {"direction": [0.0, 1.0, 0.0], "intensity": [1.5, 1.25, 1.0]},
    }


def panorama_light() -> dict:
    """The light of a panorama-only frame as SPEC.md section 4 defines its parts (made-up
    coefficients, 4 bands; `panorama_from_world` the identity, so world = panorama frame):
    panorama_sh the Rec. 709 luminance of panorama_sh_rgb, the direction normalize(c[3],
    c[1], c[2]) of it, the intensity Sloan's extraction along it (rounded: the vector must not
    depend on the last bits of the SH basis code)."""
    base = [0.5 - 0.03125 * i for i in range(16)]
    rgb = [[x * 2.0 for x in base], base, [x * 0.5 for x in base]]
    lum = [0.2126 * r + 0.7152 * g + 0.0722 * b for r, g, b in zip(*rgb, strict=True)]
    norm = math.sqrt(lum[3] ** 2 + lum[1] ** 2 + lum[2] ** 2)
    direction = [lum[3] / norm, lum[1] / norm, lum[2] / norm]
    intensity = round(intensity_along(np.array(lum), np.array(direction)), 9)
    return {"sh": lum, "sh_rgb": rgb, "direction": direction, "intensity": intensity}


def compact_source() -> dict:
    """One compact source (SPEC.md section 4, "result: compact sources") seen from pose():
    a sun 53 degrees up the world's -y towards +z; direction_camera = R^T direction_world,
    written out (R a turn of 0.5 rad about y); intensity the Rec. 709 luminance of rgb
    (rounded to 9 decimals, as panorama_light())."""
    c, s = math.cos(0.5), math.sin(0.5)
    x, y, z = 0.0, -0.8, 0.6
    rgb = [3.5, 2.875, 2.25]
    return {
        "direction_world": [x, y, z],
        "direction_camera": [c * x - s * z, y, s * x + c * z],
        "intensity": round(0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2], 9),
        "rgb": rgb,
        "angular_radius_deg": 0.27,
        "share": 0.625,
    }


def probe_cube() -> ProbeCube:
    """A reflection probe (SPEC.md section 4, "result: the reflection probe") of 32 texels a
    face and two levels whose texels say where they are: at column i, row j of face f of an
    n-texel level, R = (i + 1) / n, G = (j + 1) / n, B = f / 8 (exact in RGB9E5)."""
    levels = []
    for n in (32, 16):
        j, i = np.mgrid[0:n, 0:n]
        faces = [
            np.stack([(i + 1) / n, (j + 1) / n, np.full((n, n), f / 8)], axis=-1) for f in range(6)
        ]
        levels.append(np.stack(faces).astype(np.float32))
    return ProbeCube([0.25, -0.5, 1.5], levels, [0.0, 1.0 / 3.0])


def vectors() -> dict[str, object]:
    cal = CameraCalibration(8, 6, 5.25, 5.5, 3.5, 2.5, "plumb_bob", (0.1, -0.05, 0.0, 0.0, 0.01))
    rgb, depth = color_8x6(), depth_8x6()
    sh = [0.5 - 0.03125 * i for i in range(16)]
    pano = panorama_light()
    sun = compact_source()
    sun_gl = [sun["direction_camera"][0], -sun["direction_camera"][1], -sun["direction_camera"][2]]
    return {
        "hello": Hello(
            PROTOCOL_VERSION,
            SessionConfig(
                session="golden-1",
                client_name="golden vectors",
                role="capture",
                calibration=cal,
                depth_scale=5000.0,
                preset="fast",
                overrides={"sh_bands": 3, "sigma": 0.5, "visibility": False, "note": "x"},
                virtual_scene="bunny.ply",
                mode="lossless",
                want_composite=True,
            ),
        ),
        "hello_scene": Hello(
            PROTOCOL_VERSION,
            SessionConfig(
                session="golden-scene",
                role="capture",
                calibration=cal,
                depth_scale=1000.0,
                want_composite=True,
                scene=scene(),
            ),
        ),
        "hello_panorama": Hello(
            PROTOCOL_VERSION,
            SessionConfig(
                session="golden-pano",
                role="capture",
                calibration=cal,
                depth_scale=1000.0,
                panorama=PanoramaConfig(
                    "paper", "panorama", (0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0)
                ),
            ),
        ),
        "hello_panorama_only": Hello(
            PROTOCOL_VERSION,
            SessionConfig(
                session="golden-pano-only",
                role="capture",
                mode="lossless",
                panorama=PanoramaConfig(),
            ),
        ),
        "hello_exports": Hello(
            PROTOCOL_VERSION,
            SessionConfig(
                session="golden-exports",
                role="capture",
                calibration=cal,
                depth_scale=1000.0,
                exports=("arcore", "gltf", "unity", "filament", "main_light"),
            ),
        ),
        "hello_display": Hello(PROTOCOL_VERSION, SessionConfig(session="golden-1", role="display")),
        "welcome": Welcome(PROTOCOL_VERSION, "golden-1", 8, 1.0, "arlight"),
        "frame_raw_raw": Frame(7, 1234.5, rgb, depth, pose(), None, "raw", "raw"),
        "frame_png_zstd": Frame(8, 1234.75, rgb, depth, None, panorama_16x8(), "png", "zstd"),
        "frame_panorama_only": Frame(12, 1236.0, None, None, None, panorama_16x8(), "png"),
        "frame_png_png": Frame(9, 1235.0, rgb, depth, pose(), None, "png", "png"),
        "frame_raw_rvl": Frame(10, 1235.25, rgb, depth, None, None, "raw", "rvl"),
        "frame_jpeg_zstd": Frame(11, 1235.5, rgb, depth, pose(), None, "jpeg", "zstd", 95),
        "result": Result(
            seq=7,
            timestamp=1234.5,
            sh=sh,
            sh_camera=[-x for x in sh],
            sh_rgb=[sh, [x * 0.5 for x in sh], [x * 0.25 for x in sh]],
            dominant_direction_camera=[0.0, -0.6, 0.8],
            dominant_direction_world=[0.6, -0.8, 0.0],
            intensity=2.5,
            confidence={"samples": 1200, "condition": 12.5, "bands": 4, "unconstrained": []},
            pose=pose().tolist(),
            timings_ms={"reconstruct": 3.5, "light_estimation": 0.75},
            diagnostics={
                "tracking": {"ok": True, "reason": ""},
                "residuals": [0.5, 0.25],
                "bands_estimated": 3,
                "note": "golden",
            },
            frames_received=8,
            frames_processed=7,
            frames_dropped=1,
            server_receive_time=100.25,
            server_finish_time=100.5,
            composite=rgb,
            composite_codec="png",
        ),
        # the Result of frame_panorama_only in the session of hello_panorama_only (identity
        # panorama_from_world, operator nil: boost), as SPEC.md "result: the panorama light"
        # defines a panorama-only Result (made-up SH: panorama_light())
        "result_panorama": Result(
            seq=12,
            timestamp=1236.0,
            sh=pano["sh"],
            sh_camera=pano["sh"],
            sh_rgb=pano["sh_rgb"],
            dominant_direction_camera=pano["direction"],
            dominant_direction_world=pano["direction"],
            intensity=pano["intensity"],
            confidence=Confidence(
                samples=128, condition_number=1.0, bands_estimated=4, value=1.0
            ).to_dict(),
            pose=np.eye(4).tolist(),
            timings_ms={
                "PanoramaInverseTone": 0.5,
                "PanoramaDownsample": 0.25,
                "PanoramaSH": 0.25,
                "PanoramaDiffuse": 0.125,
            },
            diagnostics={"light_source": "panorama", "panorama_operator": "boost"},
            frames_received=1,
            frames_processed=1,
            frames_dropped=0,
            server_receive_time=6.0,
            server_finish_time=6.25,
            panorama_sh=pano["sh"],
            panorama_sh_rgb=pano["sh_rgb"],
            panorama_dominant_direction=pano["direction"],
        ),
        # no direction (SPEC.md "result: directions"): a first frame without usable depth
        "result_no_direction": Result(
            seq=20,
            timestamp=1240.0,
            sh=[0.0] * 16,
            sh_camera=[0.0] * 16,
            dominant_direction_camera=[0.0, 0.0, 0.0],
            dominant_direction_world=[0.0, 0.0, 0.0],
            intensity=0.0,
            confidence=Confidence(reason="no valid depth").to_dict(),
            pose=np.eye(4).tolist(),
            timings_ms={"LightEst": 0.0},
            diagnostics={"tracking": {"ok": False, "reason": "no valid depth"}},
            frames_received=1,
            frames_processed=1,
            frames_dropped=0,
            server_receive_time=8.0,
            server_finish_time=8.25,
        ),
        "result_exports": Result(
            seq=13,
            timestamp=1236.5,
            sh=sh,
            sh_camera=sh,
            dominant_direction_camera=[0.0, 1.0, 0.0],
            dominant_direction_world=[0.0, 1.0, 0.0],
            intensity=1.0,
            confidence={"value": 0.5},
            pose=np.eye(4).tolist(),
            timings_ms={},
            frames_received=1,
            frames_processed=1,
            frames_dropped=0,
            server_receive_time=7.0,
            server_finish_time=7.25,
            exports=exports(),
        ),
        # one compact source (issue 32): the dominant directions are its own, and the
        # main_light layout is it (its direction in OpenGL camera axes, its rgb)
        "result_compact": Result(
            seq=14,
            timestamp=1237.0,
            sh=sh,
            sh_camera=sh,
            dominant_direction_camera=sun["direction_camera"],
            dominant_direction_world=sun["direction_world"],
            intensity=1.5,
            compact_sources=[sun],
            confidence={"value": 0.75},
            pose=pose().tolist(),
            timings_ms={"LightEst": 12.5},
            diagnostics={
                "compact": {"reason": "1 compact source", "rays": 4096, "kept": 1, "gain": [0.125]}
            },
            frames_received=2,
            frames_processed=2,
            frames_dropped=0,
            server_receive_time=9.0,
            server_finish_time=9.25,
            exports={"main_light": {"direction": sun_gl, "intensity": sun["rgb"]}},
        ),
        "result_no_composite": Result(
            seq=7,
            timestamp=1234.5,
            sh=sh,
            dominant_direction_camera=[0.0, 0.0, 1.0],
            dominant_direction_world=[0.0, 0.0, 1.0],
            intensity=0.0,
            confidence={"condition": float("inf")},
            pose=np.eye(4).tolist(),
            timings_ms={},
            frames_received=1,
            frames_processed=0,
            frames_dropped=1,
            server_receive_time=5.0,
            server_finish_time=5.0,
        ),
        "credit": Credit(4),
        "error": Error(
            "bad_field", "depth is 8 x 6, colour 4 x 3: they must agree", "frame.depth", 12
        ),
        "error_retryable": Error(
            "bad_state", "more than 4 frames unacknowledged", ErrorField.CREDITS, 13, retryable=True
        ),
        "heartbeat": Heartbeat(100.125),
        "bye": Bye("end of recording", ByeKind.END_OF_STREAM),
        "bye_shutdown": Bye("server shutting down", ByeKind.SHUTDOWN),
        # session tokens (issue 14): the optional keys config.token and Welcome token
        "hello_display_token": Hello(
            PROTOCOL_VERSION, SessionConfig(session="golden-1", role="display", token=GOLDEN_TOKEN)
        ),
        "hello_capture_token": Hello(
            PROTOCOL_VERSION,
            SessionConfig(
                session="golden-1",
                role="capture",
                calibration=cal,
                depth_scale=1000.0,
                token=GOLDEN_TOKEN,
            ),
        ),
        # both optional keys at once: pins their order (exports, then token)
        "hello_exports_token": Hello(
            PROTOCOL_VERSION,
            SessionConfig(
                session="golden-1",
                role="capture",
                calibration=cal,
                depth_scale=1000.0,
                exports=("webxr", "main_light"),
                token=GOLDEN_TOKEN,
            ),
        ),
        # the reflection probe (issue 33): Hello config.probe, and a Result carrying one
        "hello_probe": Hello(
            PROTOCOL_VERSION,
            SessionConfig(
                session="golden-1",
                role="capture",
                calibration=cal,
                depth_scale=1000.0,
                probe=ProbeRequest(64, (0.25, -0.5, 1.5), True),
            ),
        ),
        "result_probe": Result(
            seq=15,
            timestamp=1237.5,
            sh=sh,
            sh_camera=sh,
            dominant_direction_camera=[0.0, 1.0, 0.0],
            dominant_direction_world=[0.0, 1.0, 0.0],
            intensity=1.0,
            confidence={"value": 0.5},
            pose=np.eye(4).tolist(),
            timings_ms={"Probe": 20.5},
            diagnostics={"probe": {"size": 32, "levels": 4, "hit_fraction": 0.375}},
            frames_received=3,
            frames_processed=3,
            frames_dropped=0,
            server_receive_time=10.0,
            server_finish_time=10.25,
            probe=probe_cube(),
        ),
        "welcome_token": Welcome(PROTOCOL_VERSION, "golden-1", 8, 1.0, "arlight", GOLDEN_TOKEN),
        "error_unauthorized": Error(
            "unauthorized", "session golden-1 needs its token", "hello.config.token"
        ),
        # `arlight serve --ray` (issue 20): a lost pipeline, retryable
        "error_pipeline_lost": Error(
            "bad_state",
            "the session's pipeline was lost: send it again",
            ErrorField.PIPELINE_LOST,
            14,
            retryable=True,
        ),
    }


# --------------------------------------------------------------------------- refused vectors


class Pairs(list):
    """A msgpack map written from its (key, value) pairs as given, so a key may repeat."""


def pack(v: object) -> bytes:
    """msgpack as encode() writes it (str as str, ints smallest, floats 64), Pairs as a map."""
    packer = msgpack.Packer(use_bin_type=True)
    if isinstance(v, dict):
        v = Pairs(v.items())
    if isinstance(v, Pairs):
        return packer.pack_map_header(len(v)) + b"".join(pack(k) + pack(x) for k, x in v)
    if isinstance(v, list):
        return packer.pack_array_header(len(v)) + b"".join(pack(x) for x in v)
    return packer.pack(v)


def edited(message: object, edit) -> list[bytes]:
    """The parts of `message` with its header replaced by edit(header) (a dict or Pairs)."""
    parts = [bytes(p) for p in encode(message)]
    header = msgpack.unpackb(parts[0], raw=False)
    return [pack(edit(header)), *parts[1:]]


def _set(path: tuple, value: object):
    def edit(header: dict) -> dict:
        d = header
        for key in path[:-1]:
            d = d[key]
        d[path[-1]] = value
        return header

    return edit


def _repeat_session(header: dict) -> dict:
    """config.session twice: a reader keeping the first value sees golden-1, one keeping the
    last golden-2."""
    header["config"] = Pairs([*header["config"].items(), ("session", "golden-2")])
    return header


def refused() -> dict[str, tuple[list[bytes], str, str, str]]:
    """name -> (parts, code, field, the rule): messages every decoder must refuse with that
    code and field (SPEC.md section 9, "Refused vectors")."""
    v = vectors()
    return {
        "hello_repeated_key": (
            edited(v["hello"], _repeat_session),
            "malformed",
            "header",
            "section 2: every key of every map exactly once",
        ),
        "hello_unknown_key": (
            edited(v["hello"], _set(("config", "capabilities"), ["x"])),
            "bad_field",
            "hello.config.capabilities",
            "section 2: a key the message does not define",
        ),
        "hello_exports_empty": (
            edited(v["hello_exports"], _set(("config", "exports"), [])),
            "bad_field",
            "hello.config.exports",
            "section 4: config.exports holds 1..6 names (none: nil or absent)",
        ),
        "heartbeat_v3": (
            edited(v["heartbeat"], _set(("v",), 3)),
            "bad_version",
            "v",
            "section 10: another version",
        ),
        "frame_seq_too_large": (
            edited(v["frame_raw_raw"], _set(("seq",), 2**63)),
            "bad_field",
            "frame.seq",
            "sections 3 and 4: seq is 0..2^63-1",
        ),
        "frame_truncated": (
            [bytes(p) for p in encode(v["frame_png_zstd"])][:-1],
            "malformed",
            "frame.buffers",
            "section 6: buffers disagreeing with the parts",
        ),
        "bye_unknown_kind": (
            edited(v["bye"], _set(("kind",), "goodbye")),
            "bad_field",
            "bye.kind",
            "section 4: kind is end_of_stream, shutdown or leaving",
        ),
        "result_direction_not_unit": (
            edited(v["result"], _set(("dominant_direction_world",), [0.6, -0.8, 0.5])),
            "bad_field",
            "result.dominant_direction_world",
            "section 4: a direction is a unit vector or [0, 0, 0]",
        ),
    }


def main() -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    for name, msg in vectors().items():
        path = OUT / f"{name}.bin"
        path.write_bytes(write_container([encode(msg)]))
        print(f"{path.relative_to(OUT.parents[2])}: {path.stat().st_size} bytes")
    (OUT / "refused").mkdir(exist_ok=True)
    expected = {}
    for name, (parts, code, field, rule) in refused().items():
        path = OUT / "refused" / f"{name}.bin"
        path.write_bytes(write_container([parts]))
        expected[name] = {"code": code, "field": field, "rule": rule}
        print(f"{path.relative_to(OUT.parents[2])}: {path.stat().st_size} bytes")
    (OUT / "refused" / "expected.json").write_text(json.dumps(expected, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
