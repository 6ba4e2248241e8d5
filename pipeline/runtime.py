"""Process-wide compute settings, chosen once by the entry point (server, CLI), never a session.

Thread safety: a `Pipeline` holds one session's state and is not thread-safe (one frame at a
time per instance). Distinct instances may process frames in parallel threads when
`concurrent_pipelines_safe()` says the kernels' threading layer allows it.
"""

from __future__ import annotations


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
