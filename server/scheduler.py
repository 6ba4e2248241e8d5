"""Which session's frame a free worker takes next (issue 39, item 4): fair shares of the
worker pool.

Before, frames went to a first-in-first-out pool: two sessions whose frames the budget
allowed (just under the 60 s deadline each) held both workers, and a light session's frame
waited behind theirs; a legitimate 5-frame stream got 1-3 Results in 100-120 s. Now:

- a free worker takes the frame of the waiting session that has used the least worker time
  lately (each session's seconds decay with a half-life of `HALF_LIFE_S`): a light session
  goes first, and sessions of equal cost take turns;
- heavy frames (a session whose frames take `HEAVY_FRAME_S` or more, by the cost model or by
  its frames so far) run on at most `workers - 1` workers at once, so one worker is always
  left for the light sessions: a light frame waits at most for a light frame ahead of it.

The frames of one session still run one at a time, in order (server/frame_queue.py). The
scheduler lives on the I/O thread; workers report how long each frame took (`finished`).
Times: time.monotonic(), seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

HEAVY_FRAME_S = 2.0  # a frame this long or longer is heavy
HALF_LIFE_S = 30.0  # of a session's worker time, for the order of turns
MEASURED_WEIGHT = 0.5  # of each frame's time in the session's running mean frame time


@dataclass
class Share:
    """One session's use of the workers: decayed worker seconds (at `stamp`), its mean frame
    time so far, the modelled one, and whether it waits for a worker."""

    modelled_s: float
    used_s: float = 0.0
    stamp: float = 0.0
    mean_frame_s: float | None = None
    waiting: bool = False
    running: bool = False
    closed: bool = False

    @property
    def heavy(self) -> bool:
        measured = self.mean_frame_s or 0.0
        return max(self.modelled_s, measured) >= HEAVY_FRAME_S

    def used_at(self, now: float) -> float:
        return self.used_s * 0.5 ** ((now - self.stamp) / HALF_LIFE_S)


@dataclass
class Scheduler:
    """Fair turns on `workers` workers (module docstring). reserve_light: keep one worker for
    light frames (False: a remote compute, whose workers only wait)."""

    workers: int
    reserve_light: bool = True
    shares: dict[object, Share] = field(default_factory=dict)

    def add(self, key: object, modelled_s: float) -> None:
        """A session (its key) whose frames the cost model prices at `modelled_s`."""
        self.shares.setdefault(key, Share(modelled_s if math.isfinite(modelled_s) else 0.0))

    def remove(self, key: object) -> None:
        """The session closed (a frame of it still in a worker counts until `finished`)."""
        share = self.shares.get(key)
        if share is None:
            return
        if share.running:
            share.waiting, share.closed = False, True
        else:
            del self.shares[key]

    def wait(self, key: object) -> None:
        """The session has a frame for a worker."""
        share = self.shares.get(key)
        if share is not None and not share.running and not share.closed:
            share.waiting = True

    def next(self, now: float) -> object | None:
        """The session whose frame a free worker runs now (marked running), or None."""
        running = [s for s in self.shares.values() if s.running]
        if len(running) >= self.workers:
            return None
        heavy_cap = self.workers - 1 if self.reserve_light and self.workers > 1 else self.workers
        heavy_running = sum(s.heavy for s in running)
        best = None
        for key, share in self.shares.items():
            if not share.waiting or (share.heavy and heavy_running >= heavy_cap):
                continue
            if best is None or share.used_at(now) < self.shares[best].used_at(now):
                best = key
        if best is not None:
            chosen = self.shares[best]
            chosen.waiting, chosen.running = False, True
        return best

    def finished(self, key: object, worker_s: float, now: float) -> None:
        """The session's frame left its worker after `worker_s` seconds."""
        share = self.shares.get(key)
        if share is None:
            return
        share.running = False
        if share.closed:
            del self.shares[key]
            return
        share.used_s = share.used_at(now) + worker_s
        share.stamp = now
        mean = share.mean_frame_s
        share.mean_frame_s = (
            worker_s if mean is None else mean + MEASURED_WEIGHT * (worker_s - mean)
        )
