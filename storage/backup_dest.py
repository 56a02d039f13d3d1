"""Where a backup goes: the checks of its ``dest``, the lock beside it, the hidden folder it is built in, and the
rename that puts that folder in place (``storage.backup`` fills it).

``dest`` is a new directory, or an empty one that the finished copy replaces by a rename: so it cannot be a link
(the rename would replace the link, not what it points to) nor a mount point (the copy is built beside it, on the
parent's file system, and a mount point cannot be removed); and it is outside the data directory and outside the
folders the data directory's top-level folders link to (``episodes/`` on a volume of its own, say), where the
service's sweeps would take the copy's files for strays of its own.
"""

from __future__ import annotations

import errno
import fcntl
import os
import re
import shutil
import stat
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from storage.database import EPISODES_DIR, MODELS_DIR, QUARANTINE_DIR
from storage.errors import BackupError
from storage.files import fsync_dir
from storage.strays import ORPHANS_DIR

#: The data directory's top-level folders that may live elsewhere (README, Layout: a link or a mount).
LINKABLE_DIRS = (EPISODES_DIR, QUARANTINE_DIR, ORPHANS_DIR, MODELS_DIR)
#: The mount table of this process's mount namespace (Linux); where it cannot be read, ``os.path.ismount`` alone.
_MOUNTINFO = Path("/proc/self/mountinfo")
#: Hex digits that end the name of the hidden folder a backup is built in (``work_folder``).
_WORK_SUFFIX_CHARS = 8


def absolute(dest: str | os.PathLike[str]) -> Path:
    """``dest`` made absolute without following links (``.``, ``""`` and ``a/..`` get a name of their own, so what
    is made beside ``dest`` is made beside it, not inside it)."""
    return Path(os.path.abspath(dest))


def check_dest(data_dir: str | os.PathLike[str], dest: str | os.PathLike[str]) -> None:
    """Raise ``BackupError`` unless ``dest`` can take a backup of ``data_dir``: absent or an empty directory, not a
    link nor a mount point, outside the data directory and outside the folders its top-level folders link to
    (``LINKABLE_DIRS``), its nearest existing parent a writable folder. Changes nothing."""
    data_dir, dest = Path(data_dir), absolute(dest)
    if dest.is_symlink():
        raise BackupError(f"{dest} is a symbolic link (to {os.readlink(dest)}); give the directory itself, "
                          "or a new one")
    try:
        target = dest.resolve()
        inside = target.is_relative_to(data_dir.resolve())
        linked = next(((name, folder) for name in LINKABLE_DIRS
                       if target.is_relative_to(folder := (data_dir / name).resolve())), None)
    except (OSError, RuntimeError) as exc:  # (RuntimeError: a loop of links)
        raise BackupError(f"cannot look at {dest}: {getattr(exc, 'strerror', None) or exc}") from exc
    if inside:
        raise BackupError(f"the backup {dest} would be inside the data directory {data_dir}; "
                          "choose a place outside it (better: on another disk)")
    if linked is not None:
        raise BackupError(f"the backup {dest} would be inside {linked[1]}, which the data directory's "
                          f"{linked[0]}/ links to (its sweeps would take the backup's files); "
                          "choose a place outside it")
    if dest.is_dir() and any(dest.iterdir()):
        raise BackupError(f"{dest} already exists and is not empty; choose a new directory")
    if dest.exists() and not dest.is_dir():
        raise BackupError(f"{dest} is a file; choose a new directory")
    if dest.is_dir() and _is_mount_point(dest):
        raise BackupError(f"{dest} is a mount point, which a backup cannot replace (it is built beside {dest} and "
                          f"renamed into place); give a new folder inside it, e.g. {dest / 'backup'}")
    parent = dest.parent  # the nearest folder that exists is where the backup's folders are made
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise BackupError(f"{parent} is a file, so {dest} cannot be made; choose a new directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise BackupError(f"cannot write in {parent} (permission denied); choose a new directory")
    try:
        name_max = os.pathconf(parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    work_name = len(os.fsencode(work_prefix(dest))) + _WORK_SUFFIX_CHARS  # the longest name made beside it
    if work_name > name_max:
        extra = work_name - len(os.fsencode(dest.name))
        raise BackupError(f"the name of {dest} is too long for a backup: the folder it is built in beside it is "
                          f"named after it, {extra} characters longer, past the file system's {name_max}; "
                          "choose a shorter one")


def _is_mount_point(folder: Path) -> bool:
    """Whether the folder ``folder`` is a mount point: another file system than its parent's, or a bind
    mount of a folder of the same one (which only the mount table tells)."""
    if os.path.ismount(folder):
        return True
    try:
        lines = _MOUNTINFO.read_text().splitlines()
    except OSError:
        return False
    # The 5th field is the mount point, with space, tab, newline and backslash as octal escapes (\040 ...).
    points = {re.sub(r"\\([0-7]{3})", lambda m: chr(int(m[1], 8)), line.split(" ")[4])
              for line in lines if line.count(" ") >= 4}
    return str(folder.resolve()) in points


def work_prefix(dest: Path) -> str:
    """The start of the name of the hidden folder a backup to ``dest`` is built in, beside it (then
    ``_WORK_SUFFIX_CHARS`` hex digits: ``work_folder``)."""
    return f".{dest.name}.backup-"


def work_folder(dest: Path) -> Path:
    """A new name for the hidden folder a backup to ``dest`` is built in, beside it."""
    return dest.parent / f"{work_prefix(dest)}{uuid.uuid4().hex[:_WORK_SUFFIX_CHARS]}"


def lock_path(dest: Path) -> Path:
    """The file a backup to ``dest`` holds locked while it runs, beside it."""
    return dest.parent / f".{dest.name}.backup.lock"


def move_into_place(work: Path, dest: Path) -> None:
    """Rename the finished copy ``work`` to ``dest``, which is absent or an empty directory (checked; ``work``
    takes its permissions). Raises ``BackupError`` when something else has been put at ``dest`` meanwhile (a
    process that takes no lock: a backup by older code, a copy by hand); it is left as it is."""
    try:
        if dest.is_dir():
            os.chmod(work, stat.S_IMODE(dest.stat().st_mode))  # a folder made private beforehand stays private
            dest.rmdir()  # (fails unless still empty) the rename below takes its place
        os.rename(work, dest)  # (fails onto a directory that is not empty, or onto a file)
    except OSError as exc:
        if exc.errno in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR):
            raise BackupError(f"{dest} appeared while this backup ran: another backup or process wrote it; "
                              "this backup is discarded") from exc
        raise
    fsync_dir(dest.parent)


@contextmanager
def dest_locked(dest: Path) -> Iterator[None]:
    """Holds ``lock_path(dest)`` locked, with this process's pid in it, and deletes it on the way out. Raises
    ``BackupError`` naming the holder when another backup to ``dest`` holds it."""
    path = lock_path(dest)
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise BackupError(f"cannot create {path}: {exc.strerror or exc}") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
            os.close(fd)
            running = f"another backup to {dest} is running" + (f" (pid {holder})" if holder.isdigit() else "")
            raise BackupError(f"{running}; wait for it to finish, or back up to another DEST") from None
        if _is_still(path, fd):
            break
        os.close(fd)  # a backup that finished meanwhile deleted it: take the next one
    try:
        try:
            os.ftruncate(fd, 0)  # (a killed backup's pid may be in it)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as exc:
            raise BackupError(f"cannot write {path}: {exc.strerror or exc}") from exc
        yield
    finally:
        path.unlink(missing_ok=True)  # while locked: a backup that opened it before finds it gone and opens anew
        os.close(fd)


def _is_still(path: Path, fd: int) -> bool:
    """Whether ``path`` is still the file open at ``fd``."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return False
    return (st.st_dev, st.st_ino) == (os.fstat(fd).st_dev, os.fstat(fd).st_ino)


@contextmanager
def locked(folder: Path) -> Iterator[None]:
    """An exclusive lock on ``folder`` (the folder itself, so nothing is added to it), held in the block; the kernel
    releases it when the process dies, even by SIGKILL."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def sweep_unfinished(dest: Path) -> list[Path]:
    """Deletes the hidden folders beside ``dest`` that earlier backups to it were building when they were killed
    (unlocked: no live backup's); returns those deleted. Best effort: one that cannot be deleted stays, for the
    next backup to try again."""
    swept = []
    # (not a backup's to `<dest>.backup-x`)
    name = re.compile(re.escape(work_prefix(dest)) + "[0-9a-f]" * _WORK_SUFFIX_CHARS)
    for path in sorted(dest.parent.iterdir()):
        if not name.fullmatch(path.name) or path.is_symlink() or not path.is_dir():
            continue
        try:
            fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # (BlockingIOError: a live backup's)
            shutil.rmtree(path)
            swept.append(path)
        except OSError:
            continue
        finally:
            os.close(fd)
    return swept
