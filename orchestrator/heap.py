"""Handing the C heap's free memory back to the system, for a long-running process that scores.

glibc's malloc raises its mmap threshold each time a large block it had mapped is freed, so before
long the tensors of every scoring pass come from the heap instead, and the memory they free between
longer-lived small objects stays with the process. ``serve``'s resident memory grew 435 -> 564 MiB over
a 15-minute soak's 600 episodes that way (428 -> 442 MiB with this); ``serve``'s planner alone, fed the
same episodes in one process, 388 -> 521 MiB, and 379 -> 380 MiB with ``malloc_trim(0)`` after every
episode, which made it 0.79 as fast (~2 ms a trim, then the page faults of taking the memory back).
At most once a second it kept within 419 MiB at full speed (1.01), so ``HeapTrimmer`` trims at most
every ``interval_s``. Fixing the threshold instead (``MALLOC_MMAP_THRESHOLD_``) kept it flat too but
made planning 0.77 as fast: every pass mapped its buffers anew. BENCHMARKS.md, "The service's memory:
the heap handed back" (``bench/heap_trim.py``).

On a C library without ``malloc_trim`` (not glibc) it does nothing.
"""

from __future__ import annotations

import ctypes
import threading
import time
from typing import Callable

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
