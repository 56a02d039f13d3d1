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
The bytes of an episode already indexed put back its file when it is lost or damaged: an ingest of them
also ends its quarantine (``ingest_bytes``); a worker's upload of them, repeated or racing its first copy, does
not (``repair_file``, ``ingest_bytes(readmit=False)``).

A catalog holds one frame size, its eval split's, else its first episode's; that first
episode must be of a size a model trains on (``storage.records.trainable_size``).

Other components (``storage.queue``, ``storage.models``) keep their tables in the
same file (``storage.database``). ``Catalog`` is this module's ingest and the parts it is made of, one
concept each, every method opening its own connection and, to write, its own transaction:
``storage.catalog_reads`` (the paths, the connections, the rows and files read back), ``storage.catalog_quarantine``
(quarantine and restore), ``storage.catalog_eval`` (the eval split, snapshots, the frame size) and
``storage.catalog_strays`` (the sweep of what crashed ingests left). Their steps over a connection are
``storage.episode_table`` (the episodes: schema, rows, filters), ``storage.eval_split``, ``storage.quarantine`` and
``storage.strays``. The rows the catalog answers with are ``storage.rows``'s dataclasses; they, the splits and
the strays' names are re-exported here.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

from storage.episode_reader import EpisodeInfo, inspect_episode, read_file
from storage.episodes import encode_episode
from storage.database import (DB_NAME, EPISODES_DIR, Migration, ensure_schema, refuse_lost_database, storage_error,
                              transaction, undo_unless_committed)
from storage.errors import CatalogError, CatalogFolderError, CorruptEpisodeError, EpisodeError, OtherSplitError
from storage.files import holds, make_folder, move, publish, sha256_hex, stage_bytes
from storage import episode_table
# (named apart from the methods Catalog.eval_split, Catalog.quarantine and Catalog.strays)
from storage import eval_split as eval_splits
from storage import quarantine as quarantines
from storage import strays as stray_files
from storage.catalog_eval import CatalogEvalSplit
from storage.catalog_quarantine import CatalogQuarantine
from storage.catalog_reads import SPLITS, check_split
from storage.catalog_strays import CatalogStrays
from storage.records import MAX_FRAME_SIZE, MIN_FRAME_SIZE, TRAINABLE_SIZES, Episode, EpisodeMeta, trainable_size
from storage.rows import EpisodeRow, EvalSplit, IngestResult, Snapshot
from storage.strays import ORPHANS_DIR, STAGING_MAX_AGE_S, Strays

__all__ = ["SPLITS", "Catalog", "EpisodeRow", "EvalSplit", "IngestResult", "Snapshot", "ORPHANS_DIR",
           "STAGING_MAX_AGE_S", "Strays"]

#: One entry per schema version; a change to the tables is a new entry at the end. Each says which older
#: code may still use the file after it (``compatible_with``, see ``storage.database.Migration``): leave
#: the default, its own version, unless that code can neither misread nor damage the new shape.
_CATALOG_MIGRATIONS: tuple[Migration, ...] = (
    Migration((*episode_table.SCHEMA, *eval_splits.TABLES)),
    # The quarantine table (storage.quarantine). Not for version-1 code, which would ignore the table:
    # snapshot quarantined episodes for training (their files are gone) and let them be pinned in the eval split.
    Migration((quarantines.TABLE,), compatible_with=2),
    # The number of episodes in each split, kept by triggers (``storage.database.kept_counts``) for the
    # service's once-a-second gauges and the retrain trigger's count. Fine for version-2 code: it never reads
    # the table, and its own writes keep the counts through the triggers.
    Migration(episode_table.COUNTS, compatible_with=2),
)

_T = TypeVar("_T")


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


class Catalog(CatalogQuarantine, CatalogEvalSplit, CatalogStrays):
    """Index of the episodes under ``data_dir``; safe to share between threads and processes."""

    def __init__(self, data_dir: str | Path, make_episodes_dir: bool = True):
        self.data_dir = Path(data_dir).absolute()
        refuse_lost_database(self.data_dir, CatalogError)
        self.episodes_dir = self.data_dir / EPISODES_DIR
        make_folder(self.episodes_dir, CatalogFolderError, "the catalog keeps its episode files there",
                    create=make_episodes_dir)  # (False: a reader that must write nothing; ingests make their folders)
        self._db_path = self.data_dir / DB_NAME
        with self._connect() as conn:
            ensure_schema(conn, "catalog", _CATALOG_MIGRATIONS)

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
                     write_lock: AbstractContextManager[Any] | None = None, readmit: bool = True) -> IngestResult:
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

        ``readmit``: what the bytes of an episode already indexed do when no intact copy of them is in place (its
        file lost or damaged, or the episode quarantined). True (an operator's ``ingest``): they put its file back
        and end its quarantine (``restored``). False (a worker's upload, ``orchestrator.uploads``): they are kept as
        ``repair_file`` keeps them, which never ends a quarantine (``restored`` when they were written).

        Raises ``CorruptEpisodeError`` on a sha256 mismatch, the ``EpisodeError`` subclasses of ``verify_episode``,
        ``CatalogError`` for an unknown split, an unsafe episode id, an id already indexed with different bytes or
        in another split, or a replay of an episode of the other split (``storage.eval_split.refuse_replay``).
        """
        return self._ingest(data, expected_sha256, split, in_transaction, None, verified, write_lock, readmit)

    def _ingest(self, data: bytes, expected_sha256: str | None, split: str,
                in_transaction: Callable[[sqlite3.Connection], None] | None, name: str | None,
                verified: EpisodeInfo | None = None,
                write_lock: AbstractContextManager[Any] | None = None, readmit: bool = True) -> IngestResult:
        check_split(split)
        data = bytes(data)
        sha = sha256_hex(data)
        if expected_sha256 is not None and expected_sha256.lower() != sha:
            raise CorruptEpisodeError(f"{name or 'upload'}: sha256 mismatch: expected {expected_sha256}, "
                                      f"found {sha} ({len(data)} bytes)")
        info = verified if verified is not None else inspect_episode(data, name=name)
        return self._store(data, sha, info.meta, info.frames, split, in_transaction, write_lock, readmit)

    def _store(self, data: bytes, sha: str, meta: EpisodeMeta, frames: int, split: str,
               in_transaction: Callable[[sqlite3.Connection], None] | None,
               write_lock: AbstractContextManager[Any] | None = None, readmit: bool = True) -> IngestResult:
        check_split(split)
        rel = episode_table.file_path(meta)
        final = self.data_dir / rel
        known = self.find(meta.episode_id)
        if known is not None:  # fast path; re-checked under the lock below
            return self._duplicate(known, sha, split, data, readmit, write_lock)
        insert = partial(self._insert, final=final, rel=rel, data=data, sha=sha, meta=meta, frames=frames,
                         split=split, in_transaction=in_transaction, readmit=readmit)
        return self._staged(final, data, write_lock, insert, f"cannot store episode {meta.episode_id} at {final}")

    def _insert(self, conn: sqlite3.Connection, staged: Path, final: Path, rel: str, data: bytes,
                sha: str, meta: EpisodeMeta, frames: int, split: str,
                in_transaction: Callable[[sqlite3.Connection], None] | None, readmit: bool) -> IngestResult:
        conn.execute("BEGIN IMMEDIATE")
        try:
            known = episode_table.find(conn, self.data_dir, meta.episode_id)
            if known is not None:
                conn.execute("ROLLBACK")
                return self._duplicate(known, sha, split, data, readmit, None)  # (the write lock is held here)
            _check_frame_size(conn, meta)
            eval_splits.refuse_replay(conn, meta, split)  # no split may hold a recording of the other's
            publish(staged, final)
            episode_table.insert(conn, meta, rel, sha, frames, split, len(data))
            if in_transaction is not None:
                in_transaction(conn)
            conn.execute("COMMIT")
        except BaseException as exc:
            if not staged.exists():  # published (maybe not returned: a signal's exception in its fsync): removed
                # under the write lock unless its row committed; nobody else can index it
                undo_unless_committed(conn, lambda c: stray_files.indexed(c, rel),
                                      lambda: final.unlink(missing_ok=True), exc, str(final))
            elif conn.in_transaction:
                conn.execute("ROLLBACK")
            raise
        return IngestResult(meta.episode_id, final, sha, duplicate=False)

    def _duplicate(self, known: EpisodeRow, sha: str, split: str, data: bytes, readmit: bool,
                   write_lock: AbstractContextManager[Any] | None) -> IngestResult:
        if known.sha256 != sha:
            raise CatalogError(f"episode {known.episode_id} is already indexed with sha256 {known.sha256}; "
                               f"refusing different bytes (sha256 {sha})")
        if known.split != split:
            raise OtherSplitError(f"episode {known.episode_id} is already indexed in split {known.split!r}, "
                                  f"not {split!r}", known.split)
        if not known.quarantined and holds(known.path, sha):
            return IngestResult(known.episode_id, known.path, sha, duplicate=True)
        if not readmit:  # a worker's upload: kept where they are missing, a quarantine stands
            written = self._keep_intact(known, data, write_lock)
            return IngestResult(known.episode_id, known.path, sha, duplicate=True, restored=written is not None)
        # the same bytes restore a file lost from disk, damaged, or quarantined (which ends the quarantine)
        self._staged(known.path, data, None, partial(self._readmit, known),
                     f"cannot restore episode {known.episode_id} at {known.path}")
        return IngestResult(known.episode_id, known.path, sha, duplicate=True, restored=True)

    def _readmit(self, known: EpisodeRow, conn: sqlite3.Connection, staged: Path) -> None:
        with transaction(conn):
            publish(staged, known.path)
            quarantines.readmit(conn, known.episode_id, self._kept(known))

    # --- a worker's upload of bytes indexed -----------------------------------------------------

    def repair_file(self, episode_id: str, data: bytes,
                    write_lock: AbstractContextManager[Any] | None = None) -> Path | None:
        """Keeps ``data``, the bytes ``episode_id`` indexes, where the catalog looks for them when no intact copy
        is left there; returns the file it wrote, None when it wrote none.

        For a worker's upload (``orchestrator.uploads``: a repeat, or through ``ingest_bytes(readmit=False)`` a
        copy racing the first), whose bytes may be the last intact copy: they put back the file of an episode in
        training, and are kept in ``DATA/quarantine/`` for a quarantined one (recorded in its quarantine row, so
        ``restore`` brings it back). Unlike an operator's ingest of the same bytes (``ingest_bytes``) it never ends
        a quarantine: an operator's or a training job's decision is not undone by a worker's retry, not even a
        quarantine that commits while this call runs, which is why it is checked again under the write lock
        (``write_lock``: as for ``ingest_bytes``). A copy kept in quarantine is removed again, under the write
        lock, unless the row that names it commits.

        Raises ``UnknownEpisodeError`` for an episode not indexed, ``CatalogError`` for other bytes than those
        indexed or a write that fails (``CatalogUnavailableError`` for a full disk).
        """
        row = self.get(episode_id)
        data = bytes(data)
        sha = sha256_hex(data)
        if sha != row.sha256:
            raise CatalogError(f"episode {row.episode_id} is indexed with sha256 {row.sha256}; refusing to "
                               f"repair it with other bytes (sha256 {sha})")
        return self._keep_intact(row, data, write_lock)

    def _keep_intact(self, row: EpisodeRow, data: bytes,
                     write_lock: AbstractContextManager[Any] | None) -> Path | None:
        """``repair_file`` once ``data`` is known to be the bytes ``row`` indexes."""
        target = quarantines.copy_wanted(row, self._kept(row), bool(row.quarantined))
        if target is None:  # (checked again under the write lock)
            return None
        return self._staged(target, data, write_lock, partial(self._repair, row),
                            f"cannot restore episode {row.episode_id} at {target}")

    def _repair(self, row: EpisodeRow, conn: sqlite3.Connection, staged: Path) -> Path | None:
        """``repair_file``'s write, under the write lock: decided again on the quarantine row as it is now."""
        kept = self._kept(row)
        moved_to = kept.relative_to(self.data_dir).as_posix()
        kept_here = False
        try:
            with transaction(conn):
                target = quarantines.copy_wanted(row, kept, quarantines.is_quarantined(conn, row.episode_id))
                if target is None:
                    return None  # (the transaction wrote nothing: it only held the lock)
                kept_here = target == kept  # (before the move: one cut short may leave a copy there too)
                move(staged, target)  # (staged beside it, or beside the file if a quarantine committed since)
                if kept_here:
                    quarantines.keep_copy(conn, row.episode_id, moved_to)
        except BaseException as error:
            if kept_here:  # removed under the write lock unless its row, which names it, committed
                undo_unless_committed(conn, lambda c: quarantines.keeps(c, row.episode_id, moved_to),
                                      lambda: kept.unlink(missing_ok=True), error, str(kept))
            raise
        return target

    def _staged(self, target: Path, data: bytes, write_lock: AbstractContextManager[Any] | None,
                under_lock: Callable[[sqlite3.Connection, Path], _T], failed: str) -> _T:
        """``under_lock(conn, staged)`` on a connection of its own, ``write_lock`` held, once ``data`` is staged
        beside ``target`` (``stage_bytes``: the slow part, the write and its fsync, outside any lock); it opens
        the write transaction and publishes ``staged`` or not. The staging file is gone afterwards either way.
        Raises ``CatalogError`` for an ``OSError`` (``CatalogUnavailableError`` for a full disk), ``failed``
        saying what could not be done."""
        staged = None
        try:
            staged = stage_bytes(target, data)
            # The lock outermost: an error inside is made a CatalogError (``connection``; an OSError of the publish
            # here) while it is held, so a ``write_lock`` that notes outages (the service's turn) notes it before
            # another writer goes: its reaper would otherwise expire the leases nobody could renew meanwhile.
            with write_lock if write_lock is not None else nullcontext():
                try:
                    with self._connect() as conn:
                        return under_lock(conn, staged)
                except OSError as exc:
                    raise storage_error(exc, CatalogError, f"{failed}: {exc.strerror or exc}", target) from exc
        except OSError as exc:  # staging
            raise storage_error(exc, CatalogError, f"{failed}: {exc.strerror or exc}", target) from exc
        finally:
            if staged is not None:
                staged.unlink(missing_ok=True)
