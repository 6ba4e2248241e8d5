"""The `arlight` command: parse -> frozen Config -> library call; typed errors -> exit codes.

Exit codes: 0 success, 1 unexpected failure, 2 bad input or usage (the message says what to do).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import re
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from arlight import __version__

EXIT_BAD_INPUT = 2


def _parse_override(text: str) -> tuple[str, object]:
    from arlight.pipeline.config import Config

    if "=" not in text:
        raise argparse.ArgumentTypeError(f"--set expects KEY=VALUE, got {text!r}")
    key, value = text.split("=", 1)
    try:
        return key, Config.parse_flat_value(key, value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{exc} (--set {key}=VALUE)") from None


def _build_config(args: argparse.Namespace):
    from arlight.pipeline.config import Config

    overrides = dict(args.set or [])
    if getattr(args, "rgb", False):
        overrides["estimate_rgb"] = True
    if getattr(args, "device", None):
        overrides["device"] = args.device
    return Config.from_preset(args.preset, **overrides)


def _open_source(args: argparse.Namespace):
    """(camera, frames, per-frame ground truth (arlight.evaluation.FrameTruth) or None)."""
    from arlight.sources.image_pair import open_pair, without_poses
    from arlight.sources.sequence import open_sequence

    use_poses = args.poses == "groundtruth"
    if args.path == "synthetic":
        from arlight.evaluation import scene_truth
        from arlight.sources.synthetic import make_sequence

        seq = make_sequence(num_frames=args.max_frames or 12)
        frames = [f if use_poses else dataclasses.replace(f, pose=None) for f in seq.frames]
        return seq.camera, frames, scene_truth(seq)
    if args.depth:
        seq = without_poses(open_pair(args.path, args.depth, args.depth_encoding), use_poses)
    else:
        seq = open_sequence(args.path, depth_encoding=args.depth_encoding, use_poses=use_poses,
                            max_frames=args.max_frames)
    return seq.camera, seq.frames, None


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return float("nan")
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def cmd_estimate(args: argparse.Namespace) -> int:
    from arlight.pipeline.pipeline import Pipeline
    from arlight.pipeline.runtime import require_device
    from arlight.server.results import offline_record

    config = _build_config(args)
    require_device(config.device)  # before the source is read
    camera, frames, truth = _open_source(args)
    n = len(frames)
    print(f"arlight estimate: {args.path} ({_count(n, 'frame')}, {camera.width}x{camera.height}), "
          f"preset {config.preset}, poses {args.poses}", file=sys.stderr)
    pipeline = Pipeline(config, camera, _load_scene(args, (camera.width, camera.height)))
    composites = _output_folder(args.composite_out, "--composite-out")
    environments = _output_folder(args.env_exr, "--env-exr")
    if args.cubemap and environments is None:
        raise _BadInput("--cubemap writes faces beside the --env-exr maps: give --env-exr DIR")
    out = open(args.out, "w") if args.out else None  # noqa: SIM115
    errors = []
    try:
        for i in range(n):
            frame = frames[i]
            t0 = time.perf_counter()
            start_wall = time.time()
            result = pipeline.process(frame)
            ms = (time.perf_counter() - t0) * 1e3
            # the record `arlight stream --out` writes, from the Result the server would send
            record = offline_record(result, i, start_wall, tuple(args.export or ()))
            d = result.dominant_direction_camera
            line = (f"[{i + 1:>4}/{n}] t={result.timestamp:.3f}s  light(cam)=({d[0]:+.2f}, "
                    f"{d[1]:+.2f}, {d[2]:+.2f})  intensity={result.intensity:.3g}  "
                    f"conf={result.confidence.value:.2f}  bands={result.confidence.bands_estimated}"
                    f"  {ms:.0f} ms")
            if truth is not None:
                # in the camera frame: tracking's world is the first camera, the scene's
                # world is its own, and the camera frame is the one both share; against the
                # light that can reach the scene (its upper hemisphere), as `arlight bench`
                err = _angle_deg(result.dominant_direction_camera,
                                 truth[i].dominant_upper_camera)
                errors.append(err)
                record["angular_error_deg"] = err
                line += f"  error={err:.1f} deg"
            print(line, flush=True)
            if out:
                out.write(json.dumps(record) + "\n")
            if environments is not None:
                _write_environment(environments, i, result, args.env_size, args.cubemap)
            if composites is not None:
                image = result.composite if result.composite is not None else frame.color
                cv2.imwrite(str(composites / f"{i:06d}.png"), image[..., ::-1])
    finally:
        if out:
            out.close()
    if errors:
        print(f"median angular error of the dominant light: {np.nanmedian(errors):.1f} deg "
              f"(90th percentile {np.nanpercentile(errors, 90):.1f})", file=sys.stderr)
    if args.out:
        print(f"wrote {_count(n, 'result')} to {args.out}", file=sys.stderr)
    if composites is not None:
        print(f"wrote {_count(n, 'composite')} to {composites}/", file=sys.stderr)
    if environments is not None:
        print(f"wrote {_count(n, 'environment map')} to {environments}/ (OpenEXR, half float"
              f"{', with cubemap faces' if args.cubemap else ''})", file=sys.stderr)
    return 0


_RAY_ADDRESS = re.compile(r"auto|local|(ray://)?[A-Za-z0-9_.\[\]:-]+:[0-9]{1,5}")


def cmd_batch(args: argparse.Namespace) -> int:
    """Exit 0 when every stream is ok or skipped, 1 when any failed, 2 for bad usage."""
    from arlight.batch import BatchOptions, collect_inputs, format_summary, run_batch

    if args.ray is not None and not _RAY_ADDRESS.fullmatch(args.ray):
        raise _BadInput(f"--ray expects a Ray address such as ray://HOST:10001, HOST:6379 or "
                        f"auto, got {args.ray!r}")
    items = collect_inputs(args.inputs)
    options = BatchOptions(preset=args.preset, overrides=tuple(args.set or ()),
                           device=args.device, max_frames=args.max_frames,
                           depth_encoding=args.depth_encoding)
    print(f"arlight batch: {_count(len(items), 'stream')}, preset {args.preset}, results in "
          f"{args.out}/", file=sys.stderr)
    report = run_batch(items, args.out, options, address=args.ray, force=args.force,
                       progress=sys.stderr.isatty() and not args.no_progress)
    for summary in report.streams:
        print(format_summary(summary))
    print(f"arlight batch: {report.count('ok')} ok, {report.count('failed')} failed, "
          f"{report.count('skipped')} skipped; summary in {report.summary_path}",
          file=sys.stderr)
    return 0 if report.ok else 1


def _load_scene(args: argparse.Namespace, image_size: tuple[int, int] = (640, 480)):
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
        raise _BadInput(f"--scene {args.scene}: {exc}") from None


# `--export` names (protocols.EXPORT_LAYOUTS = engine_export.EXPORTERS; tests/test_protocols.py
# checks all three agree), written out so that building the help imports neither
LAYOUT_NAMES = "arcore, webxr, gltf, unity, filament, main_light"


def _parse_exports(text: str) -> list[str]:
    """--export arcore,webxr,...: engine layout names, checked."""
    from arlight.pipeline.engine_export import EXPORTERS

    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in EXPORTERS]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"unknown engine layout {', '.join(bad) or repr(text)}; choose from "
            f"{', '.join(EXPORTERS)} (comma-separated)")
    return names


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


def cmd_bench(args: argparse.Namespace) -> int:
    from arlight.bench import BenchError, parse_sweep, run_benchmark
    from arlight.report import (
        accuracy_table,
        folds_table,
        layout_table,
        map_table,
        speed_table,
        write_report,
    )

    try:
        sweeps = [parse_sweep(text) for text in args.sweep]
        report = run_benchmark(args.data, args.presets, sweeps, args.frames, args.warmup,
                               dict(args.set or []), progress=sys.stderr.isatty(),
                               scene=_load_scene(args), folds=args.folds)
    except BenchError as exc:
        raise _BadInput(str(exc)) from None
    print(speed_table(report))
    for table in (accuracy_table(report), map_table(report), layout_table(report),
                  folds_table(report)):
        if table:
            print()
            print(table)
    written = write_report(report, args.out)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1) + "\n")
        written.append(Path(args.json))
    print(f"arlight bench: wrote {', '.join(str(p) for p in written)}", file=sys.stderr)
    return 0


# --------------------------------------------------------------------------- streaming

class _BadInput(ValueError):
    """A usage error found after parsing (exit code 2)."""


def _check_address(address: str, option: str) -> str:
    if not address.startswith(("tcp://", "ipc://", "inproc://")):
        raise _BadInput(f"{option} expects a ZeroMQ address such as tcp://HOST:PORT, "
                        f"got {address!r}")
    return address


def _parse_size(text: str) -> tuple[int, int]:
    from arlight.sources.synthetic import parse_size

    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def _at_least_1_mb(text: str) -> float:
    value = _positive_float(text)
    if value < 1.0:
        raise argparse.ArgumentTypeError(f"expected at least 1 (MiB), got {text!r}")
    return value


def _int_at_least_2_even(text: str) -> int:
    value = _int_at_least(text, 2)
    if value % 2:
        raise argparse.ArgumentTypeError(f"expected an even number of pixels, got {value}")
    return value


def _positive_int(text: str) -> int:
    return _int_at_least(text, 1)


def _jpeg_quality(text: str) -> int:
    value = _int_at_least(text, 1)
    if value > 100:
        raise argparse.ArgumentTypeError(f"expected 1..100, got {text!r}")
    return value


def _non_negative_int(text: str) -> int:
    return _int_at_least(text, 0)


def _int_at_least(text: str, low: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}")
    return value


def cmd_serve(args: argparse.Namespace) -> int:
    from arlight.protocols import DEFAULT_MAX_MESSAGE_BYTES
    from arlight.server.server import Server, ServerOptions

    _check_address(args.bind, "--bind")
    admin_token = None
    if args.admin_token_file:
        from arlight.server.security import read_token_file

        admin_token = read_token_file(args.admin_token_file, "--admin-token-file")
    logging.getLogger("arlight.server").setLevel(logging.INFO)
    for handler in logging.getLogger().handlers:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: "
                                               "%(message)s"))
    options = ServerOptions(
        bind=args.bind, workers=args.workers, credits=args.credits,
        heartbeat_interval_s=args.heartbeat, session_timeout_s=args.session_timeout,
        log_interval_s=args.log_interval, max_sessions=args.max_sessions,
        max_message_bytes=int(args.max_message_mb * 2**20) if args.max_message_mb
        else DEFAULT_MAX_MESSAGE_BYTES, shutdown_grace_s=args.shutdown_grace,
        keys_dir=args.keys, insecure=args.insecure, admin_token=admin_token,
        **_budget_options(args))
    compute, started_ray = None, False
    if args.ray is not None:  # each session's pipeline in a Ray actor (arlight/ray_serve.py)
        if not _RAY_ADDRESS.fullmatch(args.ray):
            raise _BadInput(f"--ray expects local, auto or a Ray address such as "
                            f"ray://HOST:10001 or HOST:6379, got {args.ray!r}")
        from arlight.ray_serve import RayCompute, connect

        logging.getLogger("arlight.ray_serve").setLevel(logging.INFO)

        ray, started_ray = connect(args.ray)  # BatchUsageError (exit 2): no Ray, no cluster
        compute = RayCompute(ray)
    try:
        return _serve(args, Server(options, process=compute), admin_token)
    finally:
        if compute is not None:
            compute.close()
            if started_ray:
                ray.shutdown()


def _serve(args: argparse.Namespace, server, admin_token: str | None) -> int:
    import signal
    import threading

    server.start()  # InsecureBindError, SecurityError: exit 2
    stop = threading.Event()
    signals_seen = []

    def on_signal(signum, _frame) -> None:
        signals_seen.append(signum)
        if len(signals_seen) > 1:
            print("arlight serve: second signal, exiting now", file=sys.stderr, flush=True)
            os._exit(130)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    keys = (f"; clients need --server-key {Path(args.keys) / 'server.key'} --client-key "
            f"{Path(args.keys) / 'NAME.key_secret'}" if args.keys else "")
    print(f"arlight serve: listening on {server.endpoint} (clients: --server "
          f"{server.connect_address}{keys}); Ctrl-C or SIGTERM stops it", file=sys.stderr,
          flush=True)
    if admin_token is None:  # generated: the operator's only way to learn it
        print(f"arlight serve: admin token (a display with it may watch any session; keep it "
              f"secret, or give your own with --admin-token-file): {server.admin_token}",
              file=sys.stderr, flush=True)
    while not stop.is_set() and not server.wait(0.2):
        pass
    name = signal.Signals(signals_seen[0]).name if signals_seen else "server stopped"
    print(f"arlight serve: {name}: shutting down (in-flight lossless frames finish, "
          f"at most {args.shutdown_grace:g} s)", file=sys.stderr, flush=True)
    server.stop()
    _exit_if_workers_busy(server)
    return 0


def _budget_options(args: argparse.Namespace) -> dict:
    """ServerOptions' budget fields from `arlight serve --frame-deadline/--session-memory-mb`."""
    return {"frame_deadline_s": args.frame_deadline,
            "session_memory_bytes": int(args.session_memory_mb * 2**20)}


WORKER_EXIT_WAIT_S = 2.0  # after the grace, for a worker to reach its next stage boundary


def _exit_if_workers_busy(server) -> None:
    """The server has stopped (every unfinished frame reported to its client); a worker
    still inside a pipeline stage would keep the process alive: exit without it."""
    if server.wait_workers(WORKER_EXIT_WAIT_S):
        return
    print("arlight serve: a worker is still inside a pipeline stage; exiting without it "
          "(its frame was reported to the client as not processed)", file=sys.stderr,
          flush=True)
    logging.shutdown()
    os._exit(0)


def _stream_options(args: argparse.Namespace, source) -> object:
    from arlight.client.capture import StreamOptions

    recorded = source.recorded_config
    mode = args.mode or (recorded.mode if recorded else "live")
    preset = args.preset or (recorded.preset if recorded else "full")
    overrides = dict(recorded.overrides) if recorded and not args.set else {}
    for key, value in args.set or []:
        overrides[key] = value
    composite = args.composite or bool(recorded and recorded.want_composite)
    return StreamOptions(
        server=_check_address(getattr(args, "server", None) or "tcp://127.0.0.1:5555",
                              "--server"),
        session=args.session or (recorded.session if recorded else None),
        client_name=f"arlight-{args.command}", mode=mode, rate=getattr(args, "rate", "max"),
        loop=getattr(args, "loop", False), color_codec=args.color_codec,
        depth_codec=args.depth_codec, jpeg_quality=args.jpeg_quality, preset=preset,
        overrides=overrides, want_composite=composite, timestamps=args.timestamps,
        max_frames=args.max_frames if getattr(args, "loop", False) else None,
        reconnect_timeout_s=getattr(args, "reconnect_timeout", 30.0),
        scene=_load_scene(args), panorama=_panorama_config(args),
        exports=tuple(getattr(args, "export", None) or
                      (recorded.exports if recorded else ())),
        token=_token_of(args), keys=_client_keys(args))


def _client_keys(args: argparse.Namespace):
    """CURVE keys from --server-key and --client-key (both or neither), or None."""
    from arlight.protocols.curve import ClientKeys

    server_key = getattr(args, "server_key", None)
    client_key = getattr(args, "client_key", None)
    if server_key is None and client_key is None:
        return None
    if server_key is None or client_key is None:
        raise _BadInput("give both --server-key DIR/server.key and --client-key "
                        "DIR/NAME.key_secret (made by `arlight keys generate DIR`), or neither")
    return ClientKeys.load(server_key, client_key)


def _token_of(args: argparse.Namespace) -> str | None:
    """The session token from --token or --token-file (not both), or None."""
    token = getattr(args, "token", None)
    token_file = getattr(args, "token_file", None)
    if token and token_file:
        raise _BadInput("give --token or --token-file, not both")
    if token_file:
        from arlight.server.security import read_token_file

        return read_token_file(token_file, "--token-file")
    if token is not None:
        from arlight.protocols import TOKEN_RE

        if not TOKEN_RE.fullmatch(token):
            raise _BadInput("--token expects 16..128 characters from A-Z a-z 0-9 _ - (as "
                            "`arlight stream` prints it)")
    return token


def _panorama_config(args: argparse.Namespace):
    """The Hello's config.panorama from --panorama-operator, --light-source and
    --panorama-from-world (None when none is given: the server's defaults)."""
    from arlight.protocols import PanoramaConfig

    operator = getattr(args, "panorama_operator", None)
    light_source = getattr(args, "light_source", None)
    rotation = getattr(args, "panorama_from_world", None)
    if operator is None and light_source is None and rotation is None:
        return None
    return PanoramaConfig(operator, light_source or "rgbd",
                          rotation or PanoramaConfig().panorama_from_world)


def _rotation_3x3(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 9:
        raise argparse.ArgumentTypeError(f"expected 9 comma-separated numbers (a 3x3 rotation, "
                                         f"row-major), got {text!r}")
    return values


def _open_stream_source(args: argparse.Namespace):
    from arlight.sources.panorama_stream import (
        is_panorama_input,
        panorama_only_source,
        with_panorama,
    )
    from arlight.sources.source import open_source

    if is_panorama_input(args.source):  # a 360-degree video or image: panorama-only frames
        return panorama_only_source(args.source, max_frames=args.max_frames)
    if getattr(args, "panorama", None):
        return with_panorama(_open_stream_source_rgbd(args, open_source), args.panorama)
    return _open_stream_source_rgbd(args, open_source)


def _open_stream_source_rgbd(args: argparse.Namespace, open_source):
    from arlight.sources.camera import parse_camera_spec

    if getattr(args, "loop", False) and parse_camera_spec(args.source) is not None:
        raise _BadInput(f"--loop does not apply to a camera (SOURCE {args.source}): it streams "
                        "until --max-frames N or Ctrl-C")
    source = open_source(args.source, use_poses=args.poses == "groundtruth",
                         max_frames=args.max_frames, depth_encoding=args.depth_encoding,
                         synthetic_size=args.size, synthetic_frames=args.max_frames or 12,
                         camera_fps=args.fps)
    return source  # its notes (defaults chosen for the data) were logged as warnings


def cmd_stream(args: argparse.Namespace) -> int:
    from arlight.client.capture import CaptureClient, StreamError
    from arlight.client.foxglove_sinks import Recorders
    from arlight.protocols.records import pipeline_ms

    # the flags' own checks first: a camera opened (its pipeline started) before a usage
    # error would only be released by its frames
    _token_of(args), _client_keys(args)
    foxglove = _foxglove_address(args)
    source = _open_stream_source(args)
    options = _stream_options(args, source)
    live = None
    if foxglove is not None:
        from arlight.client.foxglove_sinks import FoxgloveStream, LiveSink

        try:
            live = FoxgloveStream(LiveSink(*foxglove, name=f"arlight stream {args.source}"))
        except OSError as exc:
            raise _BadInput(f"--foxglove/--port: {exc}") from None
        print(f"arlight stream: Foxglove WebSocket on ws://{foxglove[0]}:{live.sink.port}",
              file=sys.stderr, flush=True)
    recorder = None
    if args.record:
        from arlight.client.recording import Recorder

        recorder = Recorder(args.record, source=args.source, depth_scale=source.depth_scale)
    to_stdout = args.out == "-"  # the JSON lines on stdout, the per-frame lines on stderr
    out = sys.stdout if to_stdout else open(args.out, "w") if args.out else None  # noqa: SIM115
    total = "loop" if options.loop else str(source.num_frames or "live")

    def on_result(result, receive_time_wall: float) -> None:
        d = result.dominant_direction_camera
        in_server_ms = (result.server_finish_time - result.server_receive_time) * 1e3
        print(f"[{result.seq + 1:>5}/{total}] light(cam)=({d[0]:+.2f}, {d[1]:+.2f}, "
              f"{d[2]:+.2f})  conf={result.confidence.get('value', 0):.2f}  "
              f"pipeline {pipeline_ms(result):5.0f} ms  in server {in_server_ms:5.0f} ms  "
              f"received {result.frames_received}  dropped {result.frames_dropped}"
              + ("" if result.panorama_dominant_direction is None else "  panorama light=("
                 + ", ".join(f"{x:+.2f}" for x in result.panorama_dominant_direction) + ")"),
              file=sys.stderr if to_stdout else sys.stdout, flush=True)
        if out or recorder is not None or live is not None:
            from arlight.protocols import received_record

            record = received_record(result, receive_time_wall)  # with the server's exports
        if recorder is not None:  # the Foxglove channels of the Result beside the frames
            recorder.write_result(result, record)
        if live is not None:
            live.write_result(result, record, time.time_ns())
        if out:
            out.write(json.dumps(record) + "\n")

    sinks = recorder if live is None else Recorders(recorder, live)
    client = CaptureClient(source, options, on_result=on_result, recorder=sinks)
    size = ("panorama only" if source.calibration is None
            else f"{source.calibration.width}x{source.calibration.height}")
    count = _count(source.num_frames, "frame") if source.num_frames else "live"
    print(f"arlight stream: {args.source} ({count}, "
          f"{size}) -> {options.server}, "
          f"session {client.session!r}, {options.mode}, rate {options.rate}, colour "
          f"{options.color_codec}, depth {options.depth_codec}"
          + ("" if source.recorded_config is None else " (recorded frames, sent as recorded)"),
          file=sys.stderr, flush=True)
    keys = (f" --server-key {args.server_key} --client-key DIR/NAME.key_secret"
            if options.keys else "")
    token = (f"--token-file {args.token_file}" if getattr(args, "token_file", None)
             else f"--token {client.token}")  # a token from a file stays off the screen
    print(f"arlight stream: display with: arlight display --server {options.server} --session "
          f"{client.session} {token}{keys}  (the token is a secret: whoever has it sees this "
          "session)", file=sys.stderr, flush=True)
    try:
        summary = client.run()
    except StreamError as exc:
        print(f"arlight stream: error: {exc}", file=sys.stderr)
        refused = "refused" in str(exc)
        return EXIT_BAD_INPUT if refused else 1
    finally:
        if out and not to_stdout:
            out.close()
        if recorder is not None:
            recorder.close()
        if live is not None:
            live.close()
    lat = summary.latencies_s
    drops = (f"{summary.frames_dropped} dropped by the server (live: newest frame wins), "
             f"{summary.frames_not_sent} not sent (send queue full), "
             if options.mode == "live" else "")
    median = f"{np.median(lat) * 1e3:.0f} ms" if lat else "-"
    print(f"arlight stream: {_count(summary.frames_sent, 'frame')} sent, "
          f"{_count(summary.results, 'result')}, "
          f"{drops}{len(summary.errors)} rejected, {summary.reconnects} reconnect(s); "
          f"send-to-result median {median}; {summary.elapsed_s:.1f} s", file=sys.stderr)
    if args.record:
        print(f"recorded {_count(recorder.frames, 'frame')} to {args.record}", file=sys.stderr)
    if summary.errors:
        first = summary.errors[0]
        print(f"arlight stream: {_count(len(summary.errors), 'frame')} rejected by the server, "
              "first: "
              f"{first.code} {first.field or ''}: {first.message}", file=sys.stderr)
        return 1
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    from arlight.client.recording import record

    if not args.out.lower().endswith(".mcap"):
        raise _BadInput(f"--out must name an .mcap file, got {args.out!r}")
    args.server = None
    source = _open_stream_source(args)
    options = _stream_options(args, source)
    t0 = time.perf_counter()

    def on_frame(seq: int, parts) -> None:
        size = sum(len(memoryview(p)) for p in parts)
        print(f"[{seq + 1:>5}/{source.num_frames or 'live'}] {size / 1024:8.1f} KiB",
              flush=True)

    n, session = record(source, args.out, options, on_frame=on_frame)
    print(f"arlight record: wrote {_count(n, 'frame')} (session {session}, "
          f"{options.mode}, colour {options.color_codec}, depth {options.depth_codec}) to "
          f"{args.out} in {time.perf_counter() - t0:.1f} s; replay with `arlight stream "
          f"{args.out} --server tcp://HOST:PORT`", file=sys.stderr)
    return 0


def cmd_display(args: argparse.Namespace) -> int:
    from arlight.client.display import DisplayClient, DisplayError, DisplayOptions, print_line

    _check_address(args.server, "--server")
    if args.video and not args.video.lower().endswith((".mp4", ".m4v", ".mov")):
        raise _BadInput(f"--video expects an .mp4 file, got {args.video!r}")
    if args.export and not args.out:
        raise _BadInput("--export adds to the results.jsonl that --out writes: give --out DIR")
    if args.record and not args.record.lower().endswith(".mcap"):
        raise _BadInput(f"--record must name an .mcap file, got {args.record!r}")
    foxglove = _foxglove_address(args)
    http = None
    if args.http:
        from arlight.client.web_display import parse_http_address

        try:
            http = parse_http_address(args.http)
        except ValueError as exc:
            raise _BadInput(str(exc)) from None
        _warn_if_exposed("--http", *http)
    options = DisplayOptions(server=args.server, session=args.session, out_dir=args.out,
                             exports=tuple(args.export or ()), record=args.record,
                             foxglove=foxglove, http=http,
                             video=args.video, video_fps=args.video_fps,
                             max_results=args.max_results, idle_exit_s=args.idle_exit,
                             follow=args.follow, reconnect_timeout_s=args.reconnect_timeout,
                             token=_token_of(args), keys=_client_keys(args))
    print(f"arlight display: session {args.session!r} on {args.server}"
          + (f", writing {args.out}/results.jsonl and {args.out}/frames/" if args.out else "")
          + (f", video {args.video}" if args.video else "")
          + (f", recording {args.record}" if args.record else ""), file=sys.stderr, flush=True)
    client = DisplayClient(options, printer=print_line)
    try:
        summary = client.run()
    except DisplayError as exc:
        print(f"arlight display: error: {exc}", file=sys.stderr)
        return 1
    info = summary.to_dict()
    lat = info["latency_ms"]
    latency = (f"{lat['kind'].replace('_', '-')} latency median {lat['median']:.0f} ms, p95 "
               f"{lat['p95']:.0f} ms" if lat["median"] is not None else "no latency measured")
    print(f"arlight display: {info['results']} results ({info['composites']} composites), "
          f"{info['fps']:.1f} fps, {latency}; {info['results_missed']} missed; "
          f"{'stream ended' if info['stream_ended'] else 'stopped'}", file=sys.stderr)
    if client.plot_path is not None:
        print(f"arlight display: latency and fps over time in {client.plot_path}",
              file=sys.stderr)
    if args.record:
        print(f"arlight display: recorded {_count(info['results'], 'result')} to "
              f"{args.record} (Foxglove opens it; topics in the README)", file=sys.stderr)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from arlight.demo import run_demo

    t0 = time.perf_counter()
    try:
        summary = run_demo(out_dir=args.out, frames=args.frames, size=args.size,
                           preset=args.preset, video=args.video)
    except RuntimeError as exc:  # StreamError, DisplayError: the loopback service failed
        print(f"arlight demo: error: {exc}", file=sys.stderr)
        return 1
    lat = summary["latency_ms"]
    err = summary["angular_error_deg"]
    stages = ", ".join(f"{k} {v:.0f}" for k, v in summary["timings_ms_median"].items())
    print(f"arlight demo: {summary['results']}/{summary['frames_sent']} results, "
          f"{_figure(summary['fps'], '.1f')} fps delivered (pipeline alone "
          f"{_figure(summary['pipeline_ms_median'], '.0f')} ms/frame = "
          f"{_figure(summary['pipeline_fps'], '.1f')} fps); end-to-end latency median "
          f"{_figure(lat['median'], '.0f')} ms (p95 {_figure(lat['p95'], '.0f')}, lossless: "
          f"includes queueing); median stage ms: {stages}; dominant light error median "
          f"{_figure(err['median'], '.1f')} deg", file=sys.stderr)
    plot = Path(args.out) / "latency.png"
    print(f"wrote {args.out}/frames/ ({summary['composites']} composites), "
          f"{args.out}/results.jsonl, {args.out}/summary.json"
          + (f", {plot} (latency and fps over time)" if plot.exists() else "") + " in "
          f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    complete = summary["results"] == summary["frames_sent"] == args.frames
    if not complete:
        print("arlight demo: error: not every frame came back", file=sys.stderr)
    return 0 if complete else 1


# --------------------------------------------------------------------------- 360 panoramas

def _panorama_size(text: str) -> tuple[int, int]:
    """--diffuse-size WxH: a 2:1 equirectangular size."""
    from arlight.pipeline.ibl import MAX_DIFFUSE_HEIGHT

    width, height = _parse_size(text)
    if width != 2 * height:
        raise argparse.ArgumentTypeError(f"an equirectangular map is twice as wide as high "
                                         f"(e.g. 32x16), got {text!r}")
    if height > MAX_DIFFUSE_HEIGHT:
        raise argparse.ArgumentTypeError(f"at most {2 * MAX_DIFFUSE_HEIGHT}x{MAX_DIFFUSE_HEIGHT} "
                                         f"(brute force grows as the 4th power), got {text!r}")
    return width, height


def cmd_ibl(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from arlight.ibl import SYNTHETIC, frame_record, run, synthetic_panorama, truth_error_deg
    from arlight.pipeline.environment_map import cubemap_from_equirect
    from arlight.pipeline.ibl import IblParams
    from arlight.sources.exr import write_exr
    from arlight.sources.panorama import open_panorama

    params = IblParams(operator=args.operator, diffuse_size=args.diffuse_size)
    renderer = _ibl_renderer(args)  # before any output: a bad --scene stops here
    exr_dir = _output_folder(args.exr, "--exr")
    if args.cubemap and exr_dir is None:
        raise _BadInput("--cubemap writes faces beside the --exr maps: give --exr DIR")
    render_dir = _output_folder(args.render, "--render")
    if args.panorama == SYNTHETIC:
        source = synthetic_panorama(args.max_frames or 8)
        truth = source.truth_directions
    else:
        source = open_panorama(args.panorama, fps=args.fps, max_frames=args.max_frames)
        truth = None
    operator = "none (HDR input)" if source.hdr else args.operator
    total = source.num_frames
    print(f"arlight ibl: {args.panorama} ({source.kind}, "
          f"{_count(total, 'frame') if total else 'frames'}, {source.size[0]}x"
          f"{source.size[1]}{', HDR' if source.hdr else ''}), operator {operator}, diffuse map "
          f"{args.diffuse_size[0]}x{args.diffuse_size[1]}", file=sys.stderr, flush=True)
    try:
        out = open(args.out, "w") if args.out else sys.stdout  # noqa: SIM115
    except OSError as exc:
        source.close()
        raise _BadInput(f"--out {args.out}: cannot write this file ({exc.strerror})") from None
    bar = tqdm(total=total, unit="frame", disable=not sys.stderr.isatty(), dynamic_ncols=True,
               leave=False)
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
                        frame.hdr, max(1, frame.hdr.shape[0] // 2)).items():
                    write_exr(exr_dir / f"{frame.index:06d}_{face}.exr", image)
        if renderer is not None:
            target = render_dir / f"{frame.index:06d}.png"
            if not cv2.imwrite(str(target), renderer.render(frame)[..., ::-1]):
                raise OSError(f"--render {args.render}: cannot write {target}")
        process_ms.append(frame.process_ms)
        bar.update(1)

    t0 = time.perf_counter()
    try:
        n = run(source, params, on_frame)
    finally:
        bar.close()
        source.close()
        if out is not sys.stdout:
            out.close()
        else:
            out.flush()
    elapsed = time.perf_counter() - t0
    wait = ""
    if source.wait_ms and source.decode_ms:  # a video: decoding ran on its own thread
        wait = (f"; waited for decoding {np.median(source.wait_ms):.1f} ms/frame (decode "
                f"{np.median(source.decode_ms):.1f} ms/frame on its own thread)")
    print(f"arlight ibl: {_count(n, 'frame')} in {elapsed:.1f} s, processing median "
          f"{np.median(process_ms) if process_ms else float('nan'):.1f} ms/frame{wait}",
          file=sys.stderr)
    if errors:
        print(f"dominant direction against the HDR original: median {np.median(errors):.1f} "
              f"deg (max {np.max(errors):.1f})", file=sys.stderr)
    if args.out:
        print(f"wrote {_count(n, 'result')} to {args.out}", file=sys.stderr)
    if exr_dir is not None:
        print(f"wrote {_count(n, 'HDR map')} to {exr_dir}/ (NNNNNN.exr, half float)",
              file=sys.stderr)
    if renderer is not None and renderer.timings_ms:
        w, h = renderer.setup.size
        layout = f"stereo side by side, {w}x{h} per eye" if args.stereo else f"{w}x{h}"
        print(f"wrote {_count(n, 'render')} to {render_dir}/ (NNNNNN.png, {layout}, "
              f"{_count(len(renderer.setup.scene.objects), 'object')}); render median "
              f"{np.median([t['Render'] for t in renderer.timings_ms]):.0f} ms/frame",
              file=sys.stderr)
    return 0


MAX_RENDER_PIXELS = 4096 * 4096  # per view of --render: about 1.4 GB of per-pixel buffers


def _ibl_renderer(args: argparse.Namespace):
    """The FrameRenderer of --render (None without it); errors name the flag."""
    if not args.render:
        for flag, given in (("--stereo", args.stereo), ("--scene", args.scene),
                            ("--render-size", args.render_size), ("--view", args.view),
                            ("--roughness", args.roughness)):
            if given:
                raise _BadInput(f"{flag} needs --render DIR (it sets up the rendering)")
        return None
    from arlight.ibl import FrameRenderer, RenderSetup
    from arlight.pipeline import ibl_render
    from arlight.pipeline.virtual_scene import SceneError

    azimuth, elevation = args.view or (180.0, 0.0)
    forward = ibl_render.direction_of(azimuth, elevation)
    if args.scene and args.scene != "demo":
        if args.roughness:
            raise _BadInput("--roughness sets the built-in scene's glossy objects; a --scene "
                            "file gives each object's own material.roughness")
        from arlight.sources.virtual_scene_file import load_virtual_scene

        try:
            scene = load_virtual_scene(args.scene, frame="world")
        except SceneError as exc:
            raise _BadInput(f"--scene {args.scene}: {exc}") from None
    else:
        scene = ibl_render.demo_scene(forward, args.roughness or ibl_render.DEMO_ROUGHNESS)
    size = args.render_size or (ibl_render.EYE_SIZE if args.stereo else ibl_render.MONO_SIZE)
    if size[0] * size[1] > MAX_RENDER_PIXELS:
        raise _BadInput(f"--render-size {size[0]}x{size[1]}: at most {MAX_RENDER_PIXELS} "
                        f"pixels per view (e.g. 4096x4096)")
    setup = RenderSetup(scene, ibl_render.look_along(forward), size, args.fov_deg, args.stereo)
    try:
        return FrameRenderer(setup)
    except SceneError as exc:
        raise _BadInput(f"--scene {args.scene or 'demo'}: {exc}") from None


def _roughness_pair(text: str) -> tuple[float, float]:
    """--roughness R1,R2: the built-in scene's two glossy roughnesses, each in 0.01..0.5."""
    from arlight.pipeline.glossy import check_roughness

    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError(f"expected two numbers R1,R2, got {text!r}")
        return tuple(check_roughness(float(p), "each roughness") for p in parts)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _view_angles(text: str) -> tuple[float, float]:
    """--view AZ,EL in degrees: azimuth 0..360 (the panorama's column u = AZ / 360),
    elevation -89..89."""
    parts = text.split(",")
    try:
        az, el = (float(p) for p in parts) if len(parts) == 2 else (math.nan, math.nan)
    except ValueError:
        az = el = math.nan
    if not (math.isfinite(az) and math.isfinite(el) and -89.0 <= el <= 89.0):
        raise argparse.ArgumentTypeError(f"expected AZ,EL in degrees with EL in [-89, 89], "
                                         f"got {text!r}")
    return az % 360.0, el


def _field_of_view(text: str) -> float:
    value = _positive_float(text)
    if not 1.0 <= value <= 170.0:
        raise argparse.ArgumentTypeError(f"expected degrees in [1, 170], got {text!r}")
    return value


def _output_folder(path: str | None, option: str) -> Path | None:
    """A folder to write into, created; None when not asked for; errors name `option`."""
    if not path:
        return None
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _BadInput(f"{option} {path}: cannot create the folder ({exc.strerror})") from None
    return folder


def _add_ibl_parser(sub) -> None:
    from arlight.pipeline.inverse_tone import DEFAULT_OPERATOR, OPERATORS

    ibl = sub.add_parser(
        "ibl", help="lighting from a 360-degree panorama (video, images): SH per frame",
        description="Image-based lighting from an equirectangular 360-degree LDR video, "
                    "image sequence or image: per frame, inverse tone mapping to an HDR "
                    "radiance map, its SH radiance (16 luminance coefficients and 3x16 RGB, "
                    "the project's convention), the dominant light direction and a "
                    "low-resolution diffuse map; one JSON line per frame, in the panorama's "
                    "frame (+y up; a direction d shows at column atan2(d.x, -d.z) / 2 pi, "
                    "row acos(d.y) / pi, row 0 at the top). HDR inputs (.hdr, .exr) are used "
                    "as they are.")
    ibl.add_argument("panorama", nargs="?", default="synthetic", metavar="PANORAMA",
                     help="a video file (any format OpenCV's FFmpeg backend reads), a folder "
                          "of PNG/JPEG images (sorted by name), one image, or a Radiance "
                          ".hdr / OpenEXR .exr; 'synthetic' (the default): a built-in sky "
                          "turning about +y, with its known light")
    ibl.add_argument("--out", metavar="FILE",
                     help="write the JSON lines to FILE (default: standard output)")
    ops = "; ".join(f"{op.name}: {op.summary}" for op in OPERATORS.values())
    ibl.add_argument("--operator", choices=tuple(OPERATORS), default=DEFAULT_OPERATOR,
                     help=f"inverse tone mapping (default {DEFAULT_OPERATOR}). {ops}")
    ibl.add_argument("--exr", metavar="DIR",
                     help="also write each frame's HDR map as DIR/NNNNNN.exr (OpenEXR, "
                          "equirectangular, linear, half float)")
    ibl.add_argument("--cubemap", action="store_true",
                     help="with --exr, also the six cube faces NNNNNN_px.exr ... of each HDR "
                          "map (OpenGL face order and orientation, half the map's height a "
                          "side)")
    ibl.add_argument("--diffuse-size", type=_panorama_size, default=(32, 16), metavar="WxH",
                     help="size of the diffuse map, brute force over the map area-averaged "
                          "to the same size (default 32x16, the paper's)")
    ibl.add_argument("--fps", type=_positive_float, metavar="F",
                     help="frames per second for the timestamps of an image sequence "
                          "(default 30), or instead of a video's own timestamps")
    ibl.add_argument("--max-frames", type=_positive_int, metavar="N",
                     help="only the first N frames (synthetic: its length, default 8)")
    ibl.add_argument("--render", metavar="DIR",
                     help="render virtual objects lit by each frame into a perspective view "
                          "cut from the panorama: DIR/NNNNNN.png (diffuse map, mirror and "
                          "glossy mipmap sampling)")
    ibl.add_argument("--stereo", action="store_true",
                     help="with --render: a stereo pair for head-mounted displays, side by "
                          "side, 1182x1464 per eye (Oculus DK2), eyes 64 mm apart")
    ibl.add_argument("--scene", metavar="FILE",
                     help="with --render: the virtual objects (a scene file, "
                          "docs/scene-files.md; poses in the panorama's frame, +y up, metres, "
                          "the camera at the origin); default 'demo': 5 built-in objects "
                          "(diffuse, glossy 0.1, mirror, glossy 0.3, a half-glossy torus) 1.6 m "
                          "ahead")
    ibl.add_argument("--view", type=_view_angles, metavar="AZ,EL",
                     help="with --render: the view direction in degrees, azimuth (the "
                          "panorama's column u = AZ / 360) and elevation (default 180,0: the "
                          "centre of the panorama, +z)")
    ibl.add_argument("--fov-deg", type=_field_of_view, default=75.0, metavar="DEG",
                     help="with --render: horizontal field of view (default 75)")
    ibl.add_argument("--render-size", type=_parse_size, metavar="WxH",
                     help="with --render: the view's size, per eye with --stereo (default "
                          "1280x720, stereo 1182x1464)")
    ibl.add_argument("--roughness", type=_roughness_pair, metavar="R1,R2",
                     help="with --render and the built-in scene: its two glossy spheres' "
                          "roughness, each in 0.01..0.5 (default 0.1,0.3)")
    ibl.set_defaults(func=cmd_ibl)


def _count(n: int, noun: str) -> str:
    """'1 frame', '2 frames'."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _figure(value: float | None, spec: str) -> str:
    """A number for a summary line; '-' where nothing was measured."""
    return "-" if value is None else format(value, spec)


def _add_source_options(p: argparse.ArgumentParser) -> None:
    from arlight.protocols import (
        COLOR_CODECS,
        DEFAULT_COLOR_CODEC,
        DEFAULT_DEPTH_CODEC,
        DEFAULT_JPEG_QUALITY,
        DEPTH_CODECS,
    )

    p.add_argument("source", metavar="SOURCE",
                   help="'synthetic' (the built-in scene), a TUM / Open3D-Redwood / 7-Scenes "
                        "folder, a recording FILE.mcap (sent exactly as recorded), or a "
                        "camera: depthai[:DEVICE_ID] (Luxonis OAK), openni2[:URI] or FILE.oni "
                        "(OpenNI2 device or recording), realsense[:SERIAL] (Intel RealSense); "
                        "cameras need their extra: pip install 'arlight[depthai]' etc.")
    p.add_argument("--session", metavar="NAME", help="session name, [A-Za-z0-9_.-]{1,64} "
                   "(default: the source's name plus 4 random hex digits; a recording: its own)")
    p.add_argument("--mode", choices=("live", "lossless"),
                   help="live: latest frame wins, drops counted (default); lossless: every "
                        "frame processed once, in order (for recorded streams)")
    p.add_argument("--color-codec", choices=COLOR_CODECS, default=DEFAULT_COLOR_CODEC,
                   help=f"colour codec (default {DEFAULT_COLOR_CODEC}; png/raw are lossless)")
    p.add_argument("--depth-codec", choices=DEPTH_CODECS, default=DEFAULT_DEPTH_CODEC,
                   help=f"depth codec, all lossless (default {DEFAULT_DEPTH_CODEC})")
    p.add_argument("--jpeg-quality", type=_jpeg_quality, default=DEFAULT_JPEG_QUALITY, metavar="Q",
                   help=f"JPEG quality 1..100 (default {DEFAULT_JPEG_QUALITY})")
    p.add_argument("--preset", choices=("full", "fast", "mobile"),
                   help="the session's pipeline preset (default full; a recording: its own)")
    p.add_argument("--set", action="append", type=_parse_override, metavar="KEY=VALUE",
                   help="override a pipeline Config field for the session")
    p.add_argument("--composite", action="store_true",
                   help="ask the server for composited frames (the input frame with the "
                        "estimated light drawn in), for display clients")
    p.add_argument("--poses", choices=("groundtruth", "track"), default="track",
                   help="'groundtruth': send the data set's camera poses (tracking is then "
                        "skipped); 'track' (default): the server tracks the camera")
    p.add_argument("--max-frames", type=_positive_int, metavar="N", help="only the first N frames "
                   "(with --loop: N frames in total); synthetic: the number of frames (12)")
    p.add_argument("--depth-encoding", choices=("tum", "mm", "sun", "nyu"),
                   help="depth encoding of a data set (default: from its layout)")
    p.add_argument("--size", type=_parse_size, default=(640, 480), metavar="WxH",
                   help="image size of the synthetic scene or of a camera (default 640x480)")
    p.add_argument("--fps", type=_positive_float, default=30.0, metavar="F",
                   help="a camera's frame rate in Hz (default 30)")
    p.add_argument("--timestamps", choices=("capture", "source"),
                   help="frame timestamps: 'capture' = time.time() when sent (end-to-end "
                        "latency measurable; default in live mode), 'source' = the data set's "
                        "(default in lossless mode); recordings keep theirs")
    _add_scene_options(p)


def _add_scene_options(p: argparse.ArgumentParser) -> None:
    """--scene and --scene-frame, shared by estimate and stream."""
    p.add_argument("--scene", metavar="FILE",
                   help="virtual objects to render into the frames: a scene file (JSON or "
                        "TOML, see docs/scene-files.md; e.g. a data set's ar/virtual_scene."
                        "json), or 'demo' (a sphere and a torus standing on the detected "
                        "ground)")
    p.add_argument("--scene-frame", choices=("world", "cam0"),
                   help="frame of the scene file's poses: 'world' = the data set's pose frame "
                        "(default with --poses groundtruth), 'cam0' = the first camera "
                        "(default when tracking, whose world is the first camera)")


def _add_reconnect_timeout(p: argparse.ArgumentParser) -> None:
    """--reconnect-timeout, shared by the two clients (stream, display)."""
    p.add_argument("--reconnect-timeout", type=_positive_float, default=30.0, metavar="S",
                   help="give up after S seconds without a server (default 30)")


def _add_streaming_parsers(sub) -> None:
    """The service's subcommands: serve, stream, record, display, demo."""
    _add_serve_parser(sub)
    _add_stream_parser(sub)
    _add_record_parser(sub)
    _add_display_parser(sub)
    _add_demo_parser(sub)
    _add_keys_parser(sub)


def _add_serve_parser(sub) -> None:
    from arlight.server.server import DEFAULT_BIND, ServerOptions

    defaults = ServerOptions()
    serve = sub.add_parser(
        "serve", help="run the streaming server (sessions, live/lossless delivery)",
        description="Run the arlight streaming server: capture clients stream RGB-D frames "
                    "into named sessions (each with its own pipeline state); Results go back "
                    "to the capture client and to every display client subscribed to the "
                    "session. Logs each session's frame rate and latency. SIGINT/SIGTERM shut "
                    "it down cleanly.")
    serve.add_argument("--bind", default=DEFAULT_BIND, metavar="ADDRESS",
                       help=f"ZeroMQ address to listen on (default {DEFAULT_BIND}: this "
                            "machine only); any other address needs --keys (or --insecure)")
    serve.add_argument("--keys", metavar="DIR",
                       help="CURVE keys from `arlight keys generate DIR`: encrypt the traffic "
                            "and admit only clients whose public keys are in DIR/authorized/")
    serve.add_argument("--insecure", action="store_true",
                       help="allow a --bind other machines can reach without --keys (no "
                            "encryption, any client admitted; warned at every start)")
    serve.add_argument("--admin-token-file", metavar="FILE",
                       help="a file holding the admin token (a display with it may watch any "
                            "session); default: a random one, printed at start")
    serve.add_argument("--workers", type=_positive_int, default=defaults.workers,
                       help=f"worker threads running the pipeline (default {defaults.workers}; "
                            "one frame per session at a time)")
    serve.add_argument("--credits", type=_positive_int, default=defaults.credits,
                       help="lossless credit window: frames a client may have unacknowledged "
                            f"(default {defaults.credits})")
    serve.add_argument("--heartbeat", type=_positive_float,
                       default=defaults.heartbeat_interval_s, metavar="S",
                       help=f"heartbeat interval in seconds; a peer silent for "
                            f"{defaults.liveness} intervals is dead "
                            f"(default {defaults.heartbeat_interval_s:g})")
    serve.add_argument("--session-timeout", type=_positive_float,
                       default=defaults.session_timeout_s, metavar="S",
                       help="a session without frames for S seconds expires and frees its "
                            f"memory (default {defaults.session_timeout_s:g})")
    serve.add_argument("--log-interval", type=_positive_float, default=defaults.log_interval_s,
                       metavar="S", help="seconds between per-session rate/latency log lines "
                                         f"(default {defaults.log_interval_s:g})")
    serve.add_argument("--max-sessions", type=_positive_int, default=defaults.max_sessions,
                       help=f"most concurrent sessions (default {defaults.max_sessions})")
    serve.add_argument("--max-message-mb", type=_positive_float, metavar="MB",
                       help="largest message accepted, MiB (default "
                            f"{defaults.max_message_bytes / 2**20:g}); a peer sending more is "
                            "disconnected")
    serve.add_argument("--shutdown-grace", type=float, default=defaults.shutdown_grace_s,
                       metavar="S", help="on SIGINT/SIGTERM, time given to lossless frames "
                                         "already received (default "
                                         f"{defaults.shutdown_grace_s:g}); the rest are "
                                         "reported to their clients")
    _add_budget_options(serve, defaults)
    serve.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                       help="run each session's pipeline in a Ray actor (pip install "
                            "'arlight[ray]'): --ray or --ray local starts a local Ray, "
                            "--ray auto joins this machine's cluster, --ray ray://HOST:10001 "
                            "connects to one; the socket and I/O stay in this process. A lost "
                            "actor's frames are reported retryable and go to a new actor "
                            "(a fresh volume)")
    serve.set_defaults(func=cmd_serve)


def _add_budget_options(serve, defaults) -> None:
    """`arlight serve`'s budgets (README, "Limits and budgets")."""
    serve.add_argument("--frame-deadline", type=_positive_float,
                       default=defaults.frame_deadline_s, metavar="S",
                       help="a frame still in the pipeline after S seconds is abandoned at "
                            "the next stage (Error deadline), and a session whose settings "
                            "could not meet it is refused at Hello (default "
                            f"{defaults.frame_deadline_s:g})")
    serve.add_argument("--session-memory-mb", type=_at_least_1_mb,
                       default=defaults.session_memory_bytes / 2**20, metavar="MB",
                       help="memory budget of one session (image buffers, volume): a Hello "
                            "over it is refused; the sessions' memory is at most "
                            "--max-sessions x this (default "
                            f"{defaults.session_memory_bytes / 2**20:g})")


def _add_stream_parser(sub) -> None:
    stream = sub.add_parser(
        "stream", help="stream a source to a server and print the lighting per frame",
        description="Stream RGB-D frames to an arlight server (`arlight serve`) and print "
                    "the Result of each frame. Reconnects if the server restarts (lossless "
                    "mode re-sends unacknowledged frames, so none is lost).")
    _add_source_options(stream)
    stream.add_argument("--server", default="tcp://127.0.0.1:5555", metavar="ADDRESS",
                        help="the server, tcp://HOST:PORT (default tcp://127.0.0.1:5555)")
    stream.add_argument("--rate", choices=("native", "max"), default="native",
                        help="native: at the source's own frame rate (default); max: as fast "
                             "as the mode allows")
    stream.add_argument("--loop", action="store_true", help="start over at the end (until "
                        "--max-frames or Ctrl-C)")
    stream.add_argument("--out", metavar="FILE",
                        help="also write the Results as JSON lines ('-': standard output; "
                             "the per-frame lines then go to standard error)")
    stream.add_argument("--export", type=_parse_exports, metavar="LAYOUTS",
                        help="ask the server for the light in these engines' layouts in every "
                             "Result (\"exports\", also in the --out lines and what displays "
                             "receive; camera frame, the engine's axes): comma-separated from "
                             + LAYOUT_NAMES)
    stream.add_argument("--record", metavar="FILE.mcap",
                        help="also record the stream as sent to an MCAP file")
    _add_foxglove_options(stream, "the camera (colour, depth, calibration, pose) and the "
                                  "Results that come back")
    from arlight.pipeline.inverse_tone import OPERATORS

    stream.add_argument("--panorama", metavar="FILE",
                        help="also send this LDR 360-degree video (or images) with the RGB-D "
                             "frames, paired by index; a SOURCE that is itself a video or "
                             "image streams panorama-only frames")
    stream.add_argument("--panorama-operator", choices=tuple(OPERATORS), metavar="NAME",
                        help="the session's inverse tone mapping operator for the panorama "
                             f"({', '.join(OPERATORS)}; default: the server's)")
    stream.add_argument("--light-source", choices=("rgbd", "panorama"),
                        help="which light renders the virtual objects when a frame has both "
                             "RGB-D and a panorama (default rgbd)")
    stream.add_argument("--panorama-from-world", type=_rotation_3x3, metavar="R00,...,R22",
                        help="3x3 rotation, row-major: d_panorama = R d_world (default "
                             "identity)")
    stream.add_argument("--token", metavar="T",
                        help="the session token (16..128 of A-Z a-z 0-9 _ -): a new session "
                             "takes it, resuming an existing one needs it; default random, "
                             "printed for the displays")
    stream.add_argument("--token-file", metavar="FILE", help="read --token from FILE")
    _add_key_options(stream)
    _add_reconnect_timeout(stream)
    stream.set_defaults(func=cmd_stream)


def _add_key_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--server-key", metavar="DIR/server.key",
                   help="the server's public CURVE key (for a server run with --keys DIR)")
    p.add_argument("--client-key", metavar="DIR/NAME.key_secret",
                   help="this client's CURVE key pair; its public half must be in the "
                        "server's DIR/authorized/")


def _add_record_parser(sub) -> None:
    rec = sub.add_parser(
        "record", help="record a source as a stream into one MCAP file (no server needed)",
        description="Write the stream `arlight stream SOURCE` would send (session config, "
                    "frames as encoded, timestamps) to one MCAP file; `arlight stream "
                    "FILE.mcap` replays it bit-exactly.")
    _add_source_options(rec)
    rec.add_argument("--out", required=True, metavar="FILE.mcap", help="the MCAP file to write")
    rec.set_defaults(func=cmd_record)


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port 0..65535, got {text!r}")
    return value


def _add_foxglove_options(parser, what: str) -> None:
    """--foxglove, --port, --foxglove-host (stream and display)."""
    parser.add_argument("--foxglove", action="store_true",
                        help=f"serve {what} live over Foxglove's WebSocket protocol (open "
                             "ws://HOST:PORT in the Foxglove app)")
    parser.add_argument("--port", type=_port, metavar="P",
                        help="with --foxglove: its port (default 8765; 0 = any free port)")
    parser.add_argument("--foxglove-host", default="127.0.0.1", metavar="HOST",
                        help="with --foxglove: the address to bind (default 127.0.0.1; "
                             "0.0.0.0 for other machines)")


def _foxglove_address(args: argparse.Namespace) -> tuple[str, int] | None:
    """(host, port) of --foxglove, or None; --port without --foxglove is refused."""
    if args.port is not None and not args.foxglove:
        raise _BadInput("--port is the port of --foxglove: give --foxglove too")
    if not args.foxglove:
        return None
    address = (args.foxglove_host, 8765 if args.port is None else args.port)
    _warn_if_exposed("--foxglove-host", *address)
    return address


def _warn_if_exposed(flag: str, host: str, port: int) -> None:
    """A viewer served beyond loopback has neither keys nor token: say so (README,
    "Security")."""
    from arlight.server.security import is_loopback

    if not is_loopback(f"tcp://{host}:{port}"):
        print(f"arlight: warning: {flag} {host}: what it shows (composite, light; a stream: "
              f"the camera) is served on port {port} to anyone who can reach this machine, "
              f"without keys or token (README, \"Security\")", file=sys.stderr, flush=True)


def _add_display_parser(sub) -> None:
    disp = sub.add_parser(
        "display", help="subscribe to a session: write its Results and composites, print fps",
        description="The thin display client: receives the Results of one session from the "
                    "server, prints frames per second and latency, and writes results.jsonl, "
                    "composited frames, a video and latency.png; records the Results to MCAP "
                    "(--record), serves them to Foxglove (--foxglove) and to a browser "
                    "(--http). Exits when the stream ends.")
    disp.add_argument("--server", required=True, metavar="ADDRESS",
                      help="the server, tcp://HOST:PORT")
    disp.add_argument("--session", required=True, metavar="NAME",
                      help="the session to show (as printed by `arlight stream`)")
    disp.add_argument("--out", metavar="DIR",
                      help="write DIR/results.jsonl and DIR/frames/NNNNNN.png")
    disp.add_argument("--export", type=_parse_exports, metavar="LAYOUTS",
                      help="with --out, also the light in these engines' layouts in each "
                           "results.jsonl line (\"exports\"; camera frame, the engine's "
                           "axes): comma-separated from " + LAYOUT_NAMES)
    disp.add_argument("--video", metavar="FILE.mp4", help="write the composites as a video")
    disp.add_argument("--video-fps", type=_positive_float, default=15.0, metavar="FPS",
                      help="frame rate written into the video (default 15)")
    disp.add_argument("--max-results", type=_positive_int, metavar="N",
                      help="exit after N results")
    disp.add_argument("--idle-exit", type=_positive_float, metavar="S",
                      help="exit after S seconds without a result")
    disp.add_argument("--follow", action="store_true",
                      help="keep waiting when the stream ends (for the next stream: it must "
                           "use the same token, `arlight stream --token-file F`)")
    disp.add_argument("--record", metavar="FILE.mcap",
                      help="record the Results to an MCAP file: as received (/arlight/result) "
                           "and in Foxglove's schemas (composite, light, lighting JSON, /tf)")
    _add_foxglove_options(disp, "the session's Results (composite, light, lighting, pose)")
    disp.add_argument("--http", metavar="[HOST:]PORT",
                      help="serve a live page for a browser on this address (HOST default "
                           "127.0.0.1; 0.0.0.0:PORT for a tablet on the network)")
    disp.add_argument("--token", metavar="T",
                      help="the session's token, as `arlight stream` prints it (or the "
                           "server's admin token); without it the server refuses")
    disp.add_argument("--token-file", metavar="FILE", help="read --token from FILE (keeps "
                      "it out of the process list)")
    _add_key_options(disp)
    _add_reconnect_timeout(disp)
    disp.set_defaults(func=cmd_display)


def _add_keys_parser(sub) -> None:
    keys = sub.add_parser(
        "keys", help="make CURVE keys for `arlight serve --keys` and its clients",
        description="Make ZeroMQ CURVE certificates (zmq.auth format). `generate DIR` writes "
                    "DIR/server.key (public: give it to clients), DIR/server.key_secret "
                    "(the server's only), DIR/client.key and DIR/client.key_secret (a "
                    "client's pair) and DIR/authorized/client.key (the keys the server "
                    "admits). `add DIR NAME` makes another client's pair and authorises it.")
    verbs = keys.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    gen = verbs.add_parser("generate", help="server and first client keys in DIR")
    gen.add_argument("dir", metavar="DIR")
    add = verbs.add_parser("add", help="another client's keys, authorised in DIR/authorized/")
    add.add_argument("dir", metavar="DIR")
    add.add_argument("name", metavar="NAME", help="the client's name (letters, digits, _ . -)")
    keys.set_defaults(func=cmd_keys)


def cmd_keys(args: argparse.Namespace) -> int:
    from arlight.server.security import add_client_key, generate_keys

    if args.keys_command == "generate":
        written = generate_keys(args.dir)
        d = Path(args.dir)
        print(f"arlight keys: wrote {', '.join(str(p) for p in written)}\n"
              f"  server:  arlight serve --bind tcp://*:5555 --keys {d}\n"
              f"  clients: --server-key {d / 'server.key'} --client-key "
              f"{d / 'client.key_secret'} (copy both files to the client; *.key_secret files "
              "are secrets)", file=sys.stderr)
    else:
        written = add_client_key(args.dir, args.name)
        print(f"arlight keys: wrote {', '.join(str(p) for p in written)}; restart the "
              f"server to admit it (client: --client-key {written[1]})", file=sys.stderr)
    return 0


def _add_demo_parser(sub) -> None:
    demo = sub.add_parser(
        "demo", help="server + capture + display on this machine: the built-in scene end to end",
        description="Start a server, stream the built-in synthetic scene to it over loopback "
                    "in lossless mode, run a display client, and write DIR: frames/ "
                    "(composites), results.jsonl and summary.json (fps, latency, per-stage "
                    "timings, light direction error).")
    demo.add_argument("--out", default="out", metavar="DIR", help="output folder (default out)")
    demo.add_argument("--frames", type=_positive_int, default=24,
                      help="frames of the synthetic scene (default 24)")
    demo.add_argument("--size", type=_parse_size, default=(320, 240), metavar="WxH",
                      help="image size (default 320x240)")
    demo.add_argument("--preset", choices=("full", "fast", "mobile"), default="fast",
                      help="pipeline preset (default fast)")
    demo.add_argument("--video", metavar="FILE.mp4", help="also write the composites as a video")
    demo.set_defaults(func=cmd_demo)


def _add_batch_parser(sub) -> None:
    batch = sub.add_parser(
        "batch", help="estimate the lighting of many recordings / sequences on Ray",
        description="Run the pipeline over many streams on Ray, one actor (and one pipeline "
                    "state) per stream: a local Ray, or the cluster at --ray ADDRESS. Each "
                    "stream's JSON lines (those `arlight estimate --out` writes) go to "
                    "DIR/NAME.jsonl, written whole or not at all; DIR/batch.json lists each "
                    "stream as ok, failed (with the reason) or skipped. A rerun skips the "
                    "streams already finished. Exit code 1 when any stream failed. Needs "
                    "pip install 'arlight[ray]'.")
    batch.add_argument("inputs", nargs="*", metavar="INPUT",
                       help="recordings (FILE.mcap, from `arlight record`), sequence folders "
                            "(as `arlight estimate` reads), or folders of recordings")
    batch.add_argument("--ray", metavar="ADDRESS",
                       help="a running Ray cluster, e.g. ray://HOST:10001 or auto (default: "
                            "start a local Ray)")
    batch.add_argument("--out", default="batch-out", metavar="DIR",
                       help="results folder (default batch-out)")
    batch.add_argument("--preset", choices=("full", "fast", "mobile"), default="full",
                       help="speed/accuracy preset of every stream (default full); also the "
                            "CPUs per actor: full 2, fast 1, mobile 1")
    batch.add_argument("--device", help="Open3D device of every stream's volume, e.g. CUDA:0 "
                                         "(then each actor asks Ray for one GPU; default CPU:0)")
    batch.add_argument("--set", action="append", type=_parse_override, metavar="KEY=VALUE",
                       help="override a pipeline Config field for every stream")
    batch.add_argument("--max-frames", type=_positive_int, metavar="N",
                       help="only the first N frames of each stream")
    batch.add_argument("--depth-encoding", choices=("tum", "mm", "sun", "nyu"),
                       help="depth encoding of the sequence folders (default: from the layout)")
    batch.add_argument("--force", action="store_true",
                       help="redo streams whose results exist (default: skip them)")
    batch.add_argument("--no-progress", action="store_true", help="no progress bar")
    batch.set_defaults(func=cmd_batch)


def _add_synth_parser(sub) -> None:
    from arlight.synth.command import add_parser

    add_parser(sub)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="arlight", description="Probeless light estimation from RGB-D (recorded data "
                                    "sets, recordings and the built-in scene), in-process or "
                                    "as a streaming service. Rendering of virtual objects and "
                                    "live camera sources are not there yet.")
    parser.add_argument("--version", action="version", version=f"arlight {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log details (warnings "
                        "about defaults chosen for the data are shown either way)")
    parser.add_argument("--open3d-threads", type=_positive_int, metavar="N",
                        help="CPU threads for Open3D (volume, ray cast, tracking); default: "
                             "all cores. 1 makes tracked poses reproducible run to run, at the "
                             "cost of a slower Surface stage")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    est = sub.add_parser(
        "estimate", help="estimate the lighting of an RGB-D sequence, one JSON line per frame",
        description="Estimate spherical-harmonics lighting per frame. PATH is a TUM RGB-D "
                    "folder, an Open3D/Redwood folder, a 7-Scenes folder, a colour image "
                    "(with --depth, or a *depth* file beside it), or 'synthetic' (the "
                    "built-in scene with known light; the default).")
    est.add_argument("path", nargs="?", default="synthetic", metavar="PATH")
    est.add_argument("--preset", choices=("full", "fast", "mobile"), default="full",
                     help="speed/accuracy preset (default: full, the paper's 'Ours')")
    est.add_argument("--poses", choices=("groundtruth", "track"), default="track",
                     help="'groundtruth': use the data set's camera poses and skip tracking; "
                          "'track' (default): frame-to-model tracking")
    est.add_argument("--rgb", action="store_true", help="also estimate one SH per RGB channel")
    est.add_argument("--out", metavar="FILE", help="write results as JSON lines to FILE")
    est.add_argument("--max-frames", type=_positive_int, metavar="N",
                     help="only the first N frames (synthetic: its length, default 12)")
    est.add_argument("--depth", metavar="FILE", help="depth image for a single colour image")
    est.add_argument("--depth-encoding", choices=("tum", "mm", "sun", "nyu"),
                     help="depth encoding (default: from the data set's layout or file name)")
    est.add_argument("--device", help="Open3D device for the volume, e.g. CUDA:0 (default CPU:0)")
    est.add_argument("--set", action="append", type=_parse_override, metavar="KEY=VALUE",
                     help="override any Config field, e.g. --set rt_directions=128")
    _add_scene_options(est)
    est.add_argument("--composite-out", metavar="DIR",
                     help="write each frame's composite (the virtual objects rendered in) as "
                          "DIR/NNNNNN.png, NNNNNN the frame's index; without --scene, the "
                          "input frames")
    est.add_argument("--export", type=_parse_exports, metavar="LAYOUTS",
                     help="also put the light in these engines' layouts into each JSON line "
                          "(\"exports\"; camera frame, the engine's axes): comma-separated "
                          "from " + LAYOUT_NAMES)
    est.add_argument("--env-exr", metavar="DIR",
                     help="write the estimated light per frame as an equirectangular HDR map "
                          "DIR/NNNNNN.exr (OpenEXR half float, world frame, +y up)")
    est.add_argument("--env-size", type=_int_at_least_2_even, default=256, metavar="W",
                     help="width of the --env-exr maps in pixels (even; default 256)")
    est.add_argument("--cubemap", action="store_true",
                     help="with --env-exr, also write the six cube faces NNNNNN_px.exr ... "
                          "(OpenGL face order and orientation, W / 4 pixels a side)")
    est.set_defaults(func=cmd_estimate)

    bench = sub.add_parser(
        "bench", help="speed and accuracy per configuration: report.md, report.json, trade.png",
        description="Run each configuration (presets, comparators, sweep points) over the same "
                    "frames and report per-stage milliseconds (the rows of the paper's table "
                    "1, median and spread, warm-up excluded), frames per second and, where the "
                    "data has ground truth, the angular error of the dominant light against the "
                    "whole sphere and the upper hemisphere, the SH error and the diffuse-shading "
                    "error. Poses come from the data (tracking skipped).")
    bench.add_argument("data", nargs="*", default=["synthetic"], metavar="DATA",
                       help="'synthetic' (the built-in scene, default), 'synthetic-held' (the "
                            "same scene seen by a camera held still, the sun moving half-way: "
                            "what a still camera's reuse saves), a sequence folder with "
                            "lighting_gt.json, or a folder of them (../shared/data/synthetic)")
    bench.add_argument("--presets", nargs="+", default=["full", "fast"],
                       choices=("full", "fast", "mobile", "baseline", "raycast"),
                       help="configurations to compare (default full fast; baseline = full "
                            "without visibility, K = 1; raycast = full with object-space "
                            "visibility, rays against the volume's mesh, rt_method=raycast)")
    bench.add_argument("--sweep", action="append", default=[], metavar="KEY=V1,V2,...",
                       help="a curve: the first preset with KEY set to each value in turn "
                            "(any --set key, or size=WxH,... for the built-in scene); repeatable")
    bench.add_argument("--set", action="append", type=_parse_override, metavar="KEY=VALUE",
                       help="override a pipeline Config field for every configuration")
    bench.add_argument("--frames", type=_positive_int, metavar="N",
                       help="timed frames of the built-in scene (default 8) / at most N frames "
                            "of each sequence (default all)")
    bench.add_argument("--warmup", type=_non_negative_int, default=2, metavar="N",
                       help="frames per sequence left out of the timings (JIT, caches; default 2)")
    bench.add_argument("--out", default="bench-report", metavar="DIR",
                       help="write DIR/report.json, report.md, trade.png (default bench-report)")
    bench.add_argument("--json", metavar="FILE", help="also write report.json to FILE")
    bench.add_argument("--folds", action="store_true",
                       help="leave one environment map out: for each map, the configuration "
                            "(preset or sweep point) with the lowest median over the OTHER "
                            "maps, and its error on the held-out map; shows whether choosing "
                            "a configuration generalises to unseen lighting")
    bench.add_argument("--scene", metavar="FILE",
                       help="render these virtual objects into every frame, so the Rendering "
                            "stage is timed: a scene file (docs/scene-files.md) or 'demo' (a "
                            "sphere and a torus on the detected ground); poses in each "
                            "sequence's pose frame")
    bench.set_defaults(func=cmd_bench)
    _add_batch_parser(sub)
    _add_ibl_parser(sub)
    _add_synth_parser(sub)
    _add_streaming_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    from arlight.pipeline.pipeline import FrameError
    from arlight.pipeline.runtime import configure_process
    from arlight.sources.errors import DatasetError

    configure_process(args.open3d_threads)  # once per process, before any Pipeline
    try:
        return args.func(args)
    except (DatasetError, FrameError, ValueError, OSError) as exc:  # incl. ProtocolError,
        # RecordingError and _BadInput (all ValueError)
        print(f"arlight {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
