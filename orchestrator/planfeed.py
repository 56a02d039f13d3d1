"""The service's planning side: stored episodes to the planner, the planner's requests to the queue.

``PlanFeed`` seeds an empty queue at start (``seed``), then on a thread of its own ("episodes") hands each
batch of stored episodes to the planner and to the ``on_episode`` callbacks, queues what the planner asks for,
and keeps the queue at its floor (``ServiceConfig.min_queued``) with the planner's seed draws, so that scoring
and planning never stall leasing. The planner only reads (its scorer: the catalog and the registry); the
feed's writes take the service's writer turn and are told to its storage health like any other.

Split from ``orchestrator.service``, which owns the Zenoh side (leases, uploads, admin) and starts and stops
this.
"""

from __future__ import annotations

import logging
import queue as queue_mod
import threading
from collections.abc import Callable, Sequence
from typing import Any, ContextManager

from orchestrator.heap import HeapTrimmer
from orchestrator.planner import Planner
from orchestrator.protocol import EventKind
from orchestrator.serviceconfig import ServiceConfig
from orchestrator.storagehealth import StorageHealth
from orchestrator.uploads import StoredEpisode
from storage.errors import StorageUnavailableError
from storage.queue import RequestQueue
from storage.requests import NewRequest

log = logging.getLogger("orchestrator.service")  # (the service's lines, as before the split)


class PlanFeed:
    """The planner and the ``on_episode`` callbacks behind the service (see the module's docstring).

    ``writing``: the service's writer turn, a context manager around each queue write; ``publish``: its event
    publisher; ``heap``: trimmed after each batch (what scoring freed). ``planner`` None: the callbacks alone.
    """

    def __init__(self, config: ServiceConfig, planner: Planner | None, queue: RequestQueue, storage: StorageHealth,
                 writing: Callable[[], ContextManager[None]], publish: Callable[[EventKind, dict[str, Any]], None],
                 heap: HeapTrimmer) -> None:
        self.config = config
        self.planner = planner
        self.queue = queue
        self.storage = storage
        self._writing = writing
        self._publish = publish
        self._heap = heap
        self._stored: queue_mod.Queue[StoredEpisode | None] = queue_mod.Queue()
        self._thread: threading.Thread | None = None

    def seed(self) -> None:
        """At start, before leasing: ``seed_requests`` of the planner's draws into a queue with nothing queued or
        leased. Raises StorageError when they cannot be queued (nothing was)."""
        if self.planner is None or not self.config.seed_requests:
            return
        counts = self.queue.counts()
        if counts["queued"] + counts["leased"] == 0:
            self.enqueue(self.planner.seed(self.config.seed_requests), "seed")

    def enqueue(self, news: Sequence[NewRequest], source: str) -> None:
        """Queue ``news`` in one write and publish ``request.queued`` for each that was new."""
        if not news:
            return
        with self._writing():
            stored = self.queue.enqueue_many(news)
        for request, created in stored:
            if created:
                self._publish(EventKind.REQUEST_QUEUED, {"request_id": request.id, "status": request.status.value,
                                                         "priority": request.priority, "shape": request.shape,
                                                         "source": source})

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="episodes", daemon=True)
        self._thread.start()

    def put(self, stored: StoredEpisode) -> None:
        """An episode was stored: the planner and the callbacks get it with the next batch."""
        self._stored.put(stored)

    def stop(self, timeout: float = 30.0) -> None:
        """Finish the episodes in hand, then end the thread (waiting at most ``timeout``). Idempotent."""
        self._stored.put(None)
        if self._thread is not None:
            self._thread.join(timeout=timeout)

    def _run(self) -> None:
        """One batch of stored episodes at a time; with a queue floor, also the top-ups (after each batch and
        after ``reap_interval_s`` without one)."""
        floor = self.planner is not None and self.config.min_queued > 0
        wait = self.config.reap_interval_s if floor else None  # no floor: nothing to wake up for
        while True:
            try:
                batch = [self._stored.get(timeout=wait)]
            except queue_mod.Empty:
                self._top_up()
                continue
            while not self._stored.empty():
                batch.append(self._stored.get_nowait())
            done = None in batch
            batch = [b for b in batch if b is not None]
            if batch:
                self._handle(batch)
                self._heap()
            if done:
                return
            self._top_up()

    def _top_up(self) -> None:
        """Tops the queue up to ``min_queued`` with the planner's seed draws; one that fails is tried again at the
        next interval."""
        if self.planner is None or not self.config.min_queued:
            return
        missing = self.storage.read("the queue's depth",
                                    lambda: self.config.min_queued - self.queue.counts()["queued"])
        if missing is not None and missing > 0:
            news = self.storage.read(f"what planner {self.planner.name} seeds with",
                                     lambda: self.planner.seed(missing, "top-up"))
            self._queue_up(news or [], "top-up")

    def _queue_up(self, news: Sequence[NewRequest], source: str) -> None:
        """``enqueue`` from this thread: a failed write is logged (and, passing, storage down)."""
        try:
            self.enqueue(news, source)
        except StorageUnavailableError as exc:  # these requests are lost; the queue floor tops up later
            log.warning("%d request(s) of %s could not be queued: %s", len(news), source, exc)
        except Exception:  # noqa: BLE001 -- must not stop ingest or the top-ups; it is logged
            log.exception("queueing %d request(s) of %s failed", len(news), source)

    def _handle(self, batch: list[StoredEpisode]) -> None:
        if self.planner is not None:  # the planner only reads (its scorer: the catalog, the registry; the depth)
            news = self.storage.read(f"what planner {self.planner.name} plans with",
                                     lambda: self.planner.plan([b.episode for b in batch]))
            self._queue_up(news or [], self.planner.name)
        for stored in batch:
            for callback in self.config.on_episode:
                try:
                    callback(stored)
                except Exception:  # noqa: BLE001 -- one failing callback must not starve the others
                    log.exception("on_episode callback %r failed for %s", callback, stored.episode_id)

