"""Depth encodings of recorded depth images, decoded into the sensor's integers.

A stored depth image is uint16; what a value means depends on the data set (`DEPTH_ENCODINGS`).
Decoding gives (H, W) uint16 units, 0 = missing, and their units per metre: the metres are
``arlight.core.checks.depth_metres(units, units_per_metre)``, computed once where the pipeline
takes the frame.

- "tum", "mm": linear integers, kept as stored (65535, the sensors' "invalid", becomes 0);
- "sun": millimetres bit-rotated by 3: rotated back into the millimetre integers;
- "nyu": raw Kinect disparity, not linear in depth: converted to metres with NYU's formula
  and quantised to uint16 at `NYU_DEPTH_SCALE` (5000 units per metre, 0.2 mm steps).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from arlight.core.checks import check_image
from arlight.sources.errors import DatasetError, dataset_errors
from arlight.sources.images import read_image

#: Depth encodings: name -> what a stored uint16 value means.
DEPTH_ENCODINGS: dict[str, str] = {
    "tum": "uint16, metres * 5000 (TUM RGB-D); 0 and 65535 = missing",
    "mm": "uint16 millimetres (Open3D/Redwood, 7-Scenes, most sensors); 0 and 65535 = missing",
    "sun": "uint16 millimetres bit-rotated by 3 (SUN RGB-D): mm = ((v >> 3) | (v << 13)) & 0xFFFF",
    "nyu": "raw Kinect disparity (NYU Depth v2 PGM, stored little-endian): "
    "metres = 351.3 / (1092.5 - raw); raw 2047 = missing; read as metres * 5000",
}
#: Units per metre of the decoded integers, per encoding ("tum"/"mm" may be overridden).
UNITS_PER_METRE = {"tum": 5000.0, "mm": 1000.0, "sun": 1000.0}

INVALID_U16 = 0xFFFF  # the data sets' "invalid" marker
MAX_UNITS = 0xFFFE  # the largest depth a quantised uint16 holds (65535 would read as invalid)

#: Units per metre of NYU depth once quantised (0.2 mm steps; 13.1 m at most).
NYU_DEPTH_SCALE = 5000.0
#: Depth beyond this many metres from NYU raw disparity is treated as missing (Kinect v1 range;
#: the NYU toolbox clamps to 10 m, which would invent depth).
NYU_MAX_DEPTH_M = 10.0


def check_encoding(encoding: str) -> None:
    """DatasetError unless `encoding` is one of DEPTH_ENCODINGS."""
    if encoding not in DEPTH_ENCODINGS:
        raise DatasetError(
            f"unknown depth encoding {encoding!r}; --depth-encoding takes one of: "
            f"{', '.join(DEPTH_ENCODINGS)}"
        )


def read_depth(
    path: str | Path, encoding: str, units_per_metre: float | None = None
) -> tuple[np.ndarray, float]:
    """(units (H, W) uint16, 0 = missing; units per metre) from a depth image in `encoding`.

    units_per_metre overrides the encoding's scale for "tum"/"mm" (e.g. camera.json).
    """
    path = Path(path)
    raw = read_image(path, cv2.IMREAD_UNCHANGED, "depth image")
    with dataset_errors(
        f"this is not a depth map in encoding {encoding!r} (a single-channel uint16 image)"
    ):
        check_image(raw, str(path), dtype=np.uint16)
    return decode_depth(raw, encoding, units_per_metre, source=str(path))


def decode_depth(
    raw: np.ndarray, encoding: str, units_per_metre: float | None = None, source: str = "depth"
) -> tuple[np.ndarray, float]:
    """(units (H, W) uint16, 0 = missing; units per metre) from stored uint16 depth `raw`.

    See DEPTH_ENCODINGS; units_per_metre overrides the scale of "tum"/"mm"/"sun".
    """
    check_encoding(encoding)
    if encoding == "nyu":
        return _decode_nyu(raw, source), NYU_DEPTH_SCALE
    values = np.array(raw, dtype=np.uint16)  # a copy: the stored integers, never rescaled
    if encoding == "sun":
        v = values.astype(np.uint32)
        values = (((v >> 3) | (v << 13)) & 0xFFFF).astype(np.uint16)
    values[values == INVALID_U16] = 0  # saturated / invalid marker
    scale = units_per_metre if units_per_metre is not None else UNITS_PER_METRE[encoding]
    return values, float(scale)


def metres_to_units(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """(H, W) float metres -> uint16 at depth_scale units per metre (rounded to nearest).

    For depth that is not stored as linear integers (disparity, reprojected depth). Missing,
    NaN, negative or beyond MAX_UNITS / depth_scale metres -> 0.
    """
    d = np.asarray(depth_m, dtype=np.float64) * depth_scale
    d = np.where(np.isfinite(d), np.rint(d), 0.0)
    d[(d < 0) | (d > MAX_UNITS)] = 0.0
    return d.astype(np.uint16)


def _decode_nyu(raw: np.ndarray, source: str) -> np.ndarray:
    # NYU's PGMs are little-endian although PGM is big-endian, so a PGM reader returns the
    # bytes swapped. Raw Kinect disparity has 11 bits: pick the byte order that fits.
    swapped = raw.byteswap()
    if int(swapped.max(initial=0)) <= 2047:
        disparity = swapped
    elif int(raw.max(initial=0)) <= 2047:
        disparity = raw  # already converted to the right byte order
    else:
        raise DatasetError(
            f"{source}: values exceed 2047 in either byte order, so this is not raw Kinect "
            "disparity (NYU Depth v2 raw PGM); pick another --depth-encoding"
        )
    d = disparity.astype(np.float64)
    with np.errstate(divide="ignore"):
        depth_m = 351.3 / (1092.5 - d)
    bad = (disparity == 2047) | ~np.isfinite(depth_m) | (depth_m <= 0) | (depth_m > NYU_MAX_DEPTH_M)
    depth_m[bad] = 0.0
    return metres_to_units(depth_m, NYU_DEPTH_SCALE)
