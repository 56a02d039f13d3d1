"""The request queue on real SQLite files: lifecycle, fencing, reaping, ordering. (Durability and concurrency:
test_queue_durability.py.)"""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from storage.errors import QueueError, StaleLeaseError
from storage.queue import RequestQueue, steady_clock
from storage.request_table import LEASE_SQL
from storage.requests import (
    TRANSITIONS,
    IllegalTransitionError,
    NewRequest,
    RequestStatus,
    UnknownRequestError,
    check_transition,
)

START = {"shape": "T", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.0]}


def new(shape: str = "T", priority: float = 0.0, **kw) -> NewRequest:
    return NewRequest(task="push", shape=shape, start_state=dict(START, shape=shape), priority=priority, **kw)


def test_enqueue_lease_complete(queue: RequestQueue) -> None:
    req, created = queue.enqueue(new(reason={"model_version": "m1", "score": 0.5}), now=100.0)
    assert created and req.status == RequestStatus.QUEUED and req.token == 0 and req.attempts == 0
    assert req.reason == {"model_version": "m1", "score": 0.5} and req.start_state["shape"] == "T"
    lease = queue.lease("w1", lease_s=10, now=101.0)
    assert lease is not None and lease.request.id == req.id and lease.token == 1 and lease.expires_at == 111.0
    assert queue.get(req.id).status == RequestStatus.LEASED and queue.get(req.id).worker_id == "w1"
    assert queue.renew(req.id, 1, "w1", lease_s=10, now=105.0) == 115.0
    assert queue.complete(req.id, 1, "ep1", worker_id="w1", now=106.0) is True
    done = queue.get(req.id)
    assert done.status == RequestStatus.DONE and done.episode_id == "ep1" and done.lease_expires is None
    assert queue.lease("w1", now=107.0) is None
    assert queue.counts() == {"queued": 0, "leased": 0, "done": 1, "dead": 0, "cancelled": 0}


def test_duplicate_completion_reported_and_other_completion_refused(queue: RequestQueue) -> None:
    req, _ = queue.enqueue(new())
    lease = queue.lease("w1")
    assert queue.complete(req.id, lease.token, "ep1") is True
    assert queue.complete(req.id, lease.token, "ep1") is False  # the same upload again: acknowledged
    with pytest.raises(StaleLeaseError):
        queue.complete(req.id, lease.token, "ep2")  # another episode for a done request
    assert queue.get(req.id).episode_id == "ep1"


def test_complete_inside_a_callers_transaction(queue: RequestQueue, tmp_path: Path) -> None:
    req, _ = queue.enqueue(new())
    lease = queue.lease("w1")
    conn = sqlite3.connect(tmp_path / "catalog.sqlite", isolation_level=None)
    conn.execute("BEGIN IMMEDIATE")
    assert queue.complete(req.id, lease.token, "ep1", conn=conn) is True
    conn.execute("ROLLBACK")  # the caller's transaction failed: the completion goes with it
    assert queue.get(req.id).status == RequestStatus.LEASED
    conn.execute("BEGIN IMMEDIATE")
    assert queue.complete(req.id, lease.token, "ep1", conn=conn) is True
    conn.execute("COMMIT")
    conn.close()
    assert queue.get(req.id).status == RequestStatus.DONE


def test_stale_token_or_wrong_worker_refused(queue: RequestQueue) -> None:
    req, _ = queue.enqueue(new())
    first = queue.lease("w1", lease_s=5, now=0.0)
    assert queue.reap_expired(now=10.0) == 1
    second = queue.lease("w2", lease_s=5, now=11.0)
    assert second.token == first.token + 1
    for call in (lambda: queue.renew(req.id, first.token, "w1", now=12.0),
                 lambda: queue.complete(req.id, first.token, "ep-late", now=12.0),
                 lambda: queue.fail(req.id, first.token, "late", now=12.0),
                 lambda: queue.renew(req.id, second.token, "w1", now=12.0),
                 lambda: queue.complete(req.id, second.token, "ep", worker_id="w1", now=12.0)):
        with pytest.raises(StaleLeaseError):
            call()
    assert queue.get(req.id).status == RequestStatus.LEASED
    assert queue.complete(req.id, second.token, "ep", worker_id="w2", now=12.0) is True


def test_fail_requeues_then_dead_after_max_attempts_and_never_leased_again(queue: RequestQueue) -> None:
    req, _ = queue.enqueue(new(max_attempts=3))
    for attempt in range(1, 4):
        lease = queue.lease("w1")
        assert lease.request.id == req.id and lease.token == attempt
        after = queue.fail(req.id, lease.token, f"boom {attempt}", worker_id="w1")
        assert after.attempts == attempt
    dead = queue.get(req.id)
    assert dead.status == RequestStatus.DEAD and dead.last_error == "boom 3"
    assert queue.lease("w1") is None


def test_poison_request_that_kills_its_workers_ends_dead(queue: RequestQueue) -> None:
    """Expiry and worker loss count attempts too, so a request that never completes cannot loop."""
    req, _ = queue.enqueue(new(max_attempts=2))
    queue.lease("w1", lease_s=1, now=0.0)
    assert queue.release_worker("w1", now=0.5) == 1
    assert queue.get(req.id).status == RequestStatus.QUEUED and queue.get(req.id).attempts == 1
    queue.lease("w2", lease_s=1, now=1.0)
    ended = queue.expire_leases(now=5.0)
    assert [r.id for r in ended] == [req.id] and ended[0].status == RequestStatus.DEAD
    assert "lease expired" in ended[0].last_error and "w2" in ended[0].last_error
    assert queue.lease("w3", now=6.0) is None


def test_reap_only_expired_and_renew_keeps_alive(queue: RequestQueue) -> None:
    a, _ = queue.enqueue(new(priority=2))
    b, _ = queue.enqueue(new(priority=1))
    la = queue.lease("w1", lease_s=10, now=0.0)
    lb = queue.lease("w2", lease_s=10, now=0.0)
    assert (la.request.id, lb.request.id) == (a.id, b.id)
    queue.renew(a.id, la.token, "w1", lease_s=10, now=8.0)
    assert queue.reap_expired(now=10.0) == 1
    assert queue.get(a.id).status == RequestStatus.LEASED
    assert queue.get(b.id).status == RequestStatus.QUEUED and queue.get(b.id).attempts == 1


def test_extend_leases_gives_every_live_lease_at_least_that_long_and_shortens_none(queue: RequestQueue) -> None:
    """After a storage outage (no worker could renew): a lease with less left gets ``lease_s`` from now, a longer
    one keeps its own, and only those extended are counted."""
    long_, _ = queue.enqueue(new(priority=2))
    short, _ = queue.enqueue(new(priority=1))
    queued, _ = queue.enqueue(new(priority=0))
    queue.lease("w1", lease_s=100, now=0.0)
    queue.lease("w2", lease_s=5, now=0.0)
    assert queue.extend_leases(10, now=1.0) == 1
    assert queue.get(long_.id).lease_expires == 100.0 and queue.get(short.id).lease_expires == 11.0
    assert queue.get(queued.id).status == RequestStatus.QUEUED and queue.get(queued.id).lease_expires is None
    assert queue.extend_leases(10, now=1.0) == 0  # (both have at least 10 s left now)


def test_release_worker_only_touches_that_worker(queue: RequestQueue) -> None:
    ids = [queue.enqueue(new())[0].id for _ in range(3)]
    queue.lease("w1")
    queue.lease("w1")
    queue.lease("w2")
    assert queue.release_worker("w1") == 2
    assert queue.release_worker("w1") == 0
    statuses = sorted(queue.get(i).status.value for i in ids)
    assert statuses == ["leased", "queued", "queued"]


def test_graceful_release_counts_no_attempt(queue: RequestQueue) -> None:
    req, _ = queue.enqueue(new(max_attempts=1))
    lease = queue.lease("w1")
    after = queue.release(req.id, lease.token, worker_id="w1")
    assert after.status == RequestStatus.QUEUED and after.attempts == 0
    assert queue.lease("w2").token == 2


def test_cancel_and_retry(queue: RequestQueue) -> None:
    queued, _ = queue.enqueue(new())
    leased, _ = queue.enqueue(new())
    assert queue.cancel(queued.id).status == RequestStatus.CANCELLED
    lease = queue.lease("w1")
    assert lease.request.id == leased.id
    queue.cancel(leased.id)
    with pytest.raises(StaleLeaseError):  # the worker of a cancelled request cannot complete it
        queue.complete(leased.id, lease.token, "ep")
    again = queue.retry(leased.id)
    assert again.status == RequestStatus.QUEUED and again.attempts == 0
    relet = queue.lease("w2")
    assert relet.request.id == leased.id and relet.token == lease.token + 1  # token stays monotonic
    with pytest.raises(StaleLeaseError):
        queue.renew(leased.id, lease.token, "w1")


def test_retry_dead_resets_attempts_keeps_error(queue: RequestQueue) -> None:
    req, _ = queue.enqueue(new(max_attempts=1))
    queue.fail(req.id, queue.lease("w1").token, "sim crashed")
    assert queue.get(req.id).status == RequestStatus.DEAD
    back = queue.retry(req.id)
    assert back.status == RequestStatus.QUEUED and back.attempts == 0 and back.last_error == "sim crashed"


@pytest.mark.parametrize("action, status", [
    ("cancel", "done"), ("cancel", "dead"), ("cancel", "cancelled"),
    ("retry", "queued"), ("retry", "leased"), ("retry", "done"),
    ("prioritize", "done"),
])
def test_illegal_transitions_refused(queue: RequestQueue, action: str, status: str) -> None:
    req, _ = queue.enqueue(new(max_attempts=1))
    if status != "queued":
        lease = queue.lease("w1")
        if status == "done":
            queue.complete(req.id, lease.token, "ep")
        elif status == "dead":
            queue.fail(req.id, lease.token, "x")
        elif status == "cancelled":
            queue.cancel(req.id)
    before = queue.get(req.id)
    assert before.status.value == status
    call = {"cancel": lambda: queue.cancel(req.id), "retry": lambda: queue.retry(req.id),
            "prioritize": lambda: queue.prioritize(req.id, 5.0)}[action]
    with pytest.raises(IllegalTransitionError, match=f"found {status}"):
        call()
    assert queue.get(req.id) == before


def test_transition_table_is_the_only_authority() -> None:
    check_transition("lease", RequestStatus.QUEUED, RequestStatus.LEASED)
    with pytest.raises(IllegalTransitionError):
        check_transition("complete", RequestStatus.QUEUED, RequestStatus.DONE)
    with pytest.raises(IllegalTransitionError):
        check_transition("fail", RequestStatus.LEASED, RequestStatus.DONE)
    reachable = {t for _, targets in TRANSITIONS.values() for t in targets}
    assert reachable == set(RequestStatus)
    assert all(RequestStatus.DONE not in sources for sources, _ in TRANSITIONS.values())  # done is final


def test_unknown_request(queue: RequestQueue) -> None:
    for call in (lambda: queue.get("nope"), lambda: queue.cancel("nope"), lambda: queue.retry("nope"),
                 lambda: queue.renew("nope", 1, "w"), lambda: queue.complete("nope", 1, "ep")):
        with pytest.raises(UnknownRequestError):
            call()


def test_priority_then_age_ordering(queue: RequestQueue) -> None:
    low, _ = queue.enqueue(new(priority=1.0), now=1.0)
    old_high, _ = queue.enqueue(new(priority=5.0), now=2.0)
    new_high, _ = queue.enqueue(new(priority=5.0), now=3.0)
    same_time, _ = queue.enqueue(new(priority=5.0), now=3.0)
    assert [r.id for r in queue.list(status="queued")] == [old_high.id, new_high.id, same_time.id, low.id]
    order = [queue.lease("w", now=10.0).request.id for _ in range(4)]
    assert order == [old_high.id, new_high.id, same_time.id, low.id]


def test_equal_priorities_lease_in_arrival_order_whatever_the_clock_said(queue: RequestQueue) -> None:
    """After a restart that found the wall clock stepped back, a new request is stamped earlier than the ones
    already queued: it still waits its turn (by rowid), it does not jump the queue for the length of the step."""
    first, _ = queue.enqueue(new(priority=5.0), now=1_000.0)
    second, _ = queue.enqueue(new(priority=5.0), now=2_000.0)
    after_step_back, _ = queue.enqueue(new(priority=5.0), now=500.0)
    urgent, _ = queue.enqueue(new(priority=9.0), now=400.0)
    expected = [urgent.id, first.id, second.id, after_step_back.id]
    assert [r.id for r in queue.list(status="queued")] == expected
    assert [queue.lease("w", now=3_000.0).request.id for _ in range(4)] == expected


def test_a_file_with_the_age_ordered_index_is_brought_to_the_arrival_ordered_one(tmp_path: Path) -> None:
    """A file of the last version (index on (priority, created)) is upgraded on open: the arrival-ordered index is
    made, and leasing uses it; the old one stays, for an older service still leasing on the file."""
    path = tmp_path / "catalog.sqlite"
    RequestQueue(path).close()
    with sqlite3.connect(path) as conn:
        conn.execute("DROP INDEX requests_fifo")
        conn.execute("CREATE INDEX requests_queued ON requests (priority DESC, created) WHERE status = 'queued'")
    with RequestQueue(path) as queue:
        a, _ = queue.enqueue(new(priority=1.0), now=2.0)
        b, _ = queue.enqueue(new(priority=1.0), now=1.0)
        assert queue.lease("w").request.id == a.id
    with sqlite3.connect(path) as conn:
        names = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'index'")}
        plan = " ".join(r[3] for r in conn.execute("EXPLAIN QUERY PLAN " + LEASE_SQL.format(filters=""),
                                                    ("w", 1.0, 1.0)))
    assert {"requests_fifo", "requests_queued"} <= names
    assert "USING INDEX requests_fifo" in plan and "TEMP B-TREE" not in plan, plan


def test_prioritize_changes_order(queue: RequestQueue) -> None:
    a, _ = queue.enqueue(new(priority=1.0), now=1.0)
    b, _ = queue.enqueue(new(priority=2.0), now=2.0)
    assert queue.prioritize(a.id, 3.0).priority == 3.0
    assert queue.lease("w").request.id == a.id


def test_capabilities_matching(queue: RequestQueue) -> None:
    t, _ = queue.enqueue(new("T", priority=9.0))
    box, _ = queue.enqueue(new("box", priority=1.0))
    assert queue.lease("w", tasks=["push"], shapes=["disk"]) is None
    assert queue.lease("w", tasks=["other"]) is None
    assert queue.lease("w", tasks=["push"], shapes=["box", "disk"]).request.id == box.id
    assert queue.lease("w", tasks=[], shapes=[]).request.id == t.id


def test_idempotency_key(queue: RequestQueue) -> None:
    first, created = queue.enqueue(new(idempotency_key="k1"))
    again, created_again = queue.enqueue(new(priority=9.0, idempotency_key="k1"))
    assert created and not created_again and again.id == first.id and again.priority == 0.0
    other, created_other = queue.enqueue(new(idempotency_key="k2"))
    assert created_other and other.id != first.id
    batch = queue.enqueue_many([new(idempotency_key="k3"), new(idempotency_key="k3")])
    assert [c for _, c in batch] == [True, False] and batch[0][0].id == batch[1][0].id
    assert queue.counts()["queued"] == 3


def test_bad_new_request_refused() -> None:
    with pytest.raises(QueueError, match="steps"):
        new(steps=0)
    with pytest.raises(QueueError, match="max_attempts"):
        new(max_attempts=0)
    with pytest.raises(QueueError, match="task"):
        NewRequest(task="", shape="T", start_state=START)


def test_survives_reopening(tmp_path: Path) -> None:
    path = tmp_path / "catalog.sqlite"
    q = RequestQueue(path)
    done, _ = q.enqueue(new(idempotency_key="a"))
    q.complete(done.id, q.lease("w1").token, "ep1")
    leased, _ = q.enqueue(new())
    lease = q.lease("w1", lease_s=30, now=0.0)
    waiting, _ = q.enqueue(new(priority=-1))
    q.close()
    with pytest.raises(QueueError, match="closed"):
        q.get(done.id)

    q2 = RequestQueue(path)
    assert q2.get(done.id).status == RequestStatus.DONE and q2.get(done.id).episode_id == "ep1"
    assert q2.get(leased.id).status == RequestStatus.LEASED
    assert q2.complete(leased.id, lease.token, "ep2", now=1.0) is True
    assert q2.get(waiting.id).status == RequestStatus.QUEUED
    assert q2.enqueue(new(idempotency_key="a"))[1] is False
    assert q2.counts() == {"queued": 1, "leased": 0, "done": 2, "dead": 0, "cancelled": 0}
    conn = sqlite3.connect(path)
    assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    conn.close()
    q2.close()


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 0, -1, "10"])
def test_a_lease_time_must_be_a_finite_positive_number(queue: RequestQueue, bad) -> None:
    """SQLite stores NaN as NULL: a NaN lease would never expire."""
    req, _ = queue.enqueue(new())
    with pytest.raises(QueueError, match="lease_s: expected a finite number > 0"):
        queue.lease("w1", lease_s=bad, now=0.0)
    lease = queue.lease("w1", lease_s=10, now=0.0)
    with pytest.raises(QueueError, match="lease_s"):
        queue.renew(req.id, lease.token, "w1", lease_s=bad, now=1.0)
    assert [r.id for r in queue.expire_leases(now=11.0)] == [req.id]  # the lease kept its finite expiry


@pytest.mark.parametrize("bad", [float("nan"), float("-inf"), "high", None])
def test_a_priority_must_be_a_finite_number(queue: RequestQueue, bad) -> None:
    with pytest.raises(QueueError, match="priority: expected a finite number"):
        new(priority=bad)
    req, _ = queue.enqueue(new())
    with pytest.raises(QueueError, match="priority"):
        queue.prioritize(req.id, bad)
    assert queue.get(req.id).priority == 0.0


def test_sqlite_errors_on_reads_are_queue_errors(queue: RequestQueue) -> None:
    """The service's maintenance loop handles QueueError; a raw sqlite3 error would end it."""
    req, _ = queue.enqueue(new())
    with sqlite3.connect(queue.db_path) as other:
        other.execute("ALTER TABLE requests RENAME TO requests_elsewhere")  # what a damaged file can look like
        other.execute("ALTER TABLE request_counts RENAME TO counts_elsewhere")
    for read in (queue.counts, lambda: queue.get(req.id), queue.list):
        with pytest.raises(QueueError, match="cannot read the queue"):
            read()


def test_a_steady_clock_moves_with_the_time_elapsed_not_with_steps_of_the_wall_clock() -> None:
    wall, elapsed = [1_000.0], [5.0]
    clock = steady_clock(lambda: wall[0], lambda: elapsed[0])
    wall[0] += 3600.0  # NTP steps the wall clock an hour forward
    elapsed[0] += 2.0
    assert clock() == 1_002.0
    wall[0] -= 7200.0
    assert clock() == 1_002.0


def test_extend_leases_exactly_gives_every_live_lease_exactly_that_term(queue: RequestQueue) -> None:
    for i in range(3):
        queue.enqueue(new(), now=float(i))
    near, far = queue.lease("w1", lease_s=1, now=0.0), queue.lease("w2", lease_s=86400, now=0.0)
    assert queue.extend_leases(10, now=5.0, exactly=True) == 2
    assert {queue.get(x.request.id).lease_expires for x in (near, far)} == {15.0}
    assert queue.get(queue.list(RequestStatus.QUEUED)[0].id).lease_expires is None  # a queued one untouched
