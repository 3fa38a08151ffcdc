"""Test-side guards: fail a block that hangs instead of hanging the test run."""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator

__all__ = ["Hang", "deadline"]


class Hang(BaseException):
    """Raised by :func:`deadline` (a BaseException, so no ``except Exception`` can swallow it)."""


@contextlib.contextmanager
def deadline(seconds: float = 10.0) -> Iterator[None]:
    """Raise :class:`Hang` if the block runs longer than ``seconds`` (SIGALRM interrupts blocking I/O)."""

    def on_alarm(signum: int, frame: object) -> None:
        raise Hang(f"still running after {seconds} s: the reader hangs")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
