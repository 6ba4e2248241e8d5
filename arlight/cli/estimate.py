"""`arlight estimate`: the lighting of an RGB-D sequence, one line (and JSON record) per frame."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np

from arlight.cli.common import (
    DEPTH_ENCODINGS,
    LAYOUT_NAMES,
    PRESETS,
    BadInput,
    add_scene_options,
    at_least_1_mb,
    build_config,
    config_override,
    count,
    engine_layouts,
    even_int_at_least_2,
    load_scene,
    output_folder,
    positive_float,
    positive_int,
)
from arlight.cli.probe_files import PROBE_LAYOUT_HELP, PROBE_LAYOUTS, write_probe_files
from arlight.cli.stop_signals import finalised_on_sigterm

# the server's default budgets (`arlight serve --frame-deadline / --session-memory-mb`)
DEFAULT_FRAME_DEADLINE_S = 60.0
DEFAULT_MEMORY_MB = 1024.0


def add_parser(sub) -> None:
    est = sub.add_parser(
        "estimate",
        help="estimate the lighting of an RGB-D sequence, one JSON line per frame",
        description="Estimate spherical-harmonics lighting per frame. PATH is a TUM RGB-D "
        "folder, an Open3D/Redwood folder, a 7-Scenes folder, a colour image "
        "(with --depth, or a *depth* file beside it), or 'synthetic' (the "
        "built-in scene with known light; the default).",
    )
    est.add_argument("path", nargs="?", default="synthetic", metavar="PATH")
    est.add_argument(
        "--preset",
        choices=PRESETS,
        default="full",
        help="speed/accuracy preset (default: full, the paper's 'Ours', steadiest on real "
        "frames; fast takes half the time and is as accurate over the 22 maps of the "
        "corpus; mobile is fastest, 4-10 degrees worse: docs, Results: accuracy)",
    )
    est.add_argument(
        "--poses",
        choices=("groundtruth", "track"),
        default="track",
        help="'groundtruth': use the data set's camera poses and skip tracking; "
        "'track' (default): frame-to-model tracking",
    )
    est.add_argument("--rgb", action="store_true", help="also estimate one SH per RGB channel")
    est.add_argument("--out", metavar="FILE", help="write results as JSON lines to FILE")
    est.add_argument(
        "--overlap",
        action="store_true",
        help="process the next frame's reconstruction beside this frame's light fit: more "
        "frames a second on 2+ cores, a frame's latency longer (docs/decisions/"
        "0042-overlapped-frames.md); the ms printed per frame is then the time between results",
    )
    est.add_argument(
        "--max-frames",
        type=positive_int,
        metavar="N",
        help="only the first N frames (synthetic: of its 12-frame orbit, or of an N-frame "
        "orbit where N is more)",
    )
    est.add_argument("--depth", metavar="FILE", help="depth image for a single colour image")
    est.add_argument(
        "--depth-encoding",
        choices=DEPTH_ENCODINGS,
        help="depth encoding (default: from the data set's layout or file name)",
    )
    est.add_argument("--device", help="Open3D device for the volume, e.g. CUDA:0 (default CPU:0)")
    est.add_argument(
        "--set",
        action="append",
        type=config_override,
        metavar="KEY=VALUE",
        help="override any Config field, e.g. --set rt_directions=128; the "
        "settings are priced by the server's cost model first (see "
        "--frame-deadline)",
    )
    add_scene_options(est)
    est.add_argument(
        "--composite-out",
        metavar="DIR",
        help="write each frame's composite (the virtual objects rendered in) as "
        "DIR/NNNNNN.png, NNNNNN the frame's index; without --scene, the "
        "input frames",
    )
    est.add_argument(
        "--export",
        type=engine_layouts,
        metavar="LAYOUTS",
        help="also put the light in these engines' layouts into each JSON line "
        '("exports"; camera frame, the engine\'s axes): comma-separated '
        "from " + LAYOUT_NAMES,
    )
    est.add_argument(
        "--env-exr",
        metavar="DIR",
        help="write the estimated light per frame as an equirectangular HDR map "
        "DIR/NNNNNN.exr (OpenEXR half float, world frame, +y up)",
    )
    est.add_argument(
        "--gltf",
        metavar="DIR",
        help="write the estimated light per frame as a glTF asset DIR/NNNNNN.glb: "
        "EXT_lights_image_based (irradiance SH and GGX-prefiltered specular cube, from the "
        "reflection probe when the frame made one, else from the SH) on a white sphere; "
        "camera frame, OpenGL axes",
    )
    est.add_argument(
        "--probe-out",
        metavar="DIR",
        help="write each frame's reflection probe (pipeline/probe.py) as OpenEXR cube maps "
        "DIR/NNNNNN_<face>_m<level>.exr, every GGX-prefiltered mip level (linear HDR, half "
        "float, world axes, OpenGL face order and orientation) and DIR/NNNNNN.json (point, "
        "roughness per level, diagnostics); at --probe-at or the --scene objects' centre",
    )
    est.add_argument(
        "--probe-layout",
        choices=PROBE_LAYOUTS,
        default="world",
        help=PROBE_LAYOUT_HELP,
    )
    est.add_argument(
        "--probe-at",
        metavar="X,Y,Z",
        help="the reflection probe's point, world frame, metres (default: the centre of "
        "the --scene objects)",
    )
    est.add_argument(
        "--env-size",
        type=even_int_at_least_2,
        default=256,
        metavar="W",
        help="width of the --env-exr maps in pixels (even; default 256)",
    )
    est.add_argument(
        "--cubemap",
        action="store_true",
        help="with --env-exr, also write the six cube faces NNNNNN_px.exr ... "
        "(OpenGL face order and orientation, W / 4 pixels a side)",
    )
    est.add_argument(
        "--frame-deadline",
        type=positive_float,
        default=DEFAULT_FRAME_DEADLINE_S,
        metavar="S",
        help="refuse settings (--preset, --set, image size, --scene) that the "
        "server's cost model prices over S seconds a frame, as `arlight "
        f"serve` does (default {DEFAULT_FRAME_DEADLINE_S:g}, the server's); "
        "raise it for a slow offline run",
    )
    est.add_argument(
        "--memory-mb",
        type=at_least_1_mb,
        default=DEFAULT_MEMORY_MB,
        metavar="MB",
        help="likewise for the memory the cost model prices (default "
        f"{DEFAULT_MEMORY_MB:g}, the server's per-session budget)",
    )
    est.set_defaults(func=run)


@finalised_on_sigterm
def run(args: argparse.Namespace) -> int:
    from arlight.offline import FrameNotes, estimate_frames, has_usable_depth
    from arlight.pipeline.pipeline import Pipeline
    from arlight.pipeline.runtime import require_device

    config = build_config(args)
    require_device(config.device)  # before the source is read
    camera, frames, truth = _open_source(args)
    n = len(frames)
    print(
        f"arlight estimate: {args.path} ({count(n, 'frame')}, {camera.width}x{camera.height}), "
        f"preset {config.preset}, poses {args.poses}",
        file=sys.stderr,
    )
    scene = load_scene(args, (camera.width, camera.height))
    _check_cost(args, config, camera, len(scene.objects) if scene else 0)
    pipeline = Pipeline(config, camera, scene)
    composites = output_folder(args.composite_out, "--composite-out")
    environments = output_folder(args.env_exr, "--env-exr")
    gltf_dir = output_folder(args.gltf, "--gltf")
    probes = _probe_output(args, pipeline, scene)
    if args.cubemap and environments is None:
        raise BadInput("--cubemap writes faces beside the --env-exr maps: give --env-exr DIR")
    out = open(args.out, "w") if args.out else None  # noqa: SIM115
    errors, sun_errors = [], []
    notes = FrameNotes()
    try:
        for done in estimate_frames(
            pipeline, (frames[i] for i in range(n)), tuple(args.export or ()), args.overlap
        ):
            i, result, record = done.index, done.result, done.record
            d = result.dominant_direction_camera
            line = (
                f"[{i + 1:>4}/{n}] t={result.timestamp:.3f}s  light(cam)=({d[0]:+.2f}, "
                f"{d[1]:+.2f}, {d[2]:+.2f})  intensity={result.intensity:.3g}  "
                f"conf={result.confidence.value:.2f}  bands={result.confidence.bands_estimated}"
                f"  {done.process_ms:.0f} ms"
            )
            if truth is not None:
                # in the camera frame: tracking's world is the first camera, the scene's
                # world is its own, and the camera frame is the one both share; against the
                # light that can reach the scene (its upper hemisphere), as `arlight bench`
                err = _angle_deg(result.dominant_direction_camera, truth[i].dominant_upper_camera)
                errors.append(err)
                record["angular_error_deg"] = err
                line += f"  error={err:.1f} deg"
                if result.compact_sources and truth[i].sun_camera is not None:
                    # the kept source against the scene's sun, what it is (arlight demo)
                    sun_err = _angle_deg(
                        result.compact_sources[0].direction_camera, truth[i].sun_camera
                    )
                    sun_errors.append(sun_err)
                    line += f" (a compact source, {sun_err:.1f} deg from the sun)"
            print(line, flush=True)
            note = notes.note(
                result.confidence.value, result.confidence.reason, has_usable_depth(done.frame)
            )
            if note:
                print(f"arlight estimate: [{i + 1}/{n}] {note}", file=sys.stderr, flush=True)
            if out:
                out.write(json.dumps(record) + "\n")
                out.flush()  # each Result on disk as it comes (a stopped run keeps them)
            if environments is not None:
                _write_environment(environments, i, result, args.env_size, args.cubemap)
            if gltf_dir is not None:
                _write_gltf(gltf_dir / f"{i:06d}.glb", result, pipeline.last_probe)
            if probes is not None and pipeline.last_probe is not None:
                write_probe(
                    probes / f"{i:06d}", pipeline.last_probe, args.probe_layout, result.pose
                )
            if composites is not None:
                image = result.composite if result.composite is not None else done.frame.color
                cv2.imwrite(str(composites / f"{i:06d}.png"), image[..., ::-1])
    finally:
        if out:
            out.close()
    if notes.summary():
        print(f"arlight estimate: {notes.summary()}", file=sys.stderr)
    if errors:
        print(
            f"median angular error of the dominant light: {np.nanmedian(errors):.1f} deg "
            f"(90th percentile {np.nanpercentile(errors, 90):.1f}; against the first moment "
            "of the light above the horizon)",
            file=sys.stderr,
        )
    if sun_errors:
        print(
            f"a compact source on {len(sun_errors)} of {count(n, 'frame')}, median "
            f"{np.nanmedian(sun_errors):.1f} deg from the scene's sun",
            file=sys.stderr,
        )
    if args.out:
        print(f"wrote {count(n, 'result')} to {args.out}", file=sys.stderr)
    if composites is not None:
        print(f"wrote {count(n, 'composite')} to {composites}/", file=sys.stderr)
    if gltf_dir is not None:
        print(f"wrote {count(n, 'glTF light')} to {gltf_dir}/ (.glb)", file=sys.stderr)
    if probes is not None:
        made = len(list(probes.glob("*.json")))
        missing = "" if made == n else "; frames before the objects were placed have none"
        print(
            f"wrote {count(made, 'reflection probe')} to {probes}/ (OpenEXR cube maps and "
            f"their mips){missing}",
            file=sys.stderr,
        )
    if environments is not None:
        print(
            f"wrote {count(n, 'environment map')} to {environments}/ (OpenEXR, half float"
            f"{', with cubemap faces' if args.cubemap else ''})",
            file=sys.stderr,
        )
    return 0


def _check_cost(args: argparse.Namespace, config, camera, objects: int) -> None:
    """Price the settings with the server's cost model (server/budget.py, the one that
    refuses a Hello with `over_budget`) against --frame-deadline and --memory-mb; BadInput
    naming the flag behind the costliest setting."""
    from arlight.server.budget import BudgetError, SessionBudget, check_cost

    budget = SessionBudget(args.frame_deadline, int(args.memory_mb * 2**20))
    try:
        check_cost(config, camera, objects, budget)
    except BudgetError as exc:
        given = {key for key, _ in args.set or ()}
        flag = (
            f"--set {exc}"
            if exc.setting in given
            else f"the image size {camera.width}x{camera.height} of {args.path}: {exc}"
            if exc.setting == "calibration"
            else f"--preset {config.preset}: {exc}"
        )
        raise BadInput(
            f"{flag}. arlight estimate prices its settings as the server does; "
            f"--frame-deadline S and --memory-mb MB raise its limits "
            f"({args.frame_deadline:g} s, {args.memory_mb:g} MiB)"
        ) from None


def _open_source(args: argparse.Namespace):
    """(camera, frames, per-frame ground truth (arlight.evaluation.FrameTruth) or None)."""
    from arlight.sources.image_pair import open_pair, without_poses
    from arlight.sources.sequence import open_sequence

    use_poses = args.poses == "groundtruth"
    if args.path == "synthetic":
        from arlight.evaluation import scene_truth
        from arlight.sources.synthetic import CLI_FRAMES, make_sequence

        # the first N frames of the orbit (not an N-frame orbit, whose steps may be too long
        # to track)
        synthetic = make_sequence(num_frames=max(args.max_frames or 0, CLI_FRAMES))
        first = synthetic.frames[: args.max_frames or CLI_FRAMES]
        frames = [f if use_poses else dataclasses.replace(f, pose=None) for f in first]
        return synthetic.camera, frames, scene_truth(synthetic)[: len(frames)]
    if args.depth:
        seq = without_poses(open_pair(args.path, args.depth, args.depth_encoding), use_poses)
    else:
        seq = open_sequence(
            args.path,
            depth_encoding=args.depth_encoding,
            use_poses=use_poses,
            max_frames=args.max_frames,
        )
    return seq.camera, seq.frames, None


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return float("nan")
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def _write_environment(folder: Path, index: int, result, width: int, cubemap: bool) -> None:
    """DIR/NNNNNN.exr: the estimated light as an equirectangular HDR map (world frame, the
    SH's units), and with cubemap the six faces NNNNNN_px.exr ... (size width / 4)."""
    from arlight.pipeline.environment_map import cubemap_from_sh, equirect_from_sh
    from arlight.sources.exr import write_exr

    light = result.sh_rgb if result.sh_rgb is not None else result.sh
    write_exr(folder / f"{index:06d}.exr", equirect_from_sh(light, width))
    if cubemap:
        for face, image in cubemap_from_sh(light, max(1, width // 4)).items():
            write_exr(folder / f"{index:06d}_{face}.exr", image)


def _probe_output(args: argparse.Namespace, pipeline, scene) -> Path | None:
    """--probe-at set on the pipeline and --probe-out's folder (None without it); BadInput
    naming the flag for a bad point, or a probe with nowhere to be."""
    from arlight.pipeline.probe import parse_point

    if args.probe_at is not None:
        try:
            pipeline.probe_point = parse_point(args.probe_at, "--probe-at")
        except ValueError as exc:
            raise BadInput(str(exc)) from None
    folder = output_folder(args.probe_out, "--probe-out")
    if folder is None:
        if args.probe_layout != "world":
            raise BadInput("--probe-layout says how --probe-out writes: give --probe-out DIR")
        return None
    if not pipeline.config.render.probe:
        raise BadInput("--probe-out needs the probe: drop --set probe=false")
    if args.probe_at is None and not scene:
        raise BadInput("--probe-out needs a point: give --probe-at X,Y,Z or a --scene")
    pipeline.probe_wanted = True
    return folder


def write_probe(stem: Path, probe, layout: str = "world", pose: np.ndarray | None = None) -> None:
    """The pipeline's ProbeResult as --probe-out writes it (probe_files.write_probe_files):
    STEM_<face>_m<level>.exr and STEM.json; layout "world" or an engine's, in the camera
    frame of `pose` (4 x 4 camera-to-world)."""
    write_probe_files(stem, probe.mips, probe.point_world, layout, pose, probe.diagnostics)


def _write_gltf(path: Path, result, probe) -> None:
    """The frame's light as a .glb (pipeline/gltf_asset.py) in the camera frame with OpenGL
    axes, as the Result's engine layouts; the probe's cube when the frame made one."""
    from arlight.pipeline import sh
    from arlight.pipeline.gltf_asset import write_glb

    light = result.sh_rgb if result.sh_rgb is not None else result.sh
    engine_from_world = sh.GL_FROM_CV @ np.asarray(result.pose, np.float64)[:3, :3].T
    write_glb(
        path,
        light,
        engine_from_world,
        probe=None if probe is None else probe.mips,
    )
