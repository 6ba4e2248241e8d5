"""The queue and credit state machine of a session (server/frame_queue.py), without sockets.

The loopback tests (test_server.py, test_server_limits.py) drive the same class through the
server; these call it directly, one transition at a time.
"""

from __future__ import annotations

import threading

import pytest

from arlight.server.frame_queue import (
    LOSSLESS_QUEUE_SLACK,
    OUTCOME_CACHE_EXTRA,
    Counters,
    FrameQueue,
    Job,
    Offer,
)


def job(seq: int, t: float = 0.0) -> Job:
    return Job(seq, [f"frame {seq}".encode()], receive_time_wall=1000.0 + t, receive_time_mono=t)


def reply(seq: int) -> list:
    return [f"reply {seq}".encode()]


def run_one(q: FrameQueue, t: float = 1.0, final: bool = True, processed: bool = True) -> Job:
    """The frame in the worker (or the next one) gets its reply (a Result unless told); the
    slot goes to the frame after it."""
    j = q.in_flight or q.next_job()
    assert j is not None
    if processed:
        q.count_processed()
    else:
        q.count_failed()
    q.finish(j, reply(j.seq), final=final, processed=processed, finish_time_mono=t)
    return j


class TestLive:
    def test_a_frame_is_queued_and_taken(self):
        q = FrameQueue(lossless=False, credits=4)
        assert q.idle
        assert q.offer(job(0)) is Offer.QUEUED
        assert not q.idle and q.next_job().seq == 0
        assert q.next_job() is None  # one frame in a worker at a time
        assert q.counters() == Counters(received=1)

    def test_a_newer_frame_replaces_the_pending_one_and_the_drop_is_counted(self):
        q = FrameQueue(lossless=False, credits=4)
        q.offer(job(0))
        q.next_job()  # 0 in the worker
        assert q.offer(job(1)) is Offer.QUEUED
        assert q.offer(job(2)) is Offer.REPLACED
        assert q.offer(job(3)) is Offer.REPLACED
        assert [j.seq for j in q.pending] == [3]  # the newest only
        assert q.counters() == Counters(received=4, dropped=2)

    def test_the_next_frame_waits_for_the_one_in_the_worker(self):
        q = FrameQueue(lossless=False, credits=4)
        q.offer(job(0))
        first = q.next_job()
        q.offer(job(1))
        assert q.next_job() is None
        second = q.finish(first, reply(0), final=True, processed=True, finish_time_mono=1.0)
        assert second is not None and second.seq == 1 and q.in_flight is second
        assert (
            q.finish(
                second, reply(1), final=True, processed=True, finish_time_mono=2.0, start_next=False
            )
            is None
        )

    def test_live_keeps_no_replies_and_drops_pending_at_shutdown(self):
        q = FrameQueue(lossless=False, credits=4)
        q.offer(job(0))
        run_one(q)
        assert not q.outcomes
        q.offer(job(1))
        assert [j.seq for j in q.drop_pending()] == [1]
        assert q.counters().dropped == 1 and q.idle


class TestLossless:
    def test_every_frame_in_order(self):
        q = FrameQueue(lossless=True, credits=4)
        for seq in range(4):
            assert q.offer(job(seq)) is Offer.QUEUED
        done = [run_one(q, t=seq + 1.0).seq for seq in range(4)]
        assert done == [0, 1, 2, 3] and q.idle
        assert q.counters() == Counters(received=4, processed=4)

    def test_the_credit_window_and_its_slack(self):
        credits = 2
        q = FrameQueue(lossless=True, credits=credits)
        limit = credits + LOSSLESS_QUEUE_SLACK
        for seq in range(limit):
            assert q.offer(job(seq)) is Offer.QUEUED
        assert q.offer(job(limit)) is Offer.OVERFLOW
        assert q.counters().received == limit  # a refused frame is not received

    def test_after_a_refusal_later_frames_wait_for_the_refused_one(self):
        q = FrameQueue(lossless=True, credits=1)
        limit = 1 + LOSSLESS_QUEUE_SLACK
        for seq in range(limit):
            q.offer(job(seq))
        assert q.offer(job(limit)) is Offer.OVERFLOW
        run_one(q)  # room again, but frame limit + 1 may not pass frame limit
        assert q.offer(job(limit + 1)) is Offer.OVERFLOW
        assert q.offer(job(limit)) is Offer.QUEUED  # the refused one, sent again
        run_one(q)
        assert q.offer(job(limit + 1)) is Offer.QUEUED
        assert q.in_flight.seq == 2 and [j.seq for j in q.pending] == list(range(3, limit + 2))

    def test_duplicates_resends_and_expired_frames(self):
        q = FrameQueue(lossless=True, credits=1)
        q.offer(job(0))
        assert q.offer(job(0)) is Offer.DUPLICATE  # queued: answered when it finishes
        q.next_job()
        assert q.offer(job(0)) is Offer.DUPLICATE  # in the worker
        q.finish(q.in_flight, reply(0), final=True, processed=True, finish_time_mono=1.0)
        assert q.offer(job(0)) is Offer.RESEND and q.reply(0) == reply(0)
        for seq in range(1, 1 + q.keeps + 1):  # push reply 0 out of the kept ones
            q.offer(job(seq))
            run_one(q)
        assert len(q.outcomes) == q.keeps == 1 + OUTCOME_CACHE_EXTRA
        assert 0 not in q.outcomes
        assert q.offer(job(0)) is Offer.EXPIRED
        assert q.counters().received == 1 + q.keeps + 1  # no duplicate counted

    def test_a_retryable_error_is_not_kept(self):
        q = FrameQueue(lossless=True, credits=4)
        q.offer(job(0))
        run_one(q, final=False, processed=False)
        assert 0 not in q.outcomes
        assert q.counters() == Counters(received=1, failed=1)

    def test_unaccept_after_a_lost_pipeline_takes_the_frames_back_in_order(self):
        q = FrameQueue(lossless=True, credits=4)
        for seq in range(4):
            q.offer(job(seq))
        lost = q.next_job()  # frame 0 was in the lost pipeline: the server un-accepts the
        assert [j.seq for j in q.unaccept(lost)] == [1, 2, 3]  # rest before it finishes it
        assert q.finish(lost, reply(0), final=False, processed=False, finish_time_mono=1.0) is None
        assert q.counters().received == 0
        assert q.offer(job(1)) is Offer.OVERFLOW  # not before frame 0 comes again
        for seq in range(4):
            assert q.offer(job(seq)) is Offer.QUEUED
        assert [run_one(q).seq for _ in range(4)] == [0, 1, 2, 3]

    def test_lossless_frames_are_not_dropped_at_shutdown(self):
        q = FrameQueue(lossless=True, credits=4)
        q.offer(job(0))
        q.offer(job(1))
        assert [j.seq for j in q.drop_pending()] == [0, 1]
        assert q.counters().dropped == 0


class TestBookkeeping:
    def test_activity_and_latency(self):
        q = FrameQueue(lossless=False, credits=4, now=5.0)
        assert q.last_activity == 5.0
        q.offer(job(0, t=7.0))
        assert q.last_activity == 7.0
        run_one(q, t=7.25)
        assert q.last_activity == 7.25
        assert list(q.recent) == [(7.25, 0.25)]
        q.offer(job(1, t=8.0))
        run_one(q, t=8.5, final=True, processed=False)  # an Error: no latency recorded
        assert len(q.recent) == 1

    def test_credits_must_be_positive(self):
        with pytest.raises(ValueError, match="credits"):
            FrameQueue(lossless=True, credits=0)

    def test_counters_are_consistent_across_threads(self):
        q = FrameQueue(lossless=False, credits=4)
        q.offer(job(0))

        def count():
            for _ in range(1000):
                q.count_processed()
                q.count_failed()

        threads = [threading.Thread(target=count) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert q.counters() == Counters(received=1, processed=4000, failed=4000)
