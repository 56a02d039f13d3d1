"""The eval split, and the snapshots training takes (``Catalog.pin_eval_split``, ``eval_split``, ``snapshot``).

The eval split is a fixed set of episodes indexed with split ``eval``: pinned once (tables ``eval_split``,
its hash and params, and ``eval_split_members``), it never changes for the life of the data directory, so
every model's metrics are measured on the same episodes; its hash is the content hash of their ids and
sha256s, checked whenever it is read. It fixes the catalog's one frame size (``frame_size``; before it is
pinned, the first episode does). A snapshot is the episodes of a split at one time, with a content id; a
training snapshot leaves out the eval split and quarantined episodes.

These are the catalog's steps, over a connection it opened (``pin`` inside its ``BEGIN IMMEDIATE``
transaction); ``storage.catalog`` owns the connections and transactions.
"""

from __future__ import annotations

import json
import sqlite3
from datetime import datetime, timezone
from typing import Any

from storage import quarantine as quarantines
from storage.errors import CatalogError
from storage.rows import EvalSplit, Snapshot, content_hash

#: The tables, as the catalog's schema version 1 made them (``storage.catalog._CATALOG_MIGRATIONS``): a change
#: to them is a new migration, never an edit here.
TABLES = (
    """CREATE TABLE IF NOT EXISTS eval_split (
            id INTEGER PRIMARY KEY CHECK (id = 1),
            hash TEXT NOT NULL,
            params TEXT NOT NULL,
            created TEXT NOT NULL)""",
    """CREATE TABLE IF NOT EXISTS eval_split_members (
            episode_id TEXT PRIMARY KEY REFERENCES episodes(episode_id))""",
)


def pin(conn: sqlite3.Connection, ids: list[str], params: dict[str, Any] | None) -> str:
    """Inside a transaction: pin the eval split to ``ids`` (sorted, at least one); return its hash.

    The same ids again return the same hash. Raises ``CatalogError`` for an unknown episode, one not of
    split ``eval``, a quarantined one, ``params`` whose ``image_size`` is not the episodes', or another set
    than the one already pinned.
    """
    marks = ",".join("?" * len(ids))
    rows = conn.execute(f"SELECT episode_id, sha256, split FROM episodes WHERE episode_id IN ({marks})",
                        ids).fetchall()
    unknown = sorted(set(ids) - {r["episode_id"] for r in rows})
    if unknown:
        raise CatalogError(f"cannot pin unknown episodes: {', '.join(unknown[:5])}"
                           f"{' ...' if len(unknown) > 5 else ''}")
    wrong = [r["episode_id"] for r in rows if r["split"] != "eval"]
    if wrong:
        raise CatalogError(f"episodes {', '.join(wrong[:5])} are in split 'train'; only episodes "
                           "added with split='eval' can be pinned")
    held = quarantines.quarantined_among(conn, ids)
    if held:
        raise CatalogError(f"episodes {', '.join(held[:5])} are quarantined; restore them first, or pin "
                           "others")
    sizes = {r[0] for r in conn.execute(f"SELECT DISTINCT json_extract(meta, '$.image_size') FROM episodes "
                                        f"WHERE episode_id IN ({marks})", ids)}
    said = (params or {}).get("image_size")
    if said is not None and ({said} != sizes or isinstance(said, bool)):
        raise CatalogError(f"params say image_size {said!r}, the episodes have "
                           f"{', '.join(map(str, sorted(sizes)))}px frames")
    digest = content_hash([(r["episode_id"], r["sha256"]) for r in rows])
    current = conn.execute("SELECT hash FROM eval_split WHERE id = 1").fetchone()
    if current is not None:
        if current["hash"] != digest:
            raise CatalogError(f"an eval split is already pinned (hash {current['hash'][:16]}); "
                               "it cannot be replaced")
        return digest
    created = datetime.now(timezone.utc).isoformat(timespec="seconds")
    conn.execute("INSERT INTO eval_split(id, hash, params, created) VALUES (1, ?, ?, ?)",
                 (digest, json.dumps(params or {}, sort_keys=True), created))
    conn.executemany("INSERT INTO eval_split_members(episode_id) VALUES (?)", [(i,) for i in ids])
    return digest


def read(conn: sqlite3.Connection) -> EvalSplit | None:
    """The pinned eval split, or None. ``CatalogError`` if its rows no longer match its hash."""
    head = conn.execute("SELECT hash, params, created FROM eval_split WHERE id = 1").fetchone()
    if head is None:
        return None
    rows = conn.execute("SELECT m.episode_id, e.sha256 FROM eval_split_members m "
                        "JOIN episodes e USING (episode_id) ORDER BY m.episode_id").fetchall()
    digest = content_hash([(r["episode_id"], r["sha256"]) for r in rows])
    if digest != head["hash"]:
        raise CatalogError(f"the pinned eval split's episodes hash to {digest[:16]}, "
                           f"pinned as {head['hash'][:16]}")
    return EvalSplit(ids=[r["episode_id"] for r in rows], hash=head["hash"],
                     params=json.loads(head["params"]), created=head["created"])


def frame_size(conn: sqlite3.Connection) -> tuple[int, str] | None:
    """(frame size, what fixed it) of a catalog: its pinned eval split's, else its first episode's; None
    while it holds no episode."""
    row = conn.execute("SELECT json_extract(params, '$.image_size'), json_type(params, '$.image_size') "
                       "FROM eval_split WHERE id = 1").fetchone()
    if row is not None and row[1] == "integer":
        return row[0], "its eval split"
    first = conn.execute("SELECT episode_id, json_extract(meta, '$.image_size') FROM episodes "
                         "ORDER BY rowid LIMIT 1").fetchone()
    if first is not None and isinstance(first[1], int):
        return first[1], f"its first episode, {first[0]}"
    return None


def snapshot(conn: sqlite3.Connection, split: str) -> Snapshot:
    """The episodes of ``split`` now, less the quarantined ones and, for ``train``, the eval split's."""
    rows = conn.execute(
        f"SELECT episode_id, sha256 FROM episodes WHERE split = ? AND {quarantines.NOT_QUARANTINED}"
        + (" AND episode_id NOT IN (SELECT episode_id FROM eval_split_members)" if split == "train" else "")
        + " ORDER BY episode_id", (split,)).fetchall()
    return Snapshot.of([(r["episode_id"], r["sha256"]) for r in rows])
