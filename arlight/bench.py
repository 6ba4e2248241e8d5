"""`arlight bench`: speed and accuracy of each configuration, measured in one run.

Never a single call: every configuration runs over the same frames in the same process,
warm-up frames first (JIT, caches) and left out of the timings; stage milliseconds are the
rows of the paper's table 1, reported as median and 10th-90th percentile. Where the data has
ground truth (a `lighting_gt.json`, or the built-in scene) each frame is also scored
(arlight.evaluation): the angular error of the dominant direction against the whole sphere
and the upper hemisphere, the SH error and the diffuse-shading error. Poses are the data's
own (tracking skipped), so accuracy measures the light estimate, not the tracker. Seeds are
fixed. Each scored frame keeps the name of the environment map that lit it and its sequence's
layout, so the report groups errors by map and by layout as well as by sequence, and
`folds=True` adds the leave-one-map-out choice among the configurations (arlight.folds). The
report (report.json, report.md, trade.png) is written by arlight.report.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from arlight import evaluation
from arlight.core.checks import depth_metres
from arlight.pipeline.channels import any_nonzero
from arlight.pipeline.config import Config
from arlight.pipeline.depth_filter import normals_from_depth
from arlight.pipeline.pipeline import STAGES, Pipeline, smooth_depth_for_normals
from arlight.sources.synthetic import parse_size

BUILT_IN = "synthetic"
# the built-in scene seen by a camera held still, the sun moving half-way through: what
# reusing a still camera's work (ReuseParams) saves, and that the light is still followed
BUILT_IN_HELD = "synthetic-held"
# configurations that are not presets: a preset and what they change in it
COMPARATORS: dict[str, tuple[str, dict[str, Any]]] = {  # name -> (preset, overrides)
    # K = 1: no visibility at all, and the SH alone (the paper's comparator)
    "baseline": ("full", {"visibility": False, "compact_sources": 0}),
    # object-space visibility (GR12/GR14 style): rays against the volume's mesh; the
    # auxiliary buffers serve only SSDO, so they are not rendered for it
    "raycast": ("full", {"rt_method": "raycast", "aux_buffers": False}),
}
NORMAL_SAMPLES = 4000  # observed normals per frame for the shading error
NORMAL_WINDOW = 15  # pixels, the pipeline's default smoothing before normals


class BenchError(ValueError):
    """Bad benchmark input (a CLI usage error: exit code 2)."""


@dataclass
class BenchSequence:
    """Frames to run, their camera, and the truth per frame (None: timings only)."""

    name: str
    camera: Any
    frames: list
    truth: list[evaluation.FrameTruth] | None


@dataclass(frozen=True)
class BenchConfig:
    """One point of the report: a name, the Config, and where it came from."""

    name: str
    config: Config
    size: tuple[int, int] | None = None  # built-in scene rendered at this size (size sweep)
    sweep: str | None = None  # the swept key, or None
    value: Any = None  # its value


@dataclass
class ConfigResult:
    name: str
    overrides: dict
    sweep: str | None
    value: Any
    stage_ms: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STAGES})
    total_ms: list[float] = field(default_factory=list)
    # milliseconds between consecutive results (what a frame costs when frames overlap)
    period_ms: list[float] = field(default_factory=list)
    overlapped: bool = False
    per_sequence: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    # what the scene required of the model: per frame the SH bands solved for and which
    # stage outputs a still camera reused; per sequence the volume's blocks at its end
    bands_estimated: list[int] = field(default_factory=list)
    reused: dict[str, list[bool]] = field(
        default_factory=lambda: {"Surface": [], "RadTransfer": []}
    )
    volume_blocks: dict[str, int] = field(default_factory=dict)
    # per sequence: the environment map of each scored frame (aligned with per_sequence's
    # lists; None: unknown) and the sequence's layout (None: unknown)
    env_maps: dict[str, list[str | None]] = field(default_factory=dict)
    layouts: dict[str, str | None] = field(default_factory=dict)


# --------------------------------------------------------------------------- inputs


def parse_sweep(text: str) -> tuple[str, list[Any]]:
    """ "KEY=V1,V2,..." -> (KEY, values), each value typed by the Config key ("size": WxH)."""
    if "=" not in text:
        raise BenchError(f"--sweep expects KEY=V1,V2,..., got {text!r}")
    key, values = text.split("=", 1)
    items = [v.strip() for v in values.split(",") if v.strip()]
    if not items:
        raise BenchError(f"--sweep {key}= has no values")
    try:
        if key == "size":
            return key, [parse_size(v) for v in items]
        return key, [Config.parse_flat_value(key, v) for v in items]
    except ValueError as exc:
        raise BenchError(f"--sweep {key}: {exc}") from None


def make_configs(
    presets: list[str], sweeps: list[tuple[str, list[Any]]], overrides: dict[str, Any]
) -> list[BenchConfig]:
    """The presets (and comparators), then each sweep's points on the first preset."""
    configs = []
    for name in presets:
        base, extra = COMPARATORS.get(name, (name, {}))
        configs.append(BenchConfig(name, Config.from_preset(base, **{**overrides, **extra})))
    base_preset = COMPARATORS.get(presets[0], (presets[0], {}))[0]
    for key, values in sweeps:
        for value in values:
            if key == "size":
                name = f"{base_preset} size={value[0]}x{value[1]}"
                configs.append(
                    BenchConfig(
                        name,
                        Config.from_preset(base_preset, **overrides),
                        size=value,
                        sweep=key,
                        value=list(value),
                    )
                )
            else:
                config = Config.from_preset(base_preset, **{**overrides, key: value})
                configs.append(
                    BenchConfig(f"{base_preset} {key}={value}", config, sweep=key, value=value)
                )
    return configs


def open_data(
    paths: list[str], frames: int | None, warmup: int, size: tuple[int, int] = (640, 480)
) -> list[BenchSequence]:
    """BenchSequences of the DATA arguments: "synthetic", sequence folders, or folders of them."""
    from arlight.sources.sequence import open_sequence
    from arlight.sources.synthetic import make_sequence

    out = []
    for p in paths:
        if p in (BUILT_IN, BUILT_IN_HELD):
            n = warmup + (frames or 8)
            held = p == BUILT_IN_HELD
            scene = make_sequence(
                num_frames=n,
                width=size[0],
                height=size[1],
                held=held,
                light_change_frame=warmup + (n - warmup) // 2 if held else None,
            )
            out.append(BenchSequence(p, scene.camera, scene.frames, evaluation.scene_truth(scene)))
            continue
        folder = Path(p)
        if not folder.is_dir():
            raise BenchError(
                f"DATA {p!r}: no such folder (give 'synthetic', "
                f"'{BUILT_IN_HELD}', a sequence folder, or a folder of sequence "
                "folders)"
            )
        children = sorted(c for c in folder.iterdir() if evaluation.has_ground_truth(c))
        for seq_folder in children if not evaluation.has_ground_truth(folder) else [folder]:
            try:  # the truth first: a file that cannot be scored fails before any work
                truth = (
                    evaluation.load_ground_truth(seq_folder)
                    if evaluation.has_ground_truth(seq_folder)
                    else None
                )
            except evaluation.GroundTruthError as exc:
                raise BenchError(str(exc)) from None
            seq = open_sequence(seq_folder, use_poses=True, max_frames=frames)
            out.append(BenchSequence(seq_folder.name, seq.camera, list(seq.frames), truth))
        if not children and not evaluation.has_ground_truth(folder):
            seq = open_sequence(folder, use_poses=True, max_frames=frames)
            out.append(BenchSequence(folder.name, seq.camera, list(seq.frames), None))
    return out


# --------------------------------------------------------------------------- running


def observed_normals_world(frame, camera, rng: np.random.Generator) -> np.ndarray:
    """Up to NORMAL_SAMPLES unit normals (N, 3), world frame, of the frame's valid depth."""
    depth = depth_metres(frame.depth, frame.depth_scale)
    normals = normals_from_depth(smooth_depth_for_normals(depth, NORMAL_WINDOW), camera)
    valid = any_nonzero(normals)
    n = normals[valid].astype(np.float64)
    if len(n) > NORMAL_SAMPLES:
        n = n[rng.choice(len(n), NORMAL_SAMPLES, replace=False)]
    rotation = np.asarray(frame.pose, float)[:3, :3] if frame.pose is not None else np.eye(3)
    return n @ rotation.T


def run_config(
    bench: BenchConfig,
    sequences: list[BenchSequence],
    warmup: int,
    on_frame=None,
    scene=None,
    overlap: bool = False,
) -> ConfigResult:
    """Process every sequence's frames with one configuration; time and score each frame.
    scene: a VirtualScene rendered into every frame (the Rendering stage), or None;
    overlap: through Pipeline.process_overlapped (the time between results is the cost)."""
    overrides = {
        k: v
        for k, v in bench.config.flat().items()
        if v != Config.from_preset(_preset_name(bench.config)).flat().get(k)
    }
    result = ConfigResult(bench.name, overrides, bench.sweep, bench.value, overlapped=overlap)
    rng = np.random.default_rng(0)
    for seq in sequences:
        pipeline = Pipeline(bench.config, seq.camera, scene)
        scores: dict[str, list[float]] = {
            "angle_upper_deg": [],
            "sh_angle_upper_deg": [],
            "angle_deg": [],
            "sh_error": [],
            "shading_error": [],
            "confidence": [],
        }
        maps: list[str | None] = []
        process = pipeline.process_overlapped if overlap else partial(map, pipeline.process)
        outputs = process(seq.frames)
        last = time.perf_counter()
        for i, (frame, out) in enumerate(zip(seq.frames, outputs, strict=True)):
            now = time.perf_counter()
            period, last = (now - last) * 1e3, now
            result.bands_estimated.append(int(out.confidence.bands_estimated))
            for stage, flags in result.reused.items():
                flags.append(bool(out.diagnostics.get("reused", {}).get(stage, False)))
            if i >= warmup or len(seq.frames) <= warmup:
                for stage in STAGES:
                    result.stage_ms[stage].append(out.timings_ms.get(stage, 0.0))
                result.total_ms.append(sum(out.timings_ms.values()))
                result.period_ms.append(period)
            if seq.truth is not None and i < len(seq.truth):
                _score(scores, out, seq.truth[i], frame, seq.camera, rng)
                maps.append(seq.truth[i].env_map)
            if on_frame is not None:
                on_frame()
        result.per_sequence[seq.name] = scores
        result.volume_blocks[seq.name] = pipeline.volume_blocks
        if seq.truth is not None:
            result.env_maps[seq.name] = maps
            result.layouts[seq.name] = seq.truth[0].layout if seq.truth else None
    return result


def _preset_name(config: Config) -> str:
    preset = str(config.preset)
    return preset if preset in ("full", "fast", "mobile") else "full"


def _score(
    scores: dict[str, list[float]],
    out,
    truth: evaluation.FrameTruth,
    frame,
    camera,
    rng: np.random.Generator,
) -> None:
    scores["angle_deg"].append(
        evaluation.angular_error_deg(out.dominant_direction_camera, truth.dominant_camera)
    )
    scores["angle_upper_deg"].append(
        evaluation.angular_error_deg(out.dominant_direction_camera, truth.dominant_upper_camera)
    )
    # the SH's own direction, which a kept compact source's replaces as the reported one
    own = out.diagnostics.get("sh_direction_world")
    scores["sh_angle_upper_deg"].append(
        math.nan
        if own is None
        else evaluation.angular_error_deg(
            np.asarray(out.pose)[:3, :3].T @ np.asarray(own), truth.dominant_upper_camera
        )
    )
    scores["confidence"].append(float(out.confidence.value))
    if truth.sh_upper_world is not None:
        scores["sh_error"].append(evaluation.sh_error(out.sh, truth.sh_upper_world))
        normals = observed_normals_world(frame, camera, rng)
        scores["shading_error"].append(
            evaluation.shading_error(out.sh, truth.sh_upper_world, normals)
        )


def run_benchmark(
    data: list[str],
    presets: list[str],
    sweeps: list[tuple[str, list[Any]]],
    frames: int | None,
    warmup: int,
    overrides: dict[str, Any],
    progress: bool = True,
    size: tuple[int, int] = (640, 480),
    scene=None,
    folds: bool = False,
    overlap: bool = False,
) -> dict:
    """Every configuration over every DATA sequence; the report's figures (a plain dict).

    size: image size of the built-in scene (pixels) where no size sweep sets it;
    scene: virtual objects rendered into every frame (VirtualScene), or None (Rendering 0);
    folds: add the leave-one-map-out choice among the configurations (report "folds");
    overlap: frames through Pipeline.process_overlapped (FPS from the time between results).
    """
    from arlight.report import summarise

    configs = make_configs(presets, sweeps, overrides)
    if any(b.size is not None for b in configs) and data != [BUILT_IN]:
        raise BenchError(
            "--sweep size renders the built-in scene: use it without DATA (or with DATA synthetic)"
        )
    base_data = open_data(data, frames, warmup, size)
    sized: dict[tuple[int, int], list[BenchSequence]] = {}
    for bench in configs:
        if bench.size is not None and bench.size not in sized:
            sized[bench.size] = open_data([BUILT_IN], frames, warmup, bench.size)
    total = sum(
        sum(len(s.frames) for s in (sized[b.size] if b.size else base_data)) for b in configs
    )
    bar = _progress_bar(total, progress)
    results = []
    try:
        for k, bench in enumerate(configs, 1):
            seqs = sized[bench.size] if bench.size else base_data
            bar.set_description(bench.name)
            if not progress:  # no terminal for a bar: a line per configuration
                print(
                    f"arlight bench: [{k}/{len(configs)}] {bench.name}: "
                    f"{sum(len(s.frames) for s in seqs)} frames of {len(seqs)} sequence(s)",
                    file=sys.stderr,
                    flush=True,
                )
            results.append(
                run_config(
                    bench,
                    seqs,
                    warmup,
                    on_frame=lambda: bar.update(1),
                    scene=scene,
                    overlap=overlap,
                )
            )
    finally:
        bar.close()
    return summarise(
        results,
        data=[s.name for s in base_data],
        frames=frames,
        warmup=warmup,
        sweeps=[k for k, _ in sweeps],
        configs_used=[b.config for b in configs],
        folds=folds,
    )


def _progress_bar(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", disable=not enabled, dynamic_ncols=True, leave=False)
