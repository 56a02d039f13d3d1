"""How serve, router and worker are asked to stop (``orchestrator.signals``): SIGTERM, and SIGINT unless
they were started ignoring it (a script's background job)."""

from __future__ import annotations

import os
import signal
import threading

from orchestrator.signals import on_stop_signals
from tests.conftest import free_port, wait_for
from tests.orchestrator.test_router import start, start_plain_router
from tests.orchestrator.test_service_worker import signal_masks


def bit(sig: int) -> int:
    return 1 << (sig - 1)


def test_sigterm_and_sigint_call_the_handler_and_restore_puts_the_old_ones_back() -> None:
    calls: list[int] = []
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    restore = on_stop_signals(lambda: calls.append(1))
    try:
        for sig in (signal.SIGTERM, signal.SIGINT):
            os.kill(os.getpid(), sig)
        wait_for(lambda: len(calls) == 2, message="both signals handled")
    finally:
        restore()
    assert {s: signal.getsignal(s) for s in before} == before


def test_a_sigint_ignored_at_start_stays_ignored() -> None:
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        restore = on_stop_signals(lambda: None)
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, signal.SIG_IGN)
        restore()
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    finally:
        signal.signal(signal.SIGINT, old)


def test_outside_the_main_thread_nothing_is_installed() -> None:
    before = signal.getsignal(signal.SIGTERM)
    out: list = []
    t = threading.Thread(target=lambda: out.append(on_stop_signals(lambda: None)))
    t.start()
    t.join()
    assert signal.getsignal(signal.SIGTERM) == before
    out[0]()  # (restore is a no-op there)


def test_a_router_started_ignoring_sigint_keeps_ignoring_it_and_stops_on_sigterm() -> None:
    """As ``activecollect router`` (and ``serve``, the same function) in a script's background."""
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)  # inherited across exec, as from such a parent
    try:
        ignoring = start("--listen", f"tcp/127.0.0.1:{free_port()}")
    finally:
        signal.signal(signal.SIGINT, old)
    plain = start_plain_router((f"tcp/127.0.0.1:{free_port()}",))
    try:
        for p in (ignoring, plain):  # (it prints its ready line after its handlers are in place)
            wait_for(lambda: signal_masks(p.popen.pid)[1] & bit(signal.SIGTERM), message="SIGTERM handled")
        ignored, caught = signal_masks(ignoring.popen.pid)
        assert ignored & bit(signal.SIGINT) and not caught & bit(signal.SIGINT)
        ignored, caught = signal_masks(plain.popen.pid)
        assert caught & bit(signal.SIGINT) and not ignored & bit(signal.SIGINT)
        ignoring.popen.send_signal(signal.SIGINT)  # ignored: still routing
        plain.popen.send_signal(signal.SIGINT)
        assert plain.popen.wait(15) == 0, plain.output()
        assert ignoring.popen.poll() is None
        ignoring.popen.send_signal(signal.SIGTERM)
        assert ignoring.popen.wait(15) == 0, ignoring.output()
    finally:
        ignoring.stop()
        plain.stop()
