"""Handing the C heap's free memory back to the system, for a long-running process that scores.

glibc's malloc raises its mmap threshold each time a large block it had mapped is freed, so before
long the tensors of every scoring pass come from the heap instead, and the memory they free between
longer-lived small objects stays with the process. ``serve``'s resident memory grew by ~130 MiB over
its first ~600 episodes that way (and levelled off there); the planner alone, fed the same episodes
in one process, grew 385 -> 531 MiB, and 379 -> 380 MiB with ``malloc_trim(0)`` after every episode.
Trimming costs ~2 ms, plus the page faults of taking the memory back, so ``HeapTrimmer`` does it at
most every ``interval_s`` (once a second in that loop: within 380-411 MiB, scoring 1-3 % slower).
Fixing the threshold instead (``MALLOC_MMAP_THRESHOLD_``) kept it flat too but made scoring 25 %
slower: every pass mapped its buffers anew. BENCHMARKS.md, "A soak with serve's thread settings".

On a C library without ``malloc_trim`` (not glibc) it does nothing.
"""

from __future__ import annotations

import ctypes
import logging
import threading
import time
from typing import Callable

log = logging.getLogger(__name__)

#: The service's trims are at least this many seconds apart.
TRIM_INTERVAL_S = 5.0


def _malloc_trim() -> Callable[[int], int] | None:
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # no C library to load, or not glibc
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


class HeapTrimmer:
    """``trimmer()`` gives free heap memory back (``malloc_trim(0)``) unless it did less than ``interval_s``
    ago; thread-safe. ``available`` is False where the C library has no ``malloc_trim``."""

    def __init__(self, interval_s: float = TRIM_INTERVAL_S, clock: Callable[[], float] = time.monotonic) -> None:
        if not interval_s >= 0:
            raise ValueError(f"interval_s must be >= 0, found {interval_s}")
        self.interval_s = interval_s
        self.clock = clock
        self.trims = 0
        """How many times it has trimmed."""
        self._trim = _malloc_trim()
        self._last = -float("inf")
        self._lock = threading.Lock()

    @property
    def available(self) -> bool:
        return self._trim is not None

    def __call__(self) -> bool:
        """Trim if it is due; True when it did."""
        if self._trim is None:
            return False
        with self._lock:
            now = self.clock()
            if now - self._last < self.interval_s:
                return False
            self._last = now
            self._trim(0)
            self.trims += 1
        return True
