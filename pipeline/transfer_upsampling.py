"""From the transfer's (sub-sampled) grid to pixels: up-sampling to the full image
("OursFast") and the interpolated samples the light estimate draws."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from arlight.pipeline.transfer_types import TransferResult

REMAP_MAX_CHANNELS = 128  # cv2 (5.0) reads an (H, W, C > 128) array as a 2-D image


def _remap_channels(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bilinear cv2.remap of an (h, w, C) image for any C >= 1, as (H, W, C) float32: cv2
    drops a single channel's axis (sh_bands 1) and mistakes more than 128 channels for a
    2-D image (sh_bands 12), so those go in chunks; C <= 128 is one call, as before."""
    c = image.shape[2]
    chunks = []
    for start in range(0, c, REMAP_MAX_CHANNELS):
        part = np.ascontiguousarray(image[..., start : start + REMAP_MAX_CHANNELS])
        out = cv2.remap(part, map_x, map_y, cv2.INTER_LINEAR)
        chunks.append(out.reshape(*map_x.shape, part.shape[2]))
    return chunks[0] if len(chunks) == 1 else np.concatenate(chunks, axis=2)


def upsample_transfer(result: TransferResult, valid_full: np.ndarray) -> TransferResult:
    """Sub-sampled transfer -> every pixel of the image ("OursFast": up-sampling in image
    space), by normalised bilinear interpolation between the valid grid points.

    valid_full: (H, W) bool, pixels with geometry (depth and normal). A pixel is kept when
    all grid points around it are valid, so no transfer is borrowed across a hole or a
    depth edge the grid saw. Identity when the grid is already full resolution.
    """
    h, w = valid_full.shape
    hs, ws = result.valid.shape
    if hs == h and ws == w:
        return result
    # fractional grid index of every pixel (exact also for the clamped last row/column)
    map_u = np.interp(np.arange(w), result.pixel_u, np.arange(ws)).astype(np.float32)
    map_v = np.interp(np.arange(h), result.pixel_v, np.arange(hs)).astype(np.float32)
    map_x = np.ascontiguousarray(np.broadcast_to(map_u[None, :], (h, w)))
    map_y = np.ascontiguousarray(np.broadcast_to(map_v[:, None], (h, w)))
    weight = result.valid.astype(np.float32)
    transfer = _remap_channels(
        np.asarray(result.transfer * weight[..., None], np.float32), map_x, map_y
    )
    den = cv2.remap(weight, map_x, map_y, cv2.INTER_LINEAR)
    keep = valid_full & (den > 0.999)
    # normalised, and zero where not kept, in place (float32 throughout)
    inv = np.where(keep, 1.0 / np.maximum(den, 1e-6), 0.0).astype(np.float32)
    transfer *= inv[..., None]
    bounce = None
    if result.bounce is not None:
        remapped: np.ndarray = cv2.remap(
            np.asarray(result.bounce * weight, np.float32), map_x, map_y, cv2.INTER_LINEAR
        )
        remapped *= inv
        bounce = remapped
    return TransferResult(transfer, keep, np.arange(w), np.arange(h), bounce)


@dataclass
class TransferSamples:
    """The transfer at a list of pixels: pixel_v, pixel_u (K,) int64 full-resolution
    coordinates; transfer (K, C) float32; bounce (K,) float32 or None; clipped_fraction:
    the share of the pixels with geometry that are clipped, when the pixels were chosen
    among unclipped ones only (None: they were not)."""

    pixel_v: np.ndarray
    pixel_u: np.ndarray
    transfer: np.ndarray
    bounce: np.ndarray | None
    clipped_fraction: float | None = None


def random_pixels(mask: np.ndarray, max_pixels: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) int64 of the True pixels of `mask`, row-major; above `max_pixels` a
    seeded uniform random subset of that many (still row-major)."""
    flat = np.flatnonzero(mask)
    if len(flat) > max_pixels:
        flat = np.sort(np.random.default_rng(seed).choice(flat, max_pixels, replace=False))
    rows, cols = np.divmod(flat, mask.shape[1])
    return rows.astype(np.int64), cols.astype(np.int64)


def transfer_samples(
    result: TransferResult, valid_full: np.ndarray | None, max_pixels: int, seed: int
) -> TransferSamples:
    """`interpolated_samples` without edge refinement: the samples only."""
    return interpolated_samples(result, valid_full, max_pixels, seed)[0]


def interpolated_samples(
    result: TransferResult,
    valid_full: np.ndarray | None,
    max_pixels: int,
    seed: int,
    edge_spread: float = 0.0,
) -> tuple[TransferSamples, tuple[np.ndarray, np.ndarray]]:
    """The pixels the light estimate may use, at most `max_pixels` of them (a seeded random
    subset above that; neighbouring pixels repeat each other), with their transfer.

    valid_full: (H, W) bool pixels with geometry, for a sub-sampled grid to be interpolated
    at every such pixel ("OursFast"): the same normalised bilinear interpolation as
    `upsample_transfer`, evaluated at the chosen pixels only (a pixel is kept when every
    grid point around it is valid). None: the grid points themselves.

    edge_spread > 0 (TransferParams.rt_refine_spread): the chosen pixels whose grid points'
    transfers differ by more than edge_spread (the largest distance of a corner's vector
    from their mean, relative to the mean's length: a shadow or crease edge) are returned
    apart, as (rows, cols), for their own transfer. (Pixels beside an invalid grid point
    stay dropped: giving them their own transfer, on dev_d, raised the error by a degree;
    they lie on depth edges, where depth and normals are least reliable.) 0: none.
    """
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    hs, ws = result.valid.shape
    interpolate = valid_full is not None and (hs, ws) != valid_full.shape
    mask = valid_full if interpolate and valid_full is not None else result.valid
    rows, cols = random_pixels(mask, max_pixels, seed)
    bounce = result.bounce
    if not interpolate:
        pv = np.asarray(result.pixel_v)[rows]
        pu = np.asarray(result.pixel_u)[cols]
        return TransferSamples(
            pv.astype(np.int64),
            pu.astype(np.int64),
            result.transfer[rows, cols],
            None if bounce is None else bounce[rows, cols],
        ), none
    gu = np.interp(cols, result.pixel_u, np.arange(ws))  # fractional grid coordinates
    gv = np.interp(rows, result.pixel_v, np.arange(hs))
    u0 = np.minimum(np.floor(gu).astype(np.int64), ws - 1)
    v0 = np.minimum(np.floor(gv).astype(np.int64), hs - 1)
    u1, v1 = np.minimum(u0 + 1, ws - 1), np.minimum(v0 + 1, hs - 1)
    fu, fv = (gu - u0).astype(np.float32), (gv - v0).astype(np.float32)
    corners = [
        (v0, u0, (1 - fv) * (1 - fu)),
        (v0, u1, (1 - fv) * fu),
        (v1, u0, fv * (1 - fu)),
        (v1, u1, fv * fu),
    ]
    den = np.zeros(len(rows), np.float32)
    num = np.zeros((len(rows), result.transfer.shape[-1]), np.float32)
    num_b = None if bounce is None else np.zeros(len(rows), np.float32)
    flat_t = result.transfer.reshape(hs * ws, -1)
    flat_valid = result.valid.reshape(-1)
    flat_b = None if bounce is None else bounce.reshape(-1)
    for v, u, wgt in corners:
        at = v * ws + u  # np.take on the flattened grid: cheaper than 2-D fancy indexing
        wv = wgt * np.take(flat_valid, at)
        den += wv
        num += wv[:, None] * np.take(flat_t, at, axis=0)
        if num_b is not None and flat_b is not None:
            num_b += wv * np.take(flat_b, at)
    keep = den > 0.999
    edges = none
    if edge_spread > 0.0:
        mean = num / np.maximum(den, 1e-6)[:, None]
        spread = np.zeros(len(rows), np.float32)
        for v, u, wgt in corners:  # the corners the pixel's interpolation reads
            at = v * ws + u
            gap = np.linalg.norm(np.take(flat_t, at, axis=0) - mean, axis=1)
            spread = np.maximum(spread, np.where(np.take(flat_valid, at) & (wgt > 0), gap, 0.0))
        sharp = keep & (spread > edge_spread * np.linalg.norm(mean, axis=1))
        edges = (rows[sharp].astype(np.int64), cols[sharp].astype(np.int64))
        keep &= ~sharp
    inv = 1.0 / den[keep]
    return TransferSamples(
        rows[keep].astype(np.int64),
        cols[keep].astype(np.int64),
        num[keep] * inv[:, None],
        None if num_b is None else num_b[keep] * inv,
    ), edges
