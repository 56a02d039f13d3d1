"""``RoundPlanner``: the service's planner in lockstep rounds, for ``activecollect run`` (``orchestrator.loop``)."""

from __future__ import annotations

import threading
from typing import Callable, Sequence

from orchestrator.planner import Planner
from storage.records import Episode
from storage.requests import NewRequest


class RoundPlanner:
    """Lockstep rounds for the service: collect a round, retrain, then plan the next round.

    The service calls ``plan`` for every stored episode (in its background thread);
    this only keeps the round's episodes. ``release`` (called when a retrain has
    finished, so the freshest champion scores them) asks the inner planner for the
    next round and fills it up to ``round_episodes`` with uniform requests. Requests
    never exceed what is left of ``budget``: workers idle while the model retrains,
    which is what lets each round be planned by the model the previous rounds made.
    """

    def __init__(self, inner: Planner, round_episodes: int, budget: int, collected: Callable[[], int],
                 outstanding: Callable[[], int]) -> None:
        self.inner = inner
        self.name = inner.name
        self.round_episodes = round_episodes
        self.budget = budget
        self.collected = collected
        self.outstanding = outstanding
        self._buffer: list[Episode] = []
        self._lock = threading.Lock()

    def seed(self, n: int, why: str = "seed") -> list[NewRequest]:
        return self.inner.seed(min(n, self._room()), why)

    def observe(self, episodes: Sequence[Episode]) -> None:
        self.inner.observe(episodes)

    def plan(self, new_episodes: Sequence[Episode], limit: int | None = None) -> list[NewRequest]:
        """Buffers the episodes for ``release``; plans nothing now."""
        with self._lock:
            self._buffer.extend(new_episodes)
            del self._buffer[:-self.round_episodes]  # a round's worth is all a plan looks at
        return []

    def has_episodes(self) -> bool:
        with self._lock:
            return bool(self._buffer)

    def remember(self, episodes: Sequence[Episode]) -> None:
        """Put episodes back in the buffer (a resumed run plans from the catalog's latest)."""
        self.plan(episodes)

    def _room(self) -> int:
        return max(0, min(self.round_episodes, self.budget - self.collected() - self.outstanding()))

    def release(self, limit: int | None = None) -> list[NewRequest]:
        """The next round's requests: planned from the buffered episodes, topped up uniformly.

        ``limit``: at most this many (the rest of a round that a dead or cancelled request left short).
        """
        with self._lock:
            episodes, self._buffer = self._buffer, []
        room = self._room() if limit is None else min(self._room(), max(0, limit))
        if room == 0:
            return []
        planned = self.inner.plan(episodes, limit=room) if episodes else []  # (not a cut: the planner
        # remembers what it returns, and keeps its next candidates away from those states)
        return planned + self.inner.seed(room - len(planned))
