"""A backup SIGKILLed midway: no DEST, and the hidden copy it was building is deleted by the next backup to DEST
(never one a live backup is building)."""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from storage.backup import backup
from storage.catalog import Catalog
from tests.conftest import REPO, run_cli, wait_for
from tests.storage.test_episodes import make_episode


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(2125)


def _killed_midway(data: Path, dest: Path) -> Path:
    """Runs ``activecollect backup DEST`` and SIGKILLs it once it has copied some episodes and stalls reading the
    last one (a FIFO stands in for that file: a stalled disk); returns the hidden folder it left."""
    rows = Catalog(data).list()
    last = max(rows, key=lambda r: r.path.relative_to(data).as_posix()).path  # (copied in path order: the last)
    real = last.read_bytes()
    last.unlink()
    os.mkfifo(last)
    proc = subprocess.Popen([sys.executable, "-m", "orchestrator", "backup", str(dest), "--data", str(data)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        left = wait_for(lambda: [p for p in dest.parent.glob(f".{dest.name}.backup-*")
                                 if len(list(p.rglob("*.mcap"))) == len(rows) - 1],
                        timeout=60, message="the backup to copy all but the stalled episode")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    last.unlink()
    last.write_bytes(real)
    return left[0]


def test_a_backup_killed_midway_leaves_no_dest_and_the_next_one_deletes_what_it_left(tmp_path, rng, capsys):
    """A killed backup's hidden copy (as large as the data) once stayed beside DEST for good: every backup killed
    by a timeout in a cron job left one more."""
    data, dest = tmp_path / "data", tmp_path / "backups" / "nightly"
    cat = Catalog(data)
    for _ in range(4):
        cat.add_episode(make_episode(rng))
    left = _killed_midway(data, dest)
    assert not dest.exists() and left.is_dir()

    rc, out, err = run_cli(capsys, "backup", str(dest), "--data", str(data), "--json")

    assert rc == 0 and sorted(p.name for p in dest.parent.iterdir()) == ["nightly"]
    assert json.loads(out)["swept"] == [str(left)]
    assert f"deleted {left}, left by a backup to {dest} that was killed midway" in err
    copy = Catalog(dest)
    assert copy.count() == 4
    for row in copy.list():
        copy.verify(row.episode_id)


def test_a_live_backups_folder_is_not_deleted(tmp_path, rng):
    """Two backups to one DEST at once: neither deletes the folder the other is building (locked while it lives)."""
    data, dest = tmp_path / "data", tmp_path / "b"
    Catalog(data).add_episode(make_episode(rng))
    live = tmp_path / ".b.backup-0123abcd"
    live.mkdir()
    (live / "catalog.sqlite").write_bytes(b"being written")
    fd = os.open(live, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # as a live backup holds it
        result = backup(data, dest)
    finally:
        os.close(fd)
    assert result.swept == [] and (live / "catalog.sqlite").read_bytes() == b"being written"
    assert result.episodes == 1 and not result.problems
    assert backup(data, tmp_path / "other").swept == []  # another DEST's backup takes no folder of b's
    assert live.is_dir()
