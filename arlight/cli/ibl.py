"""`arlight ibl`: lighting from a 360-degree panorama (video, images), SH per frame, and
virtual objects rendered under it."""

from __future__ import annotations

import argparse
import json
import math
import queue
import sys
import threading
import time

import cv2
import numpy as np

from arlight.cli.common import (
    BadInput,
    count,
    image_size,
    output_folder,
    positive_float,
    positive_int,
)
from arlight.pipeline.inverse_tone import DEFAULT_OPERATOR, OPERATORS

MAX_RENDER_PIXELS = 4096 * 4096  # per view of --render: about 1.4 GB of per-pixel buffers


def add_parser(sub) -> None:
    ibl = sub.add_parser(
        "ibl",
        help="lighting from a 360-degree panorama (video, images): SH per frame",
        description="Image-based lighting from an equirectangular 360-degree LDR video, "
        "image sequence or image: per frame, inverse tone mapping to an HDR "
        "radiance map, its SH radiance (16 luminance coefficients and 3x16 RGB, "
        "the project's convention), the dominant light direction and a "
        "low-resolution diffuse map; one JSON line per frame, in the panorama's "
        "frame (+y up; a direction d shows at column atan2(d.x, -d.z) / 2 pi, "
        "row acos(d.y) / pi, row 0 at the top). HDR inputs (.hdr, .exr) are used "
        "as they are.",
    )
    ibl.add_argument(
        "panorama",
        nargs="?",
        default="synthetic",
        metavar="PANORAMA",
        help="a video file (any format OpenCV's FFmpeg backend reads), a folder "
        "of PNG/JPEG images (sorted by name), one image, or a Radiance "
        ".hdr / OpenEXR .exr; 'synthetic' (the default): a built-in sky "
        "turning about +y, with its known light",
    )
    ibl.add_argument(
        "--out", metavar="FILE", help="write the JSON lines to FILE (default: standard output)"
    )
    ops = "; ".join(f"{op.name}: {op.summary}" for op in OPERATORS.values())
    ibl.add_argument(
        "--operator",
        choices=tuple(OPERATORS),
        default=DEFAULT_OPERATOR,
        help=f"inverse tone mapping (default {DEFAULT_OPERATOR}). {ops}",
    )
    ibl.add_argument(
        "--exr",
        metavar="DIR",
        help="also write each frame's HDR map as DIR/NNNNNN.exr (OpenEXR, "
        "equirectangular, linear, half float)",
    )
    ibl.add_argument(
        "--cubemap",
        action="store_true",
        help="with --exr, also the six cube faces NNNNNN_px.exr ... of each HDR "
        "map (OpenGL face order and orientation, half the map's height a "
        "side)",
    )
    ibl.add_argument(
        "--diffuse-size",
        type=_panorama_size,
        default=(32, 16),
        metavar="WxH",
        help="size of the diffuse map, brute force over the map area-averaged "
        "to the same size (default 32x16, the paper's)",
    )
    ibl.add_argument(
        "--fps",
        type=positive_float,
        metavar="F",
        help="frames per second for the timestamps of an image sequence "
        "(default 30), or instead of a video's own timestamps",
    )
    ibl.add_argument(
        "--max-frames",
        type=positive_int,
        metavar="N",
        help="only the first N frames (synthetic: its length, default 8)",
    )
    ibl.add_argument(
        "--render",
        metavar="DIR",
        help="render virtual objects lit by each frame into a perspective view "
        "cut from the panorama: DIR/NNNNNN.png (diffuse map, mirror and "
        "glossy mipmap sampling)",
    )
    ibl.add_argument(
        "--stereo",
        action="store_true",
        help="with --render: a stereo pair for head-mounted displays, side by "
        "side, 1182x1464 per eye (Oculus DK2), eyes 64 mm apart",
    )
    ibl.add_argument(
        "--scene",
        metavar="FILE",
        help="with --render: the virtual objects (a scene file, "
        "docs/scene-files.md; poses in the panorama's frame, +y up, metres, "
        "the camera at the origin); default 'demo': 5 built-in objects "
        "(diffuse, glossy 0.1, mirror, glossy 0.3, a half-glossy torus) 1.6 m "
        "ahead",
    )
    ibl.add_argument(
        "--view",
        type=_view_angles,
        metavar="AZ,EL",
        help="with --render: the view direction in degrees, azimuth (the "
        "panorama's column u = AZ / 360) and elevation (default 180,0: the "
        "centre of the panorama, +z)",
    )
    ibl.add_argument(
        "--fov-deg",
        type=_field_of_view,
        default=75.0,
        metavar="DEG",
        help="with --render: horizontal field of view (default 75)",
    )
    ibl.add_argument(
        "--render-size",
        type=image_size,
        metavar="WxH",
        help="with --render: the view's size, per eye with --stereo (default "
        "1280x720, stereo 1182x1464)",
    )
    ibl.add_argument(
        "--roughness",
        type=_roughness_pair,
        metavar="R1,R2",
        help="with --render and the built-in scene: its two glossy spheres' "
        "roughness, each in 0.01..0.5 (default 0.1,0.3)",
    )
    ibl.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from arlight.ibl import (
        SYNTHETIC,
        SyntheticPanorama,
        frame_record,
        synthetic_panorama,
        truth_error_deg,
    )
    from arlight.ibl import run as run_ibl
    from arlight.pipeline.environment_map import cubemap_from_equirect
    from arlight.pipeline.ibl import IblParams
    from arlight.sources.exr import write_exr
    from arlight.sources.panorama import PanoramaSource, open_panorama

    params = IblParams(operator=args.operator, diffuse_size=args.diffuse_size)
    renderer = _renderer(args)  # before any output: a bad --scene stops here
    exr_dir = output_folder(args.exr, "--exr")
    if args.cubemap and exr_dir is None:
        raise BadInput("--cubemap writes faces beside the --exr maps: give --exr DIR")
    render_dir = output_folder(args.render, "--render")
    source: SyntheticPanorama | PanoramaSource
    if args.panorama == SYNTHETIC:
        source = synthetic_panorama(args.max_frames or 8)
        truth = source.truth_directions
    else:
        source = open_panorama(args.panorama, fps=args.fps, max_frames=args.max_frames)
        truth = None
    operator = "none (HDR input)" if source.hdr else args.operator
    total = source.num_frames
    print(
        f"arlight ibl: {args.panorama} ({source.kind}, "
        f"{count(total, 'frame') if total else 'frames'}, {source.size[0]}x"
        f"{source.size[1]}{', HDR' if source.hdr else ''}), operator {operator}, diffuse map "
        f"{args.diffuse_size[0]}x{args.diffuse_size[1]}",
        file=sys.stderr,
        flush=True,
    )
    try:
        out = open(args.out, "w") if args.out else sys.stdout  # noqa: SIM115
    except OSError as exc:
        source.close()
        raise BadInput(f"--out {args.out}: cannot write this file ({exc.strerror})") from None
    bar = tqdm(
        total=total, unit="frame", disable=not sys.stderr.isatty(), dynamic_ncols=True, leave=False
    )
    errors: list[float] = []
    process_ms: list[float] = []

    def on_frame(frame) -> None:
        record = frame_record(frame, operator)
        err = truth_error_deg(frame, truth)
        if err is not None:
            record["angular_error_deg"] = err
            errors.append(err)
        out.write(json.dumps(record) + "\n")
        if exr_dir is not None:
            write_exr(exr_dir / f"{frame.index:06d}.exr", frame.hdr)
            if args.cubemap:
                for face, image in cubemap_from_equirect(
                    frame.hdr, max(1, frame.hdr.shape[0] // 2)
                ).items():
                    write_exr(exr_dir / f"{frame.index:06d}_{face}.exr", image)
        if renderer is not None and writer is not None and render_dir is not None:
            writer.put(render_dir / f"{frame.index:06d}.png", renderer.render(frame))
        process_ms.append(frame.process_ms)
        bar.update(1)

    writer = _PngWriter(f"--render {args.render}") if render_dir is not None else None
    t0 = time.perf_counter()
    try:
        n = run_ibl(source, params, on_frame)
        if writer is not None:
            writer.close()  # the last frames written; a failed write raises here
    finally:
        if writer is not None:
            writer.close()
        bar.close()
        source.close()
        if out is not sys.stdout:
            out.close()
        else:
            out.flush()
    elapsed = time.perf_counter() - t0
    wait = ""
    if source.wait_ms and source.decode_ms:  # a video: decoding ran on its own thread
        wait = (
            f"; waited for decoding {np.median(source.wait_ms):.1f} ms/frame (decode "
            f"{np.median(source.decode_ms):.1f} ms/frame on its own thread)"
        )
    print(
        f"arlight ibl: {count(n, 'frame')} in {elapsed:.1f} s, processing median "
        f"{np.median(process_ms) if process_ms else float('nan'):.1f} ms/frame{wait}",
        file=sys.stderr,
    )
    if errors:
        print(
            f"dominant direction against the HDR original: median {np.median(errors):.1f} "
            f"deg (max {np.max(errors):.1f})",
            file=sys.stderr,
        )
    if args.out:
        print(f"wrote {count(n, 'result')} to {args.out}", file=sys.stderr)
    if exr_dir is not None:
        print(
            f"wrote {count(n, 'HDR map')} to {exr_dir}/ (NNNNNN.exr, half float)", file=sys.stderr
        )
    if renderer is not None and renderer.timings_ms:
        w, h = renderer.setup.size
        layout = f"stereo side by side, {w}x{h} per eye" if args.stereo else f"{w}x{h}"
        print(
            f"wrote {count(n, 'render')} to {render_dir}/ (NNNNNN.png, {layout}, "
            f"{count(len(renderer.setup.scene.objects), 'object')}); render median "
            f"{np.median([t['Render'] for t in renderer.timings_ms]):.0f} ms/frame",
            file=sys.stderr,
        )
    return 0


class _PngWriter:
    """Writes the renders as PNG on its own thread (at most 2 waiting): the encoding of
    frame i overlaps the processing of frame i + 1 (OpenCV releases the GIL). A failed
    write raises OSError naming `flag` at the next put or at close."""

    def __init__(self, flag: str):
        self._flag = flag
        self._queue: queue.Queue = queue.Queue(maxsize=2)
        self._error: OSError | None = None
        self._thread: threading.Thread | None = threading.Thread(
            target=self._run, name="png-writer", daemon=True
        )
        self._thread.start()

    def put(self, path, rgb: np.ndarray) -> None:
        """Queue (H, W, 3) uint8 RGB for `path` (waits while 2 are queued)."""
        self._raise()
        self._queue.put((path, rgb))

    def close(self) -> None:
        """Write what is queued and stop the thread (again: nothing); raise a failed write."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None
        self._raise()

    def _raise(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            path, rgb = item
            if self._error is None and not cv2.imwrite(str(path), rgb[..., ::-1]):
                self._error = OSError(f"{self._flag}: cannot write {path}")


def _renderer(args: argparse.Namespace):
    """The FrameRenderer of --render (None without it); errors name the flag."""
    if not args.render:
        for flag, given in (
            ("--stereo", args.stereo),
            ("--scene", args.scene),
            ("--render-size", args.render_size),
            ("--view", args.view),
            ("--roughness", args.roughness),
        ):
            if given:
                raise BadInput(f"{flag} needs --render DIR (it sets up the rendering)")
        return None
    from arlight.ibl import FrameRenderer, RenderSetup
    from arlight.pipeline import ibl_render
    from arlight.pipeline.virtual_scene import SceneError

    azimuth, elevation = args.view or (180.0, 0.0)
    forward = ibl_render.direction_of(azimuth, elevation)
    if args.scene and args.scene != "demo":
        if args.roughness:
            raise BadInput(
                "--roughness sets the built-in scene's glossy objects; a --scene "
                "file gives each object's own material.roughness"
            )
        from arlight.sources.virtual_scene_file import load_virtual_scene

        try:
            scene = load_virtual_scene(args.scene, frame="world")
        except SceneError as exc:
            raise BadInput(f"--scene {args.scene}: {exc}") from None
    else:
        scene = ibl_render.demo_scene(forward, args.roughness or ibl_render.DEMO_ROUGHNESS)
    size = args.render_size or (ibl_render.EYE_SIZE if args.stereo else ibl_render.MONO_SIZE)
    if size[0] * size[1] > MAX_RENDER_PIXELS:
        raise BadInput(
            f"--render-size {size[0]}x{size[1]}: at most {MAX_RENDER_PIXELS} "
            f"pixels per view (e.g. 4096x4096)"
        )
    setup = RenderSetup(scene, ibl_render.look_along(forward), size, args.fov_deg, args.stereo)
    try:
        return FrameRenderer(setup)
    except SceneError as exc:
        raise BadInput(f"--scene {args.scene or 'demo'}: {exc}") from None


def _panorama_size(text: str) -> tuple[int, int]:
    """--diffuse-size WxH: a 2:1 equirectangular size."""
    from arlight.pipeline.ibl import MAX_DIFFUSE_HEIGHT

    width, height = image_size(text)
    if width != 2 * height:
        raise argparse.ArgumentTypeError(
            f"an equirectangular map is twice as wide as high (e.g. 32x16), got {text!r}"
        )
    if height > MAX_DIFFUSE_HEIGHT:
        raise argparse.ArgumentTypeError(
            f"at most {2 * MAX_DIFFUSE_HEIGHT}x{MAX_DIFFUSE_HEIGHT} "
            f"(brute force grows as the 4th power), got {text!r}"
        )
    return width, height


def _roughness_pair(text: str) -> tuple[float, float]:
    """--roughness R1,R2: the built-in scene's two glossy roughnesses, each in 0.01..0.5."""
    from arlight.pipeline.glossy import check_roughness

    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError(f"expected two numbers R1,R2, got {text!r}")
        first, second = (check_roughness(float(p), "each roughness") for p in parts)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return first, second


def _view_angles(text: str) -> tuple[float, float]:
    """--view AZ,EL in degrees: azimuth 0..360 (the panorama's column u = AZ / 360),
    elevation -89..89."""
    parts = text.split(",")
    try:
        az, el = (float(p) for p in parts) if len(parts) == 2 else (math.nan, math.nan)
    except ValueError:
        az = el = math.nan
    if not (math.isfinite(az) and math.isfinite(el) and -89.0 <= el <= 89.0):
        raise argparse.ArgumentTypeError(
            f"expected AZ,EL in degrees with EL in [-89, 89], got {text!r}"
        )
    return az % 360.0, el


def _field_of_view(text: str) -> float:
    value = positive_float(text)
    if not 1.0 <= value <= 170.0:
        raise argparse.ArgumentTypeError(f"expected degrees in [1, 170], got {text!r}")
    return value
