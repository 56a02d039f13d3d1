"""Every transition of the queue at once, from threads that each play one worker (or the reaper, or an operator),
on one real SQLite file: whatever the interleaving, the lifecycle's invariants hold at the end."""

from __future__ import annotations

import threading
from collections import Counter
from pathlib import Path

import numpy as np

from storage.errors import StaleLeaseError
from storage.queue import RequestQueue
from storage.requests import IllegalTransitionError, NewRequest, RequestStatus

START = {"shape": "T", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.0]}
_Q, _L, _D, _X, _C = (RequestStatus.QUEUED, RequestStatus.LEASED, RequestStatus.DONE, RequestStatus.DEAD,
                      RequestStatus.CANCELLED)


class Log:
    """What each thread was told, under a lock."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.grants: list[tuple[str, int, str]] = []  # (request, token, worker) of each new lease
        self.done: dict[str, tuple[int, str]] = {}  # request -> (token, worker) of the completion that returned True

    def granted(self, request_id: str, token: int, worker: str) -> None:
        with self.lock:
            self.grants.append((request_id, token, worker))

    def completed(self, request_id: str, token: int, worker: str) -> None:
        with self.lock:
            assert request_id not in self.done, f"{request_id} completed twice"
            self.done[request_id] = (token, worker)


def _worker(queue: RequestQueue, name: str, log: Log, seed: int, rounds: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(rounds):
        lease = queue.lease(name, lease_s=0.05, one_per_worker=True)
        if lease is None:
            continue
        if not lease.again:
            log.granted(lease.request.id, lease.token, name)
        rid, token, roll = lease.request.id, lease.token, rng.random()
        try:
            if roll < 0.3:
                queue.renew(rid, token, name, lease_s=0.05)
            if roll < 0.05:
                if queue.complete(rid, token, f"ep-{rid}-{token}", worker_id=name):
                    log.completed(rid, token, name)
            elif roll < 0.35:
                queue.fail(rid, token, f"{name} failed token {token}", worker_id=name)
            elif roll < 0.7:
                queue.release(rid, token, worker_id=name)
            # else: walk away (the lease expires, or the worker is declared lost)
        except StaleLeaseError:
            pass  # the reaper, a loss or an operator got there first: told so, nothing changed


def _reaper(queue: RequestQueue, stop: threading.Event, workers: list[str], seed: int) -> None:
    rng = np.random.default_rng(seed)
    while not stop.is_set():
        queue.expire_leases()
        queue.release_worker_leases(str(rng.choice(workers)))


def _operator(queue: RequestQueue, ids: list[str], stop: threading.Event, seed: int) -> None:
    rng = np.random.default_rng(seed)
    while not stop.is_set():
        rid = str(rng.choice(ids))
        roll = rng.random()  # mostly retries: dead and cancelled requests come back for more churn
        action = (queue.cancel if roll < 0.1 else queue.retry if roll < 0.7
                  else lambda r: queue.prioritize(r, float(rng.integers(0, 5))))
        try:
            action(rid)
        except IllegalTransitionError:
            pass
        queue.enqueue(NewRequest(task="push", shape="T", start_state=START,  # a planner's, asked again and again
                                 idempotency_key=f"step-{int(rng.integers(0, 20))}"))
        queue.list(limit=50)  # `queue ls` while leasing
        queue.counts()


def test_every_transition_at_once_keeps_the_lifecycle(tmp_path: Path) -> None:
    queue = RequestQueue(tmp_path / "catalog.sqlite", background_checkpoint=True)
    try:
        ids = [r.id for r, _ in queue.enqueue_many([NewRequest(task="push", shape="T", start_state=START,
                                                               max_attempts=5) for _ in range(100)])]
        log, stop = Log(), threading.Event()
        names = [f"w{i}" for i in range(6)]
        workers = [threading.Thread(target=_worker, args=(queue, n, log, i, 1500)) for i, n in enumerate(names)]
        others = [threading.Thread(target=_reaper, args=(queue, stop, names, 99)),
                  threading.Thread(target=_operator, args=(queue, ids, stop, 7))]
        for t in workers + others:
            t.start()
        for t in workers:
            t.join(120)
        stop.set()
        for t in others:
            t.join(120)
        assert not any(t.is_alive() for t in workers + others)

        # Each new lease of a request has the next token: never two grants of one token (two holders at once).
        assert not [k for k, n in Counter((r, t) for r, t, _ in log.grants).items() if n > 1]
        everything = queue.list()
        keys = [r.idempotency_key for r in everything if r.idempotency_key is not None]
        assert len(keys) == len(set(keys)) <= 20 and len(everything) == len(ids) + len(keys)
        for rid in (r.id for r in everything):
            tokens = [t for r, t, _ in log.grants if r == rid]
            assert sorted(tokens) == list(range(1, len(tokens) + 1)), (rid, tokens)
            request = queue.get(rid)
            assert request.token == len(tokens)
            if request.status == _D:  # done by the holder of its latest token, with that lease's episode
                assert log.done[rid] == (request.token, request.worker_id)
                assert request.episode_id == f"ep-{rid}-{request.token}"
            else:
                assert rid not in log.done and request.episode_id is None
            if request.status == _X:
                assert request.attempts == request.max_attempts
            elif request.status in (_Q, _L):
                assert request.attempts < request.max_attempts
            if request.status != _L:  # only a live lease has an expiry
                assert request.lease_expires is None
        held = Counter(r.worker_id for r in queue.list(status=_L))
        assert all(n == 1 for n in held.values()), held  # one lease per worker
        assert sum(queue.counts().values()) == len(everything)
    finally:
        queue.close()


def test_releases_never_count_and_every_other_ending_does_until_dead_then_retry_starts_over(tmp_path: Path) -> None:
    with RequestQueue(tmp_path / "catalog.sqlite") as queue:
        rid = queue.enqueue(NewRequest(task="push", shape="T", start_state=START, max_attempts=3))[0].id
        for i in range(5):  # a draining worker gives it back, again and again
            lease = queue.lease(f"d{i}", lease_s=10, now=0.0)
            assert queue.release(rid, lease.token, worker_id=f"d{i}", now=1.0).attempts == 0
        endings = [lambda t: queue.release_worker_leases("lost", now=2.0),
                   lambda t: queue.expire_leases(now=100.0),
                   lambda t: queue.fail(rid, t, "boom", worker_id="failing", now=3.0)]
        for worker, end in zip(("lost", "expiring", "failing"), endings):
            end(queue.lease(worker, lease_s=10, now=1.0).token)
        dead = queue.get(rid)
        assert (dead.status, dead.attempts, dead.token, dead.last_error) == (_X, 3, 8, "boom")
        assert queue.lease("w", now=4.0) is None
        back = queue.retry(rid, now=5.0)
        assert (back.status, back.attempts, back.token) == (_Q, 0, 8)
        assert queue.lease("w", now=6.0).token == 9  # the fencing token goes on growing
