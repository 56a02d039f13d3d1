"""A worker's first second: the stop and drain signals that come before its own handlers are in place.

``python -m workers.agent`` spends about a second importing (numpy, the simulator, MCAP, Zenoh) before
``Worker.install_signal_handlers``; until then SIGUSR1 would kill it, SIGTERM too, and SIGINT end it with a
traceback. ``guard()``, called before those imports, notes them instead, and ``taken()``, asked once the
worker's own handlers are in, says which came meanwhile: the worker then exits 0 without starting (it
holds no lease yet, so a supervisor or ``activecollect run`` draining a just-started worker loses nothing).

Imports only the standard library: it runs before anything heavy is imported.
"""

from __future__ import annotations

import signal

#: "Drain; if draining already, nothing": what ``activecollect run`` sends its workers to stop them.
DRAIN_SIGNAL = signal.SIGUSR1

_taken: list[int] = []  # appended to by the handler (on the main thread, between two bytecodes)


def guard() -> None:
    """Note SIGTERM, SIGINT (unless this process was started ignoring it: it stays ignored, as
    ``orchestrator.signals`` keeps it) and DRAIN_SIGNAL from now on, instead of dying of them.
    Main thread only; the worker's own handlers replace these."""
    for sig in (signal.SIGTERM, signal.SIGINT, DRAIN_SIGNAL):
        if sig == signal.SIGINT and signal.getsignal(sig) == signal.SIG_IGN:
            continue
        signal.signal(sig, _note)


def taken() -> list[signal.Signals]:
    """The signals ``guard`` noted, in the order they came (none where it was never called)."""
    return [signal.Signals(number) for number in _taken]


def _note(signum: int, frame: object) -> None:
    _taken.append(signum)
