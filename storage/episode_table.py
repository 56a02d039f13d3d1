"""The ``episodes`` table: one row per indexed episode file (``storage.rows.EpisodeRow``).

``SCHEMA`` is the table and its indexes as the catalog's schema version 1 made them
(``storage.catalog._CATALOG_MIGRATIONS``): a change to them is a new migration, never an edit here. A row's
``path`` is where its file is under the data directory (``file_path``: by the day the episode was created).
Every read of rows goes through ``SELECT_ROWS``, the row joined with the quarantine table, so a row says
whether, and why, its episode is out of training; ``row`` makes it an ``EpisodeRow`` (``find`` and
``by_prefix`` read them so). ``where`` turns the filters of ``Catalog.list`` and ``Catalog.count`` into SQL,
``summary`` totals the rows.

These are the catalog's steps, over a connection it opened (``insert`` inside its ``BEGIN IMMEDIATE``
transaction); ``storage.catalog`` owns the connections, the transactions and the files.
"""

from __future__ import annotations

import re
import sqlite3
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from storage import quarantine as quarantines
from storage.database import EPISODES_DIR, kept_counts
from storage.errors import CatalogError
from storage.records import EpisodeMeta
from storage.rows import EpisodeRow

SCHEMA = (
    """CREATE TABLE IF NOT EXISTS episodes (
            episode_id TEXT PRIMARY KEY,
            path TEXT NOT NULL,
            sha256 TEXT NOT NULL,
            frames INTEGER NOT NULL,
            task TEXT NOT NULL,
            shape TEXT NOT NULL,
            request_id TEXT NOT NULL,
            worker_id TEXT NOT NULL,
            model_version TEXT NOT NULL,
            split TEXT NOT NULL,
            created TEXT NOT NULL,
            size_bytes INTEGER NOT NULL,
            ingested REAL NOT NULL,
            meta TEXT NOT NULL)""",
    "CREATE INDEX IF NOT EXISTS episodes_split ON episodes(split, shape)",
    "CREATE INDEX IF NOT EXISTS episodes_request ON episodes(request_id)",
    "CREATE INDEX IF NOT EXISTS episodes_ingested ON episodes(ingested)",
)
#: The catalog's schema version 3: ``episode_counts``, the number of episodes in each split (``count_sql``).
COUNTS = kept_counts("episodes", "split", "episode_counts")
#: Every catalog query of episode rows: the row and, when it is quarantined, why.
FROM_ROWS = "episodes e LEFT JOIN quarantine q USING (episode_id)"
SELECT_ROWS = f"SELECT e.*, q.reason AS quarantined FROM {FROM_ROWS}"
_SAFE_ID = re.compile(r"^[A-Za-z0-9_-]{1,128}$")


def _episode_date(created: str) -> str:
    try:
        when = datetime.fromisoformat(created)
    except (TypeError, ValueError):
        when = datetime.now(timezone.utc)
    if when.tzinfo is None:
        when = when.replace(tzinfo=timezone.utc)
    try:
        return when.astimezone(timezone.utc).strftime("%Y-%m-%d")
    except OverflowError:  # e.g. 9999-12-31T23:00-05:00 is past the last representable UTC day
        return datetime.now(timezone.utc).strftime("%Y-%m-%d")


def file_path(meta: EpisodeMeta) -> str:
    """Where the file of the episode ``meta`` describes goes, relative to the data directory
    (``episodes/<yyyy-mm-dd>/<episode_id>.mcap``); ``CatalogError`` when its id is not a safe file name."""
    if not isinstance(meta.episode_id, str) or not _SAFE_ID.fullmatch(meta.episode_id):
        raise CatalogError(f"episode id {meta.episode_id!r} is not a safe file name "
                           "(expected 1-128 letters, digits, '-' or '_')")
    return f"{EPISODES_DIR}/{_episode_date(meta.created)}/{meta.episode_id}.mcap"


def row(r: sqlite3.Row, data_dir: Path) -> EpisodeRow:
    """The ``EpisodeRow`` of a row ``SELECT_ROWS`` read from the catalog in ``data_dir``."""
    return EpisodeRow(
        episode_id=r["episode_id"], path=data_dir / r["path"], sha256=r["sha256"],
        frames=r["frames"], task=r["task"], shape=r["shape"], request_id=r["request_id"],
        worker_id=r["worker_id"], split=r["split"], created=r["created"],
        size_bytes=r["size_bytes"], model_version=r["model_version"], ingested=r["ingested"],
        quarantined=r["quarantined"] or "")


def find(conn: sqlite3.Connection, data_dir: Path, episode_id: str) -> EpisodeRow | None:
    """The row of ``episode_id``, or None when it is not indexed."""
    r = conn.execute(f"{SELECT_ROWS} WHERE episode_id = ?", (episode_id,)).fetchone()
    return row(r, data_dir) if r else None


def by_prefix(conn: sqlite3.Connection, data_dir: Path, prefix: str) -> list[EpisodeRow]:
    """Up to three rows whose episode id starts with ``prefix`` (as SQL's ``LIKE`` compares: ASCII case aside)."""
    pattern = prefix.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"
    return [row(r, data_dir) for r in conn.execute(f"{SELECT_ROWS} WHERE episode_id LIKE ? ESCAPE '\\' LIMIT 3",
                                                   (pattern,)).fetchall()]


def insert(conn: sqlite3.Connection, meta: EpisodeMeta, rel: str, sha: str, frames: int, split: str,
           size_bytes: int) -> None:
    """Inside a transaction: the row of a new episode, its file at ``rel``, indexed now."""
    conn.execute(
        "INSERT INTO episodes(episode_id, path, sha256, frames, task, shape, request_id, worker_id, "
        "model_version, split, created, size_bytes, ingested, meta) "
        "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        (meta.episode_id, rel, sha, frames, str(meta.task), str(meta.shape),
         str(meta.request_id), str(meta.worker_id), str(meta.model_version), split,
         str(meta.created), size_bytes, time.time(), meta.to_json()))


def _since_seconds(since: float | str | datetime) -> float:
    if isinstance(since, datetime):
        return (since if since.tzinfo else since.replace(tzinfo=timezone.utc)).timestamp()
    if isinstance(since, str):
        try:
            return _since_seconds(datetime.fromisoformat(since))
        except ValueError:
            raise CatalogError(f"since must be an ISO 8601 time, found {since!r}") from None
    return float(since)


def where(split: str | None, shape: str | None, since: float | str | datetime | None,
          quarantined: bool | None) -> tuple[str, list[Any]]:
    """The ``WHERE`` clause (or '') and its arguments for rows of ``split`` (a known one), of ``shape``,
    indexed at or after ``since`` (unix seconds, ISO 8601 or datetime; ``CatalogError`` for another
    string), quarantined or not; None takes any."""
    clauses, args = [], []
    if quarantined is not None:
        clauses.append(f"q.episode_id IS {'NOT ' if quarantined else ''}NULL")
    if split is not None:
        clauses.append("split = ?")
        args.append(split)
    if shape is not None:
        clauses.append("shape = ?")
        args.append(shape)
    if since is not None:
        clauses.append("ingested >= ?")
        args.append(_since_seconds(since))
    return (" WHERE " + " AND ".join(clauses) if clauses else ""), args


def count_sql(split: str | None, shape: str | None, since: float | str | datetime | None,
              quarantined: bool | None) -> tuple[str, list[Any]]:
    """The query, and its arguments, that counts the rows ``where`` selects: from ``episode_counts`` when only
    the split is asked (a few rows, whatever the history); else from the rows, joined with the quarantine only
    when asked about it (the join reads every row: see BENCHMARKS, "Counting a long history")."""
    if shape is None and since is None and quarantined is None:
        return ("SELECT COALESCE(SUM(n), 0) FROM episode_counts" + (" WHERE split = ?" if split is not None else ""),
                [] if split is None else [split])
    clauses, args = where(split, shape, since, quarantined)
    return f"SELECT COUNT(*) FROM {FROM_ROWS if quarantined is not None else 'episodes e'}{clauses}", args


def summary(conn: sqlite3.Connection) -> dict[str, Any]:
    """Episode, frame and byte totals, by split and by shape, and how many are quarantined."""
    rows = conn.execute("SELECT split, shape, COUNT(*) AS n, SUM(frames) AS frames, "
                        "SUM(size_bytes) AS bytes FROM episodes GROUP BY split, shape").fetchall()
    quarantined = quarantines.count(conn)
    out: dict[str, Any] = {"episodes": 0, "frames": 0, "bytes": 0, "by_split": {}, "by_shape": {},
                           "quarantined": quarantined}
    for r in rows:
        out["episodes"] += r["n"]
        out["frames"] += r["frames"]
        out["bytes"] += r["bytes"]
        out["by_split"][r["split"]] = out["by_split"].get(r["split"], 0) + r["n"]
        out["by_shape"][r["shape"]] = out["by_shape"].get(r["shape"], 0) + r["n"]
    return out
