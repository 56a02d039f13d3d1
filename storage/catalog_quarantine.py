"""Taking an episode out of training and putting it back (``Catalog.quarantine``, ``Catalog.restore``).

``CatalogQuarantine`` is the part of ``storage.catalog.Catalog`` that owns the connections, the write
transactions and the moves of files between ``DATA/episodes/`` and ``DATA/quarantine/``; the rows and the
decisions over a connection are ``storage.quarantine``'s. A file moves inside the write transaction that
records it, and back, under the write lock, when that transaction does not commit
(``storage.database.undo_unless_committed``).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

from storage import quarantine as quarantines
from storage.catalog_reads import CatalogReads
from storage.database import storage_error, transaction, undo_unless_committed
from storage.errors import CatalogError
from storage.files import holds, move
from storage.rows import EpisodeRow


class CatalogQuarantine(CatalogReads):
    """Quarantine and restore of the episodes under ``data_dir``."""

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
        moving = False
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
                            moving = True
                            move(row.path, kept)  # (over a damaged leftover there)
                except BaseException as error:
                    # Moved (maybe not returned: a signal's exception in its fsync), the file goes back where its
                    # row says it is unless the quarantine committed.
                    if moving and not row.path.exists():
                        undo_unless_committed(conn, lambda c: quarantines.is_quarantined(c, row.episode_id),
                                              partial(self._move_back, kept, row, error), error, str(kept))
                    raise
        except OSError as exc:
            raise storage_error(exc, CatalogError, f"cannot move {row.path} to {kept}: {exc.strerror or exc}",
                                kept) from exc
        return self.get(row.episode_id)

    def kept_file(self, row: EpisodeRow) -> Path | None:
        """Where the file of the quarantined episode ``row`` is kept (``DATA/quarantine/...``, for ``restore``);
        None when no file is kept there (it was gone when quarantined, or deleted since: then only an ingest of its
        original bytes brings it back)."""
        kept = self._kept(row)
        return kept if row.quarantined and kept.is_file() else None

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
        back in place). ``quarantine.NotQuarantinedError`` when it is not quarantined; ``CatalogError`` when its
        file is gone or damaged: then ingesting its original bytes again restores it.
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
