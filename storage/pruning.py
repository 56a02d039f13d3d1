"""Pruning: deleting the files of models no rollback needs (``ModelRegistry.prune``).

A prune keeps the champion, the earlier champions ``rollback`` walks back to, then the latest champions a
rollback took out of service; it marks the rest of the retired and rejected models (``pruned_at``), all in
one transaction, then deletes their directories, each claimed first by a rename to ``.prune-*`` so that of
two prunes at once one deletes (and counts) it. Rows stay, so every model's metrics and history remain.

These are the registry's steps: ``keep_order``, ``mark`` and ``marked`` over a connection it opened (the
last two inside its ``BEGIN IMMEDIATE`` transaction), the sha256 checks and the deletes outside any lock
(``storage.models`` owns connections and transactions).
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path

from storage.errors import CorruptCheckpointError
from storage.files import age_s
from storage.model_rows import ModelStatus

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


def unusable(wanted: Iterable[str], keep: int, verify: Callable[[str], None]) -> set[str]:
    """Those of ``wanted`` (in keep order) whose weights ``verify`` refuses (``CorruptCheckpointError``),
    checked until ``keep`` have passed: rollback would skip them, so they take no keep slot."""
    found, intact = set(), 0
    for version in wanted:
        if intact == keep:
            break
        try:
            verify(version)
            intact += 1
        except CorruptCheckpointError:
            found.add(version)
    return found


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


def delete(models_dir: Path, versions: Iterable[str]) -> tuple[list[str], int]:
    """Delete the directories of ``versions`` under ``models_dir``; return those this call deleted and the
    bytes they held (one already gone, or claimed by another prune, is neither)."""
    deleted, freed = [], 0
    for version in versions:
        # Claimed by an atomic rename: of two prunes at once, one deletes and counts each directory.
        claimed = models_dir / f".prune-{version}-{uuid.uuid4().hex[:8]}"
        try:
            os.rename(models_dir / version, claimed)
        except FileNotFoundError:
            continue
        freed += tree_size(claimed)
        shutil.rmtree(claimed)
        deleted.append(version)
    return deleted, freed


def sweep_stale(models_dir: Path, now: float) -> None:
    """Delete the dot folders a crashed ``register`` (``.tmp-*``) or ``prune`` (``.prune-*``) left, once
    older than ``STALE_AGE_S`` at ``now`` (unix seconds; a younger one may be a live call's)."""
    for stale in (*models_dir.glob(".tmp-*"), *models_dir.glob(".prune-*")):
        if age_s(stale, now) > STALE_AGE_S:
            shutil.rmtree(stale, ignore_errors=True)


def tree_size(path: Path) -> int:
    """Bytes of the files under ``path`` (files that vanish meanwhile count 0)."""
    total = 0
    for f in path.rglob("*"):
        try:
            total += f.stat().st_size if f.is_file() else 0
        except FileNotFoundError:
            continue
    return total
