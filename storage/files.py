"""Durable file writes: stage under a temporary name with an fsync, rename, fsync the directory.

A crash never leaves a partial file under a final name: readers see the old file or the new
one. Used for episodes (``storage.episodes``, ``storage.catalog``) and model checkpoints
(``storage.models``).

A data directory's top-level folders may live on file systems of their own (``DATA/episodes`` a link to,
or a mount of, a big volume): ``move`` copies a file across them where a rename cannot.
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from storage.errors import MisplacedFolderError

#: Read and written at a time when ``move`` copies a file across file systems.
_COPY_CHUNK = 1 << 20


def age_s(path: Path, now: float, follow: bool = True) -> float:
    """Seconds since ``path`` was last modified; 0 when it is gone (a live call finished with it while we
    looked). What the sweeps of files a crash left go by: a younger file may be a live call's. ``follow=False``:
    a symbolic link's own age, not its target's (which may be gone)."""
    try:
        return now - (path.stat() if follow else path.lstat()).st_mtime
    except FileNotFoundError:
        return 0.0


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def fsync_dir(directory: Path) -> None:
    """Makes a rename in ``directory`` durable (no-op where directories cannot be opened)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def ensure_dir(path: str | os.PathLike) -> None:
    """``mkdir -p`` made durable: the parent of every directory it creates is fsynced.

    Without that, a file fsynced into a new directory (the first episode of a day) can
    survive a power loss while the directory's own entry does not.
    """
    path = Path(path)
    created, p = [], path
    while not p.exists():
        created.append(p)
        p = p.parent
    path.mkdir(parents=True, exist_ok=True)
    for d in reversed(created):
        fsync_dir(d.parent)


def make_folder(path: Path, error: type[MisplacedFolderError], purpose: str, create: bool = True) -> None:
    """``mkdir -p path``; ``error`` (the caller's ``MisplacedFolderError``) naming it when a file, or a link to no
    directory, is in its place, where mkdir said only "[Errno 17] File exists". ``purpose`` says what the folder is
    for. A link is not to be moved away: it may point at a volume not mounted now (``move``'s folders on file
    systems of their own). ``create=False`` (a reader that must write nothing) makes none where none is: only
    what is in its place is checked."""
    cause: OSError | None = None
    if create:
        try:
            path.mkdir(parents=True, exist_ok=True)
            return
        except FileExistsError as exc:
            cause = exc
    elif path.is_dir() or not (path.exists() or path.is_symlink()):
        return
    if path.is_symlink():
        raise error(f"{path} is a link to {os.readlink(path)}, which is not a directory (a volume not "
                    f"mounted?): {purpose}; mount it, or point the link at the folder") from cause
    raise error(f"{path} is not a directory: {purpose}; move the file away") from cause


def stage_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Writes ``data`` to a fresh temporary file next to ``path`` and fsyncs it; returns its path.

    The name (``.<name>.*.tmp``) never matches ``*.mcap``, so a leftover from a crash is
    never mistaken for an episode. On an exception the temporary file is removed.
    """
    return _stage(Path(path), lambda f: f.write(data))


def _stage_copy(src: Path, path: Path) -> Path:
    """``stage_bytes`` of the bytes of the file ``src`` (streamed; its mode kept). Its times are the copy's own:
    the sweeps of what crashes left tell a live call's staging file from a crash's by its age."""
    def copy(f: BinaryIO) -> None:
        with open(src, "rb") as source:
            shutil.copyfileobj(source, f, _COPY_CHUNK)
            os.chmod(f.fileno(), stat.S_IMODE(os.fstat(source.fileno()).st_mode))
    return _stage(path, copy)


def _stage(path: Path, write: Callable[[BinaryIO], object]) -> Path:
    ensure_dir(path.parent)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return Path(tmp)


def publish(staged: Path, path: str | os.PathLike) -> None:
    """Renames a staged file to its final name and makes the rename durable."""
    path = Path(path)
    os.replace(staged, path)
    fsync_dir(path.parent)


def move(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Moves ``src`` to ``dst`` (over a file there; its folder made as needed), durably: after a crash the file
    is under one name or the other, or, mid-way across file systems, under both; never under neither.

    Within a file system a rename, both folders fsynced. Across two (EXDEV: a top-level folder of the data
    directory on a volume of its own), a file is copied to ``.<name>.*.tmp`` beside ``dst`` and fsynced
    (``stage_bytes``'s names: the catalog's sweep deletes a crash's leftover), renamed to ``dst`` (its folder
    fsynced), and only then is ``src`` removed (its folder fsynced). Raises ``OSError``: a copy that fails (a
    full disk) leaves ``src`` as it was and nothing beside ``dst``; a removal that fails leaves both. A
    folder is not copied: across file systems it raises EXDEV.
    """
    src, dst = Path(src), Path(dst)
    ensure_dir(dst.parent)
    try:
        os.replace(src, dst)
    except OSError as exc:
        if exc.errno != errno.EXDEV or not stat.S_ISREG(os.lstat(src).st_mode):
            raise
        _publish_or_remove(_stage_copy(src, dst), dst)  # durable under its new name before the old one goes
        os.unlink(src)
    else:
        fsync_dir(dst.parent)
    fsync_dir(src.parent)


def holds(path: str | os.PathLike, sha256: str) -> bool:
    """Whether the file at ``path`` exists and its bytes hash to ``sha256`` (False when it cannot be read:
    then it is to be repaired, or not trusted)."""
    try:
        return sha256_hex(Path(path).read_bytes()) == sha256
    except OSError:
        return False


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Writes ``data`` to a temporary name in the same directory, fsyncs, renames, fsyncs the dir.

    A crash or an exception never leaves a partial file under ``path``, and the
    temporary file is removed on an exception.
    """
    _publish_or_remove(stage_bytes(path, data), path)


def _publish_or_remove(staged: Path, path: str | os.PathLike) -> None:
    try:
        publish(staged, path)
    except BaseException:
        staged.unlink(missing_ok=True)
        raise


def write_synced(path: str | os.PathLike, data: bytes) -> None:
    """Writes ``data`` to ``path`` (a file of a directory not yet published) and fsyncs it."""
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
