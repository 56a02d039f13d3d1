"""A catalog in a rollback-journal mode (written by another tool: sqlite3's ``.dump`` into a new file, say; every
catalog this project makes is WAL from its creation) is converted to WAL by the first connection that can do it at
once; one that cannot -- on read-only storage, or while another connection reads the file -- reads it as it is,
instead of being refused or kept waiting the busy timeout for a lock only the conversion needs."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

import storage.database
from storage.catalog import Catalog
from storage.database import BUSY_TIMEOUT_MS, configure, connect
from tests.storage.test_episodes import make_episode


def journal_mode(db: Path) -> str:
    """The mode the file's header records (what a new connection will use), read without changing it."""
    return {1: "rollback", 2: "wal"}[db.read_bytes()[18]]


@pytest.fixture
def rollback_catalog(cat: Catalog, rng) -> Catalog:
    """``cat`` holding two episodes, its file in rollback-journal (DELETE) mode."""
    for _ in range(2):
        cat.add_episode(make_episode(rng))
    conn = sqlite3.connect(cat.db_path)
    try:
        assert conn.execute("PRAGMA journal_mode = DELETE").fetchone()[0] == "delete"
    finally:
        conn.close()
    assert journal_mode(cat.db_path) == "rollback"
    return cat


def test_a_rollback_journal_catalog_on_read_only_storage_is_read_as_it_is(rollback_catalog: Catalog) -> None:
    """A connection that may only read (as on a file system remounted read-only) was refused by the conversion:
    "attempt to write a readonly database"."""
    conn = sqlite3.connect(f"file:{rollback_catalog.db_path}?mode=ro", uri=True, isolation_level=None)
    try:
        configure(conn, BUSY_TIMEOUT_MS, "FULL")
        assert conn.execute("SELECT COUNT(*) FROM episodes").fetchone()[0] == 2
        assert conn.execute("PRAGMA busy_timeout").fetchone()[0] == BUSY_TIMEOUT_MS
    finally:
        conn.close()
    assert journal_mode(rollback_catalog.db_path) == "rollback"


def test_a_rollback_journal_catalog_another_connection_reads_is_read_at_once_and_converted_after(
        rollback_catalog: Catalog, monkeypatch) -> None:
    """While another connection reads the file (it holds a shared lock), the conversion cannot have the lock it
    needs: the reader waited the whole busy timeout (30 s) and was refused "database is locked"."""
    monkeypatch.setattr(storage.database, "BUSY_TIMEOUT_MS", 2_000)  # what the old code waited, shortened
    holder = sqlite3.connect(rollback_catalog.db_path, isolation_level=None)
    try:
        holder.execute("BEGIN")
        assert holder.execute("SELECT COUNT(*) FROM episodes").fetchone()[0] == 2  # its shared lock taken
        assert Catalog(rollback_catalog.data_dir).count() == 2
        conn = connect(rollback_catalog.db_path)
        try:
            assert conn.execute("PRAGMA busy_timeout").fetchone()[0] == 2_000  # set back after the attempt
        finally:
            conn.close()
        assert journal_mode(rollback_catalog.db_path) == "rollback"
    finally:
        holder.close()
    assert Catalog(rollback_catalog.data_dir).count() == 2  # the first open that can converts it
    assert journal_mode(rollback_catalog.db_path) == "wal"


def test_a_new_file_is_made_wal_and_a_file_that_is_not_a_database_is_refused(tmp_path: Path) -> None:
    conn = connect(tmp_path / "new.sqlite")
    conn.close()
    assert journal_mode(tmp_path / "new.sqlite") == "wal"
    (tmp_path / "junk.sqlite").write_bytes(b"not a database, " * 100)
    with pytest.raises(sqlite3.DatabaseError, match="file is not a database"):
        connect(tmp_path / "junk.sqlite")
