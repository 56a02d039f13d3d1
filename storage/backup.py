"""A backup of a data directory, taken while the service runs: one consistent copy to serve from.

The SQLite file (episodes, eval split, request queue, model registry) is copied with SQLite's online
backup API in one step: a snapshot at one instant, while writers go on (in WAL mode a reader does
not block them). Then the files that snapshot names are copied: first the checkpoint folder of every
model whose files are kept (a few small folders, so right after the snapshot), then every indexed
episode (the long part), each episode and each set of weights checked against its recorded sha256 as
it is read. Files written after the snapshot are not in it and are not copied. A model pruned between
the snapshot and its copy is marked pruned in the copy too, unless the copy needs it (its champion, or
an earlier champion its rollback returns to): then a retrain promoted and pruned meanwhile, and the
snapshot is taken again (``SNAPSHOT_TRIES`` in all, then the backup names it in ``problems``), so a
backup that reports none serves its champion.
A quarantined episode's file is copied from ``quarantine/`` as it is, unchecked (it may be what was damaged,
unless a worker's upload of the same bytes has put an intact copy there since: ``Catalog.repair_file``; one
that is missing is named in ``problems``), and one quarantined or restored between the snapshot and its copy
is so in the copy too, with its file (the source's state is read until it holds still across a look for it).

The copy is built under a hidden name next to ``dest`` (``.<dest>.backup-<8 hex>``, locked while its backup
lives) and renamed into place last, so ``dest`` exists only when complete; a backup killed midway leaves its
hidden folder, which the next backup to ``dest`` deletes (``swept``). One backup to ``dest`` at a time: each holds
``.<dest>.backup.lock`` beside it (its pid inside) from its check of ``dest`` to its rename, so a second one fails
at once naming the first rather than copying everything only to find ``dest`` taken; the holder deletes the file
when done, and the kernel lets go of the lock of one killed midway (the next backup takes it and deletes it).
``storage.backup_dest`` checks ``dest`` (see ``check_dest``), holds its lock and moves the copy into place.
The service's retrain schedule is carried as it was at the snapshot when the caller asks (``backup``'s
``carry``: read before the snapshot, written into the copy after it). Not copied: ``reports/`` (made again by
``run``), ``logs/``, lock files, and what crashed calls left (staging files, ``orphans/``, ``models/.orphans/``).
To restore, stop the service and serve from the backup (``--data DEST``) or move it into place.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from storage import promotions, quarantine as quarantines
from storage.backup_dest import (absolute, check_dest, dest_locked, locked, move_into_place, sweep_unfinished,
                                  work_folder)
from storage.database import DB_NAME, connection
from storage.catalog import Catalog
from storage.quarantine import quarantine_path
from storage.errors import BackupError, StorageError
from storage.files import ensure_dir, fsync_dir, sha256_hex, write_synced
from storage.models import MODELS_DIR, WEIGHTS_FILE, ModelRegistry

#: Snapshots a backup takes before it reports a champion (or an earlier champion its rollback needs)
#: pruned between its snapshot and its copy; each retake copies only the checkpoints again (seconds).
SNAPSHOT_TRIES = 3
#: Looks for the file of an episode whose quarantine state changed since the snapshot, each between two reads of
#: that state, before the backup takes the last state read (a restore or quarantine moved it meanwhile).
EPISODE_TRIES = 3


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
    sha256; a quarantined episode's kept file missing; or the copy's champion or rollback chain, pruned while
    the backup ran and every retake),
    one line each; the backup holds everything else. ``episodes verify`` on the source shows the same."""
    swept: list[Path] = field(default_factory=list)
    """The hidden folders of earlier backups to ``dest`` that were killed midway, deleted by this one."""


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
    episode's quarantine state as the source has it now and its intact bytes wherever they are
    (``_copy_as_now``). Raises ``_Unusable`` when an episode in training has no intact file, or a quarantined
    one no file where its quarantine row says."""
    episode_id, rel, sha, moved_to = row
    try:
        if moved_to is None:
            return _copy_checked(source_db.parent / rel, work / rel, sha, dirs), True
        if moved_to:
            return _copy_checked(source_db.parent / moved_to, work / moved_to, None, dirs), False
    except _Unusable:
        pass
    return _copy_as_now(conn, source_db, work, (episode_id, rel, sha), dirs)


def _copy_as_now(conn: sqlite3.Connection, source_db: Path, work: Path, episode: tuple[str, str, str],
                 dirs: set[Path]) -> tuple[int, bool]:
    """``_copy_episode`` once the source has changed since the snapshot: its quarantine state is read before and
    after each look for the file, until it is the same both times (``EPISODE_TRIES`` looks at most: a quarantine
    or a restore moves the file between the two places looked in), and the copy takes the last one read, with
    its file where that state puts it; its quarantine row is written once the file is copied."""
    data_dir = source_db.parent
    episode_id, rel, sha = episode
    kept = quarantine_path(rel)
    for attempt in range(EPISODE_TRIES):
        if attempt:  # (what an earlier look copied, taken again)
            for path in (work / rel, work / kept):
                path.unlink(missing_ok=True)
        before = _quarantine_in_source(source_db, episode_id)
        size, at, intact = _copy_found(data_dir, work, (rel, kept, sha), before, dirs)
        now = _quarantine_in_source(source_db, episode_id)
        stable = (before and tuple(before)) == (now and tuple(now))
        if stable and (at is not None or (now is not None and not now["moved_to"])):
            break
    if at is not None and now is None and not intact:  # (damaged bytes, taken as quarantined ones as they are)
        (work / at).unlink()
        size, at = 0, None
    place = rel if now is None else kept
    if at is not None and at != place:  # the state changed after the file was copied, on the last look
        ensure_dir((work / place).parent)
        os.rename(work / at, work / place)
        dirs.add((work / place).parent)
    quarantines.remove(conn, episode_id)
    if now is None:
        if at is None:
            raise _Unusable(f"{data_dir / rel} is missing or does not hold the bytes indexed (sha256 {sha[:16]}...)")
        return size, True
    quarantines.insert(conn, episode_id, now["reason"], kept if at is not None else now["moved_to"], now["at"])
    if at is None and now["moved_to"]:
        raise _Unusable(f"{data_dir / now['moved_to']} is missing (the file of this quarantined episode)")
    return size, False


def _copy_found(data_dir: Path, work: Path, episode: tuple[str, str, str], state: sqlite3.Row | None,
                dirs: set[Path]) -> tuple[int, str | None, bool]:
    """One look for an episode's file, in the state ``state`` (its quarantine row, None in training): its intact
    bytes from either place, copied to where ``state`` puts them, else (quarantined) the file kept as it is.
    Returns (bytes copied, where in the copy, whether they are the bytes indexed); (0, None, False) for none."""
    rel, kept, sha = episode
    places = (rel, kept) if state is None else (kept, rel)
    for src in places:  # each read once, checked as it is copied: no look that a move outdates before the read
        try:
            return _copy_checked(data_dir / src, work / places[0], sha, dirs), places[0], True
        except _Unusable:
            pass
    if state is not None and state["moved_to"]:  # what is left of a damaged file, as it is
        try:
            return _copy_checked(data_dir / kept, work / kept, None, dirs), kept, False
        except _Unusable:
            pass
    return 0, None, False


def backup(data_dir: str | os.PathLike[str], dest: str | os.PathLike[str],
           progress: Callable[[int, int], None] | None = None,
           carry: Callable[[Path], Callable[[Path], None]] | None = None) -> BackupResult:
    """Copy the data directory ``data_dir`` to ``dest`` (a new directory), consistently, while it is in use.

    ``progress(done, total)`` is called after each file; ``carry(data_dir)`` right before each snapshot, to read
    what else the copy needs as ``data_dir`` has it then, and the function it returns with the copy right after,
    its catalog and registry in place, to write it there (the service's retrain schedule:
    ``orchestrator.scheduler.carry_schedule``). Raises ``BackupError`` when there is no
    catalog in ``data_dir``, ``dest`` is in the way (see ``check_dest``), another backup to ``dest`` is running
    (at once, naming its pid), something else took ``dest`` meanwhile, or the copy cannot be written (a full
    disk): then this backup leaves nothing, at ``dest`` or beside it. Files the snapshot names that cannot be
    copied intact do not stop the backup: they are listed in ``problems``.
    """
    t0 = time.perf_counter()
    data_dir, dest = Path(data_dir), absolute(dest)
    source_db = data_dir / DB_NAME
    if not source_db.is_file():
        raise BackupError(f"no catalog at {source_db}: nothing to back up")
    check_dest(data_dir, dest)
    try:
        ensure_dir(dest.parent)
    except OSError as exc:
        raise BackupError(f"cannot write the backup at {dest}: {exc.strerror or exc}") from exc
    with dest_locked(dest):
        check_dest(data_dir, dest)  # again, as the lock's holder: an earlier backup may have just finished it
        swept = sweep_unfinished(dest)
        result = _build(data_dir, dest, progress, carry)
    episodes, models, size, problems = result
    return BackupResult(dest=dest, episodes=episodes, models=models, bytes=size, problems=problems,
                        seconds=round(time.perf_counter() - t0, 3), swept=swept)


def _build(data_dir: Path, dest: Path, progress: Callable[[int, int], None] | None,
           carry: Callable[[Path], Callable[[Path], None]] | None) -> tuple[int, int, int, list[str]]:
    """``_fill`` a hidden folder beside ``dest`` and rename it into place; on any failure the folder is deleted."""
    work = work_folder(dest)
    try:
        work.mkdir()
        with locked(work):  # until it is renamed into place: no other backup's sweep takes it
            result = _fill(data_dir, work, progress, carry)
            move_into_place(work, dest)
    except BaseException as exc:
        shutil.rmtree(work, ignore_errors=True)
        if isinstance(exc, OSError):  # a full disk
            raise BackupError(f"cannot write the backup at {dest}: {exc.strerror or exc}") from exc
        if isinstance(exc, StorageError) and not isinstance(exc, BackupError):  # e.g. a catalog newer than this code
            raise BackupError(f"cannot back up {data_dir}: {exc}") from exc
        raise
    return result


class _Tally:
    """What one backup has copied so far, and its progress (``done`` goes on across retakes)."""

    def __init__(self, progress: Callable[[int, int], None] | None) -> None:
        self.progress, self.done, self.total = progress, 0, 0
        self.restart()

    def restart(self) -> None:
        self.episodes, self.models, self.bytes = 0, 0, 0
        self.problems: list[str] = []
        self.dirs: set[Path] = set()

    def expect(self, files: int) -> None:
        """A snapshot names ``files`` more files to copy."""
        self.total = self.done + files
        if self.progress is not None:
            self.progress(self.done, self.total)

    def tick(self) -> None:
        self.done += 1
        if self.progress is not None:
            self.progress(self.done, self.total)


def _fill(data_dir: Path, work: Path, progress: Callable[[int, int], None] | None,
          carry: Callable[[Path], Callable[[Path], None]] | None) -> tuple[int, int, int, list[str]]:
    """The backup's contents under ``work``: (episodes, models, bytes, problems).

    The checkpoints first, right after the snapshot (a few small folders), then the episodes (the long
    part). A checkpoint the copy's registry needs (its champion, or an earlier champion its rollback
    walks back to) that was pruned between the snapshot and its copy means the registry moved on (a
    retrain promoted and pruned): the snapshot is taken again, up to ``SNAPSHOT_TRIES`` times, then the
    backup names it in ``problems`` rather than hand over a copy that cannot serve."""
    source_db = data_dir / DB_NAME
    tally = _Tally(progress)
    for attempt in range(1, SNAPSHOT_TRIES + 1):
        if attempt > 1:  # a retake: start again from an empty folder, the same one (locked; the count goes on)
            for path in list(work.iterdir()):
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                else:
                    path.unlink()
            tally.restart()
        db = work / DB_NAME
        carried = carry(data_dir) if carry is not None else None
        _snapshot_db(source_db, db)
        Catalog(work)  # the copy at this code's schema (an older source has fewer columns)
        ModelRegistry(work)
        if carried is not None:
            carried(work)
        with connection(db, BackupError) as conn:
            episodes = conn.execute("SELECT e.episode_id, e.path, e.sha256, q.moved_to FROM episodes e "
                                    "LEFT JOIN quarantine q USING (episode_id) ORDER BY e.path").fetchall()
            models = conn.execute("SELECT version, weights_sha256 FROM models WHERE pruned_at IS NULL "
                                  "ORDER BY seq").fetchall()
            tally.expect(len(episodes) + len(models))
            if not _copy_models(conn, source_db, work, models, tally, last=attempt == SNAPSHOT_TRIES):
                continue
            for row in episodes:
                try:
                    copied, in_training = _copy_episode(conn, source_db, work, row, tally.dirs)
                    tally.bytes += copied
                    tally.episodes += in_training
                except _Unusable as exc:
                    tally.problems.append(f"episode {row['episode_id']}: {exc}")
                tally.tick()
        break
    # closed: the copy's WAL is checkpointed into the file and removed
    tally.bytes += sum(p.stat().st_size for p in work.glob(f"{DB_NAME}*"))
    for d in sorted(tally.dirs | {work}):
        fsync_dir(d)
    return tally.episodes, tally.models, tally.bytes, tally.problems


_CHAMPION, _EARLIER = "its champion", "an earlier champion its rollback returns to"


def _needed(conn: sqlite3.Connection) -> dict[str, str]:
    """In the copy: the models its registry serves or rolls back to (the champion, then the earlier
    champions not rolled back), each with what it is to the copy."""
    champion = promotions.champion(conn)  # (none when the alias names no model)
    chain = [r[0] for r in conn.execute(
        "SELECT version FROM champion_history WHERE rolled_back_at IS NULL ORDER BY id DESC")]
    needed = dict.fromkeys(chain, _EARLIER)
    if champion is not None:
        needed[champion] = _CHAMPION
    return needed


def _copy_models(conn: sqlite3.Connection, source_db: Path, work: Path, models: list[sqlite3.Row],
                 tally: _Tally, last: bool) -> bool:
    """Copy the checkpoint folders the snapshot keeps; False when one the copy needs (``_needed``) was
    pruned since the snapshot and this is not the ``last`` try (the snapshot is to be taken again)."""
    needed = _needed(conn)
    for version, sha in models:
        try:
            tally.bytes += _copy_model(source_db.parent / MODELS_DIR / version, work / MODELS_DIR / version,
                                       sha, tally.dirs)
            tally.models += 1
        except _Unusable as exc:
            if not _pruned_in_source(source_db, version):
                tally.problems.append(f"model {version}: {exc}")
            elif version in needed and not last:
                return False
            else:  # pruned since the snapshot: as the source is now (a champion stays one: no prune takes it)
                if needed.get(version) != _CHAMPION:
                    now = datetime.now(timezone.utc).isoformat(timespec="microseconds")
                    conn.execute("UPDATE models SET pruned_at = ? WHERE version = ?", (now, version))
                if version in needed:
                    tally.problems.append(
                        f"model {version}, {needed[version]} in the backup: pruned in the source while the "
                        f"backup ran ({SNAPSHOT_TRIES} snapshots, each outrun by a retrain or `models prune`); "
                        "back up again")
        tally.tick()
    return True


def _copy_model(folder: Path, copy: Path, sha: str, dirs: set[Path]) -> int:
    """Copy one checkpoint folder, its weights checked against ``sha``; returns the bytes copied. Raises
    ``_Unusable`` (leaving no partial copy) when a file is missing, unreadable or fails its sha256."""
    try:
        try:
            files = sorted(p for p in folder.iterdir() if p.is_file())
        except FileNotFoundError:
            raise _Unusable(f"{folder} is missing") from None
        if WEIGHTS_FILE not in {p.name for p in files}:
            raise _Unusable(f"{folder / WEIGHTS_FILE} is missing")
        return sum(_copy_checked(src, copy / src.name, sha if src.name == WEIGHTS_FILE else None, dirs)
                   for src in files)
    except _Unusable:
        shutil.rmtree(copy, ignore_errors=True)
        raise
