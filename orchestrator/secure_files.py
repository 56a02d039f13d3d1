"""Writing a secure profile's files all or nothing (``orchestrator.secure.init_secure``).

A new profile is staged file by file beside its final names and put in place by renames, and what this call made
is removed again when anything fails (``write_new``); a profile that ``--force`` replaces is written whole into a
sibling folder and swapped in by two folder renames, the old one kept aside until the new one is in place
(``replace``), so a failure or a crash leaves one whole profile, never old and new files mixed.
"""

from __future__ import annotations

import os
import secrets
import shutil
from collections.abc import Iterable
from pathlib import Path

from orchestrator.transport import SecureConfigError
from storage.files import fsync_dir

#: Each file's bytes and whether it is a secret (0600), by its path.
Files = dict[Path, tuple[bytes, bool]]


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


def replace(directory: Path, files: Files) -> Path | None:
    """Replaces the profile in ``directory`` whole; returns where the old one is left when it cannot be deleted.

    The new one is written into a sibling ``.NAME.new-*`` folder, then swapped in by two renames, the old one
    kept aside (``.NAME.old-*``) until the new one is in place, put back when it cannot be. A failure leaves the
    old profile; a crash the old one or the new one (between the renames: the old one aside), never a mix. Done
    where a link to ``directory`` points: the configs name the files by their resolved paths."""
    target = directory.resolve()
    new, old = (target.with_name(f".{target.name}.{kind}-{secrets.token_hex(4)}") for kind in ("new", "old"))
    try:
        new.mkdir(mode=0o700)
        os.chmod(new, 0o700)
        for path, (data, secret) in files.items():
            _write(new / path.name, data, secret)
        fsync_dir(new)
        _swap_in(new, target, old)
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)  # never in place: this call's own files
        raise
    fsync_dir(target.parent)
    try:
        shutil.rmtree(old)
    except OSError:
        return old
    return None


def _swap_in(new: Path, target: Path, old: Path) -> None:
    """Renames ``target`` to ``old``, then ``new`` to ``target``; when that fails, ``old`` back to ``target``."""
    try:
        os.rename(target, old)
    except OSError as exc:  # e.g. a mount point, which cannot be renamed
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
