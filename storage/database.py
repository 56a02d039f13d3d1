"""The one SQLite file of a data directory (``DATA/catalog.sqlite``), shared by every component.

The catalog (episodes, eval split), the model registry and the request queue keep their
tables in it: open it with ``connect`` and create a component's tables with
``ensure_schema``, which records each component's schema version in ``schema_versions``.

Older code may keep using a file that newer code migrated, when the newer migrations allow it: each
``Migration`` declares ``compatible_with``, the oldest schema version whose code can still read and write
the file after it (by default its own version). ``schema_versions.compatible`` holds the highest level of
the migrations applied; code that knows N versions opens a file at version M > N, unchanged, only when
that level is at most N (a file without one counts as its own version's), and refuses it otherwise.
"""

from __future__ import annotations

import errno
import os
import shutil
import sqlite3
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
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
#: The busy timeout ``connect`` gives the connections a thread opens (``busy_timeout`` sets it for a block;
#: None: ``BUSY_TIMEOUT_MS``).
_BUSY_TIMEOUT_MS: ContextVar[int | None] = ContextVar("busy_timeout_ms", default=None)
#: What the WAL file is cut back to once a checkpoint has emptied it. SQLite reuses the file instead of
#: shrinking it, so without a limit one burst (or a long backup, during which it cannot be reset) would
#: hold its high-water size for as long as any connection stays open -- the service's always does.
JOURNAL_SIZE_LIMIT = 1 << 20


@dataclass(frozen=True)
class Migration:
    """One schema version of a component: the SQL statements that bring a file there, and the oldest
    version whose code may still use the file after them. A plain sequence of statements stands for
    ``Migration(statements)``."""

    statements: Sequence[str]
    """Applied in order, in one transaction together with the version bump."""
    compatible_with: int | None = None
    """The lowest schema version of the component whose code can still safely read and write a file at
    this version; None: this migration's own version (older code refuses the file, the safe default).
    Lower it only for a change older code cannot notice, and whose absence from the rows that code writes
    newer code accepts (a table, index or nullable column it never reads); never for one it would misread
    or undo (rows it must now skip, a column it would not fill)."""

    def __post_init__(self) -> None:
        if isinstance(self.statements, str):
            raise ValueError(f"statements: expected a sequence of SQL statements, found the string "
                             f"{self.statements[:60]!r}")
        if self.compatible_with is not None and self.compatible_with < 1:
            raise ValueError(f"compatible_with: expected a schema version >= 1, found {self.compatible_with}")


#: SQLite's primary result codes for a condition that passes: BUSY, LOCKED, NOMEM, READONLY (a database file,
#: or the file system under it, that cannot be written now: remounted read-only after disk errors, say),
#: IOERR (also how a full disk shows when the WAL's shared-memory file cannot be made), FULL, PROTOCOL.
_TRANSIENT_SQLITE = {5, 6, 7, 8, 10, 13, 15}
#: Extended codes of those that do not pass: READONLY_DBMOVED, the file was moved or deleted under the
#: connection, which never writes to it again.
_LASTING_SQLITE = {1032}
#: A full disk, a quota, an I/O error, a read-only file system (as after disk errors): all pass.
_TRANSIENT_ERRNO = {errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EROFS}
_UNAVAILABLE: dict[type[StorageError], type[StorageError]] = {
    CatalogError: CatalogUnavailableError, QueueError: QueueUnavailableError,
    RegistryError: RegistryUnavailableError}
#: Below this many free bytes a failure says how full the disk is.
LOW_SPACE_BYTES = 16 << 20


def _primary_code(exc: sqlite3.Error) -> int:
    """SQLite's primary result code of ``exc`` (its extended code's low byte; 0 when it carries none)."""
    return (getattr(exc, "sqlite_errorcode", None) or 0) & 0xFF


def is_transient(exc: BaseException) -> bool:
    """Whether ``exc`` (an ``sqlite3.Error`` or ``OSError``) is a condition that passes: a full disk, an
    I/O error, a busy database, a read-only one or a read-only file system (which an operator makes
    writable again: refusing the write as bad input would make workers drop what they collected)."""
    if isinstance(exc, sqlite3.Error):
        return _primary_code(exc) in _TRANSIENT_SQLITE and exc.sqlite_errorcode not in _LASTING_SQLITE
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


def quarantine_bytes(data_dir: str | Path) -> int | None:
    """Bytes the files in ``DATA/quarantine/`` take (0 when it holds none): what ``stats``, the dashboard and
    ``/metrics`` report beside how many episodes are quarantined. None when it cannot be read. A walk, one stat
    per file kept there: callers that ask often keep the answer a while (``orchestrator.metrics``)."""
    total, folders = 0, [Path(data_dir) / QUARANTINE_DIR]
    try:
        while folders:
            try:
                entries = list(os.scandir(folders.pop()))
            except FileNotFoundError:  # none yet, or emptied and removed meanwhile
                continue
            for entry in entries:
                try:
                    if entry.is_dir(follow_symlinks=False):
                        folders.append(entry.path)
                    elif entry.is_file(follow_symlinks=False):
                        total += entry.stat(follow_symlinks=False).st_size
                except FileNotFoundError:  # restored or re-ingested meanwhile: no longer there
                    continue
    except OSError:
        return None
    return total


def storage_error(exc: sqlite3.Error | OSError, error: type[StorageError], message: str,
                  path: str | Path) -> StorageError:
    """``error(message)``, or its ``...UnavailableError`` subclass when ``exc`` is a condition that passes
    (then with how full the disk holding ``path`` is, when that is the likely cause)."""
    if not is_transient(exc):
        return error(message)
    return _UNAVAILABLE.get(error, error)(message + space_note(path))


@contextmanager
def busy_timeout(seconds: float) -> Iterator[None]:
    """Within the block, the connections ``connect`` opens in this thread wait at most ``seconds`` for a lock
    (``BUSY_TIMEOUT_MS`` elsewhere): a reader that answers someone waiting (the dashboard's HTTP clients,
    whose scrapes time out after 10 s) says "busy, retry" sooner than a writer that must get through."""
    token = _BUSY_TIMEOUT_MS.set(max(0, int(seconds * 1000)))
    try:
        yield
    finally:
        _BUSY_TIMEOUT_MS.reset(token)


def connect(db_path: str | Path) -> sqlite3.Connection:
    """Opens the catalog database: autocommit (explicit transactions), WAL, busy timeout (``busy_timeout``).

    One connection per thread: open one where you need it and close it after.
    """
    busy_ms = _BUSY_TIMEOUT_MS.get()
    if busy_ms is None:
        busy_ms = BUSY_TIMEOUT_MS
    conn = sqlite3.connect(db_path, timeout=busy_ms / 1000, isolation_level=None)
    try:
        conn.row_factory = sqlite3.Row
        configure(conn, busy_ms, "FULL")  # FULL: a committed ingest survives power loss
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
    _use_wal(conn, busy_timeout_ms)
    conn.execute(f"PRAGMA synchronous = {synchronous}")
    conn.execute(f"PRAGMA journal_size_limit = {JOURNAL_SIZE_LIMIT}")


def _use_wal(conn: sqlite3.Connection, busy_timeout_ms: int) -> None:
    """The file in WAL mode, as every catalog is from its creation. One in another journal mode (written by
    another tool: sqlite3's ``.dump`` into a new file, say) is converted when that can be done at once; one that
    cannot be written (read-only storage) or that another connection is reading is used in its own mode, so a
    reader (``stats``, the dashboard) is not refused, nor kept waiting the busy timeout for a lock only the
    conversion needs (a write then meets the same condition, and says so)."""
    if conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal":  # the first read of the file: not a database?
        return
    if not conn.execute("PRAGMA page_count").fetchone()[0]:  # a new file: made WAL, as any write would wait
        _new_file_wal(conn, busy_timeout_ms)
        return
    conn.execute("PRAGMA busy_timeout = 0")
    try:
        conn.execute("PRAGMA journal_mode = WAL")
    except sqlite3.Error as exc:
        if not is_transient(exc):
            raise
    finally:
        conn.execute(f"PRAGMA busy_timeout = {busy_timeout_ms}")


def _new_file_wal(conn: sqlite3.Connection, busy_timeout_ms: int) -> None:
    """Make a new, empty file WAL. Connections opening it at once (``collect`` making a catalog while a dashboard
    or ``stats`` reads it) each hold the shared lock the others' conversion needs: SQLite answers all but one
    "database is locked" at once, without the busy wait (it would deadlock). Such a one finds the file WAL once
    the other has made it, or tries again, within the busy timeout."""
    deadline = time.monotonic() + busy_timeout_ms / 1000
    while True:
        try:
            conn.execute("PRAGMA journal_mode = WAL")
            return
        except sqlite3.OperationalError as exc:
            if _primary_code(exc) != sqlite3.SQLITE_BUSY or time.monotonic() >= deadline:
                raise
        if conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal":
            return
        time.sleep(0.005)


def _unwritable_note(exc: sqlite3.Error, db_path: str | Path) -> str:
    """Why a database in a folder that cannot be written (a read-only mount, a copy on read-only media) fails to
    open even to be read, or ''. SQLite's error says only "unable to open database file"."""
    folder = Path(db_path).parent
    if _primary_code(exc) not in (sqlite3.SQLITE_CANTOPEN, sqlite3.SQLITE_READONLY) or os.access(folder, os.W_OK):
        return ""
    return (f" ({folder} cannot be written: SQLite writes its -wal and -shm files beside the database even to "
            "read it; make it writable, or copy the data directory somewhere that is)")


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
        raise storage_error(exc, error, f"cannot open the database {db_path}: {exc}{_unwritable_note(exc, db_path)}",
                            db_path) from exc
    try:
        yield conn
    except sqlite3.Error as exc:
        converted = storage_error(exc, error, f"database {db_path}: {exc}", db_path)
        for note in getattr(exc, "__notes__", ()):  # e.g. what undo_unless_committed left in place
            converted.add_note(note)
        raise converted from exc
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


def undo_unless_committed(conn: sqlite3.Connection, committed: Callable[[sqlite3.Connection], bool],
                          undo: Callable[[], None], error: BaseException, left: str) -> None:
    """After ``error``, raised inside a write transaction on ``conn`` or by its ``COMMIT``: runs ``undo()``, which
    takes back what the transaction put in place outside the database (``left``: a file published, moved), unless
    the transaction committed. No transaction is open on ``conn`` after it.

    Whether it committed is not whether one is still open: a signal's exception (``KeyboardInterrupt`` on Ctrl-C)
    that arrives while ``COMMIT`` runs its fsync is raised once the call has returned, committed; and SQLite rolls
    back by itself on some errors (a full disk). So when none is open the write lock is taken again and
    ``committed(conn)`` reads the rows while no other writer can be half-way through the same change; ``undo``
    runs under the write lock either way. When that cannot be read, or ``undo`` fails, a note on ``error`` (which
    stays the one raised) says what is left; a file no row names is a stray (``storage.strays``).
    """
    try:
        if not conn.in_transaction:
            conn.execute("BEGIN IMMEDIATE")
            if committed(conn):
                return
        undo()
    except sqlite3.Error as exc:
        error.add_note(f"{left} is left in place: whether its row committed cannot be read ({exc})")
    except OSError as exc:
        error.add_note(f"{left} is left in place: {exc.strerror or exc}")
    finally:
        if conn.in_transaction:
            conn.execute("ROLLBACK")


def kept_counts(table: str, column: str, counts: str, values: str | None = None) -> tuple[str, ...]:
    """The statements that make ``counts`` (``column`` value -> ``n``) hold the number of rows of ``table`` with
    each value of ``column`` -- only those in ``values`` (an SQL list, ``"('a', 'b')"``) when given -- kept by
    triggers in every write's own transaction (any process's, any code version's), so a count reads a handful
    of rows instead of an index that grows with the history. A write that moves no counted value fires none:
    ``values`` spares a hot path (the queue's leases) the page the counts take in each of its commits.

    Idempotent, and safe in any transaction that holds the write lock (``BEGIN IMMEDIATE``, a migration's):
    the first run counts the rows already there (no write can come between that count and the triggers), a
    later one keeps the counts it finds. A value whose rows all left stays, at 0."""
    def only(condition: str, keyword: str = " WHEN ") -> str:  # the condition, when only some values are counted
        return "" if values is None else keyword + condition

    def count_in(row: str) -> str:
        return (f"INSERT OR IGNORE INTO {counts} ({column}, n) SELECT {row}.{column}, 0"
                f"{only(f'{row}.{column} IN {values}', ' WHERE ')}; "
                f"UPDATE {counts} SET n = n + 1 WHERE {column} = {row}.{column}; ")

    count_out = f"UPDATE {counts} SET n = n - 1 WHERE {column} = OLD.{column}; "  # (a row of counts: counted)
    moved = f" WHEN OLD.{column} IS NOT NEW.{column}" + only(
        f"(OLD.{column} IN {values} OR NEW.{column} IN {values})", " AND ")
    triggers = (("insert", "INSERT", only(f"NEW.{column} IN {values}"), count_in("NEW")),
                ("update", f"UPDATE OF {column}", moved, count_out + count_in("NEW")),
                ("delete", "DELETE", only(f"OLD.{column} IN {values}"), count_out))
    return (f"CREATE TABLE IF NOT EXISTS {counts} ({column} TEXT PRIMARY KEY, n INTEGER NOT NULL)",
            f"INSERT OR IGNORE INTO {counts} ({column}, n) SELECT {column}, COUNT(*) FROM {table}"
            f"{only(f'{column} IN {values}', ' WHERE ')} GROUP BY {column}",
            *(f"CREATE TRIGGER IF NOT EXISTS {counts}_{name} AFTER {event} ON {table}{cond} BEGIN {body}END"
              for name, event, cond, body in triggers))


def ensure_schema(conn: sqlite3.Connection, component: str,
                  migrations: Sequence[Migration | Sequence[str]], error: type[StorageError] = CatalogError) -> int:
    """Applies ``migrations[v:]`` where ``v`` is ``component``'s recorded version; returns the file's
    version after the call.

    Each migration is applied in one transaction together with the version bump and the file's new
    compatible level (the highest ``compatible_with`` of ``migrations``). A file already at this code's
    version, or at a newer one whose level is at most ``len(migrations)``, is only read: opening a catalog
    does not wait for writers. Raises ``error`` (the component's: ``CatalogError``, ``RegistryError``)
    if the file is newer than this code and not compatible with it; ``ValueError`` if a migration declares a
    level above its own version.
    """
    known, level = len(migrations), _compatible_level(migrations)
    recorded = _recorded(conn, component)
    if recorded is not None and recorded[0] >= known:
        return _usable_version(component, *recorded, known, error)
    with transaction(conn):
        version, compatible = _recorded(conn, component) or (0, None)
        if version >= known:  # another process migrated it since the read above
            return _usable_version(component, version, compatible, known, error)
        _create_versions_table(conn)
        for entry in migrations[version:]:
            for sql in entry.statements if isinstance(entry, Migration) else entry:
                conn.execute(sql)
        conn.execute("INSERT INTO schema_versions(component, version, updated, compatible) VALUES (?, ?, ?, ?) "
                     "ON CONFLICT(component) DO UPDATE SET version = excluded.version, "
                     "updated = excluded.updated, compatible = excluded.compatible",
                     (component, known, _now_iso(), level))
    return known


def _compatible_level(migrations: Sequence[Migration | Sequence[str]]) -> int:
    """The lowest code version that may use a file after all of ``migrations``: the highest of their levels."""
    level = 0
    for version, entry in enumerate(migrations, 1):
        declared = entry.compatible_with if isinstance(entry, Migration) else None
        if declared is not None and declared > version:
            raise ValueError(f"migration to schema version {version}: compatible_with must be at most "
                             f"{version}, found {declared}")
        level = max(level, version if declared is None else declared)
    return level


def _usable_version(component: str, version: int, compatible: int | None, known: int,
                    error: type[StorageError]) -> int:
    """``version``, the file's, when code that knows ``known`` versions may use it unchanged (``version``
    >= ``known``); raises ``error`` when it is newer and not declared compatible with that code."""
    needed = version if compatible is None else compatible
    if version > known and needed > known:
        raise error(f"{component} tables are at schema version {version}, this code knows versions "
                    f"up to {known} and the file needs code that knows version {needed} or later; "
                    f"upgrade activecollect")
    return version


def _create_versions_table(conn: sqlite3.Connection) -> None:
    """``schema_versions``, with the ``compatible`` column even where code from before it made the table
    (a nullable column added in the migration's transaction: that code's statements name their columns)."""
    conn.execute("CREATE TABLE IF NOT EXISTS schema_versions (component TEXT PRIMARY KEY, "
                 "version INTEGER NOT NULL, updated TEXT NOT NULL, compatible INTEGER)")
    if "compatible" not in {r[1] for r in conn.execute("PRAGMA table_info(schema_versions)")}:
        conn.execute("ALTER TABLE schema_versions ADD COLUMN compatible INTEGER")


def _recorded(conn: sqlite3.Connection, component: str) -> tuple[int, int | None] | None:
    """``component``'s ``(version, compatible level)`` in the file, read without a write lock (None: not
    recorded; level None: recorded by code from before levels)."""
    if not conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'schema_versions'").fetchone():
        return None
    cursor = conn.execute("SELECT * FROM schema_versions WHERE component = ?", (component,))  # one snapshot
    row = cursor.fetchone()
    if row is None:
        return None
    fields = dict(zip((d[0] for d in cursor.description), row))
    return fields["version"], fields.get("compatible")


def _now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")
