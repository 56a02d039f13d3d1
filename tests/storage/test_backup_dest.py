"""Where a backup may go: a DEST it cannot replace by a rename, or one the service would sweep, is refused before
anything is copied (exit 2, one line, nothing changed); the spellings and folders it can take are taken whole."""

from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from storage.backup import backup, check_dest
from storage.backup_dest import LINKABLE_DIRS
from storage.catalog import Catalog
from storage.errors import BackupError
from tests.conftest import REPO, run_cli
from tests.storage.test_episodes import make_episode


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(3201)


def _data(tmp_path: Path, rng: np.random.Generator) -> Path:
    """A data directory of three episodes."""
    data = tmp_path / "data"
    cat = Catalog(data)
    for _ in range(3):
        cat.add_episode(make_episode(rng))
    return data


def _tree(root: Path) -> list[tuple[str, bool]]:
    """Every path under ``root`` (links not followed), and whether it is a link."""
    return sorted((p.relative_to(root).as_posix(), p.is_symlink()) for p in root.rglob("*"))


def _refused(capsys, data: Path, dest: str | Path, why: str) -> str:
    """``dest`` is refused by ``check_dest`` and by the CLI (exit 2, one line), saying ``why``; returns the line."""
    with pytest.raises(BackupError, match=re.escape(why)):
        check_dest(data, dest)
    rc, _, err = run_cli(capsys, "backup", str(dest), "--data", str(data))
    assert rc == 2 and why in err and err.count("\n") == 1, err
    return err


@pytest.mark.parametrize("folder", LINKABLE_DIRS)
def test_a_dest_inside_a_folder_the_data_directory_links_to_is_refused(tmp_path, rng, capsys, folder) -> None:
    """``episodes/`` on a volume of its own: a backup kept on that volume, under it, would be swept by the service
    (every episode file of it taken for a stray and moved to ``DATA/orphans/``)."""
    data = _data(tmp_path, rng)
    (data / folder).mkdir(exist_ok=True)
    volume = tmp_path / "volume"
    volume.mkdir()
    shutil.move(data / folder, volume / folder)
    (data / folder).symlink_to(volume / folder)
    before = _tree(tmp_path)

    _refused(capsys, data, volume / folder / "backups" / "b1",
             f"inside {volume / folder}, which the data directory's {folder}/ links to")

    assert _tree(tmp_path) == before
    rc, out, _ = run_cli(capsys, "backup", str(volume / "b1"), "--data", str(data))  # beside it, on that volume
    assert rc == 0 and "backed up 3 episodes" in out


@pytest.mark.parametrize("how", ["tmpfs", "bind"])
def test_a_dest_that_is_a_mount_point_is_refused(tmp_path, rng, capsys, how) -> None:
    """A mount point cannot be replaced by the finished copy (EBUSY); before, that was found after the whole copy,
    built on the parent's file system instead of the mounted one. A bind mount of a folder of the same file system
    has the parent's device: only the mount table shows it."""
    if os.geteuid() != 0:
        pytest.skip("mounting a file system needs root")
    data = _data(tmp_path, rng)
    disk, source = tmp_path / "disk", tmp_path / "source"
    disk.mkdir()
    source.mkdir()
    argv = (["mount", "-t", "tmpfs", "-o", "size=8m", "none", str(disk)] if how == "tmpfs"
            else ["mount", "--bind", str(source), str(disk)])
    mounted = subprocess.run(argv, capture_output=True, text=True, timeout=30)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount here: {mounted.stderr.strip()}")
    try:
        err = _refused(capsys, data, disk, f"{disk} is a mount point")
        assert f"give a new folder inside it, e.g. {disk / 'backup'}" in err
        assert not list(disk.iterdir()) and sorted(p.name for p in tmp_path.iterdir()) == ["data", "disk", "source"]

        result = backup(data, disk / "backup")  # what it says to do

        assert result.problems == [] and Catalog(disk / "backup").count() == 3
    finally:
        subprocess.run(["umount", str(disk)], check=True, timeout=30)


@pytest.mark.parametrize("target", ["empty", "nowhere"])
def test_a_dest_that_is_a_symbolic_link_is_refused(tmp_path, rng, capsys, target) -> None:
    """The rename that puts the copy in place would meet the link, not the folder it names (to an empty folder,
    or dangling): before, that failed after the whole copy, saying DEST appeared while the backup ran."""
    data = _data(tmp_path, rng)
    (tmp_path / "empty").mkdir()
    link = tmp_path / "link"
    link.symlink_to(tmp_path / target)
    before = _tree(tmp_path)

    _refused(capsys, data, link, f"{link} is a symbolic link (to {tmp_path / target})")

    assert _tree(tmp_path) == before


def test_dest_the_current_folder_is_backed_up_to(tmp_path, rng) -> None:
    """``backup .`` in an empty folder: the lock file and the hidden folder go beside it, not into it (which made
    it not empty, so the backup failed). (``backup ''``, an unset variable, is refused: test_cli_misc_hostile.)"""
    data = _data(tmp_path, rng)
    here = tmp_path / "here"
    here.mkdir()

    proc = subprocess.run([sys.executable, "-m", "orchestrator", "backup", ".", "--data", str(data)],
                          capture_output=True, text=True, timeout=120, cwd=here,
                          env={**os.environ, "PYTHONPATH": str(REPO)})

    assert proc.returncode == 0, proc.stderr
    assert f"to {here} in" in proc.stdout
    assert Catalog(here).count() == 3 and not list(here.glob(".*"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "here"]  # no lock file or hidden folder left


@pytest.mark.parametrize("mode", [0o700, 0o750, 0o2775])
def test_an_empty_dest_keeps_its_permissions(tmp_path, rng, mode) -> None:
    """A folder made private (or group-shared) for the backup beforehand is so afterwards: the finished copy that
    replaces it takes its mode."""
    data = _data(tmp_path, rng)
    dest = tmp_path / "private"
    dest.mkdir()
    os.chmod(dest, mode)

    result = backup(data, dest)

    assert result.problems == [] and stat.S_IMODE(dest.stat().st_mode) == mode
    assert Catalog(dest).count() == 3


def test_a_dest_whose_hidden_folder_name_would_be_too_long_is_refused(tmp_path, rng, capsys) -> None:
    data = _data(tmp_path, rng)
    dest = tmp_path / ("x" * 245)

    _refused(capsys, data, dest, "is too long for a backup")

    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    assert backup(data, tmp_path / ("x" * 238)).problems == []  # the longest name that fits: 238 + 17 = 255
