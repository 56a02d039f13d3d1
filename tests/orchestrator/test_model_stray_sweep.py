"""The service's sweep of what crashed registers left (``orchestrator.sweeps``): a checkpoint folder no model row
names that cannot be moved aside stays where it is and is said, with why, and holds up none of the others (a real
catalog and registry on disk; the failing rename injected, as no disk here can be made to refuse one)."""

from __future__ import annotations

import errno
import logging

import pytest

from orchestrator import sweeps
from orchestrator.storagehealth import StorageHealth
from storage.catalog import Catalog
from storage.errors import RegistryError
from storage.models import ModelRegistry
from tests.conftest import failing_renames_of


def test_a_folder_that_cannot_be_moved_aside_is_said_and_the_others_are_moved(tmp_path, monkeypatch, caplog) -> None:
    data = tmp_path / "data"
    catalog, reg = Catalog(data), ModelRegistry(data)
    stuck, free = reg.models_dir / "m000007-0badf00d", reg.models_dir / "m000008-0badf00d"
    for folder in (stuck, free):
        folder.mkdir()
        (folder / "weights.pt").write_bytes(b"a killed register's")
    failing_renames_of(monkeypatch, lambda src: src == stuck, errno.EXDEV)
    log = logging.getLogger("test.sweeps")
    with caplog.at_level(logging.WARNING, logger="test.sweeps"):
        sweeps.sweep_leftovers(catalog, data, StorageHealth(log), log)

    assert (stuck / "weights.pt").is_file() and (reg.models_dir / ".orphans" / free.name / "weights.pt").is_file()
    assert [r.getMessage() for r in caplog.records] == [
        "moved 1 checkpoint folder(s) no model row names to models/.orphans/ (a register killed before its commit; "
        "none was acknowledged): m000008-0badf00d",
        "cannot move 1 checkpoint folder(s) no model row names to models/.orphans/ (a register killed before its "
        "commit; none was acknowledged); they stay where they are, unused, until a later sweep: m000007-0badf00d "
        "(Invalid cross-device link)"]


def test_the_staging_folders_a_killed_register_left_are_deleted_once_stale_and_said(tmp_path, caplog) -> None:
    import os
    import time

    from storage.pruning import STALE_AGE_S
    data = tmp_path / "data"
    catalog, reg = Catalog(data), ModelRegistry(data)
    old, young = reg.models_dir / ".tmp-m000003-killed", reg.models_dir / ".tmp-m000004-live"
    for folder in (old, young):
        folder.mkdir()
        (folder / "weights.pt").write_bytes(b"staged")
    then = time.time() - STALE_AGE_S - 60
    os.utime(old, (then, then))
    os.utime(old / "weights.pt", (then, then))
    log = logging.getLogger("test.sweeps")
    with caplog.at_level(logging.WARNING, logger="test.sweeps"):
        sweeps.sweep_leftovers(catalog, data, StorageHealth(log), log)

    assert not old.exists() and (young / "weights.pt").is_file()  # a younger one may be a live register's
    assert [r.getMessage() for r in caplog.records] == [
        "deleted 1 staging folder(s) a retrain or prune killed midway left in models/ (none was acknowledged): "
        ".tmp-m000003-killed"]


@pytest.mark.parametrize("link", [False, True])
def test_a_file_where_models_goes_is_one_warning_of_the_sweep(tmp_path, caplog, link) -> None:
    """The running service's sweep said so in a warning, as for any models/ it cannot list; once ModelRegistry named
    the file, its RegistryError escaped the sweep (the maintenance thread's traceback, every sweep)."""
    data = tmp_path / "data"
    catalog = Catalog(data)
    if link:  # a volume not mounted
        (data / "models").symlink_to(tmp_path / "volume")
    else:
        (data / "models").write_text("not a folder")
    log = logging.getLogger("test.sweeps")
    with caplog.at_level(logging.WARNING, logger="test.sweeps"):
        sweeps.sweep_leftovers(catalog, data, StorageHealth(log), log)

    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and said[0].startswith(f"cannot look for checkpoint folders no model row names ({data}"), said
    assert "which is not a directory" in said[0] if link else "is not a directory" in said[0], said


def test_a_registry_it_cannot_open_for_another_reason_is_still_raised(tmp_path) -> None:
    """Only a file where models/ goes is passed over: a registry refusing to open (here its database lost, in a
    directory of its own so that the catalog's sweep goes through) is raised on, as before."""
    catalog, data = Catalog(tmp_path / "data"), tmp_path / "lost"
    (data / "models" / "m000001-0badf00d").mkdir(parents=True)
    log = logging.getLogger("test.sweeps")
    with pytest.raises(RegistryError, match="catalog.sqlite is missing"):
        sweeps.sweep_leftovers(catalog, data, StorageHealth(log), log)
