"""The catalog's reads: its rows (find, get, resolve, list, count, summary, meta) and its files (load, verify).

``CatalogReads`` is the part of ``storage.catalog.Catalog`` every other part builds on: the paths of a data
directory, the connection each call opens (``_connect``) and the row answered (``storage.rows.EpisodeRow``,
read through ``storage.episode_table``). ``Catalog`` sets the paths and the schema (``Catalog.__init__``); the
other parts (``storage.catalog_quarantine``, ``storage.catalog_eval``, ``storage.catalog_strays``) subclass this
one. Each method opens its own connection and, when it writes, its own ``BEGIN IMMEDIATE`` transaction.

Reads write in one case: a read that finds an episode in training with its file missing moves it back from
``DATA/quarantine/``, where a quarantine a crash cut short left it (``storage.quarantine.heal``).
"""

from __future__ import annotations

import sqlite3
from contextlib import AbstractContextManager
from datetime import datetime
from pathlib import Path
from typing import Any

from storage import episode_table
from storage import quarantine as quarantines
from storage.database import connection, transaction
from storage.episode_reader import read_episode, verify_episode
from storage.errors import CatalogError, CorruptEpisodeError, EpisodeError, MissingEpisodeError, UnknownEpisodeError
from storage.files import sha256_hex
from storage.quarantine import quarantine_path
from storage.records import Episode, EpisodeMeta
from storage.rows import EpisodeRow

#: Splits an episode can belong to. ``eval`` episodes never enter a training snapshot.
SPLITS: tuple[str, ...] = ("train", "eval")


def check_split(split: str) -> None:
    """``CatalogError`` unless ``split`` is one of ``SPLITS``."""
    if split not in SPLITS:
        raise CatalogError(f"unknown split {split!r}; expected one of {', '.join(SPLITS)}")


class CatalogReads:
    """What the catalog under ``data_dir`` indexes, and its files read back and checked."""

    data_dir: Path
    """The data directory (absolute)."""
    episodes_dir: Path
    """``DATA/episodes``, where the episode files are."""
    _db_path: Path
    """``DATA/catalog.sqlite``."""

    @property
    def db_path(self) -> Path:
        return self._db_path

    def _connect(self) -> AbstractContextManager[sqlite3.Connection]:
        return connection(self._db_path, CatalogError)

    def _row(self, r: sqlite3.Row) -> EpisodeRow:
        return episode_table.row(r, self.data_dir)

    def _kept(self, row: EpisodeRow) -> Path:
        """Where a quarantine keeps the file of ``row`` (``storage.quarantine.quarantine_path``)."""
        return self.data_dir / quarantine_path(row.path.relative_to(self.data_dir).as_posix())

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
            args.append(min(int(limit), 2**63 - 1))  # (more than SQLite's int64 holds: no fewer rows than all)
        with self._connect() as conn:
            return [self._row(r) for r in conn.execute(sql, args).fetchall()]

    def count(self, split: str | None = None, shape: str | None = None,
              since: float | str | datetime | None = None, quarantined: bool | None = None) -> int:
        """How many episodes ``list`` would return with these filters (without a limit)."""
        if split is not None:
            check_split(split)
        sql, args = episode_table.count_sql(split, shape, since, quarantined)
        with self._connect() as conn:
            return conn.execute(sql, args).fetchone()[0]

    def _filters(self, split: str | None, shape: str | None, since: float | str | datetime | None,
                 quarantined: bool | None) -> tuple[str, list[Any]]:
        if split is not None:
            check_split(split)
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

    def verify(self, episode_id: str) -> EpisodeMeta:
        """Re-hashes and re-verifies an indexed episode's file; raises a ``StorageError`` if bad."""
        row = self.get(episode_id)
        meta = verify_episode(self._read_checked(row), name=str(row.path))
        if meta.episode_id != row.episode_id:
            raise CorruptEpisodeError(f"{row.path}: holds episode {meta.episode_id}, "
                                      f"indexed as {row.episode_id}")
        return meta
