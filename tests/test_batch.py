"""`arlight batch` on a real local Ray: one actor per stream, failures reported, reruns skip.

Inputs are tiny (64x48, 3 frames): a TUM folder written from the built-in scene, a
recording of that folder (`arlight record`, lossless PNG colour, so its frames are the
folder's bit for bit), a corrupt .mcap and a folder whose third colour image is garbage (it
fails after two frames). One local Ray (2 CPUs) serves the whole module.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from arlight.batch import (
    BatchItem,
    BatchOptions,
    BatchUsageError,
    actor_resources,
    collect_inputs,
    import_ray,
    init_local_ray,
    run_batch,
)
from arlight.cli import EXIT_BAD_INPUT, main
from arlight.sources.synthetic import make_sequence

ray = pytest.importorskip("ray", reason="Ray is an optional extra: pip install 'arlight[ray]'")

FRAMES = 3
PRESET = "fast"  # one CPU per actor: two streams at once on the module's 2-CPU Ray
TIMING_KEYS = ("timings_ms",)


def write_tum(folder: Path, n: int = FRAMES) -> Path:
    """The built-in scene (64x48) as a TUM RGB-D folder with camera.json."""
    seq = make_sequence(num_frames=n, width=64, height=48)
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb, depth, assoc = [], [], []
    for i, f in enumerate(seq.frames):
        t = f"{f.timestamp:.6f}"
        assert cv2.imwrite(str(folder / "rgb" / f"{i}.png"), f.color[..., ::-1])
        assert cv2.imwrite(str(folder / "depth" / f"{i}.png"), f.depth)
        rgb.append(f"{t} rgb/{i}.png")
        depth.append(f"{t} depth/{i}.png")
        assoc.append(f"{t} rgb/{i}.png {t} depth/{i}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth) + "\n")
    (folder / "associations.txt").write_text("\n".join(assoc) + "\n")
    c = seq.camera
    (folder / "camera.json").write_text(
        json.dumps(
            {
                "fx": c.fx,
                "fy": c.fy,
                "cx": c.cx,
                "cy": c.cy,
                "width": c.width,
                "height": c.height,
                "depth_scale": float(seq.frames[0].depth_scale),
            }
        )
    )
    return folder


def records(path: Path) -> list[dict]:
    """The JSON lines of a results file, timing fields aside."""
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    for row in rows:
        for key in TIMING_KEYS:
            row.pop(key)
    return rows


# numbers of records made in different processes: the same frames through the same code,
# but BLAS and Numba reductions may sum in another order (about 1e-8 relative seen)
RTOL = 1e-6


def assert_records_close(got, want, rtol: float = RTOL, where: str = "records") -> None:
    """Equal structure, keys, strings, ints, bools and nulls; floats within rtol (arrays:
    of their largest magnitude, so a component that is zero up to rounding compares)."""
    if isinstance(want, dict):
        assert isinstance(got, dict) and list(got) == list(want), (where, got, want)
        for key in want:
            assert_records_close(got[key], want[key], rtol, f"{where}.{key}")
    elif isinstance(want, list) and _is_array(want):
        a, b = np.asarray(got, float), np.asarray(want, float)
        assert a.shape == b.shape, (where, got, want)
        np.testing.assert_allclose(
            a, b, rtol=rtol, atol=rtol * float(np.max(np.abs(b))), err_msg=where
        )
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), (where, got, want)
        for i, (g, w) in enumerate(zip(got, want, strict=True)):
            assert_records_close(g, w, rtol, f"{where}[{i}]")
    elif isinstance(want, float):  # abs_tol: a value that is zero up to rounding
        assert isinstance(got, float) and math.isclose(got, want, rel_tol=rtol, abs_tol=1e-12), (
            where,
            got,
            want,
        )
    else:  # str, int, bool, None: exactly
        assert type(got) is type(want) and got == want, (where, got, want)


def _is_array(value: list) -> bool:
    """A (nested) list of numbers with at least one float: compared as an array."""
    leaves = list(_leaves(value))
    return (
        bool(leaves)
        and any(isinstance(x, float) for x in leaves)
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in leaves)
    )


def _leaves(value: list):
    for x in value:
        yield from _leaves(x) if isinstance(x, list) else (x,)


@pytest.fixture(scope="module")
def local_ray():
    init_local_ray(ray, num_cpus=2)  # its servers on loopback only (issue 39)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("batch")
    scene = write_tum(d / "scene")
    recording = d / "scene_rec.mcap"
    assert (
        main(
            [
                "record",
                str(scene),
                "--out",
                str(recording),
                "--mode",
                "lossless",
                "--color-codec",
                "png",
            ]
        )
        == 0
    )
    corrupt = d / "corrupt.mcap"
    corrupt.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)
    late = write_tum(d / "late_failure")
    (late / "rgb" / "2.png").write_bytes(b"not a png at all")
    return {"scene": scene, "recording": recording, "corrupt": corrupt, "late": late}


@pytest.fixture(scope="module")
def first_run(local_ray, inputs, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    items = collect_inputs([inputs[k] for k in ("scene", "recording", "corrupt", "late")])
    report = run_batch(items, out, BatchOptions(preset=PRESET), progress=False)
    return out, items, report


class TestBatchOnRay:
    def test_failures_are_reported_and_the_others_finish(self, first_run):
        out, items, report = first_run
        by_name = {s.name: s for s in report.streams}
        assert [s.name for s in report.streams] == ["scene", "scene_rec", "corrupt", "late_failure"]
        assert by_name["scene"].status == by_name["scene_rec"].status == "ok"
        assert by_name["scene"].frames == by_name["scene_rec"].frames == FRAMES
        assert 0.0 <= by_name["scene"].median_confidence <= 1.0
        assert by_name["corrupt"].status == "failed" and "corrupt.mcap" in by_name["corrupt"].reason
        late = by_name["late_failure"]
        assert late.status == "failed" and "2.png" in late.reason, late.reason
        assert not report.ok
        # only the finished streams have results; no temporary file is left behind
        assert sorted(p.name for p in out.iterdir()) == [
            "batch.json",
            "scene.jsonl",
            "scene_rec.jsonl",
        ]

    def test_batch_json_lists_every_stream(self, first_run):
        out, _, report = first_run
        doc = json.loads((out / "batch.json").read_text())
        assert doc["counts"] == {"ok": 2, "failed": 2, "skipped": 0}
        assert doc["options"] == {
            "preset": PRESET,
            "device": "CPU:0",
            "overrides": {},
            "max_frames": None,
            "depth_encoding": None,
        }
        rows = {r["name"]: r for r in doc["streams"]}
        assert rows["scene"]["status"] == "ok" and rows["scene"]["frames"] == FRAMES
        assert rows["scene"]["seconds"] > 0
        assert rows["corrupt"]["status"] == "failed" and rows["corrupt"]["reason"]
        assert rows["late_failure"]["reason"] == next(
            s.reason for s in report.streams if s.name == "late_failure"
        )

    def test_records_equal_arlight_estimate(self, first_run, inputs, tmp_path):
        out, _, _ = first_run
        expected = tmp_path / "estimate.jsonl"
        # one Open3D thread, as each fast-preset actor (1 CPU): tracking is then reproducible
        assert (
            main(
                [
                    "--open3d-threads",
                    "1",
                    "estimate",
                    str(inputs["scene"]),
                    "--preset",
                    PRESET,
                    "--out",
                    str(expected),
                ]
            )
            == 0
        )
        want = records(expected)
        assert len(want) == FRAMES
        # another process (the actor) with its own thread pools: equal up to rounding
        assert_records_close(records(out / "scene.jsonl"), want)
        # the lossless recording of the folder gives the same records as the folder itself
        assert_records_close(records(out / "scene_rec.jsonl"), want)

    def test_rerun_skips_finished_streams_and_retries_failed_ones(self, first_run):
        out, items, _ = first_run
        before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.jsonl")}
        report = run_batch(items, out, BatchOptions(preset=PRESET), progress=False)
        status = {s.name: s.status for s in report.streams}
        assert status == {
            "scene": "skipped",
            "scene_rec": "skipped",
            "corrupt": "failed",
            "late_failure": "failed",
        }
        assert {s.name: s.frames for s in report.streams}["scene"] == FRAMES
        assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.jsonl")} == before
        doc = json.loads((out / "batch.json").read_text())
        assert doc["counts"] == {"ok": 0, "failed": 2, "skipped": 2}

    def test_force_redoes_a_finished_stream_with_progress(
        self, local_ray, inputs, tmp_path, capsys
    ):
        items = collect_inputs([inputs["scene"]])
        options = BatchOptions(preset=PRESET, max_frames=2)
        assert run_batch(items, tmp_path, options, progress=False).streams[0].status == "ok"
        first = (tmp_path / "scene.jsonl").read_text()
        capsys.readouterr()
        again = run_batch(items, tmp_path, options, force=True, progress=True)
        assert again.streams[0].status == "ok" and again.streams[0].frames == 2
        assert_records_close(
            records(tmp_path / "scene.jsonl"),
            [
                {k: v for k, v in json.loads(line).items() if k not in TIMING_KEYS}
                for line in first.splitlines()
            ],
        )  # two actors: two processes
        # the bar counts the batch's frames (the actor reports them) and finished streams
        bar = capsys.readouterr().err
        assert "2/2" in bar and "1/1 streams, 0 failed" in bar

    def test_other_options_on_the_same_folder_are_refused(self, first_run):
        out, items, _ = first_run
        with pytest.raises(BatchUsageError, match="use another --out, or --force"):
            run_batch(items, out, BatchOptions(preset="mobile"), progress=False)

    def test_cli_exit_code_1_when_a_stream_failed(self, first_run, inputs, capsys):
        out, _, _ = first_run
        code = main(
            [
                "batch",
                str(inputs["scene"]),
                str(inputs["corrupt"]),
                "--out",
                str(out),
                "--preset",
                PRESET,
            ]
        )
        text = capsys.readouterr()
        assert code == 1
        assert "skipped scene" in text.out and "failed  corrupt" in text.out
        assert "1 failed, 1 skipped" in text.err and "Traceback" not in text.err

    def test_cli_exit_code_0_when_all_ok_or_skipped(self, first_run, inputs, capsys):
        out, _, _ = first_run
        assert main(["batch", str(inputs["scene"]), "--out", str(out), "--preset", PRESET]) == 0
        assert "0 failed, 1 skipped" in capsys.readouterr().err


class TestRecordComparison:
    """The tolerance of the comparison above, on hand-made records."""

    WANT = {
        "frame": 1,
        "sh": [0.25, 1e-17, -0.5],
        "confidence": {"value": 0.02, "reason": "x", "samples": 100, "condition_number": None},
        "pose": [[1.0, 0.0], [0.0, 1.0]],
    }

    def test_rounding_passes(self):
        got = json.loads(json.dumps(self.WANT))
        got["sh"] = [0.25 * (1 + 1e-8), -3e-17, -0.5]
        got["confidence"]["value"] = 0.02 * (1 - 1e-8)
        got["pose"][0][1] = 1e-18
        assert_records_close(got, self.WANT)

    @pytest.mark.parametrize(
        ("path", "value"),
        [
            (("sh", 0), 0.2501),  # a number beyond rtol
            (("confidence", "reason"), "y"),  # strings exactly
            (("confidence", "samples"), 101),  # ints exactly
            (("confidence", "condition_number"), 0.0),  # null stays null
            (("frame",), 1.0),  # an int is not a float
        ],
    )
    def test_differences_fail(self, path, value):
        got = json.loads(json.dumps(self.WANT))
        target = got
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value
        with pytest.raises(AssertionError):
            assert_records_close(got, self.WANT)


class TestInputs:
    def test_names_are_unique_and_stable(self, tmp_path):
        for sub in ("a", "b"):
            (tmp_path / sub / "seq").mkdir(parents=True)
        items = collect_inputs(
            [tmp_path / "a" / "seq", tmp_path / "b" / "seq", tmp_path / "a" / "seq"]
        )  # the duplicate counts once
        assert len(items) == 2
        names = [i.name for i in items]
        assert len(set(names)) == 2 and all(n.startswith("seq-") for n in names)
        assert collect_inputs([tmp_path / "b" / "seq", tmp_path / "a" / "seq"])[0].name == names[1]

    def test_a_folder_of_recordings_stands_for_them(self, tmp_path):
        for name in ("b.mcap", "a.mcap", "notes.txt"):
            (tmp_path / name).write_bytes(b"")
        items = collect_inputs([tmp_path])
        assert items == [
            BatchItem(str(tmp_path / "a.mcap"), "a"),
            BatchItem(str(tmp_path / "b.mcap"), "b"),
        ]

    def test_no_inputs_is_a_usage_error(self):
        with pytest.raises(BatchUsageError, match="no inputs"):
            collect_inputs([])


class TestResources:
    @pytest.mark.parametrize(
        ("preset", "cpus", "want"),
        [
            ("full", 2, {"num_cpus": 2, "num_gpus": 0, "slots": 1}),
            ("full", 8, {"num_cpus": 2, "num_gpus": 0, "slots": 4}),
            ("fast", 2, {"num_cpus": 1, "num_gpus": 0, "slots": 2}),
            ("mobile", 3, {"num_cpus": 1, "num_gpus": 0, "slots": 3}),
            ("full", 1, {"num_cpus": 1, "num_gpus": 0, "slots": 1}),  # capped at the cluster
        ],
    )
    def test_cpus_per_actor_from_the_preset(self, preset, cpus, want):
        assert actor_resources(preset, None, {"CPU": float(cpus)}) == want

    def test_cuda_asks_one_gpu_per_actor(self):
        res = actor_resources("fast", "CUDA:0", {"CPU": 8.0, "GPU": 2.0})
        assert res == {"num_cpus": 1, "num_gpus": 1, "slots": 2}

    def test_cuda_on_a_cluster_without_gpus_is_a_usage_error(self):
        with pytest.raises(BatchUsageError, match="--device CUDA:0.*no GPU"):
            actor_resources("fast", "CUDA:0", {"CPU": 8.0})


class TestUsage:
    def test_without_ray_the_error_names_the_extra(self, monkeypatch):
        monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
        with pytest.raises(BatchUsageError, match=r"pip install 'arlight\[ray\]'"):
            import_ray()

    def test_cli_without_ray_exits_2(self, monkeypatch, tmp_path, capsys):
        monkeypatch.setitem(sys.modules, "ray", None)
        assert main(["batch", str(tmp_path), "--out", str(tmp_path / "out")]) == EXIT_BAD_INPUT
        err = capsys.readouterr().err
        assert "arlight[ray]" in err and "Traceback" not in err

    @pytest.mark.parametrize(
        ("argv", "names"),
        [
            (["batch"], "no inputs"),
            (["batch", "x", "--ray", "not an address"], "--ray"),
            (["batch", "x", "--set", "rt_directions=zero"], "--set"),
        ],
    )
    def test_bad_usage_exits_2_naming_the_flag(self, argv, names, capsys):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse's own usage errors
            code = exc.code
        captured = capsys.readouterr()
        assert code == EXIT_BAD_INPUT
        assert names in captured.err and "Traceback" not in captured.err
