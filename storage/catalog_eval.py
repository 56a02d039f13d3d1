"""The catalog's eval split, snapshots and frame size (``Catalog.pin_eval_split``, ``eval_split``, ``snapshot``).

``CatalogEvalSplit`` is the part of ``storage.catalog.Catalog`` that opens the connections (and, to pin, the
``BEGIN IMMEDIATE`` transaction) for ``storage.eval_split``'s steps: the pinned eval split, the snapshots
training takes, the episodes of one split that replay the other's, and the one frame size a catalog holds.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from storage import eval_split as eval_splits
from storage.catalog_reads import CatalogReads, check_split
from storage.database import transaction
from storage.errors import CatalogError
from storage.records import EpisodeMeta
from storage.rows import EvalSplit, Snapshot


class CatalogEvalSplit(CatalogReads):
    """The eval split and the snapshots of the catalog under ``data_dir``."""

    def frame_size(self) -> int | None:
        """The frame size every episode here has (its eval split's, else its first episode's); None
        while it holds none."""
        with self._connect() as conn:
            fixed = eval_splits.frame_size(conn)
        return None if fixed is None else fixed[0]

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
        check_split(split)
        with self._connect() as conn:
            return eval_splits.snapshot(conn, split)

    def replays(self, split: str = "train", metas: Sequence[EpisodeMeta] | None = None, *,
                within: bool = False) -> dict[str, str]:
        """Episodes of ``split`` (or ``metas``) replaying one of the other (``within``: of ``split`` itself):
        {id: its id} (``eval_split.replays``)."""
        check_split(split)
        with self._connect() as conn:
            return eval_splits.replays(conn, split, metas, within=within)
