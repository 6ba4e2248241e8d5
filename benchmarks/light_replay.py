"""Replay the light estimate (LightEst) on cached inputs: a choice of the fit judged in minutes.

    python benchmarks/light_replay.py record DATA... --preset full --out CACHE
    python benchmarks/light_replay.py replay CACHE [--set KEY=VALUE ...] [--hold-out-maps]

`record` runs the pipeline once over ground-truth sequences (their poses; tracking skipped)
and stores, per frame, exactly what `estimate_light` received (the rows it would use: the
same seeded subset), the support plane's up, the pose and the truth. `replay` re-runs only
`estimate_light` with the EstimationParams changed by --set, and reports the angular error of
the reported direction (above the support plane's horizon, camera frame) against the upper-
hemisphere truth (or the probe's where the sequence says so), before the temporal filter
("raw") and after it: per map (median of the frames lit by it), the median over maps, the p90
over frames and the worst map. --hold-out-maps leaves each frame's maps out of the learned
light prior (light_prior_exclude), so the prior is judged on maps it never saw.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
from pathlib import Path

import numpy as np

from arlight import evaluation
from arlight.pipeline import light_estimation, sh
from arlight.pipeline.config import Config
from arlight.pipeline.temporal_filter import TemporalFilter

try:
    from benchmarks.error_by_view import azimuth_deg, wrapped
except ModuleNotFoundError:  # run as `python benchmarks/light_replay.py` from the checkout
    from error_by_view import azimuth_deg, wrapped  # type: ignore[import-not-found,no-redef]


def record(data: list[str], preset: str, out: Path, frames: int | None, overrides: dict) -> None:
    import arlight.pipeline.light_stage as light_stage_module
    import arlight.pipeline.pipeline as pipeline_module
    from arlight.bench import open_data

    out.mkdir(parents=True, exist_ok=True)
    config = Config.from_preset(preset, **overrides)
    captured: list[dict] = []
    real = light_stage_module.estimate_light

    def spy(
        transfer,
        color_linear,
        params,
        segments=None,
        bounce=None,
        up=None,
        below_horizon_unseen=False,
        *,
        seed=0,
        checkpoint=None,
        clipped_fraction=None,
    ):
        t = np.asarray(transfer).reshape(-1, np.asarray(transfer).shape[-1])
        keep = _kept_rows(t, color_linear, bounce, segments, params, seed)
        captured.append(
            {
                "transfer": t[keep],
                "color": np.asarray(color_linear).reshape(-1, 3)[keep],
                "segments": None if segments is None else np.asarray(segments).reshape(-1)[keep],
                "bounce": None if bounce is None else np.asarray(bounce).reshape(-1)[keep],
                "up": None if up is None else np.asarray(up, float),
                "below_horizon_unseen": bool(below_horizon_unseen),
                "seed": int(seed),
                "rows": keep,
            }
        )
        return real(
            transfer,
            color_linear,
            params,
            segments,
            bounce,
            up,
            below_horizon_unseen,
            seed=seed,
            checkpoint=checkpoint,
            clipped_fraction=clipped_fraction,
        )

    light_stage_module.estimate_light = spy
    try:
        for seq in open_data(data, frames, 0):
            pipe = pipeline_module.Pipeline(config, seq.camera)
            captured.clear()
            poses = []
            for frame in seq.frames:
                poses.append(pipe.process(frame).pose)
                _capture_geometry(pipe, captured[-1], poses[-1])
            _save(out / f"{seq.name}.npz", seq, captured, poses)
            print(f"recorded {seq.name}: {len(captured)} frames", file=sys.stderr, flush=True)
    finally:
        light_stage_module.estimate_light = real
    (out / "config.json").write_text(json.dumps({"preset": preset, "overrides": overrides}))


def _capture_geometry(pipe, captured: dict, pose: np.ndarray) -> None:
    """The fitted rows' world points and normals, and the volume's mesh (world), for the
    cues that test geometry (compact sources: shadows cast at any distance)."""
    geometry, transfer = pipe._last_transfer
    keep = captured["rows"]
    v, u = transfer.pixel_v[keep], transfer.pixel_u[keep]
    rot, origin = pose[:3, :3], pose[:3, 3]
    captured["points"] = (geometry.points[v, u].astype(np.float64) @ rot.T + origin).astype(
        np.float32
    )
    captured["normals"] = (geometry.normals[v, u].astype(np.float64) @ rot.T).astype(np.float32)
    # the frame's depth as the pipeline's depth mesh takes it (camera frame, every 2nd pixel)
    captured["depth_points"] = np.ascontiguousarray(geometry.points[::2, ::2], np.float32)
    vertices, triangles = (
        pipe._volume.triangle_mesh()
        if pipe._volume is not None
        else (np.zeros((0, 3)), np.zeros((0, 3)))
    )
    captured["mesh_vertices"] = np.asarray(vertices, np.float32)
    captured["mesh_triangles"] = np.asarray(triangles, np.int32)


def _kept_rows(t, color_linear, bounce, segments, params, seed) -> np.ndarray:
    """The rows estimate_light's own _usable_samples keeps (its rules, its seed)."""
    rgb = np.asarray(color_linear).reshape(-1, 3)
    s = light_estimation._usable_samples(t, rgb, bounce, segments, params.light_max_samples, seed)
    assert s.rows is not None
    return s.rows


def _save(path: Path, seq, captured: list[dict], poses: list) -> None:
    arrays: dict[str, np.ndarray] = {}
    meta = []
    for i, c in enumerate(captured):
        for key in (
            "transfer",
            "color",
            "segments",
            "bounce",
            "points",
            "normals",
            "depth_points",
            "mesh_vertices",
            "mesh_triangles",
        ):
            if c.get(key) is not None:
                arrays[f"{i}_{key}"] = c[key]
        truth = seq.truth[i]
        meta.append(
            {
                "up": None if c["up"] is None else c["up"].tolist(),
                "below_horizon_unseen": c["below_horizon_unseen"],
                "seed": c["seed"],
                "pose": np.asarray(poses[i]).tolist(),
                "truth_upper_camera": truth.dominant_upper_camera.tolist(),
                "env_map": truth.env_map,
                "layout": truth.layout,
            }
        )
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez_compressed(path, **arrays)


def _with_compact_source(
    data, i: int, est, up, compact: dict, pose: np.ndarray
) -> tuple[np.ndarray, dict]:
    """The estimate's SH with a compact source fitted beside it (pipeline.compact_light),
    against the frame's recorded mesh; (total SH, what was found)."""
    from arlight.pipeline.compact_light import ShadowTester, fit_compact_source
    from arlight.pipeline.object_space_transfer import OcclusionScene, SurfaceMesh

    f = est.fit
    if f is None or f"{i}_points" not in data:
        return est.sh, {}
    from arlight.pipeline.object_space_transfer import depth_mesh

    rows = f.rows
    options = dict(compact)
    # depth_only=S: the frame's depth mesh alone, at every S-th recorded point (the record
    # keeps every 2nd pixel of the work image), in place of the volume's mesh
    depth_only = int(options.pop("depth_only", 0))
    scenes = []
    if not depth_only:
        scene = OcclusionScene(
            SurfaceMesh(data[f"{i}_mesh_vertices"], data[f"{i}_mesh_triangles"], in_world=True)
        )
        scenes.append((scene, np.eye(4)))
    if (options.pop("depth_mesh", 0) or depth_only) and f"{i}_depth_points" in data:
        step = max(1, depth_only)
        points = data[f"{i}_depth_points"][::step, ::step]
        scenes.append((OcclusionScene(depth_mesh(np.ascontiguousarray(points))), pose))
    tester = ShadowTester(
        scenes,
        data[f"{i}_points"][rows].astype(np.float64),
        data[f"{i}_normals"][rows].astype(np.float64),
    )
    fit = fit_compact_source(
        f.design, f.albedo, f.weights, f.lum, None, f.penalty, f.bands, tester, up, **options
    )
    total = np.zeros_like(est.sh)
    n = f.bands * f.bands
    total[:n] = fit.ambient
    for source in fit.sources:
        total[:n] += source.sh(f.bands)
    info = {
        "reason": fit.reason,
        "rays": tester.rays,
        "contrast": fit.contrast,
        "radius": fit.radius_deg,
        "edge": fit.edge_step,
    }
    if fit.sources:
        info.update(
            direction=fit.sources[0].direction,
            share=fit.sources[0].share,
            gain=fit.sources[0].gain,
        )
    return total, info


@functools.lru_cache(maxsize=4)
def _compact_region(maps_dir: str, env_map: str, rotation_deg: float):
    from arlight.synth.environment import brightest_compact_region, load_map

    return brightest_compact_region(load_map(Path(maps_dir) / f"{env_map}.hdr"), rotation_deg)


def _frame_rotations(truth_dir: Path | None, sequence: str) -> list[float] | None:
    """The map rotation of each frame (lighting_gt.json of the sequence in truth_dir)."""
    if truth_dir is None or not (truth_dir / sequence / "lighting_gt.json").is_file():
        return None
    data = json.loads((truth_dir / sequence / "lighting_gt.json").read_text())
    return [float(f.get("env_rotation_deg", 0.0)) for f in data["frames"]]


def estimate_recorded(data, i: int, meta: dict, params) -> light_estimation.LightEstimate:
    """`estimate_light` on frame i of a recorded sequence (`data`: its .npz, `meta`: that
    frame's entry of data["meta"]) with EstimationParams `params`."""
    return light_estimation.estimate_light(
        data[f"{i}_transfer"],
        data[f"{i}_color"],
        params,
        data[f"{i}_segments"] if f"{i}_segments" in data else None,
        data[f"{i}_bounce"] if f"{i}_bounce" in data else None,
        None if meta["up"] is None else np.asarray(meta["up"]),
        meta["below_horizon_unseen"],
        seed=meta["seed"],
    )


def replay(
    cache: Path,
    overrides: dict,
    hold_out_maps: bool,
    compact: dict | None = None,
    truth_dir: Path | None = None,
    maps_dir: str = "../shared/data/hdri",
) -> dict:
    """Per-frame errors (raw and filtered) of the fit with `overrides`; figures by map."""
    base = json.loads((cache / "config.json").read_text())
    config = Config.from_preset(base["preset"], **{**base["overrides"], **overrides})
    rows = []
    for file in sorted(cache.glob("*.npz")):
        data = np.load(file)
        meta = json.loads(str(data["meta"]))
        filt = TemporalFilter(config.temporal)
        up_seen = None
        rotations = _frame_rotations(truth_dir, file.stem)
        for i, m in enumerate(meta):
            params = config.estimation
            if hold_out_maps and m["env_map"]:
                params = dataclasses.replace(params, light_prior_exclude=m["env_map"])
            up = None if m["up"] is None else np.asarray(m["up"])
            est = estimate_recorded(data, i, m, params)
            if up is not None:
                up_seen = up
            light = est.sh
            info: dict = {}
            if compact is not None:
                light, info = _with_compact_source(data, i, est, up, compact, np.asarray(m["pose"]))
            filtered = filt.update(light, est.confidence.value)
            r = np.asarray(m["pose"])[:3, :3]
            truth = np.asarray(m["truth_upper_camera"])

            rows.append(
                {
                    "sequence": file.stem,
                    "map": m["env_map"],
                    "layout": m["layout"],
                    "raw": _error(light, up_seen, r, truth),
                    "sh_only": _error(est.sh, up_seen, r, truth),
                    "source_deg": (
                        evaluation.angular_error_deg(r.T @ info["direction"], truth)
                        if "direction" in info
                        else None
                    ),
                    "compact": info.get("reason", ""),
                    "source_or_sh": (
                        evaluation.angular_error_deg(r.T @ info["direction"], truth)
                        if "direction" in info
                        else _error(est.sh, up_seen, r, truth)
                    ),
                    "share": info.get("share"),
                    "source_elevation": (
                        float(np.degrees(np.arcsin(np.clip(info["direction"] @ up, -1, 1))))
                        if "direction" in info and up is not None
                        else None
                    ),
                    "gain": info.get("gain"),
                    "contrast": info.get("contrast"),
                    "radius": info.get("radius"),
                    "edge": info.get("edge"),
                    **_compact_truth(m, rotations, i, maps_dir, info),
                    "filtered": _error(filtered, up_seen, r, truth),
                    "confidence": est.confidence.value,
                    "light_from_view": _light_from_view(r, truth),
                }
            )
    return summarise(rows)


def _compact_truth(m: dict, rotations, i: int, maps_dir: str, info: dict) -> dict:
    """The truth's brightest compact region (share, and the found source's error to it)."""
    if rotations is None or not m["env_map"]:
        return {}
    region = _compact_region(maps_dir, m["env_map"], rotations[i])
    out = {"truth_share": region.share}
    if "direction" in info:
        out["source_to_region_deg"] = evaluation.angular_error_deg(
            info["direction"], region.direction
        )
    return out


def _error(
    coeffs: np.ndarray,
    up: np.ndarray | None,
    world_from_cam_rot: np.ndarray,
    truth_camera: np.ndarray,
) -> float:
    """Degrees between the reported direction (above the horizon of `up`) and the truth."""
    d = sh.dominant_direction(coeffs) if up is None else sh.above_horizon_direction(coeffs, up)
    return evaluation.angular_error_deg(world_from_cam_rot.T @ d, truth_camera)


def _light_from_view(world_from_cam_rot: np.ndarray, truth_camera: np.ndarray) -> float:
    """Degrees of azimuth (about world +Y, the generator's up) between the true light and
    the camera's view direction: 0 is a back-lit view (error_by_view.py)."""
    truth_world = world_from_cam_rot @ truth_camera
    return abs(wrapped(azimuth_deg(truth_world) - azimuth_deg(world_from_cam_rot[:, 2])))


def summarise(rows: list[dict]) -> dict:
    out: dict = {"rows": rows}
    for kind in ("raw", "filtered", "sh_only", "source_or_sh"):
        if kind not in rows[0]:
            continue
        by_map: dict[str, list[float]] = {}
        for r in rows:
            by_map.setdefault(r["map"], []).append(r[kind])
        medians = {k: float(np.median(v)) for k, v in by_map.items()}
        worst = max(medians, key=medians.get)
        by_seq: dict[str, list[float]] = {}
        for r in rows:
            by_seq.setdefault(r["sequence"], []).append(r[kind])
        out[kind] = {
            "median_over_maps": float(np.median(list(medians.values()))),
            "p90_frames": float(np.percentile([r[kind] for r in rows], 90)),
            "worst_map": worst,
            "worst_map_deg": medians[worst],
            "median_of_sequence_medians": float(np.median([np.median(v) for v in by_seq.values()])),
            "per_map": medians,
        }
    out["frames"] = len(rows)
    return out


def _override(text: str) -> tuple[str, object]:
    key, value = text.split("=", 1)
    return key, Config.parse_flat_value(key, value)


COMPACT_KEYS = (
    "candidates",
    "search_samples",
    "min_gain",
    "min_contrast",
    "min_edge_step",
    "max_radius_deg",
    "min_pixels",
    "depth_mesh",
    "depth_only",
)


def _override_compact(text: str) -> tuple[str, float] | None:
    """--compact on, or KEY=VALUE with KEY one of COMPACT_KEYS (argparse: exit 2 else)."""
    if text in ("", "on"):
        return None
    key, _, value = text.partition("=")
    if key not in COMPACT_KEYS:
        raise argparse.ArgumentTypeError(f"{key!r}: not one of {', '.join(COMPACT_KEYS)}")
    try:
        return key, (int(value) if value.isdigit() else float(value))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{key}: a number, got {value!r}") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="verb", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("data", nargs="+")
    rec.add_argument("--preset", default="full")
    rec.add_argument("--out", required=True)
    rec.add_argument("--frames", type=int)
    rec.add_argument("--set", action="append", type=_override, default=[])
    rep = sub.add_parser("replay")
    rep.add_argument("cache")
    rep.add_argument("--set", action="append", type=_override, default=[])
    rep.add_argument("--hold-out-maps", action="store_true")
    rep.add_argument("--json")
    rep.add_argument("--truth-dir", type=Path, help="the sequences' folder (lighting_gt.json)")
    rep.add_argument(
        "--compact",
        action="append",
        type=_override_compact,
        help="fit a compact source beside the SH (pipeline.compact_light): KEY=VALUE options",
    )
    args = parser.parse_args(argv)
    if args.verb == "record":
        record(args.data, args.preset, Path(args.out), args.frames, dict(args.set))
        return 0
    compact = None if args.compact is None else dict(kv for kv in args.compact if kv)
    report = replay(Path(args.cache), dict(args.set), args.hold_out_maps, compact, args.truth_dir)
    for kind in ("raw", "filtered", "sh_only", "source_or_sh"):
        if kind not in report:
            continue
        r = report[kind]
        print(
            f"{kind:9s} median over maps {r['median_over_maps']:5.1f}  p90 frames "
            f"{r['p90_frames']:5.1f}  worst map {r['worst_map']} {r['worst_map_deg']:.1f}  "
            f"(median of sequence medians {r['median_of_sequence_medians']:.1f}; "
            f"{report['frames']} frames)"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
