"""Promotions: the champion alias, the history of promotions, and the walk back of a rollback.

The alias ``champion`` (table ``model_aliases``) names the model in service; ``champion_history`` has one row
per promotion, oldest first, with ``rolled_back_at`` set on those a rollback undid, so the promotions not
rolled back (``live_history``) are the chain ``rollback`` walks back along. A promotion (``switch``) retires
the champion, crowns the new one and records it; a rollback (``roll_back``) returns to an earlier champion of
that chain (``rollback_target``: the latest whose weights still match their sha256).

These are the registry's steps: ``rollback_target`` outside any lock (it reads weights files), the others over
a connection it opened (those that write, inside its ``BEGIN IMMEDIATE`` transaction); ``storage.models`` owns
the connections and transactions. Every change of a model's status goes through ``set_status``.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from datetime import datetime, timezone

from storage import checkpoint_files
from storage.errors import CorruptCheckpointError, RegistryError
from storage.model_rows import ChampionEntry, ModelStatus

#: The alias of the model in service.
CHAMPION = "champion"


def now() -> str:
    """The time now, as the registry records it (ISO 8601 UTC, microseconds)."""
    return datetime.now(timezone.utc).isoformat(timespec="microseconds")


def champion(conn: sqlite3.Connection) -> str | None:
    """The version in service, or None before the first promotion -- and when the alias names no registered model
    (a row deleted by hand: the file does not enforce the reference), so that the next gate or ``promote`` crowns
    one instead of every command failing on an unknown version (``switch`` retires any row left marked)."""
    row = conn.execute("SELECT a.version FROM model_aliases a JOIN models m ON m.version = a.version "
                       "WHERE a.alias = ?", (CHAMPION,)).fetchone()
    return None if row is None else row[0]


def history(conn: sqlite3.Connection) -> list[ChampionEntry]:
    """Every promotion, oldest first (rolled-back ones carry ``rolled_back_at``)."""
    rows = conn.execute("SELECT version, promoted_at, reason, rolled_back_at "
                        "FROM champion_history ORDER BY id").fetchall()
    return [ChampionEntry(*tuple(r)) for r in rows]


def how_promoted(conn: sqlite3.Connection, version: str) -> tuple[str | None, str]:
    """The champion before the champion ``version`` (None for the first), and the reason of its promotion."""
    entries = history(conn)
    before = next((e.version for e in reversed(entries) if e.version != version), None)
    return before, entries[-1].reason if entries and entries[-1].version == version else "promoted"


def live_history(conn: sqlite3.Connection) -> list[tuple[int, str]]:
    """(id, version) of promotions not rolled back, oldest first."""
    return [(r[0], r[1]) for r in conn.execute(
        "SELECT id, version FROM champion_history WHERE rolled_back_at IS NULL ORDER BY id")]


def set_status(conn: sqlite3.Connection, version: str, status: ModelStatus, reason: str) -> None:
    """Inside a transaction: ``version`` is ``status`` now, for ``reason``."""
    conn.execute("UPDATE models SET status = ?, reason = ?, updated = ? WHERE version = ?",
                 (status.value, reason, now(), version))


def switch(conn: sqlite3.Connection, version: str, reason: str) -> None:
    """Inside a transaction: retire the champion (every row marked so: one, unless the alias was broken by hand),
    crown ``version``, record the promotion."""
    marked = conn.execute("SELECT version FROM models WHERE status = ? AND version != ?",
                          (ModelStatus.CHAMPION.value, version)).fetchall()
    for (current,) in marked:
        set_status(conn, current, ModelStatus.RETIRED, f"replaced by {version}")
    set_status(conn, version, ModelStatus.CHAMPION, reason)
    conn.execute("INSERT OR REPLACE INTO model_aliases (alias, version) VALUES (?, ?)", (CHAMPION, version))
    conn.execute("INSERT INTO champion_history (version, promoted_at, reason) VALUES (?, ?, ?)",
                 (version, now(), reason))


def rollback_target(entries: list[tuple[int, str]], current: str, verify: Callable[[str], None],
                    other_split: dict[str, str] | None = None) -> str:
    """The latest earlier champion of ``entries`` (``live_history``) other than ``current`` whose weights pass
    ``verify`` (which raises ``CorruptCheckpointError``) and that is not in ``other_split`` (version: the eval
    split it was measured on, when not the current one: ``promote`` refuses those too); the others are skipped.
    Raises ``RegistryError`` when none is left, ``RegistryUnavailableError`` when one's weights cannot be read
    now."""
    skipped: list[str] = []
    other_split = other_split or {}
    for _, version in reversed(entries[:-1]):
        if version == current:
            continue
        if version in other_split:
            skipped.append(f"{version} (evaluated on another eval split, {other_split[version]})")
            continue
        try:
            verify(version)
        except CorruptCheckpointError as exc:
            checkpoint_files.raise_unless_lasting(exc, f"roll back past {version}")
            skipped.append(f"{version} (weights unusable: {exc})")
            continue
        return version
    why = f"; skipped: {'; '.join(skipped)}" if skipped else ""
    raise RegistryError(f"no previous champion to roll back to from {current}{why}")


def roll_back(conn: sqlite3.Connection, current: str, target: str, entries: list[tuple[int, str]]) -> None:
    """Inside a transaction: from ``current`` back to ``target``, chosen from ``entries`` before the write lock
    (``rollback_target``): the promotions after ``target``'s last are rolled back, ``current`` is retired and
    ``target`` is the champion again. ``RegistryError`` when the champion, the history or ``target``'s files
    (pruned) changed since, and nothing changes."""
    pruned = conn.execute("SELECT pruned_at FROM models WHERE version = ?", (target,)).fetchone()
    if champion(conn) != current or live_history(conn) != entries or pruned is None or pruned[0] is not None:
        raise RegistryError("the champion changed while rolling back; run rollback again")
    at = now()
    last_of_target = max(eid for eid, v in entries if v == target)
    conn.executemany("UPDATE champion_history SET rolled_back_at = ? WHERE id = ?",
                     [(at, eid) for eid, _ in entries if eid > last_of_target])
    set_status(conn, current, ModelStatus.RETIRED, f"rolled back to {target} at {at}")
    set_status(conn, target, ModelStatus.CHAMPION, f"restored by rollback from {current}")
    conn.execute("INSERT OR REPLACE INTO model_aliases (alias, version) VALUES (?, ?)", (CHAMPION, target))
