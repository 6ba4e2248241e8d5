"""The JSON record of one frame's lighting: one line of every `--out` file.

`arlight estimate --out`, `arlight stream --out` and `arlight display --out` all write
`result_record` (docs/reference/output-record.md); the two streaming clients add
the delivery fields of `received_record`. `estimate` has no Result: it converts its pipeline
FrameResult with the server's own conversion (arlight.server.results.result_message) first.
"""

from __future__ import annotations

from .frame_result import Result

WALL_CLOCK_WINDOW_S = 3600.0  # timestamps within this of the receive time are capture times


def result_record(result: Result) -> dict:
    """The record of one Result: plain JSON values, in docs/reference/output-record.md's key
    order."""
    return {
        "timestamp": result.timestamp,
        "frame": result.seq,
        "sh": result.sh,
        "sh_camera": result.sh_camera,
        "sh_rgb": result.sh_rgb,
        "dominant_direction_camera": result.dominant_direction_camera,
        "dominant_direction_world": result.dominant_direction_world,
        "intensity": result.intensity,
        # compact sources kept beside the SH (SPEC.md "result: compact sources"): when any
        **({} if result.compact_sources is None else {"compact_sources": result.compact_sources}),
        "confidence": result.confidence_map,  # as the wire carried it
        "pose": result.pose,
        "timings_ms": {k: round(v, 3) for k, v in result.timings_ms.items()},
        "diagnostics": result.diagnostics,
        **(
            {}
            if result.panorama_sh is None
            else {  # a frame with a panorama
                "panorama_sh": result.panorama_sh,
                "panorama_sh_rgb": result.panorama_sh_rgb,
                "panorama_dominant_direction": result.panorama_dominant_direction,
            }
        ),
        **({} if result.exports is None else {"exports": result.exports}),  # Hello asked
    }


def received_record(result: Result, receive_time: float) -> dict:
    """result_record plus what a client that received it knows (wall-clock seconds).

    Each latency names the two instants it lies between (milliseconds):
    - pipeline_ms: the pipeline's own stages (sum of timings_ms), no waiting;
    - in_server_ms = server_finish_time - server_receive_time: queueing (lossless mode keeps
      up to `credits` frames waiting) + decoding + the pipeline + encoding;
    - server_to_client_ms = receive_time - server_finish_time: the trip back (needs the two
      machines' clocks in sync);
    - end_to_end_ms = receive_time - the frame's timestamp, when that timestamp is a capture
      time (within WALL_CLOCK_WINDOW_S of receive_time), else None.
    """
    e2e = receive_time - result.timestamp
    return {
        **result_record(result),
        "frames_received": result.frames_received,
        "frames_processed": result.frames_processed,
        "frames_dropped": result.frames_dropped,
        "server_receive_time": result.server_receive_time,
        "server_finish_time": result.server_finish_time,
        "receive_time": receive_time,
        "end_to_end_ms": round(e2e * 1e3, 3) if abs(e2e) < WALL_CLOCK_WINDOW_S else None,
        "pipeline_ms": round(pipeline_ms(result), 3),
        "in_server_ms": round((result.server_finish_time - result.server_receive_time) * 1e3, 3),
        "server_to_client_ms": round((receive_time - result.server_finish_time) * 1e3, 3),
    }


def pipeline_ms(result: Result) -> float:
    """The pipeline's time for this frame: the sum of its per-stage milliseconds."""
    return float(sum(result.timings_ms.values()))
