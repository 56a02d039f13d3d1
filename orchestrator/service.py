"""The orchestrator service: the queue, the catalog and the planner behind Zenoh.

``Service(ServiceConfig).start()`` opens a Zenoh session and answers:

- ``NS/orch/lease | renew | upload | fail | release`` for workers (see ``orchestrator.messages``);
- ``NS/admin/**`` for operators and dashboards (``orchestrator.admin``);

it holds ``DATA/service.lock`` from before its first write until ``stop()`` (one service per data directory: a
second is refused, naming the first; ``storage.servicelock``), watches the liveliness tokens ``NS/workers/*`` (a
lost worker's leases go back to the queue after a grace), expires leases on a timer, and publishes on ``NS/events/**``.

Threads: lease / renew / fail / release are answered on Zenoh's callback threads (one short SQLite transaction
each); uploads (``orchestrator.uploads``) and admin queries are handed to a small pool per key (verification,
fsync). The queue checkpoints its WAL on a thread of its own, so no transition waits for those fsyncs. A
maintenance thread reaps expired leases and releases lost workers' leases (``orchestrator.liveliness``).
``orchestrator.planfeed`` seeds the queue and, on a thread of its own, hands each stored episode to the planner and
the ``on_episode`` callbacks and keeps the queue at its floor, so scoring and planning never stall leasing.

Every reply is ``protocol.ok_reply`` / ``error_reply`` bytes; a message that fails validation gets an error reply
and changes nothing.

The configuration (``ServiceConfig``), what a planner factory or callback is handed (``ServiceContext``) and
``ServiceError`` live in ``orchestrator.serviceconfig``.
"""

from __future__ import annotations

import contextlib
import logging
import queue as queue_mod
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import zenoh

from orchestrator import admin, messages, protocol, serving, sweeps, transport
from orchestrator.heap import HeapTrimmer
from orchestrator.liveliness import Presence
from orchestrator.metrics import ServiceMetrics
from orchestrator.planfeed import PlanFeed
from orchestrator.planner import Planner
from orchestrator.protocol import ErrorCode, EventKind, Keys, ProtocolError
from orchestrator.refusallog import RefusalLog
from orchestrator.serviceconfig import ServiceConfig, ServiceContext, ServiceError, where_served
from orchestrator.storagehealth import StorageHealth
from orchestrator.transport import Incoming, Response
from orchestrator.uploads import StoredEpisode, UploadHandler, release_lease
from storage.catalog import STAGING_MAX_AGE_S, Catalog
from storage.errors import QueueError, StorageError, StorageUnavailableError
from storage.models import ModelRegistry
from storage.queue import RequestQueue, steady_clock
from storage.requests import Request, RequestStatus
from storage.servicelock import DataDirectoryBusyError, ServiceLock

log = logging.getLogger(__name__)


class Service:
    """The orchestrator: ``start()`` serves until ``stop()``."""

    def __init__(self, config: ServiceConfig, *, wall_clock: Callable[[], float] = time.time,
                 elapsed: Callable[[], float] = time.monotonic) -> None:
        """``wall_clock``: read once at start, and ``elapsed`` since, make the queue's ``steady_clock`` (a test's fake
        clocks step or jump)."""
        self.config = config
        self._wall_clock, self._elapsed = wall_clock, elapsed
        self._last_reap: float | None = None
        """``_elapsed`` at the last reap: a gap far past the interval is a service that did not run (``_reap``)."""
        self.keys = Keys(config.namespace)
        self.metrics = config.metrics if config.metrics is not None else ServiceMetrics()
        self.session: zenoh.Session | None = None
        self.queue: RequestQueue | None = None
        self.catalog: Catalog | None = None
        self._frame_size_known = 0
        self._frame_size_next = 0.0
        self.context: ServiceContext | None = None
        self.planner: Planner | None = None
        self.feed: PlanFeed | None = None
        self._servers: list[serving.Server] = []
        self._publishers: dict[EventKind, Any] = {}
        self._liveliness_sub: Any = None
        self.presence = Presence(config.lost_worker_grace_s, gauge=self.metrics.set_workers_alive,
                                 release=self._worker_lost, leased=lambda: self.storage.read(
                                     "the leased requests", lambda: self.queue.list(RequestStatus.LEASED)))
        self._tasks: queue_mod.Queue[Callable[[], None] | None] = queue_mod.Queue()
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        # Writes to catalog.sqlite from our own threads (queue transitions, an upload's ingest transaction) take
        # turns here instead of inside SQLite, whose busy handler sleeps in steps of up to 100 ms (a lease's p99).
        self._writes = threading.Lock()
        self.storage = StorageHealth(log)
        """Whether writes fail for now (no lease expires meanwhile) and which reads fail (warnings only)."""
        self.heap = HeapTrimmer()
        """Gives the heap's free memory back after the planner's batches (scoring's tensors), every few seconds."""
        self._lock = ServiceLock(config.data_dir)
        self.refusals = RefusalLog(log, clock=elapsed)
        """The line for a refused query: one per (key, code, worker) a minute, with a count of those not logged."""

    # --- lifecycle -----------------------------------------------------------------------------

    def start(self) -> None:
        """Open storage and Zenoh and start answering. Raises ServiceError (after stopping what it had started),
        also when another service holds the data directory (nothing there is changed then)."""
        try:
            self._start()
        except BaseException:
            self.stop()
            raise

    def claim(self) -> None:
        """Take the data directory (``DATA/service.lock``) now rather than in ``start``, for a caller that writes
        there before it starts the service (``activecollect run``); ``stop()`` lets it go (or, after
        ``stop(keep_claim=True)``, ``release_claim()``). Raises DataDirectoryBusyError (a StorageError) naming the
        service that holds it; OSError when the directory or the lock file cannot be made."""
        cfg = self.config
        cfg.data_dir.mkdir(parents=True, exist_ok=True)
        self._lock.acquire(where_served(cfg.listen, cfg.connect, cfg.zenoh_config), cfg.namespace)

    def release_claim(self) -> None:
        """Let the data directory go (see ``claim``). Idempotent."""
        self._lock.release()

    def _start(self) -> None:
        cfg = self.config
        try:
            self.claim()  # before anything writes: a directory another service serves is left as it was
            self.catalog = Catalog(cfg.data_dir)
            self._sweep()  # before any upload is answered
            # leases judged by a clock that NTP's steps cannot move (expired all at once on a step forward)
            self.queue = RequestQueue(self.catalog.db_path, background_checkpoint=True,
                                      clock=steady_clock(self._wall_clock, self._elapsed))
            self._carry_leases_over()  # before the first reap
            registry = ModelRegistry(cfg.data_dir)
        except DataDirectoryBusyError as exc:
            raise ServiceError(str(exc)) from exc
        except (StorageError, OSError) as exc:
            raise ServiceError(f"cannot open the data directory {cfg.data_dir}: {exc}") from exc
        self.context = ServiceContext(cfg.data_dir, self.keys, self.queue, self.catalog, registry,
                                      self.metrics, self.publish)
        try:
            self.session = transport.open_session(cfg.mode, cfg.listen, cfg.connect, cfg.zenoh_config)
        except transport.TransportError as exc:
            raise ServiceError(str(exc)) from exc
        # One declared publisher per event kind: a put skips resolving the key (every lease and fail publishes).
        self._publishers = {kind: self.session.declare_publisher(self.keys.events(kind)) for kind in EventKind}
        if cfg.planner is not None:
            self.planner = cfg.planner(self.context)
        self.feed = PlanFeed(cfg, self.planner, self.queue, self.storage, self._writing, self.publish, self.heap)
        try:
            self.feed.seed()
        except StorageError as exc:  # e.g. a full disk: nothing was queued
            raise ServiceError(f"cannot seed the queue with {cfg.seed_requests} request(s): {exc}") from exc
        self._uploads = UploadHandler(self.queue, self.catalog, self.metrics, self.publish, self._writing,
                                      cfg.max_upload_bytes, self._episode_stored, self._frame_size,
                                      health=self.storage, parts_max_age_s=max(2 * cfg.lease_s, 10.0))
        self._threads = [threading.Thread(target=self._maintain, name="maintenance", daemon=True)]
        for t in self._threads:
            t.start()
        self.feed.start()
        k, fast = self.keys, 0 if cfg.inline_dispatch else cfg.handler_threads
        self._servers = [self._serve(k.lease, self._lease, fast), self._serve(k.renew, self._renew, fast),
                         self._serve(k.fail, self._fail, fast), self._serve(k.release, self._release, fast),
                         self._serve(k.upload, self._uploads.handle, cfg.handler_threads),
                         self._serve(k.admin_all, self._admin, 2, source="operator")]
        self._liveliness_sub = self.session.liveliness().declare_subscriber(
            k.workers_all, self._on_liveliness, history=True)
        log.info("serving namespace %s (listen %s, connect %s, data %s)", cfg.namespace,
                 list(cfg.listen), list(cfg.connect), cfg.data_dir)

    def stop(self, *, keep_claim: bool = False) -> None:
        """Stop answering, finish the work in hand, close Zenoh and storage. Idempotent. ``keep_claim``: the data
        directory stays claimed for a caller that still writes there (``run``'s report; see ``claim``)."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        if self._liveliness_sub is not None:
            self._liveliness_sub.undeclare()
        for server in self._servers:
            server.close()
        self.refusals.flush(everything=True)
        self._tasks.put(None)
        if self.feed is not None:
            self.feed.stop(timeout=30)
        for t in self._threads:
            t.join(timeout=30)
        if self.session is not None:
            self.session.close()
        if self.queue is not None:
            self.queue.close()
        if not keep_claim:
            self.release_claim()  # last: another service may start once nothing of ours writes
        if self.catalog is not None:  # (a start refused before it opened anything says so in its error alone)
            log.info("stopped")

    def __enter__(self) -> Service:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def workers(self) -> list[str]:
        """Ids of the workers whose liveliness token is alive now."""
        return self.presence.alive()

    def publish(self, kind: EventKind, data: dict[str, Any]) -> None:
        """Publish one event on ``NS/events/<kind>`` (best effort: an event is a notification, not state).

        ``data`` must be JSON-able with finite numbers. Encoded directly (an ``Event`` in wire form) rather than
        through the validating dataclass: this runs on every lease."""
        if self.session is None or self.session.is_closed():
            return
        kind = EventKind(kind)
        payload = protocol.encode({"v": protocol.PROTOCOL_VERSION, "kind": kind.value, "at": time.time(),
                                   "data": data})
        try:
            self._publishers[kind].put(payload)
        except zenoh.ZError as exc:
            log.warning("cannot publish %s: %s", kind.value, exc)

    @contextlib.contextmanager
    def _writing(self) -> Iterator[None]:
        """The writer turn (``_writes``) around a write of ours; one the storage refuses for a reason that passes
        is ``storage``'s to know, whichever path wrote (no lease expires until a write works again). Known before
        the turn passes on: a reap that took it in between would expire the leases nobody could renew."""
        with self._writes, self.storage.writing():
            yield

    # --- query handlers ------------------------------------------------------------------------

    def _serve(self, key: str, handler: Callable[[Incoming], bytes], threads: int,
               source: str = "worker") -> serving.Server:
        """A Server for ``handler``: a ProtocolError becomes its error reply (a refusal from ``source``)."""

        def answer(msg: Incoming) -> Response:
            try:
                return Response(handler(msg))
            except ProtocolError as exc:
                self.metrics.refusal(exc.code.value, source)  # every one; the log line, rate-limited
                self.refusals.refused(msg, exc)
                return Response(exc.reply())

        def crashed(code: str, message: str) -> bytes:  # a bug in a handler: logged by the Server
            self.metrics.refusal(code, source)
            return protocol.error_reply(code, message)

        return serving.Server(self.session, key, answer, threads, error_body=crashed)

    def _lease(self, msg: Incoming) -> bytes:
        req = messages.LeaseRequest.from_json(msg.payload)
        self._uploads.check_lease(req.worker_id, req.image_size)  # an older worker of another size: refused
        lease_s = self.config.lease_s
        frame_size = self._frame_size() if req.image_size else 0  # before the lease: it must not fail after
        try:
            with self._writing():
                # One lease per worker: a query it asked again (the first one's answer came too late, e.g.
                # behind another process's write lock) gets the lease the first one granted, not a second.
                lease = self.queue.lease(req.worker_id, req.tasks, req.shapes, lease_s, one_per_worker=True)
        except QueueError as exc:
            raise admin.protocol_error(exc) from exc
        if lease is None:
            return protocol.error_reply(ErrorCode.NO_WORK, "no queued request matches "
                                        f"tasks={req.tasks or 'any'} shapes={req.shapes or 'any'}")
        r = lease.request
        # Built as a dict, not a LeaseGrant: the request was checked before it was queued (by RequestSpec, or in
        # bounds by construction), the worker checks the grant, and dataclass round trips cost ~100 us per lease.
        grant = {"request_id": r.id, "task": r.task, "shape": r.shape, "start_state": r.start_state,
                 "policy": r.policy, "policy_params": r.policy_params, "action_prefix": r.action_prefix,
                 "steps": r.steps, "model_version": str(r.reason.get("model_version") or ""),
                 "token": lease.token, "expires_at": lease.expires_at, "lease_s": lease_s,
                 "seed": messages.request_seed(r.id, lease.token)}
        if req.image_size:  # a worker that records at the catalog's size (older ones refuse the field)
            grant["image_size"] = frame_size
        if not frame_size:  # it records at its own size: an upload of another than the catalog's is given back
            self._uploads.sizeless(r.id, lease.token, older=not req.image_size)
        if lease.again:
            log.info("lease of %s (token %d) answered again for %s, which asked again", r.id, lease.token,
                     req.worker_id)
        else:
            self.metrics.lease()
            self.publish(EventKind.REQUEST_LEASED, {"request_id": r.id, "worker_id": req.worker_id,
                                                    "token": lease.token, "shape": r.shape})
        return protocol.ok_reply(grant=grant)

    def _episode_stored(self, stored: StoredEpisode) -> None:
        """An upload was indexed: its frame size is the catalog's now (if it was not already)."""
        if not self._frame_size_known:
            self._frame_size_known = int(stored.episode.frames.shape[1])
        self.feed.put(stored)

    def _frame_size(self) -> int:
        """The catalog's frame size for grants (0 while it holds no episode). Fixed once known, so cached;
        while unknown, asked at most once a second (leases are the hot path; other processes may add the
        first episode)."""
        if not self._frame_size_known and time.monotonic() >= self._frame_size_next:
            self._frame_size_next = time.monotonic() + 1.0
            try:
                size = self.catalog.frame_size()
            except StorageError as exc:  # a busy or damaged catalog: the worker's own size this time
                log.warning("cannot read the catalog's frame size: %s", exc)
                size = None
            if size:  # never overwrites what an upload on another thread just set
                self._frame_size_known = size
        return self._frame_size_known

    def _renew(self, msg: Incoming) -> bytes:
        req = messages.RenewRequest.from_json(msg.payload)
        try:
            with self._writing():
                expires = self.queue.renew(req.request_id, req.token, req.worker_id, self.config.lease_s)
        except QueueError as exc:
            raise admin.protocol_error(exc) from exc
        return protocol.ok_reply(expires_at=expires)

    def _fail(self, msg: Incoming) -> bytes:
        req = messages.FailRequest.from_json(msg.payload)
        try:
            with self._writing():
                request = self.queue.fail(req.request_id, req.token, req.error, worker_id=req.worker_id)
        except QueueError as exc:
            raise admin.protocol_error(exc) from exc
        self._publish_lease_end(request, f"worker {req.worker_id} failed")
        return protocol.ok_reply(status=request.status.value, attempts=request.attempts)

    def _release(self, msg: Incoming) -> bytes:
        req = messages.ReleaseRequest.from_json(msg.payload)
        try:
            request = release_lease(self.queue, self._writing, self.publish, req.request_id, req.token, req.worker_id)
        except QueueError as exc:
            raise admin.protocol_error(exc) from exc
        return protocol.ok_reply(status=request.status.value, attempts=request.attempts)

    def _admin(self, msg: Incoming) -> bytes:
        op = self.keys.admin_op(msg.key)
        if msg.payload:
            request = messages.AdminRequest.from_json(msg.payload)
            if request.op != op:
                raise ProtocolError(ErrorCode.BAD_FIELD, f"op: expected {op!r} (the key's op), found {request.op!r}")
        else:
            request = messages.AdminRequest(op=op)
        # Reads (queue ls, stats, ...) run on their own connections beside the writer: a listing holds up no lease.
        with self._writing() if request.op in admin.WRITE_OPS else contextlib.nullcontext():
            body = admin.handle(request.op, request.args, queue=self.queue, catalog=self.catalog,
                                registry=self.context.registry, workers=self.workers)
        event = admin.admin_event(request.op, body)
        if event is not None:
            self.publish(EventKind(event.kind), admin.finite(event.data))
        return protocol.ok_reply(**body)

    # --- background ------------------------------------------------------------------------------

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        """Zenoh thread: note the change, leave the SQLite work to the maintenance thread."""
        try:
            worker_id = self.keys.worker_id(str(sample.key_expr))
        except ProtocolError as exc:
            log.warning("ignoring liveliness token %s: %s", sample.key_expr, exc)
            return
        self._uploads.forget_worker(worker_id)  # (before ``workers()`` says so) restarted, perhaps at another size
        if sample.kind == zenoh.SampleKind.PUT:
            if self.presence.joined(worker_id):  # back within its grace
                self._tasks.put(self.presence.say_back)
            self.publish(EventKind.WORKER_JOINED, {"worker_id": worker_id})
        else:
            self.presence.left(worker_id)
            self._tasks.put(self.presence.release_due)  # no grace: released now; else wakes the maintenance thread

    def _worker_lost(self, worker_id: str) -> None:
        if self.presence.is_alive(worker_id):  # it came back before we got here
            return
        with self._writing():
            released = self.queue.release_worker_leases(worker_id)
        if released:
            log.info("worker %s lost; %d lease(s) released", worker_id, len(released))
        else:  # (one that finished its work and exited: not the line an operator alerts on)
            log.info("worker %s gone; it held no lease", worker_id)
        self.publish(EventKind.WORKER_LOST, {"worker_id": worker_id, "released": [r.id for r in released]})
        for request in released:
            self._publish_lease_end(request, f"worker {worker_id} lost")

    def _publish_lease_end(self, request: Request, why: str) -> None:
        kind = EventKind.REQUEST_DEAD if request.status == RequestStatus.DEAD else EventKind.REQUEST_FAILED
        self.publish(kind, {"request_id": request.id, "status": request.status.value,
                            "attempts": request.attempts, "why": why, "error": (request.last_error or "")[:500]})

    def _maintain(self) -> None:
        """Reap expired leases every reap_interval_s, sweep crash leftovers every STAGING_MAX_AGE_S, release a
        lost worker's leases when its grace is over; run liveliness tasks as they come. ``stop`` waits for no grace."""
        interval = self.config.reap_interval_s
        next_reap = time.monotonic()
        next_sweep = next_reap + STAGING_MAX_AGE_S
        while True:
            try:
                task = self._tasks.get(timeout=max(0.0, min(next_reap, self.presence.next_due()) - time.monotonic()))
            except queue_mod.Empty:
                if self.presence.next_due() <= time.monotonic():
                    task = self.presence.release_due
                else:
                    task, next_reap = self._reap, time.monotonic() + interval
                    if next_reap >= next_sweep:  # a crash's staging files live at most two of these periods
                        task, next_sweep = self._sweep_all, next_reap + STAGING_MAX_AGE_S
            if task is None:
                return
            try:
                task()
            except StorageUnavailableError:  # a write's, said by storage.writing (reads go through storage.read)
                pass  # no lease expires until a write works again; the next reap tries one
            except Exception:  # noqa: BLE001 -- lease expiry must outlive any one failure
                log.exception("maintenance task failed; will try again")

    def _sweep(self) -> None:
        """What crashes left (``orchestrator.sweeps``): before any upload is answered, then every STAGING_MAX_AGE_S."""
        sweeps.sweep_leftovers(self.catalog, self.config.data_dir, self.storage, log)

    def _sweep_all(self) -> None:
        """The periodic sweep: the parts of uploads whose worker went away mid-way (first: memory, which a storage
        failure of the other does not hold), and crash leftovers."""
        self._uploads.parts.sweep()
        self._sweep()

    def _carry_leases_over(self) -> None:
        """At start-up: every live lease gets a full term from now. No worker could renew while the service
        was down; reaped at once, each request would go back to the queue (an attempt counted, ``dead`` after
        a few restarts) and its worker would drop the episode it collected but has not yet uploaded. A worker
        that is gone lets its lease run out one term later -- exactly one: an expiry further out, reckoned by
        the last service's steady clock after the wall clock stepped back, is brought back to it."""
        try:
            with self.storage.writing():
                extended = self.queue.extend_leases(self.config.lease_s, exactly=True)
        except StorageUnavailableError:  # a full disk: the reaper extends them once writes work again
            return
        if extended:
            log.info("%d lease(s) from before the start extended by %.0f s so their workers can renew",
                     extended, self.config.lease_s)

    def _reap(self) -> None:
        self.refusals.flush()  # (a client refused no more: its count is not left unsaid)
        try:
            with self._writing():
                # The service did not run (SIGSTOP, a paused container or VM, a starved host), or this pass waited
                # that long for the writer turn, behind which renewals wait too: its clock went on, so every live
                # lease would expire at once though no worker could renew; each gets a term from now instead.
                # (Read in the turn: a stall while this pass waited for it counts.)
                now, last = self._elapsed(), self._last_reap
                self._last_reap = now
                late_s = self.config.reap_interval_s + max(2.0, self.config.lease_s / 3)
                stalled = last is not None and now - last > late_s
                if stalled and (extended := self.queue.extend_leases(self.config.lease_s)):
                    log.warning("the service did not run for %.0f s (stopped, paused or starved); %d live lease(s) "
                                "extended by %.0f s so their workers can renew", now - last, extended,
                                self.config.lease_s)
                if self.storage.down_since is not None:
                    extended = self.queue.extend_leases(self.config.lease_s)
                    down_s = self.storage.writes_work()
                    if extended and down_s is not None:  # (with no live lease this write proves little: no line)
                        log.warning("storage writable again after %.0f s; %d live lease(s) extended by %.0f s so "
                                    "their workers can renew", down_s, extended, self.config.lease_s)
                expired = self.queue.expire_leases()
        finally:  # the gauges also while writes fail: the disk's free space is what an operator is alerted on
            self.storage.read("the queue, catalog and registry for the metrics",
                              lambda: self.metrics.read_stores(self.queue, self.catalog, self.context.registry))
        for request in expired:
            log.info("lease of %s expired (attempt %d)", request.id, request.attempts)
            self._publish_lease_end(request, "lease expired")
