"""SPEC.md read as an outside implementer reads it (issue 36): each rule it states about bytes
is checked against the golden vectors, the decoder and a loopback server, with the numbers
read from SPEC.md's own text where it writes them out. One class per point of the issue;
here: 1 key order (tables = vectors), 8 defaults, bounds, CURVE key files, engine layouts'
constants, 9 determinism. Points 2 to 7 (directions without an estimate,
result_panorama.bin, the seq bound, the version rule, the ambiguities settled, repeated
keys): test_spec_rules_messages.py. Shared helpers (spec_section, ...): conftest.py.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq
from conftest import GOLDEN, load_vector_script, refused_parts, spec_section
from conftest import expect_refusal as expect
from conftest import golden_bytes as golden_parts
from streaming_support import SMALL, RawPeer, identity_step
from zmq.utils import z85

from arlight.pipeline.runtime import configure_open3d_threads
from arlight.protocols import PROTOCOL_VERSION, Frame, Hello, Result, SessionConfig, Welcome, decode

# one Open3D thread: tracking is deterministic (SPEC.md section 11, as the entry points set)
configure_open3d_threads(1)


VEC = load_vector_script("make_protocol_vectors_rules")


# --------------------------------------------------------------------------- SPEC.md's text


def spec_tables(text: str) -> list[list[list[str]]]:
    """Each Markdown table of `text`: its body rows, each a list of cells."""
    tables, rows = [], None
    for line in text.splitlines():
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if rows is None:
                rows = []  # the header row
            elif not all(set(c) <= set("-: ") for c in cells):
                rows.append(cells)
        elif rows is not None:
            tables.append(rows)
            rows = None
    if rows is not None:
        tables.append(rows)
    return tables


def table_keys(heading: str, index: int = 0, prefix: str = "") -> list[tuple[str, bool]]:
    """(key, optional) of each row of a field table, in order: the backquoted names of the
    first column (rows naming the header's `v` skipped); optional: the type says absent."""
    out = []
    for cells in spec_tables(spec_section(heading))[index]:
        if "(header)" in cells[0]:
            continue
        for name in re.findall(r"`([^`]+)`", cells[0]):
            out.append((name.removeprefix(prefix), "**absent**" in cells[1]))
    return out


def assert_in_table_order(keys: list[str], table: list[tuple[str, bool]], what: str) -> None:
    order = [k for k, _ in table]
    unknown = [k for k in keys if k not in order]
    assert not unknown, f"{what}: keys {unknown} are in no SPEC.md table row"
    assert keys == [k for k in order if k in keys], f"{what}: {keys} is not the table's order"
    missing = [k for k, optional in table if not optional and k not in keys]
    assert not missing, f"{what}: required keys {missing} absent"


def golden_header(name: str) -> dict:
    return msgpack.unpackb(golden_parts(name)[0], raw=False)


# --------------------------------------------------------------------------- 1. key order

MESSAGE_HEADINGS = {
    "hello": "hello (client",
    "welcome": "welcome (server",
    "frame": "frame (capture",
    "result": "result (server",
    "credit": "credit (server",
    "error": "error (either",
    "heartbeat": "heartbeat (either",
    "bye": "bye (either",
}


class TestKeyOrder:
    """Point 1: the encoder writes keys in the order of SPEC.md's tables; every table is
    checked against every golden vector that has its map."""

    def test_header_table_puts_buffers_last(self):
        first_cells = [row[0] for row in spec_tables(spec_section("2. The header"))[0]]
        assert first_cells == ["`v`", "`type`", "*fields*", "`buffers`"]
        for name in VEC.vectors():
            keys = list(golden_header(name))
            assert keys[:2] == ["v", "type"], name
            if "buffers" in keys:
                assert keys[-1] == "buffers", name

    @pytest.mark.parametrize("name", sorted(VEC.vectors()))
    def test_message_fields_in_table_order(self, name):
        header = golden_header(name)
        kind = header["type"]
        fields = [k for k in header if k not in ("v", "type", "buffers")]
        if kind == "hello":
            assert fields == ["config"]
            table = table_keys(MESSAGE_HEADINGS[kind], prefix="config.")
            assert_in_table_order(list(header["config"]), table, f"{name} config")
        else:
            assert_in_table_order(fields, table_keys(MESSAGE_HEADINGS[kind]), name)

    def test_image_descriptors_in_table_order(self):
        table = table_keys("Image descriptors")
        assert [k for k, _ in table][-2:] == ["quality", "buffer"]
        table = [(k, k == "quality") for k, _ in table]  # quality: jpeg only
        seen = 0
        for name in VEC.vectors():
            header = golden_header(name)
            for key in ("color", "depth", "panorama", "composite"):
                if isinstance(header.get(key), dict):
                    assert_in_table_order(list(header[key]), table, f"{name}.{key}")
                    seen += 1
        assert seen >= 12
        assert "quality" in golden_header("frame_jpeg_zstd")["color"]

    def test_hello_maps_in_table_order(self):
        row = next(
            c
            for c in spec_tables(spec_section("hello (client"))[0]
            if c[0] == "`config.calibration`"
        )
        calibration = [
            (k.strip(), False) for k in re.search(r"`\{([^}]*)\}`", row[2]).group(1).split(",")
        ]
        panorama = table_keys("hello: the panorama light")
        scene, objects = (
            table_keys("hello: the virtual scene", 0),
            table_keys("hello: the virtual scene", 1),
        )
        for name in VEC.vectors():
            config = golden_header(name).get("config", {})
            if isinstance(config.get("calibration"), dict):
                assert_in_table_order(list(config["calibration"]), calibration, name)
            if isinstance(config.get("panorama"), dict):
                assert_in_table_order(list(config["panorama"]), panorama, name)
            if isinstance(config.get("scene"), dict):
                assert_in_table_order(list(config["scene"]), scene, name)
                for obj in config["scene"]["objects"]:
                    assert_in_table_order(list(obj), objects, f"{name} object")
                    if obj["anchor"] is not None:
                        assert list(obj["anchor"]) == ["pixel", "yaw_deg"]

    def test_exports_in_the_hellos_order(self):
        from arlight.pipeline.engine_export import camera_exports

        hello = golden_header("hello_exports")["config"]["exports"]
        result = golden_header("result_exports")["exports"]
        assert list(result) == hello
        assert list(result["gltf"]) == ["intensity", "rotation", "irradianceCoefficients"]
        assert list(result["main_light"]) == ["direction", "intensity"]
        names = ["main_light", "webxr", "unity"]
        assert list(camera_exports(np.eye(3, 9), np.eye(4), names)) == names


# --------------------------------------------------------------------------- 8. written out


class TestWrittenOut:
    """Point 8: the defaults, the JPEG bound, the CURVE files and socket options and the
    engine layouts' constants, each read from SPEC.md and checked against the code."""

    def test_session_config_defaults(self):
        text = spec_section("hello (client")
        paragraph = text[text.index("Python's `SessionConfig` fills in") :]
        paragraph = paragraph.partition("\n\n")[0]
        stated = dict(re.findall(r"`(\w+)`\s+(`[^`]*`|nil)", paragraph))
        assert set(stated) == {
            "client_name",
            "role",
            "calibration",
            "depth_scale",
            "preset",
            "overrides",
            "virtual_scene",
            "mode",
            "want_composite",
        }
        defaults = SessionConfig(session="x")
        display = golden_header("hello_display")["config"]
        for key, value in stated.items():
            want = None if value == "nil" else json.loads(value.strip("`"))
            assert getattr(defaults, key) == want, key
            if key not in ("role",):
                assert display[key] == want, key
        absent = re.search(r"`scene`,\s+`panorama`,\s+`exports` and `token` absent", paragraph)
        assert absent
        assert (defaults.scene, defaults.panorama, defaults.exports, defaults.token) == (
            None,
            None,
            (),
            None,
        )
        assert not {"scene", "panorama", "exports", "token"} & set(display)

    def test_jpeg_vector_bound(self):
        golden = spec_section("9. Golden vectors")
        bound = float(re.search(r"PSNR above \*\*(\d+) dB\*\*", golden).group(1))
        y, x = np.mgrid[0:6, 0:8]
        stated = np.stack([30 * x + 10, 40 * y + 20, 200 - 10 * x - 10 * y], -1)
        stated[0, 0] = 255
        assert np.array_equal(stated.astype(np.uint8), VEC.color_8x6())
        got = decode(golden_parts("frame_jpeg_zstd")).color.astype(np.float64)
        mse = np.mean((got - stated) ** 2)
        assert 10 * math.log10(255.0**2 / mse) > bound

    def test_curve_key_files_as_described(self, tmp_path):
        from arlight.server.security import add_client_key, generate_keys

        generate_keys(str(tmp_path))
        add_client_key(str(tmp_path), "tablet")
        names = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file())
        assert names == sorted(
            [
                "server.key",
                "server.key_secret",
                "client.key",
                "client.key_secret",
                "authorized/client.key",
                "tablet.key",
                "tablet.key_secret",
                "authorized/tablet.key",
            ]
        )
        for name in ("server", "client", "tablet"):
            public = _zpl_curve(tmp_path / f"{name}.key")
            pair = _zpl_curve(tmp_path / f"{name}.key_secret")
            assert set(public) == {"public-key"} and set(pair) == {"public-key", "secret-key"}
            assert pair["public-key"] == public["public-key"]
            for key in pair.values():
                assert len(key) == 40 and len(z85.decode(key)) == 32
            assert (tmp_path / f"{name}.key_secret").stat().st_mode & 0o077 == 0
        assert _zpl_curve(tmp_path / "authorized" / "client.key") == _zpl_curve(
            tmp_path / "client.key"
        )

    def test_curve_socket_options_as_described(self, tmp_path, make_server):
        from arlight.server.security import generate_keys

        generate_keys(str(tmp_path))
        row = next(c for c in spec_tables(spec_section("CURVE keys"))[0] if c[0] == "client DEALER")
        options = re.findall(r"`(ZMQ_CURVE_\w+)`", row[1])
        assert options == ["ZMQ_CURVE_SERVERKEY", "ZMQ_CURVE_PUBLICKEY", "ZMQ_CURVE_SECRETKEY"]
        server = make_server(process=identity_step(), keys_dir=str(tmp_path))
        client = _zpl_curve(tmp_path / "client.key_secret")
        values = {
            "ZMQ_CURVE_SERVERKEY": _zpl_curve(tmp_path / "server.key")["public-key"],
            "ZMQ_CURVE_PUBLICKEY": client["public-key"],
            "ZMQ_CURVE_SECRETKEY": client["secret-key"],
        }
        peer = RawPeer.__new__(RawPeer)
        peer.ctx = zmq.Context.instance()
        peer.socket = peer.ctx.socket(zmq.DEALER)
        peer.socket.setsockopt(zmq.LINGER, 0)
        for name in options:
            peer.socket.setsockopt(getattr(zmq, name.removeprefix("ZMQ_")), values[name].encode())
        peer.socket.connect(server.connect_address)
        assert isinstance(peer.hello("curve"), Welcome)
        peer.close()

    def test_server_socket_options_as_described(self, make_server):
        row = next(
            c for c in spec_tables(spec_section("1. Transport"))[0] if c[0] == "server ROUTER"
        )
        stated = dict(re.findall(r"`ZMQ_(\w+)` `?(\w+)`?", row[1]))
        server = make_server(process=identity_step())
        sock = server._router
        assert stated["SNDHWM"] == "send_hwm" and sock.getsockopt(zmq.SNDHWM) == 32
        assert stated["RCVHWM"] == "256" and sock.getsockopt(zmq.RCVHWM) == 256
        assert sock.getsockopt(zmq.MAXMSGSIZE) == 64 * 2**20
        assert stated["LINGER"] == "0" and sock.getsockopt(zmq.LINGER) == 0

    @pytest.mark.parametrize("rotated", [False, True])
    def test_engine_layouts_from_the_written_constants(self, rotated):
        from arlight.pipeline.engine_export import camera_exports

        text = spec_section("result: engine layouts")
        k = np.array([float(v) for v in re.search(r"`K = \(([^)]*)\)`", text).group(1).split(",")])
        a = [_pi_term(t) for t in re.search(r"`A = \(([^)]*)\)`", text).group(1).split(",")]
        assert a == [math.pi, 2 * math.pi / 3, math.pi / 4]
        per_band_a = np.array([a[0]] + [a[1]] * 3 + [a[2]] * 5)
        rng = np.random.default_rng(5)
        light = rng.normal(size=(3, 9)) * 0.3
        light[:, 0] += 1.0
        pose = np.eye(4)
        if rotated:
            q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
            pose[:3, :3] = q * np.sign(np.linalg.det(q))
        got = camera_exports(
            light, pose, ["arcore", "webxr", "gltf", "unity", "filament", "main_light"]
        )
        cs = np.array([1, -1, 1, -1, 1, -1, 1, -1, 1.0])
        for name, axes in (("webxr", np.diag([1.0, -1, -1])), ("unity", np.diag([1.0, -1, 1]))):
            c = _rotate_bands_0_2(light, axes @ pose[:3, :3].T, k)
            e = c * per_band_a
            if name == "webxr":
                np.testing.assert_allclose(got["webxr"], c.T.reshape(-1), rtol=1e-5, atol=1e-6)
                np.testing.assert_allclose(
                    got["arcore"], (c * cs).T.reshape(-1), rtol=1e-5, atol=1e-6
                )
                np.testing.assert_allclose(
                    got["gltf"]["irradianceCoefficients"], (e * cs).T, rtol=1e-5, atol=1e-6
                )
                assert got["gltf"]["intensity"] == 1.0
                assert got["gltf"]["rotation"] == [0.0, 0.0, 0.0, 1.0]
                lines = got["filament"].split("\n")
                assert lines[-1] == "" and len(lines) == 10
                for i, line in enumerate(lines[:-1]):
                    m = re.fullmatch(
                        r"\(([ -]\d\.\d{15}), ([ -]\d\.\d{15}), ([ -]\d\.\d{15})\);"
                        r" // L(\d)(-?\d)",
                        line,
                    )
                    assert m, line
                    band, order = int(m.group(4)), int(m.group(5))
                    assert band * (band + 1) + order == i
                    np.testing.assert_allclose(
                        [float(m.group(j)) for j in (1, 2, 3)], (c * cs)[:, i], atol=2e-6
                    )
                y = np.array([0.2126, 0.7152, 0.0722]) @ c
                d = np.array([y[3], y[1], y[2]]) / np.linalg.norm([y[3], y[1], y[2]])
                basis = k * np.array(
                    [
                        1,
                        d[1],
                        d[2],
                        d[0],
                        d[0] * d[1],
                        d[1] * d[2],
                        3 * d[2] ** 2 - 1,
                        d[0] * d[2],
                        d[0] ** 2 - d[1] ** 2,
                    ]
                )
                np.testing.assert_allclose(got["main_light"]["direction"], d, rtol=1e-9)
                np.testing.assert_allclose(
                    got["main_light"]["intensity"],
                    np.maximum(0, c @ basis / (basis @ basis)),
                    rtol=1e-5,
                )
            else:
                np.testing.assert_allclose(got["unity"], e * k / math.pi, rtol=1e-5, atol=1e-6)
        if not rotated:  # the diagonal case: each coefficient times its polynomial's sign
            sx, sy, sz = 1.0, -1.0, -1.0
            signs = np.array([1, sy, sz, sx, sx * sy, sy * sz, 1, sx * sz, 1])
            np.testing.assert_allclose(
                got["webxr"], (light * signs).T.reshape(-1), rtol=1e-9, atol=1e-12
            )
        dark = camera_exports(np.tile([1.0] + [0.0] * 8, (3, 1)), pose, ["main_light"])
        assert dark["main_light"] == {"direction": [0.0, 1.0, 0.0], "intensity": [0.0] * 3}


def _pi_term(term: str) -> float:
    """A term as SPEC.md writes it: "pi", "2 pi / 3", "pi / 4"."""
    numerator, _, denominator = term.partition("/")
    value = 1.0
    for factor in numerator.split():
        value *= math.pi if factor == "pi" else float(factor)
    return value / float(denominator) if denominator.strip() else value


def _zpl_curve(path: Path) -> dict[str, str]:
    """The `curve` section of a ZPL certificate, read as SPEC.md section 1 describes it:
    `#` comments, sections at column 0, entries indented 4 spaces as name = "value"."""
    section, out = None, {}
    for line in path.read_text().splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        if not line.startswith(" "):
            section = line.strip()
        elif section == "curve":
            assert line.startswith("    ")
            name, value = (s.strip() for s in line.split("=", 1))
            out[name] = value.strip('"')
    return out


def _rotate_bands_0_2(c: np.ndarray, m: np.ndarray, k: np.ndarray) -> np.ndarray:
    """SPEC.md's frame change L_e(d) = L(M^T d) of bands 0..2 (per channel, rows of `c`):
    band 1 the vector (c3, c1, c2) times M, band 2 the quadratic form Q -> M Q M^T."""
    out = np.array(c, dtype=np.float64)
    for ch in range(c.shape[0]):
        x = c[ch]
        v = m @ np.array([x[3], x[1], x[2]])
        out[ch, 3], out[ch, 1], out[ch, 2] = v
        q = np.array(
            [
                [-x[6] * k[6] + x[8] * k[8], x[4] * k[4] / 2, x[7] * k[7] / 2],
                [x[4] * k[4] / 2, -x[6] * k[6] - x[8] * k[8], x[5] * k[5] / 2],
                [x[7] * k[7] / 2, x[5] * k[5] / 2, 2 * x[6] * k[6]],
            ]
        )
        r = m @ q @ m.T
        out[ch, 4] = 2 * r[0, 1] / k[4]
        out[ch, 5] = 2 * r[1, 2] / k[5]
        out[ch, 7] = 2 * r[0, 2] / k[7]
        out[ch, 6] = r[2, 2] / (2 * k[6])
        out[ch, 8] = (r[0, 0] + out[ch, 6] * k[6]) / k[8]
    return out


# --------------------------------------------------------------------------- 9. determinism


class TestDeterminism:
    """Point 9: with Open3D on one thread, the same frames give bit-identical Results in two
    sessions (two clients), tracking included (no poses sent)."""

    LIGHT_FIELDS = (
        "sh",
        "sh_camera",
        "sh_rgb",
        "dominant_direction_camera",
        "dominant_direction_world",
        "intensity",
        "confidence_map",
        "pose",
        "diagnostics",
        "exports",
        "frames_received",
        "frames_processed",
        "frames_dropped",
    )

    def test_the_determinism_section_names_the_switch(self):
        from arlight.cli import build_parser

        text = spec_section("11. Determinism")
        assert (
            "`arlight\n--open3d-threads 1 serve`" in text
            or "`arlight --open3d-threads 1 serve`" in " ".join(text.split())
        )
        args = build_parser().parse_args(["--open3d-threads", "1", "serve"])
        assert args.open3d_threads == 1 and args.command == "serve"

    def test_two_clients_same_frames_same_results(self, make_server):
        from arlight.sources.source import calibration_of
        from arlight.sources.synthetic import make_sequence

        sequence = make_sequence(num_frames=3, width=160, height=120, seed=2)
        server = make_server(workers=2)
        results = {}
        for name in ("one", "two"):
            peer = RawPeer(server.connect_address)
            peer.send_message(
                Hello(
                    PROTOCOL_VERSION,
                    SessionConfig(
                        session=name,
                        calibration=calibration_of(sequence.camera),
                        depth_scale=float(sequence.frames[0].depth_scale),
                        preset="fast",
                        overrides=SMALL,
                        mode="lossless",
                        exports=("webxr", "main_light"),
                    ),
                )
            )
            assert isinstance(peer.receive(), Welcome)
            got = []
            for seq, frame in enumerate(sequence.frames):  # no pose: the server tracks
                peer.send_message(
                    Frame(
                        seq,
                        float(frame.timestamp),
                        frame.color,
                        frame.depth,
                        None,
                        None,
                        "png",
                        "zstd",
                    )
                )
                got.append(peer.receive(timeout_s=60))
            peer.close()
            results[name] = got
        for a, b in zip(results["one"], results["two"], strict=True):
            assert isinstance(a, Result) and isinstance(b, Result), (a, b)
            for field in self.LIGHT_FIELDS:
                assert getattr(a, field) == getattr(b, field), field
        assert results["one"][-1].pose != np.eye(4).tolist()  # tracked: the camera moved


def test_refused_vectors_are_the_spec_table_and_reproduce():
    """Every refused vector: SPEC.md section 9's table, expected.json and the script agree,
    the stored bytes are the script's, and decode() refuses each with its code and field."""
    rows = spec_tables(spec_section("Refused vectors"))[0]
    table = {r[0].strip("`").removesuffix(".bin"): (r[1].strip("`"), r[2].strip("`")) for r in rows}
    expected = json.loads((GOLDEN / "refused" / "expected.json").read_text())
    made = VEC.refused()
    assert set(table) == set(expected) == set(made)
    stored = {p.stem for p in (GOLDEN / "refused").glob("*.bin")}
    assert stored == set(made)
    for name, (parts, code, field, _) in made.items():
        assert table[name] == (code, field) == (expected[name]["code"], expected[name]["field"])
        assert refused_parts(name) == parts, name
        expect(code, field, decode, parts)


def test_dataclass_fields_of_result_cover_the_table():
    """The Result table names every wire field of Result (and nothing else)."""
    table = {k for k, _ in table_keys("result (server")}
    wire = {f.name for f in dataclasses.fields(Result)} - {"composite_codec", "jpeg_quality"}
    assert table == wire
