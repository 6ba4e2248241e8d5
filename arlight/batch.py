"""`arlight batch`: many recordings and sequences on Ray, one stateful actor per stream.

Each input (an MCAP recording made by `arlight record`, or a sequence folder that
`arlight estimate` reads) gets its own actor: the pipeline's volume, pose and temporal filter
are per-stream state, so a stream never shares a Pipeline. The actor opens the source itself
by path (frames never travel through Ray's object store), runs `Pipeline.process` over every
frame, and writes `OUT/<name>.jsonl` -- the records `arlight estimate --out` writes -- under a
temporary name, renamed when complete: a `<name>.jsonl` in OUT is a finished stream, skipped
on a rerun (unless `force`). `OUT/batch.json` lists every input's status (ok, failed,
skipped), reason, frames and seconds; it is rewritten after each stream ends.

Resources per actor (`actor_resources`): `num_cpus` from the preset -- full 2 (its 256^3
volume and full-resolution radiance transfer keep two cores busy), fast 1, mobile 1 -- capped
at what the cluster has; `num_gpus` 1 when the device is CUDA. At most as many actors run at
once as the cluster's CPUs (and GPUs) allow; the rest wait their turn.

Ray is an optional dependency (`pip install arlight[ray]`); without it `run_batch` raises
`BatchUsageError` naming the extra, with no fallback.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

PRESET_NUM_CPUS = {"full": 2, "fast": 1, "mobile": 1}
SUMMARY_FILE = "batch.json"
RECORDS_SUFFIX = ".jsonl"
POLL_INTERVAL_S = 0.5
_NAME_CHARS = re.compile(r"[^A-Za-z0-9_.-]+")


class BatchUsageError(ValueError):
    """Bad usage of `arlight batch` (no inputs, Ray missing, resources the cluster lacks)."""


@dataclass(frozen=True)
class BatchItem:
    """One stream of the batch: `path` (recording or sequence folder) and its unique `name`
    in the output folder (records in `<name>.jsonl`)."""

    path: str
    name: str


@dataclass(frozen=True)
class BatchOptions:
    """How every stream is processed: preset, Config overrides ((key, value) pairs),
    device ("CPU:0" or "CUDA:0"), max_frames (None: all) and the sequences' depth_encoding
    (None: from their layout)."""

    preset: str = "full"
    overrides: tuple[tuple[str, object], ...] = ()
    device: str | None = None
    max_frames: int | None = None
    depth_encoding: str | None = None

    def settings(self) -> dict:
        """What decides the records, as plain JSON (batch.json's "options")."""
        return {
            "preset": self.preset,
            "device": self.device or "CPU:0",
            "overrides": {k: repr(v) for k, v in self.overrides},
            "max_frames": self.max_frames,
            "depth_encoding": self.depth_encoding,
        }

    def config(self):
        """The pipeline Config of every stream (ValueError for a bad preset or override)."""
        from arlight.pipeline.config import Config

        overrides = dict(self.overrides)
        if self.device:
            overrides["device"] = self.device
        return Config.from_preset(self.preset, **overrides)


@dataclass
class StreamSummary:
    """What became of one stream: status "ok", "failed", "skipped" (or "pending": not run,
    the batch was interrupted); reason (failed: why, skipped: that its records exist);
    frames written; seconds of the actor's work; median_confidence of its frames (None
    without frames); output: the records file."""

    name: str
    input: str
    status: str
    reason: str = ""
    frames: int = 0
    seconds: float = 0.0
    median_confidence: float | None = None
    output: str | None = None


@dataclass
class BatchReport:
    """Every stream's summary, in input order, and where batch.json was written."""

    streams: list[StreamSummary] = field(default_factory=list)
    summary_path: Path | None = None

    def count(self, status: str) -> int:
        return sum(s.status == status for s in self.streams)

    @property
    def ok(self) -> bool:
        """True when no stream failed."""
        return self.count("failed") == 0


# --------------------------------------------------------------------------- inputs


def collect_inputs(paths: Sequence[str | Path]) -> list[BatchItem]:
    """The batch's streams: each path a recording (FILE.mcap) or a sequence folder; a folder
    holding .mcap files stands for those recordings (sorted). Duplicates (the same resolved
    path) count once. Names: the file's stem or the folder's name, made unique with 8 hex
    digits of the resolved path where two inputs share one (stable from run to run)."""
    if not paths:
        raise BatchUsageError("no inputs: give recordings (FILE.mcap) or sequence folders")
    streams: list[Path] = []
    seen: set[Path] = set()
    for raw in paths:
        path = Path(raw)
        recordings = sorted(path.glob("*.mcap")) if path.is_dir() else []
        for p in recordings or [path]:
            key = p.resolve()
            if key not in seen:
                seen.add(key)
                streams.append(p)
    bases = [_base_name(p) for p in streams]
    taken = {b: bases.count(b) for b in bases}
    items = []
    for p, base in zip(streams, bases, strict=True):
        name = base
        if taken[base] > 1:
            digest = hashlib.sha1(str(p.resolve()).encode()).hexdigest()[:8]
            name = f"{base}-{digest}"
        items.append(BatchItem(str(p), name))
    return items


def _base_name(path: Path) -> str:
    stem = path.stem if path.suffix.lower() == ".mcap" else path.name
    stem = _NAME_CHARS.sub("_", stem or path.resolve().name).strip("._")
    return stem or "stream"


def records_path(out_dir: Path, item: BatchItem) -> Path:
    return out_dir / f"{item.name}{RECORDS_SUFFIX}"


# --------------------------------------------------------------------------- one stream


def open_frames(path: str, options: BatchOptions):
    """(camera, number of frames, iterator over FrameInputs) of a recording or sequence.

    Sequences are read as `arlight estimate PATH` reads them (tracking, no poses); a
    recording's frames as the server receives them (`arlight.offline.open_recording`, poses
    as recorded). Raises DatasetError, RecordingError or ProtocolError (all ValueError) for
    unusable input.
    """
    if path.lower().endswith(".mcap"):
        from arlight.offline import open_recording

        return open_recording(path, options.max_frames)
    from arlight.sources.sequence import open_sequence

    seq = open_sequence(
        path, depth_encoding=options.depth_encoding, use_poses=False, max_frames=options.max_frames
    )
    frames = seq.frames
    return seq.camera, len(frames), (frames[i] for i in range(len(frames)))


def process_stream(
    path: str,
    out_path: str | Path,
    options: BatchOptions,
    on_frame: Callable[[int, int], None] | None = None,
) -> StreamSummary:
    """Run a fresh Pipeline over one stream, writing its records to `out_path` atomically.

    The records are `arlight estimate --out`'s (`arlight.offline.frame_record`). They go to
    a temporary file beside `out_path`, renamed to it once every frame is written; on any
    error the temporary file is removed and the exception propagates. on_frame(done, total)
    is called after each frame.
    """
    from arlight.offline import estimate_frames
    from arlight.pipeline.pipeline import Pipeline
    from arlight.pipeline.runtime import require_device

    t0 = time.perf_counter()
    out_path = Path(out_path)
    config = options.config()
    require_device(config.device)
    camera, n, frames = open_frames(path, options)
    pipeline = Pipeline(config, camera)
    if on_frame is not None:
        on_frame(0, n)
    tmp = out_path.with_name(f".{out_path.name}.{os.getpid()}.tmp")
    confidences = []
    try:
        with open(tmp, "w") as out:
            for done in estimate_frames(pipeline, frames):
                out.write(json.dumps(done.record) + "\n")
                confidences.append(done.result.confidence.value)
                if on_frame is not None:
                    on_frame(done.index + 1, n)
        os.replace(tmp, out_path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    median = float(np.median(confidences)) if confidences else None
    return StreamSummary(
        out_path.stem,
        path,
        "ok",
        frames=len(confidences),
        seconds=time.perf_counter() - t0,
        median_confidence=median,
        output=str(out_path),
    )


class StreamWorker:
    """The body of the Ray actor that processes one stream (wrapped by `ray.remote` in
    `run_batch`). `run` does the work; `progress` answers (frames done, total) meanwhile
    (the actor runs two calls at once: max_concurrency=2)."""

    def __init__(self, num_cpus: int):
        from arlight.pipeline.runtime import configure_process, limit_numba_threads

        configure_process(num_cpus)  # Open3D on the actor's own cores
        with contextlib.suppress(Exception):  # and the kernels, where numba allows it
            limit_numba_threads(num_cpus)
        self._lock = threading.Lock()
        self._done, self._total = 0, 0

    def _on_frame(self, done: int, total: int) -> None:
        with self._lock:
            self._done, self._total = done, total

    def progress(self) -> tuple[int, int]:
        with self._lock:
            return self._done, self._total

    def run(self, item: BatchItem, out_path: str, options: BatchOptions) -> StreamSummary:
        """The stream's summary; expected failures (bad input) come back as status failed."""
        from arlight.pipeline.pipeline import FrameError
        from arlight.sources.errors import DatasetError

        t0 = time.perf_counter()
        try:
            summary = process_stream(item.path, out_path, options, self._on_frame)
        except (DatasetError, FrameError, ValueError, OSError) as exc:
            return StreamSummary(
                item.name,
                item.path,
                "failed",
                reason=str(exc),
                frames=self._done,
                seconds=time.perf_counter() - t0,
            )
        summary.name = item.name
        return summary


# --------------------------------------------------------------------------- the batch


def import_ray():
    """The ray module, or BatchUsageError naming the extra to install."""
    try:
        import ray
    except ImportError:
        raise BatchUsageError("Ray is not installed: pip install 'arlight[ray]'") from None
    return ray


# Ray (2.x) makes its node's address the machine's reachable one, and its GCS, raylet, object
# manager, runtime-env agent and workers listen on every interface, unless it takes this
# node for a single machine ("cluster mode" off: what it does on macOS and Windows): then
# its node address is 127.0.0.1 and every one of them listens on loopback only
# (issue 39, item 8; tests/test_security_ray.py checks the listening sockets).
LOOPBACK_RAY_ENV = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}


def init_local_ray(ray: Any, **options: Any) -> None:
    """Start a new Ray of this machine only: no dashboard, and every server it starts
    listening on 127.0.0.1 (`LOOPBACK_RAY_ENV`). options: more ray.init keywords
    (num_cpus, ...). The driver's setting is restored afterwards; Ray's own processes keep
    it (they inherit the environment when they start)."""
    constants = ray._private.ray_constants  # read when ray is imported: set it here too
    saved_env = {key: os.environ.get(key) for key in LOOPBACK_RAY_ENV}
    saved_cluster = constants.ENABLE_RAY_CLUSTER
    os.environ.update(LOOPBACK_RAY_ENV)
    constants.ENABLE_RAY_CLUSTER = False
    try:
        ray.init(address="local", include_dashboard=False, log_to_driver=False, **options)
    finally:
        constants.ENABLE_RAY_CLUSTER = saved_cluster
        for key, value in saved_env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def actor_resources(preset: str, device: str | None, cluster: dict) -> dict:
    """{"num_cpus": n, "num_gpus": g} of one actor (module docstring), and "slots": how many
    actors the cluster's resources (ray.cluster_resources()) run at once.

    BatchUsageError when CUDA is asked of a cluster without GPUs.
    """
    cpus = max(1.0, float(cluster.get("CPU", 1)))
    num_cpus = min(PRESET_NUM_CPUS.get(preset, 1), int(cpus)) or 1
    slots = max(1, int(cpus // num_cpus))
    num_gpus = 0
    if device and device.upper().startswith("CUDA"):
        gpus = float(cluster.get("GPU", 0))
        if gpus < 1:
            raise BatchUsageError(
                f"--device {device}: the Ray cluster offers no GPU "
                f"({cpus:g} CPUs, 0 GPUs); use --device CPU:0"
            )
        num_gpus = 1
        slots = min(slots, int(gpus))
    return {"num_cpus": num_cpus, "num_gpus": num_gpus, "slots": slots}


def write_summary(out_dir: Path, report: BatchReport, options: BatchOptions) -> Path:
    """OUT/batch.json (atomically): options and each stream's summary."""
    path = out_dir / SUMMARY_FILE
    doc = {
        "options": options.settings(),
        "counts": {s: report.count(s) for s in ("ok", "failed", "skipped")},
        "streams": [asdict(s) for s in report.streams],
    }
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    os.replace(tmp, path)
    return path


def _failure_reason(exc: BaseException) -> str:
    """One line for an actor that raised or died (Ray wraps the cause)."""
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException):
        return f"{type(cause).__name__}: {cause}".splitlines()[0]
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[-1] if text else ''}"


def _check_same_options(out_dir: Path, options: BatchOptions, force: bool) -> None:
    """BatchUsageError when DIR's records were made with other options (a rerun would skip
    them and mix two configurations); --force redoes them instead."""
    path = out_dir / SUMMARY_FILE
    if force or not path.is_file():
        return
    try:
        before = json.loads(path.read_text()).get("options")
    except (OSError, ValueError, AttributeError):
        return  # not ours to judge: the rerun rewrites it
    if before is not None and before != options.settings():
        raise BatchUsageError(
            f"{out_dir} holds results made with {before}, not "
            f"{options.settings()}: use another --out, or --force to "
            "redo every stream"
        )


def _count_lines(path: Path) -> int:
    with open(path, "rb") as f:
        return sum(1 for _ in f)


def run_batch(
    items: Sequence[BatchItem],
    out_dir: str | Path,
    options: BatchOptions,
    *,
    address: str | None = None,
    force: bool = False,
    progress: bool = True,
    on_done: Callable[[StreamSummary], None] | None = None,
) -> BatchReport:
    """Process every stream on Ray; the report of all of them, also in OUT/batch.json.

    Uses the running Ray connection when there is one; otherwise `ray.init(address)` (None:
    a local Ray), shut down again at the end. Streams whose records exist are skipped unless
    `force`. A failing stream is reported and the others carry on. progress: a tqdm bar over
    the frames of the whole batch (on stderr). on_done(summary) after each stream.
    """
    if not items:
        raise BatchUsageError("no inputs: give recordings (FILE.mcap) or sequence folders")
    options.config()  # a bad preset or override is a usage error before Ray starts
    ray = import_ray()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    _check_same_options(out_dir, options, force)
    report = BatchReport([StreamSummary(it.name, it.path, "pending") for it in items])
    todo = []
    for index, item in enumerate(items):
        path = records_path(out_dir, item)
        if path.is_file() and not force:
            report.streams[index] = StreamSummary(
                item.name,
                item.path,
                "skipped",
                reason=f"{path.name} exists (--force redoes it)",
                frames=_count_lines(path),
                output=str(path),
            )
        else:
            todo.append(index)
    started_ray = False
    if todo and not ray.is_initialized():
        try:
            if address:  # a cluster keeps its own settings
                ray.init(address=address, log_to_driver=False)
            else:
                init_local_ray(ray)
        except Exception as exc:  # noqa: BLE001 - Ray raises many types for "cannot connect"
            where = f"--ray {address}" if address else "a local Ray"
            raise BatchUsageError(
                f"{where}: cannot start or connect ({type(exc).__name__}: {exc})"
            ) from None
        started_ray = True
    try:
        if todo:
            _run_actors(ray, items, todo, out_dir, options, report, progress, on_done)
    finally:
        report.summary_path = write_summary(out_dir, report, options)
        if started_ray:
            ray.shutdown()
    return report


def _run_actors(ray, items, todo, out_dir, options, report, progress, on_done) -> None:
    from tqdm import tqdm

    res = actor_resources(options.preset, options.device, ray.cluster_resources())
    worker_class = ray.remote(StreamWorker).options(
        num_cpus=res["num_cpus"], num_gpus=res["num_gpus"], max_concurrency=2
    )
    waiting = list(todo)
    running: dict = {}  # ObjectRef of run() -> (index, actor)
    done_frames: dict[int, tuple[int, int]] = {}
    bar = tqdm(total=0, unit="frame", desc="arlight batch", disable=not progress)

    def refresh() -> None:
        bar.total = sum(t for _, t in done_frames.values())
        bar.n = sum(d for d, _ in done_frames.values())
        finished = sum(s.status in ("ok", "failed") for s in report.streams)
        bar.set_postfix_str(
            f"{finished}/{len(todo)} streams, "
            f"{sum(s.status == 'failed' for s in report.streams)} failed"
        )
        bar.refresh()

    try:
        while waiting or running:
            while waiting and len(running) < res["slots"]:
                index = waiting.pop(0)
                actor = worker_class.remote(res["num_cpus"])
                # absolute: a cluster's workers do not share the driver's working directory
                item = items[index]
                out_path = str(records_path(out_dir, item).resolve())
                job = BatchItem(str(Path(item.path).resolve()), item.name)
                running[actor.run.remote(job, out_path, options)] = (index, actor)
            ready, _ = ray.wait(list(running), num_returns=1, timeout=POLL_INTERVAL_S)
            for ref in ready:
                index, actor = running.pop(ref)
                item = items[index]
                try:
                    summary = ray.get(ref)
                    summary.input = item.path  # as the user gave it
                    summary.output = summary.output and str(records_path(out_dir, item))
                except Exception as exc:  # noqa: BLE001 - the actor raised or died
                    summary = StreamSummary(
                        item.name, item.path, "failed", reason=_failure_reason(exc)
                    )
                ray.kill(actor)
                report.streams[index] = summary
                done_frames[index] = (summary.frames, summary.frames)
                write_summary(out_dir, report, options)
                if on_done is not None:
                    on_done(summary)
            polls = {i: a.progress.remote() for i, a in running.values()}
            for i, ref in polls.items():
                with contextlib.suppress(Exception):  # an actor just ending: next poll
                    done_frames[i] = ray.get(ref, timeout=POLL_INTERVAL_S)
            refresh()
    finally:
        for _, actor in running.values():
            with contextlib.suppress(Exception):
                ray.kill(actor)
        bar.close()


def format_summary(s: StreamSummary) -> str:
    """One line per stream for the terminal."""
    conf = (
        "-"
        if s.median_confidence is None or math.isnan(s.median_confidence)
        else f"{s.median_confidence:.2f}"
    )
    line = f"{s.status:<7} {s.name}: {s.frames} frames, {s.seconds:.1f} s, confidence {conf}"
    return line + (f" ({s.reason})" if s.reason else "")
