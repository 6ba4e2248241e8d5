"""RVL lossless depth codec (A. D. Wilson, "Fast Lossless Depth Image Compression", ISS 2017).

Byte layout (also written out in SPEC.md): the image is read in row-major order as unsigned
16-bit values and cut into alternating runs: a run of zeros, then a run of non-zeros, then
zeros again, and so on (the first zero run may be empty). Each pair is written as

    VLE(number of zeros), VLE(number of non-zeros), VLE(zigzag(delta)) for each non-zero

where ``delta = value - previous`` over the unsigned values (``previous`` is the last
non-zero value written, starting at 0), ``zigzag(d) = (d << 1) ^ (d >> 31)``, and VLE writes
a non-negative integer as 4-bit nibbles, least significant 3 data bits first, the nibble's
high bit set when more nibbles follow. Nibbles fill 32-bit words from the most significant
nibble down; each full word is stored little-endian; the last word is padded with zero
nibbles (a decoder rejects anything after the last pixel but zero padding). This is the
unsigned variant used by ROS ``compressed_depth_image_transport``.

The payload carries no size: width and height travel in the message's image descriptor, and
the decoder writes exactly ``width * height`` pixels, checking every read against the
payload length (hostile input cannot overrun a buffer or loop forever).
"""

from __future__ import annotations

import numpy as np
from numba import njit

# decoder status codes
RVL_OK = 0
RVL_TRUNCATED = 1  # ran out of words before all pixels were decoded
RVL_RUN_OVERFLOW = 2  # a run is longer than the pixels left
RVL_BAD_VALUE = 3  # a decoded non-zero value is 0 or outside 0..65535
RVL_TRAILING = 4  # words, or non-zero nibbles, left over after the last pixel
RVL_VLE_TOO_LONG = 5  # a variable-length integer of more than 11 nibbles (33 bits)

RVL_STATUS_TEXT = {
    RVL_TRUNCATED: "payload ends before all pixels are decoded",
    RVL_RUN_OVERFLOW: "a run is longer than the pixels left",
    RVL_BAD_VALUE: "a non-zero run decodes to 0 or to a value outside 0..65535",
    RVL_TRAILING: "data left over after the last pixel (padding nibbles must be 0)",
    RVL_VLE_TOO_LONG: "a variable-length integer is longer than 11 nibbles",
}

_MAX_VLE_NIBBLES = 11


def max_encoded_words(num_pixels: int) -> int:
    """Upper bound on the RVL size of ``num_pixels`` pixels, in 32-bit words."""
    # per run pair two counts of at most 11 nibbles, at most num_pixels + 1 pairs; at most
    # 6 nibbles per value (zigzag of a delta in -65535..65535 has 18 bits)
    nibbles = (num_pixels + 1) * 2 * _MAX_VLE_NIBBLES + num_pixels * 6
    return nibbles // 8 + 2


@njit(cache=True)
def _encode(depth: np.ndarray, out: np.ndarray) -> int:  # pragma: no cover - compiled
    n = depth.shape[0]
    word = np.uint32(0)
    nib_in_word = 0
    nwords = 0
    previous = 0
    i = 0
    while i < n:
        # zeros, then non-zeros
        zeros = 0
        while i + zeros < n and depth[i + zeros] == 0:
            zeros += 1
        i += zeros
        nonzeros = 0
        while i + nonzeros < n and depth[i + nonzeros] != 0:
            nonzeros += 1
        for k in range(nonzeros + 2):
            if k == 0:
                value = zeros
            elif k == 1:
                value = nonzeros
            else:
                current = np.int64(depth[i + k - 2])
                delta = current - previous
                previous = current
                value = (delta << 1) ^ (delta >> 63)
            # VLE
            while True:
                nibble = value & 7
                value >>= 3
                if value:
                    nibble |= 8
                word = np.uint32((word << np.uint32(4)) | np.uint32(nibble))
                nib_in_word += 1
                if nib_in_word == 8:
                    out[nwords] = word
                    nwords += 1
                    nib_in_word = 0
                    word = np.uint32(0)
                if value == 0:
                    break
        i += nonzeros
    if nib_in_word:
        out[nwords] = np.uint32(word << np.uint32(4 * (8 - nib_in_word)))
        nwords += 1
    return nwords


# The VLE read is written out twice in _decode (run lengths, zigzag deltas) on purpose: a
# shared @njit helper returning the nibble-stream state (inlined or not) decoded a 640 x 480
# frame about 40 % slower, a single read site with a phase switch about 12 % slower.
@njit(cache=True)
def _decode(words: np.ndarray, out: np.ndarray) -> int:  # pragma: no cover - compiled
    nw = words.shape[0]
    n = out.shape[0]
    pos = 0  # next word
    word = np.uint32(0)
    nib_left = 0
    written = 0
    previous = 0
    while written < n:
        for k in range(2):
            # VLE: run length
            value = 0
            shift = 0
            count = 0
            while True:
                if nib_left == 0:
                    if pos >= nw:
                        return RVL_TRUNCATED
                    word = words[pos]
                    pos += 1
                    nib_left = 8
                nibble = np.int64(word >> np.uint32(28))
                word = np.uint32(word << np.uint32(4))
                nib_left -= 1
                value |= (nibble & 7) << shift
                shift += 3
                count += 1
                if not (nibble & 8):
                    break
                if count >= _MAX_VLE_NIBBLES:
                    return RVL_VLE_TOO_LONG
            if value > n - written:
                return RVL_RUN_OVERFLOW
            if k == 0:
                for j in range(value):
                    out[written + j] = 0
                written += value
            else:
                for j in range(value):
                    # VLE: zigzag delta
                    v = 0
                    shift = 0
                    count = 0
                    while True:
                        if nib_left == 0:
                            if pos >= nw:
                                return RVL_TRUNCATED
                            word = words[pos]
                            pos += 1
                            nib_left = 8
                        nibble = np.int64(word >> np.uint32(28))
                        word = np.uint32(word << np.uint32(4))
                        nib_left -= 1
                        v |= (nibble & 7) << shift
                        shift += 3
                        count += 1
                        if not (nibble & 8):
                            break
                        if count >= _MAX_VLE_NIBBLES:
                            return RVL_VLE_TOO_LONG
                    delta = (v >> 1) ^ -(v & 1)
                    current = previous + delta
                    if current <= 0 or current > 65535:
                        return RVL_BAD_VALUE
                    out[written + j] = current
                    previous = current
                written += value
    if pos != nw or word != 0:  # whole words left, or non-zero nibbles after the last pixel
        return RVL_TRAILING
    return RVL_OK


def rvl_encode(depth: np.ndarray) -> bytes:
    """Encode a (H, W) or flat uint16 image; returns the RVL payload (a multiple of 4 bytes)."""
    flat = np.ascontiguousarray(depth, dtype=np.uint16).reshape(-1)
    out = np.empty(max_encoded_words(flat.size), dtype=np.uint32)
    nwords = _encode(flat, out)
    return out[:nwords].astype("<u4", copy=False).tobytes()


def rvl_decode(payload, num_pixels: int) -> tuple[np.ndarray, int]:
    """Decode ``num_pixels`` pixels; returns (flat uint16 array, status).

    ``status`` is ``RVL_OK`` or one of the error codes (see ``RVL_STATUS_TEXT``); on error the
    array content is undefined. A payload whose length is not a multiple of 4 returns
    ``RVL_TRUNCATED``. Allocates exactly ``num_pixels`` values, whatever the payload says.
    """
    mv = memoryview(payload).cast("B")
    out = np.empty(num_pixels, dtype=np.uint16)
    if len(mv) % 4:
        return out, RVL_TRUNCATED
    words = np.frombuffer(mv, dtype="<u4")
    if not words.dtype.isnative:
        words = words.astype(np.uint32)
    return out, int(_decode(words, out))
