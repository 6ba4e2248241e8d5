"""Hostile input to arlight.protocols: every malformed or hostile message must raise
ProtocolError with the right code, and never anything else; random mutations of the golden
vectors (fuzzing) likewise."""

from __future__ import annotations

import math
import random
import struct
import zlib

import msgpack
import numpy as np
import pytest
import zstandard
from conftest import (
    as_bytes,
    calibration,
    expect,
    frame,
    load_vector_script,
    noisy_depth,
    result,
    smooth_rgb,
    tamper,
)

from arlight.protocols import (
    COLOR_CODECS,
    DEFAULT_MAX_PIXELS,
    DEPTH_CODECS,
    PROTOCOL_VERSION,
    Bye,
    Heartbeat,
    Hello,
    ProtocolError,
    SessionConfig,
    decode,
    decode_color,
    decode_depth,
    encode,
    encode_color,
    encode_depth,
    peek_header,
)
from arlight.protocols import codecs as codecs_module
from arlight.protocols import rvl as rvl_module

VEC = load_vector_script()


def png_with_ihdr(payload, width: int, height: int, fix_crc: bool = True) -> bytes:
    data = bytearray(memoryview(payload).cast("B"))
    struct.pack_into(">II", data, 16, width, height)
    if fix_crc:
        struct.pack_into(">I", data, 29, zlib.crc32(bytes(data[12:29])))
    return bytes(data)


# --------------------------------------------------------------------------- hostile input


class TestHostileInput:
    @pytest.mark.parametrize(
        "parts",
        [
            [b""],
            [b"\xc1"],
            [b"\xff" * 64],
            [b"\x81"],
            [bytes(range(256))],
            [b"\x92\x01\x02"],
        ],
    )
    def test_garbage_header(self, parts):
        expect("malformed", decode, parts)

    @pytest.mark.parametrize("value", [[1, 2], 5, "frame", None, b"xx", 1.5])
    def test_msgpack_of_a_non_map(self, value):
        expect("malformed", decode, [msgpack.packb(value, use_bin_type=True)])

    def test_not_a_part_sequence(self):
        for parts in (b"abc", "abc", 5, None, [], [object()], [1]):
            expect("malformed", decode, parts)
        expect("malformed", decode, [b"\x80"] * 17)

    def test_version_and_type(self):
        parts = encode(Heartbeat(1.0))
        expect(
            "bad_version",
            decode,
            tamper(parts, lambda h: h.update(v=PROTOCOL_VERSION + 1)),
            field="v",
        )
        expect(
            "bad_version",
            decode,
            encode(Hello(PROTOCOL_VERSION + 1, SessionConfig("s", role="display"))),
        )
        expect("malformed", decode, tamper(parts, lambda h: h.update(v="1")), field="v")
        expect("malformed", decode, tamper(parts, lambda h: h.pop("v")), field="v")
        expect(
            "unknown_type", decode, tamper(parts, lambda h: h.update(type="Frame")), field="type"
        )
        expect("malformed", decode, tamper(parts, lambda h: h.update(type=3)), field="type")
        expect("bad_version", peek_header, tamper(parts, lambda h: h.update(v=0)))

    def test_missing_and_wrong_typed_fields(self):
        parts = encode(frame())
        expect("bad_field", decode, tamper(parts, lambda h: h.pop("seq")), field="frame.seq")
        expect("bad_field", decode, tamper(parts, lambda h: h.update(seq="3")), field="frame.seq")
        expect("bad_field", decode, tamper(parts, lambda h: h.update(seq=True)), field="frame.seq")
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h.update(timestamp=None)),
            field="frame.timestamp",
        )
        expect("bad_field", decode, tamper(parts, lambda h: h.update(extra=1)), field="frame.extra")
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h["depth"].update(width=-1)),
            field="frame.depth.width",
        )
        hello = encode(Hello(PROTOCOL_VERSION, SessionConfig("s", calibration=calibration())))
        expect(
            "bad_field",
            decode,
            tamper(hello, lambda h: h["config"]["calibration"].update(K=[1.0] * 9)),
            field="hello.config.calibration.K",
        )
        expect(
            "bad_field",
            decode,
            tamper(hello, lambda h: h["config"].update(mode="fast")),
            field="hello.config.mode",
        )
        expect(
            "bad_field",
            decode,
            tamper(hello, lambda h: h["config"].update(overrides={"a": [1]})),
            field="hello.config.overrides.a",
        )
        expect(
            "bad_field",
            decode,
            tamper(hello, lambda h: h["config"].update(depth_scale=0)),
            field="hello.config.depth_scale",
        )

    def test_non_finite_numbers(self):
        parts = encode(frame())

        def nan_pose(h):
            h["pose"][1][2] = float("nan")

        expect("bad_field", decode, tamper(parts, nan_pose), field="frame.pose[1][2]")
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h.update(timestamp=math.inf)),
            field="frame.timestamp",
        )
        res = encode(result())
        expect(
            "bad_field",
            decode,
            tamper(res, lambda h: h["sh"].__setitem__(0, math.nan)),
            field="result.sh[0]",
        )
        expect(
            "bad_field",
            decode,
            tamper(encode(Heartbeat(1.0)), lambda h: h.update(time=-math.inf)),
            field="heartbeat.time",
        )

    def test_pose_must_be_a_rigid_4x4(self):
        parts = encode(frame())
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h.update(pose=[[1.0] * 4] * 3)),
            field="frame.pose",
        )
        expect(
            "bad_field",
            decode,
            tamper(parts, lambda h: h.update(pose=[1.0] * 16)),
            field="frame.pose",
        )
        scaled = (np.eye(4) * 2).tolist()
        expect(
            "bad_field", decode, tamper(parts, lambda h: h.update(pose=scaled)), field="frame.pose"
        )

    def test_mismatched_color_and_depth_sizes(self):
        parts = encode(frame(color_codec="raw", depth_codec="raw"))

        def smaller_depth(h):
            h["depth"].update(width=32, step=64)

        expect("bad_field", decode, tamper(parts, smaller_depth), field="frame.depth")

    def test_huge_declared_sizes_are_rejected_before_allocation(self, monkeypatch):
        monkeypatch.setattr(codecs_module, "_cv_decode", lambda *a: pytest.fail("decoded"))
        monkeypatch.setattr(rvl_module, "rvl_decode", lambda *a: pytest.fail("decoded"))
        parts = encode(frame(color_codec="raw", depth_codec="rvl"))

        def huge(h):
            for key in ("color", "depth"):
                h[key].update(width=65535, height=65535)
            h["color"]["step"] = 65535 * 3
            h["depth"]["step"] = 65535 * 2

        err = expect("too_large", decode, tamper(parts, huge))
        assert err.field == "frame.color" and "max_pixels" in err.message

        def too_wide(h):
            h["depth"].update(width=2**40)

        expect("bad_field", decode, tamper(parts, too_wide), field="frame.depth.width")
        expect("too_large", decode, parts, max_pixels=100)

    def test_message_size_limit(self):
        parts = encode(frame(color_codec="raw", depth_codec="raw"))
        total = sum(len(p) for p in as_bytes(parts))
        expect("too_large", decode, parts, max_message_bytes=total - 1)
        decode(parts, max_message_bytes=total)
        expect("too_large", decode, [b"\x80" * (2**20 + 1)], field="header")

    def test_truncated_and_extra_parts(self):
        parts = as_bytes(encode(frame(panorama=smooth_rgb(8, 16))))
        expect("malformed", decode, parts[:-1], field="frame.buffers")
        expect("malformed", decode, parts[:1], field="frame.buffers")
        expect("malformed", decode, [*parts, b"extra"], field="frame.buffers")
        expect("malformed", decode, [*as_bytes(encode(Bye())), b""], field="bye.buffers")
        expect("malformed", decode, [parts[0], parts[1][:-1], *parts[2:]], field="frame.buffers[0]")

        def unused_buffer(h):
            h["buffers"].append(0)

        expect("malformed", decode, [*tamper(parts, unused_buffer), b""], field="frame.buffers")

        def shared_buffer(h):
            h["depth"]["buffer"] = 0

        expect("bad_field", decode, tamper(parts, shared_buffer), field="frame.depth.buffer")

    def test_zstd_bomb(self):
        # 1 GiB of zeros in ~40 KB; the descriptor claims 64 x 48 depth
        cobj = zstandard.ZstdCompressor(level=1).compressobj(size=2**30)
        chunk = bytes(2**20)
        bomb = b"".join(cobj.compress(chunk) for _ in range(1024)) + cobj.flush()
        assert zstandard.frame_content_size(bomb) == 2**30 and len(bomb) < 2**20
        parts = as_bytes(encode(frame(depth_codec="zstd")))
        header = msgpack.unpackb(parts[0], raw=False)
        index = header["depth"]["buffer"]
        parts[index + 1] = bomb
        header["buffers"][index] = len(bomb)
        bombed = [msgpack.packb(header, use_bin_type=True), *parts[1:]]
        err = expect("decode_failed", decode, bombed, field="frame.depth")
        assert "content size" in err.message
        # a frame that hides its size, and two frames back to back
        meta = {"format": "zstd", "encoding": "16UC1", "width": 4, "height": 2, "step": 8}
        no_size = zstandard.ZstdCompressor(write_content_size=False).compress(bytes(16))
        expect("decode_failed", decode_depth, no_size, meta)
        one = zstandard.ZstdCompressor().compress(bytes(16))
        expect("decode_failed", decode_depth, one + one, meta)
        expect("decode_failed", decode_depth, one[:-2], meta)
        expect("decode_failed", decode_depth, b"not zstd at all", meta)

    def test_png_whose_ihdr_lies(self, monkeypatch):
        d = noisy_depth(6, 8)
        payload, meta = encode_depth(d, "png")
        calls = []
        real = codecs_module._cv_decode
        monkeypatch.setattr(codecs_module, "_cv_decode", lambda *a: calls.append(1) or real(*a))
        for fix_crc in (True, False):
            lie = png_with_ihdr(payload, 60000, 60000, fix_crc)
            err = expect("decode_failed", decode_depth, lie, meta, field="depth")
            assert "IHDR" in err.message
            lie = png_with_ihdr(payload, 8, 5, fix_crc)  # one row short
            expect("decode_failed", decode_depth, lie, meta)
        assert calls == []  # never handed to the decoder
        big = dict(meta, width=60000, height=60000, step=120000)
        expect("too_large", decode_depth, png_with_ihdr(payload, 60000, 60000), big)
        # colour PNG lies the same way; and a greyscale PNG sent as colour
        rgb_payload, rgb_meta = encode_color(smooth_rgb(6, 8), "png")
        expect("decode_failed", decode_color, png_with_ihdr(rgb_payload, 9, 6), rgb_meta)
        expect("decode_failed", decode_color, payload, rgb_meta)
        expect("decode_failed", decode_depth, rgb_payload, meta)
        assert calls == []

    def test_png_structure(self):
        payload, meta = encode_depth(noisy_depth(6, 8), "png")
        data = bytes(payload)
        expect("decode_failed", decode_depth, data[:-1], meta)  # IEND cut
        expect("decode_failed", decode_depth, data + b"\0", meta)  # trailing byte
        expect("decode_failed", decode_depth, data[:40], meta)
        expect("decode_failed", decode_depth, b"\x89PNG\r\n\x1a\n" + b"\0" * 40, meta)
        corrupt = bytearray(data)
        corrupt[45] ^= 0xFF  # inside IDAT: zlib or CRC error
        expect("decode_failed", decode_depth, bytes(corrupt), meta)

    def test_jpeg_whose_sof_lies(self, monkeypatch):
        payload, meta = encode_color(smooth_rgb(6, 8), "jpeg")
        data = bytearray(bytes(payload))
        sof = next(
            i
            for i in range(2, len(data) - 1)
            if data[i] == 0xFF and data[i + 1] in (0xC0, 0xC1, 0xC2)
        )
        monkeypatch.setattr(codecs_module, "_cv_decode", lambda *a: pytest.fail("decoded"))
        for h, w in ((65000, 65000), (6, 9), (0, 8)):
            lie = bytearray(data)
            struct.pack_into(">HH", lie, sof + 5, h, w)
            expect("decode_failed", decode_color, bytes(lie), meta, field="color")
        expect("decode_failed", decode_color, bytes(data[:sof]), meta)
        expect("decode_failed", decode_color, b"\xff\xd8\xff\xd9", meta)
        expect("decode_failed", decode_color, b"GIF89a", meta)
        expect("bad_codec", decode_color, payload, dict(meta, format="gif"))
        expect("bad_codec", decode_color, payload, dict(meta, encoding="bgr8"))
        expect("bad_field", decode_color, payload, dict(meta, step=25))

    def test_raw_payload_size(self):
        payload, meta = encode_depth(noisy_depth(6, 8), "raw")
        expect("decode_failed", decode_depth, bytes(payload)[:-2], meta)
        payload, meta = encode_color(smooth_rgb(6, 8), "raw")
        expect("decode_failed", decode_color, bytes(payload) + b"\0\0\0", meta)

    def test_rvl_payload_errors_are_decode_failed(self):
        meta = {"format": "rvl", "encoding": "16UC1", "width": 4, "height": 2, "step": 8}
        for payload in (b"", b"\xff" * 8, b"\0\0\0", b"\0" * 400):
            expect("decode_failed", decode_depth, payload, meta, field="depth")

    def test_descriptor_checks(self):
        payload, meta = encode_depth(noisy_depth(6, 8), "zstd")
        expect("bad_field", decode_depth, payload, "not a map")
        expect("bad_field", decode_depth, payload, dict(meta, width=8.0), field="depth.width")
        expect("bad_field", decode_depth, payload, dict(meta, height=0), field="depth.height")
        expect(
            "bad_field",
            decode_depth,
            payload,
            {k: v for k, v in meta.items() if k != "step"},
            field="depth.step",
        )
        expect("bad_codec", decode_depth, payload, dict(meta, encoding="mono16"))
        expect("bad_field", decode_depth, payload, dict(meta, format=None))
        expect("too_large", decode_depth, payload, meta, max_pixels=47)
        assert decode_depth(payload, meta, max_pixels=48).shape == (6, 8)
        assert DEFAULT_MAX_PIXELS == 4096 * 4096


# --------------------------------------------------------------------------- fuzz


def _fuzz_corpus() -> list[list[bytes]]:
    corpus = [as_bytes(encode(m)) for m in VEC.vectors().values()]
    small = dict(color=smooth_rgb(6, 8), depth=noisy_depth(6, 8), panorama=smooth_rgb(4, 8))
    for cc in COLOR_CODECS:
        for dc in DEPTH_CODECS:
            corpus.append(as_bytes(encode(frame(color_codec=cc, depth_codec=dc, **small))))
    return corpus


def _mutate(parts: list[bytes], rnd: random.Random) -> list[bytes]:
    parts = [bytearray(p) for p in parts]
    for _ in range(rnd.randint(1, 4)):
        op = rnd.random()
        if op < 0.05 and len(parts) > 1:
            del parts[rnd.randrange(1, len(parts))]
            continue
        if op < 0.08:
            parts.append(bytearray(rnd.randbytes(rnd.randint(0, 16))))
            continue
        i = rnd.randrange(len(parts)) if rnd.random() < 0.5 else 0  # the header half the time
        p = parts[i]
        if not p:
            continue
        j = rnd.randrange(len(p))
        if op < 0.5:
            p[j] ^= 1 << rnd.randrange(8)
        elif op < 0.7:
            p[j] = rnd.randrange(256)
        elif op < 0.8:
            del p[j : j + rnd.randint(1, 8)]
        elif op < 0.9:
            p[j:j] = rnd.randbytes(rnd.randint(1, 8))
        else:
            parts[i] = p[:j]
    return [bytes(p) for p in parts]


def test_fuzz_mutations_only_raise_protocol_error():
    rnd = random.Random(20240603)
    corpus = _fuzz_corpus()
    codes = set()
    for _ in range(3000):
        parts = _mutate(rnd.choice(corpus), rnd)
        try:
            decode(parts)
        except ProtocolError as exc:
            codes.add(exc.code)
            # explicit validation, not decode()'s last-resort wrapper around a stray exception
            assert exc.__cause__ is None, f"{exc!r} came from {exc.__cause__!r}"
        # any other exception type fails the test by propagating
    assert {"malformed", "bad_field", "decode_failed"} <= codes
