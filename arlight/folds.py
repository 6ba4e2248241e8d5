"""Leave-one-map-out selection: does choosing a configuration generalise to unseen lighting?

`arlight bench --folds` tunes by picking, among the candidates it ran (presets, comparators,
sweep points), the one with the lowest error. Picked on every map, that figure flatters the
winner: it was chosen on the very maps it is scored on. Here each environment map in turn is
held out: the candidate with the lowest median over the OTHER maps is chosen, and scored on
the held-out map only. The median of those held-out scores is what tuning is worth on a map
it has not seen; each fixed candidate's median over maps is the figure to compare it with.

Pure functions of numbers (no pipeline): the input is, per candidate, its error per map
(in `arlight bench`, the median over that map's frames of the angular error against the
upper-hemisphere truth, degrees).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import asdict, dataclass

import numpy as np


class FoldsError(ValueError):
    """Inputs the folds cannot be computed from (no candidate, maps that differ, < 2 maps)."""


@dataclass(frozen=True)
class Fold:
    """One held-out map.

    held_out: the map left out; chosen: the candidate with the lowest median over the other
    maps (ties: the first in candidate order); in_sample: that median (degrees);
    chosen_error: the chosen candidate's error on the held-out map (degrees); errors: every
    candidate's error on the held-out map (degrees), in candidate order.
    """

    held_out: str
    chosen: str
    in_sample: float
    chosen_error: float
    errors: dict[str, float]


@dataclass(frozen=True)
class Folds:
    """All folds and their aggregates (degrees).

    held_out_median: median over held-out maps of the chosen candidate's error there (what
    tuning gives on unseen lighting). fixed_median: per candidate, the median over all maps
    of its error (a candidate kept fixed whatever the map). best_in_sample: the candidate with
    the lowest fixed_median (what tuning on every map would pick).
    """

    candidates: list[str]
    maps: list[str]
    folds: list[Fold]
    held_out_median: float
    fixed_median: dict[str, float]
    best_in_sample: str

    def as_dict(self) -> dict:
        """Plain JSON values (report.json's "folds")."""
        return asdict(self)

    def choices_text(self) -> str:
        """How often each candidate was chosen, most often first: "a x3, b x1"."""
        counts = Counter(f.chosen for f in self.folds)
        return ", ".join(f"{name} x{n}" for name, n in counts.most_common())


def _argmin(scores: dict[str, float]) -> str:
    """The key of the lowest value; ties go to the first key (candidate order)."""
    best = next(iter(scores))
    for name, value in scores.items():
        if value < scores[best]:
            best = name
    return best


def leave_one_map_out(per_map: dict[str, dict[str, float]]) -> Folds:
    """Leave-one-map-out choice among candidates.

    per_map: {candidate: {map: error}}, errors in degrees (lower is better), every candidate
    with the same maps; the candidates' order breaks ties. Raises FoldsError with no
    candidate, with candidates whose maps differ, or with fewer than two maps (nothing would
    be left to choose on).
    """
    if not per_map:
        raise FoldsError("no candidate to choose from")
    candidates = list(per_map)
    maps = list(per_map[candidates[0]])
    for name in candidates[1:]:
        if set(per_map[name]) != set(maps):
            raise FoldsError(
                f"candidates {candidates[0]!r} and {name!r} were scored on "
                f"different maps: {sorted(maps)} vs {sorted(per_map[name])}"
            )
    if len(maps) < 2:
        raise FoldsError(
            f"leaving one map out needs at least two environment maps; the data "
            f"has {len(maps)} ({', '.join(maps) or 'none'})"
        )
    folds = []
    for held_out in maps:
        in_sample = {
            c: float(np.median([per_map[c][m] for m in maps if m != held_out])) for c in candidates
        }
        chosen = _argmin(in_sample)
        folds.append(
            Fold(
                held_out=held_out,
                chosen=chosen,
                in_sample=in_sample[chosen],
                chosen_error=float(per_map[chosen][held_out]),
                errors={c: float(per_map[c][held_out]) for c in candidates},
            )
        )
    fixed = {c: float(np.median([per_map[c][m] for m in maps])) for c in candidates}
    return Folds(
        candidates=candidates,
        maps=maps,
        folds=folds,
        held_out_median=float(np.median([f.chosen_error for f in folds])),
        fixed_median=fixed,
        best_in_sample=_argmin(fixed),
    )
