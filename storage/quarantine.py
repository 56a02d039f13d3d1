"""Quarantine: episodes taken out of training while their rows stay (``Catalog.quarantine``).

A quarantined episode has a row in the ``quarantine`` table (why, where its file went, when) and its
file, when there is one, under ``DATA/quarantine/<yyyy-mm-dd>/<episode_id>.mcap`` (``quarantine_path``).
Snapshots leave it out and the eval split cannot take it; ``Catalog.restore``, or ingesting the same bytes
again, brings it back. A worker's repeated upload of its bytes does not end a quarantine, but when no intact copy
is kept it keeps one (``copy_wanted``, ``keep_copy``: ``Catalog.repair_file``), so ``restore`` can.

These are the catalog's steps, over a connection it opened (those that write, inside its ``BEGIN IMMEDIATE``
transaction) and an episode's row (``storage.rows.EpisodeRow``); the catalog owns the connections and
transactions, and the moves of files into quarantine, which it undoes when the row does not commit
(``storage.catalog_quarantine``, and ``storage.catalog`` for a repeated upload's copy).
``storage.backup`` reads a source's quarantine rows and writes its copy's with ``find``, ``insert`` and
``remove``.

A move across file systems (``quarantine/`` or ``episodes/`` on a volume of its own) that a crash cuts short
leaves the file in both places (``storage.files.move``), like a quarantine whose row did not commit leaves an
intact copy in ``quarantine/``: ``record`` then moves the file in place over that copy, ``put_back`` and
``readmit`` delete it, and a read in between finds the file in place.
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Sequence
from pathlib import Path, PurePosixPath

from storage.database import QUARANTINE_DIR
from storage.errors import CatalogError
from storage.files import holds, move
from storage.rows import EpisodeRow


class NotQuarantinedError(CatalogError):
    """A restore of an episode that is in training: nothing to do (``episodes restore`` says so, exit 0)."""


#: The table, as the catalog's schema version 2 made it (``storage.catalog._CATALOG_MIGRATIONS``): a change
#: to it is a new migration, never an edit here. Episodes taken out of training (see Catalog.quarantine);
#: moved_to '' when the file was already gone (until a worker's repeated upload keeps a copy: ``keep_copy``).
TABLE = """CREATE TABLE IF NOT EXISTS quarantine (
            episode_id TEXT PRIMARY KEY REFERENCES episodes(episode_id),
            reason TEXT NOT NULL,
            moved_to TEXT NOT NULL,
            at REAL NOT NULL)"""
#: A quarantine reason is kept to one line of at most this many characters.
MAX_REASON_CHARS = 500
#: An SQL condition on ``episodes``: the episode is not quarantined.
NOT_QUARANTINED = "episode_id NOT IN (SELECT episode_id FROM quarantine)"


def looks_unmounted(damaged: int, read: int) -> bool:
    """Whether ``damaged`` missing or damaged files among ``read`` episodes read at once say more than lost files:
    more than one and more than half (a disk not mounted, a folder moved). Then nothing is quarantined (a retrain,
    ``run``): each would stay out of training after the disk is back, until ``episodes restore``."""
    return damaged > 1 and 2 * damaged > read


def quarantine_path(rel: str) -> str:
    """Where ``Catalog.quarantine`` keeps the file of the episode indexed at ``rel`` (relative to the data
    directory): one place per episode, so a quarantine a crash cut short is found again."""
    path = PurePosixPath(rel)
    return f"{QUARANTINE_DIR}/{path.parent.name}/{path.name}"


def clean_reason(reason: object) -> str:
    """``reason`` on one line of at most ``MAX_REASON_CHARS``; ``CatalogError`` when nothing is left."""
    reason = " ".join(str(reason).split())[:MAX_REASON_CHARS]
    if not reason:
        raise CatalogError("a quarantine needs a reason")
    return reason


def refuse_pinned(conn: sqlite3.Connection, episode_id: str) -> None:
    """``CatalogError`` when the episode is in the pinned eval split, which cannot change."""
    if conn.execute("SELECT 1 FROM eval_split_members WHERE episode_id = ?",
                    (episode_id,)).fetchone():
        raise CatalogError(pinned_refusal(episode_id))


def pinned_refusal(episode_id: str) -> str:
    """Why the pinned eval split's episode ``episode_id`` cannot be quarantined, and what to do instead."""
    return (f"episode {episode_id} is in the pinned eval split, which cannot change: restore its file "
            "instead (ingest its bytes again, e.g. from a backup)")


def find(conn: sqlite3.Connection, episode_id: str) -> sqlite3.Row | None:
    """The quarantine row of ``episode_id`` (``reason``, ``moved_to``, ``at``); None while it is in training.
    Over any connection to a catalog's file (``storage.backup`` reads its source's with it)."""
    return conn.execute("SELECT reason, moved_to, at FROM quarantine WHERE episode_id = ?", (episode_id,)).fetchone()


def is_quarantined(conn: sqlite3.Connection, episode_id: str) -> bool:
    return find(conn, episode_id) is not None


def insert(conn: sqlite3.Connection, episode_id: str, reason: str, moved_to: str, at: float) -> None:
    """The quarantine row of ``episode_id``, as given: ``record`` decides it for the catalog, inside its write
    transaction; ``storage.backup`` copies its source's. ``moved_to``: relative to the data directory, '' when
    the file was already gone; ``at``: unix seconds."""
    conn.execute("INSERT INTO quarantine(episode_id, reason, moved_to, at) VALUES (?, ?, ?, ?)",
                 (episode_id, reason, moved_to, at))


def remove(conn: sqlite3.Connection, episode_id: str) -> None:
    """Deletes the quarantine row of ``episode_id``, if any (its file is the caller's)."""
    conn.execute("DELETE FROM quarantine WHERE episode_id = ?", (episode_id,))


def record(conn: sqlite3.Connection, row: EpisodeRow, kept: Path, data_dir: Path, reason: str) -> bool:
    """In a write transaction: records the quarantine of ``row``, its file kept at ``kept``. True when the
    caller is to move the file there, inside the same transaction: it is present, and no intact copy is
    already kept or it is intact too (an intact copy is never overwritten by other bytes; the same bytes in
    both places go, or they would stay in ``episodes/`` while quarantined)."""
    copy_kept = holds(kept, row.sha256)  # e.g. a quarantine a crash cut short
    present = row.path.exists()
    insert(conn, row.episode_id, reason, kept.relative_to(data_dir).as_posix() if present or copy_kept else "",
           time.time())
    return present and (not copy_kept or holds(row.path, row.sha256))


def put_back(conn: sqlite3.Connection, row: EpisodeRow, kept: Path) -> None:
    """In a write transaction: ends the quarantine of ``row``, its file moved back from ``kept`` if it still
    holds the bytes indexed (or is already back in place). ``NotQuarantinedError`` when it is not quarantined,
    ``CatalogError`` when its file is gone or damaged. An episode in training whose file a quarantine a crash
    cut short left at ``kept`` is healed instead (``heal``)."""
    q = find(conn, row.episode_id)
    if q is None:
        if heal(conn, row, kept):
            return
        raise NotQuarantinedError(f"episode {row.episode_id} is not quarantined")
    if not holds(row.path, row.sha256):
        if not holds(kept, row.sha256):
            state = (f"{kept} does not hold the bytes indexed (sha256 {row.sha256[:16]}...)"
                     if kept.exists() else f"{kept} is missing" if q["moved_to"] else
                     "its file was already missing when it was quarantined")
            raise CatalogError(f"cannot restore episode {row.episode_id}: {state}; ingest its original "
                               "bytes again (activecollect ingest FILE), which restores it")
        move(kept, row.path)
    else:
        kept.unlink(missing_ok=True)  # the bytes indexed are in place: a copy, or a damaged file, is worth nothing
    remove(conn, row.episode_id)


def readmit(conn: sqlite3.Connection, episode_id: str, kept: Path) -> None:
    """In a write transaction, once an ingest has put the bytes indexed back in place: the episode is in
    training again (if it was quarantined), and nothing is left at ``kept`` (a copy of the same bytes, or the
    damaged file a quarantine took aside, which no row would name any more)."""
    remove(conn, episode_id)
    kept.unlink(missing_ok=True)


def heal(conn: sqlite3.Connection, row: EpisodeRow, kept: Path) -> bool:
    """In a write transaction: move the file of an episode that is in training back from
    ``DATA/quarantine/``, where a quarantine a crash cut short (file moved, row not committed) left
    it. True when it did."""
    if is_quarantined(conn, row.episode_id) or row.path.exists() or not holds(kept, row.sha256):
        return False
    move(kept, row.path)
    return True


def copy_wanted(row: EpisodeRow, kept: Path, quarantined: bool) -> Path | None:
    """Where the bytes ``row`` indexes are to be written for an intact copy of them to be where the catalog
    looks, without changing whether the episode is in training (``Catalog.repair_file``): None when one is
    there (its file, or, while ``quarantined``, the copy at ``kept``), else its file while it is in training
    and ``kept`` while it is quarantined (``keep_copy`` records it there, so ``put_back`` finds it)."""
    if holds(row.path, row.sha256) or (quarantined and holds(kept, row.sha256)):
        return None
    return kept if quarantined else row.path


def keep_copy(conn: sqlite3.Connection, episode_id: str, moved_to: str) -> None:
    """In a write transaction, once an intact copy of a quarantined episode's file is at ``moved_to`` (relative
    to the data directory): its quarantine row says so (it said '' when the file was already gone)."""
    conn.execute("UPDATE quarantine SET moved_to = ? WHERE episode_id = ?", (moved_to, episode_id))


def keeps(conn: sqlite3.Connection, episode_id: str, moved_to: str) -> bool:
    """Whether the quarantine row of ``episode_id`` names its file at ``moved_to`` (``keep_copy`` committed)."""
    q = find(conn, episode_id)
    return q is not None and q["moved_to"] == moved_to


def quarantined_among(conn: sqlite3.Connection, ids: Sequence[str]) -> list[str]:
    marks = ",".join("?" * len(ids))
    return [r[0] for r in conn.execute(f"SELECT episode_id FROM quarantine WHERE episode_id IN ({marks})", ids)]


def count(conn: sqlite3.Connection) -> int:
    return conn.execute("SELECT COUNT(*) FROM quarantine").fetchone()[0]
