"""The service's metrics, exposed by the dashboard at ``/metrics`` in Prometheus text format 0.0.4.

A thin layer over ``prometheus_client``: each ``ServiceMetrics`` owns its own ``CollectorRegistry``
(no process-global state, so two services or two tests never share counters), and its methods name
what happened (``lease()``, ``upload("stored")``) instead of exposing label plumbing to callers.
``prometheus_client`` metrics are thread-safe, so the Zenoh handlers, the scheduler and the HTTP
server may all touch one instance.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4, generate_latest

from storage.database import disk_json, quarantine_bytes

#: The Content-Type header to send with ``render()``'s text (names are legacy-valid, so the 0.0.4
#: text format is exact; prometheus_client's "latest" would announce 1.0.0).
CONTENT_TYPE = CONTENT_TYPE_PLAIN_0_0_4
NAMESPACE = "activecollect"

#: Request statuses always exported (0 when empty), so a dashboard's series never vanish.
QUEUE_STATUSES: tuple[str, ...] = ("queued", "leased", "done", "dead", "cancelled")
#: Catalog splits the episode gauge (and ``stats``) count.
SPLITS: tuple[str, ...] = ("train", "eval")
UPLOAD_RESULTS: tuple[str, ...] = ("stored", "duplicate", "refused")
RETRAIN_OUTCOMES: tuple[str, ...] = ("promoted", "rejected", "busy", "failed")
#: Who sent a refused message: a worker (lease, renew, fail, release, upload) or an operator (an admin query,
#: whose typo, an unknown request id say, an alert on the workers' refusals must not count).
REFUSAL_SOURCES: tuple[str, ...] = ("worker", "operator")


def retrain_outcome(status: str) -> str:
    """A finished retrain job's ``RetrainStatus`` value as a ``retrains_total`` outcome: ``busy`` (another job held
    the lock: nothing went wrong) is its own, so an alert on ``failed`` (a failure, a timeout, a kill) does not fire
    when a cron retrain meets a manual one."""
    return status if status in ("promoted", "rejected", "busy") else "failed"
#: Scoring one episode takes milliseconds (tiny CPU model) to seconds (big model, slow host).
SCORING_BUCKETS: tuple[float, ...] = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
#: The gauges ``read_stores`` sets: all that a process without the service knows (see ``render_stores``).
STORE_GAUGES: tuple[str, ...] = ("queue_depth", "episodes", "episodes_quarantined", "quarantine_bytes",
                                 "champion_h1_mse", "champion_weights_damaged", "champion_info",
                                 "data_disk_free_bytes", "data_disk_size_bytes")
#: How long the space of ``DATA/quarantine/`` is taken as read: the service reads the stores every
#: ``reap_interval_s`` (a second) and a dashboard on every request, and each walk stats every file kept there.
QUARANTINE_WALK_S = 60.0


def _check(value: str, allowed: Iterable[str], what: str) -> str:
    allowed = tuple(allowed)
    if value not in allowed:
        raise ValueError(f"{what} must be one of {', '.join(allowed)}, found {value!r}")
    return value


class QuarantineSpace:
    """``storage.database.quarantine_bytes`` of a data directory, walked again only once ``every_s`` have passed
    since the last walk (thread-safe: callers at once wait for one walk)."""

    def __init__(self, every_s: float = QUARANTINE_WALK_S) -> None:
        self.every_s = every_s
        self._lock = threading.Lock()
        self._walked: tuple[float, Path, int | None] | None = None  # (when, of which directory, bytes)

    def read(self, data_dir: str | Path) -> int | None:
        """The bytes the files in ``data_dir``'s quarantine take (None: it cannot be read)."""
        with self._lock:
            now, data_dir = time.monotonic(), Path(data_dir)
            if self._walked is None or self._walked[1] != data_dir or now - self._walked[0] >= self.every_s:
                self._walked = (now, data_dir, quarantine_bytes(data_dir))
            return self._walked[2]


class ServiceMetrics:
    """The counters, gauges and histograms the service and dashboard report.

    Parameters: ``registry`` to register into (a fresh ``CollectorRegistry`` when None); ``quarantine_walk_s``,
    how long ``read_stores`` keeps the space of ``DATA/quarantine/`` before walking it again.
    """

    def __init__(self, registry: CollectorRegistry | None = None,
                 quarantine_walk_s: float = QUARANTINE_WALK_S) -> None:
        self.registry = registry if registry is not None else CollectorRegistry(auto_describe=True)
        r, ns = self.registry, NAMESPACE
        self.queue_depth = Gauge("queue_depth", "Collection requests in the queue, by status.",
                                 ["status"], namespace=ns, registry=r)
        self.leases = Counter("leases", "Leases handed to workers.", namespace=ns, registry=r)
        self.uploads = Counter("uploads", "Episode uploads, by result (stored, duplicate, refused).",
                               ["result"], namespace=ns, registry=r)
        self.upload_parts_held_bytes = Gauge("upload_parts_held_bytes", "Bytes the service holds in memory for "
                                             "uploads sent in parts and not yet complete.", namespace=ns, registry=r)
        self.refusals = Counter("refusals", "Inbound messages refused, by reason (protocol error code) and source "
                                "(worker: the collection protocol; operator: an admin query).",
                                ["reason", "source"], namespace=ns, registry=r)
        self.retrains = Counter("retrains", f"Retrain jobs finished, by outcome ({', '.join(RETRAIN_OUTCOMES)}).",
                                ["outcome"], namespace=ns, registry=r)
        self.scoring_seconds = Histogram("scoring_seconds", "Time to score one episode with the champion.",
                                         namespace=ns, registry=r, buckets=SCORING_BUCKETS)
        self.workers_alive = Gauge("workers_alive", "Workers with a live liveliness token.",
                                   namespace=ns, registry=r)
        self.episodes = Gauge("episodes", "Episodes in the catalog, by split.", ["split"],
                              namespace=ns, registry=r)
        self.episodes_quarantined = Gauge("episodes_quarantined", "Episodes taken out of training because their "
                                          "files were found missing or damaged, or an operator rejected them.",
                                          namespace=ns, registry=r)
        self.quarantine_bytes = Gauge("quarantine_bytes", "Bytes the files of quarantined episodes take in DATA/"
                                      f"quarantine/ (walked again at most every {quarantine_walk_s:g} s).",
                                      namespace=ns, registry=r)
        self.quarantine_bytes.set(float("nan"))  # unknown until read
        self.quarantine_space = QuarantineSpace(quarantine_walk_s)
        self.champion_h1_mse = Gauge("champion_h1_mse", "The champion's horizon-1 MSE on the eval split.",
                                     namespace=ns, registry=r)
        self.champion_weights_damaged = Gauge("champion_weights_damaged", "1 when the champion's weights are "
                                              "missing or fail their sha256 (it cannot be served), else 0.",
                                              namespace=ns, registry=r)
        self.champion_info = Gauge("champion_info", "The champion's version (value 1; label version).",
                                   ["version"], namespace=ns, registry=r)
        self._champion: str | None = None  # the version champion_info shows
        self._champion_lock = threading.Lock()
        self.disk_free_bytes = Gauge("data_disk_free_bytes", "Free bytes on the file system of the data directory.",
                                     namespace=ns, registry=r)
        self.disk_size_bytes = Gauge("data_disk_size_bytes", "Size in bytes of the file system of the data "
                                     "directory.", namespace=ns, registry=r)
        self.set_disk(None)
        self.set_champion(None)  # NaN until there is one, not a perfect 0.0
        for status in QUEUE_STATUSES:
            self.queue_depth.labels(status=status).set(0)
        for result in UPLOAD_RESULTS:
            self.uploads.labels(result=result)
        for outcome in RETRAIN_OUTCOMES:
            self.retrains.labels(outcome=outcome)

    def set_queue_depth(self, counts: Mapping[str, int]) -> None:
        """Set the queue gauge from ``RequestQueue.counts()``; statuses not in ``counts`` read 0."""
        for status in sorted(set(QUEUE_STATUSES) | set(counts)):
            self.queue_depth.labels(status=status).set(counts.get(status, 0))

    def lease(self, n: int = 1) -> None:
        """Count ``n`` leases handed out."""
        self.leases.inc(n)

    def upload(self, result: str) -> None:
        """Count one upload; ``result`` is one of ``UPLOAD_RESULTS`` (ValueError otherwise)."""
        self.uploads.labels(result=_check(result, UPLOAD_RESULTS, "upload result")).inc()

    def refusal(self, reason: str, source: str = "worker") -> None:
        """Count one refused message; ``reason`` should be a short code (``bad_sha256``), not a message; ``source``
        is one of ``REFUSAL_SOURCES`` (ValueError otherwise)."""
        if not reason:
            raise ValueError("refusal reason must be a non-empty code, found ''")
        self.refusals.labels(reason=reason, source=_check(source, REFUSAL_SOURCES, "refusal source")).inc()

    def retrain(self, outcome: str) -> None:
        """Count one finished retrain; ``outcome`` is one of ``RETRAIN_OUTCOMES`` (ValueError otherwise)."""
        self.retrains.labels(outcome=_check(outcome, RETRAIN_OUTCOMES, "retrain outcome")).inc()

    def observe_scoring(self, seconds: float) -> None:
        """Record how long scoring one episode took."""
        self.scoring_seconds.observe(seconds)

    @contextmanager
    def time_scoring(self) -> Iterator[None]:
        """Time the block as one scoring (recorded even if it raises)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.observe_scoring(time.perf_counter() - start)

    def set_workers_alive(self, n: int) -> None:
        self.workers_alive.set(n)

    def set_episodes(self, counts: Mapping[str, int]) -> None:
        """Set the catalog gauge from ``{split: count}``."""
        for split, n in counts.items():
            self.episodes.labels(split=split).set(n)

    def set_champion(self, version: str | None, h1_mse: float | None = None) -> None:
        """Name the champion (None: there is none) and its eval error.

        ``champion_info`` changes only when the version does, the new series set before the old one is
        removed: a scrape between the two never finds none (an ``absent()`` alert would fire).
        """
        with self._champion_lock:
            if version != self._champion:
                if version is not None:
                    self.champion_info.labels(version=version).set(1)
                if self._champion is not None:
                    self.champion_info.remove(self._champion)
                self._champion = version
        self.champion_h1_mse.set(float("nan") if h1_mse is None else h1_mse)

    def set_disk(self, disk: Mapping[str, int] | None) -> None:
        """Set the disk gauges from ``storage.database.disk_json`` (None: unknown, NaN)."""
        self.disk_free_bytes.set(float("nan") if disk is None else disk["free_bytes"])
        self.disk_size_bytes.set(float("nan") if disk is None else disk["size_bytes"])

    def read_stores(self, queue: Any, catalog: Any, registry: Any) -> None:
        """Set the gauges the data directory holds: queue depth, episodes per split, how many are quarantined
        and the space their files take, the champion, and the free space of its disk.

        ``queue``, ``catalog`` and ``registry`` are a RequestQueue, Catalog and ModelRegistry (any
        process may have changed them: a retrain job, ``train``, ``models promote``).
        """
        self.set_queue_depth(queue.counts())
        self.set_episodes({split: catalog.count(split=split) for split in SPLITS})
        self.episodes_quarantined.set(catalog.count(quarantined=True))
        space = self.quarantine_space.read(catalog.data_dir)
        self.quarantine_bytes.set(float("nan") if space is None else space)
        self.set_disk(disk_json(catalog.data_dir))
        champion = registry.champion()
        h1 = registry.get(champion).metrics.get("h1_mse") if champion is not None else None
        self.set_champion(champion, h1 if isinstance(h1, (int, float)) else None)
        self.champion_weights_damaged.set(champion is not None and registry.weights_problem(champion) is not None)

    def render(self) -> str:
        """Every metric in Prometheus text exposition format 0.0.4 (HELP and TYPE lines, escaped labels)."""
        return generate_latest(self.registry).decode("utf-8")

    def render_stores(self) -> str:
        """``render`` of the ``STORE_GAUGES`` only, for a process that is not the service (``activecollect
        dashboard``): its counters and ``workers_alive`` would read 0 whatever the service counted, and an alert
        on a stalled upload rate or on no live workers would fire on them; absent, they are known to be unknown."""
        names = [f"{NAMESPACE}_{name}" for name in STORE_GAUGES]
        return generate_latest(self.registry.restricted_registry(names)).decode("utf-8")
