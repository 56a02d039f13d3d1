"""The catalog's rows: plain dataclasses of what ``storage.catalog.Catalog`` answers with.

``EpisodeRow`` (one indexed episode), ``IngestResult`` (what an ingest did), ``EvalSplit`` (the pinned
evaluation split) and ``Snapshot`` (the episodes of a split at one time, with a content id). They import
nothing of the catalog; ``storage.catalog`` re-exports them.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any


def content_hash(pairs: Sequence[tuple[str, str]]) -> str:
    """sha256 over sorted ``(episode_id, sha256)`` pairs, one ``id sha\\n`` line each."""
    h = hashlib.sha256()
    for episode_id, sha in sorted(pairs):
        h.update(f"{episode_id} {sha}\n".encode())
    return h.hexdigest()


@dataclass
class EpisodeRow:
    """One indexed episode."""

    episode_id: str
    path: Path
    """Absolute path of the MCAP file."""
    sha256: str
    frames: int
    task: str
    shape: str
    request_id: str
    worker_id: str
    split: str
    created: str
    """When the episode was collected (ISO 8601 UTC, from its metadata)."""
    size_bytes: int
    model_version: str
    ingested: float
    """When it was indexed (unix seconds)."""
    quarantined: str = ""
    """Why it was taken out of training (``Catalog.quarantine``); '' while it is in."""

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["path"] = str(self.path)
        return out


@dataclass
class IngestResult:
    episode_id: str
    path: Path
    sha256: str
    duplicate: bool
    """True when this exact file was already indexed."""
    restored: bool = False
    """True for a duplicate whose bytes were written: they put back a file that was missing, damaged or
    quarantined, or (``ingest_bytes(readmit=False)``) were kept in ``quarantine/`` for a quarantined episode."""


@dataclass
class EvalSplit:
    ids: list[str]
    """Sorted episode ids."""
    hash: str
    """sha256 over the sorted (episode_id, sha256) pairs."""
    params: dict[str, Any] = field(default_factory=dict)
    """How the split was generated (episodes, seed, steps, image_size ...)."""
    created: str = ""


@dataclass
class Snapshot:
    ids: list[str]
    """Sorted episode ids."""
    snapshot_id: str
    """First 16 hex digits of the content hash of ``ids`` and their sha256s."""
    sha256s: list[str] = field(default_factory=list)
    """The sha256 of each of ``ids``."""

    @classmethod
    def of(cls, pairs: Sequence[tuple[str, str]]) -> Snapshot:
        """The snapshot of (episode_id, sha256) ``pairs``, sorted by id."""
        return cls(ids=[p[0] for p in pairs], snapshot_id=content_hash(pairs)[:16], sha256s=[p[1] for p in pairs])

    def is_of(self, snapshot_id: str) -> bool:
        """Whether these are the episodes of ``snapshot_id``: sorted by id, one sha256 each, hashing to it."""
        return (len(self.sha256s) == len(self.ids) and self.ids == sorted(self.ids)
                and Snapshot.of(list(zip(self.ids, self.sha256s))).snapshot_id == snapshot_id)

    def without(self, drop: Sequence[str]) -> Snapshot:
        """This snapshot less the episodes ``drop`` (those a job found damaged and quarantined)."""
        dropped = set(drop)
        return Snapshot.of([(i, s) for i, s in zip(self.ids, self.sha256s) if i not in dropped])
