"""Strays: files a crashed ingest left under ``DATA/episodes/`` (``Catalog.strays``, ``Catalog.sweep_strays``).

An ingest stages its bytes under a hidden temporary name, then, inside its write transaction, renames the
file into place and inserts its row. A crash before the rename leaves a staging file; one between the
rename and the commit, an episode file no row indexes. Neither was acknowledged (the row is the one commit
point), so a sweep deletes staging files and moves unindexed files aside to ``DATA/orphans/``.

These are the catalog's steps: the directory walks outside any lock, ``unindexed`` over a connection it
opened, inside its ``BEGIN IMMEDIATE`` transaction (``storage.catalog`` owns connections and transactions).
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path

from storage.database import EPISODES_DIR
from storage.files import age_s, move

#: Where ``sweep_strays`` moves episode files that have no catalog row.
ORPHANS_DIR = "orphans"
#: A staging file older than this belongs to no live ingest (an ingest stages, then commits, in seconds).
STAGING_MAX_AGE_S = 300.0


@dataclass
class Strays:
    """Files a crashed ingest left under ``episodes/``."""

    staging: list[Path]
    """``.<id>.mcap.*.tmp`` files: written before a crash, never renamed into place."""
    unindexed: list[Path]
    """Episode files with no catalog row: renamed into place, then a crash before the commit."""

    def __bool__(self) -> bool:
        return bool(self.staging or self.unindexed)


def episode_files(episodes_dir: Path) -> list[Path]:
    """The episode files under ``episodes_dir``, sorted (staging files, hidden, left out)."""
    return sorted(p for p in episodes_dir.rglob("*.mcap") if not p.name.startswith("."))


def unindexed(conn: sqlite3.Connection, data_dir: Path, files: list[Path], move_to: Path | None) -> list[Path]:
    """In a write transaction: those of ``files`` (under ``DATA/episodes/``) still there with no row; moved
    under ``move_to`` (at the same path below it) when given."""
    episodes_dir = data_dir / EPISODES_DIR
    rows = {r["path"] for r in conn.execute("SELECT path FROM episodes")}
    found = [p for p in files if p.relative_to(data_dir).as_posix() not in rows and p.exists()]
    for path in found if move_to is not None else ():
        move(path, move_to / path.relative_to(episodes_dir))
    return found


def indexed(conn: sqlite3.Connection, rel: str) -> bool:
    """Whether a row indexes the episode file at ``rel`` (relative to the data directory, posix): after a
    failed ingest, whether its file is an episode or a stray."""
    return conn.execute("SELECT 1 FROM episodes WHERE path = ?", (rel,)).fetchone() is not None


def staging_files(episodes_dir: Path, min_age_s: float, now: float) -> list[Path]:
    """The staging files under ``episodes_dir`` older than ``min_age_s`` at ``now`` (unix seconds), sorted."""
    return sorted(p for p in episodes_dir.rglob(".*.mcap.*.tmp") if age_s(p, now) > min_age_s)
