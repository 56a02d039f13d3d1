"""The shared SQLite file's connection settings (a real file)."""

from __future__ import annotations

import os
import sqlite3

from storage.database import JOURNAL_SIZE_LIMIT, connect
from storage.queue import RequestQueue
from storage.requests import NewRequest


def test_the_wal_shrinks_back_after_a_burst(tmp_path) -> None:
    db = tmp_path / "catalog.sqlite"
    conn = connect(db)  # stays open, as the service's connections do
    try:
        conn.execute("CREATE TABLE t (b BLOB)")
        conn.execute("BEGIN")
        for _ in range(40):
            conn.execute("INSERT INTO t VALUES (?)", (os.urandom(100_000),))
        conn.execute("COMMIT")
        wal = tmp_path / "catalog.sqlite-wal"
        assert wal.stat().st_size > 3 * JOURNAL_SIZE_LIMIT
        other = sqlite3.connect(db)  # what storage.wal.Checkpointer runs
        try:
            busy, frames, done = other.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
        finally:
            other.close()
        assert busy == 0 and frames == done
        conn.execute("INSERT INTO t VALUES (1)")  # the next writer starts the WAL over, and cuts it back
        assert wal.stat().st_size <= JOURNAL_SIZE_LIMIT
        assert conn.execute("SELECT count(*) FROM t").fetchone()[0] == 41
    finally:
        conn.close()


def test_the_queues_writer_cuts_the_wal_back_too(tmp_path) -> None:
    db = tmp_path / "catalog.sqlite"
    queue = RequestQueue(db)  # its own connections, kept open for its life
    try:
        big = {"note": "x" * 200_000}
        queue.enqueue_many([NewRequest("push", "box", {}, reason=big) for _ in range(12)])
        wal = tmp_path / "catalog.sqlite-wal"
        assert wal.stat().st_size > 2 * JOURNAL_SIZE_LIMIT
        other = sqlite3.connect(db)
        try:
            busy, frames, done = other.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
        finally:
            other.close()
        assert busy == 0 and frames == done
        queue.enqueue(NewRequest("push", "disk", {}))
        assert wal.stat().st_size <= JOURNAL_SIZE_LIMIT
        assert len(queue.list()) == 13
    finally:
        queue.close()
