"""A session's frames between the socket and the worker: the queue and credit state machine.

No sockets, no pipeline, no clock of its own: the server's I/O thread offers each received
Frame (`offer`, which says what became of it), takes the next one for a worker (`next_job`)
and hands back each frame's reply once it is made (`finish`, which gives the freed worker
slot to the next frame). At most one frame of a session
is in a worker at a time, so a session's frames are processed in order.

Delivery modes (docs/architecture.md; drops are counted, never silent):
- live: the queue holds the newest frame only; an older pending frame is replaced and
  counted in `frames_dropped`, which every Result reports.
- lossless: every frame is processed exactly once, in order. The client keeps at most
  `credits` frames unacknowledged (the queue tolerates LOSSLESS_QUEUE_SLACK more, and
  `max_queued_bytes` of them, before it refuses one); a frame whose seq was already
  accepted is a duplicate (a client resending after a reconnect): it is not processed
  again. Its final reply, the Result or the final Error, is kept for the last
  `credits + OUTCOME_CACHE_EXTRA` frames and sent again; a duplicate still queued or in a
  worker is answered when it finishes; an older one gets a final `bad_state` Error (field
  "duplicate"), so every frame the client sends gets an answer
  and a lossless stream never waits forever.

Threads: the queue itself is the I/O thread's; the counters are also written by workers
(`count_processed`, `count_failed`) and read by anyone (`counters`), under a lock.
Times are the caller's time.monotonic() seconds (`Job.receive_time_mono`, `finish`).
"""

from __future__ import annotations

import collections
import threading
from dataclasses import dataclass
from enum import Enum

LOSSLESS_QUEUE_SLACK = 2  # frames beyond the credit window a lossless queue tolerates
OUTCOME_CACHE_EXTRA = 4  # final replies kept for resending after a reconnect: credits + this
RECENT_LATENCIES = 512  # (finish time, latency) pairs kept for the periodic log


class Offer(Enum):
    """What `FrameQueue.offer` did with a received frame (what the server answers)."""

    QUEUED = "queued"  # waits for a worker
    REPLACED = "replaced"  # live: queued, and an older pending frame dropped (counted)
    DUPLICATE = "duplicate"  # lossless: already accepted, still queued or in a worker: its
    # reply comes when it finishes
    RESEND = "resend"  # lossless: already finished: its kept reply (`reply(seq)`) again
    EXPIRED = "expired"  # lossless: at or below the highest seq accepted, neither waiting
    # nor kept: its reply can no longer be sent again (a final Error says so)
    OVERFLOW = "overflow"  # lossless: the client ignored its credit window; refused
    # (retryable: send it again after a Result)


@dataclass
class Job:
    """A received frame waiting for (or in) a worker. parts: the encoded message, undecoded."""

    seq: int
    parts: list
    receive_time_wall: float  # time.time(), seconds: the Result's server_receive_time
    receive_time_mono: float  # time.monotonic(), seconds: latency and liveness

    @property
    def size(self) -> int:
        """The frame's bytes, all parts."""
        return sum(len(p) for p in self.parts)


@dataclass(frozen=True)
class Counters:
    """A session's frame counters so far (every Result reports the first three)."""

    received: int = 0  # accepted into the queue (a refused or duplicate frame is not)
    processed: int = 0  # answered with a Result
    dropped: int = 0  # live: replaced in the queue before a worker took them
    failed: int = 0  # answered with an Error


class FrameQueue:
    """One session's queue, credit window, kept replies and counters.

    lossless: the session's mode; credits: the lossless credit window (frames a client may
    have unacknowledged); now: time.monotonic() when the session began (`last_activity`).
    """

    def __init__(
        self,
        *,
        lossless: bool,
        credits: int,
        now: float = 0.0,
        max_queued_bytes: float = float("inf"),
    ):
        if credits < 1:
            raise ValueError(f"credits must be >= 1, got {credits}")
        self.lossless = lossless
        self.credits = credits
        self.max_queued_bytes = max_queued_bytes  # lossless: of the pending frames
        self.pending: collections.deque[Job] = collections.deque()
        self.in_flight: Job | None = None
        self.highest_seq = -1  # highest seq accepted (lossless duplicate detection)
        self.refused_from: int | None = None  # lossless: first seq refused for credits
        self.last_activity = now  # time.monotonic() of the last frame offered or finished
        # lossless: seq -> encoded final reply (Result or final Error) of the last frames
        self.outcomes: collections.OrderedDict[int, list] = collections.OrderedDict()
        # (monotonic finish time, receive-to-finish latency), seconds, of processed frames
        self.recent: collections.deque[tuple[float, float]] = collections.deque(
            maxlen=RECENT_LATENCIES
        )
        self._lock = threading.Lock()
        self._received = self._processed = self._dropped = self._failed = 0

    @property
    def keeps(self) -> int:
        """How many final replies a lossless queue keeps for resending."""
        return self.credits + OUTCOME_CACHE_EXTRA

    # ------------------------------------------------------------------ I/O thread

    def offer(self, job: Job) -> Offer:
        """Queue a received frame, or say why not (`Offer`)."""
        seq = job.seq
        self.last_activity = job.receive_time_mono
        if self.lossless:
            if seq <= self.highest_seq:
                if seq in self.outcomes:
                    return Offer.RESEND
                waiting = (self.in_flight is not None and self.in_flight.seq == seq) or any(
                    j.seq == seq for j in self.pending
                )
                return Offer.DUPLICATE if waiting else Offer.EXPIRED
            # once a frame is refused, later ones are refused too until it comes again: a
            # client that retries in order then keeps its frames in order
            queued = sum(j.size for j in self.pending)
            if (
                len(self.pending) >= self.credits + LOSSLESS_QUEUE_SLACK
                or (self.pending and queued + job.size > self.max_queued_bytes)
                or (self.refused_from is not None and seq > self.refused_from)
            ):
                self.refused_from = seq if self.refused_from is None else self.refused_from
                return Offer.OVERFLOW
            self.refused_from = None
            with self._lock:
                self._received += 1
            self.highest_seq = seq
            self.pending.append(job)
            return Offer.QUEUED
        offer = Offer.QUEUED
        with self._lock:
            self._received += 1
            if self.pending:
                self.pending.clear()
                self._dropped += 1
                offer = Offer.REPLACED
        self.highest_seq = max(self.highest_seq, seq)
        self.pending.append(job)
        return offer

    def reply(self, seq: int) -> list:
        """The kept final reply of frame `seq` (after `Offer.RESEND`)."""
        return self.outcomes[seq]

    def next_job(self) -> Job | None:
        """The next frame to process, if none of this queue's frames is in a worker."""
        if self.in_flight is not None or not self.pending:
            return None
        self.in_flight = self.pending.popleft()
        return self.in_flight

    def finish(
        self,
        job: Job,
        reply: list,
        *,
        final: bool,
        processed: bool,
        finish_time_mono: float,
        start_next: bool = True,
    ) -> Job | None:
        """The reply of `job` (the frame in the worker) was made: the worker's slot is free.
        final: it is the frame's last word (a Result or a final Error; not a retryable
        Error), kept in lossless mode for a resent duplicate; processed: a Result (its
        latency is recorded). Returns the next frame, now in the slot (`next_job`), unless
        start_next is False or none is queued."""
        if self.in_flight is job:
            self.in_flight = None
        self.last_activity = max(self.last_activity, finish_time_mono)
        if self.lossless and final:
            self.outcomes[job.seq] = reply
            while len(self.outcomes) > self.keeps:
                self.outcomes.popitem(last=False)
        if processed:
            self.recent.append((finish_time_mono, finish_time_mono - job.receive_time_mono))
        return self.next_job() if start_next else None

    def unaccept(self, job: Job) -> list[Job]:
        """After `job` (finished) failed without being processed and must be sent again (its
        pipeline was lost): un-accept it and the queued frames, returned (the caller reports
        them retryable). Lossless: the highest accepted seq goes back below job's, and frames
        above it are refused (OVERFLOW) until it comes again, so the resent frames keep
        their order."""
        jobs = list(self.pending)
        self.pending.clear()
        with self._lock:
            self._received -= 1 + len(jobs)
        if self.lossless:
            self.highest_seq = min(self.highest_seq, job.seq - 1)
            self.refused_from = job.seq
        return jobs

    def drop_pending(self) -> list[Job]:
        """Remove and return the queued frames (shutdown); live frames count as dropped."""
        jobs = list(self.pending)
        self.pending.clear()
        if not self.lossless:
            with self._lock:
                self._dropped += len(jobs)
        return jobs

    @property
    def idle(self) -> bool:
        return self.in_flight is None and not self.pending

    # ------------------------------------------------------------------ any thread

    def count_processed(self) -> Counters:
        """Count a frame answered with a Result; the counters its Result reports."""
        with self._lock:
            self._processed += 1
            return self._counters()

    def count_failed(self) -> None:
        """Count a frame answered with an Error."""
        with self._lock:
            self._failed += 1

    def counters(self) -> Counters:
        with self._lock:
            return self._counters()

    def _counters(self) -> Counters:
        return Counters(self._received, self._processed, self._dropped, self._failed)
