"""arlight.protocols' version 2 fields, the engine layouts (Hello config.exports, Result
exports) and the per-frame records (result_record, received_record)."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from conftest import calibration, expect, result, tamper
from conftest import load_vector_script as _load_vector_script

from arlight.protocols import (
    EXPORT_LAYOUTS,
    PROTOCOL_VERSION,
    Bye,
    ByeKind,
    Error,
    ErrorField,
    Hello,
    ProtocolError,
    Result,
    SessionConfig,
    decode,
    encode,
    error_from_exception,
    plain_diagnostics,
    received_record,
    result_record,
)

# --------------------------------------------------------------------------- v2 fields


class TestVersion2Fields:
    """Error.retryable, Bye.kind, Result.sh_camera and Result.diagnostics (SPEC.md v2)."""

    def test_retryable_error_and_bye_kinds_round_trip(self):
        err = Error("bad_state", "busy", ErrorField.CREDITS, 5, retryable=True)
        assert err.field == "credits" and type(err.field) is str
        assert decode(encode(err)) == err
        for kind in ByeKind:
            assert decode(encode(Bye("why", kind))).kind is kind
        assert Bye().kind is ByeKind.LEAVING
        assert error_from_exception(ProtocolError("bad_field", "x")).retryable is False

    def test_retryable_and_kind_are_checked(self):
        expect(
            "bad_field",
            decode,
            tamper(encode(Error("a", "b")), lambda h: h.update(retryable=1)),
            field="error.retryable",
        )
        expect(
            "bad_field",
            decode,
            tamper(encode(Error("a", "b")), lambda h: h.pop("retryable")),
            field="error.retryable",
        )
        expect(
            "bad_field",
            decode,
            tamper(encode(Bye()), lambda h: h.update(kind="ended")),
            field="bye.kind",
        )
        expect("bad_field", encode, Bye("x", "ended"), field="bye.kind")

    def test_result_sh_camera_and_diagnostics_round_trip(self):
        diagnostics = {
            "tracking": {"ok": False, "reason": "too few points"},
            "residuals": [0.5, 1, math.inf],
            "bands_estimated": 3,
            "up": None,
            "a": {"b": {"c": {"d": 1.5}}},
        }
        back = decode(encode(result(sh_camera=[0.2] * 9, diagnostics=diagnostics)))
        assert back.sh_camera == [0.2] * 9
        assert back.diagnostics == diagnostics
        assert decode(encode(result())).sh_camera is None
        assert decode(encode(result())).diagnostics == {}

    def test_numpy_diagnostics_are_made_plain(self):
        d = {
            "n": np.int64(3),
            "ok": np.bool_(True),
            "v": np.arange(3, dtype=np.float32),
            "t": (1.0, 2.0),
        }
        assert plain_diagnostics(d) == {"n": 3, "ok": True, "v": [0.0, 1.0, 2.0], "t": [1.0, 2.0]}
        assert decode(encode(result(diagnostics=d))).diagnostics == plain_diagnostics(d)

    @pytest.mark.parametrize(
        "diagnostics, field",
        [
            ({"s": {1, 2}}, "result.diagnostics.s"),
            ({"o": object()}, "result.diagnostics.o"),
            ({"b": b"bytes"}, "result.diagnostics.b"),
            ({"m": np.eye(2)}, "result.diagnostics.m[0]"),
            ({"strings": ["a"]}, "result.diagnostics.strings[0]"),
            ({"a": {"b": {"c": {"d": {"e": 1}}}}}, "result.diagnostics.a.b.c.d"),
            ({f"k{i}": i for i in range(65)}, "result.diagnostics"),
            ({"long": "x" * 1025}, "result.diagnostics.long"),
            ({"big": [0.0] * 1025}, "result.diagnostics.big"),
            ({f"k{i}": [0.0] * 1000 for i in range(5)}, "result.diagnostics.k4"),
            ({"bad key!": 1}, "result.diagnostics key"),
            ({3: 1}, "result.diagnostics key"),
            ({"huge": 2**70}, "result.diagnostics.huge"),
        ],
        ids=[
            "set",
            "object",
            "bytes",
            "2-D array",
            "array of strings",
            "too deep",
            "too many keys",
            "long string",
            "long array",
            "too many values",
            "bad key",
            "int key",
            "huge int",
        ],
    )
    def test_non_plain_diagnostics_are_refused_naming_the_key(self, diagnostics, field):
        expect("bad_field", encode, result(diagnostics=diagnostics), field=field)
        expect("bad_field", plain_diagnostics, diagnostics, field=field)

    def test_hostile_diagnostics_and_sh_camera_on_decode(self):
        parts = encode(result(sh_camera=[0.0] * 9, diagnostics={"a": 1}))
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h.update(diagnostics=None)),
            field="result.diagnostics",
        )
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h.update(diagnostics=[1])),
            field="result.diagnostics",
        )
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h["diagnostics"].update(a=[[1.0]])),
            field="result.diagnostics.a[0]",
        )
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h.update(sh_camera=[0.0] * 4)),
            field="result.sh_camera",
        )
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h.pop("sh_camera")),
            field="result.sh_camera",
        )

    def test_result_is_built_with_keywords_only(self):
        with pytest.raises(TypeError):
            Result(3, 12.5, [0.1])


class TestEngineLayouts:
    """Hello config.exports and Result exports (SPEC.md section 4, "engine layouts"): optional
    keys, absent when not asked for; each layout's shape checked both ways."""

    def layouts(self) -> dict:
        return _load_vector_script().exports()

    def hello(self, **kw) -> Hello:
        return Hello(
            PROTOCOL_VERSION,
            SessionConfig(session="s", role="capture", calibration=calibration(), **kw),
        )

    def test_round_trip_and_absent_when_not_asked(self):
        back = decode(encode(self.hello(exports=("unity", "arcore"))))
        assert back.config.exports == ("unity", "arcore")
        assert "exports" not in msgpack.unpackb(bytes(encode(self.hello())[0]), raw=False)["config"]
        assert decode(encode(self.hello())).config.exports == ()
        got = decode(encode(result(exports=self.layouts())))
        assert got.exports == self.layouts()
        assert decode(encode(result())).exports is None
        assert "exports" not in msgpack.unpackb(bytes(encode(result())[0]), raw=False)

    def test_protocol_names_are_the_exporters(self):
        from arlight.cli.common import LAYOUT_NAMES
        from arlight.pipeline.engine_export import EXPORTERS

        assert EXPORT_LAYOUTS == tuple(EXPORTERS)
        assert LAYOUT_NAMES == ", ".join(EXPORT_LAYOUTS)  # the --export help

    @pytest.mark.parametrize(
        "names, field",
        [
            (("arcore", "arcore"), "hello.config.exports"),
            (("opengl",), "hello.config.exports[0]"),
            (tuple(EXPORT_LAYOUTS) + ("arcore",), "hello.config.exports"),
        ],
        ids=["twice", "unknown", "too many"],
    )
    def test_bad_names_refused_both_ways(self, names, field):
        expect("bad_field", encode, self.hello(exports=names), field=field)
        parts = encode(self.hello(exports=("arcore",)))
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h["config"].update(exports=list(names))),
            field=field,
        )

    def test_nil_is_none_and_displays_do_not_choose(self):
        parts = encode(self.hello(exports=("arcore",)))
        assert (
            decode(tamper(parts, lambda h: h["config"].update(exports=None))).config.exports == ()
        )
        display = Hello(
            PROTOCOL_VERSION, SessionConfig(session="s", role="display", exports=("arcore",))
        )
        expect("bad_field", encode, display, field="hello.config.exports")
        parts = encode(Hello(PROTOCOL_VERSION, SessionConfig(session="s", role="display")))
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h["config"].update(exports=["arcore"])),
            field="hello.config.exports",
        )

    @pytest.mark.parametrize(
        "layout, value, field",
        [
            ("arcore", [0.0] * 26, "result.exports.arcore"),
            ("webxr", [0.0] * 26 + [math.nan], "result.exports.webxr[26]"),
            ("unity", [[0.0] * 9] * 2, "result.exports.unity"),
            ("unity", [[0.0] * 9, [0.0] * 9, [0.0] * 8], "result.exports.unity[2]"),
            ("gltf", {"intensity": 1.0, "rotation": [0.0] * 4}, "result.exports.gltf"),
            (
                "gltf",
                {
                    "intensity": 1.0,
                    "rotation": [0.0] * 3,
                    "irradianceCoefficients": [[0.0] * 3] * 9,
                },
                "result.exports.gltf.rotation",
            ),
            ("filament", 3.0, "result.exports.filament"),
            (
                "main_light",
                {"direction": [0.0, 1.0], "intensity": [1.0] * 3},
                "result.exports.main_light.direction",
            ),
            ("opengl", [0.0], "result.exports key"),
        ],
        ids=[
            "arcore short",
            "webxr nan",
            "unity rows",
            "unity cols",
            "gltf keys",
            "gltf rotation",
            "filament type",
            "main light",
            "unknown layout",
        ],
    )
    def test_bad_layouts_refused_both_ways(self, layout, value, field):
        expect("bad_field", encode, result(exports={layout: value}), field=field)
        parts = encode(result(exports={"arcore": [0.0] * 27}))
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h.update(exports={layout: value})),
            field=field,
        )

    def test_empty_or_non_map_exports_refused(self):
        parts = encode(result(exports={"arcore": [0.0] * 27}))
        for bad in ({}, None, [1.0]):
            expect(
                "bad_field",
                decode,
                tamper(parts, lambda h, b=bad: h.update(exports=b)),
                field="result.exports",
            )


class TestRecords:
    def test_result_record_layout(self):
        msg = result(
            sh_camera=[0.2] * 9,
            diagnostics={"tracking": {"ok": True}},
            timings_ms={"render": 1.23456},
        )
        record = result_record(msg)
        assert list(record) == [
            "timestamp",
            "frame",
            "sh",
            "sh_camera",
            "sh_rgb",
            "dominant_direction_camera",
            "dominant_direction_world",
            "intensity",
            "confidence",
            "pose",
            "timings_ms",
            "diagnostics",
        ]
        assert record["frame"] == 3 and record["sh_camera"] == [0.2] * 9
        assert record["timings_ms"] == {"render": 1.235}
        assert record["diagnostics"] == {"tracking": {"ok": True}}

    def test_received_record_adds_delivery_fields(self):
        msg = result(timestamp=100.0, server_receive_time=100.5, server_finish_time=100.75)
        record = received_record(msg, 101.0)
        assert list(record)[:12] == list(result_record(msg))
        assert record["end_to_end_ms"] == 1000.0 and record["in_server_ms"] == 250.0
        assert record["server_to_client_ms"] == 250.0 and record["receive_time"] == 101.0
        assert record["pipeline_ms"] == pytest.approx(sum(msg.timings_ms.values()), abs=1e-3)
        assert received_record(msg, 100.0 + 7200.0)["end_to_end_ms"] is None
