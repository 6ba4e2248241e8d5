"""Image codecs of the wire protocol: colour (JPEG, PNG, raw) and depth (zstd, PNG, RVL, raw).

Each encoder returns ``(payload, meta)``: the payload travels as its own ZeroMQ frame, the
meta dict goes into the message header as the image descriptor (Foxglove
CompressedImage/RawImage-style field names: ``format``, ``encoding``, ``width``, ``height``,
``step``). Each decoder checks the descriptor, then the size the payload itself declares
(PNG IHDR, JPEG SOF, zstd frame content size) against it and against ``max_pixels`` before
allocating anything, and checks that the decoded image has exactly the declared shape.

Colour: (H, W, 3) uint8 RGB. Depth: (H, W) uint16, 0 = missing, units given by the session's
``depth_scale``. Raw payloads are the row-major pixel bytes without padding (depth
little-endian); raw encoders return a zero-copy memoryview of the caller's array when it is
C-contiguous, and raw/zstd decoders may return read-only arrays (copy before writing).
"""

from __future__ import annotations

import math
import struct

import cv2
import numpy as np
import zstandard

from .errors import ProtocolError

DEFAULT_MAX_PIXELS: int = 4096 * 4096
MAX_IMAGE_SIDE: int = 65535  # JPEG's limit; applied to every codec

COLOR_CODECS: tuple[str, ...] = ("jpeg", "png", "raw")
DEPTH_CODECS: tuple[str, ...] = ("zstd", "png", "rvl", "raw")
DEFAULT_COLOR_CODEC: str = "jpeg"
DEFAULT_JPEG_QUALITY: int = 90
# benchmarks/depth_codecs.py on 125 real 640 x 480 depth frames (SPEC.md, "Codecs"): zstd
# level 1 gives 6.6:1 at 1.4 ms encode / 0.7 ms decode; RVL 3.4:1 at 1.4 / 0.9 ms; PNG
# 5.2:1 at 7.5 / 3.3 ms. zstd level 3 saves 3.5 % of the bytes for 13 % more encode time.
DEFAULT_DEPTH_CODEC: str = "zstd"
ZSTD_LEVEL: int = 1
PNG_COMPRESSION: int = 1  # zlib level used for PNG (colour and depth)

COLOR_ENCODING = "rgb8"  # ROS/Foxglove encoding names
DEPTH_ENCODING = "16UC1"

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"\x00\x00\x00\x00IEND\xae\x42\x60\x82"
_JPEG_SOF = frozenset(
    (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF)
)
_CV_COLOR = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
_CV_DEPTH16 = cv2.IMREAD_ANYDEPTH | cv2.IMREAD_IGNORE_ORIENTATION


# --------------------------------------------------------------------------- helpers


def as_bytes_view(part) -> memoryview:
    """A flat byte memoryview of bytes / bytearray / memoryview / numpy / zmq.Frame."""
    buf = getattr(part, "buffer", None)  # zmq.Frame
    try:
        mv = memoryview(buf if buf is not None else part)
        if mv.ndim != 1 or mv.itemsize != 1 or mv.format != "B":
            mv = mv.cast("B")
    except (TypeError, ValueError) as exc:
        raise ProtocolError("malformed", f"message part is not a byte buffer: {exc}") from None
    return mv


def _int_field(meta: dict, key: str, field: str, lo: int, hi: int) -> int:
    value = meta.get(key)
    if type(value) is not int:
        raise ProtocolError(
            "bad_field", f"expected an integer, got {type(value).__name__}", f"{field}.{key}"
        )
    if not lo <= value <= hi:
        raise ProtocolError("bad_field", f"{value} is outside {lo}..{hi}", f"{field}.{key}")
    return value


def check_image_meta(
    meta,
    codecs: tuple[str, ...],
    encoding: str,
    channels: int,
    bytes_per_channel: int,
    max_pixels: int,
    field: str,
) -> tuple[str, int, int]:
    """Validate an image descriptor; returns (format, width, height). Allocates nothing."""
    if not isinstance(meta, dict):
        raise ProtocolError("bad_field", f"expected a map, got {type(meta).__name__}", field)
    fmt = meta.get("format")
    if not isinstance(fmt, str):
        raise ProtocolError("bad_field", "missing image format", f"{field}.format")
    if fmt not in codecs:
        raise ProtocolError(
            "bad_codec", f"format {fmt[:32]!r} is not one of {codecs}", f"{field}.format"
        )
    enc = meta.get("encoding")
    if not isinstance(enc, str):
        raise ProtocolError("bad_field", "missing pixel encoding", f"{field}.encoding")
    if enc != encoding:
        raise ProtocolError(
            "bad_codec", f"encoding {enc[:32]!r}, expected {encoding!r}", f"{field}.encoding"
        )
    width = _int_field(meta, "width", field, 1, MAX_IMAGE_SIDE)
    height = _int_field(meta, "height", field, 1, MAX_IMAGE_SIDE)
    if width * height > max_pixels:
        raise ProtocolError(
            "too_large",
            f"{width} x {height} = {width * height} pixels exceeds max_pixels {max_pixels}",
            field,
        )
    step = _int_field(meta, "step", field, 0, MAX_IMAGE_SIDE * 8)
    if step != width * channels * bytes_per_channel:
        raise ProtocolError(
            "bad_field",
            f"step {step}, expected width * {channels * bytes_per_channel} = "
            f"{width * channels * bytes_per_channel} (rows are not padded)",
            f"{field}.step",
        )
    return fmt, width, height


# The headers are read in Python before the C decoders run, so their cost must not grow
# with the payload (issue 39, item 2: 60 MiB of empty JPEG APP segments, walked one by one,
# held the GIL 8 s a frame; figures: docs/reliability.md). A PNG may hold
# PNG_MAX_ANCILLARY chunks other than IDAT (libpng warns on each broken one, on stderr) and
# one chunk per PNG_BYTES_PER_CHUNK bytes in all (encoders write IDAT chunks of 8 KiB or
# more); a JPEG's SOF must come within JPEG_MAX_SEGMENTS segments (cameras write about
# 10-20 before it: APPn with EXIF and ICC, DQT, DHT), after at most JPEG_MAX_FILL fill
# bytes each, found at C speed.
PNG_MAX_ANCILLARY = 64
PNG_BYTES_PER_CHUNK = 1024
JPEG_MAX_SEGMENTS = 256
JPEG_MAX_FILL = 4096


def png_header(data: memoryview) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from the IHDR chunk, after walking the chunk
    structure (IHDR first, lengths in bounds, IEND last, at most 64 + len / 1024 chunks of
    which PNG_MAX_ANCILLARY not IDAT). Raises ProtocolError."""
    n = len(data)
    if n < 8 + 25 + 12 or bytes(data[:8]) != _PNG_SIGNATURE:
        raise ProtocolError("decode_failed", "not a PNG (bad signature or too short)")
    length, ctype = struct.unpack_from(">I4s", data, 8)
    if ctype != b"IHDR" or length != 13:
        raise ProtocolError("decode_failed", "PNG does not start with a 13-byte IHDR chunk")
    width, height, bit_depth, colour_type = struct.unpack_from(">IIBB", data, 16)
    pos = 8
    ancillary = 0
    for _ in range(64 + n // PNG_BYTES_PER_CHUNK):  # every chunk: 4 length + 4 type + data + 4 CRC
        if pos + 12 > n:
            raise ProtocolError("decode_failed", "PNG is truncated (no IEND chunk)")
        length, ctype = struct.unpack_from(">I4s", data, pos)
        end = pos + 12 + length
        if length > 0x7FFFFFFF or end > n:
            raise ProtocolError("decode_failed", "PNG chunk runs past the end of the payload")
        if ctype == b"IEND":
            if end != n:
                raise ProtocolError("decode_failed", "bytes after the PNG IEND chunk")
            return width, height, bit_depth, colour_type
        if ctype != b"IDAT":
            ancillary += 1
            if ancillary > PNG_MAX_ANCILLARY:
                raise ProtocolError(
                    "decode_failed", f"PNG has over {PNG_MAX_ANCILLARY} chunks other than IDAT"
                )
        pos = end
    raise ProtocolError("decode_failed", f"PNG has over one chunk per {PNG_BYTES_PER_CHUNK} bytes")


def jpeg_header(data: memoryview) -> tuple[int, int, int, int]:
    """(width, height, components, precision) from the first SOF marker, which must come
    within JPEG_MAX_SEGMENTS segments. Raises ProtocolError."""
    n = len(data)
    if n < 4 or data[0] != 0xFF or data[1] != 0xD8:
        raise ProtocolError("decode_failed", "not a JPEG (no SOI marker)")
    pos = 2
    for _ in range(JPEG_MAX_SEGMENTS):
        if pos + 4 > n or data[pos] != 0xFF:
            raise ProtocolError("decode_failed", "JPEG has no frame header (SOF) before its data")
        window = bytes(data[pos : pos + JPEG_MAX_FILL + 1])  # fill bytes, then the marker
        fill = len(window) - len(window.lstrip(b"\xff"))
        if fill > JPEG_MAX_FILL:
            raise ProtocolError("decode_failed", f"JPEG has over {JPEG_MAX_FILL} fill bytes")
        pos += fill
        if pos >= n:
            raise ProtocolError("decode_failed", "JPEG is truncated")
        marker = data[pos]
        pos += 1
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # no length
            continue
        if marker in (0xD8, 0xD9, 0xDA):  # SOI again, EOI or scan before any SOF
            raise ProtocolError("decode_failed", "JPEG has no frame header (SOF) before its data")
        if pos + 2 > n:
            raise ProtocolError("decode_failed", "JPEG is truncated")
        (length,) = struct.unpack_from(">H", data, pos)
        if length < 2 or pos + length > n:
            raise ProtocolError("decode_failed", "JPEG segment runs past the end of the payload")
        if marker in _JPEG_SOF:
            if length < 8:
                raise ProtocolError("decode_failed", "JPEG frame header is too short")
            precision, height, width, components = struct.unpack_from(">BHHB", data, pos + 2)
            return width, height, components, precision
        pos += length
    raise ProtocolError(
        "decode_failed",
        f"JPEG has no frame header (SOF) within its first {JPEG_MAX_SEGMENTS} segments",
    )


def _check_declared(got_w: int, got_h: int, width: int, height: int, what: str, field: str):
    if (got_w, got_h) != (width, height):
        raise ProtocolError(
            "decode_failed",
            f"{what} declares {got_w} x {got_h}, the descriptor {width} x {height}",
            field,
        )


def _cv_decode(data: memoryview, flags: int, field: str) -> np.ndarray:
    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    except cv2.error as exc:
        raise ProtocolError("decode_failed", f"image decoder failed: {exc}", field) from None
    if img is None:
        raise ProtocolError("decode_failed", "image decoder rejected the payload", field)
    return img


def _check_shape(img: np.ndarray, shape: tuple[int, ...], dtype, field: str) -> np.ndarray:
    if img.shape != shape or img.dtype != dtype:
        raise ProtocolError(
            "decode_failed",
            f"decoded {img.shape} {img.dtype}, declared {shape} {np.dtype(dtype)}",
            field,
        )
    return img


def _raw_view(arr: np.ndarray) -> memoryview:
    return np.ascontiguousarray(arr).reshape(-1).view(np.uint8).data


def _check_array(arr, ndim: int, dtype, field: str, channels: int | None = None) -> np.ndarray:
    if not isinstance(arr, np.ndarray):
        raise ProtocolError("bad_field", f"expected a numpy array, got {type(arr).__name__}", field)
    if arr.dtype != dtype:
        raise ProtocolError(
            "bad_field", f"expected dtype {np.dtype(dtype)}, got {arr.dtype}", field
        )
    shape_ok = arr.ndim == ndim and (channels is None or arr.shape[2] == channels)
    if not shape_ok:
        want = "(H, W, 3)" if channels else "(H, W)"
        raise ProtocolError("bad_field", f"expected shape {want}, got {arr.shape}", field)
    h, w = arr.shape[:2]
    if not (1 <= h <= MAX_IMAGE_SIDE and 1 <= w <= MAX_IMAGE_SIDE):
        raise ProtocolError(
            "bad_field", f"{w} x {h} image; sides must be 1..{MAX_IMAGE_SIDE}", field
        )
    return arr


def _cv_encode(ext: str, img: np.ndarray, params: list[int], field: str) -> memoryview:
    ok, buf = cv2.imencode(ext, img, params)
    if not ok:  # pragma: no cover - OpenCV only fails on invalid input, checked above
        raise ProtocolError("bad_field", f"OpenCV could not encode {ext}", field)
    return buf.reshape(-1).data


# --------------------------------------------------------------------------- colour


def encode_color(
    rgb: np.ndarray, codec: str, quality: int = DEFAULT_JPEG_QUALITY, *, field: str = "color"
) -> tuple[bytes | memoryview, dict]:
    """Encode (H, W, 3) uint8 RGB; returns (payload, descriptor meta)."""
    _check_array(rgb, 3, np.uint8, field, channels=3)
    if codec not in COLOR_CODECS:
        raise ProtocolError(
            "bad_codec", f"colour codec {codec!r} is not one of {COLOR_CODECS}", field
        )
    h, w = rgb.shape[:2]
    meta = {"format": codec, "encoding": COLOR_ENCODING, "width": w, "height": h, "step": w * 3}
    if codec == "raw":
        return _raw_view(rgb), meta
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    if codec == "png":
        return _cv_encode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION], field), meta
    if type(quality) is not int or not 1 <= quality <= 100:
        raise ProtocolError(
            "bad_field", f"JPEG quality {quality!r} is not an integer 1..100", f"{field}.quality"
        )
    meta["quality"] = quality
    return _cv_encode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality], field), meta


def decode_color(
    payload, meta: dict, *, max_pixels: int = DEFAULT_MAX_PIXELS, field: str = "color"
) -> np.ndarray:
    """Decode to (H, W, 3) uint8 RGB, exactly the descriptor's size; raises ProtocolError."""
    fmt, width, height = check_image_meta(
        meta, COLOR_CODECS, COLOR_ENCODING, 3, 1, max_pixels, field
    )
    data = as_bytes_view(payload)
    shape = (height, width, 3)
    if fmt == "raw":
        return _raw_image(data, shape, np.uint8, field)
    if fmt == "png":
        _check_png(data, width, height, 8, 2, "colour PNG must be 8-bit RGB (colour type 2)", field)
    else:
        if "quality" in meta:
            _int_field(meta, "quality", field, 1, 100)
        w, h, components, precision = _with_field(jpeg_header, data, field)
        _check_declared(w, h, width, height, "JPEG SOF", field)
        if components != 3 or precision != 8:
            raise ProtocolError(
                "decode_failed",
                f"colour JPEG must have 3 components of 8 bits, got {components} of {precision}",
                field,
            )
    bgr = _check_shape(_cv_decode(data, _CV_COLOR, field), shape, np.uint8, field)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _with_field(fn, data, field):
    try:
        return fn(data)
    except ProtocolError as exc:
        raise ProtocolError(exc.code, exc.message, field) from None


def _raw_image(data: memoryview, shape: tuple[int, ...], dtype, field: str) -> np.ndarray:
    """A raw payload as an array of `shape` (a view of it, possibly read-only); its length
    must match."""
    expected = math.prod(shape) * np.dtype(dtype).itemsize
    if len(data) != expected:
        raise ProtocolError(
            "decode_failed", f"raw payload of {len(data)} bytes, expected {expected}", field
        )
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def _check_png(
    data, width: int, height: int, bit_depth: int, colour_type: int, rule: str, field: str
) -> None:
    """Check a PNG's IHDR before decoding: the descriptor's size, and `bit_depth` and
    `colour_type` (`rule` says which, for the error message)."""
    w, h, got_depth, got_type = _with_field(png_header, data, field)
    _check_declared(w, h, width, height, "PNG IHDR", field)
    if (got_depth, got_type) != (bit_depth, colour_type):
        raise ProtocolError(
            "decode_failed",
            f"{rule}, got bit depth {got_depth}, colour type {got_type}",
            field,
        )


# --------------------------------------------------------------------------- depth


def encode_depth(
    depth_u16: np.ndarray,
    codec: str,
    *,
    field: str = "depth",
    zstd_level: int = ZSTD_LEVEL,
    png_compression: int = PNG_COMPRESSION,
) -> tuple[bytes | memoryview, dict]:
    """Encode (H, W) uint16 depth losslessly; returns (payload, descriptor meta).

    ``zstd_level`` and ``png_compression`` trade encode time for size; the decoder does not
    need them.
    """
    _check_array(depth_u16, 2, np.uint16, field)
    if codec not in DEPTH_CODECS:
        raise ProtocolError(
            "bad_codec", f"depth codec {codec!r} is not one of {DEPTH_CODECS}", field
        )
    h, w = depth_u16.shape
    meta = {"format": codec, "encoding": DEPTH_ENCODING, "width": w, "height": h, "step": w * 2}
    if codec == "png":
        params = [cv2.IMWRITE_PNG_COMPRESSION, png_compression]
        return _cv_encode(".png", depth_u16, params, field), meta
    if codec == "rvl":
        from .rvl import rvl_encode  # numba loads on first use (0.4 s), not at import

        return rvl_encode(depth_u16), meta
    little = depth_u16.astype("<u2", copy=False)
    if codec == "raw":
        return _raw_view(little), meta
    raw = np.ascontiguousarray(little)
    return zstandard.ZstdCompressor(level=zstd_level).compress(raw.data), meta


def decode_depth(
    payload, meta: dict, *, max_pixels: int = DEFAULT_MAX_PIXELS, field: str = "depth"
) -> np.ndarray:
    """Decode to (H, W) uint16, bit-exact, exactly the descriptor's size; raises ProtocolError."""
    fmt, width, height = check_image_meta(
        meta, DEPTH_CODECS, DEPTH_ENCODING, 1, 2, max_pixels, field
    )
    data = as_bytes_view(payload)
    n = width * height
    shape = (height, width)
    if fmt == "raw":
        return _native_u16(_raw_image(data, shape, "<u2", field))
    if fmt == "zstd":
        try:
            size = zstandard.frame_content_size(data)
        except zstandard.ZstdError as exc:
            raise ProtocolError("decode_failed", f"not a zstd frame: {exc}", field) from None
        if size != 2 * n:
            what = "no content size" if size < 0 else f"content size {size} bytes"
            raise ProtocolError(
                "decode_failed",
                f"zstd frame declares {what}, the descriptor {width} x {height} x 2 = {2 * n}",
                field,
            )
        dobj = zstandard.ZstdDecompressor().decompressobj()
        try:
            # bounded: libzstd stops at the declared (checked) frame content size
            raw = dobj.decompress(data)
        except zstandard.ZstdError as exc:
            raise ProtocolError("decode_failed", f"zstd: {exc}", field) from None
        if not dobj.eof or dobj.unused_data or len(raw) != 2 * n:
            raise ProtocolError(
                "decode_failed",
                "zstd payload is truncated, has trailing bytes or does not decode to "
                "exactly one frame of the declared size",
                field,
            )
        return _native_u16(np.frombuffer(raw, dtype="<u2").reshape(shape))
    if fmt == "rvl":
        from .rvl import RVL_OK, RVL_STATUS_TEXT, rvl_decode

        flat, status = rvl_decode(data, n)
        if status != RVL_OK:
            raise ProtocolError("decode_failed", f"RVL: {RVL_STATUS_TEXT[status]}", field)
        return flat.reshape(shape)
    _check_png(
        data, width, height, 16, 0, "depth PNG must be 16-bit greyscale (colour type 0)", field
    )
    return _check_shape(_cv_decode(data, _CV_DEPTH16, field), shape, np.uint16, field)


def _native_u16(a: np.ndarray) -> np.ndarray:
    return a if a.dtype.isnative else a.astype(np.uint16)
