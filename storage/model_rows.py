"""The model registry's rows: plain dataclasses of what ``storage.models.ModelRegistry`` answers with.

``ModelStatus`` (where a model stands), ``ModelRecord`` (one registered model), ``ChampionEntry`` (one
promotion), ``StrayFolders`` (what a sweep did with the checkpoint folders no row names) and ``PruneResult``
(what a prune did, those folders included), with the names of a checkpoint directory's files, and
``record_of``, a row as a ``ModelRecord``. They import
nothing of the registry; ``storage.models`` re-exports them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

from storage.errors import RegistryError
from storage.jsonsafe import finite_json

#: The files of a checkpoint directory ``DATA/models/<version>/``.
WEIGHTS_FILE = "weights.pt"
CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.json"
META_FILE = "meta.json"
#: The episodes a model was trained on (``storage.rows.Snapshot``): ``{"snapshot_id", "episodes": [[id, sha256]]}``.
SNAPSHOT_FILE = "snapshot.json"


class ModelStatus(str, Enum):
    """Where a registered model stands. Transitions happen only in ``ModelRegistry``, each through
    ``storage.promotions.set_status``."""

    CANDIDATE = "candidate"
    """Registered, not yet through the gate."""
    CHAMPION = "champion"
    """The model in service (exactly one, or none before the first promotion)."""
    RETIRED = "retired"
    """A former champion, replaced by a better one or rolled back."""
    REJECTED = "rejected"
    """Refused by the gate; kept, with the reason."""


@dataclass(frozen=True)
class ModelRecord:
    """One registered model: its registry row plus where its files are."""

    version: str
    """Unique, sortable version name (``m000001-1a2b3c4d``)."""
    status: ModelStatus
    """Current status."""
    reason: str
    """Why it has that status (the gate's or the operator's words); '' for a fresh candidate."""
    parent: str | None
    """Version it was warm-started from, if any."""
    snapshot_id: str
    """Catalog snapshot it was trained on (its episodes: ``ModelRegistry.snapshot``)."""
    eval_split_hash: str
    """Hash of the eval split its metrics were measured on."""
    weights_sha256: str
    """sha256 hex of the weights file as registered."""
    size_bytes: int
    """Size of the weights file."""
    created: str
    """Registration time, ISO 8601 UTC."""
    metrics: dict[str, Any]
    """Evaluation metrics (``h1_mse`` ...)."""
    config: dict[str, Any]
    """Model / training configuration, as the trainer gave it."""
    path: Path
    """The checkpoint directory."""
    pruned_at: str | None = None
    """When ``prune`` deleted its files (ISO 8601 UTC); None while they are kept."""

    @property
    def weights_path(self) -> Path:
        return self.path / WEIGHTS_FILE

    def to_json(self) -> dict[str, Any]:
        """A strict-JSON-able dict: non-finite metric values (NaN, inf) become None."""
        return {
            "version": self.version, "status": self.status.value, "reason": self.reason,
            "parent": self.parent, "snapshot_id": self.snapshot_id,
            "eval_split_hash": self.eval_split_hash, "weights_sha256": self.weights_sha256,
            "size_bytes": self.size_bytes, "created": self.created, "metrics": finite_json(self.metrics),
            "config": self.config, "path": str(self.path), "pruned_at": self.pruned_at,
        }


@dataclass(frozen=True)
class ChampionEntry:
    """One promotion in the champion history."""

    version: str
    promoted_at: str
    reason: str
    rolled_back_at: str | None = field(default=None)


@dataclass(frozen=True)
class PruneResult:
    """What ``ModelRegistry.prune`` deleted (or, with ``dry_run``, would delete)."""

    pruned: list[str]
    """Versions whose files were deleted, in registration order."""
    kept: list[str]
    """Models whose files are kept for going back: the champion, the earlier champions rollback returns
    to, then the latest champions a rollback took out of service (candidates are kept too, not listed)."""
    freed_bytes: int
    """Total size of the files this call deleted (or would delete)."""
    dry_run: bool = False
    orphaned: list[str] = field(default_factory=list)
    """Checkpoint folders no row names (a ``register`` that died before its commit), moved aside to
    ``DATA/models/.orphans/`` (with ``dry_run``: found, left in place); their files are kept, for the operator."""
    not_moved: dict[str, str] = field(default_factory=dict)
    """Such folders that could not be moved (version: why), left where they are: no row names them, so nothing
    serves them, and the next prune or sweep tries again. They took nothing from what this prune freed."""
    not_deleted: dict[str, str] = field(default_factory=dict)
    """Models this prune chose but could not delete (version: why). One still whole (a read-only ``models/``,
    say) is left as it was, unpruned, usable; one deleted in part stays pruned, its rest swept later."""


@dataclass(frozen=True)
class StrayFolders:
    """What ``ModelRegistry.sweep_strays`` did with the checkpoint folders no row names (a ``register`` that
    died before its commit; none was acknowledged)."""

    moved: list[str] = field(default_factory=list)
    """Versions moved aside to ``DATA/models/.orphans/`` (with ``dry_run``: found, left in place), files kept."""
    not_moved: dict[str, str] = field(default_factory=dict)
    """Those that could not be moved (version: why), left where they are for the next sweep to try again."""
    stale: list[str] = field(default_factory=list)
    """Dot folders a register (``.tmp-*``, its staged files) or a prune (``.prune-*``) killed midway left, older
    than any live call's (``storage.pruning.STALE_AGE_S``): deleted (with ``dry_run``: found, left in place)."""

    def __bool__(self) -> bool:
        return bool(self.moved or self.not_moved or self.stale)


def record_of(row: Any, models_dir: Path) -> ModelRecord:
    """The record of a ``models`` row (a ``sqlite3.Row``); ``RegistryError`` naming the version and the column when
    the row is not one the registry writes (a hand edit, a damaged file): a one-line error, not a traceback."""
    def loaded(column: str) -> dict[str, Any]:
        try:
            value = json.loads(row[column])
        except (TypeError, ValueError):
            value = None
        if not isinstance(value, dict):
            raise RegistryError(f"registry row {row['version']}: {column} is not a JSON object "
                                f"({str(row[column])[:40]!r})")
        return value
    try:
        status = ModelStatus(row["status"])
    except ValueError:
        raise RegistryError(f"registry row {row['version']}: status {row['status']!r} is none of "
                            f"{', '.join(s.value for s in ModelStatus)}") from None
    return ModelRecord(
        version=row["version"], status=status, reason=row["reason"],
        parent=row["parent"], snapshot_id=row["snapshot_id"],
        eval_split_hash=row["eval_split_hash"], weights_sha256=row["weights_sha256"],
        size_bytes=row["size_bytes"], created=row["created"],
        metrics=loaded("metrics"), config=loaded("config"),
        path=models_dir / row["version"], pruned_at=row["pruned_at"],
    )
