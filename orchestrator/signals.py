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

The handlers that do raise (``sigterm_raises``, and Ctrl-C's KeyboardInterrupt in the CLI, ``ctrl_c_put_off``)
raise nowhere the exception would be lost or break a C library's state: inside pymunk's callbacks and finalizers
the signal is put off (``put_off``), and one lost in a callback whose exceptions Python only reports is sent
again (``_lost_sent_again``).

Imports nothing of ours: workers use it too.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Iterable, Iterator, Mapping
from types import FrameType
from typing import Callable

log = logging.getLogger(__name__)

#: Where a C library calls our processes' Python code back: pymunk's callbacks (its ``_callbacks`` module, which
#: Chipmunk's iterators and a body's velocity and position functions go through) and its objects' finalizers
#: (``freebody``, ``shapefree``, ``spacefree``..., which the garbage collector runs at any allocation). An exception
#: a signal raises there is printed and dropped, or leaves Chipmunk half updated (``freebody``: a segfault), so a
#: raising handler puts it off (``put_off``). The rest of pymunk is Python called from Python, where it may raise.
CALLBACK_MODULES = frozenset({"pymunk._callbacks"})
CALLBACK_FINALIZERS = ("pymunk", "free")  # (a function of this package with this in its name)
#: How long a put-off signal waits before it is sent again.
PUT_OFF_S = 0.01


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


def put_off(signum: int, frame: FrameType | None) -> bool:
    """For a handler that raises (or exits): True when the main thread is in a callback of ``CALLBACK_MODULES`` or
    ``CALLBACK_FINALIZERS`` (or in what one called), where the exception would be lost or crash the process; the
    signal is then sent again ``PUT_OFF_S`` later, and the handler must return without raising. The handler runs
    again then, wherever the thread is by that time."""
    package, part = CALLBACK_FINALIZERS
    while frame is not None:
        module = str(frame.f_globals.get("__name__", ""))
        if module in CALLBACK_MODULES or (module.partition(".")[0] == package and part in frame.f_code.co_name):
            _send_later(signum)
            return True
        frame = frame.f_back
    return False


def _send_later(signum: int) -> None:
    threading.Timer(PUT_OFF_S, os.kill, (os.getpid(), signum)).start()


class Terminated(BaseException):
    """SIGTERM, raised in the main thread inside ``sigterm_raises``. A BaseException, as KeyboardInterrupt is, so
    that no ``except Exception`` takes it for an error of the work it stopped."""


#: What the raising handlers raise, and for which signal.
RAISED = ((Terminated, signal.SIGTERM), (KeyboardInterrupt, signal.SIGINT))


@contextlib.contextmanager
def _lost_sent_again() -> Iterator[None]:
    """Within the block, a ``RAISED`` exception that Python could only report (raised in a callback it calls and
    whose exceptions it drops: a weakref's, a ``__del__``, which the garbage collector runs at any allocation) is
    not reported: its signal is sent again ``PUT_OFF_S`` later, so that it is raised where it can unwind."""
    previous = sys.unraisablehook

    def hook(unraisable: sys.UnraisableHookArgs) -> None:
        for raised, signum in RAISED:
            if isinstance(unraisable.exc_value, raised):
                _send_later(signum)
                return
        previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        if sys.unraisablehook is hook:
            sys.unraisablehook = previous


def interrupt_put_off(signum: int, frame: FrameType | None) -> None:
    """Python's own SIGINT handler (KeyboardInterrupt), put off while the main thread is in a callback (``put_off``)."""
    if not put_off(signum, frame):
        signal.default_int_handler(signum, frame)


@contextlib.contextmanager
def ctrl_c_put_off() -> Iterator[None]:
    """Within the block, a SIGINT handled by Python's own handler is ``interrupt_put_off``'s, and a KeyboardInterrupt
    lost in a callback is raised again (``_lost_sent_again``): the CLI's, for the commands that simulate in their
    main thread (``collect``, ``bench loop --jobs 1``). An ignored SIGINT stays ignored, another handler stays;
    Python's own is back after the block, unless the block put in another (a process's ``ignore_while_exiting``).
    Outside the main thread, nothing."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return
    signal.signal(signal.SIGINT, interrupt_put_off)
    try:
        with _lost_sent_again():
            yield
    finally:
        if signal.getsignal(signal.SIGINT) is interrupt_put_off:
            signal.signal(signal.SIGINT, signal.default_int_handler)


@contextlib.contextmanager
def sigterm_raises() -> Iterator[None]:
    """Within the block SIGTERM raises Terminated in the main thread, as SIGINT raises KeyboardInterrupt, so that
    a command's ``except`` and ``finally`` clauses run on a supervisor's stop (``kill PID``, a timeout's) as
    they do on Ctrl-C. The previous handler is back after the block.

    For a command whose main thread only computes and waits on its children (``bench loop``): the exception
    comes wherever that thread is, as KeyboardInterrupt does, except in pymunk's callbacks (``put_off``); one
    lost in another callback is raised again (``_lost_sent_again``). The services above use ``on_stop_signals``
    instead, which never interrupts their main thread. Outside the main thread it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def raise_terminated(signum: int, frame: FrameType | None) -> None:
        if not put_off(signum, frame):
            raise Terminated()

    previous = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        with _lost_sent_again():
            yield
    finally:
        signal.signal(signal.SIGTERM, previous)
