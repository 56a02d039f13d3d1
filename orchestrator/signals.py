"""How our long-running processes (``serve``, ``router``, ``worker``, ``run``) are asked to stop, and how a command
that only computes (``bench loop``) takes a supervisor's SIGTERM as it takes Ctrl-C (``sigterm_raises``).

SIGTERM, and SIGINT unless the process was started ignoring it. A shell starts a script's
background jobs with SIGINT ignored (a terminal's Ctrl-C is not theirs), an ignored signal stays
ignored across exec, and Python then installs no KeyboardInterrupt handler of its own; our
processes keep to the same, so a SIGINT their parent ignores does not stop them either (e.g. the
workers of an ``activecollect run`` started in a script's background). A supervisor stops them
with SIGTERM either way.

The stop callback never runs inside the signal handler. Python runs a handler on the main thread
between two bytecodes, wherever that thread was, maybe inside ``Event.wait`` holding the Event's
lock; a callback that took the same lock there (``Event.set``) would wait on its own thread for
ever. So the signal only wakes a watcher thread, through ``signal.set_wakeup_fd`` (written by
the C-level handler, which takes no lock and does not wait for the main thread to reach a
bytecode), and the watcher thread calls the callback, once per signal it is told of.

Imports nothing of ours: workers use it too.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from collections.abc import Iterable, Iterator, Mapping
from typing import Callable

log = logging.getLogger(__name__)


def on_stop_signals(handler: Callable[[], None], sigint: bool = True,
                    also: Mapping[signal.Signals, Callable[[], None]] | None = None) -> Callable[[], None]:
    """Calls ``handler`` on SIGTERM and on SIGINT, unless SIGINT is ignored when this is called (as it is in
    a process started ignoring it, before anything of ours installs a handler): then it stays ignored.
    ``sigint=False``: SIGTERM alone (the caller keeps Python's KeyboardInterrupt for Ctrl-C). ``also``: other
    signals and their handlers, taken the same way (a worker's drain signal).

    ``handler`` runs on a thread of its own ("stop-signals"), one call per signal (two signals that
    arrive before the first is handled may count as one); it may take locks. Returns a function that
    puts the previous handlers (and the previous ``signal.set_wakeup_fd``) back and ends that thread:
    restore in the reverse order of installing. Outside the main thread, where Python takes no signal
    handlers, it installs nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    handlers = {int(signal.SIGTERM): handler}
    if sigint and signal.getsignal(signal.SIGINT) != signal.SIG_IGN:
        handlers[int(signal.SIGINT)] = handler
    handlers |= {int(sig): call for sig, call in (also or {}).items()}
    sigs = [signal.Signals(number) for number in handlers]
    read_fd, write_fd = os.pipe()  # (not inherited by child processes)
    os.set_blocking(write_fd, False)  # set_wakeup_fd's demand: a signal must never wait on a full pipe

    def watch() -> None:
        while data := os.read(read_fd, 64):  # b"": restore closed the write end
            for signum in data:  # the number of every signal Python has a handler for, ours or not
                if signum in handlers:
                    try:
                        handlers[signum]()
                    except Exception:  # noqa: BLE001 -- the next signal must still be heard
                        log.exception("stop-signal handler failed")
        os.close(read_fd)

    threading.Thread(target=watch, name="stop-signals", daemon=True).start()
    previous = {sig: signal.getsignal(sig) for sig in sigs}
    # The wake-up fd before the handlers: a signal between the two then reaches the watcher (and a handler there
    # was, e.g. workers.startup's); the other way round it would reach only _noted, and be lost.
    previous_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    # The Python-level handler does nothing: the C-level one has written the wake-up byte already.
    for sig in sigs:
        signal.signal(sig, _noted)
    restored = False

    def restore() -> None:
        nonlocal restored
        if restored:
            return
        restored = True
        for sig, old in previous.items():
            signal.signal(sig, old)
        signal.set_wakeup_fd(previous_fd)
        os.close(write_fd)  # after set_wakeup_fd: no handler writes to it any more
    return restore


def _noted(signum: int, frame: object) -> None:
    """The Python-level handler of a signal taken here: nothing, and so no lock (see the module's docstring)."""


def ignore_while_exiting(sigs: Iterable[signal.Signals]) -> None:
    """Ignore ``sigs`` from now on, for a process whose work is done and that only exits (main thread only).

    Python's shutdown puts the default disposition back for every signal that has a Python handler, so
    a stop signal in a process's last milliseconds (systemd's SIGTERM to the group, just as the process
    finished on its own) would kill it: exit -15, not the status it returned. An ignored signal stays
    ignored through the shutdown. A process that then hangs in its shutdown needs SIGKILL, as any hung
    process does.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in sigs:
        signal.signal(sig, signal.SIG_IGN)


class Terminated(BaseException):
    """SIGTERM, raised in the main thread inside ``sigterm_raises``. A BaseException, as KeyboardInterrupt is, so
    that no ``except Exception`` takes it for an error of the work it stopped."""


@contextlib.contextmanager
def sigterm_raises() -> Iterator[None]:
    """Within the block SIGTERM raises Terminated in the main thread, as SIGINT raises KeyboardInterrupt, so that
    a command's ``except`` and ``finally`` clauses run on a supervisor's stop (``kill PID``, a timeout's) as
    they do on Ctrl-C. The previous handler is back after the block.

    For a command whose main thread only computes and waits on its children (``bench loop``): the exception
    comes wherever that thread is, as KeyboardInterrupt does. The services above use ``on_stop_signals``
    instead, which never interrupts their main thread. Outside the main thread it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def raise_terminated(signum: int, frame: object) -> None:
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
