"""How serve, router and worker are asked to stop (``orchestrator.signals``): SIGTERM, and SIGINT unless they
were started ignoring it (a script's background job). The worker's case is in test_service_worker.py."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading

from orchestrator.signals import on_stop_signals
from tests.conftest import REPO, disposition, free_port, ignoring_sigint, wait_for
from tests.orchestrator.test_router import start, start_plain_router


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


def test_the_handler_runs_off_the_main_thread_and_restore_puts_the_wakeup_fd_back() -> None:
    threads: list[threading.Thread] = []
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    old_fd = signal.set_wakeup_fd(write_fd)
    try:
        restore = on_stop_signals(lambda: threads.append(threading.current_thread()), sigint=False)
        try:
            assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # sigint=False: left alone
            os.kill(os.getpid(), signal.SIGTERM)
            wait_for(lambda: threads, message="SIGTERM handled")
        finally:
            restore()
        assert threads[0] is not threading.main_thread() and threads[0].name == "stop-signals"
        assert signal.set_wakeup_fd(write_fd) == write_fd
    finally:
        signal.set_wakeup_fd(old_fd)
        os.close(read_fd)
        os.close(write_fd)


#: A process whose main thread takes and lets go of an Event's lock in a tight loop while another thread
#: SIGTERMs it: a stop callback run inside the signal handler (on the main thread) that sets the same
#: Event finds the lock held by the very thread it interrupted, and waits for ever (or, with the signals
#: still coming, recurses until RecursionError).
HAMMERED = """
import os, signal, sys, threading, time
from orchestrator.signals import on_stop_signals
stop, handled, sent = threading.Event(), [], []
on_stop_signals(lambda: (handled.append(1), stop.set()))
def send():
    for _ in range(2000):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.0005)
    sent.append(1)
threading.Thread(target=send, daemon=True).start()
while not sent:
    stop.wait(0)
    stop.clear()
print("survived", len(handled), flush=True)
"""


def test_a_signal_that_lands_while_the_main_thread_holds_the_events_lock_does_not_deadlock() -> None:
    proc = subprocess.run([sys.executable, "-c", HAMMERED], cwd=REPO, capture_output=True, text=True,
                          timeout=30, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert proc.returncode == 0 and proc.stdout.startswith("survived "), proc.stderr[-2000:]
    assert int(proc.stdout.split()[1]) > 0


def test_a_sigint_ignored_when_called_stays_ignored() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with ignoring_sigint():
        restore = on_stop_signals(lambda: None)
        try:
            assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, signal.SIG_IGN, before)
        finally:
            restore()
    assert signal.getsignal(signal.SIGTERM) == before


def test_outside_the_main_thread_nothing_is_installed() -> None:
    before = signal.getsignal(signal.SIGTERM)
    out: list = []
    t = threading.Thread(target=lambda: out.append(on_stop_signals(lambda: None)))
    t.start()
    t.join()
    assert signal.getsignal(signal.SIGTERM) == before
    out[0]()  # (restore is a no-op there)


def test_a_router_started_ignoring_sigint_keeps_ignoring_it_and_stops_on_sigterm() -> None:
    with ignoring_sigint():
        ignoring = start("--listen", f"tcp/127.0.0.1:{free_port()}")
    plain = start_plain_router((f"tcp/127.0.0.1:{free_port()}",))
    try:
        for p in (ignoring, plain):
            wait_for(lambda: disposition(p.popen.pid, signal.SIGTERM) == "caught", message="SIGTERM handled")
        assert disposition(ignoring.popen.pid, signal.SIGINT) == "ignored"
        assert disposition(plain.popen.pid, signal.SIGINT) == "caught"
        plain.popen.send_signal(signal.SIGINT)
        assert plain.popen.wait(15) == 0, plain.output()
        ignoring.popen.send_signal(signal.SIGTERM)
        assert ignoring.popen.wait(15) == 0, ignoring.output()
    finally:
        ignoring.stop()
        plain.stop()


def test_serve_started_ignoring_sigint_keeps_ignoring_it_and_stops_on_sigterm(spawn_service) -> None:
    with ignoring_sigint():
        ignoring = spawn_service(name="service-I")
    wait_for(lambda: "serving " in ignoring.log() or not ignoring.alive(), timeout=60, message="serve to start")
    assert ignoring.alive(), ignoring.log()
    assert disposition(ignoring.pid, signal.SIGTERM) == "caught"  # (it prints 'serving' after its handlers)
    assert disposition(ignoring.pid, signal.SIGINT) == "ignored"
    ignoring.signal(signal.SIGTERM)
    assert ignoring.wait(30) == 0, ignoring.log()
