"""Checkpoint folders no registry row names: a register killed between its rename and its commit leaves one;
``sweep_strays`` and ``prune`` move it aside to ``DATA/models/.orphans/``, and never the folder of a register in
progress in another process (real processes, a real SIGKILL, the real SQLite write lock). One that cannot be
moved (another file system, a full disk) stays where it is, is said, and fails nothing: a prune frees all the
same (a real models/ on another file system; the failing call injected where none can be made to fail)."""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

import storage.database
from storage.backup import backup
from storage.catalog import Catalog
from storage.models import ModelRegistry, PruneResult, StrayFolders
from storage.pruning import STALE_AGE_S
from tests.conftest import REPO, failing_renames_of, wait_for

SPLIT = "split-aaaa"
ENV = {**os.environ, "PYTHONPATH": str(REPO)}

# A register that dies as a crash does between renaming its folder into place and committing its row.
KILLED_BEFORE_COMMIT = """
import os, signal, sys
from storage import checkpoint_files
from storage.models import ModelRegistry

real = checkpoint_files.publish
def publish(*args):
    real(*args)
    os.kill(os.getpid(), signal.SIGKILL)  # the folder renamed into place, its row not committed
checkpoint_files.publish = publish
ModelRegistry(sys.argv[1]).register(sys.argv[2].encode(), {}, {"h1_mse": 0.1}, "snap", "split-aaaa")
"""

# A register that stops between renaming its folder into place and committing its row (holding the write lock)
# until the file argv[3] exists; it says its version in argv[2] first.
PAUSED_BEFORE_COMMIT = """
import sys, time
from pathlib import Path
from storage import checkpoint_files
from storage.models import ModelRegistry

real = checkpoint_files.publish
def publish(*args):
    final = real(*args)
    Path(sys.argv[2]).write_text(final.name)
    while not Path(sys.argv[3]).exists():
        time.sleep(0.01)
    return final
checkpoint_files.publish = publish
print(ModelRegistry(sys.argv[1]).register(b"in progress", {}, {"h1_mse": 0.1}, "snap", "split-aaaa"))
"""


def _register(reg: ModelRegistry, name: str) -> str:
    return reg.register(name.encode() * 10, {}, {"h1_mse": 0.1}, "snap", SPLIT)


def _killed_register(data: Path, weights: bytes) -> str:
    """Runs a register that is killed before its commit; returns the version its folder is named."""
    done = subprocess.run([sys.executable, "-c", KILLED_BEFORE_COMMIT, str(data), weights.decode()], cwd=REPO,
                          capture_output=True, text=True, timeout=60, env=ENV)
    assert done.returncode == -signal.SIGKILL, done.stderr
    [version] = [p.name for p in (data / "models").iterdir() if hashlib.sha256(weights).hexdigest()[:8] in p.name]
    return version


def _orphan(data: Path, name: str) -> Path:
    return data / "models" / ".orphans" / name


def test_a_register_killed_before_its_commit_leaves_a_folder_that_the_sweep_moves_aside(tmp_path):
    data = tmp_path / "data"
    reg = ModelRegistry(data)
    kept = _register(reg, "kept")
    stray = _killed_register(data, b"killed before commit")
    assert (reg.models_dir / stray / "weights.pt").read_bytes() == b"killed before commit"
    assert [r.version for r in reg.list()] == [kept]  # no row names it

    assert reg.sweep_strays(dry_run=True) == StrayFolders([stray]) and (reg.models_dir / stray).is_dir()
    assert reg.sweep_strays() == StrayFolders([stray])
    assert not (reg.models_dir / stray).exists()
    assert (_orphan(data, stray) / "weights.pt").read_bytes() == b"killed before commit"  # kept, not deleted
    assert not reg.sweep_strays() and reg.load_weights(kept) == b"kept" * 10
    assert sorted(p.name for p in reg.models_dir.iterdir()) == [".orphans", kept]
    assert not (data / "orphans").exists()


def test_prune_moves_aside_the_folders_no_row_names(tmp_path):
    data = tmp_path / "data"
    reg = ModelRegistry(data)
    champion = _register(reg, "champion")
    reg.gate(champion)
    stray = _killed_register(data, b"killed before commit")

    result = reg.prune(keep=1)
    assert not (reg.models_dir / stray).exists() and (_orphan(data, stray) / "weights.pt").is_file()
    assert result.orphaned == [stray] and reg.prune(keep=1).orphaned == []
    later = _killed_register(data, b"killed later")
    assert reg.prune(keep=1, dry_run=True).orphaned == [later] and (reg.models_dir / later).is_dir()
    assert reg.champion() == champion and reg.load_weights(champion) == b"champion" * 10


def test_a_name_taken_in_orphans_gets_a_suffix(tmp_path):
    """The same weights registered under the same sequence number, killed twice: both copies are kept."""
    data = tmp_path / "data"
    reg = ModelRegistry(data)
    first = _killed_register(data, b"same bytes")
    assert reg.sweep_strays().moved == [first]
    second = _killed_register(data, b"same bytes")
    assert second == first and reg.sweep_strays().moved == [first]
    assert _orphan(data, first).is_dir() and _orphan(data, f"{first}.1").is_dir()


def test_only_version_named_folders_are_the_registrys(tmp_path):
    data = tmp_path / "data"
    reg = ModelRegistry(data)
    others = [reg.models_dir / ".tmp-0123abcd", reg.models_dir / ".prune-m000001-0123abcd-0123abcd",
              reg.models_dir / "notes", reg.models_dir / "m1-0123abcd"]
    for path in others:
        path.mkdir()
    (reg.models_dir / "m000002-0123abcd").write_bytes(b"a file, not a checkpoint folder")
    assert reg.sweep_strays() == StrayFolders()
    assert all(path.is_dir() for path in others) and (reg.models_dir / "m000002-0123abcd").is_file()
    assert not _orphan(data, "").exists()


def _waiting_for_the_write_lock(thread: threading.Thread) -> bool:
    """Whether ``thread`` is inside ``storage.database.transaction``'s ``BEGIN IMMEDIATE`` (where it waits while
    another process holds the write lock)."""
    frame = sys._current_frames().get(thread.ident)
    return frame is not None and frame.f_code is storage.database.transaction.__wrapped__.__code__


def test_a_sweep_never_takes_the_folder_of_a_register_in_progress(tmp_path):
    """The register's folder is in place and its row not yet committed when the sweep starts: the sweep waits
    for the write lock the register holds, then finds the row."""
    data, published, go = tmp_path / "data", tmp_path / "published", tmp_path / "go"
    reg = ModelRegistry(data)
    register = subprocess.Popen([sys.executable, "-c", PAUSED_BEFORE_COMMIT, str(data), str(published), str(go)],
                                cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        version = wait_for(lambda: published.exists() and published.read_text(), 60, "the register to publish")
        assert (reg.models_dir / version).is_dir() and reg.list() == []  # in place, no row yet
        swept: list[StrayFolders] = []
        sweeper = threading.Thread(target=lambda: swept.append(reg.sweep_strays()))
        sweeper.start()
        wait_for(lambda: not sweeper.is_alive() or _waiting_for_the_write_lock(sweeper), 60,
                 "the sweep to finish or wait for the write lock")
        assert sweeper.is_alive()  # waiting for the write lock the register holds
        go.touch()
        out, err = register.communicate(timeout=60)
        sweeper.join()
    finally:
        go.touch()
        if register.poll() is None:
            register.kill()
            register.wait()
    assert register.returncode == 0 and out.strip() == version, err
    assert swept == [StrayFolders()]
    assert reg.load_weights(version) == b"in progress" and not _orphan(data, "").exists()


def _champions(reg: ModelRegistry, n: int) -> list[str]:
    """``n`` models, each promoted over the one before: all but the last retired."""
    versions = []
    for i in range(n):
        version = reg.register(f"model {i}".encode() * 10, {}, {"h1_mse": 1.0 / (i + 1)}, "snap", SPLIT)
        assert reg.gate(version).promoted
        versions.append(version)
    return versions


def _refuse_moves(monkeypatch, models_dir: Path, code: int, at: str, only: str | None = None) -> None:
    """Moving a folder out of ``models_dir`` (each, or the one named ``only``) fails with ``OSError(code)`` at
    ``at``: the rename itself (EXDEV: to another file system; ENOSPC: no room for one more directory entry), or
    ``mkdir``, which on a full disk makes no folder at all (ENOSPC)."""
    if at == "mkdir":
        def mkdir(self: Path, *args, **kw) -> None:
            raise OSError(code, os.strerror(code), str(self))

        monkeypatch.setattr(Path, "mkdir", mkdir)
        return
    failing_renames_of(monkeypatch, lambda src: src.parent == models_dir and only in (None, src.name), code)


@pytest.mark.parametrize("code, at", [(errno.EXDEV, "rename"), (errno.ENOSPC, "rename"), (errno.ENOSPC, "mkdir")],
                         ids=["EXDEV-rename", "ENOSPC-rename", "ENOSPC-mkdir"])
def test_a_folder_that_cannot_be_moved_aside_stays_and_the_prune_frees_all_the_same(tmp_path, monkeypatch, code,
                                                                                    at):
    data = tmp_path / "data"
    reg = ModelRegistry(data)
    *retired, champion = _champions(reg, 3)
    stray = _killed_register(data, b"killed before commit")
    _refuse_moves(monkeypatch, reg.models_dir, code, at)

    result = reg.prune(keep=1)

    assert result.pruned == retired and result.kept == [champion] and result.freed_bytes > 0
    assert not any((reg.models_dir / v).exists() for v in retired)
    assert [m.version for m in reg.list() if m.pruned_at] == retired  # the marks committed
    assert result.orphaned == [] and result.not_moved == {stray: os.strerror(code)}
    assert (reg.models_dir / stray / "weights.pt").read_bytes() == b"killed before commit"  # where it was, whole
    assert reg.load_weights(champion) == b"model 2" * 10
    monkeypatch.undo()  # the disk has room again
    again = reg.prune(keep=1)
    assert again.pruned == [] and again.orphaned == [stray] and again.not_moved == {}
    assert (_orphan(data, stray) / "weights.pt").read_bytes() == b"killed before commit"


def test_a_sweep_moves_every_folder_it_can_and_names_the_others(tmp_path, monkeypatch):
    data = tmp_path / "data"
    reg = ModelRegistry(data)
    stuck, free = _killed_register(data, b"stuck"), _killed_register(data, b"free")
    _refuse_moves(monkeypatch, reg.models_dir, errno.EXDEV, "rename", only=stuck)

    assert reg.sweep_strays() == StrayFolders(moved=[free], not_moved={stuck: os.strerror(errno.EXDEV)})
    assert (_orphan(data, free) / "weights.pt").read_bytes() == b"free"
    assert (reg.models_dir / stuck / "weights.pt").read_bytes() == b"stuck" and not _orphan(data, stuck).exists()


def _another_file_system(than: Path) -> Path | None:
    shm = Path("/dev/shm")
    return shm if shm.is_dir() and os.access(shm, os.W_OK) and shm.stat().st_dev != than.stat().st_dev else None


def test_strays_of_a_models_folder_on_its_own_file_system_are_moved_aside_on_it(tmp_path):
    """``DATA/models`` a link to a volume of its own (big checkpoints): a rename to a folder outside it would cross
    file systems (EXDEV) and fail every prune; the folders go aside within it, and the prune frees."""
    shm = _another_file_system(tmp_path)
    if shm is None:
        pytest.skip(f"no second file system beside {tmp_path} (/dev/shm)")
    volume = Path(tempfile.mkdtemp(dir=shm))
    try:
        data = tmp_path / "data"
        data.mkdir()
        (data / "models").symlink_to(volume)
        reg = ModelRegistry(data)
        *retired, champion = _champions(reg, 3)
        stray = _killed_register(data, b"killed before commit")

        result = reg.prune(keep=1)

        assert result.pruned == retired and result.orphaned == [stray] and result.not_moved == {}
        assert (volume / ".orphans" / stray / "weights.pt").read_bytes() == b"killed before commit"
        assert sorted(p.name for p in volume.iterdir()) == [".orphans", champion]
        assert reg.load_weights(champion) == b"model 2" * 10
    finally:
        shutil.rmtree(volume, ignore_errors=True)


def test_the_folders_moved_aside_are_none_of_the_registrys(tmp_path):
    """``models/.orphans/`` is no version, no crashed call's dot folder and no row's: later sweeps and prunes leave
    it however old it is, and a backup does not copy it."""
    data = tmp_path / "data"
    Catalog(data)
    reg = ModelRegistry(data)
    [champion] = _champions(reg, 1)
    stray = _killed_register(data, b"killed before commit")
    assert reg.sweep_strays().moved == [stray]
    long_ago = time.time() - 2 * STALE_AGE_S
    for path in (_orphan(data, stray), _orphan(data, "")):
        os.utime(path, (long_ago, long_ago))

    assert not reg.sweep_strays() and reg.prune(keep=1) == PruneResult(pruned=[], kept=[champion], freed_bytes=0)
    assert (_orphan(data, stray) / "weights.pt").read_bytes() == b"killed before commit"
    copied = backup(data, tmp_path / "copy")
    assert copied.models == 1 and copied.problems == [] and not (tmp_path / "copy" / "models" / ".orphans").exists()
