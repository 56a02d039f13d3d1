"""Backups to one DEST at once: one wins and DEST is a whole, verifiable backup; the other fails at once in one
line naming the first, and neither deletes the other's work nor leaves anything beside DEST."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from storage.backup import backup
from storage.catalog import Catalog
from storage.errors import BackupError
from storage.models import ModelRegistry
from tests.conftest import REPO, run_cli, wait_for
from tests.storage.test_episodes import make_episode


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(2203)


def _filled(data: Path, rng: np.random.Generator) -> str:
    """Four episodes and two models, the second the champion; returns the champion's version."""
    cat = Catalog(data)
    evals = [cat.add_episode(make_episode(rng), split="eval").episode_id for _ in range(2)]
    for _ in range(2):
        cat.add_episode(make_episode(rng))
    split = cat.pin_eval_split(evals, {"image_size": 16})
    reg = ModelRegistry(data)
    for mse in (0.04, 0.02):
        version = reg.register(rng.bytes(200_000), {"members": 2}, {"h1_mse": mse}, snapshot_id="snap",
                               eval_split_hash=split)
        reg.gate(version)
    return version


def _backup_proc(data: Path, dest: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "orchestrator", "backup", str(dest), "--data", str(data)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                            env={**os.environ, "PYTHONPATH": str(REPO)})


@contextmanager
def _stalled_last_episode(data: Path) -> Iterator[tuple[int, Path, bytes]]:
    """The episode a backup copies last becomes a FIFO (a stalled disk): a backup copies every other file, then
    waits there until the test writes its bytes in. Yields (files before it, its path, its bytes); puts it back."""
    rows = Catalog(data).list()
    last = max(rows, key=lambda r: r.path.relative_to(data).as_posix()).path  # (copied in path order: the last)
    real = last.read_bytes()
    last.unlink()
    os.mkfifo(last)
    try:
        yield len(rows) - 1, last, real
    finally:
        last.unlink()
        last.write_bytes(real)


def _building(dest: Path, episodes: int) -> list[Path]:
    """The hidden folders beside ``dest`` holding ``episodes`` episode files."""
    return [p for p in dest.parent.glob(f".{dest.name}.backup-*")
            if p.is_dir() and len(list(p.rglob("*.mcap"))) == episodes]


def _assert_whole(dest: Path, champion: str) -> None:
    copy = Catalog(dest)
    assert copy.count() == 4
    for row in copy.list():
        copy.verify(row.episode_id)
    reg = ModelRegistry(dest)
    assert reg.champion() == champion and reg.load_weights(champion)


def test_two_backups_started_at_once_to_one_dest_one_wins_the_other_fails_at_once_naming_it(tmp_path, rng):
    """Both copied everything (an hours-long copy of a large directory, twice the disk), then the second to finish
    failed with "cannot write the backup at DEST: Directory not empty"; here the second fails before it copies
    anything, while the first is still copying, and names it."""
    data, dest = tmp_path / "data", tmp_path / "backups" / "b"
    champion = _filled(data, rng)
    dest.parent.mkdir()
    with _stalled_last_episode(data) as (before, fifo, real):
        procs = [_backup_proc(data, dest), _backup_proc(data, dest)]
        try:
            loser = wait_for(lambda: next((p for p in procs if p.poll() is not None), None), timeout=60,
                             message="one of the two backups to give up while the other copies")
            winner = next(p for p in procs if p is not loser)
            building = wait_for(lambda: _building(dest, before), timeout=60, message="the winner's copy")
            assert winner.poll() is None and not dest.exists()
            out, err = loser.communicate()
            assert loser.returncode == 1 and out == ""
            # (the pid, unless the loser read the lock file between the winner's flock and its write of the pid)
            named = [[f"activecollect: backup failed, nothing written at {dest}: another backup to {dest} is running"
                      f"{pid}; wait for it to finish, or back up to another DEST"]
                     for pid in (f" (pid {winner.pid})", "")]
            assert err.strip().splitlines() in named, err
            assert sorted(p.name for p in dest.parent.iterdir()) == sorted([building[0].name, ".b.backup.lock"])
            with open(fifo, "wb") as f:  # the stalled disk answers: the winner goes on
                f.write(real)
            out, err = winner.communicate(timeout=60)
        finally:
            for proc in procs:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
    assert winner.returncode == 0, err
    assert out.startswith("backed up 4 episodes and 2 checkpoints")
    assert sorted(p.name for p in dest.parent.iterdir()) == ["b"]  # no lock file, no hidden folder left
    _assert_whole(dest, champion)


def test_a_killed_backups_lock_and_folder_do_not_stop_the_next_backup(tmp_path, rng, capsys):
    """A backup SIGKILLed midway leaves its lock file (its pid in it) and its hidden folder: the next backup to
    DEST is not refused (the kernel let go of the lock), deletes both and leaves only DEST."""
    data, dest = tmp_path / "data", tmp_path / "b"
    champion = _filled(data, rng)
    with _stalled_last_episode(data) as (before, _, _):
        proc = _backup_proc(data, dest)
        try:
            left = wait_for(lambda: _building(dest, before), timeout=60, message="the backup to stall")[0]
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.communicate(timeout=30)
    lock = tmp_path / ".b.backup.lock"
    assert lock.read_text() == f"{proc.pid}\n" and not dest.exists()

    rc, out, err = run_cli(capsys, "backup", str(dest), "--data", str(data))

    assert rc == 0, err
    assert f"deleted {left}, left by a backup to {dest} that was killed midway" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b", "data"]
    _assert_whole(dest, champion)


def test_a_dest_written_by_something_else_meanwhile_is_left_as_it_is_and_the_backup_says_so(tmp_path, rng):
    """A process that takes no lock (a backup by older code, a copy by hand) fills DEST while the backup copies: the
    backup fails in one clear line (it said "Directory not empty"), leaves DEST as that process made it and deletes
    its own copy."""
    data, dest = tmp_path / "data", tmp_path / "b"
    _filled(data, rng)

    def other_writer(done: int, total: int) -> None:
        if done == 1:
            dest.mkdir()
            (dest / "theirs.txt").write_text("theirs")

    with pytest.raises(BackupError) as caught:
        backup(data, dest, progress=other_writer)

    assert str(caught.value) == (f"{dest} appeared while this backup ran: another backup or process wrote it; "
                                 "this backup is discarded")
    assert sorted(p.name for p in dest.iterdir()) == ["theirs.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b", "data"]


def test_a_sweep_takes_only_its_own_dests_folders(tmp_path, rng):
    """A backup to ``b`` once deleted what a killed backup to ``b.backup-x`` left (its name starts the same),
    and named it as its own."""
    data = tmp_path / "data"
    _filled(data, rng)
    others = tmp_path / ".b.backup-x.backup-0123abcd"
    others.mkdir()
    (others / "catalog.sqlite").write_bytes(b"theirs")
    own = tmp_path / ".b.backup-89abcdef"
    own.mkdir()

    result = backup(data, tmp_path / "b")

    assert result.swept == [own] and not own.exists()
    assert (others / "catalog.sqlite").read_bytes() == b"theirs"
