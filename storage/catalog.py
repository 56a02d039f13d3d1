"""The catalog: an SQLite index (WAL mode) of every episode file under a data directory.

Layout::

    DATA/catalog.sqlite                       this index, plus other components' tables
    DATA/episodes/<yyyy-mm-dd>/<episode_id>.mcap
    DATA/quarantine/<yyyy-mm-dd>/<episode_id>.mcap   files taken out of training (``Catalog.quarantine``)
    DATA/orphans/...                          episode files no row indexes, moved aside (``sweep_strays``)

Ingest is idempotent (the same file twice is one episode) and atomic: the file is
verified, staged under a temporary name and fsynced outside any lock; then, inside
one ``BEGIN IMMEDIATE`` transaction, it is renamed into place, its row inserted and
the caller's ``in_transaction`` hook run. A failure that leaves the row uncommitted removes the
renamed file under the write lock (``storage.database.undo_unless_committed``: a Ctrl-C raised as
the COMMIT returns keeps both), so an ingest never leaves a row without its file and no
other ingest can have claimed the name in between. (A quarantined episode keeps its row
while its file is away, or gone: ``quarantine`` records where it went, see ``storage.quarantine``.)

A catalog holds one frame size, its eval split's, else its first episode's; that first
episode must be of a size a model trains on (``storage.records.trainable_size``).

Other components (``storage.queue``, ``storage.models``) keep their tables in the
same file (``storage.database``). The catalog's own tables are read and written by its steps over a
connection in ``storage.episode_table`` (the episodes: schema, rows, filters), ``storage.eval_split`` (the
eval split, snapshots, the frame size) and ``storage.quarantine``. The rows the catalog answers with are
``storage.rows``'s dataclasses, its sweep of what crashed ingests left is ``storage.strays``; both
re-exported here.
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Any

from storage.episode_reader import EpisodeInfo, inspect_episode, read_episode, read_file, verify_episode
from storage.episodes import encode_episode
from storage.database import (DB_NAME, EPISODES_DIR, Migration, connection, ensure_schema, refuse_lost_database,
                              storage_error, transaction, undo_unless_committed)
from storage.errors import CatalogError, CorruptEpisodeError, EpisodeError, MissingEpisodeError, UnknownEpisodeError
from storage.files import holds, move, publish, sha256_hex, stage_bytes
from storage import episode_table
# (named apart from the methods Catalog.eval_split, Catalog.quarantine and Catalog.strays, which call them)
from storage import eval_split as eval_splits
from storage import quarantine as quarantines
from storage import strays as stray_files
from storage.quarantine import quarantine_path
from storage.records import (MAX_FRAME_SIZE, MIN_FRAME_SIZE, TRAINABLE_SIZES, Episode, EpisodeMeta,
                             trainable_size)
from storage.rows import EpisodeRow, EvalSplit, IngestResult, Snapshot
from storage.strays import ORPHANS_DIR, STAGING_MAX_AGE_S, Strays

#: Splits an episode can belong to. ``eval`` episodes never enter a training snapshot.
SPLITS: tuple[str, ...] = ("train", "eval")

#: One entry per schema version; a change to the tables is a new entry at the end. Each says which older
#: code may still use the file after it (``compatible_with``, see ``storage.database.Migration``): leave
#: the default, its own version, unless that code can neither misread nor damage the new shape.
_CATALOG_MIGRATIONS: tuple[Migration, ...] = (
    Migration((*episode_table.SCHEMA, *eval_splits.TABLES)),
    # The quarantine table (storage.quarantine). Not for version-1 code, which would ignore the table:
    # snapshot quarantined episodes for training (their files are gone) and let them be pinned in the eval split.
    Migration((quarantines.TABLE,), compatible_with=2),
)


# ---------------------------------------------------------------------------------------------
# the catalog


def _check_frame_size(conn: sqlite3.Connection, meta: EpisodeMeta) -> None:
    """Every episode of a catalog has one frame size (``storage.eval_split.frame_size``): the models train on,
    and score, one size, so one other episode would fail every retrain. The episode that fixes it must be one a
    model trains on (``trainable_size``); a catalog fixed at another size before that rule keeps its size.
    Raises ``CatalogError``."""
    if not MIN_FRAME_SIZE <= meta.image_size <= MAX_FRAME_SIZE:
        raise CatalogError(f"episode {meta.episode_id} has {meta.image_size}px frames; expected "
                           f"{MIN_FRAME_SIZE}..{MAX_FRAME_SIZE} (what the simulator renders and workers record)")
    fixed = eval_splits.frame_size(conn)
    if fixed is None and not trainable_size(meta.image_size):
        raise CatalogError(f"episode {meta.episode_id} has {meta.image_size}px frames; the first episode fixes "
                           f"this catalog's frame size, which must be {TRAINABLE_SIZES} (what a model trains on)")
    if fixed is not None and fixed[0] != meta.image_size:
        raise CatalogError(f"episode {meta.episode_id} has {meta.image_size}px frames; this catalog holds "
                           f"{fixed[0]}px episodes ({fixed[1]}): its models train and score one size")


def _check_split(split: str) -> None:
    if split not in SPLITS:
        raise CatalogError(f"unknown split {split!r}; expected one of {', '.join(SPLITS)}")


class Catalog:
    """Index of the episodes under ``data_dir``; safe to share between threads and processes."""

    def __init__(self, data_dir: str | Path):
        self.data_dir = Path(data_dir).absolute()
        refuse_lost_database(self.data_dir, CatalogError)
        self.episodes_dir = self.data_dir / EPISODES_DIR
        self.episodes_dir.mkdir(parents=True, exist_ok=True)
        self._db_path = self.data_dir / DB_NAME
        with self._connect() as conn:
            ensure_schema(conn, "catalog", _CATALOG_MIGRATIONS)

    @property
    def db_path(self) -> Path:
        return self._db_path

    def _connect(self) -> AbstractContextManager[sqlite3.Connection]:
        return connection(self._db_path, CatalogError)

    def _row(self, r: sqlite3.Row) -> EpisodeRow:
        return episode_table.row(r, self.data_dir)

    # --- ingest ---------------------------------------------------------------------------------

    def add_episode(self, ep: Episode, split: str = "train",
                    in_transaction: Callable[[sqlite3.Connection], None] | None = None) -> IngestResult:
        """Encodes an in-memory episode and indexes it (see ``ingest_bytes``)."""
        data = encode_episode(ep)
        return self._store(data, sha256_hex(data), ep.meta, len(ep), split, in_transaction)

    def ingest_file(self, path: str | Path, split: str = "train",
                    admit: Callable[[EpisodeMeta], str] | None = None) -> IngestResult:
        """Verifies and indexes an MCAP file collected elsewhere (copied into the data dir).

        ``admit(meta)``: the caller's own rule for what may enter (e.g. the task space's physics), run
        once the file has verified; a non-empty answer refuses the file with that reason
        (``EpisodeError``). Raises ``CatalogError`` for a missing/unreadable path, ``EpisodeError``
        subclasses for a bad file.
        """
        path = Path(path)
        data = read_file(path, CatalogError)
        info = inspect_episode(data, name=str(path))
        refusal = admit(info.meta) if admit is not None else ""
        if refusal:
            raise EpisodeError(f"{path}: {refusal}")
        return self._ingest(data, None, split, None, str(path), verified=info)

    def ingest_bytes(self, data: bytes, expected_sha256: str | None = None, split: str = "train",
                     in_transaction: Callable[[sqlite3.Connection], None] | None = None,
                     verified: EpisodeInfo | None = None,
                     write_lock: AbstractContextManager[Any] | None = None) -> IngestResult:
        """Verifies ``data`` (sha256 when given, MCAP structure, CRCs, schemas) and indexes it.

        ``in_transaction(conn)`` runs inside the ``BEGIN IMMEDIATE`` transaction that inserts
        the row (it must not commit); if it raises, nothing is indexed, the new file is
        removed and the exception propagates. It is not called for a duplicate (the first
        ingest of those bytes already ran it and committed).

        ``verified``: what the caller learned by fully reading these very bytes itself
        (``read_episode`` / ``inspect_episode``, e.g. the service checking an upload's provenance);
        the MCAP is then not parsed a second time. The sha256 is still computed and checked.

        ``write_lock``: held around the write transaction only (not the verification or the
        staging fsync). A process whose other threads write the same file (the service's queue)
        passes the lock they take, so they wait for this ingest on it, woken when it commits,
        rather than in SQLite's busy handler, which sleeps in steps of up to 100 ms.

        Raises ``CorruptEpisodeError`` on a sha256 mismatch, the ``EpisodeError`` subclasses of ``verify_episode``,
        ``CatalogError`` for an unknown split, an unsafe episode id, an id already indexed with different bytes or
        in another split, or a replay of an episode of the other split (``storage.eval_split.refuse_replay``).
        """
        return self._ingest(data, expected_sha256, split, in_transaction, None, verified, write_lock)

    def _ingest(self, data: bytes, expected_sha256: str | None, split: str,
                in_transaction: Callable[[sqlite3.Connection], None] | None, name: str | None,
                verified: EpisodeInfo | None = None,
                write_lock: AbstractContextManager[Any] | None = None) -> IngestResult:
        _check_split(split)
        data = bytes(data)
        sha = sha256_hex(data)
        if expected_sha256 is not None and expected_sha256.lower() != sha:
            raise CorruptEpisodeError(f"{name or 'upload'}: sha256 mismatch: expected {expected_sha256}, "
                                      f"found {sha} ({len(data)} bytes)")
        info = verified if verified is not None else inspect_episode(data, name=name)
        return self._store(data, sha, info.meta, info.frames, split, in_transaction, write_lock)

    def _store(self, data: bytes, sha: str, meta: EpisodeMeta, frames: int, split: str,
               in_transaction: Callable[[sqlite3.Connection], None] | None,
               write_lock: AbstractContextManager[Any] | None = None) -> IngestResult:
        _check_split(split)
        rel = episode_table.file_path(meta)
        final = self.data_dir / rel
        known = self.find(meta.episode_id)
        if known is not None:  # fast path; re-checked under the lock below
            return self._duplicate(known, sha, split, data)
        staged = None
        try:
            staged = stage_bytes(final, data)  # the slow part (write + fsync), outside the write lock
            with self._connect() as conn:
                with write_lock if write_lock is not None else nullcontext():
                    return self._insert(conn, staged, final, rel, data, sha, meta, frames, split, in_transaction)
        except OSError as exc:  # a full disk, staging or renaming into place: nothing indexed (rolled back)
            raise storage_error(exc, CatalogError, f"cannot store episode {meta.episode_id} at {final}: "
                                f"{exc.strerror or exc}", final) from exc
        finally:
            if staged is not None:
                staged.unlink(missing_ok=True)

    def _insert(self, conn: sqlite3.Connection, staged: Path, final: Path, rel: str, data: bytes,
                sha: str, meta: EpisodeMeta, frames: int, split: str,
                in_transaction: Callable[[sqlite3.Connection], None] | None) -> IngestResult:
        conn.execute("BEGIN IMMEDIATE")
        published = False
        try:
            known = episode_table.find(conn, self.data_dir, meta.episode_id)
            if known is not None:
                conn.execute("ROLLBACK")
                return self._duplicate(known, sha, split, data)
            _check_frame_size(conn, meta)
            eval_splits.refuse_replay(conn, meta, split)  # no split may hold a recording of the other's
            publish(staged, final)
            published = True
            episode_table.insert(conn, meta, rel, sha, frames, split, len(data))
            if in_transaction is not None:
                in_transaction(conn)
            conn.execute("COMMIT")
        except BaseException as exc:
            if published:  # removed under the write lock unless its row committed: nobody else can index it
                undo_unless_committed(conn, lambda c: stray_files.indexed(c, rel),
                                      lambda: final.unlink(missing_ok=True), exc, str(final))
            elif conn.in_transaction:
                conn.execute("ROLLBACK")
            raise
        return IngestResult(meta.episode_id, final, sha, duplicate=False)

    def _duplicate(self, known: EpisodeRow, sha: str, split: str, data: bytes) -> IngestResult:
        if known.sha256 != sha:
            raise CatalogError(f"episode {known.episode_id} is already indexed with sha256 {known.sha256}; "
                               f"refusing different bytes (sha256 {sha})")
        if known.split != split:
            raise CatalogError(f"episode {known.episode_id} is already indexed in split {known.split!r}, "
                               f"not {split!r}")
        if not known.quarantined and holds(known.path, sha):
            return IngestResult(known.episode_id, known.path, sha, duplicate=True)
        # the same bytes restore a file lost from disk, damaged, or quarantined (which ends the quarantine)
        staged = None
        try:
            staged = stage_bytes(known.path, data)
            with self._connect() as conn, transaction(conn):
                publish(staged, known.path)
                quarantines.readmit(conn, known.episode_id, self._kept(known), sha)
        except OSError as exc:
            raise storage_error(exc, CatalogError, f"cannot restore episode {known.episode_id} at {known.path}: "
                                f"{exc.strerror or exc}", known.path) from exc
        finally:
            if staged is not None:
                staged.unlink(missing_ok=True)
        return IngestResult(known.episode_id, known.path, sha, duplicate=True, restored=True)

    # --- queries ---------------------------------------------------------------------------------

    def frame_size(self) -> int | None:
        """The frame size every episode here has (its eval split's, else its first episode's); None
        while it holds none."""
        with self._connect() as conn:
            fixed = eval_splits.frame_size(conn)
        return None if fixed is None else fixed[0]

    def find(self, episode_id: str) -> EpisodeRow | None:
        with self._connect() as conn:
            return episode_table.find(conn, self.data_dir, episode_id)

    def get(self, episode_id: str) -> EpisodeRow:
        """The row of ``episode_id``; ``CatalogError`` if it is not indexed."""
        row = self.find(episode_id)
        if row is None:
            raise UnknownEpisodeError(f"no episode {episode_id!r} in the catalog at {self.data_dir}")
        return row

    def resolve(self, id_or_prefix: str) -> EpisodeRow:
        """The episode whose id is ``id_or_prefix`` or uniquely starts with it (for the CLI)."""
        row = self.find(id_or_prefix)
        if row is not None:
            return row
        with self._connect() as conn:
            rows = episode_table.by_prefix(conn, self.data_dir, id_or_prefix)
        if len(rows) == 1 and id_or_prefix:
            return rows[0]
        if len(rows) > 1 and id_or_prefix:
            raise UnknownEpisodeError(f"episode id prefix {id_or_prefix!r} is ambiguous "
                                      f"({', '.join(r.episode_id for r in rows[:2])}, ...)")
        raise UnknownEpisodeError(f"no episode {id_or_prefix!r} in the catalog at {self.data_dir}")

    def list(self, split: str | None = None, shape: str | None = None, limit: int | None = None,
             since: float | str | datetime | None = None, newest_first: bool = False,
             quarantined: bool | None = None) -> list[EpisodeRow]:
        """Indexed episodes in ingest order (``newest_first`` reverses it).

        ``since``: only episodes indexed at or after this time (unix seconds, ISO 8601 or datetime).
        ``quarantined``: only those taken out of training (True), only the others (False), or all (None).
        """
        where, args = self._filters(split, shape, since, quarantined)
        sql = f"{episode_table.SELECT_ROWS}{where} ORDER BY e.rowid {'DESC' if newest_first else 'ASC'}"
        if limit is not None:
            sql += " LIMIT ?"
            args.append(int(limit))
        with self._connect() as conn:
            return [self._row(r) for r in conn.execute(sql, args).fetchall()]

    def count(self, split: str | None = None, shape: str | None = None,
              since: float | str | datetime | None = None, quarantined: bool | None = None) -> int:
        where, args = self._filters(split, shape, since, quarantined)
        with self._connect() as conn:
            return conn.execute(f"SELECT COUNT(*) FROM {episode_table.FROM_ROWS}{where}", args).fetchone()[0]

    def _filters(self, split: str | None, shape: str | None, since: float | str | datetime | None,
                 quarantined: bool | None) -> tuple[str, list[Any]]:
        if split is not None:
            _check_split(split)
        return episode_table.where(split, shape, since, quarantined)

    def summary(self) -> dict[str, Any]:
        """Episode, frame and byte totals by split and shape (for status displays)."""
        with self._connect() as conn:
            return episode_table.summary(conn)

    def meta(self, episode_id: str) -> EpisodeMeta:
        """The provenance recorded at ingest (no file access)."""
        with self._connect() as conn:
            r = conn.execute("SELECT meta FROM episodes WHERE episode_id = ?", (episode_id,)).fetchone()
        if r is None:
            raise UnknownEpisodeError(f"no episode {episode_id!r} in the catalog at {self.data_dir}")
        return EpisodeMeta.from_json(r["meta"])

    def _read_checked(self, row: EpisodeRow, heal: bool = True) -> bytes:
        try:
            data = row.path.read_bytes()
        except FileNotFoundError:
            if heal and not row.quarantined:
                try:
                    with self._connect() as conn, transaction(conn):
                        healed = quarantines.heal(conn, row, self._kept(row))
                except OSError as exc:
                    raise EpisodeError(f"{row.path}: cannot move it back from quarantine: {exc}") from exc
                if healed:
                    return self._read_checked(row, heal=False)
            why = (f"it is quarantined ({row.quarantined}); `activecollect episodes restore` puts it back"
                   if row.quarantined else "re-ingest its bytes (e.g. from a backup) to restore it")
            raise MissingEpisodeError(f"{row.path}: file of episode {row.episode_id} is missing: {why}") from None
        except OSError as exc:
            raise EpisodeError(f"{row.path}: cannot read: {exc.strerror or exc}") from exc
        sha = sha256_hex(data)
        if sha != row.sha256:
            raise CorruptEpisodeError(f"{row.path}: sha256 is {sha}, the catalog recorded {row.sha256}")
        return data

    def load(self, episode_id: str) -> Episode:
        """Reads an indexed episode, checking its sha256 and CRCs."""
        row = self.get(episode_id)
        return read_episode(self._read_checked(row), name=str(row.path))

    def strays(self, min_tmp_age_s: float = STAGING_MAX_AGE_S, now: float | None = None) -> Strays:
        """Files under ``episodes/`` a crashed ingest left: staging files older than ``min_tmp_age_s``
        and episode files with no catalog row.

        Files are listed first, then checked under the write lock: an ingest renames its file into
        place inside its write transaction, so by the time the lock is ours every listed file's
        ingest has committed (a row) or rolled back (the file removed). Staging happens before that
        transaction, hence the age for those.
        """
        return self._strays(min_tmp_age_s, now, move_to=None)

    def sweep_strays(self, min_tmp_age_s: float = STAGING_MAX_AGE_S, now: float | None = None) -> Strays:
        """``strays`` cleaned up: staging files deleted, unindexed episode files moved to ``DATA/orphans/``.

        Neither was ever acknowledged (the catalog row is the one commit point); a worker that still
        holds the lease uploads the same bytes again. Orphans are kept for the operator (``not_moved``: left).
        The moves happen under the write lock, so an upload of the same episode cannot slip in between.
        """
        found = self._strays(min_tmp_age_s, now, move_to=self.data_dir / ORPHANS_DIR)
        for path in found.staging:
            path.unlink(missing_ok=True)
        return found

    def _strays(self, min_tmp_age_s: float, now: float | None, move_to: Path | None) -> Strays:
        now = time.time() if now is None else now
        files = stray_files.episode_files(self.episodes_dir)
        with self._connect() as conn, transaction(conn):  # held briefly: no directory walk inside
            unindexed, not_moved = stray_files.unindexed(conn, self.data_dir, files, move_to)
        return Strays(stray_files.staging_files(self.data_dir, min_tmp_age_s, now), unindexed, not_moved)

    def quarantine(self, episode_id: str, reason: str, only_if_damaged: bool = False) -> EpisodeRow:
        """Takes an episode out of training; returns its row as it is now.

        For a file found missing or damaged (a training job does this itself, see
        ``uncertainty.data.load_train``, so one lost file does not stop every retrain) or one an operator
        rejects. Its row stays (what was acknowledged stays known), its file, when there is one, moves to
        ``quarantine_path`` (an intact copy already kept there stays), and snapshots leave it out.
        ``restore``, or ingesting the same bytes again, brings it back. Quarantining twice keeps the first
        reason. Episodes of the pinned eval split cannot be quarantined (the split is fixed): restore their
        bytes instead. ``only_if_damaged``: unless its file holds the bytes indexed by the time the write
        lock is ours (a repair that came in between wins); the row returned then is not quarantined.

        The file moves inside the write transaction and back, under the write lock, if it does not commit;
        after a crash in between, the next read of the episode moves it back (``storage.quarantine.heal``).
        """
        reason = quarantines.clean_reason(reason)
        row = self.get(episode_id)
        kept = self._kept(row)
        moved = False
        try:
            with self._connect() as conn:
                try:
                    with transaction(conn):
                        quarantines.refuse_pinned(conn, row.episode_id)
                        if quarantines.is_quarantined(conn, row.episode_id):
                            return self.get(row.episode_id)  # another process's quarantine, committed
                        if only_if_damaged and holds(row.path, row.sha256):
                            return row
                        if quarantines.record(conn, row, kept, self.data_dir, reason):
                            move(row.path, kept)  # (over a damaged leftover there)
                            moved = True
                except BaseException as error:
                    if moved:  # unless the quarantine committed, the file goes back where its row says it is
                        undo_unless_committed(conn, lambda c: quarantines.is_quarantined(c, row.episode_id),
                                              partial(self._move_back, kept, row, error), error, str(kept))
                    raise
        except OSError as exc:
            raise storage_error(exc, CatalogError, f"cannot move {row.path} to {kept}: {exc.strerror or exc}",
                                kept) from exc
        return self.get(row.episode_id)

    @staticmethod
    def _move_back(kept: Path, row: EpisodeRow, error: BaseException) -> None:
        """After a quarantine that did not commit (``error``), under the write lock: its file back from ``kept``.
        That move's own failure is noted on ``error``, which stays the one raised: the next read of the episode
        moves it back (``quarantine.heal``)."""
        try:
            move(kept, row.path)
        except OSError as exc:
            error.add_note(f"{kept} could not be moved back to {row.path} ({exc.strerror or exc}); the next "
                           f"read of episode {row.episode_id} moves it back")

    def restore(self, episode_id: str) -> EpisodeRow:
        """Puts a quarantined episode back into training; returns its row as it is now.

        Its file moves back from ``DATA/quarantine/`` if it still holds the bytes indexed (or is already
        back in place). ``CatalogError`` when it is not quarantined, or its file is gone or damaged: then
        ingesting its original bytes again restores it.
        """
        row = self.get(episode_id)
        kept = self._kept(row)
        try:
            with self._connect() as conn, transaction(conn):
                quarantines.put_back(conn, row, kept)
        except OSError as exc:
            raise storage_error(exc, CatalogError, f"cannot restore episode {row.episode_id} to {row.path}: "
                                f"{exc.strerror or exc}", row.path) from exc
        return self.get(row.episode_id)

    def _kept(self, row: EpisodeRow) -> Path:
        return self.data_dir / quarantine_path(row.path.relative_to(self.data_dir).as_posix())

    def verify(self, episode_id: str) -> EpisodeMeta:
        """Re-hashes and re-verifies an indexed episode's file; raises a ``StorageError`` if bad."""
        row = self.get(episode_id)
        meta = verify_episode(self._read_checked(row), name=str(row.path))
        if meta.episode_id != row.episode_id:
            raise CorruptEpisodeError(f"{row.path}: holds episode {meta.episode_id}, "
                                      f"indexed as {row.episode_id}")
        return meta

    # --- evaluation split and snapshots --------------------------------------------------------

    def pin_eval_split(self, ids: Sequence[str], params: dict[str, Any] | None = None) -> str:
        """Pins the evaluation split to ``ids`` (all indexed with split ``eval``); returns its hash.

        Pinning the same ids again returns the same hash; a different set is refused
        (``CatalogError``): the split is fixed for the life of the data directory.
        """
        ids = sorted(set(ids))
        if not ids:
            raise CatalogError("an eval split needs at least one episode")
        with self._connect() as conn, transaction(conn):
            return eval_splits.pin(conn, ids, params)

    def eval_split(self) -> EvalSplit | None:
        """The pinned evaluation split, or None. ``CatalogError`` if its rows no longer match its hash."""
        with self._connect() as conn:
            return eval_splits.read(conn)

    def snapshot(self, split: str = "train") -> Snapshot:
        """The episodes of ``split`` now, with a content id. Training never sees eval episodes, nor
        quarantined ones."""
        _check_split(split)
        with self._connect() as conn:
            return eval_splits.snapshot(conn, split)

    def replays(self, split: str = "train", metas: Sequence[EpisodeMeta] | None = None) -> dict[str, str]:
        """Episodes of ``split`` (or ``metas``) replaying one of the other: {id: its id} (``eval_split.replays``)."""
        _check_split(split)
        with self._connect() as conn:
            return eval_splits.replays(conn, split, metas)
