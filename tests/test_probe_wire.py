"""The reflection probe on the wire (issue 33, item 3): Hello `config.probe`, Result `probe`
(RGB9E5 texels in a zstd part), their limits, the golden vectors, the server's checks and
budget, and a real session over loopback whose probe sees a red wall in its +Z face."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import GOLDEN, load_vector_script, spec_section
from streaming_support import SMALL, RawPeer, edit_header

from arlight.core.camera import PinholeCamera
from arlight.core.contracts import Confidence
from arlight.pipeline import probe_cube
from arlight.pipeline.config import Config
from arlight.protocols import (
    PROTOCOL_VERSION,
    Error,
    Frame,
    Hello,
    ProtocolError,
    Result,
    SessionConfig,
    Welcome,
    decode,
    encode,
    read_container,
)
from arlight.protocols.probe import (
    MAX_PROBE_BYTES,
    PROBE_LAST_LEVEL,
    PROBE_SIZE_MAX,
    PROBE_SIZE_MIN,
    ProbeCube,
    ProbeRequest,
    face_directions,
    num_levels,
    rgb9e5_decode,
    rgb9e5_encode,
)
from arlight.server.budget import SessionBudget, check_cost

VEC = load_vector_script("make_protocol_vectors_probe")


def _cube(size: int = 32, levels: int = 1, seed: int = 0) -> ProbeCube:
    rng = np.random.default_rng(seed)
    data = [
        rng.uniform(0.0, 4.0, (6, size >> k, size >> k, 3)).astype(np.float32)
        for k in range(levels)
    ]
    return ProbeCube(
        [0.5, -0.25, 1.0], data, list(np.linspace(0.0, 1.0, num_levels(size))[:levels])
    )


def _result(probe: ProbeCube | None) -> Result:
    return Result(
        seq=1,
        timestamp=1.0,
        sh=[0.25] + [0.0] * 15,
        dominant_direction_camera=[0.0, 0.0, 0.0],
        dominant_direction_world=[0.0, 0.0, 0.0],
        intensity=0.0,
        confidence=Confidence(),
        pose=np.eye(4).tolist(),
        timings_ms={},
        frames_received=1,
        frames_processed=1,
        frames_dropped=0,
        server_receive_time=1.0,
        server_finish_time=1.0,
        probe=probe,
    )


def _capture_hello(probe) -> Hello:
    from arlight.protocols import CameraCalibration

    cal = CameraCalibration(8, 6, 5.0, 5.0, 3.5, 2.5)
    return Hello(PROTOCOL_VERSION, SessionConfig("s", calibration=cal, probe=probe))


class TestRgb9e5:
    def test_a_known_word(self):
        # 1.0 grey: mantissas 256, exponent 16 (256 x 2^(16 - 24) = 1)
        assert int(rgb9e5_encode(np.array([1.0, 1.0, 1.0]))) == 0x84020100
        assert rgb9e5_decode(np.uint32(0x84020100)).tolist() == [1.0, 1.0, 1.0]

    def test_round_trip_within_a_mantissa_step_of_the_brightest_channel(self):
        rng = np.random.default_rng(1)
        v = rng.uniform(0.0, 1.0, (5000, 3)) * 10.0 ** rng.uniform(-3, 4, (5000, 1))
        back = rgb9e5_decode(rgb9e5_encode(v))
        err = np.abs(back - v).max(axis=1) / v.max(axis=1)
        assert err.max() <= 1.0 / 512  # half a step of a mantissa in 256..511
        tiny = np.array([[3e-6, 1e-7, 0.0]])  # below 2^-15: absolute steps of 2^-24
        assert np.abs(rgb9e5_decode(rgb9e5_encode(tiny)) - tiny).max() <= 2.0**-25

    def test_clamps_negative_nan_and_too_large(self):
        v = np.array([[-1.0, 0.5, 0.0], [np.nan, 1.0, 0.0], [1e9, 0.0, 0.0], [0.0, 0.0, 0.0]])
        back = rgb9e5_decode(rgb9e5_encode(v))
        assert back.tolist() == [[0.0, 0.5, 0.0], [0.0, 1.0, 0.0], [65408.0, 0.0, 0.0], [0.0] * 3]

    def test_the_words_are_little_endian(self):
        assert rgb9e5_encode(np.ones((2, 3))).tobytes()[:4] == bytes([0x00, 0x01, 0x02, 0x84])


class TestLayout:
    def test_the_protocols_sizes_are_the_probes(self):
        assert (PROBE_SIZE_MIN, PROBE_SIZE_MAX) == (probe_cube.SIZE_MIN, probe_cube.SIZE_MAX)
        assert PROBE_LAST_LEVEL == probe_cube.LAST_LEVEL_TEXELS
        for size in (32, 64, 128, 256):
            assert num_levels(size) == probe_cube.num_levels(size)
        assert MAX_PROBE_BYTES == 2_097_024

    @pytest.mark.parametrize("size", [4, 32])
    def test_spec_directions_are_the_pipelines_texels(self, size):
        np.testing.assert_allclose(
            face_directions(size), probe_cube.texel_directions(size), atol=1e-12
        )

    def test_spec_direction_table_is_the_written_one(self):
        text = spec_section("result: the reflection probe")
        rows = dict(
            (face, expr)
            for face, expr in (
                line.strip("| ").split(" | ")
                for line in text.splitlines()
                if line.startswith("| +") or line.startswith("| -")
            )
        )
        s, t = 0.3, -0.6
        want = {
            "+X": (1, -t, -s),
            "-X": (-1, -t, s),
            "+Y": (s, 1, t),
            "-Y": (s, -1, -t),
            "+Z": (s, -t, 1),
            "-Z": (-s, -t, -1),
        }
        for face, expr in rows.items():
            got = eval(expr.strip("`"), {"s": s, "t": t})  # noqa: S307 - SPEC.md's own text
            assert tuple(got) == want[face], face
        # and the table is what the texels are: column i, row j -> s, t
        m, i, j = 8, 2, 5
        s, t = 2 * (i + 0.5) / m - 1, 2 * (j + 0.5) / m - 1
        for f, face in enumerate(("+X", "-X", "+Y", "-Y", "+Z", "-Z")):
            d = np.array(eval(rows[face].strip("`"), {"s": s, "t": t}), float)  # noqa: S307
            np.testing.assert_allclose(d / np.linalg.norm(d), face_directions(m)[f, j, i])


class TestResultProbe:
    def test_round_trip_every_level(self):
        cube = _cube(64, num_levels(64))
        got = decode(encode(_result(cube))).probe
        assert got.size == 64 and len(got.levels) == 5 and got.roughness == cube.roughness
        assert got.point_world == cube.point_world and got.encoding == "rgb9e5"
        for a, b in zip(cube.levels, got.levels, strict=True):
            assert b.shape == a.shape and b.dtype == np.float32
            assert (np.abs(a - b).max(-1) / a.max(-1)).max() <= 1.0 / 512 + 1e-6

    def test_the_part_is_one_zstd_frame_of_the_texels(self):
        import zstandard

        parts = encode(_result(_cube(32)))
        assert len(parts) == 2
        raw = zstandard.ZstdDecompressor().decompress(bytes(parts[1]))
        assert len(raw) == 4 * 6 * 32 * 32

    def test_no_probe_is_no_key(self):
        import msgpack

        header = msgpack.unpackb(bytes(encode(_result(None))[0]))
        assert "probe" not in header and decode(encode(_result(None))).probe is None

    def test_golden_vector(self):
        (parts,) = read_container((GOLDEN / "result_probe.bin").read_bytes())
        got = decode(parts).probe
        want = VEC.probe_cube()
        assert got == want  # exact: every texel is a multiple of 1/32
        # the texel at column 3, row 5 of face -Y (3) of level 1 (16 texels a face)
        assert got.levels[1][3, 5, 3].tolist() == [4 / 16, 6 / 16, 3 / 8]


def _edit(path: tuple, value):
    def edit(header: dict) -> None:
        m = header
        for k in path[:-1]:
            m = m[k]
        if value is KeyError:
            del m[path[-1]]
        else:
            m[path[-1]] = value

    return edit


class TestResultRefused:
    @pytest.mark.parametrize(
        "path, value, code, field",
        [
            (("probe", "size"), 48, "bad_field", "result.probe.size"),
            (("probe", "size"), 512, "bad_field", "result.probe.size"),
            (("probe", "levels"), 0, "bad_field", "result.probe.levels"),
            (("probe", "levels"), 5, "bad_field", "result.probe.levels"),
            (("probe", "roughness"), [0.5], "bad_field", "result.probe.roughness"),
            (("probe", "roughness"), [0.0, 0.0], "bad_field", "result.probe.roughness"),
            (("probe", "encoding"), "f16", "bad_codec", "result.probe.encoding"),
            (("probe", "point_world"), [0.0, 1e5, 0.0], "bad_field", "result.probe.point_world[1]"),
            (("probe", "buffer"), 3, "bad_field", "result.probe.buffer"),
            (("probe", "extra"), 1, "bad_field", "result.probe.extra"),
            (("probe", "encoding"), KeyError, "bad_field", "result.probe.encoding"),
        ],
    )
    def test_header_fields(self, path, value, code, field):
        cube = _cube(32, 2)
        parts = [bytes(p) for p in encode(_result(cube))]
        with pytest.raises(ProtocolError) as exc:
            decode(edit_header(parts, _edit(path, value)))
        assert (exc.value.code, exc.value.field) == (code, field)

    def test_a_frame_of_another_size_is_refused_before_inflating(self):
        import zstandard

        parts = [bytes(p) for p in encode(_result(_cube(32)))]
        wrong = zstandard.ZstdCompressor().compress(b"\0" * (4 * 6 * 32 * 32 + 4))
        for payload in (wrong, parts[1][:-3], parts[1] + b"\0", b"not zstd"):
            header = edit_header(parts, _edit(("buffers",), [len(payload)]))[0]
            with pytest.raises(ProtocolError) as exc:
                decode([header, payload])
            assert (exc.value.code, exc.value.field) == ("decode_failed", "result.probe.buffer")

    def test_encode_refuses_a_level_of_the_wrong_shape(self):
        cube = _cube(32, 2)
        cube.levels[1] = cube.levels[1][:, :8]
        with pytest.raises(ProtocolError) as exc:
            encode(_result(cube))
        assert exc.value.field == "result.probe.levels"


class TestHello:
    def test_round_trip(self):
        request = ProbeRequest(128, (0.25, -0.5, 1.5), True)
        got = decode(encode(_capture_hello(request))).config.probe
        assert got == request and got.levels == 6 and got.max_bytes == 4 * 6 * 21840

    def test_absent_by_default_and_the_golden_vector(self):
        import msgpack

        assert "probe" not in msgpack.unpackb(bytes(encode(_capture_hello(None))[0]))["config"]
        (parts,) = read_container((GOLDEN / "hello_probe.bin").read_bytes())
        assert decode(parts).config.probe == ProbeRequest(64, (0.25, -0.5, 1.5), True)

    @pytest.mark.parametrize(
        "key, value, field",
        [
            ("size", 16, "size"),
            ("size", 96, "size"),
            ("size", 512, "size"),
            ("size", True, "size"),
            ("point_world", [0.0, float("nan"), 1.0], "point_world[1]"),
            ("point_world", [0.0, 0.0], "point_world"),
            ("point_world", [2e4, 0.0, 0.0], "point_world[0]"),
            ("mips", 1, "mips"),
            ("colour", "red", "colour"),
        ],
    )
    def test_limits_name_the_key(self, key, value, field):
        parts = [bytes(p) for p in encode(_capture_hello(ProbeRequest()))]
        with pytest.raises(ProtocolError) as exc:
            decode(edit_header(parts, _edit(("config", "probe", key), value)))
        assert (exc.value.code, exc.value.field) == ("bad_field", f"hello.config.probe.{field}")

    def test_a_display_cannot_ask(self):
        with pytest.raises(ProtocolError) as exc:
            encode(
                Hello(PROTOCOL_VERSION, SessionConfig("s", role="display", probe=ProbeRequest()))
            )
        assert exc.value.field == "hello.config.probe"


class TestBudget:
    def test_the_probe_is_priced_and_grows_with_its_size(self):
        camera = PinholeCamera.kinect_v1(640, 480)
        budget = SessionBudget()
        plain = check_cost(Config(), camera, 0, budget)
        costs = {
            size: check_cost(Config().replace(probe_size=size), camera, 0, budget, probe=True)
            for size in (64, 128, 256)
        }
        assert plain.stage_s["Probe"] == 0.0 and plain.memory_bytes["probe_size"] == 0.0
        assert costs[64].stage_s["Probe"] == pytest.approx(0.040)
        assert costs[256].stage_s["Probe"] > 10 * costs[64].stage_s["Probe"]
        assert costs[128].memory_bytes["probe_size"] == 4 * costs[64].memory_bytes["probe_size"]
        assert costs[64].memory_bytes["probe_cells"] > 0  # its room grid too

    def test_a_probe_over_the_deadline_names_its_size(self):
        from arlight.protocols import CameraCalibration
        from arlight.server.session import SessionSetup, SessionSetupError

        config = SessionConfig(
            "s",
            calibration=CameraCalibration(64, 48, 60.0, 60.0, 32.0, 24.0),
            preset="mobile",
            probe=ProbeRequest(256, (0.0, 0.0, 1.0)),
        )
        with pytest.raises(SessionSetupError) as exc:
            SessionSetup.from_config(
                config,
                max_pixels=2**24,
                max_message_bytes=2**26,
                budget=SessionBudget(frame_deadline_s=0.4),
            )
        assert exc.value.code == "over_budget" and exc.value.field == "probe.size"


# ------------------------------------------------------------------ a real session, loopback


def _red_wall_frame(seq: int) -> Frame:
    color = np.zeros((48, 64, 3), np.uint8)
    color[...] = (200, 30, 30)
    depth = np.full((48, 64), 7500, np.uint16)  # 1.5 m at depth_scale 5000
    return Frame(seq, 1.0 + seq, color, depth, None, None, "raw", "raw")


class TestSession:
    def test_a_red_wall_ahead_lands_in_the_probes_plus_z_face(self, make_server):
        """The first camera looks along world +z (OpenCV axes) at a red wall 1.5 m away; a
        probe at (0, 0, 0.75) sees it in its +Z face, the face SPEC.md's table gives for
        directions along +z, and nowhere behind it."""
        server = make_server(heartbeat_interval_s=20.0)  # the first frame compiles kernels
        peer = RawPeer(server.connect_address)
        request = ProbeRequest(32, (0.0, 0.0, 0.75), mips=True)
        hello = peer.hello("probe", preset="fast", overrides=SMALL, probe=request)
        assert isinstance(hello, Welcome), hello
        for seq in range(2):
            peer.send_message(_red_wall_frame(seq))
            result = peer.receive(120)
            assert isinstance(result, Result), result
        probe = result.probe
        assert probe is not None and probe.point_world == [0.0, 0.0, 0.75]
        assert probe.size == 32 and len(probe.levels) == num_levels(32)
        assert probe.roughness == pytest.approx([0.0, 1 / 3, 2 / 3, 1.0])
        assert result.diagnostics["probe"]["hit_fraction"] > 0.05
        level0 = probe.levels[0]
        red = level0[..., 0] > 2.0 * level0[..., 1]  # (6, 32, 32)
        share = red.reshape(6, -1).mean(axis=1)
        assert share[4] > 0.5, share  # +Z
        assert share[5] == 0.0 and max(share[:4]) < 0.25, share
        peer.close()

    def test_a_session_without_the_key_gets_no_probe(self, make_server):
        server = make_server(heartbeat_interval_s=20.0)
        peer = RawPeer(server.connect_address)
        assert isinstance(peer.hello("plain", preset="fast", overrides=SMALL), Welcome)
        peer.send_message(_red_wall_frame(0))
        result = peer.receive(120)
        assert isinstance(result, Result) and result.probe is None
        peer.close()

    @pytest.mark.parametrize(
        "config, field",
        [
            (dict(probe=ProbeRequest(64)), "hello.config.probe.point_world"),
            (
                dict(probe=ProbeRequest(64, (0.0, 0.0, 1.0)), overrides={"probe": False}),
                "hello.config.probe",
            ),
            (
                dict(probe=ProbeRequest(64, (0.0, 0.0, 1.0)), overrides={"probe_size": 128}),
                "hello.config.probe.size",
            ),
        ],
    )
    def test_the_server_refuses_naming_the_key(self, make_server, config, field):
        server = make_server()
        peer = RawPeer(server.connect_address)
        error = peer.hello("refused", **config)
        assert isinstance(error, Error) and (error.code, error.field) == ("bad_field", field)
        assert not error.retryable
        peer.close()


def test_the_clients_ask_for_and_decode_the_probe(make_server, tmp_path):
    """The Python clients over loopback: a CaptureClient whose StreamOptions ask for a probe
    gets it in each Result (decoded: a ProbeCube of float32 levels), and a display watching
    the session decodes the same Results (an older display would refuse them)."""
    import json
    import threading

    from streaming_support import flat_source, run_with_timeout

    from arlight.client.capture import StreamOptions, stream
    from arlight.client.display import DisplayClient, DisplayOptions

    server = make_server(heartbeat_interval_s=20.0)
    out = tmp_path / "display"
    display = DisplayClient(
        DisplayOptions(server=server.connect_address, session="probed", out_dir=str(out))
    )
    thread = threading.Thread(target=display.run, daemon=True)
    thread.start()
    assert display.subscribed.wait(10)
    got: list[Result] = []
    options = StreamOptions(
        server=server.connect_address,
        session="probed",
        mode="lossless",
        rate="max",
        preset="fast",
        overrides=SMALL,
        probe=ProbeRequest(32, (0.0, 0.0, 1.0), mips=False),
    )
    summary = run_with_timeout(
        lambda: stream(flat_source(2), options, on_result=lambda r, _: got.append(r)), 120
    )
    assert summary.errors == [] and len(got) == 2
    for result in got:
        assert isinstance(result.probe, ProbeCube)
        assert [lv.shape for lv in result.probe.levels] == [(6, 32, 32, 3)]
        assert result.probe.levels[0].dtype == np.float32 and result.probe.roughness == [0.0]
        assert np.all(result.probe.levels[0] >= 0.0)
    thread.join(30)
    lines = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert [line["frame"] for line in lines] == [0, 1]
    assert all(line["diagnostics"]["probe"]["size"] == 32 for line in lines)
    # what came, never the texels (output-record.md)
    assert all(
        line["probe"] == {"size": 32, "levels": 1, "roughness": [0.0], "point_world": [0, 0, 1]}
        for line in lines
    )


def test_a_server_with_a_compute_step_refuses_a_probe(make_server):
    """`arlight serve --ray` computes through a ProcessStep, which makes no probe: the Hello
    is refused naming the key, not answered with Results that silently lack it."""
    from streaming_support import identity_step

    server = make_server(process=identity_step())
    peer = RawPeer(server.connect_address)
    error = peer.hello("stepped", probe=ProbeRequest(32, (0.0, 0.0, 1.0)))
    assert isinstance(error, Error) and (error.code, error.field) == (
        "bad_field",
        "hello.config.probe",
    )
    assert "--ray" in error.message
    peer.close()


def _first_table_keys(heading: str) -> list[str]:
    """The backquoted names in the first column of the first table under `heading`."""
    import re

    table = spec_section(heading).split("|---|", 1)[1].split("\n\n", 1)[0]
    rows = [line for line in table.splitlines() if line.startswith("| `")]
    return [name for row in rows for name in re.findall(r"`([^`]+)`", row.split("|")[1])]


def test_the_golden_maps_are_in_the_spec_tables_order():
    import msgpack

    (hello,) = read_container((GOLDEN / "hello_probe.bin").read_bytes())
    (result,) = read_container((GOLDEN / "result_probe.bin").read_bytes())
    hello_map = msgpack.unpackb(bytes(hello[0]))["config"]["probe"]
    result_header = msgpack.unpackb(bytes(result[0]))
    assert list(hello_map) == _first_table_keys("hello: the reflection probe")
    keys = _first_table_keys("result: the reflection probe")
    assert list(result_header["probe"]) == keys
    assert list(result_header)[-3:] == ["probe", "composite", "buffers"]


# a flipped pose float overflows in the pose check (arlight/core/checks.py), which refuses it
@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_flipped_and_cut_probes_raise_protocol_errors_only():
    """Every byte of result_probe.bin's header flipped, and its texel part cut or flipped:
    decode returns a message or raises ProtocolError, never anything else."""
    (parts,) = read_container((GOLDEN / "result_probe.bin").read_bytes())
    header, payload = bytes(parts[0]), bytes(parts[1])
    rng = np.random.default_rng(3)
    cases = [
        [header[:i] + bytes([header[i] ^ 0xFF]) + header[i + 1 :], payload]
        for i in range(len(header))
    ]
    for _ in range(200):
        i = int(rng.integers(len(payload)))
        cases.append(
            [
                header,
                payload[:i] + bytes([payload[i] ^ (1 << int(rng.integers(8)))]) + payload[i + 1 :],
            ]
        )
    for cut in (0, 1, 10, len(payload) // 2, len(payload) - 1):
        cases.append([header, payload[:cut]])
    for case in cases:
        try:
            decode(case)
        except ProtocolError:
            pass
