"""The benchmark report: figures (report.json), tables (report.md) and the trade plot (trade.png).

Tables in the style of the paper's tables 1 (milliseconds per stage) and 2 (accuracy); the
plot puts every configuration at (milliseconds per frame, median angular error against the
upper-hemisphere truth), sweeps joined in their order.

Accuracy is grouped three ways, each on the angular error against the upper-hemisphere truth
(degrees): per sequence, per environment map (the lighting: several sequences share a map,
a light-change sequence has two) and per layout (the scene's arrangement). Per map, the
median over that map's frames; over maps, the median of those medians, the 90th percentile
over all frames and the worst map by name. With `folds`, the leave-one-map-out choice among
the configurations (arlight.folds): what choosing a configuration is worth on unseen lighting.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import numpy as np

from arlight import __version__
from arlight.pipeline.pipeline import STAGES

LIBRARIES = ("numpy", "open3d", "numba", "scipy", "opencv-contrib-python-headless", "pyzmq")


def commit() -> str:
    """The checkout's short commit hash ("unknown" outside a git checkout)."""
    try:
        return (
            subprocess.run(
                ["git", "rev-parse", "--short", "HEAD"],
                capture_output=True,
                text=True,
                check=False,
                cwd=os.path.dirname(__file__),
            ).stdout.strip()
            or "unknown"
        )
    except OSError:
        return "unknown"


def _versions() -> dict[str, str]:
    out = {}
    for name in LIBRARIES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "absent"
    return out


def _spread(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"median": None, "p10": None, "p90": None}
    v = np.asarray(values, float)
    return {
        "median": float(np.median(v)),
        "p10": float(np.percentile(v, 10)),
        "p90": float(np.percentile(v, 90)),
    }


def _finite(values: list[float]) -> list[float]:
    return [x for x in values if math.isfinite(x)]


def _unique(items) -> list:
    """Items in first-seen order, each once."""
    return list(dict.fromkeys(items))


def _map_figures(frames: list[tuple[str, float]]) -> dict:
    """(map, error in degrees) per frame -> the median per map (maps sorted by name), the
    median over maps of those, the 90th percentile over all frames and the worst map."""
    errors: dict[str, list[float]] = {}
    for env_map, error in sorted(frames, key=lambda f: f[0]):
        errors.setdefault(env_map, []).append(error)
    medians = {m: float(np.median(e)) for m, e in errors.items()}
    worst = max(medians, key=lambda m: medians[m])
    return {
        "maps": medians,
        "median_over_maps": float(np.median(list(medians.values()))),
        "p90_all_frames": float(np.percentile([e for _, e in frames], 90)),
        "worst_map": worst,
        "worst_map_median": medians[worst],
        "frames": len(frames),
    }


def group_by_map(
    errors_deg: dict[str, list[float]],
    env_maps: dict[str, list[str | None]],
    layouts: dict[str, str | None] | None = None,
) -> dict | None:
    """Per-frame errors grouped by the environment map that lit each frame, and by layout.

    errors_deg: per sequence, per scored frame, the angular error (degrees) against the
    upper-hemisphere truth; env_maps: per sequence, the map of each of those frames (the
    same length; None = unknown, left out); layouts: per sequence its layout (None or absent:
    "unknown"). Returns None when no frame names a map, else (degrees throughout):
    maps: {map: median, p90, frames, sequences, layouts}; median_over_maps (the median of the
    per-map medians), p90_all_frames, worst_map and worst_map_median; layouts: {layout: the
    same figures over that layout's frames only, per-map medians under "maps"}.
    """
    layouts = layouts or {}
    rows: list[tuple[str, str, str, float]] = []  # (map, sequence, layout, error)
    for seq, errors in errors_deg.items():
        maps = env_maps.get(seq)
        if maps is None:
            continue
        layout = layouts.get(seq) or "unknown"
        rows += [
            (m, seq, layout, float(e))
            for m, e in zip(maps, errors, strict=True)
            if m is not None and math.isfinite(e)
        ]
    if not rows:
        return None
    whole = _map_figures([(m, e) for m, _, _, e in rows])
    per_map = {}
    for env_map, median in whole.pop("maps").items():
        mine = [r for r in rows if r[0] == env_map]
        per_map[env_map] = {
            "median": median,
            "p90": float(np.percentile([r[3] for r in mine], 90)),
            "frames": len(mine),
            "sequences": _unique(r[1] for r in mine),
            "layouts": _unique(r[2] for r in mine),
        }
    by_layout = {
        layout: _map_figures([(m, e) for m, _, lay, e in rows if lay == layout])
        for layout in sorted({r[2] for r in rows})
    }
    return {"metric": "angle_upper_deg", "maps": per_map, **whole, "layouts": by_layout}


def _accuracy(
    per_sequence: dict[str, dict[str, list[float]]],
    env_maps: dict[str, list[str | None]] | None = None,
    layouts: dict[str, str | None] | None = None,
) -> dict | None:
    """Aggregates over sequences (median of per-sequence medians, p90 over all frames) and
    over environment maps (`group_by_map`; "by_map" None without map names)."""
    scored = {name: s for name, s in per_sequence.items() if s["angle_upper_deg"]}
    if not scored:
        return None
    env_maps, layouts = env_maps or {}, layouts or {}
    out: dict = {"sequences": {}}
    for name, s in scored.items():
        out["sequences"][name] = {
            key: (float(np.median(_finite(v))) if _finite(v) else None) for key, v in s.items()
        }
        out["sequences"][name]["p90_angle_upper_deg"] = float(
            np.percentile(s["angle_upper_deg"], 90)
        )
        out["sequences"][name]["frames"] = len(s["angle_upper_deg"])
        out["sequences"][name]["env_maps"] = _unique(
            m for m in env_maps.get(name, []) if m is not None
        )
        out["sequences"][name]["layout"] = layouts.get(name)
    for key in ("angle_upper_deg", "sh_angle_upper_deg", "angle_deg", "sh_error", "shading_error"):
        medians = [m[key] for m in out["sequences"].values() if m.get(key) is not None]
        every = [x for s in scored.values() for x in _finite(s.get(key, []))]
        out[key] = {
            "median_of_medians": float(np.median(medians)) if medians else None,
            "p90_all_frames": float(np.percentile(every, 90)) if every else None,
            "worst_sequence_median": float(max(medians)) if medians else None,
        }
    out["confidence_spearman"] = confidence_spearman(scored)
    out["by_map"] = group_by_map(
        {n: s["angle_upper_deg"] for n, s in scored.items()}, env_maps, layouts
    )
    # the SH's own direction (a kept compact source's replaces it as the reported one)
    own = {n: s["sh_angle_upper_deg"] for n, s in scored.items() if s.get("sh_angle_upper_deg")}
    out["by_map_sh"] = group_by_map(own, env_maps, layouts) if len(own) == len(scored) else None
    return out


def fold_figures(configs: dict[str, dict]) -> dict:
    """report.json's "folds": the leave-one-map-out choice (arlight.folds) among the
    configurations that have per-map figures, on their per-map median angular error against
    the upper-hemisphere truth (degrees). "note" says why there is nothing to choose (one
    configuration, fewer than two maps, no map names), else it is None."""
    from arlight.folds import FoldsError, leave_one_map_out

    per_map = {
        name: {m: v["median"] for m, v in c["accuracy"]["by_map"]["maps"].items()}
        for name, c in configs.items()
        if c.get("accuracy") and c["accuracy"].get("by_map")
    }
    base = {
        "metric": "angle_upper_deg",
        "candidates": list(per_map),
        "maps": sorted({m for maps in per_map.values() for m in maps}),
    }
    if not per_map:
        return {**base, "note": "no scored frame names its environment map: nothing to hold out"}
    if len(per_map) == 1:
        return {
            **base,
            "note": "one configuration: nothing to choose (run several presets or a --sweep)",
        }
    try:
        folds = leave_one_map_out(per_map)
    except FoldsError as exc:
        return {**base, "note": str(exc)}
    return {"metric": "angle_upper_deg", **folds.as_dict(), "note": None}


def spearman(pairs: list[tuple[float, float]]) -> float | None:
    """Spearman rank correlation of the finite (x, y) pairs; None when fewer than 3 are
    left or either column is constant."""
    from scipy.stats import spearmanr

    kept = [(x, y) for x, y in pairs if math.isfinite(x) and math.isfinite(y)]
    if len(kept) < 3 or len({x for x, _ in kept}) < 2 or len({y for _, y in kept}) < 2:
        return None
    return float(spearmanr(*zip(*kept, strict=True)).statistic)


def confidence_spearman(per_sequence: dict[str, dict[str, list[float]]]) -> float | None:
    """Spearman rank correlation over all frames between confidence.value and the angular
    error against the upper hemisphere (negative: confidence falls as the error grows);
    None when fewer than 3 frames or either is constant."""
    return spearman(
        [
            (c, e)
            for s in per_sequence.values()
            for c, e in zip(s.get("confidence", []), s["angle_upper_deg"], strict=False)
        ]
    )


def _model(result, config) -> dict:
    """What the scene required of the model (bench.ConfigResult): the SH bands solved for
    (frames per count), the share of frames whose stage outputs a still camera reused, and
    the volume's allocated blocks (median over sequences) against its initial hash-map
    capacity and against a dense grid of the same voxel size over volume_size_m."""
    v = config.volume
    block_bytes = v.block_resolution**3 * 8  # tsdf + weight, float32
    dense_blocks = math.ceil(v.volume_resolution / v.block_resolution) ** 3
    blocks = [b for b in result.volume_blocks.values() if b > 0]
    frames = len(result.bands_estimated)
    return {
        "bands_requested": config.transfer.sh_bands,
        "bands_estimated_frames": {
            str(b): result.bands_estimated.count(b)
            for b in sorted(set(result.bands_estimated), reverse=True)
        },
        "reused_share": {
            stage: (sum(flags) / frames if frames else 0.0)
            for stage, flags in result.reused.items()
        },
        "volume_blocks_median": float(np.median(blocks)) if blocks else 0.0,
        "volume_mb_median": float(np.median(blocks)) * block_bytes / 2**20 if blocks else 0.0,
        "volume_capacity_mb": v.block_count * block_bytes / 2**20 if v.use_volume else 0.0,
        "volume_dense_mb": dense_blocks * block_bytes / 2**20 if v.use_volume else 0.0,
    }


def summarise(
    results: list,
    data: list[str],
    frames: int | None,
    warmup: int,
    sweeps: list[str],
    configs_used: list | None = None,
    folds: bool = False,
) -> dict:
    """The report as plain JSON values (what report.json holds). configs_used: the
    pipeline Config of each result, in order (for the "model" figures; None: left out);
    folds: add "folds" (`fold_figures`)."""
    configs = {}
    for k, r in enumerate(results):
        total = _spread(r.total_ms)
        # overlapped frames: the rate results come out; else one frame's stages
        rate_ms = _spread(r.period_ms)["median"] if r.overlapped else total["median"]
        configs[r.name] = {
            "overrides": r.overrides,
            "sweep": r.sweep,
            "value": r.value,
            "stages_ms": {s: _spread(v) for s, v in r.stage_ms.items()},
            "total_ms": total,
            "fps": 1000.0 / rate_ms if rate_ms else None,
            "overlapped": r.overlapped,
            "period_ms": _spread(r.period_ms),  # between consecutive results
            "accuracy": _accuracy(r.per_sequence, r.env_maps, r.layouts),
        }
        if configs_used is not None:
            configs[r.name]["model"] = _model(r, configs_used[k])
    maps = sorted(
        {
            m
            for c in configs.values()
            if c["accuracy"] and c["accuracy"]["by_map"]
            for m in c["accuracy"]["by_map"]["maps"]
        }
    )
    report = {
        "arlight": __version__,
        "commit": commit(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "python": sys.version.split()[0],
        "libraries": _versions(),
        "data": data,
        "env_maps": maps,
        "frames": frames,
        "warmup": warmup,
        "sweeps": sweeps,
        "configs": configs,
    }
    if folds:
        report["folds"] = fold_figures(configs)
    return report


# --------------------------------------------------------------------------- tables


def _ms(spread: dict) -> str:
    if spread["median"] is None:
        return "-"
    return f"{spread['median']:.1f} [{spread['p10']:.0f}-{spread['p90']:.0f}]"


def _num(x: float | None, spec: str = ".1f") -> str:
    return "-" if x is None else format(x, spec)


def speed_table(report: dict) -> str:
    """The paper's table 1: median [p10-p90] milliseconds per stage, one column per config."""
    names = list(report["configs"])
    rows = ["| stage (ms) | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for stage in STAGES:
        rows.append(
            f"| {stage} | "
            + " | ".join(_ms(report["configs"][n]["stages_ms"][stage]) for n in names)
            + " |"
        )
    rows.append(
        "| total | " + " | ".join(_ms(report["configs"][n]["total_ms"]) for n in names) + " |"
    )
    if any(report["configs"][n].get("overlapped") for n in names):  # bench --overlap
        rows.append(
            "| ms between results | "
            + " | ".join(_ms(report["configs"][n]["period_ms"]) for n in names)
            + " |"
        )
    rows.append(
        "| FPS | " + " | ".join(_num(report["configs"][n]["fps"], ".2f") for n in names) + " |"
    )
    return "\n".join(rows)


def _worst(figures: dict) -> str:
    """ "12.3 (map_name)": the worst map's median (degrees) and its name."""
    return f"{figures['worst_map_median']:.1f} ({figures['worst_map']})"


def _by_map_cell(by_map: dict | None) -> str:
    if not by_map:
        return "-"
    return f"{by_map['median_over_maps']:.1f} / {by_map['p90_all_frames']:.1f} / {_worst(by_map)}"


def sh_direction_line(report: dict) -> str:
    """One sentence: each configuration's error of the SH's own direction (the reported
    one wherever no compact source is kept), by map where the report has maps, else by
    sequence; "" when no configuration has it."""
    accs = {name: c.get("accuracy") or {} for name, c in report["configs"].items()}
    by_map = any(a.get("by_map_sh") for a in accs.values())
    cells = []
    for name, a in accs.items():
        own = a.get("sh_angle_upper_deg") or {}
        if by_map and a.get("by_map_sh"):
            cells.append(f"{name} {_by_map_cell(a['by_map_sh'])}")
        elif not by_map and own.get("median_of_medians") is not None:
            cells.append(
                f"{name} {_num(own['median_of_medians'])} / {_num(own['p90_all_frames'])} / "
                f"{_num(own['worst_sequence_median'])}"
            )
    if not cells:
        return ""
    unit = (
        "median over maps / p90 over frames / worst map"
        if by_map
        else "median of medians / p90 / worst sequence"
    )
    return (
        "The SH's own direction, which a kept compact source's replaces as the reported one "
        f"(upper hemisphere, {unit}): " + "; ".join(cells) + "."
    )


def accuracy_table(report: dict) -> str:
    """The paper's table 2, per config: angular errors (degrees) against both truths, by
    sequence and by environment map, SH and shading errors (scale-free, 0 = exact), and the
    cost."""
    rows = [
        "| config | upper: median of medians / p90 / worst seq. | upper by map: median "
        "over maps / p90 over frames / worst map | whole sphere: median / p90 | SH error | "
        "shading error | confidence vs error (Spearman) | ms/frame |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, c in report["configs"].items():
        a = c["accuracy"]
        if a is None:
            continue
        up, whole = a["angle_upper_deg"], a["angle_deg"]
        rows.append(
            f"| {name} | {_num(up['median_of_medians'])} / {_num(up['p90_all_frames'])} / "
            f"{_num(up['worst_sequence_median'])} | {_by_map_cell(a.get('by_map'))} | "
            f"{_num(whole['median_of_medians'])} / "
            f"{_num(whole['p90_all_frames'])} | {_num(a['sh_error']['median_of_medians'], '.2f')}"
            f" | {_num(a['shading_error']['median_of_medians'], '.3f')} | "
            f"{_num(a.get('confidence_spearman'), '+.2f')} | "
            f"{_num(c['total_ms']['median'], '.0f')} |"
        )
    return "\n".join(rows) if len(rows) > 2 else ""


def sequence_table(report: dict) -> str:
    """Median angular error (degrees, upper truth) per sequence and config."""
    named = {n: c for n, c in report["configs"].items() if c["accuracy"] and not c["sweep"]}
    if not named:
        return ""
    seqs = list(next(iter(named.values()))["accuracy"]["sequences"])
    rows = ["| sequence | " + " | ".join(named) + " |", "|---|" + "---|" * len(named)]
    for s in seqs:
        rows.append(
            f"| {s} | "
            + " | ".join(
                _num(c["accuracy"]["sequences"].get(s, {}).get("angle_upper_deg"))
                for c in named.values()
            )
            + " |"
        )
    return "\n".join(rows)


def _mapped(report: dict) -> dict[str, dict]:
    """Config name -> its "by_map" figures, for the configs that have them."""
    return {
        n: c["accuracy"]["by_map"]
        for n, c in report["configs"].items()
        if c["accuracy"] and c["accuracy"].get("by_map")
    }


def map_table(report: dict) -> str:
    """Median angular error (degrees, upper truth) per environment map and config, then over
    maps: the median of the per-map medians, the 90th percentile over frames, the worst map."""
    mapped = _mapped(report)
    if not mapped:
        return ""
    first = next(iter(mapped.values()))
    rows = [
        "| environment map | layouts | frames | " + " | ".join(mapped) + " |",
        "|---|---|---|" + "---|" * len(mapped),
    ]
    for m in sorted({m for b in mapped.values() for m in b["maps"]}):
        info = first["maps"].get(m, {"layouts": [], "frames": 0})
        rows.append(
            f"| {m} | {', '.join(info['layouts'])} | {info['frames']} | "
            + " | ".join(_num(b["maps"].get(m, {}).get("median")) for b in mapped.values())
            + " |"
        )
    rows.append(
        "| median over maps | | | "
        + " | ".join(_num(b["median_over_maps"]) for b in mapped.values())
        + " |"
    )
    rows.append(
        "| p90 over frames | | | "
        + " | ".join(_num(b["p90_all_frames"]) for b in mapped.values())
        + " |"
    )
    rows.append("| worst map | | | " + " | ".join(_worst(b) for b in mapped.values()) + " |")
    return "\n".join(rows)


def layout_table(report: dict) -> str:
    """Per layout and config (degrees, upper truth): the median over that layout's maps of
    their medians / the 90th percentile over its frames / its worst map."""
    mapped = _mapped(report)
    if not mapped:
        return ""
    rows = ["| layout | maps | " + " | ".join(mapped) + " |", "|---|---|" + "---|" * len(mapped)]
    first = next(iter(mapped.values()))
    for layout in sorted({lay for b in mapped.values() for lay in b["layouts"]}):
        maps = first["layouts"].get(layout, {}).get("maps", {})
        rows.append(
            f"| {layout} | {len(maps)} | "
            + " | ".join(_by_map_cell(b["layouts"].get(layout)) for b in mapped.values())
            + " |"
        )
    return "\n".join(rows)


def folds_table(report: dict) -> str:
    """Leave one map out (report "folds"): per held-out map the candidate chosen on the other
    maps, its error on the held-out map and every candidate's there (degrees, upper truth);
    then the median over held-out maps, against each candidate kept fixed. Only the note
    when there is nothing to choose; "" without folds."""
    folds = report.get("folds")
    if folds is None:
        return ""
    if folds.get("note"):
        return f"Leave one map out: {folds['note']}."
    names = folds["candidates"]
    rows = [
        "| held-out map | chosen on the other maps (their median) | its error on the map | "
        + " | ".join(names)
        + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    for f in folds["folds"]:
        rows.append(
            f"| {f['held_out']} | {f['chosen']} ({f['in_sample']:.1f}) | "
            f"{f['chosen_error']:.1f} | "
            + " | ".join(f"{f['errors'][n]:.1f}" for n in names)
            + " |"
        )
    rows.append(
        f"| median over held-out maps | chosen per fold | "
        f"{folds['held_out_median']:.1f} | "
        + " | ".join(f"{folds['fixed_median'][n]:.1f}" for n in names)
        + " |"
    )
    best = folds["best_in_sample"]
    differ = sum(f["chosen"] != best for f in folds["folds"])
    rows += [
        "",
        f"Chosen on all maps: {best} ({folds['fixed_median'][best]:.1f} median over "
        f"maps, in sample). Chosen without the map it is scored on: "
        f"{folds['held_out_median']:.1f} median over {len(folds['folds'])} held-out maps; "
        f"the choice differs from {best} in {differ} of them.",
    ]
    return "\n".join(rows)


def model_table(report: dict) -> str:
    """Per config: SH bands solved for, still-camera reuse, the volume's memory."""
    named = {n: c["model"] for n, c in report["configs"].items() if "model" in c}
    if not named:
        return ""
    rows = [
        "| config | SH bands solved (of requested): frames | frames reusing a still "
        "camera's Surface / RadTransfer | volume: allocated (median) / initial capacity / "
        "dense grid, MB |",
        "|---|---|---|---|",
    ]
    for name, m in named.items():
        bands = ", ".join(f"{b}: {n}" for b, n in m["bands_estimated_frames"].items())
        reused = m["reused_share"]
        rows.append(
            f"| {name} | ({m['bands_requested']}) {bands} | "
            f"{100 * reused['Surface']:.0f} % / {100 * reused['RadTransfer']:.0f} % | "
            f"{m['volume_mb_median']:.0f} / {m['volume_capacity_mb']:.0f} / "
            f"{m['volume_dense_mb']:.0f} |"
        )
    return "\n".join(rows)


def markdown(report: dict) -> str:
    libs = ", ".join(f"{k} {v}" for k, v in report["libraries"].items())
    parts = [
        "# arlight bench",
        "",
        f"commit {report['commit']}, arlight {report['arlight']}, {report['machine']} with "
        f"{report['cpus']} CPUs, Python {report['python']}; {libs}.",
        f"Data: {', '.join(report['data'])}; warm-up {report['warmup']} frame(s) per sequence "
        "left out of the timings; poses from the data (tracking skipped).",
        "",
        "## Milliseconds per stage (median [p10-p90])",
        "",
        speed_table(report),
    ]
    acc = accuracy_table(report)
    if acc:
        parts += [
            "",
            "## Accuracy",
            "",
            "Angular error of the dominant light direction in degrees: against the light "
            "that can reach the scene (upper hemisphere) and the whole sphere. SH and "
            "shading errors are relative L2 after the best common scale (0 = exact, 1 = "
            "no better than nothing), against the upper-hemisphere SH.",
            "",
            acc,
        ]
        own = sh_direction_line(report)
        if own:
            parts += ["", own]
        seq = sequence_table(report)
        if seq:
            parts += ["", "## Per sequence (median degrees, upper hemisphere)", "", seq]
        maps = map_table(report)
        if maps:
            parts += [
                "",
                "## Per environment map (median degrees, upper hemisphere)",
                "",
                f"Maps: {', '.join(report.get('env_maps', []))}. Each map's figure is "
                "the median over the frames it lit (any sequence); the rows below "
                "aggregate over maps, so a map seen in many sequences counts once.",
                "",
                maps,
                "",
                "### Per layout (median over maps / p90 over frames / worst map, degrees)",
                "",
                layout_table(report),
            ]
    folds = folds_table(report)
    if folds:
        parts += [
            "",
            "## Leave one map out (degrees, upper hemisphere)",
            "",
            "Each map in turn is held out: the configuration with the lowest median over "
            "the other maps is chosen and scored on the held-out map. Compare the "
            "median over held-out maps with each configuration kept fixed.",
            "",
            folds,
        ]
    model = model_table(report)
    if model:
        parts += [
            "",
            "## What the scenes required",
            "",
            "SH bands: the light estimate solves only for the bands the observed normals "
            "constrain (condition of the normal matrix). Reuse: frames of a camera held "
            "still whose volume cast (Surface) and geometry and transfer (DynGeo, "
            "RadTransfer) were those of an earlier frame (ReuseParams). Volume: "
            "sparse blocks allocated only where depth was seen.",
            "",
            model,
        ]
    parts += ["", "![trade](trade.png)", ""]
    return "\n".join(parts)


# --------------------------------------------------------------------------- plot


def trade_plot(report: dict, path: Path) -> bool:
    """ms/frame against median angular error (upper truth); False when nothing to plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = {
        n: c
        for n, c in report["configs"].items()
        if c["accuracy"] and c["total_ms"]["median"] is not None
    }
    if not points:
        return False
    fig, ax = plt.subplots(figsize=(7, 5), dpi=120)
    for sweep in report["sweeps"]:
        line = [
            (
                c["total_ms"]["median"],
                c["accuracy"]["angle_upper_deg"]["median_of_medians"],
                c["value"],
            )
            for c in points.values()
            if c["sweep"] == sweep
        ]
        if line:
            xs, ys, labels = zip(*line, strict=True)
            ax.plot(xs, ys, "o-", label=f"sweep {sweep}")
            for x, y, label in zip(xs, ys, labels, strict=True):
                ax.annotate(
                    str(label), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7
                )
    for name, c in points.items():
        if c["sweep"] is None:
            x, y = c["total_ms"]["median"], c["accuracy"]["angle_upper_deg"]["median_of_medians"]
            ax.plot([x], [y], "s", markersize=8)
            ax.annotate(name, (x, y), textcoords="offset points", xytext=(5, -10))
    ax.set_xlabel("milliseconds per frame (median, pipeline only)")
    ax.set_ylabel("median angular error, degrees (upper hemisphere)")
    data = report["data"]
    shown = ", ".join(data) if len(data) <= 3 else f"{len(data)} sequences"
    ax.set_title(f"speed / accuracy trade ({shown})", fontsize=9)
    ax.grid(True, alpha=0.3)
    if report["sweeps"]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return True


def write_report(report: dict, out_dir: str | Path) -> list[Path]:
    """report.json, report.md and trade.png in out_dir; returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "report.json", out / "report.md"]
    written[0].write_text(json.dumps(report, indent=1) + "\n")
    written[1].write_text(markdown(report))
    if trade_plot(report, out / "trade.png"):
        written.append(out / "trade.png")
    return written
