"""`arlight stream`: stream a source to a server and print the lighting of each frame."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from arlight.cli.client_options import (
    add_foxglove_options,
    add_key_options,
    add_probe_options,
    add_reconnect_timeout,
    add_source_options,
    client_keys,
    foxglove_address,
    open_stream_source,
    probe_request,
    stream_options,
    token_of,
)
from arlight.cli.common import (
    EXIT_BAD_INPUT,
    LAYOUT_NAMES,
    BadInput,
    count,
    engine_layouts,
    output_folder,
    rotation_3x3,
)
from arlight.cli.probe_files import probe_record, write_probe_files
from arlight.cli.stop_signals import finalised_on_sigterm
from arlight.client.stop_signals import uninterrupted
from arlight.pipeline.inverse_tone import OPERATORS
from arlight.protocols import received_record
from arlight.protocols.records import pipeline_ms


def add_parser(sub) -> None:
    stream = sub.add_parser(
        "stream",
        help="stream a source to a server and print the lighting per frame",
        description="Stream RGB-D frames to an arlight server (`arlight serve`) and print "
        "the Result of each frame. Reconnects if the server restarts (lossless "
        "mode re-sends unacknowledged frames, so none is lost).",
    )
    add_source_options(stream)
    stream.add_argument(
        "--server",
        default="tcp://127.0.0.1:5555",
        metavar="ADDRESS",
        help="the server, tcp://HOST:PORT (default tcp://127.0.0.1:5555)",
    )
    stream.add_argument(
        "--rate",
        choices=("native", "max"),
        default="native",
        help="native: at the source's own frame rate (default); max: as fast as the mode allows",
    )
    stream.add_argument(
        "--loop", action="store_true", help="start over at the end (until --max-frames or Ctrl-C)"
    )
    stream.add_argument(
        "--out",
        metavar="FILE",
        help="also write the Results as JSON lines ('-': standard output; "
        "the per-frame lines then go to standard error)",
    )
    stream.add_argument(
        "--export",
        type=engine_layouts,
        metavar="LAYOUTS",
        help="ask the server for the light in these engines' layouts in every "
        'Result ("exports", also in the --out lines and what displays '
        "receive; camera frame, the engine's axes): comma-separated from " + LAYOUT_NAMES,
    )
    stream.add_argument(
        "--record", metavar="FILE.mcap", help="also record the stream as sent to an MCAP file"
    )
    stream.add_argument(
        "--record-processed",
        action="store_true",
        help="with --record: record only the frames the server processed, each beside its "
        "Result (live mode sends more frames than the server takes; default: every frame "
        "sent)",
    )
    add_probe_options(stream)
    add_foxglove_options(
        stream, "the camera (colour, depth, calibration, pose) and the Results that come back"
    )
    stream.add_argument(
        "--panorama",
        metavar="FILE",
        help="also send this LDR 360-degree video (or images) with the RGB-D "
        "frames, paired by index; a SOURCE that is itself a video or "
        "image streams panorama-only frames",
    )
    stream.add_argument(
        "--panorama-operator",
        choices=tuple(OPERATORS),
        metavar="NAME",
        help="the session's inverse tone mapping operator for the panorama "
        f"({', '.join(OPERATORS)}; default: the server's)",
    )
    stream.add_argument(
        "--light-source",
        choices=("rgbd", "panorama"),
        help="which light renders the virtual objects when a frame has both "
        "RGB-D and a panorama (default rgbd)",
    )
    stream.add_argument(
        "--panorama-from-world",
        type=rotation_3x3,
        metavar="R00,...,R22",
        help="3x3 rotation, row-major: d_panorama = R d_world (default identity)",
    )
    stream.add_argument(
        "--token",
        metavar="T",
        help="the session token (16..128 of A-Z a-z 0-9 _ -): a new session "
        "takes it, resuming an existing one needs it; default random, "
        "printed for the displays",
    )
    stream.add_argument("--token-file", metavar="FILE", help="read --token from FILE")
    add_key_options(stream)
    add_reconnect_timeout(stream)
    stream.set_defaults(func=run)


def recording_size(path: str, elapsed_s: float) -> str:
    """ ", X MiB (Y MiB per minute)" of a finished recording, or "" when unreadable."""
    try:
        mib = os.path.getsize(path) / 2**20
    except OSError:
        return ""
    per_minute = f" ({mib / elapsed_s * 60.0:.1f} MiB per minute)" if elapsed_s > 0 else ""
    return f", {mib:.1f} MiB{per_minute}"


def probe_summary(request) -> str:
    """ ", probe 64 texels at (x, y, z) [with mips]" of the Hello's ProbeRequest, or ""."""
    if request is None:
        return ""
    at = (
        "the scene objects' centre"
        if request.point_world is None
        else "(" + ", ".join(f"{x:g}" for x in request.point_world) + ")"
    )
    return f", probe {request.size} texels at {at}{' with mips' if request.mips else ''}"


@finalised_on_sigterm
def run(args: argparse.Namespace) -> int:
    from arlight.client.capture import CaptureClient, StreamError
    from arlight.client.foxglove_sinks import Recorders
    from arlight.offline import FrameNotes

    # the flags' own checks first: a camera opened (its pipeline started) before a usage
    # error would only be released by its frames
    token_of(args), client_keys(args)
    if args.record_processed and not args.record:
        raise BadInput("--record-processed chooses what --record writes: give --record FILE")
    if not args.source.lower().endswith(".mcap"):  # a recording's own probe: once read
        probe_request(args, None, bool(args.scene))
    foxglove = foxglove_address(args)
    source = open_stream_source(args)
    options = stream_options(args, source)
    if options.probe is not None and source.calibration is None:
        raise BadInput(
            f"--probe: SOURCE {args.source} is a panorama only, with no depth to make a "
            "probe of the room from; stream RGB-D frames (--panorama FILE pairs one in)"
        )
    probes = output_folder(args.probe_out, "--probe-out") if options.probe else None
    live = None
    if foxglove is not None:
        from arlight.client.foxglove_sinks import FoxgloveStream, LiveSink

        try:
            sink = LiveSink(*foxglove, name=f"arlight stream {args.source}")
        except OSError as exc:
            raise BadInput(f"--foxglove/--port: {exc}") from None
        live = FoxgloveStream(sink)
        print(
            f"arlight stream: Foxglove WebSocket on ws://{foxglove[0]}:{sink.port}",
            file=sys.stderr,
            flush=True,
        )
    recorder = None
    if args.record:
        from arlight.client.recording import ProcessedRecorder, Recorder

        whole = Recorder(args.record, source=args.source, depth_scale=source.depth_scale)
        recorder = ProcessedRecorder(whole) if args.record_processed else whole
    to_stdout = args.out == "-"  # the JSON lines on stdout, the per-frame lines on stderr
    out = sys.stdout if to_stdout else open(args.out, "w") if args.out else None  # noqa: SIM115
    total = "loop" if options.loop else str(source.num_frames or "live")
    notes = FrameNotes()
    written: list[int] = []  # the seq of each probe written to --probe-out

    def on_result(result, receive_time_wall: float) -> None:
        d = result.dominant_direction_camera
        in_server_ms = (result.server_finish_time - result.server_receive_time) * 1e3
        conf = result.confidence.value
        print(
            f"[{result.seq + 1:>5}/{total}] light(cam)=({d[0]:+.2f}, {d[1]:+.2f}, "
            f"{d[2]:+.2f})  conf={conf:.2f}  "
            f"pipeline {pipeline_ms(result):5.0f} ms  in server {in_server_ms:5.0f} ms  "
            f"received {result.frames_received}  dropped {result.frames_dropped}"
            + (
                ""
                if result.panorama_dominant_direction is None
                else "  panorama light=("
                + ", ".join(f"{x:+.2f}" for x in result.panorama_dominant_direction)
                + ")"
            ),
            file=sys.stderr if to_stdout else sys.stdout,
            flush=True,
        )
        note = notes.note(conf, result.confidence.reason)
        if note:
            print(f"arlight stream: [{result.seq + 1}/{total}] {note}", file=sys.stderr, flush=True)
        stem = None
        # ms a frame by size, levels, layout: docs/guides/engine-exports.md ("What
        # --probe-out costs")
        if probes is not None and result.probe is not None:
            stem = probes / f"{result.seq:06d}"
            write_probe_files(
                stem,
                result.probe,
                result.probe.point_world,
                args.probe_layout,
                result.pose,
                result.diagnostics.get("probe"),
            )
            written.append(result.seq)
        if out or recorder is not None or live is not None:
            record = received_record(result, receive_time_wall)  # with the server's exports
            if options.probe is not None:  # what came, where it went; never the texels
                record["probe"] = probe_record(result.probe, stem, args.probe_layout)
        with uninterrupted():  # a stop signal waits: every file holds this Result or none does
            if recorder is not None:  # the Foxglove channels of the Result beside the frames
                recorder.write_result(result, record)
            if live is not None:
                live.write_result(result, record, time.time_ns())
            if out:
                out.write(json.dumps(record) + "\n")
                out.flush()  # a line per Result as it arrives: a killed stream keeps them

    sinks = recorder if live is None else Recorders(recorder, live)
    client = CaptureClient(source, options, on_result=on_result, recorder=sinks)
    size = (
        "panorama only"
        if source.calibration is None
        else f"{source.calibration.width}x{source.calibration.height}"
    )
    frames = count(source.num_frames, "frame") if source.num_frames else "live"
    print(
        f"arlight stream: {args.source} ({frames}, "
        f"{size}) -> {options.server}, "
        f"session {client.session!r}, {options.mode}, rate {options.rate}, colour "
        f"{options.color_codec}, depth {options.depth_codec}"
        + probe_summary(options.probe)
        + ("" if source.recorded_config is None else " (recorded frames, sent as recorded)"),
        file=sys.stderr,
        flush=True,
    )
    keys = (
        f" --server-key {args.server_key} --client-key DIR/NAME.key_secret" if options.keys else ""
    )
    token = (
        f"--token-file {args.token_file}"
        if getattr(args, "token_file", None)
        else f"--token {client.token}"
    )  # a token from a file stays off the screen
    print(
        f"arlight stream: display with: arlight display --server {options.server} --session "
        f"{client.session} {token}{keys}  (the token is a secret: whoever has it sees this "
        "session)",
        file=sys.stderr,
        flush=True,
    )
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
    drops = (
        f"{summary.frames_dropped} dropped by the server (live: newest frame wins), "
        f"{summary.frames_not_sent} not sent (send queue full), "
        if options.mode == "live"
        else ""
    )
    median = f"{np.median(lat) * 1e3:.0f} ms" if lat else "-"
    print(
        f"arlight stream: {count(summary.frames_sent, 'frame')} sent, "
        f"{count(summary.results, 'result')}, "
        f"{drops}{len(summary.errors)} rejected, {summary.reconnects} reconnect(s); "
        f"send-to-result median {median}; {summary.elapsed_s:.1f} s",
        file=sys.stderr,
    )
    if notes.summary():
        print(f"arlight stream: {notes.summary()}", file=sys.stderr)
    if recorder is not None:
        print(
            f"recorded {count(recorder.frames, 'frame')} to {args.record}"
            + recording_size(args.record, summary.elapsed_s),
            file=sys.stderr,
        )
    if probes is not None:
        missing = (
            ""
            if len(written) == summary.results
            else f" ({summary.results - len(written)} Result(s) without one: before the "
            "objects were placed)"
        )
        print(
            f"wrote {count(len(written), 'reflection probe')} to {probes}/ (OpenEXR cube "
            f"maps, layout {args.probe_layout}){missing}",
            file=sys.stderr,
        )
    if summary.errors:
        first = summary.errors[0]
        print(
            f"arlight stream: {count(len(summary.errors), 'frame')} rejected by the server, "
            "first: "
            f"{first.code} {first.field or ''}: {first.message}",
            file=sys.stderr,
        )
        return 1
    return 0
