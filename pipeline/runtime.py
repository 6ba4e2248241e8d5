"""Process-wide compute settings, chosen once by the entry point (server, CLI), never a session.

Thread safety: a `Pipeline` holds one session's state and is not thread-safe (one frame at a
time per instance). Distinct instances may process frames in parallel threads when
`concurrent_pipelines_safe()` says the kernels' threading layer allows it.

Entry points call `configure_process()` (or its parts) once, before the first Pipeline:
the pipeline itself never changes a process-wide setting.
"""

from __future__ import annotations

import os

# numba's kernels need a threading layer. It probes TBB first, and a system TBB that is too old
# (common on Debian/Ubuntu) makes it warn before it falls back to OpenMP; OpenMP first is
# what it would end up with anyway, and is safe for concurrent pipelines
NUMBA_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]


def configure_open3d_threads(n: int | None = None) -> None:
    """Run Open3D on `n` CPU threads, process-wide (call once, at start; None: all cores).

    Trade-off measured at 640x480 on 2 cores: one thread makes frame-to-model tracking
    reproducible (Open3D's RGB-D odometry sums its normal equations with a TBB parallel
    reduction whose order depends on thread scheduling, so with several threads the same
    frames give poses that differ by ~1e-5 m from run to run), but fusion and the ray cast
    then run on one thread too (Surface 110 -> 174 ms, `arlight bench --presets full`).
    The tests run with one thread; `arlight --open3d-threads 1` asks for it.
    """
    if n is None:
        return
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"Open3D threads must be an integer >= 1 (--open3d-threads N), got {n!r}")
    import open3d as o3d

    o3d.utility.set_max_threads(n)


def choose_numba_threading_layer() -> None:
    """OpenMP first, so numba does not probe (and warn about) an unusable system TBB.

    Takes effect before the first parallel kernel runs; NUMBA_THREADING_LAYER set by the
    user wins.
    """
    if os.environ.get("NUMBA_THREADING_LAYER"):
        return
    import numba

    # numba.config makes its settings from the environment at import, by name (mypy sees none)
    numba.config.THREADING_LAYER_PRIORITY = list(NUMBA_LAYER_PRIORITY)  # type: ignore[attr-defined]


def limit_numba_threads(n: int) -> None:
    """Run the kernels on at most `n` threads (a Ray actor: its own cores), within the pool
    numba started with (NUMBA_NUM_THREADS, by default the machine's cores)."""
    import numba

    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]


def configure_process(open3d_threads: int | None = None) -> None:
    """What an entry point (server, CLI, benchmark) calls once before any Pipeline."""
    choose_numba_threading_layer()
    configure_open3d_threads(open3d_threads)


def require_device(device: str) -> None:
    """ValueError naming the CPU alternative unless `device` ("CPU:0", "CUDA:n") can run here.

    CUDA needs both halves of the GPU path: Open3D built with CUDA (the volume) and a GPU
    that numba sees (the kernels).
    """
    if not device.startswith("CUDA:"):
        return
    import open3d as o3d

    hint = "(--device CPU:0, or --set device=CPU:0 for a streamed session)"
    try:
        index = int(device.split(":", 1)[1])
    except ValueError:
        raise ValueError(f"device {device!r}: expected CPU:0 or CUDA:0 {hint}") from None
    if index != 0:
        raise ValueError(
            f"device {device}: the kernels run on the first GPU only; use CUDA:0 or the CPU {hint}"
        )
    count = o3d.core.cuda.device_count() if o3d.core.cuda.is_available() else 0
    if index >= count:
        seen = "no CUDA device" if count == 0 else f"only {count} CUDA device(s)"
        raise ValueError(
            f"device {device}: Open3D sees {seen} on this machine (a CPU-only "
            f"build or no GPU driver); run on the CPU {hint}"
        )
    try:
        from numba import cuda

        numba_ok = cuda.is_available()
    except Exception:  # noqa: BLE001 - any failure to load the CUDA driver means "no"
        numba_ok = False
    if not numba_ok:
        raise ValueError(
            f"device {device}: numba sees no CUDA GPU (driver or CUDA toolkit "
            f"missing), so the kernels cannot run there; use the CPU {hint}"
        )


def concurrent_pipelines_safe() -> bool:
    """True when several Pipelines may run their Numba kernels in parallel threads.

    Numba's fallback 'workqueue' layer aborts the process on concurrent parallel launches;
    OpenMP and TBB allow them. Before any parallel kernel ran the layer is unknown: False.
    """
    try:
        import numba

        return numba.threading_layer() != "workqueue"
    except (ImportError, ValueError):
        return False
