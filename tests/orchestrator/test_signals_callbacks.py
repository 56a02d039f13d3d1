"""A signal whose handler raises (``bench loop``'s SIGTERM, its arms' too, Ctrl-C's KeyboardInterrupt), landing while
the main thread runs Python code that a C library called back: raised there, the exception is printed and dropped
(a ``bench loop`` went on until it was SIGKILLed), or, in pymunk's finalizers, leaves Chipmunk half updated (a
segfault). ``put_off`` sends the signal again once the thread is out of pymunk's callbacks, and one lost in another
callback (a weakref's) is sent again too: it is raised where it can unwind."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import time
import weakref
from collections.abc import Callable

import pymunk
import pytest

from orchestrator.signals import Terminated, ctrl_c_put_off, interrupt_put_off, put_off, sigterm_raises
from tests.conftest import REPO, ignoring_sigint, wait_for


#: The handlers that raise: the context that installs one, its signal, what it raises.
RAISING = pytest.mark.parametrize("handled, sig, expected", [
    (sigterm_raises, signal.SIGTERM, Terminated),
    (ctrl_c_put_off, signal.SIGINT, KeyboardInterrupt),
], ids=["bench-loop-sigterm", "ctrl-c"])


def _raised_in_pymunk_callback(sig: int) -> tuple[BaseException | None, int]:
    """Steps a space whose body's velocity function (called from Chipmunk) sends ``sig`` to this process on its
    first call, so that the handler runs inside the callback: (what reached the stepping loop within 30 s, how many
    steps were taken after the signal was sent)."""
    space = pymunk.Space()
    body = pymunk.Body(1.0, 1.0)
    space.add(body, pymunk.Circle(body, 1.0))
    sent: list[int] = []

    def velocity(body: pymunk.Body, gravity: object, damping: float, dt: float) -> None:
        if not sent:
            signal.raise_signal(sig)  # (the handler runs at this frame's next bytecode: inside the callback)
        sent.append(1)
        pymunk.Body.update_velocity(body, gravity, damping, dt)

    body.velocity_func = velocity
    deadline = time.monotonic() + 30.0
    try:
        while time.monotonic() < deadline:
            space.step(0.01)
    except BaseException as exc:  # noqa: BLE001 -- what the handler raised, whatever it is
        return exc, len(sent)
    return None, len(sent)


@RAISING
def test_a_signal_inside_a_pymunk_callback_is_raised_once_the_main_thread_is_out_of_it(
        handled: Callable[[], contextlib.AbstractContextManager], sig: int, expected: type[BaseException]) -> None:
    with handled():
        exc, steps = _raised_in_pymunk_callback(sig)
    assert isinstance(exc, expected), f"nothing raised in {steps} steps after the signal: it was lost"


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
@RAISING
def test_a_signal_lost_in_a_callback_python_only_reports_is_raised_again(
        handled: Callable[[], contextlib.AbstractContextManager], sig: int, expected: type[BaseException]) -> None:
    """A weakref's callback (as the garbage collector runs them, at any allocation): the exception raised there is
    not reported as "Exception ignored" (pytest would fail the test); its signal comes again, and is raised."""
    class Thing:
        pass

    called: list[int] = []

    def gone(_ref: weakref.ref) -> None:
        called.append(1)
        signal.raise_signal(sig)  # (its handler runs as this returns: inside the callback)

    thing = Thing()
    ref = weakref.ref(thing, gone)
    with handled(), pytest.raises(expected):
        del thing  # (the callback runs now)
        wait_for(lambda: False, message=f"{expected.__name__} raised again")
    assert ref() is None and called == [1]


def test_put_off_is_false_outside_pymunk() -> None:
    """(The handler raises at once: no second signal is sent.)"""
    assert put_off(signal.SIGTERM, sys._getframe()) is False


def test_sigterm_while_a_process_builds_pymunk_worlds_stops_it_every_time() -> None:
    """A process that builds and frees pymunk worlds in a loop, as an arm collecting does (its finalizers run
    at any allocation), SIGTERMed again and again at random moments: every signal reaches the loop as
    Terminated, and the process neither loses one nor crashes."""
    child = """
import os, random, signal, threading, time
import numpy as np
from orchestrator.signals import Terminated, sigterm_raises
from workers.env import PushSim, sample_state
rng, sim, caught = np.random.default_rng(0), PushSim(16), 0
with sigterm_raises():
    for trial in range(150):
        deadline = time.monotonic() + 10.0
        try:  # (the timer's signal may come before its start returns)
            threading.Timer(random.uniform(0.0, 0.02), os.kill, (os.getpid(), signal.SIGTERM)).start()
            while time.monotonic() < deadline:
                sim.reset(sample_state(rng))
                sim.step(8.0, 8.0)
        except Terminated:
            caught += 1
print("caught", caught)
"""
    proc = subprocess.run([sys.executable, "-X", "faulthandler", "-c", child], cwd=REPO, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["caught", "150"], proc.stderr[-2000:]


def test_ctrl_c_put_off_leaves_an_ignored_sigint_and_one_set_inside_the_block_alone() -> None:
    """A process started ignoring SIGINT keeps ignoring it; one that ignores it to exit (``ignore_while_exiting``)
    inside the block is not given Python's handler back after it."""
    with ignoring_sigint():
        with ctrl_c_put_off():
            assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    with ctrl_c_put_off():
        assert signal.getsignal(signal.SIGINT) is interrupt_put_off
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    with ctrl_c_put_off():
        pass
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
