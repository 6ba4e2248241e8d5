"""What the commands share: the usage error, argument types (each a validator that argparse
calls, raising ArgumentTypeError with what it expected), and small helpers for options that
more than one command has (--set, --scene, --export, output folders)."""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path

EXIT_BAD_INPUT = 2
PRESETS = ("full", "fast", "mobile")
DEPTH_ENCODINGS = ("tum", "mm", "sun", "nyu")
# `--ray ADDRESS` of batch and serve: local, auto, HOST:PORT or ray://HOST:PORT
RAY_ADDRESS = re.compile(r"auto|local|(ray://)?[A-Za-z0-9_.\[\]:-]+:[0-9]{1,5}")
# `--export` names (protocols.EXPORT_LAYOUTS = engine_export.EXPORTERS;
# tests/test_protocols_fields.py checks all three agree), written out so that building the
# help imports neither
LAYOUT_NAMES = "arcore, webxr, gltf, unity, filament, main_light"


class BadInput(ValueError):
    """A usage error found after parsing (exit code 2); the message names the flag."""


# --------------------------------------------------------------------------- argument types


def int_at_least(text: str, low: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    return int_at_least(text, 1)


def non_negative_int(text: str) -> int:
    return int_at_least(text, 0)


def even_int_at_least_2(text: str) -> int:
    value = int_at_least(text, 2)
    if value % 2:
        raise argparse.ArgumentTypeError(f"expected an even number of pixels, got {value}")
    return value


def jpeg_quality(text: str) -> int:
    value = int_at_least(text, 1)
    if value > 100:
        raise argparse.ArgumentTypeError(f"expected 1..100, got {text!r}")
    return value


def port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port 0..65535, got {text!r}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def at_least_1_mb(text: str) -> float:
    value = positive_float(text)
    if value < 1.0:
        raise argparse.ArgumentTypeError(f"expected at least 1 (MiB), got {text!r}")
    return value


def image_size(text: str) -> tuple[int, int]:
    """WxH in pixels, within the synthetic scene's limits."""
    from arlight.sources.synthetic import parse_size

    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def rotation_3x3(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 9:
        raise argparse.ArgumentTypeError(
            f"expected 9 comma-separated numbers (a 3x3 rotation, row-major), got {text!r}"
        )
    return values


def config_override(text: str) -> tuple[str, object]:
    """--set KEY=VALUE: a pipeline Config field and its parsed value."""
    from arlight.pipeline.config import Config

    if "=" not in text:
        raise argparse.ArgumentTypeError(f"--set expects KEY=VALUE, got {text!r}")
    key, value = text.split("=", 1)
    try:
        return key, Config.parse_flat_value(key, value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{exc} (--set {key}=VALUE)") from None


def engine_layouts(text: str) -> list[str]:
    """--export arcore,webxr,...: engine layout names, checked."""
    from arlight.pipeline.engine_export import EXPORTERS

    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in EXPORTERS]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"unknown engine layout {', '.join(bad) or repr(text)}; choose from "
            f"{', '.join(EXPORTERS)} (comma-separated)"
        )
    return names


# --------------------------------------------------------------------------- shared options


def add_scene_options(p: argparse.ArgumentParser) -> None:
    """--scene and --scene-frame, shared by estimate, stream and record."""
    p.add_argument(
        "--scene",
        metavar="FILE",
        help="virtual objects to render into the frames: a scene file (JSON or "
        "TOML, see docs/scene-files.md; e.g. a data set's ar/virtual_scene."
        "json), or 'demo' (a sphere and a torus standing on the detected "
        "ground)",
    )
    p.add_argument(
        "--scene-frame",
        choices=("world", "cam0"),
        help="frame of the scene file's poses: 'world' = the data set's pose frame "
        "(default with --poses groundtruth), 'cam0' = the first camera "
        "(default when tracking, whose world is the first camera)",
    )


def build_config(args: argparse.Namespace):
    """The frozen pipeline Config of --preset, --set, --rgb and --device."""
    from arlight.pipeline.config import Config

    overrides = dict(args.set or [])
    if getattr(args, "rgb", False):
        overrides["estimate_rgb"] = True
    if getattr(args, "device", None):
        overrides["device"] = args.device
    return Config.from_preset(args.preset, **overrides)


def load_scene(args: argparse.Namespace, image_size: tuple[int, int] = (640, 480)):
    """The virtual scene of --scene (a file, or 'demo' anchored for image_size), or None;
    its frame from --scene-frame, else world with ground-truth poses and cam0 (the first
    camera) when tracking. A bad file is the user's error, named by its flag."""
    if not getattr(args, "scene", None):
        return None
    from arlight.pipeline.virtual_scene import SceneError, demo_scene

    if args.scene == "demo":
        return demo_scene(image_size)
    from arlight.sources.virtual_scene_file import load_virtual_scene

    poses = getattr(args, "poses", "groundtruth")  # bench: always the data set's poses
    frame = getattr(args, "scene_frame", None) or ("world" if poses == "groundtruth" else "cam0")
    try:
        return load_virtual_scene(args.scene, frame=frame)
    except SceneError as exc:
        raise BadInput(f"--scene {args.scene}: {exc}") from None


def check_address(address: str, option: str) -> str:
    """A ZeroMQ address, or BadInput naming `option`."""
    if not address.startswith(("tcp://", "ipc://", "inproc://")):
        raise BadInput(
            f"{option} expects a ZeroMQ address such as tcp://HOST:PORT, got {address!r}"
        )
    return address


def output_folder(path: str | None, option: str) -> Path | None:
    """A folder to write into, created; None when not asked for; errors name `option`."""
    if not path:
        return None
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInput(f"{option} {path}: cannot create the folder ({exc.strerror})") from None
    return folder


# --------------------------------------------------------------------------- output text


def count(n: int, noun: str) -> str:
    """'1 frame', '2 frames'."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def figure(value: float | None, spec: str) -> str:
    """A number for a summary line; '-' where nothing was measured."""
    return "-" if value is None else format(value, spec)
