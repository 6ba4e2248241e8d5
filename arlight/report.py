"""The benchmark report: figures (report.json), tables (report.md) and the trade plot (trade.png).

Tables in the style of the paper's tables 1 (milliseconds per stage) and 2 (accuracy); the
plot puts every configuration at (milliseconds per frame, median angular error against the
upper-hemisphere truth), sweeps joined in their order.
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


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=False, cwd=os.path.dirname(__file__)
                              ).stdout.strip() or "unknown"
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
    return {"median": float(np.median(v)), "p10": float(np.percentile(v, 10)),
            "p90": float(np.percentile(v, 90))}


def _finite(values: list[float]) -> list[float]:
    return [x for x in values if math.isfinite(x)]


def _accuracy(per_sequence: dict[str, dict[str, list[float]]]) -> dict | None:
    """Aggregates over sequences: median of per-sequence medians, p90 over all frames."""
    scored = {name: s for name, s in per_sequence.items() if s["angle_upper_deg"]}
    if not scored:
        return None
    out: dict = {"sequences": {}}
    for name, s in scored.items():
        out["sequences"][name] = {
            key: (float(np.median(_finite(v))) if _finite(v) else None) for key, v in s.items()}
        out["sequences"][name]["p90_angle_upper_deg"] = float(
            np.percentile(s["angle_upper_deg"], 90))
        out["sequences"][name]["frames"] = len(s["angle_upper_deg"])
    for key in ("angle_upper_deg", "angle_deg", "sh_error", "shading_error"):
        medians = [m[key] for m in out["sequences"].values() if m[key] is not None]
        every = [x for s in scored.values() for x in _finite(s[key])]
        out[key] = {"median_of_medians": float(np.median(medians)) if medians else None,
                    "p90_all_frames": float(np.percentile(every, 90)) if every else None,
                    "worst_sequence_median": float(max(medians)) if medians else None}
    out["confidence_spearman"] = confidence_spearman(scored)
    return out


def confidence_spearman(per_sequence: dict[str, dict[str, list[float]]]) -> float | None:
    """Spearman rank correlation over all frames between confidence.value and the angular
    error against the upper hemisphere (negative: confidence falls as the error grows);
    None when fewer than 3 frames or either is constant."""
    from scipy.stats import spearmanr

    pairs = [(c, e) for s in per_sequence.values()
             for c, e in zip(s.get("confidence", []), s["angle_upper_deg"], strict=False)
             if math.isfinite(c) and math.isfinite(e)]
    if len(pairs) < 3 or len({c for c, _ in pairs}) < 2 or len({e for _, e in pairs}) < 2:
        return None
    return float(spearmanr(*zip(*pairs, strict=True)).statistic)


def _model(result, config) -> dict:
    """What the scene required of the model (bench.ConfigResult): the SH bands solved for
    (frames per count), the share of frames whose stage outputs a still camera reused, and
    the volume's allocated blocks (median over sequences) against its initial hash-map
    capacity and against a dense grid of the same voxel size over volume_size_m."""
    v = config.volume
    block_bytes = v.block_resolution ** 3 * 8  # tsdf + weight, float32
    dense_blocks = math.ceil(v.volume_resolution / v.block_resolution) ** 3
    blocks = [b for b in result.volume_blocks.values() if b > 0]
    frames = len(result.bands_estimated)
    return {
        "bands_requested": config.transfer.sh_bands,
        "bands_estimated_frames": {str(b): result.bands_estimated.count(b)
                                   for b in sorted(set(result.bands_estimated), reverse=True)},
        "reused_share": {stage: (sum(flags) / frames if frames else 0.0)
                         for stage, flags in result.reused.items()},
        "volume_blocks_median": float(np.median(blocks)) if blocks else 0.0,
        "volume_mb_median": float(np.median(blocks)) * block_bytes / 2**20 if blocks else 0.0,
        "volume_capacity_mb": v.block_count * block_bytes / 2**20 if v.use_volume else 0.0,
        "volume_dense_mb": dense_blocks * block_bytes / 2**20 if v.use_volume else 0.0,
    }


def summarise(results: list, data: list[str], frames: int | None, warmup: int,
              sweeps: list[str], configs_used: list | None = None) -> dict:
    """The report as plain JSON values (what report.json holds). configs_used: the
    pipeline Config of each result, in order (for the "model" figures; None: left out)."""
    configs = {}
    for k, r in enumerate(results):
        total = _spread(r.total_ms)
        configs[r.name] = {
            "overrides": r.overrides, "sweep": r.sweep, "value": r.value,
            "stages_ms": {s: _spread(v) for s, v in r.stage_ms.items()},
            "total_ms": total,
            "fps": 1000.0 / total["median"] if total["median"] else None,
            "accuracy": _accuracy(r.per_sequence),
        }
        if configs_used is not None:
            configs[r.name]["model"] = _model(r, configs_used[k])
    return {
        "arlight": __version__, "commit": _commit(), "machine": platform.machine(),
        "cpus": os.cpu_count(), "python": sys.version.split()[0], "libraries": _versions(),
        "data": data, "frames": frames, "warmup": warmup, "sweeps": sweeps,
        "configs": configs,
    }


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
    rows = ["| stage (ms) | " + " | ".join(names) + " |",
            "|---|" + "---|" * len(names)]
    for stage in STAGES:
        rows.append(f"| {stage} | " + " | ".join(
            _ms(report["configs"][n]["stages_ms"][stage]) for n in names) + " |")
    rows.append("| total | " + " | ".join(_ms(report["configs"][n]["total_ms"])
                                         for n in names) + " |")
    rows.append("| FPS | " + " | ".join(_num(report["configs"][n]["fps"], ".2f")
                                       for n in names) + " |")
    return "\n".join(rows)


def accuracy_table(report: dict) -> str:
    """The paper's table 2, per config: angular errors (degrees) against both truths, SH and
    shading errors (scale-free, 0 = exact), and the cost."""
    rows = ["| config | upper: median of medians / p90 / worst seq. | whole sphere: median / "
            "p90 | SH error | shading error | confidence vs error (Spearman) | ms/frame |",
            "|---|---|---|---|---|---|---|"]
    for name, c in report["configs"].items():
        a = c["accuracy"]
        if a is None:
            continue
        up, whole = a["angle_upper_deg"], a["angle_deg"]
        rows.append(
            f"| {name} | {_num(up['median_of_medians'])} / {_num(up['p90_all_frames'])} / "
            f"{_num(up['worst_sequence_median'])} | {_num(whole['median_of_medians'])} / "
            f"{_num(whole['p90_all_frames'])} | {_num(a['sh_error']['median_of_medians'], '.2f')}"
            f" | {_num(a['shading_error']['median_of_medians'], '.3f')} | "
            f"{_num(a.get('confidence_spearman'), '+.2f')} | "
            f"{_num(c['total_ms']['median'], '.0f')} |")
    return "\n".join(rows) if len(rows) > 2 else ""


def sequence_table(report: dict) -> str:
    """Median angular error (degrees, upper truth) per sequence and config."""
    named = {n: c for n, c in report["configs"].items() if c["accuracy"] and not c["sweep"]}
    if not named:
        return ""
    seqs = list(next(iter(named.values()))["accuracy"]["sequences"])
    rows = ["| sequence | " + " | ".join(named) + " |", "|---|" + "---|" * len(named)]
    for s in seqs:
        rows.append(f"| {s} | " + " | ".join(
            _num(c["accuracy"]["sequences"].get(s, {}).get("angle_upper_deg"))
            for c in named.values()) + " |")
    return "\n".join(rows)


def model_table(report: dict) -> str:
    """Per config: SH bands solved for, still-camera reuse, the volume's memory."""
    named = {n: c["model"] for n, c in report["configs"].items() if "model" in c}
    if not named:
        return ""
    rows = ["| config | SH bands solved (of requested): frames | frames reusing a still "
            "camera's Surface / RadTransfer | volume: allocated (median) / initial capacity / "
            "dense grid, MB |", "|---|---|---|---|"]
    for name, m in named.items():
        bands = ", ".join(f"{b}: {n}" for b, n in m["bands_estimated_frames"].items())
        reused = m["reused_share"]
        rows.append(f"| {name} | ({m['bands_requested']}) {bands} | "
                    f"{100 * reused['Surface']:.0f} % / {100 * reused['RadTransfer']:.0f} % | "
                    f"{m['volume_mb_median']:.0f} / {m['volume_capacity_mb']:.0f} / "
                    f"{m['volume_dense_mb']:.0f} |")
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
        parts += ["", "## Accuracy", "",
                  "Angular error of the dominant light direction in degrees: against the light "
                  "that can reach the scene (upper hemisphere) and the whole sphere. SH and "
                  "shading errors are relative L2 after the best common scale (0 = exact, 1 = "
                  "no better than nothing), against the upper-hemisphere SH.", "", acc]
        seq = sequence_table(report)
        if seq:
            parts += ["", "## Per sequence (median degrees, upper hemisphere)", "", seq]
    model = model_table(report)
    if model:
        parts += ["", "## What the scenes required", "",
                  "SH bands: the light estimate solves only for the bands the observed normals "
                  "constrain (condition of the normal matrix). Reuse: frames of a camera held "
                  "still whose volume cast (Surface) and geometry and transfer (DynGeo, "
                  "RadTransfer) were those of an earlier frame (ReuseParams). Volume: "
                  "sparse blocks allocated only where depth was seen.", "", model]
    parts += ["", "![trade](trade.png)", ""]
    return "\n".join(parts)


# --------------------------------------------------------------------------- plot

def trade_plot(report: dict, path: Path) -> bool:
    """ms/frame against median angular error (upper truth); False when nothing to plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = {n: c for n, c in report["configs"].items()
              if c["accuracy"] and c["total_ms"]["median"] is not None}
    if not points:
        return False
    fig, ax = plt.subplots(figsize=(7, 5), dpi=120)
    for sweep in report["sweeps"]:
        line = [(c["total_ms"]["median"], c["accuracy"]["angle_upper_deg"]["median_of_medians"],
                 c["value"]) for c in points.values() if c["sweep"] == sweep]
        if line:
            xs, ys, labels = zip(*line, strict=True)
            ax.plot(xs, ys, "o-", label=f"sweep {sweep}")
            for x, y, label in zip(xs, ys, labels, strict=True):
                ax.annotate(str(label), (x, y), textcoords="offset points", xytext=(4, 4),
                            fontsize=7)
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
