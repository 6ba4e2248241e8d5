"""Stop signals that never cut a record in half: `interrupt` (the SIGTERM / SIGINT handler
the CLI installs, arlight.cli.stop_signals) raises KeyboardInterrupt in the main thread,
except inside `uninterrupted()` blocks (a Recorder writing one MCAP record, which the mcap
writer does in several file writes), where it waits for the block's end. So the summary
that `Recorder.close()` writes on the way out always follows whole records.

After the first signal a second SIGTERM is ignored (the writers finish); a second Ctrl-C
(SIGINT) interrupts as Python's default does.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

_state = threading.local()  # depth of uninterrupted blocks and a deferred signal, per thread


def _depth() -> int:
    return getattr(_state, "depth", 0)


def _stop(signum: int) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")


def interrupt(signum: int, _frame: FrameType | None) -> None:
    """A signal handler: KeyboardInterrupt now, or at the end of the uninterrupted block."""
    if _depth():
        _state.pending = signum
        return
    _stop(signum)


@contextmanager
def uninterrupted() -> Iterator[None]:
    """A stop signal during the block takes effect when it ends (blocks may nest)."""
    _state.depth = _depth() + 1
    try:
        yield
    finally:
        _state.depth -= 1
        pending = getattr(_state, "pending", None)
        if _state.depth == 0 and pending is not None:
            _state.pending = None
            _stop(pending)
