"""A data directory whose top-level folders live on file systems of their own (``DATA/episodes`` a link to a big
volume, say), where a rename between them fails with EXDEV: ``storage.files.move`` copies the file across, so
quarantine, restore, the read that heals a quarantine cut short and the sweep of strays work there; a crash
between the copy and the removal of the source (a real SIGKILL) leaves the file in both places, never in
neither, and every caller's recovery takes it from there. Real folders on two file systems (/dev/shm beside
the test's temporary folder; skipped where they are one)."""

from __future__ import annotations

import errno
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from storage import files
from storage.catalog import Catalog
from storage.errors import MissingEpisodeError
from storage.strays import STAGING_MAX_AGE_S
from tests.conftest import REPO
from tests.storage.test_episodes import assert_same, make_episode
from tests.storage.test_quarantine import _killed_in_quarantine
from tests.storage.test_strays_best_effort import _strays


@pytest.fixture
def volume(tmp_path) -> Iterator[Path]:
    """A folder on another file system than ``tmp_path``'s: the big volume an operator links a folder to."""
    shm = Path("/dev/shm")
    if not (shm.is_dir() and os.access(shm, os.W_OK) and shm.stat().st_dev != tmp_path.stat().st_dev):
        pytest.skip(f"no second file system beside {tmp_path} (/dev/shm)")
    folder = Path(tempfile.mkdtemp(dir=shm))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def _catalog(tmp_path: Path, volume: Path, linked: str) -> Catalog:
    """A catalog whose ``DATA/<linked>`` is a link to ``volume``."""
    data = tmp_path / "data"
    data.mkdir()
    (data / linked).symlink_to(volume)
    return Catalog(data)


def _kept(cat: Catalog, path: Path) -> Path:
    return cat.data_dir / "quarantine" / path.parent.name / path.name


def _leftovers(*folders: Path) -> list[Path]:
    return [p for folder in folders for p in folder.rglob(".*.tmp")]


def test_move_copies_a_file_across_file_systems_and_removes_it_after(tmp_path, volume):
    src = tmp_path / "a" / "ep.mcap"
    src.parent.mkdir()
    src.write_bytes(b"episode bytes" * 1000)
    os.chmod(src, 0o640)
    dst = volume / "day" / "ep.mcap"
    dst.parent.mkdir()
    dst.write_bytes(b"a damaged leftover")

    files.move(src, dst)

    assert dst.read_bytes() == b"episode bytes" * 1000 and not src.exists()
    assert dst.stat().st_mode & 0o777 == 0o640
    assert _leftovers(volume, tmp_path) == []
    files.move(dst, src)  # and back
    assert src.read_bytes() == b"episode bytes" * 1000 and not dst.exists()
    folder = tmp_path / "models" / "m000001-0badf00d"
    folder.mkdir(parents=True)
    with pytest.raises(OSError) as raised:  # a folder is not copied: its caller leaves it where it is
        files.move(folder, volume / "m000001-0badf00d")
    assert raised.value.errno == errno.EXDEV and folder.is_dir() and not (volume / "m000001-0badf00d").exists()


def test_a_copy_that_fails_leaves_the_file_where_it_was_and_nothing_beside_the_destination(tmp_path, volume,
                                                                                          monkeypatch):
    src = tmp_path / "ep.mcap"
    src.write_bytes(b"episode bytes")
    real = os.fsync

    def full_disk(fd: int) -> None:  # the copy's data reaches the disk at its fsync, and does not fit
        if stat.S_ISREG(os.fstat(fd).st_mode) and os.readlink(f"/proc/self/fd/{fd}").startswith(str(volume)):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd)
    monkeypatch.setattr(os, "fsync", full_disk)

    with pytest.raises(OSError) as raised:
        files.move(src, volume / "day" / "ep.mcap")
    assert raised.value.errno == errno.ENOSPC
    assert src.read_bytes() == b"episode bytes" and list((volume / "day").iterdir()) == []


@pytest.mark.parametrize("linked", ["episodes", "quarantine"])
def test_quarantine_and_restore_work_with_a_folder_on_a_volume_of_its_own(tmp_path, volume, rng, linked):
    cat = _catalog(tmp_path, volume, linked)
    eps = [make_episode(rng) for _ in range(2)]
    rows = [cat.get(cat.add_episode(ep).episode_id) for ep in eps]

    row = cat.quarantine(rows[0].episode_id, "operator: blurred")
    assert row.quarantined == "operator: blurred" and not row.path.exists()
    assert files.holds(_kept(cat, row.path), row.sha256)
    with pytest.raises(MissingEpisodeError, match="quarantined"):
        cat.load(row.episode_id)
    assert cat.restore(row.episode_id).quarantined == "" and not _kept(cat, row.path).exists()
    assert_same(cat.load(row.episode_id), eps[0])

    # a training job quarantines a damaged train episode (uncertainty.data.load_train)
    rows[1].path.write_bytes(rows[1].path.read_bytes()[:-7])
    assert cat.quarantine(rows[1].episode_id, "found by a training job: damaged", only_if_damaged=True).quarantined
    assert not rows[1].path.exists() and _kept(cat, rows[1].path).stat().st_size == rows[1].size_bytes - 7
    assert cat.add_episode(eps[1]).restored  # its bytes ingested again bring it back
    assert cat.verify(rows[1].episode_id) == eps[1].meta
    assert _leftovers(tmp_path, volume) == []


def test_a_quarantine_killed_before_its_commit_is_healed_across_file_systems(tmp_path, volume, rng):
    cat = _catalog(tmp_path, volume, "episodes")
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)
    _killed_in_quarantine(cat, row.episode_id)
    assert not row.path.exists() and cat.count(quarantined=True) == 0  # the file moved, the row did not
    assert_same(cat.load(row.episode_id), ep)  # the read moves it back, across
    assert row.path.exists() and not _kept(cat, row.path).exists()


@pytest.mark.parametrize("linked", ["episodes", "orphans"])
def test_the_sweep_moves_every_stray_off_a_volume_of_its_own(tmp_path, volume, rng, linked):
    cat = _catalog(tmp_path, volume, linked)
    strays = _strays(cat, rng, 3)

    swept = cat.sweep_strays()

    assert swept.unindexed == strays and swept.not_moved == {}
    for path in strays:
        assert not path.exists() and (cat.data_dir / "orphans" / path.parent.name / path.name).read_bytes()
    assert not cat.strays() and _leftovers(tmp_path, volume) == []


# A catalog call whose process dies at one call of storage.files.move across file systems: at the removal of
# the source, once the copy is in place ("unlink"), or at the rename of the copy into place ("replace").
KILLED_IN_MOVE = """
import os, signal, sys
from pathlib import Path
from storage.catalog import Catalog

data, call, episode_id, at = sys.argv[1:]
real = getattr(os, at)
def die_there(src, *args, **kw):
    if Path(src).name.endswith(".mcap" if at == "unlink" else ".tmp"):
        os.kill(os.getpid(), signal.SIGKILL)
    return real(src, *args, **kw)
setattr(os, at, die_there)
cat = Catalog(data)
{"quarantine": lambda: cat.quarantine(episode_id, "operator: blurred"), "restore": lambda: cat.restore(episode_id),
 "sweep": cat.sweep_strays}[call]()
sys.exit("not killed")
"""


def _killed_in_move(cat: Catalog, call: str, episode_id: str = "", at: str = "unlink") -> None:
    done = subprocess.run([sys.executable, "-c", KILLED_IN_MOVE, str(cat.data_dir), call, episode_id, at], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == -signal.SIGKILL, done.stderr


def test_a_quarantine_killed_between_the_copy_and_the_removal_leaves_both_and_the_next_one_takes_it(tmp_path,
                                                                                                   volume, rng):
    cat = _catalog(tmp_path, volume, "episodes")
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)

    _killed_in_move(cat, "quarantine", row.episode_id)

    assert files.holds(row.path, row.sha256) and files.holds(_kept(cat, row.path), row.sha256)  # in both places
    assert cat.count(quarantined=True) == 0 and cat.verify(row.episode_id) == ep.meta
    assert cat.quarantine(row.episode_id, "operator: blurred").quarantined == "operator: blurred"
    assert not row.path.exists() and files.holds(_kept(cat, row.path), row.sha256)  # out of episodes/ now
    assert cat.restore(row.episode_id).quarantined == "" and not _kept(cat, row.path).exists()
    assert_same(cat.load(row.episode_id), ep)


def test_a_restore_killed_between_the_copy_and_the_removal_is_finished_by_the_next_one(tmp_path, volume, rng):
    cat = _catalog(tmp_path, volume, "quarantine")
    ep = make_episode(rng)
    row = cat.quarantine(cat.add_episode(ep).episode_id, "operator: blurred")

    _killed_in_move(cat, "restore", row.episode_id)

    assert files.holds(row.path, row.sha256) and files.holds(_kept(cat, row.path), row.sha256)  # in both places
    assert cat.get(row.episode_id).quarantined == "operator: blurred"  # its end did not commit
    assert cat.restore(row.episode_id).quarantined == "" and not _kept(cat, row.path).exists()
    assert cat.verify(row.episode_id) == ep.meta


def test_a_sweep_killed_between_the_copy_and_the_removal_is_finished_by_the_next_one(tmp_path, volume, rng):
    cat = _catalog(tmp_path, volume, "orphans")
    [stray] = _strays(cat, rng, 1)
    data = stray.read_bytes()
    orphan = cat.data_dir / "orphans" / stray.parent.name / stray.name

    _killed_in_move(cat, "sweep")

    assert stray.read_bytes() == orphan.read_bytes() == data  # in both places
    assert cat.sweep_strays().unindexed == [stray]
    assert not stray.exists() and orphan.read_bytes() == data and not cat.strays()


def test_a_copy_a_crash_cut_short_is_deleted_by_the_sweep_once_old(tmp_path, volume, rng):
    cat = _catalog(tmp_path, volume, "quarantine")
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)

    _killed_in_move(cat, "quarantine", row.episode_id, at="replace")

    [copy] = _leftovers(cat.data_dir / "quarantine")
    assert files.holds(row.path, row.sha256) and not _kept(cat, row.path).exists()  # in place, the copy unnamed
    assert cat.sweep_strays().staging == [] and copy.exists()  # young: it may be a live move's
    later = copy.stat().st_mtime + STAGING_MAX_AGE_S + 1
    assert cat.sweep_strays(now=later).staging == [copy] and not copy.exists()
    assert cat.verify(row.episode_id) == ep.meta and cat.count(quarantined=True) == 0


def test_a_stray_whose_copy_does_not_fit_stays_and_the_others_are_moved(tmp_path, volume, rng, monkeypatch):
    cat = _catalog(tmp_path, volume, "orphans")
    stuck, *others = _strays(cat, rng, 3)  # the first one tried
    real = os.fsync

    def full_disk(fd: int) -> None:  # the copy of ``stuck`` reaches the volume at its fsync, and does not fit
        if os.readlink(f"/proc/self/fd/{fd}").startswith(str(volume / stuck.parent.name / f".{stuck.name}.")):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd)
    monkeypatch.setattr(os, "fsync", full_disk)

    swept = cat.sweep_strays()

    assert swept.unindexed == [stuck, *others] and swept.not_moved == {stuck: os.strerror(errno.ENOSPC)}
    assert stuck.is_file() and sorted(p.name for p in (volume / stuck.parent.name).iterdir()) == sorted(
        p.name for p in others)  # no copy of it left beside them
    assert not any(p.exists() for p in others)
