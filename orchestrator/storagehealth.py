"""What the service knows of its storage: whether writes fail for now, and which reads do.

A *write* refused for a reason that passes (a full disk, a lock held past the busy timeout) means no
worker can renew either: no lease may expire until writes work again, and then every live lease gets a
full term first. The service's reaper does both, asking ``StorageHealth.down_since``.

A failed *read* (the metrics' gauges, the planner's scorer, the queue's depth) changed nothing and kept no
worker from renewing, so it holds no lease: it is a warning, said at most once per ``warn_every_s`` for
each thing read (with the number of failures in between), and a line when that read works again.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TypeVar

from storage.errors import StorageError, StorageUnavailableError

T = TypeVar("T")


class StorageHealth:
    """Write outages and failing reads, each said once (reads again after ``warn_every_s``); thread-safe."""

    def __init__(self, log: logging.Logger, warn_every_s: float = 60.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = log
        self._warn_every_s = warn_every_s
        self._clock = clock
        self._lock = threading.Lock()
        self._reads: dict[str, tuple[float, int]] = {}  # what -> (when last warned, failures not warned of)
        self.down_since: float | None = None
        """When a write first failed with the storage unavailable (``clock``); None while writes work."""

    def write_failed(self, exc: StorageUnavailableError) -> None:
        """The storage refused a write for a reason that passes: no lease expires until ``writes_work``."""
        with self._lock:
            first = self.down_since is None
            if first:
                self.down_since = self._clock()
        if first:  # said once per outage, not once a second
            self._log.error("storage unavailable: %s; leases will not expire and uploads are refused as "
                            "'unavailable' (workers keep their episodes and retry) until it is back", exc)

    def writes_work(self) -> float:
        """A write went through: the outage (if any) is over. Returns how long it lasted (0.0: there was none)."""
        with self._lock:
            since, self.down_since = self.down_since, None
        return 0.0 if since is None else self._clock() - since

    def read(self, what: str, fn: Callable[[], T]) -> T | None:
        """``fn()``, which only reads (``what``); None when it fails. A StorageError is ``read_failed``'s warning;
        anything else is logged with its traceback (a bug in a planner or a gauge must not stop the thread
        that called it: ingest, the reaper)."""
        try:
            value = fn()
        except StorageError as exc:
            self.read_failed(what, exc)
            return None
        except Exception:  # noqa: BLE001 -- see the docstring; it is logged
            self._log.exception("reading %s failed", what)
            return None
        self.read_worked(what)
        return value

    def read_failed(self, what: str, exc: StorageError) -> None:
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
