"""Strays: files a crashed ingest left under ``DATA/episodes/`` (``Catalog.strays``, ``Catalog.sweep_strays``).

An ingest stages its bytes under a hidden temporary name, then, inside its write transaction, renames the
file into place and inserts its row. A crash before the rename leaves a staging file; one between the
rename and the commit, an episode file no row indexes. Neither was acknowledged (the row is the one commit
point), so a sweep deletes staging files and moves unindexed files aside to ``DATA/orphans/``, each as best it
can: one that cannot be moved (a full disk) stays where it is and is named, and the others still go. A move
across file systems (``DATA/episodes`` on a volume of its own, see ``storage.files.move``) is a copy under a
staging file's name, so the sweep deletes those a crash left in ``DATA/quarantine/`` and ``DATA/orphans/`` too.

The model registry's ``register`` works the same way (a ``.tmp-*`` folder staged, renamed to its version and
its row inserted in one write transaction), so a register that dies between the rename and the commit, or whose
undo cannot delete the folder, leaves a checkpoint folder no row names: ``unregistered`` finds those and moves
them aside to ``DATA/models/.orphans/`` (``ModelRegistry.sweep_strays``, and every ``prune``). That folder is
inside ``models/`` so that the move is a rename within one file system wherever ``models/`` lives (a link to,
or a mount of, a volume of its own for checkpoints, where a rename to ``DATA/orphans/`` would fail with EXDEV),
and needs no space but a directory entry. A folder that cannot be moved all the same stays where it is and is
said (no row names it, so nothing serves it): it never fails the caller's transaction, a prune's marks included.

These are the catalog's and the registry's steps: the directory walks outside any lock, ``unindexed`` and
``unregistered`` over a connection they opened, inside its ``BEGIN IMMEDIATE`` transaction (``storage.catalog``
and ``storage.models`` own connections and transactions).
"""

from __future__ import annotations

import re
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

from storage.database import EPISODES_DIR, MODELS_DIR, QUARANTINE_DIR
from storage.files import age_s, move
from storage.model_rows import StrayFolders

#: Where ``sweep_strays`` moves episode files that have no catalog row.
ORPHANS_DIR = "orphans"
#: Where ``unregistered`` moves checkpoint folders no registry row names (relative to the data directory):
#: ``DATA/models/.orphans/<version>``. A dot folder, so no walk of the registry's takes it for one of its own:
#: ``model_folders`` lists version names only, ``storage.pruning.sweep_stale`` deletes ``.tmp-*`` and
#: ``.prune-*`` only, and a backup copies the folders of rows only.
MODEL_ORPHANS_DIR = f"{MODELS_DIR}/.orphans"
#: What ``ModelRegistry.register`` names a checkpoint folder (``m<seq>-<8 hex of the weights' sha256>``); a
#: folder named otherwise under ``models/`` is no version of the registry's (the ``.tmp-*`` and ``.prune-*``
#: ones are live or crashed calls', which ``storage.pruning.sweep_stale`` takes by age).
_VERSION = re.compile(r"m[0-9]{6,}-[0-9a-f]{8}")
#: A staging file older than this belongs to no live ingest (an ingest stages, then commits, in seconds).
STAGING_MAX_AGE_S = 300.0


@dataclass
class Strays:
    """Files a crashed ingest left under ``episodes/``."""

    staging: list[Path]
    """``.<id>.mcap.*.tmp`` files: written before a crash, never renamed into place (also those of copies across
    file systems into ``quarantine/`` and ``orphans/``, see ``staging_files``)."""
    unindexed: list[Path]
    """Episode files with no catalog row: renamed into place, then a crash before the commit."""
    not_moved: dict[Path, str] = field(default_factory=dict)
    """Those of ``unindexed`` a sweep could not move aside (path: why, e.g. a full disk), left where they are,
    unindexed, for the next sweep to try again."""

    def __bool__(self) -> bool:
        return bool(self.staging or self.unindexed)


def episode_files(episodes_dir: Path) -> list[Path]:
    """The episode files under ``episodes_dir``, sorted (staging files, hidden, left out)."""
    return sorted(p for p in episodes_dir.rglob("*.mcap") if not p.name.startswith("."))


def unindexed(conn: sqlite3.Connection, data_dir: Path, files: list[Path],
              move_to: Path | None) -> tuple[list[Path], dict[Path, str]]:
    """In a write transaction: those of ``files`` (under ``DATA/episodes/``) still there with no row; moved
    under ``move_to`` (at the same path below it) when given. With them, those that could not be moved (path:
    why).

    Best effort per file, as ``unregistered``: one whose move raises ``OSError`` (no space for ``move_to``'s
    folder, or for the copy across file systems) stays where it is and the others still go; nothing is raised.
    """
    episodes_dir = data_dir / EPISODES_DIR
    rows = {r["path"] for r in conn.execute("SELECT path FROM episodes")}
    found = [p for p in files if p.relative_to(data_dir).as_posix() not in rows and p.exists()]
    not_moved: dict[Path, str] = {}
    for path in found if move_to is not None else ():
        if why := _aside(path, move_to / path.relative_to(episodes_dir)):
            not_moved[path] = why
    return found, not_moved


def indexed(conn: sqlite3.Connection, rel: str) -> bool:
    """Whether a row indexes the episode file at ``rel`` (relative to the data directory, posix): after a
    failed ingest, whether its file is an episode or a stray."""
    return conn.execute("SELECT 1 FROM episodes WHERE path = ?", (rel,)).fetchone() is not None


def staging_files(data_dir: Path, min_age_s: float, now: float) -> list[Path]:
    """The staging files older than ``min_age_s`` at ``now`` (unix seconds) under ``DATA/episodes/`` and the
    folders ``storage.files.move`` copies episode files into across file systems (``quarantine/``, ``orphans/``),
    sorted."""
    return sorted(p for folder in (EPISODES_DIR, QUARANTINE_DIR, ORPHANS_DIR)
                  for p in (data_dir / folder).rglob(".*.mcap.*.tmp") if age_s(p, now) > min_age_s)


def model_folders(models_dir: Path) -> list[Path]:
    """The checkpoint folders under ``models_dir`` (named as versions), sorted."""
    return sorted(p for p in models_dir.iterdir() if _VERSION.fullmatch(p.name) and p.is_dir())


def unregistered(conn: sqlite3.Connection, folders: list[Path], move_to: Path | None) -> StrayFolders:
    """In a write transaction: those of ``folders`` (``model_folders``) still there that no row of the registry
    names; moved under ``move_to`` (as ``<version>``, ``<version>.1`` ... when an earlier sweep took the name)
    when given, else only found (``StrayFolders.moved``).

    Certain under the write lock, however the folders were listed: a register renames its folder into place
    and inserts its row in one write transaction, so by now every listed folder's register has committed (a
    row), rolled back and taken it away, or died (an orphan). One whose undo is still to come (it too takes the
    write lock) failed: moving its folder aside takes nothing that was acknowledged.

    Best effort per folder: one whose move raises ``OSError`` (no space to make ``move_to``, a folder that is
    a mount point) stays where it is, in ``not_moved`` with why, and the others still go; nothing is raised, so
    the caller's transaction commits what else it did."""
    rows = {r[0] for r in conn.execute("SELECT version FROM models")}
    found = [p for p in folders if p.name not in rows and p.is_dir()]
    if move_to is None:
        return StrayFolders(moved=[p.name for p in found])
    moved: list[str] = []
    not_moved: dict[str, str] = {}
    for path in found:
        if why := _aside(path, _free_name(move_to / path.name)):
            not_moved[path.name] = why
        else:
            moved.append(path.name)
    return StrayFolders(moved, not_moved)


def _aside(path: Path, dest: Path) -> str | None:
    """``move``s ``path`` to ``dest``; None once it is there, else why it stayed where it was (nothing raised)."""
    try:
        move(path, dest)
    except OSError as exc:
        if path.exists():  # else moved, and a folder's fsync after it failed: it is aside all the same
            return exc.strerror or str(exc)
    return None


def _free_name(path: Path) -> Path:
    """``path``, or ``path.1``, ``path.2`` ... the first that does not exist."""
    n, free = 0, path
    while free.exists():
        n += 1
        free = path.with_name(f"{path.name}.{n}")
    return free
