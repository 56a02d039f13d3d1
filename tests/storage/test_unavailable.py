"""A full database is a condition that passes, not bad input: ``...UnavailableError``, and nothing changes.

The database is made full the way SQLite itself reports it (``SQLITE_FULL``), by capping its size with
``PRAGMA max_page_count`` on the connection that writes.
"""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

import storage.database
from orchestrator import admin
from orchestrator.protocol import ErrorCode
from storage.catalog import Catalog
from storage.database import DB_NAME, connection, is_transient
from storage.errors import (
    CatalogError,
    CatalogUnavailableError,
    QueueError,
    QueueUnavailableError,
    RegistryUnavailableError,
    StorageUnavailableError,
)
from storage.models import ModelRegistry
from storage.queue import NewRequest, RequestQueue
from tests.storage.test_episodes import make_episode

START = {"shape": "T", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.0]}


def _cap(conn: sqlite3.Connection) -> None:
    """No page more than the file has now: the next write that needs one fails with SQLITE_FULL."""
    pages = conn.execute("PRAGMA page_count").fetchone()[0]
    conn.execute(f"PRAGMA max_page_count = {max(pages, 1)}")


class FullDisk:
    """From ``fill()`` on, every connection ``storage.database.connect`` opens is capped at the file's size
    then; ``free()`` gives the space back."""

    def __init__(self, monkeypatch) -> None:
        self._monkeypatch, self._real = monkeypatch, storage.database.connect

    def _capped(self, path):
        conn = self._real(path)
        _cap(conn)
        return conn

    def fill(self) -> None:
        self._monkeypatch.setattr(storage.database, "connect", self._capped)

    def free(self) -> None:
        self._monkeypatch.setattr(storage.database, "connect", self._real)


@pytest.fixture
def full_disk(monkeypatch) -> FullDisk:
    return FullDisk(monkeypatch)


def test_a_full_database_is_unavailable_and_other_errors_are_not(tmp_path) -> None:
    db = tmp_path / DB_NAME
    with connection(db, CatalogError) as conn:
        conn.execute("CREATE TABLE t (x BLOB)")
    with pytest.raises(CatalogUnavailableError, match="database or disk is full") as caught:
        with connection(db, CatalogError) as conn:
            _cap(conn)
            conn.execute("INSERT INTO t VALUES (zeroblob(100000))")
    assert isinstance(caught.value, CatalogError) and is_transient(caught.value.__cause__)
    with pytest.raises(CatalogError) as caught:
        with connection(db, CatalogError) as conn:
            conn.execute("INSERT INTO no_such_table VALUES (1)")
    assert not isinstance(caught.value, StorageUnavailableError)


def test_a_full_queue_refuses_as_unavailable_and_changes_nothing(tmp_path) -> None:
    queue = RequestQueue(tmp_path / DB_NAME)
    try:
        queue.enqueue(NewRequest(task="push", shape="T", start_state=START))
        with queue._tx() as conn:  # the queue's one writing connection
            _cap(conn)
        with pytest.raises(QueueUnavailableError) as caught:
            queue.enqueue_many([NewRequest(task="push", shape="T", start_state=START, reason={"pad": "x" * 3000},
                                           idempotency_key=f"k{i}") for i in range(40)])
        assert isinstance(caught.value, QueueError)
        assert queue.counts()["queued"] == 1
        assert admin.protocol_error(caught.value).code == ErrorCode.UNAVAILABLE  # not bad_field: ask again
        with queue._tx() as conn:
            conn.execute("PRAGMA max_page_count = 1073741823")  # space again
        assert len(queue.enqueue_many([NewRequest(task="push", shape="T", start_state=START,
                                                  idempotency_key=f"k{i}") for i in range(3)])) == 3
    finally:
        queue.close()


def test_an_ingest_into_a_full_catalog_is_unavailable_and_leaves_no_file(tmp_path, full_disk) -> None:
    cat = Catalog(tmp_path / "data")
    rng = np.random.default_rng(3)
    cat.add_episode(make_episode(rng, steps=30, size=32))
    full_disk.fill()
    with pytest.raises(CatalogUnavailableError):
        for _ in range(20):  # until a row needs a new page
            cat.add_episode(make_episode(rng, steps=30, size=32))
    full_disk.free()
    strays = cat.strays(min_tmp_age_s=0)
    assert not strays.unindexed and not strays.staging  # the refused one's file is gone with it
    before = cat.count()
    assert not cat.add_episode(make_episode(rng, steps=30, size=32)).duplicate and cat.count() == before + 1


def test_a_checkpoint_the_registry_cannot_commit_leaves_no_folder(tmp_path, full_disk) -> None:
    reg = ModelRegistry(tmp_path / "data")
    reg.register(b"w" * 100, {}, {"h1_mse": 0.1}, "snap", "split")
    full_disk.fill()
    with pytest.raises(RegistryUnavailableError):
        for i in range(50):  # rows with large configs until one needs a new page
            reg.register(f"weights {i}".encode(), {"pad": "x" * 4000}, {"h1_mse": 0.1}, "snap", "split")
    full_disk.free()
    assert sorted(p.name for p in reg.models_dir.iterdir()) == [r.version for r in reg.list()]  # each has its row
    reg.register(b"after", {}, {"h1_mse": 0.1}, "snap", "split")
