"""The one SQLite file of a data directory (``DATA/catalog.sqlite``), shared by every component.

The catalog (episodes, eval split), the model registry and the request queue keep their
tables in it: open it with ``connect`` and create a component's tables with
``ensure_schema``, which records each component's schema version in ``schema_versions``.
"""

from __future__ import annotations

import errno
import shutil
import sqlite3
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

from storage.errors import (
    CatalogError,
    CatalogUnavailableError,
    QueueError,
    QueueUnavailableError,
    RegistryError,
    RegistryUnavailableError,
    StorageError,
)

DB_NAME = "catalog.sqlite"
#: The data directory's folders of episode files and of model checkpoints (the files the database indexes).
EPISODES_DIR, MODELS_DIR = "episodes", "models"
#: Where ``Catalog.quarantine`` keeps the files of episodes it takes out of training.
QUARANTINE_DIR = "quarantine"
BUSY_TIMEOUT_MS = 30_000
#: What the WAL file is cut back to once a checkpoint has emptied it. SQLite reuses the file instead of
#: shrinking it, so without a limit one burst (or a long backup, during which it cannot be reset) would
#: hold its high-water size for as long as any connection stays open -- the service's always does.
JOURNAL_SIZE_LIMIT = 1 << 20

#: One schema version of a component: the SQL statements that bring it there.
Migration = Sequence[str]



#: SQLite's primary result codes for a condition that passes: BUSY, LOCKED, NOMEM, IOERR (also how a full
#: disk shows when the WAL's shared-memory file cannot be made), FULL, PROTOCOL.
_TRANSIENT_SQLITE = {5, 6, 7, 10, 13, 15}
_TRANSIENT_ERRNO = {errno.ENOSPC, errno.EDQUOT, errno.EIO}
_UNAVAILABLE: dict[type[StorageError], type[StorageError]] = {
    CatalogError: CatalogUnavailableError, QueueError: QueueUnavailableError,
    RegistryError: RegistryUnavailableError}
#: Below this many free bytes a failure says how full the disk is.
LOW_SPACE_BYTES = 16 << 20


def is_transient(exc: BaseException) -> bool:
    """Whether ``exc`` (an ``sqlite3.Error`` or ``OSError``) is a condition that passes: a full disk, an
    I/O error, a busy database."""
    if isinstance(exc, sqlite3.Error):
        code = getattr(exc, "sqlite_errorcode", None)
        return code is not None and (code & 0xFF) in _TRANSIENT_SQLITE
    return isinstance(exc, OSError) and exc.errno in _TRANSIENT_ERRNO


def disk_space(path: str | Path) -> tuple[Path, int, int] | None:
    """``(directory, free bytes, size bytes)`` of the file system holding ``path`` (its nearest existing
    directory), or None when that cannot be read."""
    directory = Path(path)
    while not directory.is_dir() and directory != directory.parent:
        directory = directory.parent
    try:
        usage = shutil.disk_usage(directory)
    except OSError:
        return None
    return directory, usage.free, usage.total


def space_note(path: str | Path) -> str:
    """``" (the device holding DIR has N bytes free)"`` when that is little, else ``""``."""
    space = disk_space(path)
    if space is None or space[1] >= LOW_SPACE_BYTES:
        return ""
    return f" (the device holding {space[0]} has {space[1]} bytes free)"


def disk_json(path: str | Path) -> dict[str, int] | None:
    """``{"free_bytes", "size_bytes"}`` of the file system holding ``path`` (None when unreadable): what
    ``stats``, the dashboard and ``/metrics`` report so that an operator sees a disk fill before it is full."""
    space = disk_space(path)
    return None if space is None else {"free_bytes": space[1], "size_bytes": space[2]}


def storage_error(exc: sqlite3.Error | OSError, error: type[StorageError], message: str,
                  path: str | Path) -> StorageError:
    """``error(message)``, or its ``...UnavailableError`` subclass when ``exc`` is a condition that passes
    (then with how full the disk holding ``path`` is, when that is the likely cause)."""
    if not is_transient(exc):
        return error(message)
    return _UNAVAILABLE.get(error, error)(message + space_note(path))


def connect(db_path: str | Path) -> sqlite3.Connection:
    """Opens the catalog database: autocommit (explicit transactions), WAL, busy timeout.

    One connection per thread: open one where you need it and close it after.
    """
    conn = sqlite3.connect(db_path, timeout=BUSY_TIMEOUT_MS / 1000, isolation_level=None)
    try:
        conn.row_factory = sqlite3.Row
        configure(conn, BUSY_TIMEOUT_MS, "FULL")  # FULL: a committed ingest survives power loss
        conn.execute("PRAGMA foreign_keys = ON")
    except BaseException:
        conn.close()
        raise
    return conn


def refuse_lost_database(data_dir: Path, error: type[StorageError]) -> None:
    """Raise ``error`` when ``DATA/catalog.sqlite`` is missing or empty while ``data_dir`` holds episode files
    or model folders: the index of acknowledged data is lost, and starting a new one there would treat that
    data as a crash's leftovers. Checked before anything opens (and so creates) the file."""
    db = data_dir / DB_NAME
    try:
        if db.stat().st_size or Path(f"{db}-wal").stat().st_size:
            return
    except FileNotFoundError:
        pass
    held = next(iter((data_dir / EPISODES_DIR).rglob("*.mcap")), None) or next(
        iter((data_dir / QUARANTINE_DIR).rglob("*.mcap")), None) or next(
        (p for p in (data_dir / MODELS_DIR).glob("m*") if p.is_dir()), None)
    if held is not None:
        state = "empty" if db.exists() else "missing"
        raise error(f"{db} is {state}, but {data_dir} holds the data it indexed (e.g. {held}); nothing was "
                    f"changed: restore the directory from a backup (activecollect backup), or ingest its "
                    f"episode files into a new data directory")


def configure(conn: sqlite3.Connection, busy_timeout_ms: int, synchronous: str) -> None:
    """The settings every connection that may write the file needs: busy timeout, WAL, ``synchronous``,
    and ``JOURNAL_SIZE_LIMIT`` (the writer that starts the WAL over is the one that cuts it back)."""
    conn.execute(f"PRAGMA busy_timeout = {busy_timeout_ms}")
    conn.execute("PRAGMA journal_mode = WAL")  # the first statement to read the file: not a database?
    conn.execute(f"PRAGMA synchronous = {synchronous}")
    conn.execute(f"PRAGMA journal_size_limit = {JOURNAL_SIZE_LIMIT}")


@contextmanager
def connection(db_path: str | Path, error: type[StorageError]) -> Iterator[sqlite3.Connection]:
    """``connect`` for the length of a ``with`` block, closed after it.

    SQLite's own errors, from opening the file or from any statement in the block (a damaged
    file, "database is locked" past the busy timeout, a full disk), come out as ``error``
    naming the file, so callers handle one family of exceptions (``StorageError``); those that
    pass (a full disk, a busy database) as its ``...UnavailableError`` subclass.
    """
    try:
        conn = connect(db_path)
    except sqlite3.Error as exc:
        raise storage_error(exc, error, f"cannot open the database {db_path}: {exc}", db_path) from exc
    try:
        yield conn
    except sqlite3.Error as exc:
        raise storage_error(exc, error, f"database {db_path}: {exc}", db_path) from exc
    finally:
        conn.close()


@contextmanager
def transaction(conn: sqlite3.Connection) -> Iterator[sqlite3.Connection]:
    """``BEGIN IMMEDIATE`` ... ``COMMIT``; ``ROLLBACK`` and re-raise on any exception."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        yield conn
    except BaseException:
        if conn.in_transaction:
            conn.execute("ROLLBACK")
        raise
    conn.execute("COMMIT")


def ensure_schema(conn: sqlite3.Connection, component: str, migrations: Sequence[Migration]) -> int:
    """Applies ``migrations[v:]`` where ``v`` is ``component``'s recorded version; returns the new one.

    Each migration is a sequence of SQL statements, applied in one transaction together
    with the version bump. Raises ``CatalogError`` if the file is newer than this code. A file
    already at this code's version is only read: opening a catalog does not wait for writers.
    """
    if _recorded_version(conn, component) == len(migrations):
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
                         "updated = excluded.updated", (component, len(migrations), _now_iso()))
    return len(migrations)


def _recorded_version(conn: sqlite3.Connection, component: str) -> int | None:
    """``component``'s schema version in the file, read without a write lock (None: not recorded)."""
    if conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'schema_versions'").fetchone():
        row = conn.execute("SELECT version FROM schema_versions WHERE component = ?", (component,)).fetchone()
        return None if row is None else row["version"]
    return None


def _now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")
