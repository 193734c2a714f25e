"""Signals around writes: held back while outputs are renamed into place, and SIGTERM or SIGHUP
turned into an exception so that cleanup runs as for Ctrl-C."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Terminated", "deliver_signals", "signals_deferred", "termination_as_exception"]


@contextmanager
def signals_deferred() -> Iterator[list[int]]:
    """Hold SIGINT, SIGTERM, SIGHUP back within the block; yields the list of those that arrived,
    for the caller to `deliver_signals` when it is ready (after recording what it completed, say).

    Deferred by Python-level handlers, not by a signal mask: a mask holds signals for the calling
    thread only, and a process-directed `kill` may be taken by any of numpy's threads, after which
    Python runs the handler in the main thread anyway.
    """
    pending: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield pending
        return

    def defer(signum, frame):
        pending.append(signum)

    held = dict.fromkeys((signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", signal.SIGTERM)))
    previous = {signum: signal.signal(signum, defer) for signum in held}
    try:
        yield pending
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


def deliver_signals(pending: list[int]) -> None:
    """Raise the signals `signals_deferred` held back, each once, in arrival order."""
    for signum in dict.fromkeys(pending):
        signal.raise_signal(signum)


class Terminated(BaseException):
    """A SIGTERM or SIGHUP arrived; raised so that cleanup runs as for Ctrl-C."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f"terminated by signal {signal.Signals(signum).name}")


@contextmanager
def termination_as_exception() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise `Terminated` (SIGINT already raises
    KeyboardInterrupt), so `with OutputSet` blocks and `finally` clauses remove temporary files."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated(signum)

    previous = {}
    for signum in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if signum is not None:
            previous[signum] = signal.signal(signum, handler)
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)
