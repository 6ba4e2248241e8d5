"""The benchmark corpus: its definition (committed as ``corpus.json``) and its rendering.

The definition lists every sequence (layout, seed, maps and rotations, frames, AR frames,
virtual material). :func:`make_definition` draws it from the maps' names and a seed, so the
file can be regenerated and checked (``tests/test_synth.py``); the committed file is what
``arlight synth --corpus`` renders. Rules: every layout on ``maps_per_layout`` different maps;
``indoor`` only on indoor maps; maps used as evenly as the layouts allow (every map in at
least two sequences); the sequences ordered round by round (one per layout per round), so
a corpus cut short still covers every layout and many maps.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from importlib import resources
from pathlib import Path

import numpy as np

from arlight.synth.layouts import LAYOUTS
from arlight.synth.sequence import LightState, SequenceSpec, generate
from arlight.synth.virtual_objects import VIRTUAL_MATERIALS

DEFINITION_FILE = "corpus.json"
# ../shared/data/README.md's table: the maps lit indoors (the rest are outdoor)
INDOOR_MAPS = (
    "empty_warehouse_01",
    "studio_small_03",
    "aerodynamics_workshop",
    "autoshop_01",
    "blocky_photo_studio",
    "brown_photostudio_01",
    "brown_photostudio_06",
    "brown_photostudio_07",
    "christmas_photo_studio_07",
    "circus_arena",
    "dancing_hall",
    "peppermint_powerplant",
    "sepulchral_chapel_rotunda",
    "studio_small_05",
    "thatch_chapel",
    "vestibule",
)
OUTDOOR_MAPS = (
    "venice_sunset",
    "potsdamer_platz",
    "forest_slope",
    "kiara_1_dawn",
    "aristea_wreck_puresky",
    "chinese_garden",
    "hilly_terrain_01",
    "modern_buildings_2",
    "phalzer_forest_01",
    "st_peters_square_night",
)
# the layout whose distant light never holds gets more samples: its interior is lit
# indirectly through openings, and 32 spp leave it too noisy to judge (docs/decisions)
SPP_FACTOR = {"room": 3}


def make_definition(
    maps: tuple[str, ...] = INDOOR_MAPS + OUTDOOR_MAPS,
    seed: int = 2026,
    maps_per_layout: int = 8,
    frames: int = 6,
    spp: int = 32,
    width: int = 640,
    height: int = 480,
) -> dict:
    """The corpus definition (a JSON-able dict) drawn from `seed`."""
    rng = np.random.default_rng(seed)
    uses = {m: 0 for m in maps}
    indoor = [m for m in maps if m in INDOOR_MAPS]
    chosen: dict[str, list[str]] = {}
    # indoor first (fewest candidates), then the rest; least-used maps first, ties at random
    for layout in sorted(LAYOUTS, key=lambda name: name != "indoor"):
        pool = indoor if layout == "indoor" else list(maps)
        order = sorted(pool, key=lambda m: (uses[m], rng.random()))
        chosen[layout] = order[:maps_per_layout]
        for m in chosen[layout]:
            uses[m] += 1
    sequences: list[dict] = []
    for r in range(maps_per_layout):
        for k, layout in enumerate(LAYOUTS):
            index = len(sequences)
            name_map = chosen[layout][r]
            rotation = float(rng.integers(0, 72) * 5)
            lights = [{"map": name_map, "rotation_deg": rotation, "from_frame": 0}]
            if layout == "light_change":
                if r % 2 == 0:  # the same map turned
                    lights.append(
                        {
                            "map": name_map,
                            "from_frame": frames // 2,
                            "rotation_deg": float((rotation + rng.integers(18, 37) * 5) % 360),
                        }
                    )
                else:  # another map, the least used
                    other = sorted(
                        (m for m in maps if m != name_map), key=lambda m: (uses[m], rng.random())
                    )[0]
                    uses[other] += 1
                    lights.append(
                        {
                            "map": other,
                            "from_frame": frames // 2,
                            "rotation_deg": float(rng.integers(0, 72) * 5),
                        }
                    )
            sequences.append(
                {
                    "name": f"c{index:03d}_{layout}_{name_map}",
                    "layout": layout,
                    "seed": 1000 + index,
                    "lights": lights,
                    "frames": frames,
                    "spp": spp * SPP_FACTOR.get(layout, 1),
                    "ar_frames": [1, frames - 2] if frames >= 3 else [0],
                    "virtual_material": VIRTUAL_MATERIALS[(r + k) % len(VIRTUAL_MATERIALS)],
                }
            )
    return {
        "description": "arlight's benchmark corpus: every layout on several maps, every "
        "map in at least two sequences (docs/results/corpus.md)",
        "seed": seed,
        "width": width,
        "height": height,
        "maps": list(maps),
        "sequences": sequences,
    }


def load_definition(path: str | Path | None = None) -> dict:
    """The committed definition (package data), or the JSON file at `path`."""
    if path is None:
        text = resources.files("arlight.synth").joinpath(DEFINITION_FILE).read_text()
    else:
        p = Path(path)
        if not p.is_file():
            raise ValueError(f"--corpus {p}: no such file (omit the value for the built-in corpus)")
        text = p.read_text()
    try:
        doc = json.loads(text)
        specs(doc)  # every entry readable, before hours of rendering
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as exc:
        what = f"missing key {exc}" if isinstance(exc, KeyError) else str(exc)
        raise ValueError(f"--corpus {path}: not a corpus definition ({what})") from None
    return doc


def specs(definition: dict) -> list[SequenceSpec]:
    """The SequenceSpecs of a definition."""
    out = []
    for s in definition["sequences"]:
        lights = tuple(
            LightState(x["map"], float(x["rotation_deg"]), int(x["from_frame"]))
            for x in s["lights"]
        )
        out.append(
            SequenceSpec(
                s["name"],
                s["layout"],
                int(s["seed"]),
                lights,
                frames=int(s["frames"]),
                width=int(definition["width"]),
                height=int(definition["height"]),
                spp=int(s["spp"]),
                ar_frames=tuple(s.get("ar_frames", ())),
                virtual_material=s.get("virtual_material", "diffuse"),
            )
        )
    return out


def coverage(definition: dict) -> dict:
    """Sequences per map and maps per layout (the corpus rules, checked by the tests)."""
    per_map = {m: 0 for m in definition["maps"]}
    per_layout: dict[str, set] = {}
    for s in definition["sequences"]:
        names = {x["map"] for x in s["lights"]}
        for m in names:
            per_map[m] = per_map.get(m, 0) + 1
        per_layout.setdefault(s["layout"], set()).update(names)
    return {
        "sequences_per_map": per_map,
        "maps_per_layout": {k: len(v) for k, v in per_layout.items()},
    }


def render_corpus(
    definition: dict,
    out_root: Path,
    map_folder: Path,
    only: Callable[[SequenceSpec], bool] | None = None,
    on_frame: Callable[[], None] | None = None,
    on_sequence: Callable[[SequenceSpec, object], None] | None = None,
) -> list:
    """Render every (selected) sequence not yet complete in out_root; returns the stats."""
    out_root.mkdir(parents=True, exist_ok=True)
    results = []
    for spec in specs(definition):
        if only is not None and not only(spec):
            continue
        stats = generate(spec, out_root, map_folder, on_frame)
        results.append((spec, stats))
        if on_sequence is not None:
            on_sequence(spec, stats)
    return results
