"""Differential rendering against path-traced truth: the `ar/` pairs of the shared sequences.

For each sequence with an `ar/` folder (dev_a, dev_d in ../shared/data/synthetic) and each
preset, the Pipeline runs over the sequence's `rgb/` frames with the ground-truth poses and
the virtual scene `ar/virtual_scene.json`; at every frame with a pair it scores the
composite against `ar/real_virtual/NNNNNN.png`, as PSNR (dB) and SSIM inside
`mask_affected`, inside the shadow pixels (affected minus virtual) and on the virtual
objects themselves (`mask_virtual`), for
  (a) "estimated": the light the pipeline estimated (what users get),
  (b) "gt_light": the same frame re-rendered with the ground-truth light (lighting_gt.json,
      exposure applied; in a room, whose light the distant map does not describe, the
      light at the anchor, `probe`): rendering error without light-estimation error; its
      reflection probe is made anew from that light,
  (c) "gt_sun": the true light as SH plus the map's compact regions as sources drawn with
      hard shadows: the brightest, and up to --true-sources in all while each carries
      --true-source-share of the irradiance facing it (arlight.synth.environment.
      compact_regions; a night square's lamps, a softbox's panels),
  (d) "gt_full": gt_sun, its mirror and glossy objects reflecting a probe whose distant part
      is the true HDR map (what a streamed 360-degree panorama gives) instead of 4 SH bands,
  (e) "paste": the objects shaded by the estimated light and pasted, no shadows or bounce;
and "input" (the frame without objects) for scale. It writes side-by-side images (input,
ours, truth, 4x difference) of each sequence's first pair to --out, with report.json.

    .venv/bin/python benchmarks/ar_truth.py [SEQ ...] [--presets full fast] [--out DIR]
                                            [--set KEY=VALUE]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from arlight.pipeline import sh
from arlight.pipeline.color import LUMA
from arlight.pipeline.compact_stage import CompactLightStage
from arlight.pipeline.config import Config, DiffMode
from arlight.pipeline.glossy import mip_pyramid
from arlight.pipeline.pipeline import Pipeline
from arlight.pipeline.probe import DistantLight, ProbeResult
from arlight.pipeline.rendering import DifferentialRenderer, EnvironmentMap, RenderInputs
from arlight.pipeline.runtime import configure_process
from arlight.pipeline.sun_shadows import SourceLight
from arlight.sources.sequence import open_sequence
from arlight.sources.virtual_scene_file import load_virtual_scene

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "synthetic"
MAPS = DATA.parent / "hdri"
VARIANTS = ("input", "estimated", "gt_light", "gt_sun", "gt_full", "paste")


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (dB, peak 255) of two uint8 images over the mask's pixels (all channels)."""
    if not np.any(mask):
        return float("nan")
    d = a.astype(np.float64)[mask] - b.astype(np.float64)[mask]
    return 10.0 * math.log10(255.0**2 / max(float(np.mean(d * d)), 1e-12))


def ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM (Wang et al. 2004: Gaussian window sigma 1.5, K1 0.01, K2 0.03) of two
    uint8 RGB images, averaged over the channels."""
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    x, y = a.astype(np.float64), b.astype(np.float64)

    def blur(img):
        return cv2.GaussianBlur(img, (11, 11), 1.5)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean(axis=2)


def truth_light(
    frame_truth: dict, exposure: float, reference: str = "distant"
) -> tuple[np.ndarray, np.ndarray]:
    """(luminance SH in linear image units, our basis, world; per-channel factor (3,)).
    reference: the file's truth_reference; "probe": the light at the anchor (a room)."""
    source = frame_truth["probe"] if reference == "probe" else frame_truth
    l_gt = sh.toggle_condon_shortley(np.asarray(source["sh_lum_world"])) * exposure
    dc = np.maximum(_band0_rgb(source), 0.0)
    return l_gt, dc / max(float(LUMA @ dc), 1e-12)


def _band0_rgb(truth: dict) -> np.ndarray:
    """(3,) band 0 of a truth entry's `sh_rgb_world` (a list, or JSON text of one)."""
    rgb = truth["sh_rgb_world"]
    return np.asarray(json.loads(rgb) if isinstance(rgb, str) else rgb, np.float64)[:, 0]


def truth_sun(
    frame_truth: dict,
    exposure: float,
    l_gt: np.ndarray,
    maps_dir: Path,
    max_sources: int = 1,
    min_share: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, list[SourceLight]]:
    """The true light as the renderer's ambient SH plus the map's compact regions as sources
    (arlight.synth.environment.compact_regions: the brightest, then up to `max_sources` in
    all while each carries `min_share` of the irradiance facing it), each with its own
    colour (a warm sun under a blue sky): (ambient, its per-channel factor (3,), sources)."""
    from arlight.synth.environment import compact_regions

    name = frame_truth["env_map"]
    regions = compact_regions(
        _load_map(maps_dir / f"{name}.hdr"),
        float(frame_truth["env_rotation_deg"]),
        max_sources,
        min_share,
    )
    bands = math.isqrt(len(l_gt))
    ambient = np.array(l_gt, np.float64)
    dc_ambient = _band0_rgb(frame_truth)
    for region in regions:
        ambient -= sh.directional_light(region.direction, region.power * exposure, bands)
        # the region's share of each channel's band 0 (a delta of integrated radiance P: P Y00)
        dc_ambient = dc_ambient - region.rgb * sh.sh_basis(region.direction, 1)[0]
    dc_ambient = np.maximum(dc_ambient, 0.0)
    ambient_rgb = dc_ambient / max(float(LUMA @ dc_ambient), 1e-12)
    sources = []
    for region in regions:
        source_rgb = region.rgb / max(region.power, 1e-12) / np.maximum(ambient_rgb, 1e-6)
        radius = math.degrees(math.acos(max(-1.0, 1.0 - region.solid_angle_sr / (2 * math.pi))))
        sources.append(SourceLight(region.direction, region.power * exposure, source_rgb, radius))
    return ambient, ambient_rgb, sources


def truth_environment(frame_truth: dict, exposure: float, maps_dir: Path) -> EnvironmentMap:
    """The frame's true HDR map in linear image units, as a streamed panorama would give it
    (map_from_world: the inverse of the generator's rotation about world +Y)."""
    from arlight.synth.environment import rotation_y

    hdr = _load_map(maps_dir / f"{frame_truth['env_map']}.hdr") * exposure
    return EnvironmentMap(
        mip_pyramid(hdr.astype(np.float32)), rotation_y(float(frame_truth["env_rotation_deg"])).T
    )


def true_probe(
    pipeline: Pipeline, inputs: RenderInputs, distant: DistantLight
) -> ProbeResult | None:
    """The frame's reflection probe made anew (same room, same point) with `distant` as the
    light beyond the room; None where the frame had no probe."""
    if inputs.probe is None or pipeline._probe is None:
        return None
    return pipeline._probe.probe(inputs.probe.point_world, inputs.world_from_cam, distant)


@functools.lru_cache(maxsize=1)  # a sequence's frames share their map
def _load_map(path: Path) -> np.ndarray:
    from arlight.synth.environment import load_map

    return load_map(path)


def side_by_side(images: list[np.ndarray], names: list[str]) -> np.ndarray:
    """The images in a row with their names written in, BGR for cv2.imwrite."""
    tiles = []
    for image, name in zip(images, names, strict=True):
        tile = np.ascontiguousarray(image[..., ::-1])
        cv2.putText(
            tile, name, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2, cv2.LINE_AA
        )
        tiles.append(tile)
    return np.concatenate(tiles, axis=1)


def evaluate(
    folder: Path,
    preset: str,
    overrides: dict,
    out: Path | None,
    true_sources: tuple[int, float] = (4, 0.1),
) -> list[dict]:
    """One row per frame with a pair: PSNR/SSIM of every variant in both masks.
    true_sources: (most sources, least share) of the true light's compact sources."""
    ar = folder / "ar"
    info = json.loads((ar / "virtual_scene.json").read_text())
    truth = json.loads((folder / "lighting_gt.json").read_text())
    pairs = set(info["frames_rendered"])
    seq = open_sequence(folder, use_poses=True, max_frames=max(pairs) + 1)
    config = Config.from_preset(preset, **overrides)
    pipeline = Pipeline(config, seq.camera, load_virtual_scene(ar / "virtual_scene.json"))
    paste = DifferentialRenderer(
        pipeline.scene, seq.camera, config.replace(render_mode=DiffMode.PASTE)
    )
    rows = []
    for index, frame in enumerate(seq.frames):
        result = pipeline.process(frame)
        if index not in pairs:
            continue
        inputs, output = pipeline.last_render
        frame_truth, exposure = truth["frames"][index], truth["exposure_scale"]
        in_room = truth.get("truth_reference") == "probe"
        l_gt, rgb_gt = truth_light(frame_truth, exposure, truth.get("truth_reference", "distant"))
        gt_inputs = dataclasses.replace(
            inputs,
            light_sh=l_gt,
            light_rgb=rgb_gt,
            probe=true_probe(pipeline, inputs, DistantLight(l_gt, rgb_gt)),
        )
        t0 = time.perf_counter()
        with_gt = pipeline._renderer.render(gt_inputs).composite
        gt_ms = 1e3 * (time.perf_counter() - t0)
        with_sun = with_full = with_gt
        if "env_map" in frame_truth and MAPS.is_dir() and not in_room:
            # (a room: the map's sun is outside it, its light at the anchor is the probe's)
            ambient, ambient_rgb, sources = truth_sun(
                frame_truth, exposure, l_gt, MAPS, *true_sources
            )
            stage = pipeline.light.compact_stage or CompactLightStage(
                config.aux.aux_update_interval
            )
            occluder = stage.occluder(seq.camera.unproject(inputs.depth_m), pipeline._volume)
            sun_inputs = dataclasses.replace(
                gt_inputs,
                light_sh=ambient,
                light_rgb=ambient_rgb,
                sources=sources,
                real_occluder=occluder,
            )
            with_sun = pipeline._renderer.render(sun_inputs).composite
            environment = truth_environment(frame_truth, exposure, MAPS)
            full_probe = true_probe(
                pipeline, inputs, DistantLight(l_gt, rgb_gt, environment=environment)
            )
            with_full = pipeline._renderer.render(
                dataclasses.replace(sun_inputs, probe=full_probe)
            ).composite
        images = {
            "input": inputs.color,
            "estimated": output.composite,
            "gt_light": with_gt,
            "gt_sun": with_sun,
            "gt_full": with_full,
            "paste": paste.render(inputs).composite,
        }
        name = f"{index:06d}.png"
        real_virtual = cv2.imread(str(ar / "real_virtual" / name), cv2.IMREAD_COLOR)[..., ::-1]
        affected = cv2.imread(str(ar / "mask_affected" / name), cv2.IMREAD_GRAYSCALE) > 127
        virtual = cv2.imread(str(ar / "mask_virtual" / name), cv2.IMREAD_GRAYSCALE) > 127
        shadow = affected & ~virtual
        regions = {"affected": affected, "shadow": shadow, "virtual": virtual}
        row = {
            "sequence": folder.name,
            "preset": preset,
            "frame": index,
            "rendering_ms": result.timings_ms["Rendering"],
            "rendering_gt_ms": gt_ms,
            "virtual_iou": float(
                (output.virtual_mask & virtual).sum()
                / max(1, (output.virtual_mask | virtual).sum())
            ),
        }
        for variant, image in images.items():
            s = ssim_map(image, real_virtual)
            for region, mask in regions.items():
                row[f"{variant}_psnr_{region}"] = psnr(image, real_virtual, mask)
                row[f"{variant}_ssim_{region}"] = float(s[mask].mean()) if mask.any() else None
        rows.append(row)
        if out is not None and index == min(pairs):
            diff = np.clip(4 * np.abs(output.composite.astype(int) - real_virtual), 0, 255).astype(
                np.uint8
            )
            cv2.imwrite(
                str(out / f"{folder.name}_{preset}_{name}"),
                side_by_side(
                    [inputs.color, output.composite, with_gt, with_full, real_virtual, diff],
                    [
                        "input",
                        "ours (estimated light)",
                        "ours (true SH)",
                        "ours (true SH + sun + map)",
                        "path-traced truth",
                        "4x |estimated - truth|",
                    ],
                ),
            )
        print(
            f"  {folder.name} {preset} frame {index}: affected PSNR "
            + "  ".join(f"{v} {row[f'{v}_psnr_affected']:.1f}" for v in VARIANTS)
            + f"  rendering {row['rendering_ms']:.0f} ms",
            flush=True,
        )
    return rows


def summary_table(rows: list[dict]) -> str:
    """Markdown: per sequence and preset, the median over frames of each figure."""
    lines = [
        "| sequence | preset | region | " + " | ".join(VARIANTS) + " |",
        "|---|---|---|" + "---|" * len(VARIANTS),
    ]
    keys = sorted({(r["sequence"], r["preset"]) for r in rows})
    for seq, preset in keys:
        sel = [r for r in rows if r["sequence"] == seq and r["preset"] == preset]
        for region in ("affected", "shadow", "virtual"):
            cells = []
            for v in VARIANTS:
                p = np.nanmedian([r[f"{v}_psnr_{region}"] for r in sel])
                s = np.nanmedian(
                    [
                        np.nan if r[f"{v}_ssim_{region}"] is None else r[f"{v}_ssim_{region}"]
                        for r in sel
                    ]
                )
                cells.append(f"{p:.1f} dB / {s:.3f}")
            lines.append(f"| {seq} | {preset} | {region} | " + " | ".join(cells) + " |")
        ms = np.median([r["rendering_ms"] for r in sel])
        lines.append(
            f"| {seq} | {preset} | Rendering ms (median) | {ms:.0f} |" + " |" * (len(VARIANTS) - 1)
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "sequences",
        nargs="*",
        metavar="SEQ",
        help=f"sequence folders with an ar/ folder (default: all of {DATA} that have one)",
    )
    parser.add_argument(
        "--presets", nargs="+", default=["full", "fast"], choices=("full", "fast", "mobile")
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a Config field for every preset",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("ar_truth_report"),
        help="folder for report.json, report.md and the side-by-side images "
        "(default ar_truth_report/)",
    )
    parser.add_argument(
        "--true-sources",
        type=int,
        default=4,
        metavar="N",
        help="the true light's compact sources (gt_sun, gt_full): the map's brightest region "
        "and up to N in all (default 4; 1: the brightest alone)",
    )
    parser.add_argument(
        "--true-source-share",
        type=float,
        default=0.1,
        metavar="S",
        help="a region after the first is a source while it carries this share of the "
        "irradiance facing it (default 0.1)",
    )
    args = parser.parse_args(argv)
    if args.true_sources < 1:
        parser.error(f"--true-sources must be 1 or more, got {args.true_sources}")
    if not 0.0 <= args.true_source_share <= 1.0:
        parser.error(f"--true-source-share must be in 0..1, got {args.true_source_share:g}")
    configure_process()
    overrides = {}
    for kv in args.set:
        key, _, value = kv.partition("=")
        try:
            overrides[key] = Config.parse_flat_value(key, value)
        except ValueError as exc:
            parser.error(f"--set {kv}: {exc}")
    folders = [Path(s) for s in args.sequences] or sorted(
        p for p in DATA.glob("*") if (p / "ar" / "virtual_scene.json").is_file()
    )
    if not folders:
        print(
            f"no sequences with an ar/ folder at {DATA} (see ../shared/data/README.md)",
            file=sys.stderr,
        )
        return 2
    for f in folders:
        if not (f / "ar" / "virtual_scene.json").is_file():
            parser.error(f"{f} has no ar/virtual_scene.json")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for folder in folders:
        for preset in args.presets:
            rows.extend(
                evaluate(
                    folder,
                    preset,
                    overrides,
                    args.out,
                    (args.true_sources, args.true_source_share),
                )
            )
    table = summary_table(rows)
    (args.out / "report.json").write_text(
        json.dumps(
            {
                "rows": rows,
                "overrides": {k: str(v) for k, v in overrides.items()},
                "true_sources": [args.true_sources, args.true_source_share],
            },
            indent=1,
        )
    )
    (args.out / "report.md").write_text(
        "PSNR / SSIM against ar/real_virtual (median over "
        "the frames with a pair)\n\n" + table + "\n"
    )
    print(table)
    print(f"wrote {args.out}/report.json, report.md and side-by-side images")
    return 0


if __name__ == "__main__":
    sys.exit(main())
