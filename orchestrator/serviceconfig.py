"""The orchestrator service's configuration: ``ServiceConfig`` (what ``activecollect serve``
decides), ``ServiceContext`` (what a planner factory or an ``on_episode`` callback is handed),
``ServiceError`` and ``where_served`` (how a service is reached, in words).

``orchestrator.service.Service`` runs them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from orchestrator import protocol, transport
from orchestrator.metrics import ServiceMetrics
from orchestrator.planner import Planner
from orchestrator.protocol import EventKind, Keys, ProtocolError
from orchestrator.uploads import StoredEpisode
from storage.catalog import Catalog
from storage.models import ModelRegistry
from storage.queue import RequestQueue


class ServiceError(Exception):
    """The service could not start (bad config, Zenoh or storage refused)."""


@dataclass
class ServiceContext:
    """What a planner factory or a callback may use: the service's storage, keys and event publisher."""

    data_dir: Path
    keys: Keys
    queue: RequestQueue
    catalog: Catalog
    registry: ModelRegistry
    metrics: ServiceMetrics
    publish: Callable[[EventKind, dict[str, Any]], None]


PlannerFactory = Callable[[ServiceContext], Planner]
EpisodeCallback = Callable[[StoredEpisode], None]

#: The seconds each of these ``ServiceConfig`` fields may be (and ``serve``'s flags for them take).
SECONDS_RANGES = {"lease_s": (0.05, 86400.0), "reap_interval_s": (0.01, 3600.0), "lost_worker_grace_s": (0.0, 86400.0)}


@dataclass
class ServiceConfig:
    """Everything ``activecollect serve`` decides."""

    data_dir: Path
    """Data directory: catalog.sqlite (episodes, requests, models) and episodes/."""
    namespace: str = "activecollect"
    """Prefix of every Zenoh key of this deployment."""
    mode: str = "peer"
    """Zenoh mode without a config file: peer or client."""
    listen: tuple[str, ...] = ()
    """Zenoh endpoints to listen on, e.g. tcp/127.0.0.1:7447."""
    connect: tuple[str, ...] = ()
    """Zenoh endpoints (routers, peers) to connect to."""
    zenoh_config: Path | None = None
    """A Zenoh JSON5 config file, passed through unchanged (listen/connect add endpoints)."""
    lease_s: float = 30.0
    """Lease length handed to workers; they renew well before it runs out."""
    reap_interval_s: float = 1.0
    """How often expired leases are looked for."""
    lost_worker_grace_s: float = 10.0
    """How long a worker whose liveliness token went keeps its leases: when a Zenoh router restarts or a link blips,
    every token goes and comes back a few seconds later, each worker still collecting its episode. A token back
    within the grace keeps them; after it they go back to the queue (``orchestrator.liveliness``). 0: at once. A
    lease still expires on its own timer meanwhile."""
    max_upload_bytes: int = protocol.MAX_UPLOAD_BYTES
    """Largest episode upload accepted."""
    planner: PlannerFactory | None = None
    """Builds the planner from the service context; None plans nothing (manual requests only)."""
    seed_requests: int = 0
    """Requests the planner seeds an empty queue with at start."""
    min_queued: int = 0
    """While a planner runs, keep at least this many requests queued: whenever fewer are, the planner's
    ``seed`` (uniform draws, reason ``top-up``) tops the queue up. An active planner asks only for states above
    its threshold and away from what it asked before, so its requests can run out; once the queue is empty no
    episode comes in to plan from, and without this floor collection stops for good. 0: no floor."""
    on_episode: tuple[EpisodeCallback, ...] = ()
    """Called in the background thread for every stored episode (after the planner)."""
    handler_threads: int = 4
    """Threads answering uploads (verify, fsync, index); admin queries get 2 more."""
    inline_dispatch: bool = True
    """Answer lease / renew / fail / release on Zenoh's own threads: each is one short SQLite transaction,
    and skipping the hand-off to a Python thread gave ~40% more leases/s on 2 busy cores."""
    metrics: ServiceMetrics | None = None
    """Where to count; a fresh ServiceMetrics when None."""

    def __post_init__(self) -> None:
        self.data_dir = Path(self.data_dir)
        self.listen, self.connect = tuple(self.listen), tuple(self.connect)
        if self.zenoh_config is not None:
            self.zenoh_config = Path(self.zenoh_config)
        try:
            Keys(self.namespace)
        except ProtocolError as exc:
            raise ServiceError(f"namespace: {exc.message}") from None
        if self.mode not in transport.MODES:
            raise ServiceError(f"mode: expected one of {transport.MODES}, found {self.mode!r}")
        numbers = [(name, getattr(self, name), *SECONDS_RANGES[name]) for name in SECONDS_RANGES]
        counts = [("max_upload_bytes", self.max_upload_bytes, 1, protocol.MAX_UPLOAD_BYTES),
                  ("seed_requests", self.seed_requests, 0, 10_000), ("min_queued", self.min_queued, 0, 10_000),
                  ("handler_threads", self.handler_threads, 1, 64)]
        for kinds, what, checks in (((int, float), "a number", numbers), (int, "a whole number", counts)):
            for name, value, lo, hi in checks:
                if isinstance(value, bool) or not isinstance(value, kinds) or not lo <= value <= hi:
                    raise ServiceError(f"{name}: expected {what} in [{lo}, {hi}], found {value!r}")
        if not all(callable(cb) for cb in self.on_episode):
            raise ServiceError("on_episode: expected callables")


def where_served(listen: tuple[str, ...], connect: tuple[str, ...], zenoh_config: Path | None, *,
                 linked: bool = False) -> str:
    """``listening on EP``, ``--connect EP`` and/or ``with Zenoh config FILE``: how a service is reached. A
    ``connect`` endpoint is ``connected to EP`` only where ``linked`` (the caller saw a link to each): a peer's
    session opens with none and keeps dialling (the text in ``DATA/service.lock`` is written before it opens)."""
    parts = ([f"listening on {', '.join(listen)}"] if listen else []) + \
        ([f"{'connected to' if linked else '--connect'} {', '.join(connect)}"] if connect else []) + \
        ([f"with Zenoh config {zenoh_config}"] if zenoh_config is not None else [])
    return ", ".join(parts)
