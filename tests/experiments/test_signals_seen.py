"""A SIGTERM whose handler's exception Python loses is still seen (``ray_jobs.SignalsSeen``).

While ``ray.init`` runs, a SIGTERM that lands in an after-fork hook (``logging``'s, run each
time Ray starts one of its processes), a ``__del__`` or a weakref callback raises its
handler's exception where Python can only print "Exception ignored in ..." and go on: the
command went on training with the stop lost (one run in ten of the SIGTERM-during-start loop,
``tools/sigterm_ray_start.py``). Here the signal is sent from a ``__del__``, the same loss.
"""

from __future__ import annotations

import gc
import os
import signal
import sys

import pytest

from amuled_ma.errors import Terminated
from amuled_ma.experiments.ray_jobs import SignalsSeen


class SignalInDel:
    """Sends SIGTERM to this process from ``__del__``, where a raised exception is lost."""

    def __del__(self) -> None:
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # bytecode for the interpreter to run the handler in
            pass


def raise_terminated(signum: int, _frame: object) -> None:
    raise Terminated(signum)


@pytest.fixture
def lost(monkeypatch: pytest.MonkeyPatch) -> list[BaseException]:
    """SIGTERM raises Terminated; the exceptions Python loses (its unraisable hook) listed."""
    found: list[BaseException] = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: found.append(u.exc_value))
    previous = signal.signal(signal.SIGTERM, raise_terminated)
    yield found
    signal.signal(signal.SIGTERM, previous)


def test_a_lost_sigterm_is_seen_and_not_printed(lost: list[BaseException]) -> None:
    with SignalsSeen() as seen:
        SignalInDel()  # dropped at once: __del__ runs here, its Terminated is lost
        gc.collect()
    assert seen.numbers == {signal.SIGTERM}
    assert lost == []  # Python's "Exception ignored in ..." traceback is not printed
    assert sys.unraisablehook is not seen._unraisable  # the hook before is back


def test_without_it_the_exception_is_lost(lost: list[BaseException]) -> None:
    """The control: the same SIGTERM outside the block raises where Python loses it."""
    SignalInDel()
    gc.collect()
    assert [type(e) for e in lost] == [Terminated]


def test_other_lost_exceptions_still_reach_the_hook(lost: list[BaseException]) -> None:
    class Fails:
        def __del__(self) -> None:
            raise ValueError("x")

    with SignalsSeen() as seen:
        Fails()
    assert seen.numbers == set() and [type(e) for e in lost] == [ValueError]


def test_no_signal_no_number(lost: list[BaseException]) -> None:
    with SignalsSeen() as seen:
        pass
    assert seen.numbers == set()
    assert signal.set_wakeup_fd(-1) == -1  # the wakeup fd was put back (none before)
