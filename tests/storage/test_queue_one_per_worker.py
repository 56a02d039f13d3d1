"""``RequestQueue.lease(one_per_worker=True)``: a worker that holds a live lease gets that one again, never a
second (the service leases so: a worker's lease query asked again after a late answer must not leave a lease
behind that no worker knows of)."""

from __future__ import annotations

import threading
from pathlib import Path


from storage.queue import RequestQueue
from storage.requests import RequestStatus
from tests.storage.test_queue import new


def test_a_worker_holding_a_lease_gets_it_again_with_its_token_and_a_longer_term(queue: RequestQueue) -> None:
    a, _ = queue.enqueue(new(priority=1.0), now=0.0)
    b, _ = queue.enqueue(new(), now=0.0)
    first = queue.lease("w1", lease_s=10, now=1.0, one_per_worker=True)
    again = queue.lease("w1", lease_s=10, now=5.0, one_per_worker=True)
    assert (first.request.id, first.token, first.expires_at, first.again) == (a.id, 1, 11.0, False)
    assert (again.request.id, again.token, again.expires_at, again.again) == (a.id, 1, 15.0, True)
    assert queue.lease("w1", lease_s=10, now=2.0, one_per_worker=True).expires_at == 15.0  # never shortened
    assert queue.lease("w1", shapes=["nothing-queued"], lease_s=10, now=5.0, one_per_worker=True).request.id == a.id
    held = queue.get(a.id)
    assert (held.status, held.token, held.attempts, held.lease_expires) == (RequestStatus.LEASED, 1, 0, 15.0)
    assert queue.get(b.id).status == RequestStatus.QUEUED
    assert queue.expire_leases(now=14.0) == []  # the term the last answer gave
    assert queue.renew(a.id, first.token, "w1", lease_s=10, now=14.0) == 24.0  # either answer's token is live
    assert queue.complete(a.id, again.token, "ep-a", worker_id="w1", now=15.0)
    nxt = queue.lease("w1", lease_s=10, now=16.0, one_per_worker=True)  # done with it: the next one
    assert (nxt.request.id, nxt.token, nxt.again) == (b.id, 1, False)
    assert queue.lease("w2", now=16.0, one_per_worker=True) is None


def test_a_lease_past_its_expiry_not_yet_reaped_is_answered_again_not_doubled(queue: RequestQueue) -> None:
    a, _ = queue.enqueue(new(priority=1.0), now=0.0)
    b, _ = queue.enqueue(new(), now=0.0)
    queue.lease("w1", lease_s=1, now=0.0, one_per_worker=True)
    again = queue.lease("w1", lease_s=10, now=30.0, one_per_worker=True)  # its query waited past the term
    assert (again.request.id, again.token, again.expires_at, again.again) == (a.id, 1, 40.0, True)
    assert queue.expire_leases(now=31.0) == [] and queue.get(b.id).status == RequestStatus.QUEUED


def test_without_it_one_worker_id_may_hold_several_leases(queue: RequestQueue) -> None:
    """The queue's own callers (benches, tests, tools) that lease in bulk under one name keep doing so."""
    for _ in range(2):
        queue.enqueue(new())
    assert queue.lease("bench").request.id != queue.lease("bench").request.id
    assert queue.counts()["leased"] == 2


def test_concurrent_lease_calls_of_one_worker_grant_once(tmp_path: Path) -> None:
    """From several connections (as from several processes): SQLite's write lock orders them, and each
    sees the lease the first granted."""
    db = tmp_path / "catalog.sqlite"
    with RequestQueue(db) as q:
        q.enqueue_many([new() for _ in range(8)])
    queues = [RequestQueue(db) for _ in range(8)]
    start = threading.Barrier(len(queues))
    leases = []

    def ask(q: RequestQueue) -> None:
        start.wait()
        leases.append(q.lease("w1", lease_s=30, one_per_worker=True))

    threads = [threading.Thread(target=ask, args=(q,)) for q in queues]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    try:
        assert len(leases) == 8 and len({(x.request.id, x.token) for x in leases}) == 1
        assert sorted(x.again for x in leases) == [False] + [True] * 7
        assert queues[0].counts()["leased"] == 1 and queues[0].counts()["queued"] == 7
    finally:
        for q in queues:
            q.close()
