"""Writing a secure profile's files all or nothing (``orchestrator.secure.init_secure``).

A new profile is staged file by file beside its final names and put in place by renames, and what this call made
is removed again when anything fails (``write_new``); a profile that ``--force`` replaces is written whole into a
sibling folder and swapped in by two folder renames, the old one kept aside until the new one is in place
(``replace``), so a failure or a crash leaves one whole profile, never old and new files mixed. Where the folder
cannot be renamed (a mount point: the Docker or Kubernetes volume shared with a router container), the files are
swapped inside it the same way, through ``DIR/.new-*`` and ``DIR/.old-*``.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import shutil
from collections.abc import Iterable
from pathlib import Path

from orchestrator.transport import SecureConfigError
from storage.files import fsync_dir

#: Each file's bytes and whether it is a secret (0600), by its path.
Files = dict[Path, tuple[bytes, bool]]
#: Why a folder cannot be renamed or given a sibling where the files in it can be renamed: it is a mount point
#: (EBUSY), an overlay's lower layer or on another file system than the sibling (EXDEV), or its parent may not be
#: written while it may (EACCES, EPERM, EROFS).
_NO_FOLDER_SWAP = frozenset({errno.EBUSY, errno.EXDEV, errno.EACCES, errno.EPERM, errno.EROFS})
#: The folders ``_replace_inside`` makes in a profile's directory, which a crash may leave there.
_SWAP_FOLDER = re.compile(r"\.(new|old)-[0-9a-f]{8}")


class _NoFolderSwap(Exception):
    """The profile's folder cannot be given a sibling or be renamed (``_NO_FOLDER_SWAP``); nothing was changed."""


def _staged_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp")


def _stage(path: Path, data: bytes, secret: bool) -> Path:
    """``_write`` under a temporary name next to ``path``; returns that name, for ``os.replace`` onto ``path``."""
    tmp = _staged_name(path)
    tmp.unlink(missing_ok=True)
    _write(tmp, data, secret)
    return tmp


def _write(path: Path, data: bytes, secret: bool) -> None:
    """Writes ``data`` to the new file ``path``, fsynced, created with its final mode (so a secret is never
    readable by others)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600 if secret else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.chmod(path, 0o600 if secret else 0o644)  # umask may have narrowed the public ones


def write_new(directory: Path, files: Files) -> None:
    """Writes a profile into ``directory``, made as needed, that holds none of its files yet."""
    made = [p for p in (directory, *directory.parents) if not p.exists()][::-1]  # outermost first
    placed: list[Path] = []
    try:
        try:
            directory.mkdir(parents=True, exist_ok=True)
            os.chmod(directory, 0o700)
        except OSError as exc:
            raise SecureConfigError(f"cannot create {directory}: {exc.strerror}") from exc
        staged = {path: _stage(path, data, secret) for path, (data, secret) in files.items()}
        for path, tmp in staged.items():
            os.replace(tmp, path)
            placed.append(path)
    except BaseException:
        _undo(files, placed, made)
        raise


def _undo(files: Iterable[Path], placed: list[Path], made: list[Path]) -> None:
    """Removes the staged copies of ``files``, those ``placed`` (the directory held none of them before) and
    the directories ``write_new`` made."""
    for path in files:
        _staged_name(path).unlink(missing_ok=True)
    for path in placed:
        path.unlink(missing_ok=True)
    if made and made[0].is_dir():  # the outermost one this call made: all under it is this call's
        shutil.rmtree(made[0])


def interrupted_swaps(directory: Path) -> list[Path]:
    """The ``.new-*`` / ``.old-*`` folders that a crash in a swap inside ``directory`` left there: they hold the new
    profile's files not yet in place, and the old one's already set aside. ``replace`` deletes them."""
    return sorted(p for p in directory.iterdir() if _SWAP_FOLDER.fullmatch(p.name) and p.is_dir())


def sibling_swaps(directory: Path) -> list[Path]:
    """The ``.NAME.new-*`` / ``.NAME.old-*`` folders beside ``directory`` that a crash in a folder swap
    (``_replace_folder``) left: the new profile not yet in place, or the old one set aside (then ``directory``
    may be missing). They hold keys and passwords."""
    target = directory.resolve()
    pattern = re.compile(rf"\.{re.escape(target.name)}\.(new|old)-[0-9a-f]{{8}}")
    if not target.parent.is_dir():
        return []
    return sorted(p for p in target.parent.iterdir() if pattern.fullmatch(p.name) and p.is_dir())


def delete_swaps(folders: list[Path]) -> None:
    """Deletes what earlier, crashed swaps left (``sibling_swaps``), once a profile is whole in place."""
    for folder in folders:
        shutil.rmtree(folder, ignore_errors=True)


def staged_names(planned: list[Path]) -> set[Path]:
    """The temporary names ``write_new`` stages ``planned`` under, which a crash may leave: its own."""
    return {_staged_name(p) for p in planned}


def replace(directory: Path, files: Files) -> Path | None:
    """Replaces the profile in ``directory`` whole; returns where the old one is left when it cannot be deleted.

    The new one is written into a sibling folder and swapped in by two folder renames (``_replace_folder``); where
    the folder cannot be renamed or given a sibling (a mount point), its files are swapped inside it instead
    (``_replace_inside``). A failure leaves the old profile; a crash the old one or the new one, never a mix. Done
    where a link to ``directory`` points: the configs name the files by their resolved paths."""
    target = directory.resolve()
    try:
        return _replace_folder(target, files)
    except _NoFolderSwap:
        return _replace_inside(target, files)


def _replace_folder(target: Path, files: Files) -> Path | None:
    """The new profile written into a sibling ``.NAME.new-*`` folder and swapped in by two renames, the old one
    kept aside (``.NAME.old-*``) until the new one is in place, put back when it cannot be (``_swap_in``); then
    deleted. A crash between the renames leaves the old one whole, aside. Raises _NoFolderSwap when the sibling
    cannot be made or ``target`` cannot be renamed."""
    new, old = (target.with_name(f".{target.name}.{kind}-{secrets.token_hex(4)}") for kind in ("new", "old"))
    try:
        new.mkdir(mode=0o700)
    except OSError as exc:
        if exc.errno in _NO_FOLDER_SWAP:  # e.g. a parent that may not be written
            raise _NoFolderSwap from exc
        raise
    try:
        _fill(new, files)
        _swap_in(new, target, old)
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)  # never in place: this call's own files
        raise
    fsync_dir(target.parent)
    return _delete(old)


def _fill(folder: Path, files: Files) -> None:
    """Writes every file of ``files`` into the new, private (0700 whatever the umask) ``folder``, durably."""
    os.chmod(folder, 0o700)
    for path, (data, secret) in files.items():
        _write(folder / path.name, data, secret)
    fsync_dir(folder)


def _swap_in(new: Path, target: Path, old: Path) -> None:
    """Renames ``target`` to ``old``, then ``new`` to ``target``; when that fails, ``old`` back to ``target``."""
    try:
        os.rename(target, old)
    except OSError as exc:
        if exc.errno in _NO_FOLDER_SWAP:  # e.g. a mount point, which cannot be renamed
            raise _NoFolderSwap from exc
        raise OSError(exc.errno, f"cannot set the profile in {target} aside to replace it whole: {exc.strerror} "
                                 "(nothing changed)") from exc
    try:
        os.rename(new, target)
    except BaseException as exc:
        try:
            os.rename(old, target)
        except OSError as again:
            raise OSError(again.errno, f"cannot put the new profile in place ({exc}), nor the old one back ("
                                       f"{again.strerror}): it is whole at {old}; rename it back to {target}") from exc
        raise


def _replace_inside(target: Path, files: Files) -> Path | None:
    """The new profile staged in ``target/.new-*``, swapped with the old one's files (``_swap_files``, the old ones
    set aside in ``target/.old-*``); then both folders deleted, and those an earlier crash left (they hold files of
    the profile replaced now). ``target`` is made private (0700) first, as a new profile's folder is."""
    try:
        os.chmod(target, 0o700)
    except OSError as exc:
        raise SecureConfigError(f"cannot make {target} private (mode 0700) to replace the profile in it: "
                                f"{exc.strerror} (nothing changed)") from exc
    earlier = interrupted_swaps(target)
    new, old = (target / f".{kind}-{secrets.token_hex(4)}" for kind in ("new", "old"))
    try:
        new.mkdir(mode=0o700)
        _fill(new, files)
        old.mkdir(mode=0o700)
        _swap_files(new, target, old, [path.name for path in files])
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)  # never in place: this call's own files
        with contextlib.suppress(OSError):  # not empty when the old files could not be put back: the error names it
            old.rmdir()
        raise
    fsync_dir(target)
    return _delete(old, new, *earlier)


def _swap_files(new: Path, target: Path, old: Path, names: list[str]) -> None:
    """Moves the files ``names`` in ``target`` into ``old``, then those in ``new`` into ``target``; when that fails,
    takes the new ones out and moves the old ones back. All the old ones leave before the first new one comes in,
    so ``target`` holds old files or new ones, never both (a crash may leave some missing)."""
    moved: list[str] = []
    placed: list[str] = []
    try:
        for name in names:
            if os.path.lexists(target / name):
                os.rename(target / name, old / name)
                moved.append(name)
        fsync_dir(old)
        fsync_dir(target)  # the old ones out on disk too before a new one comes in
        for name in names:
            os.rename(new / name, target / name)
            placed.append(name)
    except BaseException as exc:
        try:
            for name in placed:
                (target / name).unlink()
            for name in moved:
                os.rename(old / name, target / name)
        except OSError as again:
            raise OSError(again.errno, f"cannot put the new profile in place ({exc}), nor the old one back ("
                                       f"{again.strerror}): move the files in {old} back into {target}") from exc
        raise


def _delete(*folders: Path) -> Path | None:
    """Deletes ``folders``; returns the first that cannot be deleted (it may hold the old keys)."""
    kept: Path | None = None
    for folder in folders:
        try:
            shutil.rmtree(folder)
        except OSError:
            kept = kept or folder
    return kept
