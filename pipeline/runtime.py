"""Process-wide compute settings, chosen once by the entry point (server, CLI), never a session.

Thread safety: a `Pipeline` holds one session's state and is not thread-safe (one frame at a
time per instance). Distinct instances may process frames in parallel threads when
`concurrent_pipelines_safe()` says the kernels' threading layer allows it.

Entry points call `configure_process()` (or its parts) once, before the first Pipeline:
the pipeline itself never changes a process-wide setting.
"""

from __future__ import annotations

import warnings

# numba probes a system TBB (too old on many distributions), warns, and falls back to
# OpenMP or workqueue; the fallback is fine and the warning only confuses users
NUMBA_TBB_WARNING = ".*TBB threading layer.*"


def configure_open3d_threads(n: int = 1) -> None:
    """Run Open3D on `n` CPU threads, process-wide (call once, at start).

    One thread (the default) is what makes sessions deterministic (docs/architecture.md,
    Conventions): Open3D's RGB-D odometry sums its normal equations with a TBB parallel
    reduction whose order depends on thread scheduling, so with several threads the same
    frames give poses that differ by ~1e-5 m from run to run. Fusion and ray casting
    then run on one thread too (slower on a many-core server; pass n > 1 where
    reproducible poses matter less than speed).
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an integer >= 1 (Open3D threads), got {n!r}")
    import open3d as o3d

    o3d.utility.set_max_threads(n)


def silence_numba_tbb_warning() -> None:
    """Hide numba's warning that the system TBB is unusable (it falls back by itself)."""
    warnings.filterwarnings("ignore", message=NUMBA_TBB_WARNING)


def configure_process(open3d_threads: int = 1) -> None:
    """What an entry point (server, CLI, benchmark) calls once before any Pipeline."""
    silence_numba_tbb_warning()
    configure_open3d_threads(open3d_threads)


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
