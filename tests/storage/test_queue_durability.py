"""The request queue on real SQLite files, its durability and concurrency: threads and processes leasing at once,
acknowledged changes across SIGKILL, the WAL's checkpoints, what is fsynced. (Its lifecycle, fencing, reaping and
ordering: test_queue.py.)"""

from __future__ import annotations

import multiprocessing
import subprocess
import sys
import sqlite3
import threading
from pathlib import Path

from storage.queue import RequestQueue
from tests.conftest import wait_for
from tests.storage.test_queue import new


def test_threads_never_lease_the_same_request(queue: RequestQueue) -> None:
    n = 200
    queue.enqueue_many([new(priority=i % 3) for i in range(n)])
    got: dict[str, list[str]] = {"a": [], "b": [], "c": []}

    def work(name: str) -> None:
        while (lease := queue.lease(name)) is not None:
            got[name].append(lease.request.id)
            queue.complete(lease.request.id, lease.token, f"ep-{lease.request.id}", worker_id=name)

    threads = [threading.Thread(target=work, args=(name,)) for name in got]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    ids = [i for ids in got.values() for i in ids]
    assert len(ids) == n and len(set(ids)) == n
    assert queue.counts()["done"] == n


def _lease_all(path: str, worker: str, out) -> None:
    q = RequestQueue(path)
    ids = []
    while (lease := q.lease(worker)) is not None:
        ids.append(lease.request.id)
        q.complete(lease.request.id, lease.token, f"ep-{lease.request.id}", worker_id=worker)
    q.close()
    out.put(ids)


def test_processes_never_lease_the_same_request(tmp_path: Path) -> None:
    path = tmp_path / "catalog.sqlite"
    with RequestQueue(path) as q:
        q.enqueue_many([new() for _ in range(100)])
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    procs = [ctx.Process(target=_lease_all, args=(str(path), f"p{i}", out)) for i in range(2)]
    for p in procs:
        p.start()
    ids = [i for _ in procs for i in out.get(timeout=120)]
    for p in procs:
        p.join(timeout=60)
        assert p.exitcode == 0
    assert len(ids) == 100 and len(set(ids)) == 100


_CHURN = """
import sys
from storage.queue import RequestQueue
from storage.requests import NewRequest
q = RequestQueue(sys.argv[1])
start = {"shape": "T", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.0]}
i = 0
while True:
    req, _ = q.enqueue(NewRequest(task="push", shape="T", start_state=start))
    lease = q.lease("w")
    if i % 2:
        q.complete(lease.request.id, lease.token, "ep" + lease.request.id)
        print("done", lease.request.id, flush=True)
    else:
        print("leased", lease.request.id, flush=True)
    i += 1
"""


def test_acknowledged_changes_survive_sigkill(tmp_path: Path) -> None:
    """Every change the queue returned from before the process was killed is on disk afterwards."""
    path = tmp_path / "catalog.sqlite"
    proc = subprocess.Popen([sys.executable, "-c", _CHURN, str(path)], stdout=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[2])
    acked: list[tuple[str, str]] = []
    try:
        while len(acked) < 60:
            line = proc.stdout.readline()
            assert line, f"the churn process ended early with {proc.wait(timeout=30)}"
            status, request_id = line.split()
            acked.append((status, request_id))
    finally:
        proc.kill()
        proc.wait(timeout=30)
        proc.stdout.close()
    with RequestQueue(path) as q:
        for status, request_id in acked:
            assert q.get(request_id).status.value == status
        assert q.counts()["done"] >= 30
    conn = sqlite3.connect(path)
    assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    conn.close()


def test_background_checkpoint_moves_the_wal_into_the_database_and_stops_on_close(tmp_path: Path) -> None:
    db = tmp_path / "catalog.sqlite"
    queue = RequestQueue(db, background_checkpoint=True, checkpoint_every=1)
    try:
        before = db.stat().st_size
        stored = queue.enqueue_many([new(reason={"note": "x" * 500}) for _ in range(300)])  # ~40 pages, WAL only
        lease = queue.lease("w1")
        queue.fail(lease.request.id, lease.token, "boom")
        wait_for(lambda: db.stat().st_size > before, timeout=30,
                 message="the checkpointer thread copies the new pages into the database file")
        assert {t.name for t in threading.enumerate()} >= {"wal-checkpoint"}
    finally:
        queue.close()
    assert "wal-checkpoint" not in {t.name for t in threading.enumerate()}
    with RequestQueue(db) as reopened:  # everything committed is there, through any connection
        assert reopened.counts()["queued"] == 300
        assert reopened.get(stored[0][0].id).reason == {"note": "x" * 500}
        assert reopened.get(lease.request.id).attempts == 1


def test_acknowledged_changes_are_fsynced_and_lease_transitions_are_not(queue: RequestQueue) -> None:
    """Enqueue and operator actions commit with synchronous=FULL; leases keep the queue's NORMAL."""
    queue.enqueue(new())  # opens the writer
    writer = queue._writer
    assert writer is not None
    seen: list[tuple[str, int]] = []

    def trace(statement: str) -> None:
        if statement in ("BEGIN IMMEDIATE", "COMMIT"):
            # The level in force for this statement (0 OFF, 1 NORMAL, 2 FULL), read on a second cursor.
            seen.append((statement, writer.execute("PRAGMA synchronous").fetchone()[0]))

    writer.set_trace_callback(trace)
    try:
        seen.clear()
        r, _ = queue.enqueue(new())
        assert seen == [("BEGIN IMMEDIATE", 2), ("COMMIT", 2)]
        seen.clear()
        lease = queue.lease("w1")
        queue.fail(lease.request.id, lease.token, "boom", worker_id="w1")
        assert {level for _, level in seen} == {1}
        seen.clear()
        queue.cancel(r.id)
        assert seen == [("BEGIN IMMEDIATE", 2), ("COMMIT", 2)]
    finally:
        writer.set_trace_callback(None)
    assert writer.execute("PRAGMA synchronous").fetchone()[0] == 1  # back to NORMAL
