"""Pruning: deleting the files of models no rollback needs (``ModelRegistry.prune``).

A prune keeps the champion, the earlier champions ``rollback`` walks back to, then the latest champions a
rollback took out of service; it marks the rest of the retired and rejected models (``pruned_at``), all in
one transaction, then deletes their directories, each claimed first by a rename to ``.prune-*`` so that of
two prunes at once one deletes (and counts) it. Rows stay, so every model's metrics and history remain. In the
same transaction the folders no row names are moved aside (``storage.strays.unregistered``), each as best it
can: one that cannot be moved is said and left, and takes nothing from the marks or the deletes.

A model whose weights cannot be read right now (an I/O error) is kept, and does not count as one of the
chain's: only a lasting verdict (not their sha256, the file missing) lets a prune delete a rollback target.

These are the registry's steps: ``keep_order``, ``mark`` and ``marked`` over a connection it opened (the
last two inside its ``BEGIN IMMEDIATE`` transaction), ``claim`` in a second one (the renames, and the marks taken
off those that could not be claimed), the sha256 checks and the deletes (``finish``) outside any lock
(``storage.models`` owns connections and transactions).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sqlite3
import time
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path

from storage import checkpoint_files
from storage.errors import CorruptCheckpointError
from storage.files import age_s, fsync_dir
from storage.model_rows import ModelStatus, PruneResult, StrayFolders

#: A staging or deleting dot folder under ``models/`` this old belongs to no live call (they take seconds).
STALE_AGE_S = 3600.0


def keep_order(conn: sqlite3.Connection, champion: str | None, live_history: list[tuple[int, str]]) -> list[str]:
    """What ``prune`` keeps first, unpruned: the rollback chain (``champion``, then the promotions of
    ``live_history``, oldest first, not rolled back), then the latest champions a rollback took out of
    service (so they can be promoted again)."""
    pruned = {r[0] for r in conn.execute("SELECT version FROM models WHERE pruned_at IS NOT NULL")}
    chain = [v for _, v in reversed(live_history)]  # what rollback walks, newest first
    every = [r[0] for r in conn.execute("SELECT version FROM champion_history ORDER BY id DESC")]
    order = dict.fromkeys(([champion] if champion else []) + chain + every)  # first place of each
    return [v for v in order if v not in pruned]


def check(wanted: Iterable[str], keep: int, verify: Callable[[str], None]) -> tuple[set[str], set[str]]:
    """``(unusable, unread)``: those of ``wanted`` (in keep order) whose weights ``verify`` refuses
    (``CorruptCheckpointError``), checked until ``keep`` have passed.

    Unusable: a lasting verdict (not their sha256, the file missing; ``checkpoint_files.lasting``): rollback
    would skip them, so they take no keep slot. Unread: the read failed in a way that may pass (an I/O
    error, too many open files): they may well be intact, so a prune never deletes them on that, yet they
    take no slot either, so the ``keep`` the chain is sure of are kept besides (``kept``)."""
    unusable: set[str] = set()
    unread: set[str] = set()
    intact = 0
    for version in wanted:
        if intact == keep:
            break
        try:
            verify(version)
            intact += 1
        except CorruptCheckpointError as exc:
            (unusable if checkpoint_files.lasting(exc) else unread).add(version)
    return unusable, unread


def kept(order: list[str], keep: int, unusable: set[str], unread: set[str]) -> list[str]:
    """What a prune keeps of ``order`` (``keep_order``, read under the write lock): the first ``keep`` that
    ``check`` found intact (or did not check: promoted since), and every one it could not read."""
    intact = [v for v in order if v not in unusable and v not in unread][:keep]
    return [v for v in order if v in intact or v in unread]


def mark(conn: sqlite3.Connection, kept: list[str], now: str | None) -> list[str]:
    """In a write transaction: the retired and rejected models not yet pruned and not ``kept``, in
    registration order; marked pruned at ``now`` unless it is None (a dry run)."""
    marks = ",".join("?" * len(kept))
    chosen = [r[0] for r in conn.execute(
        f"SELECT version FROM models WHERE status IN (?, ?) AND pruned_at IS NULL "
        f"AND version NOT IN ({marks}) ORDER BY seq",
        (ModelStatus.RETIRED.value, ModelStatus.REJECTED.value, *kept))]
    if now is not None:
        conn.executemany("UPDATE models SET pruned_at = ?, updated = ? WHERE version = ?",
                         [(now, now, v) for v in chosen])
    return chosen


def marked(conn: sqlite3.Connection) -> list[str]:
    """Every model marked pruned (with those an earlier prune marked but died before deleting)."""
    return [r[0] for r in conn.execute("SELECT version FROM models WHERE pruned_at IS NOT NULL")]


def claim(conn: sqlite3.Connection, models_dir: Path, versions: Iterable[str], now: str,
          whole: Callable[[str], bool]) -> tuple[dict[str, Path], dict[str, str]]:
    """In a write transaction, after the marks were committed in one of their own: claim the directory of each of
    ``versions`` still marked pruned by an atomic rename to ``.prune-*``, so that of two prunes at once one
    deletes (and counts) it. Returns the claimed ``{version: path}`` (for ``finish`` to delete, outside the lock)
    and those that could not be claimed (version: why; a read-only ``models/``, say): one of them still
    ``whole`` (its weights file there at its registered size) gets its mark taken off, here, so rollback
    and promote may use it again -- under the same lock that re-read the mark, so no other prune can claim it
    after a promote that the unmarking lets through. One already gone (claimed by another prune) is neither."""
    claimed: dict[str, Path] = {}
    failed: dict[str, str] = {}
    for version in versions:
        row = conn.execute("SELECT pruned_at FROM models WHERE version = ?", (version,)).fetchone()
        if row is None or row[0] is None:  # its mark taken off since (by a prune that could not claim it)
            continue
        path = models_dir / f".prune-{version}-{uuid.uuid4().hex[:8]}"
        try:
            os.rename(models_dir / version, path)
        except FileNotFoundError:
            continue
        except OSError as exc:
            failed[version] = f"cannot delete {version}/: {exc.strerror or exc}"
            if whole(version):
                conn.execute("UPDATE models SET pruned_at = NULL, updated = ? WHERE version = ?", (now, version))
            continue
        claimed[version] = path
    return claimed, failed


def _remove(path: Path) -> None:
    """Delete a claimed folder, or only the link when it is a symbolic link: what it points to (another disk)
    is not the registry's to delete."""
    if path.is_symlink():
        path.unlink()
    else:
        shutil.rmtree(path)


def finish(models_dir: Path, chosen: list[str], claimed: dict[str, Path], failed: dict[str, str], kept: list[str],
           aside: StrayFolders) -> PruneResult:
    """Once the directories are claimed (``claim``; the folders no row names moved aside as they could be,
    ``aside``): deletes the claimed ones and sweeps the dot folders crashed calls left. Those it could not
    claim, or delete in full (left in their ``.prune-*`` folder for ``sweep_stale``), are ``not_deleted``."""
    failed = dict(failed)
    deleted, freed = [], 0
    for version, path in claimed.items():
        try:
            size = 0 if path.is_symlink() else tree_size(path)
            _remove(path)
        except OSError as exc:
            failed[version] = f"deleted only in part, the rest left in {path.name}/: {exc.strerror or exc}"
            continue
        freed += size
        deleted.append(version)
    sweep_stale(models_dir, time.time())
    if deleted:
        fsync_dir(models_dir)
    return PruneResult(pruned=sorted(set(chosen) - set(failed) | set(deleted)), kept=kept, freed_bytes=freed,
                       orphaned=aside.moved, not_moved=aside.not_moved, not_deleted=failed)


def dry_run(models_dir: Path, chosen: list[str], every_marked: list[str], kept: list[str],
            aside: StrayFolders) -> PruneResult:
    """What a prune would delete: ``chosen`` and what an earlier prune marked but left, sized (a link's target
    is not counted: a prune deletes only the link)."""
    would = chosen + [v for v in every_marked if v not in chosen and (models_dir / v).exists()]
    sizes = sum(0 if (models_dir / v).is_symlink() else tree_size(models_dir / v) for v in would)
    return PruneResult(pruned=sorted(would), kept=kept, dry_run=True, orphaned=aside.moved, freed_bytes=sizes)


def sweep_stale(models_dir: Path, now: float, dry_run: bool = False) -> list[str]:
    """Delete the dot folders a crashed ``register`` (``.tmp-*``) or ``prune`` (``.prune-*``) left, once
    older than ``STALE_AGE_S`` at ``now`` (unix seconds; a younger one may be a live call's); return their names
    (with ``dry_run``, only find them). Never ``.orphans/`` (``storage.strays.MODEL_ORPHANS_DIR``): the folders
    there are kept for the operator."""
    found = sorted(p for p in (*models_dir.glob(".tmp-*"), *models_dir.glob(".prune-*"))
                   if age_s(p, now, follow=False) > STALE_AGE_S)  # (a link by its own age: its target may be gone)
    for stale in [] if dry_run else found:
        with contextlib.suppress(OSError):
            _remove(stale)
    return [p.name for p in found]


def tree_size(path: Path) -> int:
    """Bytes of the files under ``path`` (files that vanish meanwhile count 0)."""
    total = 0
    for f in path.rglob("*"):
        try:
            total += f.stat().st_size if f.is_file() else 0
        except FileNotFoundError:
            continue
    return total
