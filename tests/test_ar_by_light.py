"""benchmarks/ar_by_light.py: ar_truth.py figures grouped by kind of light and material."""

import json

import pytest

from benchmarks.ar_by_light import MAPS, compact_share, main, pair_groups, table


def _sequence(tmp_path, name, env_map, reference="distant", material="mirror"):
    folder = tmp_path / name
    (folder / "ar").mkdir(parents=True)
    frames = [{"index": i, "env_map": env_map, "env_rotation_deg": 30.0} for i in range(2)]
    (folder / "lighting_gt.json").write_text(
        json.dumps({"truth_reference": reference, "frames": frames})
    )
    (folder / "ar" / "virtual_scene.json").write_text(json.dumps({"virtual_material": material}))
    return folder


def _row(sequence, frame, psnr):
    return {"sequence": sequence, "preset": "fast", "frame": frame} | {
        f"{v}_psnr_{r}": psnr for v in ("estimated", "gt_light") for r in ("affected", "shadow")
    }


def test_a_room_is_its_own_group_whatever_its_map(tmp_path):
    folder = _sequence(tmp_path, "room", "no_such_map_1k", reference="probe", material="glossy0.1")
    assert pair_groups(_row("room", 1, 20.0), folder, 0.3) == (
        "room",
        "no_such_map_1k",
        "glossy0.1",
    )


def test_table_gives_each_group_its_pairs_maps_and_medians():
    rows = [
        _row("a", 1, 20.0) | {"light": "soft", "map": "m1"},
        _row("a", 4, 24.0) | {"light": "soft", "map": "m1"},
        _row("b", 1, 30.0) | {"light": "sunny", "map": "m2"},
    ]
    text = table(rows, "light")
    assert "| soft | 2 | 1 | 22.0 / 22.0 / nan | 22.0 / 22.0 / nan |" in text
    assert "| sunny | 1 | 1 | 30.0 / 30.0 / nan |" in text
    assert "gt_full" not in text  # a variant no row has gets no column


@pytest.mark.skipif(not MAPS.is_dir(), reason=f"no HDR maps at {MAPS} (../shared/data)")
def test_a_sunny_map_and_a_studio_fall_either_side_of_the_threshold(tmp_path, capsys):
    # the sun of chinese_garden carries most of the ground's irradiance (0.81 in decision
    # 0035); dancing_hall's lamps are many and spread (0.09)
    assert compact_share("chinese_garden_1k", 0.0) > 0.5
    assert compact_share("dancing_hall_1k", 0.0) < 0.2
    _sequence(tmp_path, "sun", "chinese_garden_1k")
    _sequence(tmp_path, "soft", "dancing_hall_1k", material="diffuse")
    report = tmp_path / "report.json"
    report.write_text(json.dumps({"rows": [_row("sun", 1, 25.0), _row("soft", 1, 31.0)]}))
    assert main([str(report), "--data", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| sunny | 1 | 1 | 25.0" in out and "| soft | 1 | 1 | 31.0" in out
    assert "| mirror | 1 | 1 | 25.0" in out


def test_a_sequence_not_found_exits_2_naming_the_flag(tmp_path, capsys):
    report = tmp_path / "report.json"
    report.write_text(json.dumps({"rows": [_row("gone", 1, 25.0)]}))
    if not MAPS.is_dir():
        pytest.skip(f"no HDR maps at {MAPS} (../shared/data)")
    assert main([str(report), "--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "gone" in err and "--data" in err


def test_a_sequence_without_its_scene_file_has_an_unknown_material(tmp_path):
    folder = _sequence(tmp_path, "room", "no_such_map_1k", reference="probe")
    (folder / "ar" / "virtual_scene.json").unlink()
    assert pair_groups(_row("room", 1, 20.0), folder, 0.3)[2] == "unknown"


@pytest.mark.parametrize("content", ['{"rows": [{"x": 1}]}', "[1, 2]", "{}"])
def test_a_foreign_report_exits_2_naming_it(tmp_path, capsys, content):
    report = tmp_path / "report.json"
    report.write_text(content)
    assert main([str(report), "--data", str(tmp_path)]) == 2
    assert "report.json: not an ar_truth.py report.json" in capsys.readouterr().err
