"""The sweep of episode files no row indexes moves each as best it can: one that cannot be moved aside (a full
disk) stays where it is and is named, with why, and the others still go; the service's sweep
(``orchestrator.sweeps``) says which stayed. A real catalog on disk; the failing rename injected at its one OS
call, as no disk here can be made to refuse one (across file systems: see test_cross_device.py)."""

from __future__ import annotations

import errno
import logging
import os
import shutil
from pathlib import Path

from orchestrator import sweeps
from orchestrator.storagehealth import StorageHealth
from storage.catalog import Catalog
from tests.conftest import failing_renames_of
from tests.storage.test_episodes import make_episode


def _strays(cat: Catalog, rng, n: int) -> list[Path]:
    """``n`` episode files no row indexes (as ingests killed before their commit leave them), sorted."""
    strays = []
    for _ in range(n):
        ep = make_episode(rng)
        path = cat.add_episode(ep).path
        strays.append(path.with_name(f"{ep.meta.episode_id[:8]}stray.mcap"))
        shutil.copyfile(path, strays[-1])
    return sorted(strays)


def _full_disk_for(monkeypatch, stuck: Path) -> None:
    """Renaming ``stuck`` fails as on a full disk (no room for one more directory entry in ``orphans/<day>/``)."""
    failing_renames_of(monkeypatch, lambda src: src == stuck, errno.ENOSPC)


def _orphan(cat: Catalog, path: Path) -> Path:
    return cat.data_dir / "orphans" / path.relative_to(cat.episodes_dir)


def test_a_stray_that_cannot_be_moved_stays_and_is_named_and_the_others_go(cat, rng, monkeypatch):
    stuck, *others = _strays(cat, rng, 3)  # the first one tried
    _full_disk_for(monkeypatch, stuck)

    swept = cat.sweep_strays()

    assert swept.unindexed == [stuck, *others] and swept.not_moved == {stuck: os.strerror(errno.ENOSPC)}
    assert stuck.is_file() and not _orphan(cat, stuck).exists()
    assert all(_orphan(cat, p).is_file() and not p.exists() for p in others)
    assert cat.strays().unindexed == [stuck] and cat.count() == 3
    monkeypatch.undo()  # room again: the next sweep takes it
    again = cat.sweep_strays()
    assert again.unindexed == [stuck] and again.not_moved == {} and _orphan(cat, stuck).is_file()
    assert not cat.strays()


def test_the_services_sweep_names_the_stray_that_stayed(tmp_path, rng, monkeypatch, caplog):
    data = tmp_path / "data"
    catalog = Catalog(data)
    stuck, free = _strays(catalog, rng, 2)
    _full_disk_for(monkeypatch, stuck)
    log = logging.getLogger("test.sweeps")

    with caplog.at_level(logging.WARNING, logger="test.sweeps"):
        sweeps.sweep_leftovers(catalog, data, StorageHealth(log), log)

    assert stuck.is_file() and _orphan(catalog, free).is_file() and not free.exists()
    assert [r.getMessage() for r in caplog.records] == [
        "moved 1 unindexed episode file(s) to orphans/ and deleted 0 staging file(s) left by a crash (none was "
        "acknowledged)",
        "cannot move the files crashed ingests left aside to orphans/ (1 unindexed episode file(s), none "
        "acknowledged); they stay where they are, unindexed, until a later sweep: "
        f"episodes/{stuck.parent.name}/{stuck.name} (No space left on device)"]
