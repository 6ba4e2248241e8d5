"""Options and helpers of the service's clients (stream, record, display): the source, the
session's settings, keys and tokens, Foxglove."""

from __future__ import annotations

import argparse
import sys

from arlight.cli.common import (
    DEPTH_ENCODINGS,
    PRESETS,
    BadInput,
    add_scene_options,
    check_address,
    config_override,
    image_size,
    jpeg_quality,
    load_scene,
    port,
    positive_float,
    positive_int,
)
from arlight.protocols import (
    COLOR_CODECS,
    DEFAULT_COLOR_CODEC,
    DEFAULT_DEPTH_CODEC,
    DEFAULT_JPEG_QUALITY,
    DEPTH_CODECS,
    TOKEN_RE,
    PanoramaConfig,
)
from arlight.protocols.curve import ClientKeys
from arlight.protocols.probe import PROBE_SIZE_MAX, PROBE_SIZE_MIN, ProbeRequest
from arlight.server.security import is_loopback, read_token_file


def add_source_options(p: argparse.ArgumentParser) -> None:
    """SOURCE and the session's settings, shared by stream and record."""
    p.add_argument(
        "source",
        metavar="SOURCE",
        help="'synthetic' (the built-in scene), a TUM / Open3D-Redwood / 7-Scenes "
        "folder, a recording FILE.mcap (sent exactly as recorded), or a "
        "camera: depthai[:DEVICE_ID] (Luxonis OAK), openni2[:URI] or FILE.oni "
        "(OpenNI2 device or recording), realsense[:SERIAL] (Intel RealSense); "
        "cameras need their extra: pip install 'arlight[depthai]' etc.",
    )
    p.add_argument(
        "--session",
        metavar="NAME",
        help="session name, [A-Za-z0-9_.-]{1,64} "
        "(default: the source's name plus 4 random hex digits; a recording: its own)",
    )
    p.add_argument(
        "--mode",
        choices=("live", "lossless"),
        help="live: latest frame wins, drops counted (default); lossless: every "
        "frame processed once, in order (for recorded streams)",
    )
    p.add_argument(
        "--color-codec",
        choices=COLOR_CODECS,
        default=DEFAULT_COLOR_CODEC,
        help=f"colour codec (default {DEFAULT_COLOR_CODEC}; png/raw are lossless)",
    )
    p.add_argument(
        "--depth-codec",
        choices=DEPTH_CODECS,
        default=DEFAULT_DEPTH_CODEC,
        help=f"depth codec, all lossless (default {DEFAULT_DEPTH_CODEC})",
    )
    p.add_argument(
        "--jpeg-quality",
        type=jpeg_quality,
        default=DEFAULT_JPEG_QUALITY,
        metavar="Q",
        help=f"JPEG quality 1..100 (default {DEFAULT_JPEG_QUALITY})",
    )
    p.add_argument(
        "--preset",
        choices=PRESETS,
        help="the session's pipeline preset (default full; a recording: its own)",
    )
    p.add_argument(
        "--set",
        action="append",
        type=config_override,
        metavar="KEY=VALUE",
        help="override a pipeline Config field for the session",
    )
    p.add_argument(
        "--composite",
        action="store_true",
        help="ask the server for the composited frame in every Result (for "
        "display clients): the input colour image with the --scene objects "
        "rendered in under the estimated light (their shading, shadows "
        "and one bounce of indirect light); without --scene, the input "
        "colour image unchanged",
    )
    p.add_argument(
        "--poses",
        choices=("groundtruth", "track"),
        default="track",
        help="'groundtruth': send the data set's camera poses (tracking is then "
        "skipped); 'track' (default): the server tracks the camera",
    )
    p.add_argument(
        "--max-frames",
        type=positive_int,
        metavar="N",
        help="only the first N frames "
        "(with --loop: N frames in total); synthetic: the first N of its 12-frame orbit "
        "(of an N-frame orbit where N is more)",
    )
    p.add_argument(
        "--depth-encoding",
        choices=DEPTH_ENCODINGS,
        help="depth encoding of a data set (default: from its layout)",
    )
    p.add_argument(
        "--size",
        type=image_size,
        default=(640, 480),
        metavar="WxH",
        help="image size of the synthetic scene or of a camera (default 640x480)",
    )
    p.add_argument(
        "--fps",
        type=positive_float,
        default=30.0,
        metavar="F",
        help="a camera's frame rate in Hz (default 30)",
    )
    p.add_argument(
        "--timestamps",
        choices=("capture", "source"),
        help="frame timestamps: 'capture' = time.time() when sent (end-to-end "
        "latency measurable; default in live mode), 'source' = the data set's "
        "(default in lossless mode); recordings keep theirs",
    )
    add_scene_options(p)


PROBE_POINT_MAX_M = 1.0e4  # |coordinate| the protocol takes (protocols/probe.py)


def probe_size(text: str) -> int:
    """--probe SIZE: texels a face, a power of two in 32..256."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not PROBE_SIZE_MIN <= value <= PROBE_SIZE_MAX or value & (value - 1):
        raise argparse.ArgumentTypeError(
            f"expected texels a face, a power of two in {PROBE_SIZE_MIN}..{PROBE_SIZE_MAX} "
            f"(32, 64, 128, 256), got {text!r}"
        )
    return value


def probe_point(text: str) -> tuple[float, float, float]:
    """--probe-at X,Y,Z: metres, world frame, each finite and within +-1e4."""
    try:
        x, y, z = (float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected X,Y,Z in metres (world frame), got {text!r}"
        ) from None
    if not all(abs(v) <= PROBE_POINT_MAX_M for v in (x, y, z)):  # NaN fails too
        raise argparse.ArgumentTypeError(
            f"expected finite X,Y,Z within +-{PROBE_POINT_MAX_M:g} m, got {text!r}"
        )
    return (x, y, z)


def add_probe_options(p: argparse.ArgumentParser) -> None:
    """--probe, --probe-at, --probe-mips, --probe-out, --probe-layout (arlight stream)."""
    from arlight.cli.probe_files import PROBE_LAYOUT_HELP, PROBE_LAYOUTS

    p.add_argument(
        "--probe",
        type=probe_size,
        metavar="SIZE",
        help="ask the server for a reflection probe in every Result (a cube map of the "
        "light arriving at one point: the room's surfaces and the distant light), SIZE "
        "texels a face, a power of two in 32..256; at --probe-at or the --scene objects' "
        "centre",
    )
    p.add_argument(
        "--probe-at",
        type=probe_point,
        metavar="X,Y,Z",
        help="with --probe: the probe's point, world frame, metres (default: the centre of "
        "the --scene objects)",
    )
    p.add_argument(
        "--probe-mips",
        action="store_true",
        help="with --probe: every GGX-prefiltered mip level down to 4 texels a face "
        "(default: level 0 only, the radiance itself)",
    )
    p.add_argument(
        "--probe-out",
        metavar="DIR",
        help="with --probe: write each Result's probe as OpenEXR cube maps "
        "DIR/NNNNNN_<face>_m<level>.exr (NNNNNN the frame's seq; linear HDR, half float) "
        "and DIR/NNNNNN.json (point, roughness per level, diagnostics), as `arlight "
        "estimate --probe-out`",
    )
    p.add_argument(
        "--probe-layout",
        choices=PROBE_LAYOUTS,
        default="world",
        help=PROBE_LAYOUT_HELP,
    )


def probe_request(args: argparse.Namespace, recorded, has_scene: bool) -> ProbeRequest | None:
    """The Hello's config.probe from --probe, --probe-at and --probe-mips (else what a
    recording asked for), or None; BadInput naming the flag for a probe option without a
    probe and for a probe with no point (no --probe-at and no --scene)."""
    size = getattr(args, "probe", None)
    at = getattr(args, "probe_at", None)
    mips = getattr(args, "probe_mips", False)
    out = getattr(args, "probe_out", None)
    if getattr(args, "probe_layout", "world") != "world" and not out:
        raise BadInput("--probe-layout says how --probe-out writes: give --probe-out DIR")
    if size is not None:
        request: ProbeRequest | None = ProbeRequest(size, at, mips)
    else:
        request = None if recorded is None else recorded.probe
        given = [flag for flag, v in (("--probe-at", at), ("--probe-mips", mips)) if v]
        if given:
            raise BadInput(f"{given[0]} shapes the probe --probe SIZE asks for: give --probe")
        if out and request is None:
            raise BadInput("--probe-out writes the probe --probe SIZE asks for: give --probe")
    if request is not None and request.point_world is None and not has_scene:
        raise BadInput(
            "--probe needs a point: give --probe-at X,Y,Z (world, metres) or a --scene "
            "(the probe then sits at its objects' centre)"
        )
    return request


def add_key_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--server-key",
        metavar="DIR/server.key",
        help="the server's public CURVE key (for a server run with --keys DIR)",
    )
    p.add_argument(
        "--client-key",
        metavar="DIR/NAME.key_secret",
        help="this client's CURVE key pair; its public half must be in the "
        "server's DIR/authorized/",
    )


def add_reconnect_timeout(p: argparse.ArgumentParser) -> None:
    """--reconnect-timeout, shared by the two clients (stream, display)."""
    p.add_argument(
        "--reconnect-timeout",
        type=positive_float,
        default=30.0,
        metavar="S",
        help="give up after S seconds without a server (default 30)",
    )


def add_foxglove_options(parser, what: str) -> None:
    """--foxglove, --port, --foxglove-host (stream and display)."""
    parser.add_argument(
        "--foxglove",
        action="store_true",
        help=f"serve {what} live over Foxglove's WebSocket protocol (open "
        "ws://HOST:PORT in the Foxglove app)",
    )
    parser.add_argument(
        "--port",
        type=port,
        metavar="P",
        help="with --foxglove: its port (default 8765; 0 = any free port)",
    )
    parser.add_argument(
        "--foxglove-host",
        default="127.0.0.1",
        metavar="HOST",
        help="with --foxglove: the address to bind (default 127.0.0.1; 0.0.0.0 for other machines)",
    )


def foxglove_address(args: argparse.Namespace) -> tuple[str, int] | None:
    """(host, port) of --foxglove, or None; --port without --foxglove is refused."""
    if args.port is not None and not args.foxglove:
        raise BadInput("--port is the port of --foxglove: give --foxglove too")
    if not args.foxglove:
        return None
    address = (args.foxglove_host, 8765 if args.port is None else args.port)
    warn_if_exposed("--foxglove-host", *address)
    return address


def warn_if_exposed(flag: str, host: str, port: int) -> None:
    """A viewer served beyond loopback has neither keys nor token: say so
    (docs/guides/security.md)."""
    if not is_loopback(f"tcp://{host}:{port}"):
        print(
            f"arlight: warning: {flag} {host}: what it shows (composite, light; a stream: "
            f"the camera) is served on port {port} to anyone who can reach this machine, "
            f"without keys or token (docs/guides/security.md)",
            file=sys.stderr,
            flush=True,
        )


def client_keys(args: argparse.Namespace) -> ClientKeys | None:
    """CURVE keys from --server-key and --client-key (both or neither), or None."""
    server_key = getattr(args, "server_key", None)
    client_key = getattr(args, "client_key", None)
    if server_key is None and client_key is None:
        return None
    if server_key is None or client_key is None:
        raise BadInput(
            "give both --server-key DIR/server.key and --client-key "
            "DIR/NAME.key_secret (made by `arlight keys generate DIR`), or neither"
        )
    return ClientKeys.load(server_key, client_key)


def token_of(args: argparse.Namespace) -> str | None:
    """The session token from --token or --token-file (not both), or None."""
    token = getattr(args, "token", None)
    token_file = getattr(args, "token_file", None)
    if token and token_file:
        raise BadInput("give --token or --token-file, not both")
    if token_file:
        return read_token_file(token_file, "--token-file")
    if token is not None and not TOKEN_RE.fullmatch(token):
        raise BadInput(
            "--token expects 16..128 characters from A-Z a-z 0-9 _ - (as "
            "`arlight stream` prints it)"
        )
    return token


def panorama_config(args: argparse.Namespace) -> PanoramaConfig | None:
    """The Hello's config.panorama from --panorama-operator, --light-source and
    --panorama-from-world (None when none is given: the server's defaults)."""
    operator = getattr(args, "panorama_operator", None)
    light_source = getattr(args, "light_source", None)
    rotation = getattr(args, "panorama_from_world", None)
    if operator is None and light_source is None and rotation is None:
        return None
    return PanoramaConfig(
        operator, light_source or "rgbd", rotation or PanoramaConfig().panorama_from_world
    )


def stream_options(args: argparse.Namespace, source):
    """The capture client's StreamOptions: the flags, else what a recording recorded."""
    from arlight.client.capture import StreamOptions

    recorded = source.recorded_config
    mode = args.mode or (recorded.mode if recorded else "live")
    preset = args.preset or (recorded.preset if recorded else "full")
    overrides = dict(recorded.overrides) if recorded and not args.set else {}
    for key, value in args.set or []:
        overrides[key] = value
    composite = args.composite or bool(recorded and recorded.want_composite)
    # the demo by name: the server's built-in one, anchored at fractions of the image
    # (any size); a scene file travels whole
    virtual_scene = "demo" if getattr(args, "scene", None) == "demo" else None
    scene = None if virtual_scene else load_scene(args)
    return StreamOptions(
        server=check_address(getattr(args, "server", None) or "tcp://127.0.0.1:5555", "--server"),
        session=args.session or (recorded.session if recorded else None),
        client_name=f"arlight-{args.command}",
        mode=mode,
        rate=getattr(args, "rate", "max"),
        loop=getattr(args, "loop", False),
        color_codec=args.color_codec,
        depth_codec=args.depth_codec,
        jpeg_quality=args.jpeg_quality,
        preset=preset,
        overrides=overrides,
        want_composite=composite,
        timestamps=args.timestamps,
        max_frames=args.max_frames if getattr(args, "loop", False) else None,
        reconnect_timeout_s=getattr(args, "reconnect_timeout", 30.0),
        scene=scene,
        virtual_scene=virtual_scene,
        panorama=panorama_config(args),
        exports=tuple(getattr(args, "export", None) or (recorded.exports if recorded else ())),
        probe=probe_request(args, recorded, bool(virtual_scene or scene)),
        token=token_of(args),
        keys=client_keys(args),
    )


def open_stream_source(args: argparse.Namespace):
    """The capture source of SOURCE (with --panorama paired in, or panorama-only)."""
    from arlight.sources.panorama_stream import (
        is_panorama_input,
        panorama_only_source,
        with_panorama,
    )

    if is_panorama_input(args.source):  # a 360-degree video or image: panorama-only frames
        return panorama_only_source(args.source, max_frames=args.max_frames)
    if getattr(args, "panorama", None):
        return with_panorama(_open_rgbd_source(args), args.panorama)
    return _open_rgbd_source(args)


def _open_rgbd_source(args: argparse.Namespace):
    from arlight.sources.camera import parse_camera_spec
    from arlight.sources.source import open_source

    if getattr(args, "loop", False) and parse_camera_spec(args.source) is not None:
        raise BadInput(
            f"--loop does not apply to a camera (SOURCE {args.source}): it streams "
            "until --max-frames N or Ctrl-C"
        )
    # its notes (defaults chosen for the data) are logged as warnings
    return open_source(
        args.source,
        use_poses=args.poses == "groundtruth",
        max_frames=args.max_frames,
        depth_encoding=args.depth_encoding,
        synthetic_size=args.size,
        camera_fps=args.fps,
    )
