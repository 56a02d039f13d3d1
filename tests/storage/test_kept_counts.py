"""The counts kept by triggers (``storage.database.kept_counts``): the queue's requests by status and the catalog's
episodes by split always equal the rows counted afresh -- through every transition, in files from before them,
and under writes that do not go through our classes (another code version's, a hand-made repair)."""

from __future__ import annotations

import sqlite3
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest

from storage.catalog import Catalog
from storage.database import connect
from storage.queue import RequestQueue
from storage.request_table import RECOUNT_SQL
from storage.requests import NewRequest, RequestStatus
from tests.storage.test_episodes import make_episode

START = {"shape": "T", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.0]}


def recounted(db_path: Path) -> dict[str, int]:
    """The queue's counts as the rows give them (zeros included), the way ``counts`` read them before."""
    out = {s.value: 0 for s in RequestStatus}
    with closing(sqlite3.connect(db_path)) as conn:
        out.update(dict(conn.execute(RECOUNT_SQL).fetchall()))
    return out


def episodes_by_split(db_path: Path) -> dict[str, int]:
    with closing(sqlite3.connect(db_path)) as conn:
        return dict(conn.execute("SELECT split, COUNT(*) FROM episodes GROUP BY split").fetchall())


def drop_counts(db_path: Path, counts: str) -> None:
    """Back to a file from before ``counts``: the table and its triggers gone."""
    with closing(sqlite3.connect(db_path)) as conn, conn:
        for (name,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'trigger' AND name LIKE ?",
                                    (f"{counts}_%",)).fetchall():
            conn.execute(f"DROP TRIGGER {name}")
        conn.execute(f"DROP TABLE {counts}")


def test_the_queues_counts_follow_every_transition(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    db = tmp_path / "catalog.sqlite"
    with RequestQueue(db) as queue:
        now, held, seen = 1000.0, [], set()
        for step in range(400):
            now += 1.0
            op = rng.integers(9)
            if op <= 2:
                queue.enqueue(NewRequest(task="push", shape="T", start_state=START, max_attempts=2), now=now)
            elif op == 3 and (lease := queue.lease("w", lease_s=float(rng.uniform(1, 20)), now=now)) is not None:
                held.append(lease)
            elif op in (4, 5, 6) and held:
                lease = held.pop(int(rng.integers(len(held))))
                rid, token = lease.request.id, lease.token
                try:
                    if op == 4:
                        queue.complete(rid, token, f"ep{step}", now=now)
                    elif op == 5:
                        queue.fail(rid, token, "boom", now=now)
                    else:
                        queue.release(rid, token, now=now)
                except Exception as exc:  # a lease the reaper took back first (StaleLeaseError)
                    assert "lease" in str(exc).lower() or "stale" in type(exc).__name__.lower()
            elif op == 7:
                queue.expire_leases(now=now)
            elif op == 8 and (rows := queue.list(limit=5)):
                row = rows[int(rng.integers(len(rows)))]
                if row.status in (RequestStatus.QUEUED, RequestStatus.LEASED):
                    queue.cancel(row.id, now=now)
                elif row.status in (RequestStatus.DEAD, RequestStatus.CANCELLED):
                    queue.retry(row.id, now=now)
            counts = queue.counts()
            assert counts == recounted(db), f"after step {step} (operation {op})"
            seen |= {status for status, n in counts.items() if n}
    # every status was held at some point, so the test walked every trigger into and out of each
    assert seen == {s.value for s in RequestStatus} and sum(counts.values()) > 100


def test_a_queue_from_before_the_counts_is_counted_when_opened(tmp_path: Path) -> None:
    db = tmp_path / "catalog.sqlite"
    with RequestQueue(db) as queue:
        for i in range(7):
            queue.enqueue(NewRequest(task="push", shape="T", start_state=START), now=float(i))
        lease = queue.lease("w", now=10.0)
        queue.complete(lease.request.id, lease.token, "ep", now=11.0)
        queue.lease("w", now=12.0)
    drop_counts(db, "request_counts")
    with RequestQueue(db) as queue:
        assert queue.counts() == recounted(db) == {**{s.value: 0 for s in RequestStatus},
                                                   "queued": 5, "leased": 1, "done": 1}
    with RequestQueue(db) as queue:  # a second open keeps the counts it finds
        queue.enqueue(NewRequest(task="push", shape="T", start_state=START), now=20.0)
        assert queue.counts()["queued"] == 6


def test_writes_that_bypass_the_queue_keep_its_counts(tmp_path: Path) -> None:
    # Older code, or an operator's repair with the sqlite3 shell: the triggers are in the file, not in our code.
    db = tmp_path / "catalog.sqlite"
    with RequestQueue(db) as queue:
        for i in range(4):
            queue.enqueue(NewRequest(task="push", shape="T", start_state=START), now=float(i))
        with closing(sqlite3.connect(db)) as conn, conn:
            conn.execute("UPDATE requests SET status = 'dead' WHERE rowid IN (SELECT rowid FROM requests LIMIT 2)")
            conn.execute("UPDATE requests SET priority = 3")  # not the status: no count moves
            conn.execute("DELETE FROM requests WHERE rowid = (SELECT MIN(rowid) FROM requests)")
        assert queue.counts() == recounted(db) == {**{s.value: 0 for s in RequestStatus}, "queued": 2, "dead": 1}


def test_the_catalogs_counts_by_split_follow_its_episodes(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    cat = Catalog(tmp_path / "data")
    assert cat.count() == cat.count(split="train") == cat.count(split="eval") == 0
    ids = [cat.add_episode(make_episode(rng), split=split).episode_id for split in ("train",) * 5 + ("eval",) * 3]
    cat.quarantine(ids[0], "damaged")  # still in its split: the count of a split is every episode indexed there
    assert (cat.count(split="train"), cat.count(split="eval"), cat.count()) == (5, 3, 8)
    assert cat.count(split="train", quarantined=False) == 4 and cat.count(quarantined=True) == 1
    assert episodes_by_split(cat.db_path) == {"train": 5, "eval": 3}
    with closing(sqlite3.connect(cat.db_path)) as conn, conn:  # by hand, past the catalog
        conn.execute("UPDATE episodes SET split = 'eval' WHERE episode_id = ?", (ids[1],))
        conn.execute("DELETE FROM episodes WHERE episode_id = ?", (ids[2],))
    assert (cat.count(split="train"), cat.count(split="eval"), cat.count()) == (3, 4, 7)
    with pytest.raises(Exception, match="split"):
        cat.count(split="nonsense")


def test_a_version_2_catalog_is_counted_when_migrated(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    data = tmp_path / "data"
    cat = Catalog(data)
    for split in ("train", "train", "eval"):
        cat.add_episode(make_episode(rng), split=split)
    drop_counts(cat.db_path, "episode_counts")
    with closing(connect(cat.db_path)) as conn, conn:
        conn.execute("UPDATE schema_versions SET version = 2, compatible = 2 WHERE component = 'catalog'")
    cat = Catalog(data)
    assert (cat.count(split="train"), cat.count(split="eval"), cat.count()) == (2, 1, 3)
    cat.add_episode(make_episode(rng))
    assert cat.count(split="train") == 3
    with closing(connect(cat.db_path)) as conn:
        assert conn.execute("SELECT version FROM schema_versions WHERE component = 'catalog'").fetchone()[0] == 3
