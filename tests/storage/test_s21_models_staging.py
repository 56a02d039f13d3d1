"""A register killed while it writes its checkpoint (a retrain killed there: SIGKILL, its timeout) leaves a
``models/.tmp-*`` folder holding the weights; a prune killed while it deletes, a ``.prune-*`` one. The service's
periodic sweep (``ModelRegistry.sweep_strays``) deletes them once older than any live call's, as ``prune`` does,
so a service that never prunes does not keep a copy of the weights of every killed job (a real SIGKILL)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from storage.models import ModelRegistry
from storage.pruning import STALE_AGE_S
from tests.conftest import REPO

#: A register that dies as a crash does once its files are staged and fsynced, before its row is committed.
KILLED_WHILE_STAGING = """
import os, signal, sys
from storage import checkpoint_files
from storage.models import ModelRegistry

real = checkpoint_files.stage
def stage(*args):
    real(*args)
    os.kill(os.getpid(), signal.SIGKILL)
checkpoint_files.stage = stage
ModelRegistry(sys.argv[1]).register(b"the weights of a killed job" * 1000, {}, {"h1_mse": 0.1}, "snap", "split")
"""


def _aged(path: Path, seconds: float) -> None:
    then = time.time() - seconds
    os.utime(path, (then, then))


def test_the_sweep_deletes_what_killed_registers_and_prunes_left_once_stale(tmp_path: Path) -> None:
    registry = ModelRegistry(tmp_path)
    killed = subprocess.run([sys.executable, "-c", KILLED_WHILE_STAGING, str(tmp_path)], cwd=REPO,
                            capture_output=True, text=True, timeout=60)
    assert killed.returncode == -9, killed.stderr
    staged = list(registry.models_dir.glob(".tmp-*"))
    assert len(staged) == 1 and (staged[0] / "weights.pt").stat().st_size == 27000 and registry.list() == []
    half_pruned = registry.models_dir / ".prune-m000001-abcdef12-0a0b0c0d"
    live = registry.models_dir / ".tmp-a-register-writing-now"
    for folder in (half_pruned, live):
        folder.mkdir()
        (folder / "weights.pt").write_bytes(b"x" * 100)

    assert not registry.sweep_strays()  # young: they may be live calls'
    _aged(staged[0], STALE_AGE_S + 60)
    _aged(half_pruned, STALE_AGE_S + 60)
    seen = registry.sweep_strays(dry_run=True)
    assert sorted(seen.stale) == sorted([staged[0].name, half_pruned.name]) and staged[0].exists()

    swept = registry.sweep_strays()
    assert sorted(swept.stale) == sorted([staged[0].name, half_pruned.name]) and swept
    assert not staged[0].exists() and not half_pruned.exists() and live.is_dir()
    assert (swept.moved, swept.not_moved) == ([], {})
