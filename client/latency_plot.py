"""The display's summary plot: latency and frames per second over the session (one PNG).

Written by `arlight display --out DIR` as DIR/latency.png when the display ends.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

FPS_WINDOW_S = 1.0


def fps_over_time(receive_s: npt.ArrayLike, window_s: float = FPS_WINDOW_S) -> np.ndarray:
    """Results per second at each receive time (receive_s: increasing, seconds on one
    clock): the intervals between the Results of the last `window_s` seconds (this one
    included) over the time they span; 0 where there is no interval yet."""
    t = np.asarray(receive_s, dtype=np.float64)
    if t.size == 0:
        return np.zeros(0)
    first = np.searchsorted(t, t - window_s, side="left")
    intervals = np.arange(t.size) - first
    span = t - t[first]
    return np.where(span > 0, intervals / np.maximum(span, 1e-12), 0.0)


def write_latency_plot(
    path: str | Path,
    receive_s: Sequence[float],
    latencies_ms: Sequence[float],
    latency_kind: str,
    title: str = "",
) -> Path:
    """Two panels over time since the first Result (s): latency (ms; `latency_kind` names
    it, e.g. "end-to-end") and frames per second (over the last FPS_WINDOW_S). Returns the
    path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(receive_s, dtype=np.float64)
    t = t - t[0] if t.size else t
    lat = np.asarray(latencies_ms, dtype=np.float64)
    fig, (ax_lat, ax_fps) = plt.subplots(2, 1, sharex=True, figsize=(7.0, 4.8), dpi=100)
    ax_lat.plot(t, lat, ".-", lw=1, ms=3, color="tab:blue")
    if lat.size:
        median = float(np.median(lat))
        ax_lat.axhline(median, color="tab:blue", lw=0.8, ls="--", label=f"median {median:.0f} ms")
        ax_lat.legend(loc="upper right", fontsize=8)
    ax_lat.set_ylabel(f"{latency_kind} latency, ms")
    ax_lat.grid(alpha=0.3)
    ax_fps.plot(t, fps_over_time(np.asarray(receive_s, dtype=np.float64)), "-", color="tab:green")
    ax_fps.set_ylabel(f"fps ({FPS_WINDOW_S:g} s window)")
    ax_fps.set_xlabel("time since the first result, s")
    ax_fps.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out
