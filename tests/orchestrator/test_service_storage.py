"""The service when its storage is slow or failing: a lease query that waits behind another process's write
lock past the worker's timeout, reads that fail while writes work, a seed that cannot be queued, writes that
fail on any path (an upload, a lease, an operator's queue change), each an outage that holds every lease."""

from __future__ import annotations

import errno
import functools
import logging
import os
import socket
import sqlite3
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from orchestrator import messages, protocol, transport
from orchestrator import service as service_module
from orchestrator.messages import LeaseGrant
from orchestrator.metrics import ServiceMetrics
from orchestrator.protocol import ErrorCode
from orchestrator.serviceconfig import ServiceConfig, ServiceError
from orchestrator.service import Service
from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
import storage.database
from storage.catalog import Catalog
from storage.errors import CatalogUnavailableError
from storage.queue import RequestQueue
from storage.requests import NewRequest, RequestStatus
from tests.conftest import wait_for
from tests.orchestrator.conftest import FailingSyncs
from tests.orchestrator.test_service import START, call, episode_bytes, lease, new_request, refused, upload


def port_free(port: int) -> bool:
    """Whether nothing listens on 127.0.0.1:``port`` any more (a closed Zenoh session's listener is gone)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name == "orchestrator.service"]


def refuse_inserts(db_path: Path) -> None:
    """The catalog's requests table refuses every insert from now on (a real SQLite error, raised by SQLite)."""
    RequestQueue(db_path).close()  # the table exists
    with sqlite3.connect(db_path) as conn:
        conn.execute("CREATE TRIGGER refuse_inserts BEFORE INSERT ON requests "
                     "BEGIN SELECT RAISE(ABORT, 'no new requests here'); END")


def test_a_lease_query_asked_again_behind_a_write_lock_leaves_one_lease(service, client, keys, data_dir) -> None:
    """Another process holds the catalog's write lock past the worker's timeout; the worker asks again (as
    ``Worker._lease`` does); once the lock goes, both queries are answered. The worker holds one lease, the
    one its answer names, with no attempt counted -- not a second lease it never heard of, which would
    expire and count an attempt against a request no worker failed."""
    first, _ = service.queue.enqueue(new_request(priority=1.0))
    other, _ = service.queue.enqueue(new_request())
    msg = messages.LeaseRequest(worker_id="w1").to_json()
    writer = sqlite3.connect(Catalog(data_dir).db_path, isolation_level=None)  # a CLI's write, a backup, ...
    writer.execute("BEGIN IMMEDIATE")
    replies: list[bytes] = []
    try:
        with pytest.raises(transport.NoReplyError):
            transport.query(client, keys.lease, msg, timeout=0.5)  # the service waits for the lock
        again = threading.Thread(target=lambda: replies.append(transport.query(client, keys.lease, msg, timeout=30)))
        again.start()
    finally:
        writer.execute("COMMIT")  # released once the first query has timed out and the second is asked
        writer.close()
    again.join(30)
    grant = LeaseGrant.from_dict(protocol.parse_reply(replies[0])["grant"])
    leased = service.queue.list(RequestStatus.LEASED)
    assert [(r.id, r.worker_id, r.token, r.attempts) for r in leased] == [(first.id, "w1", grant.token, 0)]
    assert grant.request_id == first.id and service.queue.get(other.id).status == RequestStatus.QUEUED
    assert upload(client, keys, grant, episode_bytes(grant))["request_id"] == first.id
    done = service.queue.get(first.id)
    assert (done.status, done.attempts) == (RequestStatus.DONE, 0)


class FailingReads(ServiceMetrics):
    """Gauges whose reads fail every time (a catalog that cannot be read for now), while writes work."""

    def __init__(self) -> None:
        super().__init__()
        self.reads = 0

    def read_stores(self, queue, catalog, registry) -> None:
        self.reads += 1
        raise CatalogUnavailableError("cannot read the catalog: disk I/O error")


def test_failing_reads_are_a_warning_and_hold_no_lease(make_service, client, keys, caplog) -> None:
    """Only a failed write means no worker can renew; a read that keeps failing must not keep every lease
    alive (extended at each reap), nor say ERROR every reap interval."""
    metrics = FailingReads()
    with caplog.at_level(logging.INFO, logger="orchestrator.service"):
        service = make_service(lease_s=0.5, metrics=metrics)
        request, _ = service.queue.enqueue(new_request())
        lease(client, keys)  # and never renewed
        expired = wait_for(lambda: (r := service.queue.get(request.id)).status == RequestStatus.QUEUED and r,
                           message="the unrenewed lease to expire")
        reads = metrics.reads
        wait_for(lambda: metrics.reads >= reads + 5, message="more reaps")
    assert expired.attempts == 1
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text
    warned = warnings(caplog)
    assert len(warned) == 1, warned  # said once, not once a reap
    assert warned[0].startswith("cannot read the queue, catalog and registry for the metrics: cannot read the "
                                "catalog: disk I/O error"), warned
    assert service.storage.down_since is None


def test_a_planner_whose_reads_fail_is_a_warning_until_they_work(make_service, client, keys, caplog) -> None:
    failures = [CatalogUnavailableError("cannot read the champion: disk I/O error")] * 2
    planned = threading.Semaphore(0)

    class Scoring:
        name = "scoring"

        def seed(self, n: int) -> list[NewRequest]:
            return [new_request() for _ in range(n)]

        def plan(self, episodes) -> list[NewRequest]:
            try:
                if failures:
                    raise failures.pop()
                return [new_request("L") for _ in episodes]
            finally:
                planned.release()

    with caplog.at_level(logging.INFO, logger="orchestrator.service"):
        service = make_service(planner=lambda ctx: Scoring(), seed_requests=3)
        for _ in range(3):
            grant = lease(client, keys)
            upload(client, keys, grant, episode_bytes(grant))
            assert planned.acquire(timeout=30)
        wait_for(lambda: service.queue.counts()["queued"] == 1, message="the third plan's request")
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text
    warned = warnings(caplog)
    assert len(warned) == 1 and warned[0].startswith("cannot read what planner scoring plans with: cannot read "
                                                     "the champion"), warned
    assert "reading what planner scoring plans with works again" in caplog.text
    assert service.storage.down_since is None


def test_a_seed_that_cannot_be_queued_stops_what_the_start_had_started(data_dir, endpoint, port, namespace) -> None:
    refuse_inserts(Catalog(data_dir).db_path)
    service = Service(ServiceConfig(data_dir=data_dir, namespace=namespace, listen=(endpoint,), seed_requests=2,
                                    planner=lambda ctx: UniformPlanner(UniformPlannerConfig(steps=5),
                                                                       np.random.default_rng(0))))
    with pytest.raises(ServiceError, match="cannot seed the queue with 2 request.s.: .*no new requests here"):
        service.start()
    assert service.session.is_closed()
    wait_for(lambda: port_free(port), message="the service's Zenoh listener to close")
    service.stop()  # (idempotent: the CLI stops what it started whatever the start did)


class CountedReaps(ServiceMetrics):
    """The real gauges, noting when each reap has read them (once a reap, after its expiries)."""

    def __init__(self) -> None:
        super().__init__()
        self.reaps: list[float] = []

    def read_stores(self, queue, catalog, registry) -> None:
        super().read_stores(queue, catalog, registry)
        self.reaps.append(time.time())


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS], ids=["full", "read-only"])
def test_an_upload_the_disk_refuses_holds_every_lease_until_it_goes_in(make_service, client, keys, data_dir,
                                                                       monkeypatch, caplog, code) -> None:
    """The episodes' disk is full (or read-only) while the catalog's rows stay writable: uploads are refused
    `unavailable` (the worker keeps its episode and sends it again) and nothing else fails. That is an outage of the
    storage as much as one a renew meets: the reaper extends the lease instead of expiring it (an attempt counted,
    and the upload then refused as stale: the episode dropped). Not renewed here, so that only the reaper keeps it:
    a worker's renewals can fail or wait as its uploads do. Once the disk has room, the same upload completes the
    request; the outage, ended by each reap and begun again by the next upload, is said once."""
    metrics = CountedReaps()
    with caplog.at_level(logging.INFO, logger="orchestrator"):
        service = make_service(lease_s=1.0, metrics=metrics)
        request, _ = service.queue.enqueue(new_request())
        grant = lease(client, keys)
        data = episode_bytes(grant)
        disk = FailingSyncs(data_dir / "episodes", monkeypatch, code=code)

        def sent_again() -> bool:  # as Worker._upload does after each `unavailable`
            why = refused(ErrorCode.UNAVAILABLE, upload, client, keys, grant, data)
            assert os.strerror(code) in why, why
            return sum(at > grant.expires_at for at in metrics.reaps) >= 3

        wait_for(sent_again, message="three reaps after the end of the lease's first term")
        held = service.queue.get(request.id)
        assert (held.status, held.token, held.attempts) == (RequestStatus.LEASED, grant.token, 0)
        disk.heal()
        body = upload(client, keys, grant, data)
        wait_for(lambda: service.storage.down_since is None, message="the reaper to see the storage back")
    assert "duplicate" not in body and disk.failed >= 3
    done = service.queue.get(request.id)
    assert (done.status, done.episode_id, done.attempts) == (RequestStatus.DONE, body["episode_id"], 0)
    assert Catalog(data_dir).verify(body["episode_id"])
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].startswith("storage unavailable: cannot store episode"), errors
    assert os.strerror(code) in errors[0]


@pytest.mark.parametrize("op", ["lease", "renew", "fail", "release", "queue.add"])
def test_a_write_refused_past_the_busy_timeout_is_an_outage_whichever_path_met_it(make_service, client, keys,
                                                                                 data_dir, monkeypatch, op) -> None:
    """Another process holds the catalog's write lock past the service's busy timeout; whatever write met it
    is refused `unavailable`, changes nothing, and the storage is down (no lease expires until a write works):
    not only a renew's. (The reaper, which would meet the lock too, does not run meanwhile.)"""
    monkeypatch.setattr(service_module, "RequestQueue", functools.partial(RequestQueue, busy_timeout_s=0.2))
    metrics = CountedReaps()
    service = make_service(reap_interval_s=120.0, metrics=metrics)  # (one reap now, the next long after)
    wait_for(lambda: metrics.reaps, message="the first reap, at start")
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    before = service.queue.list()
    messages_for = {
        "lease": (keys.lease, messages.LeaseRequest(worker_id="w2")),
        "renew": (keys.renew, messages.RenewRequest(request_id=request.id, token=grant.token, worker_id="w1")),
        "fail": (keys.fail, messages.FailRequest(request_id=request.id, token=grant.token, worker_id="w1",
                                                 error="boom")),
        "release": (keys.release, messages.ReleaseRequest(request_id=request.id, token=grant.token,
                                                          worker_id="w1")),
        "queue.add": (keys.admin("queue.add"), messages.AdminRequest(op="queue.add", args={
            "task": "push", "shape": "T", "start_state": {**START, "shape": "T"}})),
    }
    key, sent = messages_for[op]
    writer = sqlite3.connect(Catalog(data_dir).db_path, isolation_level=None)  # a CLI's write, a backup, ...
    writer.execute("BEGIN IMMEDIATE")
    try:
        why = refused(ErrorCode.UNAVAILABLE, call, client, key, sent.to_json())
        down = service.storage.down_since
    finally:
        writer.execute("ROLLBACK")
        writer.close()
    assert "database is locked" in why, why
    assert down is not None, f"a {op} refused for a locked database left the storage 'up'"
    assert service.queue.list() == before


@pytest.mark.parametrize("path", ["renew", "upload"])
def test_an_outage_is_known_before_the_writer_turn_passes_on(make_service, client, keys, data_dir, monkeypatch,
                                                             path) -> None:
    """A write refused for a locked database is noted as an outage while its path still holds the writer turn:
    a reap that took the turn in between would see the storage up and expire the leases nobody could renew. The
    upload's ingest noted it only after the catalog had let the turn go (a helper's reproduction: a busy timeout
    past the lease, the whole fleet's leases expired by the next reap)."""
    monkeypatch.setattr(service_module, "RequestQueue", functools.partial(RequestQueue, busy_timeout_s=0.2))
    monkeypatch.setattr(storage.database, "BUSY_TIMEOUT_MS", 200)  # the catalog's, for the upload's ingest
    metrics = CountedReaps()
    service = make_service(reap_interval_s=120.0, metrics=metrics)
    wait_for(lambda: metrics.reaps, message="the first reap, at start")
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    held_when_noted = []
    real = service.storage.write_failed
    monkeypatch.setattr(service.storage, "write_failed",
                        lambda exc: (held_when_noted.append(service._writes.locked()), real(exc)))
    data = episode_bytes(grant)
    writer = sqlite3.connect(Catalog(data_dir).db_path, isolation_level=None)
    writer.execute("BEGIN IMMEDIATE")
    try:
        if path == "renew":
            refused(ErrorCode.UNAVAILABLE, call, client, keys.renew,
                    messages.RenewRequest(request_id=request.id, token=grant.token, worker_id="w1").to_json())
        else:
            assert "database is locked" in refused(ErrorCode.UNAVAILABLE, upload, client, keys, grant, data)
    finally:
        writer.execute("ROLLBACK")
        writer.close()
    assert held_when_noted[:1] == [True], held_when_noted  # (the upload's staging notes it again, after)


def test_the_gauges_are_read_while_writes_fail(make_service, data_dir, monkeypatch) -> None:
    """A reap whose write meets the storage down still reads the gauges: the disk's free space (what an operator
    is alerted on) must not freeze at its last value for the whole outage."""
    monkeypatch.setattr(service_module, "RequestQueue", functools.partial(RequestQueue, busy_timeout_s=0.1))
    metrics = CountedReaps()
    service = make_service(reap_interval_s=0.2, metrics=metrics)
    wait_for(lambda: metrics.reaps, message="the first reap, at start")
    writer = sqlite3.connect(Catalog(data_dir).db_path, isolation_level=None)  # a CLI's write, a backup, ...
    writer.execute("BEGIN IMMEDIATE")
    try:
        wait_for(lambda: service.storage.down_since is not None, message="a reap to meet the lock")
        read = len(metrics.reaps)
        wait_for(lambda: len(metrics.reaps) >= read + 2, message="the gauges read by two more reaps meanwhile")
        assert service.storage.down_since is not None
    finally:
        writer.execute("ROLLBACK")
        writer.close()
