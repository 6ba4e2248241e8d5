"""SIGTERM finalises like Ctrl-C: what `docker stop`, systemd and `timeout` send.

Python's default for SIGTERM ends the process at once, so an MCAP without its summary, a
display's 0-byte recording or an unflushed results file was all a stopped client left
(issue 34). Inside :func:`terminate_as_interrupt` SIGTERM raises KeyboardInterrupt in the
main thread instead, the path Ctrl-C takes: each command's ``finally`` and ``with`` blocks
close their writers (MCAP summary and footer, JSON lines, PNG folders, mp4), and the CLI
exits 130 ("interrupted"). A second SIGTERM while they finish is ignored.
"""

from __future__ import annotations

import argparse
import functools
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType


def _interrupt(signum: int, _frame: FrameType | None) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # once: the writers finish undisturbed
    raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt inside the block (main thread only; elsewhere a
    no-op, as signal handlers can only be set there)."""
    try:
        previous = signal.signal(signal.SIGTERM, _interrupt)
    except ValueError:  # not the main thread (a library call from a worker)
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def finalised_on_sigterm(run: Callable[[argparse.Namespace], int]) -> Callable[..., int]:
    """A subcommand's run(args) under :func:`terminate_as_interrupt`."""

    @functools.wraps(run)
    def wrapped(args: argparse.Namespace) -> int:
        with terminate_as_interrupt():
            return run(args)

    return wrapped
