"""Which workers are alive (their liveliness tokens ``NS/workers/<id>``), and the grace a lost one gets before its
leases go back to the queue.

A token that disappears is not always a worker that is gone: when a Zenoh router restarts or a link blips, every
worker's token goes and comes back a second or two later, each worker still collecting the episode it leased
(its renewals go unanswered meanwhile, which it takes as transient). Released at once, each of those requests
would be queued again and each worker's upload refused as stale. So ``Presence`` notes each loss with the time
its grace runs out, in one heap for all of them (a fleet lost at once is one structure, no thread per loss); the
service's maintenance thread asks it which lost workers' graces are over (``pop_due``) and releases their leases
then, unless the token came back meanwhile. A grace of 0 releases at once. Lease expiry is not touched: a worker
away for longer than its lease term loses the lease that way.

Thread-safe: tokens change on Zenoh's threads, graces run out on the service's maintenance thread.
"""

from __future__ import annotations

import heapq
import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence

from storage.requests import Request

log = logging.getLogger("orchestrator.service")  # the service's lines, where an operator looks for them


class Presence:
    """The workers whose tokens are alive now, and the lost ones whose grace still runs.

    ``gauge(n)`` is told the number alive after every change (under the lock, so in order); ``release(worker_id)``
    releases a lost worker's leases (``release_due`` calls it once its grace is over); ``leased()`` lists the
    leased requests (``say_back`` counts each worker's; None when they cannot be read now)."""

    def __init__(self, grace_s: float, *, gauge: Callable[[int], None], release: Callable[[str], None],
                 leased: Callable[[], Sequence[Request] | None], clock: Callable[[], float] = time.monotonic) -> None:
        self.grace_s = grace_s
        self._gauge, self._release, self._leased, self._clock = gauge, release, leased, clock
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._away: dict[str, float] = {}
        """Lost workers whose leases are still theirs: when each one's token went (by ``clock``)."""
        self._due: list[tuple[float, str, float]] = []
        """A heap of (when the grace runs out, worker id, when its token went): the earliest first. An entry whose
        worker came back, or was lost again since, is stale and skipped."""
        self._back: list[tuple[str, float]] = []
        """Workers back within their grace and how long each was away, until ``say_back`` says so."""

    def alive(self) -> list[str]:
        """Ids of the workers whose token is alive now, sorted."""
        with self._lock:
            return sorted(self._alive)

    def is_alive(self, worker_id: str) -> bool:
        with self._lock:
            return worker_id in self._alive

    def pending(self) -> int:
        """Graces not yet looked at by ``pop_due`` (stale ones included)."""
        with self._lock:
            return len(self._due)

    def joined(self, worker_id: str) -> bool:
        """A token came, or came back. True when it came back within its grace and is the first such since the last
        ``say_back``: the caller then has ``say_back`` run (once for a whole fleet back at once)."""
        with self._lock:
            self._alive.add(worker_id)
            self._gauge(len(self._alive))
            lost_at = self._away.pop(worker_id, None)
            if lost_at is None:
                return False
            self._back.append((worker_id, self._clock() - lost_at))
            return len(self._back) == 1

    def left(self, worker_id: str) -> None:
        """A token went: its grace starts now."""
        with self._lock:
            self._alive.discard(worker_id)
            self._gauge(len(self._alive))
            now = self._clock()
            self._away[worker_id] = now
            heapq.heappush(self._due, (now + self.grace_s, worker_id, now))

    def next_due(self) -> float:
        """When the earliest grace runs out (by ``clock``); inf when none runs."""
        with self._lock:
            return self._due[0][0] if self._due else math.inf

    def release_due(self) -> None:
        """Releases the leases of each lost worker whose grace is over and whose token has not come back."""
        while (worker_id := self._pop_due()) is not None:
            self._release(worker_id)

    def _pop_due(self) -> str | None:
        with self._lock:
            now = self._clock()
            while self._due and self._due[0][0] <= now:
                _, worker_id, lost_at = heapq.heappop(self._due)
                if self._away.get(worker_id) == lost_at:
                    del self._away[worker_id]
                    return worker_id
            return None

    def say_back(self) -> None:
        """One line for each worker that came back within its grace since the last call (one read for them all)."""
        with self._lock:
            back, self._back = self._back, []
        leased = self._leased() if back else None
        held = Counter(r.worker_id for r in leased or ())
        for worker_id, away_s in back:
            log.info("worker %s back after %.1f s; its %s kept", worker_id, away_s,
                     "leases" if leased is None else f"{held[worker_id]} lease(s)")
