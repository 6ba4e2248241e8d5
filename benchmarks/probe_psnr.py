"""Mirror and glossy virtual objects against path-traced truth: the reflection probe (issue 33).

For each sequence with AR pairs (`arlight synth --ar-frames`, or the corpus), the Pipeline
runs over its frames with the true poses and `ar/virtual_scene.json`; at each frame with a
pair it renders the composite four ways and scores PSNR (dB, 8-bit) inside the pixels of the
virtual sphere (the truth's mask_virtual where our buffer shows the sphere: the object whose
material is mirror / glossy / diffuse; the arch is always diffuse):
  probe:    the reflection probe of the room (this issue), as configured (by default the
            directions that leave the room see the SH, Hanning-windowed),
  probe_sun: the same probe with the SH's dominant part drawn as a 2-degree disc
            (probe_sun=true),
  probe_nowindow: the same probe with the SH of the misses as it is, not Hanning-windowed
            (probe_sh_window=false),
  sh_probe: a probe of the distant light alone (the plain SH, not windowed: baseline (a)),
  diffuse:  the diffuse renderer (every object Lambertian: baseline (b)),
each with the estimated light and with the true light (lighting_gt.json, exposure applied;
the probe's misses then see the true SH too). Writes report.json, report.md and, per
sequence, the first pair's crops (input, probe, SH probe, diffuse, truth) to --out.

    nice -n 10 .venv/bin/python benchmarks/probe_psnr.py SEQ [SEQ ...] [--preset full]
        [--out DIR] [--set KEY=VALUE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from arlight.pipeline.config import Config
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.probe import DistantLight, ProbeSettings, ProbeStage
from arlight.pipeline.runtime import configure_process
from arlight.sources.sequence import open_sequence
from arlight.sources.virtual_scene_file import load_virtual_scene
from benchmarks.ar_truth import psnr, side_by_side, truth_light

VARIANTS = ("probe", "probe_sun", "probe_nowindow", "sh_probe", "diffuse")
LIGHTS = ("est", "gt")


def material_name(material) -> str:
    """mirror / glossyR / diffuse, as the synth's --virtual-material."""
    if material.mirror:
        return "mirror"
    if material.roughness < 1.0 or material.metalness > 0.0:
        return f"glossy{material.roughness:g}"
    return "diffuse"


def evaluate(folder: Path, preset: str, overrides: dict, out: Path | None) -> list[dict]:
    """One row per frame with a pair: PSNR of every variant x light on the sphere's pixels."""
    ar = folder / "ar"
    info = json.loads((ar / "virtual_scene.json").read_text())
    truth = json.loads((folder / "lighting_gt.json").read_text())
    pairs = set(info["frames_rendered"])
    seq = open_sequence(folder, use_poses=True, max_frames=max(pairs) + 1)
    config = Config.from_preset(preset, **overrides)
    scene = load_virtual_scene(ar / "virtual_scene.json")
    pipeline = Pipeline(config, seq.camera, scene)
    sphere = next(i for i, o in enumerate(scene.objects) if "sphere" in o.name)
    material = material_name(scene.objects[sphere].material)
    rows = []
    for index, frame in enumerate(seq.frames):
        t0 = time.perf_counter()
        result = pipeline.process(frame)
        process_ms = 1e3 * (time.perf_counter() - t0)
        if index not in pairs:
            continue
        inputs, output = pipeline.last_render
        renderer = pipeline._renderer
        stage = pipeline._probe
        probe = pipeline.last_probe
        frame_truth = truth["frames"][index]
        if truth.get("truth_reference") == "probe":  # the room: the light inside it
            frame_truth = frame_truth["probe"]
        l_gt, rgb_gt = truth_light(frame_truth, truth["exposure_scale"])
        distant = {
            "est": DistantLight(inputs.light_sh, inputs.light_rgb),
            "gt": DistantLight(l_gt, rgb_gt),
        }
        sh_stage = ProbeStage(
            ProbeSettings(config.render.probe_size, room=False, window=False), pipeline.camera
        )
        with_sun = plain = None
        if stage is not None:
            with_sun = ProbeStage(dataclasses.replace(stage.settings, sun=True), pipeline.camera)
            with_sun.grid = stage.grid
            plain = ProbeStage(dataclasses.replace(stage.settings, window=False), pipeline.camera)
            plain.grid = stage.grid
        images = {}
        for light in LIGHTS:
            base = dataclasses.replace(
                inputs, light_sh=distant[light].sh, light_rgb=distant[light].rgb
            )
            room = (
                stage.probe(probe.point_world, inputs.world_from_cam, distant[light])
                if stage is not None and probe is not None
                else None
            )
            point = probe.point_world if probe is not None else np.zeros(3)
            only_sh = sh_stage.probe(point, inputs.world_from_cam, distant[light])
            images[f"probe_{light}"] = renderer.render(
                dataclasses.replace(base, probe=room)
            ).composite
            if plain is not None and probe is not None:
                raw = plain.probe(probe.point_world, inputs.world_from_cam, distant[light])
                images[f"probe_nowindow_{light}"] = renderer.render(
                    dataclasses.replace(base, probe=raw)
                ).composite
            if with_sun is not None and probe is not None:
                sunny = with_sun.probe(probe.point_world, inputs.world_from_cam, distant[light])
                images[f"probe_sun_{light}"] = renderer.render(
                    dataclasses.replace(base, probe=sunny)
                ).composite
            images[f"sh_probe_{light}"] = renderer.render(
                dataclasses.replace(base, probe=only_sh)
            ).composite
            images[f"diffuse_{light}"] = renderer.render(
                dataclasses.replace(base, probe=None)
            ).composite
        name = f"{index:06d}.png"
        real_virtual = cv2.imread(str(ar / "real_virtual" / name), cv2.IMREAD_COLOR)[..., ::-1]
        virtual = cv2.imread(str(ar / "mask_virtual" / name), cv2.IMREAD_GRAYSCALE) > 127
        ours_sphere = output.gbuffer.object_index == sphere
        mask = virtual & ours_sphere
        row = {
            "sequence": folder.name,
            "material": material,
            "preset": preset,
            "frame": index,
            "sphere_pixels": int(mask.sum()),
            "probe_ms": result.timings_ms.get("Probe", 0.0),
            "rendering_ms": result.timings_ms.get("Rendering", 0.0),
            "process_ms": process_ms,
            "probe_diagnostics": result.diagnostics.get("probe"),
        }
        for key in (f"{v}_{light}" for light in LIGHTS for v in VARIANTS):
            image = images.get(key)
            row[f"{key}_psnr"] = float("nan") if image is None else psnr(image, real_virtual, mask)
        rows.append(row)
        print(
            f"  {folder.name} ({material}) frame {index}: sphere PSNR "
            + "  ".join(f"{k} {row[f'{k}_psnr']:.1f}" for k in images)
            + f"  probe {row['probe_ms']:.0f} ms",
            flush=True,
        )
        if out is not None and index == min(pairs) and mask.any():
            v, u = np.nonzero(mask)
            pad = 12
            v0, v1 = max(0, v.min() - pad), min(mask.shape[0], v.max() + pad)
            u0, u1 = max(0, u.min() - pad), min(mask.shape[1], u.max() + pad)
            crops = [
                im[v0:v1, u0:u1]
                for im in (
                    inputs.color,
                    images["probe_est"],
                    images["sh_probe_est"],
                    images["diffuse_est"],
                    real_virtual,
                )
            ]
            scale = max(1, 240 // max(1, v1 - v0))
            crops = [
                cv2.resize(c, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
                for c in crops
            ]
            cv2.imwrite(
                str(out / f"{folder.name}_{name}"),
                side_by_side(crops, ["input", "probe", "SH probe", "diffuse", "truth"]),
            )
    return rows


def summary_table(rows: list[dict]) -> str:
    """Markdown: per material, the median over frames of each variant x light."""
    heads = [f"{v} {light}" for light in LIGHTS for v in VARIANTS]
    lines = [
        "| material | sequences | frames | " + " | ".join(heads) + " | probe - SH probe (est) |",
        "|---|---|---|" + "---|" * (len(heads) + 1),
    ]
    for material in sorted({r["material"] for r in rows}):
        sel = [r for r in rows if r["material"] == material and r["sphere_pixels"] > 0]
        if not sel:
            continue
        med = {
            h: float(np.nanmedian([r[f"{h.replace(' ', '_')}_psnr"] for r in sel])) for h in heads
        }
        gain = float(np.nanmedian([r["probe_est_psnr"] - r["sh_probe_est_psnr"] for r in sel]))
        lines.append(
            f"| {material} | {len({r['sequence'] for r in sel})} | {len(sel)} | "
            + " | ".join(f"{med[h]:.1f}" for h in heads)
            + f" | {gain:+.1f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequences", nargs="+", metavar="SEQ", help="folders with an ar/ folder")
    parser.add_argument("--preset", default="full", choices=("full", "fast", "mobile"))
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--out", type=Path, default=Path("probe_report"))
    args = parser.parse_args(argv)
    configure_process()
    overrides = {}
    for kv in args.set:
        key, _, value = kv.partition("=")
        try:
            overrides[key] = Config.parse_flat_value(key, value)
        except ValueError as exc:
            parser.error(f"--set {kv}: {exc}")
    folders = [Path(s) for s in args.sequences]
    for f in folders:
        if not (f / "ar" / "virtual_scene.json").is_file():
            parser.error(f"{f} has no ar/virtual_scene.json")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for folder in folders:
        rows.extend(evaluate(folder, args.preset, overrides, args.out))
    table = summary_table(rows)
    (args.out / "report.json").write_text(json.dumps({"rows": rows}, indent=1, default=str))
    (args.out / "report.md").write_text(
        "PSNR (dB) on the virtual sphere's pixels against ar/real_virtual, median over "
        "the frames with a pair\n\n" + table + "\n"
    )
    print(table)
    print(f"wrote {args.out}/report.json, report.md and crops")
    return 0


if __name__ == "__main__":
    sys.exit(main())
