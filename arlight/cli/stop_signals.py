"""SIGTERM finalises like Ctrl-C: what `docker stop`, systemd and `timeout` send.

Python's default for SIGTERM ends the process at once, so an MCAP without its summary, a
display's 0-byte recording or an unflushed results file was all a stopped client left
(issue 34). Inside :func:`terminate_as_interrupt` SIGTERM and SIGINT raise
KeyboardInterrupt in the main thread (client/stop_signals.py: never inside a record being
written), the path Ctrl-C takes: each command's ``finally`` and ``with`` blocks close their
writers (MCAP summary and footer, JSON lines, PNG folders, mp4), and the CLI exits 130
("interrupted"). A second SIGTERM while they finish is ignored.
"""

from __future__ import annotations

import argparse
import functools
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from arlight.client.stop_signals import interrupt


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM and SIGINT raise KeyboardInterrupt inside the block, between records (main
    thread only; elsewhere a no-op, as signal handlers can only be set there)."""
    try:
        previous = {s: signal.signal(s, interrupt) for s in (signal.SIGTERM, signal.SIGINT)}
    except ValueError:  # not the main thread (a library call from a worker)
        yield
        return
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def finalised_on_sigterm(run: Callable[[argparse.Namespace], int]) -> Callable[..., int]:
    """A subcommand's run(args) under :func:`terminate_as_interrupt`."""

    @functools.wraps(run)
    def wrapped(args: argparse.Namespace) -> int:
        with terminate_as_interrupt():
            return run(args)

    return wrapped
