"""Read-only storage is a condition that passes, not bad input: ``...UnavailableError``, and nothing changes.

A file system remounted read-only after disk errors, or a database file the process may only read, refuses
writes until an operator makes it writable again. SQLite says so with SQLITE_READONLY (or one of its extended
codes), the OS with EROFS. Made here the way SQLite itself reports it, also as root (where a chmod stops no
write): a connection opened read-only (``mode=ro``), or ``PRAGMA query_only`` on the connection the code writes
with; EROFS is injected at the one OS call of an episode file's write (``FailingSyncs``).
"""

from __future__ import annotations

import errno
import os
import sqlite3

import numpy as np
import pytest

import storage.database
from orchestrator import admin
from orchestrator.protocol import ErrorCode
from storage.database import DB_NAME, connection, is_transient
from storage.errors import (
    CatalogError,
    CatalogUnavailableError,
    QueueUnavailableError,
    RegistryUnavailableError,
    StorageUnavailableError,
)
from storage.queue import NewRequest, RequestQueue
from storage.requests import RequestStatus
from tests.orchestrator.conftest import FailingSyncs
from tests.storage.test_episodes import make_episode

START = {"shape": "T", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.0]}


def write_error(conn: sqlite3.Connection) -> sqlite3.Error:
    """What SQLite raises for a write on ``conn`` (which has a table ``t``)."""
    with pytest.raises(sqlite3.Error) as caught:
        conn.execute("INSERT INTO t VALUES (1)")
    return caught.value


def read_only_queue(queue: RequestQueue, on: bool = True) -> None:
    """The queue's one writing connection refuses every write from now on (SQLITE_READONLY); ``on=False``
    makes it writable again."""
    with queue._write_lock:
        queue._writer = queue._writer or queue._open()
        queue._writer.execute(f"PRAGMA query_only = {int(on)}")


def read_only_database(monkeypatch) -> None:
    """Every connection ``storage.database.connect`` opens from now on (the catalog's, the registry's) may only
    read: its writes fail with SQLITE_READONLY."""
    real = storage.database.connect

    def connect(path):
        conn = real(path)
        conn.execute("PRAGMA query_only = 1")
        return conn

    monkeypatch.setattr(storage.database, "connect", connect)


def test_a_read_only_database_or_file_system_passes_and_a_moved_file_does_not(tmp_path) -> None:
    db = tmp_path / DB_NAME
    with connection(db, CatalogError) as conn:
        conn.execute("CREATE TABLE t (x)")
    reader = sqlite3.connect(f"file:{db}?mode=ro", uri=True)  # a file this process may only read
    try:
        readonly = write_error(reader)
    finally:
        reader.close()
    assert readonly.sqlite_errorname == "SQLITE_READONLY" and is_transient(readonly)
    assert is_transient(OSError(errno.EROFS, os.strerror(errno.EROFS)))
    moved = tmp_path / "moved.sqlite"  # a rollback journal: WAL writes on into a moved file
    conn = sqlite3.connect(moved)
    try:
        conn.execute("CREATE TABLE t (x)")
        moved.rename(tmp_path / "elsewhere.sqlite")
        gone = write_error(conn)
    finally:
        conn.close()
    assert gone.sqlite_errorname == "SQLITE_READONLY_DBMOVED"  # never writable again: not one that passes
    assert not is_transient(gone)


def test_a_write_to_a_read_only_database_is_unavailable(tmp_path) -> None:
    db = tmp_path / DB_NAME
    with connection(db, CatalogError) as conn:
        conn.execute("CREATE TABLE t (x)")
    with pytest.raises(CatalogUnavailableError, match="attempt to write a readonly database"):
        with connection(db, CatalogError) as conn:
            conn.execute("PRAGMA query_only = 1")
            conn.execute("INSERT INTO t VALUES (1)")
    with connection(db, CatalogError) as conn:
        assert conn.execute("SELECT COUNT(*) FROM t").fetchone()[0] == 0


def test_a_read_only_queue_refuses_renew_and_enqueue_as_unavailable_and_changes_nothing(tmp_path) -> None:
    """Not ``bad_field``: on that a worker takes its lease as lost and drops the episode it collected."""
    queue = RequestQueue(tmp_path / DB_NAME)
    try:
        request, _ = queue.enqueue(NewRequest(task="push", shape="T", start_state=START))
        lease = queue.lease("w1", lease_s=30.0)
        read_only_queue(queue)
        with pytest.raises(QueueUnavailableError, match="readonly database") as caught:
            queue.renew(request.id, lease.token, "w1", lease_s=600.0)
        assert admin.protocol_error(caught.value).code == ErrorCode.UNAVAILABLE
        with pytest.raises(QueueUnavailableError):
            queue.enqueue(NewRequest(task="push", shape="T", start_state=START))
        held = queue.get(request.id)
        assert (held.status, held.token, held.attempts, held.lease_expires) == (
            RequestStatus.LEASED, lease.token, 0, lease.expires_at)
        assert queue.counts()["queued"] == 0
        read_only_queue(queue, on=False)
        assert queue.renew(request.id, lease.token, "w1", lease_s=600.0) > lease.expires_at
    finally:
        queue.close()


def test_an_ingest_into_a_read_only_catalog_is_unavailable_and_leaves_no_file(cat, rng, monkeypatch) -> None:
    cat.add_episode(make_episode(rng))
    with monkeypatch.context() as patch:
        read_only_database(patch)
        with pytest.raises(CatalogUnavailableError, match="readonly database"):
            cat.add_episode(make_episode(rng))
    strays = cat.strays(min_tmp_age_s=0)
    assert not strays.unindexed and not strays.staging and cat.count() == 1
    assert not cat.add_episode(make_episode(rng)).duplicate and cat.count() == 2


def test_an_episode_file_on_a_read_only_file_system_is_unavailable(cat, rng, monkeypatch) -> None:
    disk = FailingSyncs(cat.episodes_dir, monkeypatch, code=errno.EROFS)
    ep = make_episode(rng)
    with pytest.raises(CatalogUnavailableError, match="Read-only file system") as caught:
        cat.add_episode(ep)
    assert isinstance(caught.value, StorageUnavailableError) and disk.failed == 1
    strays = cat.strays(min_tmp_age_s=0)
    assert not strays.unindexed and not strays.staging and cat.count() == 0
    disk.heal()
    assert cat.add_episode(ep).episode_id == ep.meta.episode_id and cat.count() == 1


def test_a_checkpoint_a_read_only_registry_cannot_commit_is_unavailable(reg, monkeypatch) -> None:
    reg.register(b"w" * 100, {}, {"h1_mse": 0.1}, "snap", "split")
    with monkeypatch.context() as patch:
        read_only_database(patch)
        with pytest.raises(RegistryUnavailableError, match="readonly database"):
            reg.register(b"other weights", {}, {"h1_mse": 0.1}, "snap", "split")
    assert sorted(p.name for p in reg.models_dir.iterdir()) == [r.version for r in reg.list()]  # no stray folder
    assert len(reg.list()) == 1
    reg.register(b"after", {}, {"h1_mse": 0.1}, "snap", "split")


def test_an_ingest_refused_for_its_content_stays_a_plain_catalog_error(cat) -> None:
    """The other side of the line: bad input (here a frame size no catalog holds) is still refused as such."""
    with pytest.raises(CatalogError, match="px frames") as caught:
        cat.add_episode(make_episode(np.random.default_rng(5), size=4))
    assert not isinstance(caught.value, StorageUnavailableError)
