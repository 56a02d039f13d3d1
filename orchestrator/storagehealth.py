"""What the service knows of its storage: whether writes fail for now, and which reads do.

A *write* refused for a reason that passes (a full disk, a lock held past the busy timeout) means no
worker can renew either: no lease may expire until writes work again, and then every live lease gets a
full term first. The service's reaper does both, asking ``StorageHealth.down_since``. Every write of the
service (a lease, a renew, a fail, an upload's ingest, an operator's queue change, the reaper's own) runs
inside ``writing``, so an outage any one of them meets counts, not only the one a renew happens to meet
(an upload refused ``unavailable`` after its worker's renewals had waited behind it, say). Only the
reaper ends an outage (``writes_work``), with the write that gives the live leases their full term: a
write that worked elsewhere ends nothing, or the leases no worker could renew meanwhile would expire.
So an outage only the episode files meet (their disk is full, the catalog's is not) ends at every reap
and begins again at the next upload: it is said (and its end) at most once per ``warn_every_s``.

A failed *read* (the metrics' gauges, the planner's scorer, the queue's depth) changed nothing and kept no
worker from renewing, so it holds no lease: it is a warning, said at most once per ``warn_every_s`` for
each thing read (with the number of failures in between), and a line when that read works again.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

from storage.errors import StorageError, StorageUnavailableError

T = TypeVar("T")


class StorageHealth:
    """Write outages and failing reads, each said at most once per ``warn_every_s``; thread-safe."""

    def __init__(self, log: logging.Logger, warn_every_s: float = 60.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = log
        self._warn_every_s = warn_every_s
        self._clock = clock
        self._lock = threading.Lock()
        self._reads: dict[str, tuple[float, int]] = {}  # what -> (when last warned, failures not warned of)
        # outages: (when one was last said, how many ended unsaid since, whether the one now was said)
        self._outages: tuple[float | None, int, bool] = (None, 0, False)
        self.down_since: float | None = None
        """When a write first failed with the storage unavailable (``clock``); None while writes work."""

    def write_failed(self, exc: StorageUnavailableError) -> None:
        """The storage refused a write for a reason that passes: no lease expires until ``writes_work``.
        Said once per outage, not once per write; an outage that begins less than ``warn_every_s`` after the
        last one said is said once that much has passed, if it lasts (else it is counted, and the count said
        with the next one)."""
        now = self._clock()
        with self._lock:
            if self.down_since is None:
                self.down_since = now
            said, missed, this = self._outages
            if this or (said is not None and now - said < self._warn_every_s):
                return
            self._outages = (now, 0, True)
        more = f" ({missed} shorter outage(s) since the last said)" if missed else ""
        self._log.error("storage unavailable: %s%s; leases will not expire and uploads are refused as "
                        "'unavailable' (workers keep their episodes and retry) until it is back", exc, more)

    @contextmanager
    def writing(self) -> Iterator[None]:
        """Around a write: a ``StorageUnavailableError`` it raises, or an error raised from one (an admin op's
        wire refusal), is ``write_failed``'s, then raised on (the caller still refuses, or tries again later)."""
        try:
            yield
        except Exception as exc:
            unavailable = exc if isinstance(exc, StorageUnavailableError) else exc.__cause__
            if isinstance(unavailable, StorageUnavailableError):
                self.write_failed(unavailable)
            raise

    def writes_work(self) -> float | None:
        """A write went through: the outage (if any) is over. Returns how long it lasted, to be said; None when
        there was none, or it was not said either (``write_failed``)."""
        with self._lock:
            since, self.down_since = self.down_since, None
            said, missed, this = self._outages
            self._outages = (said, missed + (since is not None and not this), False)
        return None if since is None or not this else self._clock() - since

    def read(self, what: str, fn: Callable[[], T]) -> T | None:
        """``fn()``, which only reads (``what``); None when it fails. A StorageError is ``read_failed``'s warning;
        anything else is logged with its traceback (a bug in a planner or a gauge must not stop the thread
        that called it: ingest, the reaper)."""
        try:
            value = fn()
        except StorageError as exc:
            self.read_failed(what, exc)
            return None
        except Exception as exc:  # noqa: BLE001 -- see the docstring; it is logged
            self._raised(what, exc)
            return None
        self.read_worked(what)
        return value

    def _raised(self, what: str, exc: Exception) -> None:
        """Reading ``what`` raised something other than a StorageError (a bug in a planner or a gauge): its traceback
        the first time, then ``read_failed``'s warning at most every ``warn_every_s`` while it goes on failing."""
        with self._lock:
            first = what not in self._reads
            if first:
                self._reads[what] = (self._clock(), 0)
        if first:
            self._log.error("reading %s failed (its traceback once; while it goes on failing, a line at most every "
                            "%g s)", what, self._warn_every_s, exc_info=exc)
        else:
            self.read_failed(what, f"{type(exc).__name__}: {exc}")

    def read_failed(self, what: str, exc: StorageError | str) -> None:
        """Reading ``what`` failed: a warning, unless one for ``what`` was given less than ``warn_every_s`` ago."""
        now = self._clock()
        with self._lock:
            warned, missed = self._reads.get(what, (None, 0))
            if warned is not None and now - warned < self._warn_every_s:
                self._reads[what] = (warned, missed + 1)
                return
            self._reads[what] = (now, 0)
        more = f" ({missed} more failure(s) since the last warning)" if missed else ""
        self._log.warning("cannot read %s: %s%s; nothing was changed and leases run as usual (said at most "
                          "every %g s while it fails)", what, exc, more, self._warn_every_s)

    def read_worked(self, what: str) -> None:
        """Reading ``what`` worked: says so once if it had failed."""
        with self._lock:
            failed = self._reads.pop(what, None)
        if failed is not None:
            self._log.info("reading %s works again", what)
