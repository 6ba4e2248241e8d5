"""The error of recorded data that cannot be read, and the bridge from `arlight.core.checks`."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from arlight.core.checks import CheckError


class DatasetError(ValueError):
    """Recorded RGB-D data that cannot be read; the message names the file and what to do."""


@contextmanager
def dataset_errors(hint: str = "") -> Iterator[None]:
    """Turn a `CheckError` raised inside into a DatasetError with the same text.

    Readers pass the file (and line) as the check's field, so the message names it; `hint`
    (what to do) is appended.
    """
    try:
        yield
    except CheckError as exc:
        raise DatasetError(f"{exc}; {hint}" if hint else str(exc)) from None
