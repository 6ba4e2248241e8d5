"""The volume V: TSDF fusion and ray casting (section 4 of seeds/000), Open3D tensor API.

The static scene is fused into a TSDF volume V (sparse Open3D ``VoxelBlockGrid`` on the
session's device) and V is ray-cast into the current view to give the geometry buffer
``G_v = (D_v, N_v)``; `surface_points` extracts V's zero crossings for the auxiliary buffers.

Frames and units: metres; camera axes are OpenCV (x right, y down, z forward); poses are
``world_from_cam`` (camera-to-world) 4x4 float64.

Open3D 0.20 behaviours this module corrects or avoids, each measured on exact synthetic
depth (tests/test_reconstruction.py); `OPEN3D_SUPPORTED` is checked at import:
- integration reads the depth pixel by truncating the projected coordinates (a half-pixel
  shift of the fused surface, hence of every tracked pose): integrate with cx, cy + 0.5;
- the ray caster samples the TSDF at the voxel corner below each step (surface off by up to a
  voxel): one Newton step on the trilinear TSDF (`ray_refine.refine_ray_cast`, Numba);
- block allocation looks at every 4th pixel only (last rows/columns lose their blocks): a
  second, shifted pass;
- the ray caster's range map overruns for image sizes that are not multiples of 8 (holes or
  a hang): cast a padded image;
- its fragment buffer drops a fragment whenever it grows (holes that vary from run to run):
  reserve it once per session;
- odometry sums with a TBB reduction (tracking.py): poses are reproducible only with Open3D
  on one thread, which an entry point may choose once (`arlight --open3d-threads 1`,
  `arlight.pipeline.runtime.configure_open3d_threads`); no module here changes that
  process-wide setting.
"""

from __future__ import annotations

import functools

import numba
import numpy as np
import open3d as o3d
import open3d.core as o3c

from arlight.core.camera import PinholeCamera
from arlight.pipeline.config import VolumeParams
from arlight.pipeline.ray_refine import refine_ray_cast

# The Open3D releases whose behaviours (listed above) this module was measured against and
# corrects; another release may have fixed one (the correction would then shift the surface)
OPEN3D_SUPPORTED = ((0, 20), (0, 21))  # [from, to)


def _check_open3d_version(version: str = o3d.__version__) -> None:
    major_minor = tuple(int(x) for x in version.split(".")[:2])
    low, high = OPEN3D_SUPPORTED
    if not low <= major_minor < high:
        raise ImportError(
            f"arlight.pipeline.volume supports open3d >={low[0]}.{low[1]},"
            f"<{high[0]}.{high[1]} (it corrects that release's ray casting and integration), "
            f"found {version}; install it with: pip install 'open3d>={low[0]}.{low[1]},"
            f"<{high[0]}.{high[1]}'"
        )


_check_open3d_version()

# Ray casting: voxels seen fewer times than this are not surface (ramped up over the first
# frames, as Open3D's slam.Model does, so the first frame already gives D_v).
WEIGHT_THRESHOLD = 3.0

# Open3D's ray-casting range map: one entry per 8 x 8 pixels (its default)
RANGE_MAP_DOWN_FACTOR = 8
# Open3D's VoxelBlockGrid.compute_unique_block_coordinates(depth) looks at every 4th pixel
BLOCK_TOUCH_STRIDE = 4


def unique_block_keys(keys: np.ndarray) -> np.ndarray:
    """The distinct rows of (N, 3) integer block coordinates, as (M, 3) int32 in the order
    of np.unique(keys, axis=0). Each row is packed into one int64 (21 bits a coordinate,
    blocks within +-2^20 of the origin: +-65 km at 6 cm blocks), so the sort is of one key
    (about 7x faster than np.unique's row-wise sort)."""
    k = np.asarray(keys, np.int64).reshape(-1, 3) + (1 << 20)
    packed = np.unique((k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2])
    mask = (1 << 21) - 1
    out = np.stack([packed >> 42, (packed >> 21) & mask, packed & mask], axis=1) - (1 << 20)
    return out.astype(np.int32)


# coarse samples within this fraction of each other count as one smooth surface
UPSAMPLE_SMOOTH_REL = 0.03


def upsample_depth(coarse: np.ndarray, factor: int, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 depth from a cast through the centres of factor x factor blocks.

    A pixel between four coarse samples that all exist and agree within
    UPSAMPLE_SMOOTH_REL of the nearest gets their bilinear interpolation (pixel centres
    aligned: full-resolution x sits at (x + 0.5) / factor - 0.5 on the coarse grid);
    elsewhere (an edge, a hole) the sample of its own block, so no depth is made up between
    two surfaces. 0 = none. One parallel pass for float32 depth (the same float32
    operations as `upsample_depth_numpy`, the oracle, which other dtypes take)."""
    if coarse.dtype != np.float32:
        return upsample_depth_numpy(coarse, factor, shape)
    h, w = shape
    if h > coarse.shape[0] * factor or w > coarse.shape[1] * factor:
        raise ValueError(f"{shape} is more than {factor} times the coarse {coarse.shape}")
    out = np.empty((h, w), np.float32)
    y0, y1, fy = _bilinear_taps(h, factor, coarse.shape[0])
    x0, x1, fx = _bilinear_taps(w, factor, coarse.shape[1])
    _upsample_depth_kernel(
        np.ascontiguousarray(coarse), factor, y0, y1, fy, x0, x1, fx,
        np.float32(UPSAMPLE_SMOOTH_REL), out,
    )  # fmt: skip
    return out


def _bilinear_taps(size: int, factor: int, coarse_size: int):
    """Per full-resolution index: the two coarse indices about it and the float32 weight of
    the second."""
    g = np.clip((np.arange(size) + 0.5) / factor - 0.5, 0, coarse_size - 1)
    first = np.floor(g).astype(np.int64)
    return first, np.minimum(first + 1, coarse_size - 1), (g - first).astype(np.float32)


@numba.njit(parallel=True, cache=True)
def _upsample_depth_kernel(coarse, factor, y0, y1, fy, x0, x1, fx, rel, out):
    one = np.float32(1.0)
    for y in numba.prange(out.shape[0]):
        a, b = y0[y], y1[y]
        wy = fy[y]
        for x in range(out.shape[1]):
            c, d = x0[x], x1[x]
            wx = fx[x]
            d00, d01, d10, d11 = coarse[a, c], coarse[a, d], coarse[b, c], coarse[b, d]
            lo = min(min(d00, d01), min(d10, d11))
            hi = max(max(d00, d01), max(d10, d11))
            if lo > 0 and hi - lo < rel * lo:
                out[y, x] = (one - wy) * ((one - wx) * d00 + wx * d01) + wy * (
                    (one - wx) * d10 + wx * d11
                )
            else:
                out[y, x] = coarse[y // factor, x // factor]


def upsample_depth_numpy(coarse: np.ndarray, factor: int, shape: tuple[int, int]) -> np.ndarray:
    """`upsample_depth` in NumPy (any dtype; its oracle in the tests)."""
    h, w = shape
    hc, wc = coarse.shape
    gy = np.clip((np.arange(h) + 0.5) / factor - 0.5, 0, hc - 1)
    gx = np.clip((np.arange(w) + 0.5) / factor - 0.5, 0, wc - 1)
    y0, x0 = np.floor(gy).astype(np.int64), np.floor(gx).astype(np.int64)
    y1, x1 = np.minimum(y0 + 1, hc - 1), np.minimum(x0 + 1, wc - 1)
    fy = (gy - y0).astype(np.float32)[:, None]
    fx = (gx - x0).astype(np.float32)[None, :]
    d00, d01 = coarse[y0][:, x0], coarse[y0][:, x1]
    d10, d11 = coarse[y1][:, x0], coarse[y1][:, x1]
    own = coarse[np.arange(h) // factor][:, np.arange(w) // factor]
    lo = np.minimum(np.minimum(d00, d01), np.minimum(d10, d11))
    hi = np.maximum(np.maximum(d00, d01), np.maximum(d10, d11))
    smooth = (lo > 0) & (hi - lo < UPSAMPLE_SMOOTH_REL * lo)
    bilinear = (1 - fy) * ((1 - fx) * d00 + fx * d01) + fy * ((1 - fx) * d10 + fx * d11)
    return np.where(smooth, bilinear, own).astype(np.float32)


def upsample_normals(coarse: np.ndarray, factor: int, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) normals from (h, w, 3) ones over factor x factor blocks: each block's own."""
    enlarged = np.repeat(np.repeat(coarse, factor, 0), factor, 1)
    return np.ascontiguousarray(enlarged[: shape[0], : shape[1]])


def _padded(size: int) -> int:
    """`size` rounded up to a multiple of RANGE_MAP_DOWN_FACTOR.

    Open3D's ray caster reads its range map (one entry per RANGE_MAP_DOWN_FACTOR^2 pixels)
    at pixel // factor but sizes it size // factor: the last rows or columns of an image
    whose size is not a multiple read past its end, and the cast then returns holes or never
    finishes (seen with 80x60 and 112x84 images). Casting a padded image and cropping it
    avoids that; the principal point stays where it is.
    """
    f = RANGE_MAP_DOWN_FACTOR
    return -(-size // f) * f


# the ray cast's fragment buffer is reserved for this many blocks in view whatever the hash
# map's initial capacity (block_count): it costs little (a session holding 10000 blocks
# with it reserved for 40000: 41 MB; the 40000-block hash map itself: 158 MB)
RANGE_MAP_BLOCKS = 40000


@functools.cache
def warm_open3d(device: str) -> None:
    """Once per process and device: fuse and ray cast a tiny throwaway volume.

    Open3D's first fusion and surface ray cast in a process pay a one-time cost (about
    0.3 s on two CPU cores, more than a frame's whole Surface stage) that a session's own
    first frame would otherwise pay; the volume's constructor calls this so that it is paid
    when the session is made, not in a frame."""
    cam = PinholeCamera.kinect_v1(64, 48)
    params = VolumeParams(volume_resolution=64, block_count=64)
    volume = TsdfVolume(params, cam, o3c.Device(device), warm=False)
    volume.integrate(np.full((cam.height, cam.width), 1.0, np.float32), np.eye(4))
    volume.ray_cast(np.eye(4))


class TsdfVolume:
    """The TSDF volume V of one session: fusion, ray casting, zero crossings.

    params: voxel size params.voxel_size_m, sparse blocks of params.block_resolution^3
        voxels with an initial hash-map capacity of params.block_count blocks, which grows
        when exceeded; TSDF truncation params.sdf_trunc_voxels voxels; depth range
        params.depth_min_m..depth_max_m. V is not clipped to a volume_size_m cube: that size
        only sets the voxel size, and V extends wherever depth within depth_max_m is seen.
    camera: intrinsics of the depth images; device: an Open3D device ("CPU:0", "CUDA:0").
    """

    def __init__(
        self, params: VolumeParams, camera: PinholeCamera, device: o3c.Device, warm: bool = True
    ):
        if warm:
            warm_open3d(str(device))
        self.params = params
        self.camera = camera
        self.device = device
        self.intrinsic = o3c.Tensor(camera.matrix, o3c.float64)  # stays on the host
        # Open3D's integration reads the depth pixel a voxel projects into by truncating its
        # projected coordinates, i.e. half a pixel to the upper left of the nearest one;
        # integrating with the principal point moved by +0.5 px makes that the nearest pixel
        # (without it the fused surface, and every tracked pose, is offset by ~z / (2 f)).
        k_integrate = camera.matrix.copy()
        k_integrate[:2, 2] += 0.5
        self._intrinsic_integrate = o3c.Tensor(k_integrate, o3c.float64)
        self.reset()

    def reset(self) -> None:
        """An empty volume."""
        c = self.params
        self._grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=["tsdf", "weight"],
            attr_dtypes=[o3c.float32, o3c.float32],
            attr_channels=[[1], [1]],
            voxel_size=c.voxel_size_m,
            block_resolution=c.block_resolution,
            block_count=c.block_count,
            device=self.device,
        )
        self._reserve_range_map()
        self.frames_integrated = 0

    def _reserve_range_map(self) -> None:
        """Grow Open3D's ray-casting fragment buffer once, up front, to RANGE_MAP_BLOCKS (or
        params.block_count if larger): blocks in view, not the hash map's capacity.

        VoxelBlockGrid.ray_cast keeps a buffer of range-map fragments (about one per block in
        view) and, when a cast needs more than it holds, drops one fragment of that cast (which
        one depends on thread timing: holes in D_v that differ from run to run) and enlarges
        the buffer for the next call. Casting once against block_count placeholder blocks in
        front of the camera (not inserted into V) sizes it so that this does not happen while
        fewer blocks are in view.
        """
        cam, c = self.camera, self.params
        block_m = c.voxel_size_m * c.block_resolution
        # one layer of blocks filling the view, far enough to hold that many of them (one
        # thin layer keeps the cast itself short: every ray stops after a block or two)
        view = (cam.width / cam.fx) * (cam.height / cam.fy)
        z = int(np.ceil(np.sqrt(max(c.block_count, RANGE_MAP_BLOCKS) / view))) + 2
        zc = (z + 0.5) * block_m
        xs = np.arange(
            np.floor(-cam.cx / cam.fx * zc / block_m),
            np.ceil((cam.width - 1 - cam.cx) / cam.fx * zc / block_m),
        )
        ys = np.arange(
            np.floor(-cam.cy / cam.fy * zc / block_m),
            np.ceil((cam.height - 1 - cam.cy) / cam.fy * zc / block_m),
        )
        gx, gy = np.meshgrid(xs, ys)
        keys = o3c.Tensor(
            np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1).astype(np.int32),
            o3c.int32,
            self.device,
        )
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            self._grid.ray_cast(
                keys,
                self.intrinsic,
                o3c.Tensor(np.eye(4)),
                _padded(cam.width),
                _padded(cam.height),
                ["depth"],
                1.0,
                c.depth_min_m,
                2.0 * zc + 1.0,
                1.0,
                c.sdf_trunc_voxels,
                RANGE_MAP_DOWN_FACTOR,
            )

    @property
    def voxel_grid(self) -> o3d.t.geometry.VoxelBlockGrid:
        """The TSDF volume V ("tsdf" and "weight" per voxel), e.g. to export a mesh."""
        return self._grid

    @property
    def num_blocks(self) -> int:
        """Voxel blocks allocated in V so far (memory: block_resolution^3 * 8 bytes each)."""
        return int(self._grid.hashmap().size())

    def sync(self) -> None:
        """Wait for the device (CUDA) so that wall-clock stage timings hold."""
        if self.device.get_type() == o3c.Device.DeviceType.CUDA:
            o3c.cuda.synchronize(self.device)

    def integrate(self, depth_m: np.ndarray, world_from_cam: np.ndarray) -> bool:
        """Fuse depth (H, W) float32 metres (0 = missing) into V at world_from_cam.

        False when no block lies in range (nothing fused)."""
        c, cam = self.params, self.camera
        extrinsic = o3c.Tensor(np.linalg.inv(world_from_cam))
        depth_image = o3d.t.geometry.Image(o3c.Tensor(depth_m, device=self.device))
        # Open3D allocates blocks around pixels (s i, s j), i < H // s, j < W // s (stride
        # s = BLOCK_TOUCH_STRIDE), so the last rows and columns can be left without blocks;
        # a second pass over the image cropped and zero-padded to put them on that grid
        # covers them.
        s = BLOCK_TOUCH_STRIDE
        sy, sx = (cam.height - 1) % s, (cam.width - 1) % s
        k_shifted = cam.matrix.copy()
        k_shifted[0, 2] -= sx
        k_shifted[1, 2] -= sy
        shifted = np.pad(depth_m[sy:, sx:], ((0, s), (0, s)))
        passes = [
            (depth_image, self.intrinsic),
            (o3d.t.geometry.Image(o3c.Tensor(shifted, device=self.device)), o3c.Tensor(k_shifted)),
        ]
        found = []
        for image, intrinsic in passes:
            try:
                found.append(
                    self._grid.compute_unique_block_coordinates(
                        image, intrinsic, extrinsic, 1.0, c.depth_max_m, c.sdf_trunc_voxels
                    )
                )
            except RuntimeError:  # Open3D aborts when no block is touched (nothing in range)
                pass
        if not found:
            return False
        blocks = found[0]
        if len(found) > 1:
            keys = unique_block_keys(np.concatenate([b.cpu().numpy() for b in found]))
            blocks = o3c.Tensor(keys, o3c.int32, self.device)
        self._grid.integrate(
            blocks,
            depth_image,
            self._intrinsic_integrate,
            extrinsic,
            1.0,
            c.depth_max_m,
            c.sdf_trunc_voxels,
        )
        self.frames_integrated += 1
        return True

    def weight_threshold(self) -> float:
        """Voxels seen fewer times than this are not surface (ramped over the first frames)."""
        return max(1.0, min(float(self.frames_integrated), WEIGHT_THRESHOLD))

    def _active_blocks(self) -> o3c.Tensor:
        hashmap = self._grid.hashmap()
        return hashmap.key_tensor()[hashmap.active_buf_indices().to(o3c.int64)]

    def ray_cast(
        self, world_from_cam: np.ndarray, subsample: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """D_v (H, W) float32 metres (0 = none) and N_v (H, W, 3) float32 (camera frame,
        unit, towards the free side) of V seen from world_from_cam; zeros while V is empty.

        subsample s > 1: cast through the pixel centres of the camera scaled by 1/s (s^2
        fewer rays) and interpolate (`upsample_depth`): bilinear on smooth surfaces, the
        block's own sample across depth edges (no depth is invented there); normals are the
        block's."""
        cam = self.camera
        h, w = cam.height, cam.width
        if self.num_blocks == 0:
            return np.zeros((h, w), np.float32), np.zeros((h, w, 3), np.float32)
        cam = cam.reduced(subsample)
        depth, normals = self._cast(cam, world_from_cam)
        if subsample > 1:
            depth = upsample_depth(depth, subsample, (h, w))
            normals = upsample_normals(normals, subsample, (h, w))
        return np.ascontiguousarray(depth), np.ascontiguousarray(normals)

    def _cast(
        self,
        cam: PinholeCamera,
        world_from_cam: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Open3D's ray cast of V through `cam`'s pixels, refined (`refine_ray_cast`)."""
        c = self.params
        h, w = cam.height, cam.width
        intrinsic = self.intrinsic if cam is self.camera else o3c.Tensor(cam.matrix, o3c.float64)
        hp, wp = _padded(h), _padded(w)
        # Open3D warns while it grows its range-map buffer; that is expected, not a problem
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            result = self._grid.ray_cast(
                self._active_blocks(),
                intrinsic,
                o3c.Tensor(np.linalg.inv(world_from_cam)),
                wp,
                hp,
                ["depth", "index", "mask", "interp_ratio"],
                1.0,
                c.depth_min_m,
                c.depth_max_m,
                self.weight_threshold(),
                c.sdf_trunc_voxels,
                RANGE_MAP_DOWN_FACTOR,
            )
        tsdf = self._grid.attribute("tsdf")
        if self.device.get_type() == o3c.Device.DeviceType.CPU:
            source, index = tsdf.numpy().reshape(-1), result["index"].numpy()[:h, :w]
        else:  # gather the 8 corner values on the device; only they travel to the host
            source = tsdf.reshape((-1,))[result["index"].reshape((-1,))].cpu().numpy()
            index = np.arange(hp * wp * 8, dtype=np.int64).reshape(hp, wp, 8)[:h, :w]
        return refine_ray_cast(
            result["depth"].cpu().numpy()[:h, :w, 0],
            source,
            index,
            result["mask"].cpu().numpy()[:h, :w],
            result["interp_ratio"].cpu().numpy()[:h, :w],
            world_from_cam,
            cam,
            c.voxel_size_m,
        )

    def triangle_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """V's zero level set as a triangle mesh (Open3D's marching cubes over the voxels
        seen as often as the ray caster requires, `weight_threshold`).

        Returns world vertices (M, 3) float32 metres and triangles (K, 3) int32, both on the
        host; empty arrays while V holds no surface. Cost: one pass over every allocated
        block (about 0.3 s for a room at 256^3 on two CPU cores).
        """
        empty = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
        if self.num_blocks == 0:
            return empty
        # Open3D keeps voxels of weight > threshold (strictly) and raises instead of
        # returning an empty mesh (0.20, without a colour attribute); weights count the
        # frames that saw a voxel, whole numbers, so threshold - 0.5 keeps weight >= threshold
        try:
            mesh = self._grid.extract_triangle_mesh(self.weight_threshold() - 0.5)
        except RuntimeError:
            return empty
        return (
            mesh.vertex.positions.cpu().numpy().astype(np.float32, copy=False),
            mesh.triangle.indices.cpu().numpy().astype(np.int32, copy=False),
        )

    def surface_points(self, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Zero crossings of the TSDF of V, on the voxel grid sub-sampled every `stride` voxels.

        Returns world points (M, 3) float32, metres, and TSDF gradients (M, 3) float32 at the
        lower sample of each crossing (unnormalised, pointing towards free space; zero
        components where a neighbour sample is unobserved). Crossings are searched along x, y
        and z between consecutive samples of weight >= the ray-casting weight threshold,
        across block borders, and placed by linear interpolation, as Open3D's
        VoxelBlockGrid.extract_point_cloud does at stride 1; a stride > 1 reads stride^3
        fewer voxels.
        """
        r = self.params.block_resolution
        if stride < 1 or r % stride:
            raise ValueError(f"stride must divide block_resolution={r}, got {stride}")
        hashmap = self._grid.hashmap()
        buf = hashmap.active_buf_indices().to(o3c.int64)
        if buf.shape[0] == 0:
            empty = np.zeros((0, 3), np.float32)
            return empty, empty
        keys = hashmap.key_tensor()[buf].cpu().numpy().astype(np.int64)  # (N, 3): x, y, z
        read = _BlockReader(self._grid, self.device, self.weight_threshold(), stride)
        tsdf, valid = read(buf)  # (N, m, m, m), array axes: block, z, y, x
        # values of the next sample along x, y, z (array axes 3, 2, 1), across block borders
        nxt, nxt_valid = [], []
        for k in range(3):
            t, v = _next_samples(hashmap, keys, tsdf, valid, read, k, self.device)
            nxt.append(t)
            nxt_valid.append(v)
        return _zero_crossings(
            keys, tsdf, valid, nxt, nxt_valid, stride, r, self.params.voxel_size_m
        )


class _BlockReader:
    """Sub-sampled tsdf and validity (weight >= threshold) of blocks of a VoxelBlockGrid."""

    def __init__(
        self, grid: o3d.t.geometry.VoxelBlockGrid, device: o3c.Device, threshold: float, stride: int
    ):
        self.tsdf = grid.attribute("tsdf")  # (capacity, r, r, r, 1): block, z, y, x
        self.weight = grid.attribute("weight")
        self.on_cpu = device.get_type() == o3c.Device.DeviceType.CPU
        if self.on_cpu:  # zero-copy views; NumPy gathers blocks far faster than Open3D
            self.tsdf_np, self.weight_np = self.tsdf.numpy(), self.weight.numpy()
        self.threshold = threshold
        self.sub = slice(None, None, stride)

    def __call__(
        self,
        index: o3c.Tensor,
        axis: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Blocks at buffer `index`; only their first layer along array `axis` if given."""
        key: list = [slice(None), self.sub, self.sub, self.sub, 0]
        if axis is not None:
            key[axis] = 0
        if self.on_cpu:
            # gather only the samples read (the whole blocks first cost 10x the time)
            key[0] = index.numpy()
            t, w = self.tsdf_np[tuple(key)], self.weight_np[tuple(key)]
        else:
            t = self.tsdf[index][tuple(key)].cpu().numpy()
            w = self.weight[index][tuple(key)].cpu().numpy()
        return t, w >= self.threshold


def _next_samples(
    hashmap,
    keys: np.ndarray,
    tsdf: np.ndarray,
    valid: np.ndarray,
    read: _BlockReader,
    k: int,
    device: o3c.Device,
) -> tuple[np.ndarray, np.ndarray]:
    """tsdf and validity of the next sample along x, y or z (k = 0, 1, 2) of every sample,
    the last layer of a block taken from its neighbour block (missing: invalid)."""
    axis = 3 - k
    n, m = tsdf.shape[0], tsdf.shape[1]
    shifted = keys.copy()
    shifted[:, k] += 1
    nb_buf, found = hashmap.find(o3c.Tensor(shifted.astype(np.int32), o3c.int32, device))
    found_np = found.cpu().numpy()
    layer = np.zeros((n, m, m), np.float32)
    layer_valid = np.zeros((n, m, m), bool)
    if found_np.any():
        t, v = read(nb_buf.to(o3c.int64)[found], axis)
        layer[found_np], layer_valid[found_np] = t, v
    rest = [slice(None)] * 4
    rest[axis] = slice(1, None)
    return (
        np.concatenate([tsdf[tuple(rest)], np.expand_dims(layer, axis)], axis),
        np.concatenate([valid[tuple(rest)], np.expand_dims(layer_valid, axis)], axis),
    )


def _zero_crossings(
    keys: np.ndarray,
    tsdf: np.ndarray,
    valid: np.ndarray,
    nxt: list,
    nxt_valid: list,
    stride: int,
    r: int,
    voxel_size_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """World points and forward-difference gradients of the sign changes between samples."""
    m = tsdf.shape[1]
    # sample index (z, y, x) in a block -> voxel offset (x, y, z) of the sample
    iz, iy, ix = np.meshgrid(*(np.arange(m) * stride,) * 3, indexing="ij")
    points, gradients = [], []
    for k in range(3):
        b, z, y, x = np.nonzero(valid & nxt_valid[k] & (tsdf * nxt[k] < 0))
        a = tsdf[b, z, y, x]
        ratio = a / (a - nxt[k][b, z, y, x])
        voxel = (keys[b] * r + np.stack([ix[z, y, x], iy[z, y, x], iz[z, y, x]], -1)).astype(
            np.float64
        )
        voxel[:, k] += stride * ratio
        points.append(voxel * voxel_size_m)
        # forward differences at the lower sample (0 where a neighbour is unobserved)
        gradients.append(
            np.stack(
                [np.where(nxt_valid[j][b, z, y, x], nxt[j][b, z, y, x] - a, 0.0) for j in range(3)],
                -1,
            )
        )
    return (np.concatenate(points).astype(np.float32), np.concatenate(gradients).astype(np.float32))
