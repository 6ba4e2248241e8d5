"""Equirectangular 360-degree panoramas: videos, image sequences, single images, HDR files.

`open_panorama(path)` gives a `PanoramaSource`, an iterable of ``(timestamp_s, image)``:

- a video file (``VIDEO_EXTS``), decoded by OpenCV's FFmpeg backend (``cv2.VideoCapture``)
  on its own thread into a small bounded queue (``queue_frames``, default 4), so decoding
  overlaps the processing of the previous frames (the paper's decode thread) and never
  drops one: when the queue is full the decoder waits. Timestamps: the container's
  (``CAP_PROP_POS_MSEC`` of the frame just read), or frame index / ``fps`` when ``fps`` is
  given (or the container has none);
- a folder of images (PNG/JPEG; or .hdr/.exr), sorted by name with numbers compared as
  numbers (``frame2`` before ``frame10``); timestamps index / ``fps`` (default 30);
- one image (timestamp 0).

LDR images leave as (H, W, 3) uint8 RGB, sRGB-encoded as stored (``source.hdr`` False);
Radiance ``.hdr`` (``cv2.imread`` with IMREAD_ANYDEPTH) and OpenEXR ``.exr`` files as
(H, W, 3) float32 linear RGB (``source.hdr`` True), for running the path on HDR truth.
Every frame must be equirectangular, twice as wide as high; one that is not raises a
`PanoramaError` naming the file and its size.
"""

from __future__ import annotations

import math
import queue
import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from arlight.core.checks import CheckError
from arlight.pipeline.equirect import check_equirect
from arlight.sources.errors import DatasetError

VIDEO_EXTS = (".mp4", ".m4v", ".mov", ".mkv", ".avi", ".webm", ".mpg", ".mpeg", ".ts")
LDR_EXTS = (".png", ".jpg", ".jpeg")
HDR_EXTS = (".hdr", ".exr")
DEFAULT_SEQUENCE_FPS = 30.0
DEFAULT_QUEUE_FRAMES = 4


class PanoramaError(DatasetError):
    """A panorama that cannot be read; the message names the file and what is wrong."""


def _checked(image: np.ndarray, path: Path) -> np.ndarray:
    try:
        return check_equirect(image, str(path))
    except CheckError as exc:
        raise PanoramaError(str(exc)) from None


def read_panorama_image(path: str | Path) -> np.ndarray:
    """One panorama file: (H, W, 3) uint8 RGB (PNG/JPEG) or float32 linear RGB (.hdr/.exr)."""
    p = Path(path)
    if not p.is_file():
        raise PanoramaError(f"{p}: file does not exist")
    ext = p.suffix.lower()
    if ext == ".exr":
        from arlight.sources.exr import read_exr

        try:
            rgb = read_exr(p)
        except DatasetError as exc:
            raise PanoramaError(str(exc)) from None
        return _checked(rgb, p)
    flags = cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR if ext == ".hdr" else cv2.IMREAD_COLOR
    data = np.fromfile(p, dtype=np.uint8)
    bgr = cv2.imdecode(data, flags) if data.size else None
    if bgr is None:
        raise PanoramaError(
            f"{p}: OpenCV cannot decode this image (empty, truncated or not "
            f"an image); panoramas are PNG/JPEG, Radiance .hdr or OpenEXR"
        )
    if ext == ".hdr":
        bgr = bgr.astype(np.float32, copy=False)
    elif bgr.dtype != np.uint8:
        raise PanoramaError(f"{p}: expected an 8-bit image, got {bgr.dtype}")
    return _checked(np.ascontiguousarray(bgr[..., ::-1]), p)


def _natural_key(path: Path) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


class PanoramaSource:
    """Iterable of (timestamp_s, image) over one panorama input; close it (or use `with`).

    Attributes: ``path``; ``kind`` ("video", "sequence", "image"); ``hdr`` (images are
    float32 linear RGB, else uint8 sRGB); ``size`` (width, height) of the first frame;
    ``num_frames`` (a video's is its container's count, which may be approximate; None
    when the container has none); ``fps``. A video also reports ``decode_ms`` (per frame,
    on the decode thread: read + colour conversion) and ``wait_ms`` (per frame, how long
    the consumer waited for it: what decoding still costs the processing path).
    """

    def __init__(
        self,
        path: Path,
        kind: str,
        hdr: bool,
        size: tuple[int, int],
        num_frames: int | None,
        fps: float | None,
    ):
        self.path = path
        self.kind = kind
        self.hdr = hdr
        self.size = size
        self.num_frames = num_frames
        self.fps = fps
        self.decode_ms: list[float] = []
        self.wait_ms: list[float] = []

    def __iter__(self) -> Iterator[tuple[float, np.ndarray]]:  # pragma: no cover - abstract
        raise NotImplementedError

    def close(self) -> None:
        """Stop decoding and release the file (idempotent)."""

    def __enter__(self) -> PanoramaSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _ImageSource(PanoramaSource):
    """A single image or a sorted folder of images, read lazily."""

    fps: float  # given (or the default): an image has no rate of its own

    def __init__(
        self, path: Path, files: list[Path], kind: str, fps: float, max_frames: int | None
    ):
        first = read_panorama_image(files[0])
        hdr = first.dtype != np.uint8
        super().__init__(
            path,
            kind,
            hdr,
            (first.shape[1], first.shape[0]),
            min(len(files), max_frames or len(files)),
            fps,
        )
        self._files = files[: self.num_frames]
        self._first = first

    def __iter__(self) -> Iterator[tuple[float, np.ndarray]]:
        for i, f in enumerate(self._files):
            image = self._first if i == 0 else read_panorama_image(f)
            if (image.dtype != np.uint8) != self.hdr:
                raise PanoramaError(
                    f"{f}: an image sequence is all LDR (PNG/JPEG) or all "
                    f"HDR (.hdr/.exr); {self._files[0].name} is "
                    f"{'HDR' if self.hdr else 'LDR'}"
                )
            yield i / self.fps, image


_END = object()


class _Failure:
    def __init__(self, error: Exception):
        self.error = error


class _VideoSource(PanoramaSource):
    """A video decoded on its own thread into a bounded queue, in order, none dropped."""

    def __init__(self, path: Path, fps: float | None, max_frames: int | None, queue_frames: int):
        capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
        if not capture.isOpened():
            raise PanoramaError(
                f"{path}: OpenCV's FFmpeg backend cannot open this video "
                f"(unknown container or codec, or not a video)"
            )
        t0 = time.perf_counter()
        ok, bgr = capture.read()
        self._read_ms = (time.perf_counter() - t0) * 1e3  # the frame's decode, done here
        if not ok or bgr is None:
            capture.release()
            raise PanoramaError(f"{path}: the video has no frame that OpenCV can decode")
        try:
            _checked(bgr, path)
        except PanoramaError:
            capture.release()
            raise
        container_fps = capture.get(cv2.CAP_PROP_FPS)
        frames = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        count = frames if frames > 0 else None
        if max_frames is not None:
            count = min(count, max_frames) if count is not None else max_frames
        super().__init__(
            path,
            "video",
            False,
            (bgr.shape[1], bgr.shape[0]),
            count,
            fps or (container_fps if container_fps > 0 else None),
        )
        self._fps_given = fps
        self._max_frames = max_frames
        self._capture = capture
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, queue_frames))
        self._stop = threading.Event()
        self._first_ms = capture.get(cv2.CAP_PROP_POS_MSEC)
        self._thread = threading.Thread(
            target=self._decode, args=(bgr,), name=f"decode {path.name}", daemon=True
        )
        self._started = False
        self._closed = False

    def _timestamp(self, index: int, pos_ms: float) -> float:
        if self._fps_given:
            return index / self._fps_given
        if index == 0 or pos_ms > 0:
            return max(0.0, pos_ms) / 1e3
        return index / (self.fps or DEFAULT_SEQUENCE_FPS)  # a container without times

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def _decode(self, first_bgr: np.ndarray) -> None:
        try:
            index, pos_ms = 0, self._first_ms
            bgr: np.ndarray | None = first_bgr
            while bgr is not None:
                t0 = time.perf_counter()
                if bgr.shape[:2] != (self.size[1], self.size[0]):
                    raise PanoramaError(
                        f"{self.path}: frame {index} is {bgr.shape[1]}x"
                        f"{bgr.shape[0]}, the first was {self.size[0]}x"
                        f"{self.size[1]}"
                    )
                rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                self.decode_ms.append((time.perf_counter() - t0) * 1e3 + self._read_ms)
                if not self._put((self._timestamp(index, pos_ms), rgb)):
                    return
                index += 1
                if self._max_frames is not None and index >= self._max_frames:
                    break
                t0 = time.perf_counter()
                ok, bgr = self._capture.read()
                self._read_ms = (time.perf_counter() - t0) * 1e3
                pos_ms = self._capture.get(cv2.CAP_PROP_POS_MSEC)
                if not ok:
                    bgr = None
            self._put(_END)
        except Exception as exc:  # handed to the consumer, raised there
            self._put(_Failure(exc))

    def __iter__(self) -> Iterator[tuple[float, np.ndarray]]:
        if self._started:
            raise RuntimeError("a video panorama source can be iterated once")
        self._started = True
        self._thread.start()
        try:
            while True:
                t0 = time.perf_counter()
                item = self._queue.get()
                self.wait_ms.append((time.perf_counter() - t0) * 1e3)
                if item is _END:
                    return
                if isinstance(item, _Failure):
                    if isinstance(item.error, DatasetError):
                        raise item.error
                    raise PanoramaError(f"{self.path}: decoding failed ({item.error})")
                yield item
        finally:
            self.close()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._started:
            self._thread.join(timeout=10.0)
        self._capture.release()


def open_panorama(
    path: str | Path,
    fps: float | None = None,
    max_frames: int | None = None,
    queue_frames: int = DEFAULT_QUEUE_FRAMES,
) -> PanoramaSource:
    """The panorama source at `path`: a video file, a folder of images, or one image.

    fps: frames per second for the timestamps of an image sequence (default 30), or to
    override a video's own timestamps (index / fps). max_frames: stop after that many.
    Raises PanoramaError (a DatasetError) naming the file when it cannot be read or is not
    2:1.
    """
    p = Path(path)
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a number > 0, got {fps}")
    if p.is_dir():
        files = sorted(
            (f for f in p.iterdir() if f.is_file() and f.suffix.lower() in LDR_EXTS + HDR_EXTS),
            key=_natural_key,
        )
        if not files:
            raise PanoramaError(
                f"{p}: no panorama images in this folder (expected "
                f"{', '.join(LDR_EXTS + HDR_EXTS)} files)"
            )
        return _ImageSource(p, files, "sequence", fps or DEFAULT_SEQUENCE_FPS, max_frames)
    if not p.exists():
        raise PanoramaError(f"{p}: no such file or folder")
    ext = p.suffix.lower()
    if ext in VIDEO_EXTS:
        return _VideoSource(p, fps, max_frames, queue_frames)
    if ext in LDR_EXTS + HDR_EXTS + (".bmp", ".tif", ".tiff", ".ppm"):
        return _ImageSource(p, [p], "image", fps or DEFAULT_SEQUENCE_FPS, 1)
    raise PanoramaError(
        f"{p}: not a panorama this reads (videos: {', '.join(VIDEO_EXTS)}; "
        f"images: {', '.join(LDR_EXTS + HDR_EXTS)}; or a folder of images)"
    )
