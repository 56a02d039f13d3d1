"""The catalog's sweep of what crashed ingests left under ``DATA/episodes/`` (``Catalog.strays``, ``sweep_strays``).

``CatalogStrays`` is the part of ``storage.catalog.Catalog`` that lists the files (outside any lock) and
checks them, and moves the unindexed ones aside, under the write lock (its ``BEGIN IMMEDIATE`` transaction);
what a stray is, and the steps, are ``storage.strays``'s.
"""

from __future__ import annotations

import time
from pathlib import Path

from storage import strays as stray_files
from storage.catalog_reads import CatalogReads
from storage.database import transaction
from storage.strays import ORPHANS_DIR, STAGING_MAX_AGE_S, Strays


class CatalogStrays(CatalogReads):
    """The strays under the ``episodes/`` of the catalog under ``data_dir``."""

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
