"""`arlight synth`: render one ground-truth sequence, or the benchmark corpus (resumable)."""

from __future__ import annotations

import argparse
import fnmatch
import os
import sys
import time
from pathlib import Path

EXIT_BAD_INPUT = 2
DEFAULT_MAPS = Path("..") / "shared" / "data" / "hdri"


def default_cache() -> Path:
    """Where the corpus is rendered by default: $XDG_CACHE_HOME/arlight/corpus."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "arlight" / "corpus"


def _frames_list(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected frame indices like 1,4, got {text!r}") from None


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 640x480, got {text!r}") from None
    return w, h


def add_parser(sub) -> None:
    from arlight.synth.layouts import LAYOUTS
    from arlight.synth.virtual_objects import VIRTUAL_MATERIALS

    p = sub.add_parser(
        "synth",
        help="render ground-truth RGB-D sequences under HDR maps (Mitsuba 3)",
        description="Path-trace RGB-D sequences with per-frame lighting truth, in the layout "
        "of ../shared/data/synthetic (TUM folders, camera.json, groundtruth.txt, "
        "clean and sensor-like depth, lighting_gt.json, AR pairs in ar/). Either "
        "one sequence (--map, --layout, --out) or the benchmark corpus (--corpus: "
        "64 sequences over the 26 shared maps, into a cache folder, resumable). "
        "Needs the synth extra: pip install 'arlight[synth]'.",
    )
    p.add_argument(
        "--map",
        action="append",
        default=[],
        metavar="NAME|FILE",
        help="equirectangular HDR map (.hdr/.exr; 2:1), a file or a name in "
        "--maps-dir; give it twice for a light change at --change-at",
    )
    p.add_argument(
        "--rotation",
        action="append",
        type=float,
        default=[],
        metavar="DEG",
        help="rotation of each --map about world +Y in degrees (default 0)",
    )
    p.add_argument(
        "--layout", default="static", choices=LAYOUTS, help="scene layout (default static)"
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        help="output folder: the sequence folder itself for one sequence; the "
        "corpus root with --corpus (default: " + str(default_cache()) + ")",
    )
    p.add_argument("--frames", type=int, default=8, metavar="N", help="frames (default 8)")
    p.add_argument(
        "--size",
        type=_size,
        default=(640, 480),
        metavar="WxH",
        help="image size (default 640x480; Kinect v1 focal length scaled)",
    )
    p.add_argument(
        "--spp",
        type=int,
        default=32,
        metavar="N",
        help="samples per pixel (default 32, as the shared set)",
    )
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument(
        "--change-at",
        type=int,
        metavar="FRAME",
        help="with two --map: the frame the second one takes over (default half-way)",
    )
    p.add_argument(
        "--ar-frames",
        type=_frames_list,
        default=(),
        metavar="I,J",
        help="frames rendered again with two virtual objects (AR pairs in ar/)",
    )
    p.add_argument(
        "--virtual-material",
        choices=VIRTUAL_MATERIALS,
        default="diffuse",
        help="the virtual sphere's material in the AR pairs (default diffuse)",
    )
    p.add_argument(
        "--maps-dir",
        default=str(DEFAULT_MAPS),
        metavar="DIR",
        help="where map names are looked up (default ../shared/data/hdri)",
    )
    p.add_argument(
        "--corpus",
        nargs="?",
        const="builtin",
        metavar="FILE",
        help="render the corpus: the built-in definition, or a definition FILE",
    )
    p.add_argument(
        "--only",
        metavar="PATTERN",
        help="with --corpus: only sequences whose name matches (glob, e.g. '*room*')",
    )
    p.add_argument(
        "--limit",
        type=int,
        metavar="N",
        help="with --corpus: only the first N sequences (the order covers every layout early)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from arlight.synth.environment import MapError
    from arlight.synth.render import MissingExtra

    try:
        return _corpus(args) if args.corpus else _one(args)
    except MissingExtra as exc:
        print(f"arlight synth: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except MapError as exc:
        print(f"arlight synth: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


def _progress(total: int, label: str):
    from tqdm import tqdm

    return tqdm(
        total=total, unit="frame", desc=label, disable=not sys.stderr.isatty(), dynamic_ncols=True
    )


def _one(args: argparse.Namespace) -> int:
    from arlight.synth.render import mitsuba
    from arlight.synth.sequence import LightState, SequenceSpec, generate

    if not args.map:
        raise ValueError("give --map NAME|FILE (an equirectangular HDR map), or --corpus")
    if not args.out:
        raise ValueError("give --out DIR, the sequence folder to write")
    if len(args.map) > 2:
        raise ValueError("--map: at most two maps (a light change)")
    if len(args.rotation) > len(args.map):
        raise ValueError(
            f"--rotation given {len(args.rotation)} times for {len(args.map)} --map: one per map"
        )
    rotations = list(args.rotation) + [0.0] * (len(args.map) - len(args.rotation))
    change = args.change_at if args.change_at is not None else args.frames // 2
    if len(args.map) == 2 and not 0 < change < args.frames:
        raise ValueError(f"--change-at must be in 1..{args.frames - 1}, got {change}")
    lights = tuple(
        LightState(m, float(r), 0 if k == 0 else change)
        for k, (m, r) in enumerate(zip(args.map, rotations, strict=False))
    )
    out = Path(args.out)
    spec = SequenceSpec(
        out.name,
        args.layout,
        args.seed,
        lights,
        frames=args.frames,
        width=args.size[0],
        height=args.size[1],
        spp=args.spp,
        ar_frames=args.ar_frames,
        virtual_material=args.virtual_material,
    )
    spec.check(Path(args.maps_dir))
    mitsuba()
    bar = _progress(spec.frames, spec.name)
    t0 = time.perf_counter()
    try:
        stats = generate(
            spec,
            out.parent if str(out.parent) else Path("."),
            Path(args.maps_dir),
            on_frame=lambda: bar.update(1),
        )
    finally:
        bar.close()
    if stats.frames_rendered == 0:
        print(
            f"arlight synth: {out} is complete already (delete it to render it again)",
            file=sys.stderr,
        )
    else:
        print(
            f"arlight synth: wrote {out} ({spec.frames} frames, "
            f"{stats.seconds / max(1, stats.frames_rendered):.1f} s a frame, "
            f"{time.perf_counter() - t0:.0f} s in all)",
            file=sys.stderr,
        )
    return 0


def _corpus(args: argparse.Namespace) -> int:
    from arlight.synth.corpus import load_definition, render_corpus, specs
    from arlight.synth.render import mitsuba

    definition = load_definition(None if args.corpus == "builtin" else args.corpus)
    out = Path(args.out) if args.out else default_cache()
    chosen = specs(definition)
    if args.only:
        chosen = [s for s in chosen if fnmatch.fnmatch(s.name, args.only)]
    if args.limit is not None:
        chosen = chosen[: args.limit]
    if not chosen:
        raise ValueError("no sequence of the corpus selected (check --only and --limit)")
    names = {s.name for s in chosen}
    maps = Path(args.maps_dir)
    for spec in chosen:
        spec.check(maps)  # every map present before hours of rendering
    mitsuba()
    done = [s for s in chosen if (out / s.name / "lighting_gt.json").is_file()]
    bar = _progress(sum(s.frames for s in chosen), "corpus")
    bar.update(sum(s.frames for s in done))
    log = out / "render-log.jsonl"

    def finished(spec, stats) -> None:
        if stats.frames_rendered:
            import json

            with open(log, "a") as f:
                f.write(
                    json.dumps(
                        {
                            "sequence": spec.name,
                            "frames": spec.frames,
                            "renders": stats.renders,
                            "spp": spec.spp,
                            "seconds": round(stats.seconds, 2),
                            "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
                        }
                    )
                    + "\n"
                )
        if not sys.stderr.isatty():
            print(f"arlight synth: {spec.name} done", file=sys.stderr, flush=True)

    print(
        f"arlight synth: {len(chosen)} sequences ({len(done)} complete already) into {out}",
        file=sys.stderr,
    )
    try:
        render_corpus(
            definition,
            out,
            maps,
            only=lambda s: s.name in names and not (out / s.name / "lighting_gt.json").is_file(),
            on_frame=lambda: bar.update(1),
            on_sequence=finished,
        )
    finally:
        bar.close()
    print(f"arlight synth: corpus complete in {out}", file=sys.stderr)
    return 0
