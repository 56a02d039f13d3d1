"""What crashes leave in a data directory, moved out of the way by the running service (``Service._sweep``).

Episode files no row indexes (an ingest killed between its file and its commit) go to ``orphans/<day>/``,
staging files older than ``STAGING_MAX_AGE_S`` are deleted (younger ones may be a live ingest's), and
checkpoint folders no model row names (a register killed before its commit, e.g. a retrain killed there)
go to ``models/.orphans/`` -- never a live register's, in any process (``ModelRegistry.sweep_strays``).
None of them was acknowledged. One that cannot be moved (a full disk cannot make ``orphans/<day>/``, or
copy it there from a volume of its own) stays where it is and is named: nothing reads it, and the next
sweep (or start) tries again; it is no reason to refuse to start. Nor does it hold up the others: the catalog
and the registry move each as best they can, and ``models prune`` frees what it should all the same.
"""

from __future__ import annotations

import logging
from pathlib import Path

from orchestrator.storagehealth import StorageHealth
from storage.catalog import ORPHANS_DIR, Catalog, Strays
from storage.errors import RegistryFolderError
from storage.models import ModelRegistry
from storage.strays import MODEL_ORPHANS_DIR


def sweep_leftovers(catalog: Catalog, data_dir: Path, health: StorageHealth, log: logging.Logger) -> None:
    """Moves aside what crashed ingests and registers left (see the module); a write the storage refuses for a
    reason that passes is ``health``'s and raised on."""
    try:
        with health.writing():
            swept = catalog.sweep_strays()
    except OSError as exc:
        log.warning("cannot move the files crashed ingests left aside (%s: %s); they stay where they are, "
                    "unindexed, until a later sweep", exc.filename or data_dir, exc.strerror or exc)
    else:
        _say_swept(swept, catalog.data_dir, log)
    try:
        with health.writing():
            models = ModelRegistry(data_dir).sweep_strays()
    except (OSError, RegistryFolderError) as exc:  # models/ could not be made, opened or listed: nothing was moved
        log.warning("cannot look for checkpoint folders no model row names (%s); any stay where they are, unused, "
                    "until a later sweep", exc)
        return
    if models.moved:
        log.warning("moved %d checkpoint folder(s) no model row names to %s/ (a register killed before its "
                    "commit; none was acknowledged): %s", len(models.moved), MODEL_ORPHANS_DIR,
                    ", ".join(models.moved))
    if models.stale:
        log.warning("deleted %d staging folder(s) a retrain or prune killed midway left in models/ (none was "
                    "acknowledged): %s", len(models.stale), ", ".join(models.stale))
    if models.not_moved:
        log.warning("cannot move %d checkpoint folder(s) no model row names to %s/ (a register killed before its "
                    "commit; none was acknowledged); they stay where they are, unused, until a later sweep: %s",
                    len(models.not_moved), MODEL_ORPHANS_DIR,
                    ", ".join(f"{v} ({why})" for v, why in models.not_moved.items()))


def _say_swept(swept: Strays, data_dir: Path, log: logging.Logger) -> None:
    moved = len(swept.unindexed) - len(swept.not_moved)
    if moved or swept.staging:
        log.warning("moved %d unindexed episode file(s) to %s/ and deleted %d staging file(s) left by a "
                    "crash (none was acknowledged)", moved, ORPHANS_DIR, len(swept.staging))
    if swept.not_moved:
        log.warning("cannot move the files crashed ingests left aside to %s/ (%d unindexed episode file(s), none "
                    "acknowledged); they stay where they are, unindexed, until a later sweep: %s", ORPHANS_DIR,
                    len(swept.not_moved), ", ".join(f"{path.relative_to(data_dir)} ({why})"
                                                    for path, why in swept.not_moved.items()))
