"""Blocking calls a worker can walk away from: a second stop signal must not wait out a query in flight.

``Abandoner.run(fn)`` calls ``fn`` on a thread of its own and waits for it; ``abandon()`` (from any
other thread) ends that wait at once, and every later ``run``, with ``Abandoned``. The abandoned
call goes on in the background (a daemon thread) and its outcome is dropped: a query the service
answers after all is the service's to settle (an upload it stored stays stored; a release that
follows finds the request done and is refused).

Imports only the wire contract (``orchestrator.transport``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TypeVar

from orchestrator import transport

T = TypeVar("T")


class Abandoned(transport.TransportError):
    """A call given up on while in flight (or not started): ``Abandoner.abandon`` was called."""


class Abandoner:
    """Runs one blocking call at a time for one caller thread; see the module docstring."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._abandoned = False
        self._waiting: threading.Event | None = None

    @property
    def abandoned(self) -> bool:
        return self._abandoned

    def abandon(self) -> None:
        """Wake the call being waited for, and refuse every later one. Not from a signal handler (a lock)."""
        with self._lock:
            self._abandoned = True
            if self._waiting is not None:
                self._waiting.set()

    def run(self, fn: Callable[[], T], name: str) -> T:
        """``fn()``'s result, or what it raised; raises ``Abandoned`` once ``abandon`` is called first."""
        done = threading.Event()
        outcome: list[tuple[bool, object]] = []
        with self._lock:
            if self._abandoned:
                raise Abandoned(f"{name}: not sent: giving the request back")
            self._waiting = done

        def call() -> None:
            try:
                outcome.append((True, fn()))
            except Exception as exc:  # noqa: BLE001 -- handed to the waiting caller, who raises it
                outcome.append((False, exc))
            done.set()

        threading.Thread(target=call, name=f"call:{name}", daemon=True).start()
        done.wait()
        with self._lock:
            self._waiting = None
        if not outcome:  # woken by abandon(): an outcome that came at the same time is kept (below)
            raise Abandoned(f"{name}: given up while in flight: giving the request back")
        ok, value = outcome[0]
        if ok:
            return value  # type: ignore[return-value]
        raise value  # type: ignore[misc]
