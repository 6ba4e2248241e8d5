"""Image descriptors (SPEC.md section 5): each image of a message is described in the header
(``format``, ``encoding``, ``width``, ``height``, ``step``, ``buffer``) and travels as its own
part. `ImageParts` checks a message's descriptors against its parts before anything is
decoded; the pixel codecs themselves are in codecs.py."""

from __future__ import annotations

from .codecs import (
    COLOR_CODECS,
    COLOR_ENCODING,
    DEPTH_CODECS,
    DEPTH_ENCODING,
    check_image_meta,
    decode_color,
    decode_depth,
)
from .errors import ProtocolError
from .fields import MAX_PARTS, FieldReader, type_name

_COLOR_KEYS = frozenset(("format", "encoding", "width", "height", "step", "buffer", "quality"))
_DEPTH_KEYS = frozenset(("format", "encoding", "width", "height", "step", "buffer"))


class ImageParts:
    """Descriptors of a message's images, checked against the parts before decoding."""

    def __init__(self, parts: list[memoryview] | None, max_pixels: int, decode: bool = True):
        self.parts = parts  # None: validate descriptors only
        self.used: set[int] = set()
        self.max_pixels = max_pixels
        self.decoding = decode  # False (encode side): check the parts, decode no image

    def part(self, m: FieldReader, key: str) -> memoryview | None:
        """The part whose index the field `key` holds (a plain buffer index, not an image
        descriptor); each part is used by one field only. None when there are no parts."""
        index = m.raw(key)
        nbuf = MAX_PARTS - 1 if self.parts is None else len(self.parts)
        if type(index) is not int or not 0 <= index < nbuf:
            raise ProtocolError(
                "bad_field", f"buffer index {index!r} is not 0..{nbuf - 1}", m.f(key)
            )
        if index in self.used:
            raise ProtocolError("bad_field", f"buffer {index} is used twice", m.f(key))
        self.used.add(index)
        return None if self.parts is None else self.parts[index]

    def descriptor(self, m: FieldReader, key: str, depth: bool, nullable: bool = False):
        desc = m.raw(key, nullable)
        if desc is None:
            return None
        name = m.f(key)
        if not isinstance(desc, dict):
            raise ProtocolError(
                "bad_field", f"expected an image descriptor, got {type_name(desc)}", name
            )
        allowed = _DEPTH_KEYS if depth else _COLOR_KEYS
        for k in desc:
            if k not in allowed:
                raise ProtocolError(
                    "bad_field", f"unknown field {str(k)[:64]!r}", f"{name}.{str(k)[:64]}"
                )
        if depth:
            fmt, w, h = check_image_meta(
                desc, DEPTH_CODECS, DEPTH_ENCODING, 1, 2, self.max_pixels, name
            )
        else:
            fmt, w, h = check_image_meta(
                desc, COLOR_CODECS, COLOR_ENCODING, 3, 1, self.max_pixels, name
            )
            if "quality" in desc and fmt != "jpeg":
                raise ProtocolError(
                    "bad_field", "quality is only for format jpeg", f"{name}.quality"
                )
        nbuf = MAX_PARTS - 1 if self.parts is None else len(self.parts)
        index = desc.get("buffer")
        if type(index) is not int or not 0 <= index < nbuf:
            raise ProtocolError(
                "bad_field", f"buffer index {index!r} is not 0..{nbuf - 1}", f"{name}.buffer"
            )
        if index in self.used:
            raise ProtocolError("bad_field", f"buffer {index} is used twice", f"{name}.buffer")
        self.used.add(index)
        return (desc, fmt, w, h, depth, name)

    def decode(self, d):
        if d is None or self.parts is None or not self.decoding:
            return None
        desc, _, _, _, depth, name = d
        payload = self.parts[desc["buffer"]]
        if depth:
            return decode_depth(payload, desc, max_pixels=self.max_pixels, field=name)
        return decode_color(payload, desc, max_pixels=self.max_pixels, field=name)

    def done(self, header_name: str) -> None:
        n = 0 if self.parts is None else len(self.parts)
        if self.parts is not None and len(self.used) != n:
            raise ProtocolError(
                "malformed",
                f"{n - len(self.used)} buffer(s) not used by any field",
                f"{header_name}.buffers",
            )


def add_image(parts: list, payload, meta: dict) -> dict:
    meta = dict(meta)
    meta["buffer"] = len(parts)
    parts.append(payload)
    return meta
