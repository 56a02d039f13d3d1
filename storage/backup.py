"""A backup of a data directory, taken while the service runs: one consistent copy to serve from.

The SQLite file (episodes, eval split, request queue, model registry) is copied with SQLite's online
backup API in one step: a snapshot at one instant, while writers go on (in WAL mode a reader does
not block them). Then the files that snapshot names are copied: every indexed episode and the
checkpoint folder of every model whose files are kept, each episode and each set of weights checked
against its recorded sha256 as it is read. Files written after the snapshot are not in it and are
not copied; a model pruned between the snapshot and its copy is marked pruned in the copy too.
A quarantined episode's file is copied from ``quarantine/`` as it is (it may be what was damaged), and
one quarantined between the snapshot and its copy is quarantined in the copy too.

The copy is built under a hidden name next to ``dest`` and renamed into place last, so ``dest``
exists only when complete. Not copied: ``reports/`` (made again by ``run``), lock files, and what
crashed calls left (staging files, ``orphans/``). To restore, stop the service and serve from the
backup (``--data DEST``) or move it into place.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from storage import quarantine as quarantines
from storage.database import DB_NAME, connection
from storage.catalog import Catalog
from storage.quarantine import quarantine_path
from storage.errors import BackupError, StorageError
from storage.files import ensure_dir, fsync_dir, holds, sha256_hex, write_synced
from storage.models import MODELS_DIR, WEIGHTS_FILE, ModelRegistry


@dataclass(frozen=True)
class BackupResult:
    """What ``backup`` copied."""

    dest: Path
    """The finished backup: a data directory."""
    episodes: int
    """Episode files copied intact."""
    models: int
    """Checkpoint folders copied intact."""
    bytes: int
    """Bytes of the files copied, the SQLite file included."""
    seconds: float
    """Wall time of the whole backup."""
    problems: list[str] = field(default_factory=list)
    """Files the snapshot names that could not be copied intact (missing, unreadable, failing their
    sha256), one line each; the backup holds everything else. ``episodes verify`` on the source shows
    the same."""


def check_dest(data_dir: str | os.PathLike[str], dest: str | os.PathLike[str]) -> None:
    """Raise ``BackupError`` unless ``dest`` can take a backup of ``data_dir``: outside it, and absent
    or an empty directory. Changes nothing."""
    data_dir, dest = Path(data_dir), Path(dest)
    try:
        inside = dest.resolve().is_relative_to(data_dir.resolve())
    except OSError as exc:
        raise BackupError(f"cannot look at {dest}: {exc.strerror or exc}") from exc
    if inside:
        raise BackupError(f"the backup {dest} would be inside the data directory {data_dir}; "
                          "choose a place outside it (better: on another disk)")
    if dest.is_dir() and any(dest.iterdir()):
        raise BackupError(f"{dest} already exists and is not empty; choose a new directory")
    if dest.exists() and not dest.is_dir():
        raise BackupError(f"{dest} is a file; choose a new directory")
    parent = dest.absolute().parent  # the nearest folder that exists is where the backup's folders are made
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise BackupError(f"{parent} is a file, so {dest} cannot be made; choose a new directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise BackupError(f"cannot write in {parent} (permission denied); choose a new directory")


def _snapshot_db(source: Path, target: Path) -> None:
    """The whole SQLite file at one instant, by the online backup API, fsynced."""
    with connection(source, BackupError) as src:
        dst = sqlite3.connect(target)
        try:
            src.backup(dst)  # all pages in one step: one read transaction, so one instant
        except sqlite3.Error as exc:
            raise BackupError(f"cannot copy {source} to {target}: {exc}") from exc
        finally:
            dst.close()
    with open(target, "rb+") as f:
        os.fsync(f.fileno())


class _Unusable(Exception):
    """A source file the snapshot names cannot be copied intact (reported, the backup goes on)."""


def _copy_checked(src: Path, dst: Path, sha256: str | None, dirs: set[Path]) -> int:
    """Copy ``src`` to ``dst``, fsynced; returns its size. Raises ``_Unusable`` when ``src`` is missing,
    unreadable or fails ``sha256``, and ``OSError`` when ``dst`` cannot be written (the backup fails)."""
    try:
        data = src.read_bytes()
    except FileNotFoundError:
        raise _Unusable(f"{src} is missing") from None
    except OSError as exc:
        raise _Unusable(f"cannot read {src}: {exc.strerror or exc}") from exc
    found = sha256_hex(data) if sha256 is not None else None
    if found != sha256:
        raise _Unusable(f"{src}: sha256 is {found}, recorded {sha256}")
    ensure_dir(dst.parent)
    write_synced(dst, data)
    dirs.add(dst.parent)
    return len(data)


def _pruned_in_source(source_db: Path, version: str) -> bool:
    with connection(source_db, BackupError) as conn:
        row = conn.execute("SELECT * FROM models WHERE version = ?", (version,)).fetchone()
    return row is not None and "pruned_at" in row.keys() and row["pruned_at"] is not None


def _quarantine_in_source(source_db: Path, episode_id: str) -> sqlite3.Row | None:
    with connection(source_db, BackupError) as conn:
        try:
            return quarantines.find(conn, episode_id)
        except sqlite3.OperationalError as exc:
            if "no such table" not in str(exc):  # busy, or failing: no answer (the backup fails, naming it)
                raise
            return None  # a catalog from before quarantines


def _copy_episode(conn: sqlite3.Connection, source_db: Path, work: Path, row: sqlite3.Row, dirs: set[Path]
                  ) -> tuple[int, bool]:
    """Copy one episode's file; returns (bytes copied, whether it is in training in the copy).

    As the snapshot knows it: its file checked against its sha256, or, when it is quarantined, the file
    kept in ``quarantine/`` as it is (when there is one). When that fails, the source changed since the
    snapshot (a quarantine or a restore went on, or one was cut short by a crash): the copy takes the
    episode's quarantine state as the source has it now and its intact bytes wherever they are. Raises
    ``_Unusable`` when an episode in training has no intact file."""
    data_dir = source_db.parent
    episode_id, rel, sha, moved_to = row
    kept = quarantine_path(rel)
    try:
        if moved_to is None:
            return _copy_checked(data_dir / rel, work / rel, sha, dirs), True
        if moved_to:
            return _copy_checked(data_dir / moved_to, work / moved_to, None, dirs), False
    except _Unusable:
        pass
    now = _quarantine_in_source(source_db, episode_id)
    intact = next((src for src in (data_dir / rel, data_dir / kept) if holds(src, sha)), None)
    quarantines.remove(conn, episode_id)
    if now is not None:
        quarantines.insert(conn, episode_id, now["reason"], kept if intact is not None or now["moved_to"] else "",
                           now["at"])
    if intact is not None:
        return _copy_checked(intact, work / (rel if now is None else kept), sha, dirs), now is None
    if now is None:
        raise _Unusable(f"{data_dir / rel} is missing or does not hold the bytes indexed (sha256 {sha[:16]}...)")
    if now["moved_to"] and (data_dir / kept).exists():  # what is left of a damaged file, as it is
        return _copy_checked(data_dir / kept, work / kept, None, dirs), False
    return 0, False


def backup(data_dir: str | os.PathLike[str], dest: str | os.PathLike[str],
           progress: Callable[[int, int], None] | None = None) -> BackupResult:
    """Copy the data directory ``data_dir`` to ``dest`` (a new directory), consistently, while it is in use.

    ``progress(done, total)`` is called after each file. Raises ``BackupError`` when there is no
    catalog in ``data_dir``, ``dest`` is in the way (see ``check_dest``), or the copy cannot be written
    (a full disk): then nothing is left at ``dest``. Files the snapshot names that cannot be copied
    intact do not stop the backup: they are listed in ``problems``.
    """
    t0 = time.perf_counter()
    data_dir, dest = Path(data_dir), Path(dest)
    source_db = data_dir / DB_NAME
    if not source_db.is_file():
        raise BackupError(f"no catalog at {source_db}: nothing to back up")
    check_dest(data_dir, dest)
    ensure_dir(dest.parent)
    work = dest.parent / f".{dest.name}.backup-{uuid.uuid4().hex[:8]}"
    try:
        work.mkdir()
        result = _fill(data_dir, work, progress)
        if dest.is_dir():
            dest.rmdir()  # empty (checked): the rename below takes its place
        os.rename(work, dest)
        fsync_dir(dest.parent)
    except BaseException as exc:
        shutil.rmtree(work, ignore_errors=True)
        if isinstance(exc, OSError):  # a full disk
            raise BackupError(f"cannot write the backup at {dest}: {exc.strerror or exc}") from exc
        if isinstance(exc, StorageError) and not isinstance(exc, BackupError):  # e.g. a catalog newer than this code
            raise BackupError(f"cannot back up {data_dir}: {exc}") from exc
        raise
    episodes, models, size, problems = result
    return BackupResult(dest=dest, episodes=episodes, models=models, bytes=size, problems=problems,
                        seconds=round(time.perf_counter() - t0, 3))


def _fill(data_dir: Path, work: Path, progress: Callable[[int, int], None] | None
          ) -> tuple[int, int, int, list[str]]:
    """The backup's contents under ``work``: (episodes, models, bytes, problems)."""
    source_db = data_dir / DB_NAME
    db = work / DB_NAME
    _snapshot_db(source_db, db)
    Catalog(work)  # the copy at this code's schema (an older source has fewer columns)
    ModelRegistry(work)
    size = 0
    with connection(db, BackupError) as conn:
        episodes = conn.execute("SELECT e.episode_id, e.path, e.sha256, q.moved_to FROM episodes e "
                                "LEFT JOIN quarantine q USING (episode_id) ORDER BY e.path").fetchall()
        models = conn.execute("SELECT version, weights_sha256 FROM models WHERE pruned_at IS NULL "
                              "ORDER BY seq").fetchall()
        total, done, problems, n_episodes, n_models = len(episodes) + len(models), 0, [], 0, 0
        dirs: set[Path] = set()
        for row in episodes:
            try:
                copied, in_training = _copy_episode(conn, source_db, work, row, dirs)
                size += copied
                n_episodes += in_training
            except _Unusable as exc:
                problems.append(f"episode {row['episode_id']}: {exc}")
            done += 1
            if progress is not None:
                progress(done, total)
        for version, sha in models:
            folder, copy = data_dir / MODELS_DIR / version, work / MODELS_DIR / version
            try:
                try:
                    files = sorted(p for p in folder.iterdir() if p.is_file())
                except FileNotFoundError:
                    raise _Unusable(f"{folder} is missing") from None
                if WEIGHTS_FILE not in {p.name for p in files}:
                    raise _Unusable(f"{folder / WEIGHTS_FILE} is missing")
                for src in files:
                    size += _copy_checked(src, copy / src.name, sha if src.name == WEIGHTS_FILE else None, dirs)
                n_models += 1
            except _Unusable as exc:
                shutil.rmtree(copy, ignore_errors=True)
                if _pruned_in_source(source_db, version):  # pruned since the snapshot: as the source is now
                    now = datetime.now(timezone.utc).isoformat(timespec="microseconds")
                    conn.execute("UPDATE models SET pruned_at = ? WHERE version = ?", (now, version))
                else:
                    problems.append(f"model {version}: {exc}")
            done += 1
            if progress is not None:
                progress(done, total)
    # closed: the copy's WAL is checkpointed into the file and removed
    size += sum(p.stat().st_size for p in work.glob(f"{DB_NAME}*"))
    for d in sorted(dirs | {work}):
        fsync_dir(d)
    return n_episodes, n_models, size, problems
