"""Compact sources on the wire (issue 32 items 1 and 4): FrameResult.compact_sources from the
pipeline, the optional Result key `compact_sources` (SPEC.md section 4, "result: compact
sources"), the JSON records, and the main light of the engine layouts."""

from __future__ import annotations

import math
import re

import msgpack
import numpy as np
import pytest
from conftest import (
    as_bytes,
    expect,
    golden_bytes,
    load_vector_script,
    result,
    spec_section,
    tamper,
)

from arlight.core.frames import CompactLight, FrameResult, compact_lights
from arlight.offline import frame_record
from arlight.pipeline import sh
from arlight.pipeline.compact_light import EDGE_STEP_FULL, CompactSource
from arlight.pipeline.config import Config
from arlight.pipeline.engine_export import main_source_from_wire
from arlight.pipeline.pipeline import Pipeline
from arlight.protocols import Result, decode, encode, received_record, result_record
from arlight.protocols.frame_result import (
    COMPACT_SOURCE_KEYS,
    MAX_COMPACT_SOURCES,
    compact_sources_to_wire,
)
from arlight.server.results import result_message
from arlight.sources.synthetic import make_sequence

VEC = load_vector_script("make_protocol_vectors_compact")
GL_FROM_CV = np.diag([1.0, -1.0, -1.0])


def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    cos = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))


@pytest.fixture(scope="module")
def sunny():
    """Two frames of the synthetic sunny scene (a camera held still, hard sun shadows) through
    the `fast` pipeline with compact sources on: [(frame result, the fit, the true sun)]."""
    seq = make_sequence(num_frames=2, width=160, height=120, seed=0, sensor_noise=False, held=True)
    pipeline = Pipeline(Config.from_preset("fast", compact_sources=1), seq.camera)
    out = []
    for frame, sun in zip(seq.frames, seq.sun_direction_world, strict=True):
        got = pipeline.process(frame)
        out.append((got, pipeline.last_compact, sun))
    return out


def _message(got: FrameResult, exports: tuple[str, ...] = ()) -> Result:
    return result_message(
        got,
        seq=5,
        counters=(1, 1, 0),
        receive_time_wall=10.0,
        finish_time_wall=10.5,
        exports=exports,
    )


class TestFrameResult:
    def test_the_pipeline_reports_the_kept_source(self, sunny):
        kept = 0
        for got, fit, sun in sunny:
            assert fit is not None
            assert len(got.compact_sources) == len(fit.sources) <= 1
            rotation = got.pose[:3, :3]
            for light, source in zip(got.compact_sources, fit.sources, strict=True):
                kept += 1
                assert isinstance(light, CompactLight)
                np.testing.assert_allclose(light.direction_world, source.direction)
                np.testing.assert_allclose(light.direction_camera, rotation.T @ source.direction)
                assert light.intensity == pytest.approx(source.intensity) and light.intensity > 0
                np.testing.assert_allclose(light.rgb, np.maximum(source.rgb, 0.0))
                assert light.angular_radius_deg == source.angular_radius_deg
                assert light.share == pytest.approx(source.share) and 0.0 < light.share <= 1.0
                # the Result's dominant direction is the source's, and the sun is there
                np.testing.assert_allclose(got.dominant_direction_world, light.direction_world)
                assert _angle_deg(light.direction_world, sun) < 10.0
        assert kept == 2, "the sunny scene keeps a source in each frame"

    def test_a_source_frame_is_as_confident_as_its_shadow_edge_is_clear(self, sunny):
        """The reported direction is the source's, found from shadows: the confidence is the
        step across its shadow's edge (times the steadiness), not the SH fit's normals."""
        first, fit, _ = sunny[0]
        assert fit.sources and fit.edge_step > 0.0
        assert first.confidence.value == pytest.approx(min(1.0, fit.edge_step / EDGE_STEP_FULL))
        assert first.confidence.side_share is None  # the view of side-facing normals: no factor
        for got, fit, _ in sunny[1:]:
            assert got.confidence.value <= min(1.0, fit.edge_step / EDGE_STEP_FULL) + 1e-12

    def test_none_without_compact_sources(self):
        seq = make_sequence(num_frames=1, width=96, height=72, seed=1, sensor_noise=False)
        pipeline = Pipeline(Config.from_preset("fast", compact_sources=0), seq.camera)
        got = pipeline.process(seq.frames[0])
        assert got.compact_sources == () and pipeline.last_compact is None
        assert "compact_sources" not in msgpack.unpackb(as_bytes(encode(_message(got)))[0])

    def test_camera_direction_and_clamped_colour(self):
        c, s = math.cos(0.3), math.sin(0.3)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        d = np.array([0.0, -0.6, 0.8])
        source = CompactSource(d, 2.0, np.array([2.5, 1.9, -0.1]), 0.27, 0.5, 0.1)
        (light,) = compact_lights((source,), rotation)
        np.testing.assert_allclose(light.direction_camera, [-0.6 * s, -0.6 * c, 0.8])
        np.testing.assert_allclose(light.rgb, [2.5, 1.9, 0.0])  # a light is never negative
        assert compact_lights((), rotation) == ()


class TestWire:
    def test_round_trip_from_the_pipeline(self, sunny):
        for got, _, _ in sunny:
            back = decode(encode(_message(got)))
            assert back.compact_sources == compact_sources_to_wire(got.compact_sources)
            (wire,) = back.compact_sources
            assert list(wire) == list(COMPACT_SOURCE_KEYS)
            (light,) = got.compact_sources
            np.testing.assert_allclose(wire["direction_camera"], light.direction_camera)
            assert wire["intensity"] == light.intensity and wire["share"] == light.share
            assert back.dominant_direction_world == wire["direction_world"]

    def test_records_carry_it_after_intensity(self, sunny):
        got = sunny[0][0]
        msg = decode(encode(_message(got)))
        for record in (
            result_record(msg),
            received_record(msg, 11.0),
            frame_record(got, 0),
        ):
            keys = list(record)
            assert keys[keys.index("intensity") + 1] == "compact_sources"
            assert record["compact_sources"] == msg.compact_sources
        plain = result(compact_sources=None)
        assert "compact_sources" not in result_record(plain)

    def test_no_source_is_no_key_and_the_old_bytes(self):
        """Absent = none: a Result without sources is what it was before the key existed
        (the golden vectors of section 9 pin the rest)."""
        parts = as_bytes(encode(result()))
        assert "compact_sources" not in msgpack.unpackb(parts[0])
        assert decode(parts).compact_sources is None
        assert as_bytes(encode(result(compact_sources=None))) == parts

    def test_golden_vector(self):
        header = msgpack.unpackb(golden_bytes("result_compact")[0], raw=False)
        fields = list(header)
        assert fields[fields.index("intensity") + 1] == "compact_sources"
        (wire,) = header["compact_sources"]
        assert list(wire) == list(COMPACT_SOURCE_KEYS)
        msg = decode(golden_bytes("result_compact"))
        assert msg.compact_sources == VEC.vectors()["result_compact"].compact_sources
        pose = np.asarray(msg.pose)
        np.testing.assert_allclose(
            pose[:3, :3].T @ wire["direction_world"], wire["direction_camera"], atol=1e-12
        )
        lum = np.array([0.2126, 0.7152, 0.0722]) @ wire["rgb"]
        assert wire["intensity"] == pytest.approx(lum, abs=1e-9)
        light = msg.exports["main_light"]
        np.testing.assert_allclose(light["direction"], GL_FROM_CV @ wire["direction_camera"])
        assert light["intensity"] == wire["rgb"]


def _set_source(key: str, value):
    def edit(header: dict) -> None:
        header["compact_sources"][0][key] = value

    return edit


def _drop_source_key(key: str):
    def edit(header: dict) -> None:
        del header["compact_sources"][0][key]

    return edit


def _set_all(value):
    def edit(header: dict) -> None:
        header["compact_sources"] = value

    return edit


F = "result.compact_sources"
ONE = VEC.compact_source()


class TestRefused:
    """Decoding checks every limit of SPEC.md's table and names the field; encode refuses
    the same."""

    @pytest.mark.parametrize(
        "edit, field",
        [
            (_set_all([]), F),
            (_set_all([ONE] * (MAX_COMPACT_SOURCES + 1)), F),
            (_set_all(ONE), F),
            (_set_all(["sun"]), f"{F}[0]"),
            (_set_source("direction_world", [0.6, 0.8, 0.5]), f"{F}[0].direction_world"),
            (_set_source("direction_world", [0.0, 0.0, 0.0]), f"{F}[0].direction_world"),
            (_set_source("direction_camera", [1.0, 0.0]), f"{F}[0].direction_camera"),
            (_set_source("intensity", -0.5), f"{F}[0].intensity"),
            (_set_source("intensity", math.nan), f"{F}[0].intensity"),
            (_set_source("intensity", True), f"{F}[0].intensity"),
            (_set_source("rgb", [1.0, -0.25, 1.0]), f"{F}[0].rgb[1]"),
            (_set_source("rgb", [1.0, 1.0]), f"{F}[0].rgb"),
            (_set_source("rgb", [1.0, math.inf, 1.0]), f"{F}[0].rgb[1]"),
            (_set_source("angular_radius_deg", 90.5), f"{F}[0].angular_radius_deg"),
            (_set_source("angular_radius_deg", -1.0), f"{F}[0].angular_radius_deg"),
            (_set_source("share", 1.25), f"{F}[0].share"),
            (_set_source("share", None), f"{F}[0].share"),
            (_set_source("gain", 0.5), f"{F}[0].gain"),
            (_drop_source_key("share"), f"{F}[0].share"),
        ],
    )
    def test_decode_refuses(self, edit, field):
        parts = tamper(golden_bytes("result_compact"), edit)
        expect("bad_field", decode, parts, field=field)

    def test_the_limits_themselves_pass(self):
        edge = {**ONE, "rgb": None, "intensity": 0.0, "angular_radius_deg": 90, "share": 1}
        back = decode(encode(result(compact_sources=[edge] * MAX_COMPACT_SOURCES)))
        assert back.compact_sources == [{**edge, "angular_radius_deg": 90.0, "share": 1.0}] * 4

    def test_encode_refuses(self):
        expect("bad_field", encode, result(compact_sources=[]), field=F)
        bad = {**ONE, "share": 2.0}
        expect("bad_field", encode, result(compact_sources=[bad]), field=f"{F}[0].share")


class TestSpec:
    """SPEC.md's subsection read as a Go client's author reads it."""

    def test_the_key_table_is_the_codes(self):
        text = spec_section("result: compact sources")
        rows = [line for line in text.splitlines() if line.startswith("| `")]
        assert [re.match(r"\| `([a-z_]+)`", r).group(1) for r in rows] == list(COMPACT_SOURCE_KEYS)
        assert f"**1 to {MAX_COMPACT_SOURCES}**" in text

    def test_the_written_band_3_is_the_basis_and_the_projection_is_the_sources(self):
        """The subtraction the text asks for, with its own band-3 polynomials: sh minus
        intensity * Y(direction) removes exactly CompactSource.sh (bands 0..3)."""
        text = spec_section("result: compact sources")
        band3 = re.search(r"band 3 \(`i = 9\.\.15`\) is\s+(.*?)\s+\(exactly", text, re.S)
        terms = re.findall(r"`([^`]+)`", band3.group(1))
        assert len(terms) == 7
        rng = np.random.default_rng(3)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        x, y, z = d
        values = []
        for term in terms:  # e.g. "0.590044 y (3 x^2 - y^2)"
            expr = term.replace("^", "**")
            expr = re.sub(r"(?<=[0-9a-z)])\s+(?=[0-9a-z(])", " * ", expr)
            values.append(eval(expr, {}, {"x": x, "y": y, "z": z}))  # noqa: S307 (SPEC text)
        np.testing.assert_allclose(values, sh.sh_basis(d, 4)[9:], rtol=2e-6)
        source = CompactSource(d, 1.75, None, 0.27, 0.5, 0.1)
        np.testing.assert_allclose(source.sh(4)[9:], 1.75 * np.array(values), rtol=2e-6)


class TestMainLight:
    def test_main_source_from_wire(self):
        assert main_source_from_wire(None) is None
        first = main_source_from_wire([ONE, {**ONE, "intensity": 9.0}])
        assert first is not None and first.intensity == ONE["intensity"]
        assert first.rgb == ONE["rgb"]

    @pytest.mark.parametrize("layout", ["arcore", "webxr"])
    def test_the_served_main_light_is_the_source(self, sunny, layout):
        """Through the server's conversion and the wire: the main light of an ARCore or
        WebXR session points at the kept source within 1 degree, with its colour; the
        layout's SH is still the whole light."""
        for got, _, _ in sunny:
            msg = decode(encode(_message(got, (layout, "main_light"))))
            (wire,) = msg.compact_sources
            light = msg.exports["main_light"]
            assert _angle_deg(light["direction"], GL_FROM_CV @ wire["direction_camera"]) < 1.0
            world = np.asarray(msg.pose)[:3, :3] @ GL_FROM_CV @ light["direction"]
            assert _angle_deg(world, wire["direction_world"]) < 1.0
            np.testing.assert_allclose(light["intensity"], wire["rgb"], rtol=1e-12)
            plain = decode(
                encode(_message(FrameResult(**{**vars(got), "compact_sources": ()}), (layout,)))
            )
            assert msg.exports[layout] == plain.exports[layout]


def test_a_display_computes_the_main_light_from_the_source(make_server, tmp_path):
    """`arlight display --export main_light` computes the layout from each Result it
    receives: with a compact source, the source (as the server's own layout)."""
    import json
    import threading

    from streaming_support import flat_source, run_with_timeout

    from arlight.client.capture import CaptureClient, StreamOptions
    from arlight.client.display import DisplayClient, DisplayOptions
    from arlight.core.frames import Confidence

    light = sh.directional_light(np.array([0.0, 0.0, 1.0]), 1.0, 4)
    light[0] += 0.5
    d = np.array([0.0, -0.8, 0.6])  # 37 degrees from the SH's own direction
    (source,) = compact_lights(
        (CompactSource(d, 2.0, np.array([2.2, 2.0, 1.5]), 0.27, 0.6, 0.1),), np.eye(3)
    )

    def step(frame, session, render_light, deadline) -> FrameResult:
        return FrameResult(
            timestamp=frame.timestamp,
            sh=light,
            sh_camera=light,
            dominant_direction_world=d,
            dominant_direction_camera=d,
            intensity=1.0,
            confidence=Confidence(),
            pose=np.eye(4),
            timings_ms={"Step": 0.0},
            compact_sources=(source,),
        )

    server = make_server(process=step)
    out = tmp_path / "out"
    display = DisplayClient(
        DisplayOptions(
            server=server.connect_address,
            session="compact",
            out_dir=str(out),
            exports=("main_light",),
            idle_exit_s=30.0,
        )
    )
    thread = threading.Thread(target=display.run, daemon=True)
    thread.start()
    assert display.subscribed.wait(10)
    options = StreamOptions(
        server=server.connect_address, session="compact", mode="lossless", rate="max"
    )
    assert run_with_timeout(lambda: CaptureClient(flat_source(1), options).run()).results == 1
    thread.join(30)
    (line,) = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert line["compact_sources"][0]["rgb"] == [2.2, 2.0, 1.5]
    main = line["exports"]["main_light"]
    assert _angle_deg(main["direction"], GL_FROM_CV @ d) < 1.0
    assert main["intensity"] == [2.2, 2.0, 1.5]
