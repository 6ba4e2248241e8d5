"""arlight bench holds environment maps out: per-frame map names and layouts from the ground
truth (the probe reference where the distant-light assumption fails), errors grouped by map
and by layout, and the leave-one-map-out choice among configurations (arlight.folds).

Unit tests on hand-made numbers; one small real run on two shared sequences."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data

from arlight import evaluation
from arlight.bench import BenchError, ConfigResult, open_data, run_benchmark
from arlight.folds import FoldsError, leave_one_map_out
from arlight.pipeline import sh
from arlight.report import (
    folds_table,
    group_by_map,
    layout_table,
    map_table,
    markdown,
    summarise,
    write_report,
)

STATIC = DATA / "synthetic" / "dev_a_static_venice"
SWITCH = DATA / "synthetic" / "dev_k_lightswitch_warehouse_venice"  # two maps, switch at 7


# --------------------------------------------------------------------------- ground truth


def _frame(k: int, env_map: str, probe: dict | None = None) -> dict:
    """A lighting_gt.json frame: light from +y (world and camera), Condon-Shortley SH."""
    upper = sh.toggle_condon_shortley(sh.directional_light(np.array([0.0, 1.0, 0.0]), 1.0, 4))
    f = {
        "index": k,
        "env_map": env_map,
        "dominant_dir_camera": [0.0, 1.0, 0.0],
        "dominant_dir_upper_camera": [0.0, 1.0, 0.0],
        "sh_lum_upper_world": upper.tolist(),
    }
    if probe is not None:
        f["probe"] = probe
    return f


def _write_gt(folder: Path, frames: list[dict], **top) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / evaluation.GT_FILE).write_text(json.dumps({**top, "frames": frames}))
    return folder


class TestGroundTruth:
    def test_map_per_frame_and_layout_from_the_category(self, tmp_path):
        folder = _write_gt(
            tmp_path / "s", [_frame(0, "a_1k"), _frame(1, "b_1k")], category="c_light_change"
        )
        truth = evaluation.load_ground_truth(folder)
        assert [t.env_map for t in truth] == ["a_1k", "b_1k"]
        assert {t.layout for t in truth} == {"light_change"}
        assert {t.reference for t in truth} == {"distant"}

    @pytest.mark.parametrize(
        ("top", "layout"),
        [
            ({"category": "a_static"}, "static"),
            ({"category": "b_dynamic_object"}, "dynamic"),
            ({"category": "d_indoor_env"}, "indoor"),
            ({"category": "e_few_normals"}, "few_normals"),
            ({"category": "f_new_thing"}, "new_thing"),
            ({"layout": "room", "category": "a_static"}, "room"),
            ({}, None),
        ],
    )
    def test_layout(self, top, layout):
        assert evaluation.layout_of(top) == layout

    def test_probe_reference_replaces_the_distant_fields(self, tmp_path):
        probe_sh = sh.toggle_condon_shortley(
            sh.directional_light(np.array([1.0, 0.0, 0.0]), 1.0, 4)
        )
        probe = {
            "dominant_dir_upper_camera": [1.0, 0.0, 0.0],
            "dominant_dir_camera": [0.0, 0.0, 1.0],
            "sh_lum_upper_world": probe_sh.tolist(),
        }
        folder = _write_gt(
            tmp_path / "room", [_frame(0, "a_1k", probe)], layout="room", truth_reference="probe"
        )
        (t,) = evaluation.load_ground_truth(folder)
        np.testing.assert_allclose(t.dominant_upper_camera, [1.0, 0.0, 0.0])
        np.testing.assert_allclose(t.dominant_camera, [0.0, 0.0, 1.0])
        # converted to arlight's basis (no phase): it points where the probe's light is
        np.testing.assert_allclose(
            sh.dominant_direction(t.sh_upper_world), [1.0, 0.0, 0.0], atol=1e-9
        )
        assert (t.layout, t.reference, t.env_map) == ("room", "probe", "a_1k")

    @pytest.mark.parametrize("probe", [None, {"dominant_dir_camera": [0.0, 1.0, 0.0]}])
    def test_probe_reference_without_a_probe_is_an_error(self, tmp_path, probe):
        folder = _write_gt(tmp_path / "room", [_frame(0, "a_1k", probe)], truth_reference="probe")
        with pytest.raises(
            evaluation.GroundTruthError, match="frame 0 has no probe.*sh_lum_upper_world"
        ):
            evaluation.load_ground_truth(folder)

    def test_the_bench_reports_a_missing_probe_as_bad_input(self, tmp_path):
        folder = _write_gt(tmp_path / "room", [_frame(0, "a_1k")], truth_reference="probe")
        (folder / "rgb").mkdir()
        with pytest.raises(BenchError, match="probe"):
            open_data([str(folder)], frames=1, warmup=0)


# --------------------------------------------------------------------------- grouping


class TestGroupByMap:
    # two sequences; "s2" switches from map B to map A half-way
    ERRORS = {"s1": [1.0, 2.0, 3.0], "s2": [10.0, 20.0, 4.0, 6.0]}
    MAPS = {"s1": ["A", "A", "A"], "s2": ["B", "B", "A", "A"]}
    LAYOUTS = {"s1": "static", "s2": "light_change"}

    def test_per_map_median_over_frames_of_every_sequence(self):
        g = group_by_map(self.ERRORS, self.MAPS, self.LAYOUTS)
        assert list(g["maps"]) == ["A", "B"]
        assert g["maps"]["A"]["median"] == 3.0  # median of 1, 2, 3, 4, 6
        assert g["maps"]["A"]["frames"] == 5
        assert g["maps"]["A"]["sequences"] == ["s1", "s2"]
        assert g["maps"]["A"]["layouts"] == ["static", "light_change"]
        assert g["maps"]["B"]["median"] == 15.0
        assert g["median_over_maps"] == 9.0  # median of 3 and 15: each map counts once
        assert g["p90_all_frames"] == pytest.approx(np.percentile([1, 2, 3, 10, 20, 4, 6], 90))
        assert (g["worst_map"], g["worst_map_median"]) == ("B", 15.0)

    def test_per_layout(self):
        g = group_by_map(self.ERRORS, self.MAPS, self.LAYOUTS)
        assert list(g["layouts"]) == ["light_change", "static"]
        change = g["layouts"]["light_change"]
        assert change["maps"] == {"A": 5.0, "B": 15.0}  # only this layout's frames
        assert change["median_over_maps"] == 10.0
        assert (change["worst_map"], change["worst_map_median"]) == ("B", 15.0)
        assert g["layouts"]["static"]["maps"] == {"A": 2.0}

    def test_frames_without_a_map_are_left_out(self):
        assert group_by_map({"s": [1.0, 2.0]}, {"s": [None, None]}) is None
        assert group_by_map({"s": [1.0]}, {}) is None
        g = group_by_map({"s": [1.0, 50.0]}, {"s": ["A", None]})
        assert g["maps"]["A"]["frames"] == 1 and g["layouts"].keys() == {"unknown"}

    def test_report_names_the_maps(self):
        results = []
        for name, shift in (("fast", 0.0), ("full", 1.0)):
            r = ConfigResult(name, {}, None, None, total_ms=[10.0])
            for seq, errors in self.ERRORS.items():
                r.per_sequence[seq] = {
                    "angle_upper_deg": [e + shift for e in errors],
                    "angle_deg": errors,
                    "sh_error": [],
                    "shading_error": [],
                    "confidence": [],
                }
                r.env_maps[seq] = self.MAPS[seq]
                r.layouts[seq] = self.LAYOUTS[seq]
            results.append(r)
        report = summarise(
            results, data=list(self.ERRORS), frames=None, warmup=0, sweeps=[], folds=True
        )
        assert report["env_maps"] == ["A", "B"]
        acc = report["configs"]["full"]["accuracy"]
        assert acc["sequences"]["s2"]["env_maps"] == ["B", "A"]
        assert acc["sequences"]["s2"]["layout"] == "light_change"
        assert acc["by_map"]["maps"]["A"]["median"] == 4.0
        table = map_table(report)
        assert "| A | static, light_change | 5 | 3.0 | 4.0 |" in table
        assert "| worst map | | | 15.0 (B) | 16.0 (B) |" in table
        assert "| light_change | 2 | 10.0 / " in layout_table(report)
        assert report["folds"]["best_in_sample"] == "fast"
        text = markdown(report)
        assert "Per environment map" in text and "Maps: A, B." in text
        assert "Leave one map out" in text


# --------------------------------------------------------------------------- folds


class TestFolds:
    def test_the_in_sample_best_loses_on_a_held_out_map(self):
        # "tuned" is good on A, B, D but bad on C; "steady" is fair everywhere. In sample
        # "tuned" wins; holding out C, the choice made on the others is still "tuned" and it
        # scores 40 there, where "steady" scores 9.
        per_map = {
            "steady": {"A": 8.0, "B": 8.0, "C": 9.0, "D": 9.0},
            "tuned": {"A": 2.0, "B": 3.0, "C": 40.0, "D": 7.0},
        }
        f = leave_one_map_out(per_map)
        assert f.best_in_sample == "tuned"
        assert f.fixed_median == {"steady": 8.5, "tuned": 5.0}
        by_map = {fold.held_out: fold for fold in f.folds}
        assert by_map["C"].chosen == "tuned" and by_map["C"].chosen_error == 40.0
        assert by_map["C"].in_sample == 3.0  # median of 2, 3, 7
        # holding out A: without its 2, "tuned" has median(3, 40, 7) = 7 < median(8, 9, 9)
        assert by_map["A"].chosen == "tuned" and by_map["A"].chosen_error == 2.0
        assert [fold.held_out for fold in f.folds] == ["A", "B", "C", "D"]
        assert by_map["D"].errors == {"steady": 9.0, "tuned": 7.0}
        assert f.held_out_median == 5.0  # median of 2, 3, 40, 7

    def test_the_best_in_sample_is_not_chosen_when_its_best_map_is_held_out(self):
        # "b" wins in sample only because of map X; hold X out and "a" is chosen (and scores
        # 30 on X): the held-out median (7.0) is worse than "b" kept fixed (5.5)
        per_map = {"a": {"X": 30.0, "Y": 5.0, "Z": 6.0}, "b": {"X": 1.0, "Y": 7.0, "Z": 5.5}}
        f = leave_one_map_out(per_map)
        assert f.best_in_sample == "b"  # median 5.5 against 6.0
        chosen = {fold.held_out: fold.chosen for fold in f.folds}
        assert chosen == {"X": "a", "Y": "b", "Z": "b"}
        assert f.held_out_median == 7.0  # errors 30 (a on X), 7 (b on Y), 5.5 (b on Z)
        assert f.held_out_median > f.fixed_median["b"]  # tuning looked better than it is

    def test_ties_go_to_the_first_candidate(self):
        f = leave_one_map_out({"p": {"A": 1.0, "B": 1.0}, "q": {"A": 1.0, "B": 1.0}})
        assert {fold.chosen for fold in f.folds} == {"p"} and f.best_in_sample == "p"

    def test_as_dict_is_plain_json(self):
        d = leave_one_map_out({"p": {"A": 1.0, "B": 2.0}}).as_dict()
        assert json.loads(json.dumps(d)) == d
        assert d["folds"][0] == {
            "held_out": "A",
            "chosen": "p",
            "in_sample": 2.0,
            "chosen_error": 1.0,
            "errors": {"p": 1.0},
        }

    @pytest.mark.parametrize(
        ("per_map", "match"),
        [
            ({}, "no candidate"),
            ({"p": {"A": 1.0}}, "at least two"),
            ({"p": {"A": 1.0, "B": 1.0}, "q": {"A": 1.0}}, "different maps"),
        ],
    )
    def test_bad_inputs(self, per_map, match):
        with pytest.raises(FoldsError, match=match):
            leave_one_map_out(per_map)

    def test_table_and_notes(self):
        report = {"folds": {"candidates": ["p"], "note": "one configuration: nothing to choose"}}
        assert folds_table(report) == "Leave one map out: one configuration: nothing to choose."
        assert folds_table({}) == ""
        f = leave_one_map_out(
            {"a": {"X": 30.0, "Y": 5.0, "Z": 6.0}, "b": {"X": 1.0, "Y": 7.0, "Z": 5.5}}
        )
        table = folds_table({"folds": {**f.as_dict(), "note": None}})
        assert "| X | a (5.5) | 30.0 | 30.0 | 1.0 |" in table
        assert "| median over held-out maps | chosen per fold | 7.0 | 6.0 | 5.5 |" in table
        assert "differs from b in 1 of them" in table


# --------------------------------------------------------------------------- a real run


@pytest.mark.slow
@pytest.mark.data
@needs_data(STATIC)
@needs_data(SWITCH)
def test_report_of_two_shared_sequences_groups_by_map(tmp_path):
    # 2 frames each: dev_k's first two frames are lit by the warehouse only
    report = run_benchmark(
        [str(STATIC), str(SWITCH)],
        ["fast"],
        [],
        frames=2,
        warmup=1,
        overrides={},
        progress=False,
        folds=True,
    )
    assert report["env_maps"] == ["empty_warehouse_01_1k", "venice_sunset_1k"]
    by_map = report["configs"]["fast"]["accuracy"]["by_map"]
    assert by_map["maps"]["venice_sunset_1k"]["sequences"] == ["dev_a_static_venice"]
    assert by_map["maps"]["empty_warehouse_01_1k"]["layouts"] == ["light_change"]
    assert set(by_map["layouts"]) == {"static", "light_change"}
    assert by_map["worst_map"] in report["env_maps"]
    assert 0 <= by_map["median_over_maps"] <= 180
    assert "nothing to choose" in report["folds"]["note"]
    write_report(report, tmp_path)
    saved = json.loads((tmp_path / "report.json").read_text())
    assert saved["configs"]["fast"]["accuracy"]["by_map"]["maps"].keys() == {
        "empty_warehouse_01_1k",
        "venice_sunset_1k",
    }
    assert "| venice_sunset_1k | static | 2 |" in (tmp_path / "report.md").read_text()


def test_the_folds_say_how_often_each_candidate_was_chosen():
    folds = leave_one_map_out(
        {"a": {"m1": 1.0, "m2": 1.0, "m3": 9.0}, "b": {"m1": 2.0, "m2": 2.0, "m3": 2.0}}
    )
    # m1 or m2 held out: a scores 5 on the others against b's 2 -> b; m3 held out: a (1 < 2)
    assert folds.choices_text() == "b x2, a x1"
