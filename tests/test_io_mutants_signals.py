"""io.signals tests, in process (test_interruption.py kills real subprocesses, which mutmut cannot
trace): `Terminated` carries its signal, `termination_as_exception` raises it and restores the
previous handlers, and `_signals_held` delivers a held signal when its block ends."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from m3t1r.io.signals import Terminated, _signals_held, termination_as_exception


@pytest.mark.parametrize(("signum", "name"), [(signal.SIGTERM, "SIGTERM"), (signal.SIGHUP, "SIGHUP")])
def test_terminated_names_its_signal(signum, name):
    error = Terminated(signum)
    assert error.signum == signum
    assert str(error) == f"terminated by signal {name}"
    assert isinstance(error, BaseException) and not isinstance(error, Exception)


def test_termination_raises_inside_the_block_and_restores_handlers():
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGHUP)
    with pytest.raises(Terminated) as caught:
        with termination_as_exception():
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):  # the handler runs between bytecodes
                pass
    assert caught.value.signum == signal.SIGTERM
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGHUP)) == before


def test_a_signal_held_during_the_renames_arrives_after_them():
    events: list[str] = []
    with pytest.raises(Terminated):
        with termination_as_exception():
            with _signals_held():
                # Directed at this thread: the mask is per thread, and a process-directed signal
                # may go to a thread that does not block it (numpy's BLAS threads).
                signal.pthread_kill(threading.main_thread().ident, signal.SIGHUP)
                for _ in range(1000):
                    pass
                events.append("renamed")
            for _ in range(1000):
                pass
            events.append("not reached")
    assert events == ["renamed"]
