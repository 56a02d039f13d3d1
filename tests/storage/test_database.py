"""The shared SQLite file (a real file): its connection settings, its components' schema versions."""

from __future__ import annotations

import os
import sqlite3
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest

from storage.catalog import _CATALOG_MIGRATIONS, Catalog
from storage.database import JOURNAL_SIZE_LIMIT, Migration, connect, ensure_schema, transaction
from storage.errors import CatalogError, RegistryError
from storage.models import _MIGRATIONS, ModelRegistry
from storage.queue import RequestQueue
from storage.requests import NewRequest
from tests.storage.test_episodes import make_episode


def _burst(conn: sqlite3.Connection, tmp_path) -> Path:
    """4 MB written in one transaction to a new table ``t`` (40 rows): the WAL it leaves, past 3 journal limits."""
    conn.execute("CREATE TABLE t (b BLOB)")
    conn.execute("BEGIN")
    for _ in range(40):
        conn.execute("INSERT INTO t VALUES (?)", (os.urandom(100_000),))
    conn.execute("COMMIT")
    wal = tmp_path / "catalog.sqlite-wal"
    assert wal.stat().st_size > 3 * JOURNAL_SIZE_LIMIT
    return wal


def test_the_wal_shrinks_back_after_a_burst(tmp_path) -> None:
    db = tmp_path / "catalog.sqlite"
    conn = connect(db)  # stays open, as the service's connections do
    try:
        wal = _burst(conn, tmp_path)
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


def test_a_wal_past_its_bound_is_emptied_by_the_checkpointer_itself(tmp_path, monkeypatch) -> None:
    """Writes and reads that keep overlapping never let a writer start the WAL over (a helper measured it growing
    ~10 MB/s at ~760 transitions/s): past WAL_TRUNCATE_BYTES the checkpointer empties it itself, with no writer
    (a PASSIVE checkpoint alone leaves the file as it is)."""
    from storage import wal as wal_module
    from storage.wal import Checkpointer
    from tests.conftest import wait_for
    monkeypatch.setattr(wal_module, "WAL_TRUNCATE_BYTES", 2 * JOURNAL_SIZE_LIMIT)
    db = tmp_path / "catalog.sqlite"
    conn = connect(db)
    try:
        wal = _burst(conn, tmp_path)
        checkpointer = Checkpointer(db, 30_000, every=1, period_s=0.05)
        try:
            wait_for(lambda: wal.stat().st_size == 0, timeout=30, message="the WAL emptied")
        finally:
            checkpointer.stop()
        assert conn.execute("SELECT count(*) FROM t").fetchone()[0] == 40  # nothing lost
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


# --- schema versions and the compatible level ---------------------------------------------------------

ITEMS = ("CREATE TABLE items (id TEXT PRIMARY KEY)",)
NOTES = ("CREATE TABLE notes (id TEXT PRIMARY KEY, note TEXT)",)  # a table code of version 1 never reads
KINDS = ("ALTER TABLE items ADD COLUMN kind TEXT NOT NULL DEFAULT 'a'",)
OTHERS, OTHERS_NOTE = ("CREATE TABLE others (id TEXT PRIMARY KEY)",), ("ALTER TABLE others ADD COLUMN note TEXT",)


def released_ensure_schema(conn: sqlite3.Connection, component: str, migrations) -> int:
    """``ensure_schema`` as released before compatible levels (its statements verbatim, its clock fixed):
    the code that wrote today's files, and that may still be running beside newer code."""
    row = None
    if conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'schema_versions'").fetchone():
        row = conn.execute("SELECT version FROM schema_versions WHERE component = ?", (component,)).fetchone()
    if row is not None and row["version"] == len(migrations):
        return len(migrations)
    with transaction(conn):
        conn.execute("CREATE TABLE IF NOT EXISTS schema_versions ("
                     "component TEXT PRIMARY KEY, version INTEGER NOT NULL, updated TEXT NOT NULL)")
        row = conn.execute("SELECT version FROM schema_versions WHERE component = ?", (component,)).fetchone()
        version = row["version"] if row else 0
        if version > len(migrations):
            raise CatalogError(f"{component} tables are at schema version {version}, this code knows "
                               f"versions up to {len(migrations)}; upgrade activecollect")
        for statements in migrations[version:]:
            for sql in statements:
                conn.execute(sql)
        if version < len(migrations):
            conn.execute("INSERT INTO schema_versions(component, version, updated) VALUES (?, ?, ?) "
                         "ON CONFLICT(component) DO UPDATE SET version = excluded.version, "
                         "updated = excluded.updated", (component, len(migrations), "2026-01-01T00:00:00+00:00"))
    return len(migrations)


def recorded(conn: sqlite3.Connection, component: str) -> tuple:
    """``(version, compatible, updated)`` of ``component`` in ``schema_versions``."""
    return tuple(conn.execute("SELECT version, compatible, updated FROM schema_versions WHERE component = ?",
                              (component,)).fetchone())


def refusal(component: str, version: int, known: int, needed: int) -> str:
    return (f"{component} tables are at schema version {version}, this code knows versions up to {known} "
            f"and the file needs code that knows version {needed} or later; upgrade activecollect")


def test_older_code_uses_a_file_whose_newer_migration_declared_it_compatible(tmp_path) -> None:
    db = tmp_path / "catalog.sqlite"
    with closing(connect(db)) as conn, closing(connect(db)) as writer:
        assert ensure_schema(conn, "c", [ITEMS, Migration(NOTES, compatible_with=1)]) == 2  # the newer code
        before = recorded(conn, "c")
        assert before[:2] == (2, 1)
        writer.execute("BEGIN IMMEDIATE")  # the older code takes no write lock: it neither waits nor writes
        conn.execute("PRAGMA busy_timeout = 0")
        assert ensure_schema(conn, "c", [ITEMS]) == 2
        writer.execute("ROLLBACK")
        conn.execute("INSERT INTO items VALUES ('i1')")  # and goes on using its tables
        assert recorded(conn, "c") == before


@pytest.mark.parametrize("levels, needed", [
    ((None, None), 3),  # the default: each migration is for its own version's code only
    ((1, 1), 1),
    ((1, 2), 2),
    ((1, None), 3),
    ((None, 1), 2),  # a compatible migration does not undo an incompatible one before it
])
def test_a_file_needs_the_highest_level_its_migrations_declared(tmp_path, levels, needed) -> None:
    migrations = [ITEMS, Migration(NOTES, compatible_with=levels[0]), Migration(KINDS, compatible_with=levels[1])]
    with closing(connect(tmp_path / "catalog.sqlite")) as conn:
        assert ensure_schema(conn, "c", migrations) == 3
        assert recorded(conn, "c")[:2] == (3, needed)
        for known in (1, 2):
            if known >= needed:
                assert ensure_schema(conn, "c", migrations[:known]) == 3
            else:
                with pytest.raises(CatalogError, match=refusal("c", 3, known, needed)):
                    ensure_schema(conn, "c", migrations[:known])
        assert recorded(conn, "c")[:2] == (3, needed)


def test_a_file_without_a_level_is_refused_by_older_code_as_before(tmp_path) -> None:
    with closing(connect(tmp_path / "catalog.sqlite")) as conn:
        released_ensure_schema(conn, "c", [ITEMS, NOTES])
        with pytest.raises(CatalogError, match=refusal("c", 2, 1, 2)):
            ensure_schema(conn, "c", [ITEMS])
        # Code that declares version 2 compatible finds the file at its version: it records no level (a
        # read only), so older code still refuses the file until a migration records one.
        assert ensure_schema(conn, "c", [ITEMS, Migration(NOTES, compatible_with=1)]) == 2
        assert "compatible" not in {r["name"] for r in conn.execute("PRAGMA table_info(schema_versions)")}
        with pytest.raises(CatalogError, match=refusal("c", 2, 1, 2)):
            ensure_schema(conn, "c", [ITEMS])


def test_a_file_written_before_levels_is_migrated_and_records_one(tmp_path) -> None:
    with closing(connect(tmp_path / "catalog.sqlite")) as conn:
        released_ensure_schema(conn, "c", [ITEMS])
        released_ensure_schema(conn, "other", [OTHERS])
        conn.execute("INSERT INTO items VALUES ('i1')")
        migrations = [ITEMS, Migration(KINDS, compatible_with=1), Migration(NOTES, compatible_with=1)]
        assert ensure_schema(conn, "c", migrations) == 3
        assert recorded(conn, "c")[:2] == (3, 1)
        assert recorded(conn, "other")[:2] == (1, None)  # untouched: a row without a level
        assert ensure_schema(conn, "c", migrations[:1]) == 3
        assert ensure_schema(conn, "other", [OTHERS]) == 1
        assert [tuple(r) for r in conn.execute("SELECT id, kind FROM items")] == [("i1", "a")]


def test_the_released_code_still_uses_a_file_this_code_migrated(tmp_path) -> None:
    with closing(connect(tmp_path / "catalog.sqlite")) as conn:
        assert ensure_schema(conn, "c", [ITEMS, Migration(NOTES, compatible_with=1)]) == 2
        assert recorded(conn, "c")[:2] == (2, 1)
        assert released_ensure_schema(conn, "c", [ITEMS, NOTES]) == 2  # at its version: reads `version` only
        with pytest.raises(CatalogError, match="schema version 2, this code knows versions up to 1; upgrade"):
            released_ensure_schema(conn, "c", [ITEMS])  # it knows no levels: refuses as it always did
        assert released_ensure_schema(conn, "other", [OTHERS, OTHERS_NOTE]) == 2
        assert recorded(conn, "other")[:2] == (2, None)  # a row it writes has no level: its own version's
        with pytest.raises(CatalogError, match=refusal("other", 2, 1, 2)):
            ensure_schema(conn, "other", [OTHERS])


def test_a_migration_cannot_declare_a_level_above_its_own_version(tmp_path) -> None:
    with closing(connect(tmp_path / "catalog.sqlite")) as conn:
        with pytest.raises(ValueError, match="schema version 2: compatible_with must be at most 2, found 3"):
            ensure_schema(conn, "c", [ITEMS, Migration(NOTES, compatible_with=3)])
        assert conn.execute("SELECT name FROM sqlite_master").fetchall() == []  # refused before any change
    with pytest.raises(ValueError, match="expected a schema version >= 1, found 0"):
        Migration(ITEMS, compatible_with=0)
    with pytest.raises(ValueError, match="expected a sequence of SQL statements, found the string"):
        Migration(ITEMS[0])


def _catalog_writes(data) -> int:
    cat = Catalog(data)
    cat.add_episode(make_episode(np.random.default_rng(5)))
    return cat.count()


def _registry_writes(data) -> int:
    reg = ModelRegistry(data)
    reg.register(b"weights", {}, {"h1_mse": 0.1}, "snap", "split")
    return len(reg.list())


COMPONENTS = [("catalog", _CATALOG_MIGRATIONS, _catalog_writes), ("models", _MIGRATIONS, _registry_writes)]


@pytest.mark.parametrize("component, migrations, writes", COMPONENTS, ids=["catalog", "models"])
def test_a_component_keeps_working_after_a_newer_compatible_migration(tmp_path, component, migrations,
                                                                      writes) -> None:
    data = tmp_path / "data"
    data.mkdir()
    newer = (*migrations, Migration(("CREATE TABLE newer_notes (id TEXT)",), compatible_with=len(migrations)))
    with closing(connect(data / "catalog.sqlite")) as conn:
        assert ensure_schema(conn, component, newer) == len(newer)  # a newer release touched the directory
    assert writes(data) == 1
    with closing(connect(data / "catalog.sqlite")) as conn:
        assert recorded(conn, component)[:2] == (len(newer), len(migrations))


@pytest.mark.parametrize("component, migrations, writes", COMPONENTS, ids=["catalog", "models"])
def test_a_component_refuses_a_file_after_a_newer_incompatible_migration(tmp_path, component, migrations,
                                                                         writes) -> None:
    data = tmp_path / "data"
    data.mkdir()
    with closing(connect(data / "catalog.sqlite")) as conn:
        ensure_schema(conn, component, (*migrations, ("CREATE TABLE newer_notes (id TEXT)",)))
    # The component's own error: a registry's refusal is a RegistryError (it was a CatalogError).
    n = len(migrations)
    with pytest.raises(CatalogError if component == "catalog" else RegistryError,
                       match=refusal(component, n + 1, n, n + 1)):
        writes(data)


@pytest.mark.parametrize("component, migrations", [("catalog", _CATALOG_MIGRATIONS), ("models", _MIGRATIONS)])
def test_version_2_of_the_catalog_and_registry_is_not_for_version_1_code(tmp_path, component, migrations) -> None:
    # Version-1 code would train on quarantined episodes (catalog), or take pruned models for loadable ones.
    with closing(connect(tmp_path / "catalog.sqlite")) as conn:
        assert ensure_schema(conn, component, migrations) == len(migrations)
        assert recorded(conn, component)[:2] == (len(migrations), 2)
        with pytest.raises(CatalogError, match=refusal(component, len(migrations), 1, 2)):
            ensure_schema(conn, component, migrations[:1])


def test_version_3_of_the_catalog_is_for_version_2_code(tmp_path) -> None:
    # The episodes' counts by split: version-2 code never reads them, and its writes keep them (triggers).
    with closing(connect(tmp_path / "catalog.sqlite")) as conn:
        assert ensure_schema(conn, "catalog", _CATALOG_MIGRATIONS) == 3
        assert ensure_schema(conn, "catalog", _CATALOG_MIGRATIONS[:2]) == 3
