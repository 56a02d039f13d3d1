"""Ctrl-C on a write transaction's COMMIT, or on the publish of its file before it: what committed keeps its files,
what did not leaves none.

CPython runs a Python signal handler once the C call it arrived in returns: a SIGINT that arrives while COMMIT
runs its fsync comes out as a ``KeyboardInterrupt`` raised after the commit. ``SigintAtCommit`` sends a real
SIGINT at that moment (or just before the COMMIT), through the real SQLite file; a process killed between the
rename and the commit is a real ``SIGKILL``.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

import storage.catalog
import storage.catalog_quarantine
import storage.checkpoint_files
import storage.database
from storage.catalog import Catalog
from storage.episodes import encode_episode
from tests.conftest import REPO
from tests.storage.test_episodes import make_episode


class SigintAtCommit:
    """Once ``arm``ed, the next ``COMMIT`` on a connection ``storage.database.connect`` opens gets a real
    SIGINT: right after it returns (``after=True``), or just before it runs."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self._real, self.armed, self.after, self.sent = storage.database.connect, False, True, False
        monkeypatch.setattr(storage.database, "connect", lambda path: _Interrupting(self._real(path), self))

    def arm(self, after: bool) -> None:
        self.armed, self.after = True, after

    def commit(self, conn: sqlite3.Connection, args: tuple[Any, ...]) -> sqlite3.Cursor:
        self.armed, self.sent = False, True
        if not self.after:
            signal.raise_signal(signal.SIGINT)
        cursor = conn.execute("COMMIT", *args)
        signal.raise_signal(signal.SIGINT)  # as one that arrived during the commit's fsync comes out
        return cursor


class _Interrupting:
    """A connection whose COMMIT goes through ``SigintAtCommit`` while it is armed."""

    def __init__(self, conn: sqlite3.Connection, plan: SigintAtCommit) -> None:
        self._conn, self._plan = conn, plan

    def execute(self, sql: str, *args: Any) -> sqlite3.Cursor:
        if sql == "COMMIT" and self._plan.armed:
            return self._plan.commit(self._conn, args)
        return self._conn.execute(sql, *args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._conn, name)


@pytest.fixture
def sigint(monkeypatch) -> Iterator[SigintAtCommit]:
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # Python's own: KeyboardInterrupt
    try:
        yield SigintAtCommit(monkeypatch)
    finally:
        signal.signal(signal.SIGINT, previous)


def test_an_ingest_interrupted_as_its_commit_returns_keeps_its_row_and_file(cat, rng, sigint):
    ep = make_episode(rng)
    sigint.arm(after=True)
    with pytest.raises(KeyboardInterrupt):
        cat.add_episode(ep)
    assert sigint.sent
    row = cat.get(ep.meta.episode_id)
    assert row.path.is_file() and cat.verify(ep.meta.episode_id) == ep.meta
    assert not cat.strays(min_tmp_age_s=0)


def test_an_ingest_interrupted_before_its_commit_leaves_no_row_and_no_file(cat, rng, sigint):
    ep = make_episode(rng)
    sigint.arm(after=False)
    with pytest.raises(KeyboardInterrupt):
        cat.add_episode(ep)
    assert sigint.sent and cat.find(ep.meta.episode_id) is None
    assert not list(cat.episodes_dir.rglob("*.mcap*")) and not cat.strays(min_tmp_age_s=0)
    assert not cat.add_episode(ep).duplicate  # nothing in its way


def test_a_registration_interrupted_as_its_commit_returns_keeps_its_row_and_folder(reg, sigint):
    sigint.arm(after=True)
    with pytest.raises(KeyboardInterrupt):
        reg.register(b"weights" * 10, {}, {"h1_mse": 0.1}, snapshot_id="s", eval_split_hash="h")
    assert sigint.sent
    [rec] = reg.list()
    assert reg.load_weights(rec.version) == b"weights" * 10
    assert [p.name for p in reg.models_dir.iterdir()] == [rec.version]


def test_a_registration_interrupted_before_its_commit_leaves_no_row_and_no_folder(reg, sigint):
    sigint.arm(after=False)
    with pytest.raises(KeyboardInterrupt):
        reg.register(b"weights" * 10, {}, {"h1_mse": 0.1}, snapshot_id="s", eval_split_hash="h")
    assert sigint.sent and reg.list() == [] and list(reg.models_dir.iterdir()) == []


def test_a_quarantine_interrupted_as_its_commit_returns_keeps_the_file_where_its_row_says(cat, rng, sigint):
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)
    sigint.arm(after=True)
    with pytest.raises(KeyboardInterrupt):
        cat.quarantine(ep.meta.episode_id, "operator: blurred")
    assert sigint.sent and cat.get(ep.meta.episode_id).quarantined == "operator: blurred"
    assert not row.path.exists() and (cat.data_dir / "quarantine" / row.path.parent.name / row.path.name).is_file()
    assert cat.restore(ep.meta.episode_id).quarantined == "" and cat.verify(ep.meta.episode_id) == ep.meta


def test_a_quarantine_interrupted_before_its_commit_puts_the_file_back(cat, rng, sigint):
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)
    sigint.arm(after=False)
    with pytest.raises(KeyboardInterrupt):
        cat.quarantine(ep.meta.episode_id, "operator: blurred")
    assert sigint.sent and cat.count(quarantined=True) == 0
    assert row.path.is_file() and not list((cat.data_dir / "quarantine").rglob("*.mcap"))
    assert cat.verify(ep.meta.episode_id) == ep.meta


def _sigint_after(monkeypatch: pytest.MonkeyPatch, module: object, name: str = "publish") -> None:
    """``module.<name>`` (a publish, a move) gets a real SIGINT once its rename is done: one that arrived during
    the fsync of the folder after it comes out as the call returns, before the caller can note the file moved."""
    real = getattr(module, name)

    def renamed(*args: Any) -> Any:
        done = real(*args)
        signal.raise_signal(signal.SIGINT)
        return done

    monkeypatch.setattr(module, name, renamed)


def test_an_ingest_interrupted_as_its_publish_returns_leaves_no_row_and_no_file(cat, rng, sigint, monkeypatch):
    """(The file was left in place, unindexed: a stray, where nothing had crashed.)"""
    ep = make_episode(rng)
    _sigint_after(monkeypatch, storage.catalog)
    with pytest.raises(KeyboardInterrupt):
        cat.add_episode(ep)
    assert cat.find(ep.meta.episode_id) is None
    assert not list(cat.episodes_dir.rglob("*.mcap*")) and not cat.strays(min_tmp_age_s=0)


def test_a_registration_interrupted_as_its_publish_returns_leaves_no_row_and_no_folder(reg, sigint, monkeypatch):
    _sigint_after(monkeypatch, storage.checkpoint_files)
    with pytest.raises(KeyboardInterrupt):
        reg.register(b"weights" * 10, {}, {"h1_mse": 0.1}, snapshot_id="s", eval_split_hash="h")
    assert reg.list() == [] and list(reg.models_dir.iterdir()) == []


def test_a_quarantine_interrupted_as_its_move_returns_puts_the_file_back(cat, rng, sigint, monkeypatch):
    """(The file was left in quarantine/ with its episode still in training, until a read healed it.)"""
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)
    _sigint_after(monkeypatch, storage.catalog_quarantine, "move")
    with pytest.raises(KeyboardInterrupt):
        cat.quarantine(ep.meta.episode_id, "operator: blurred")
    assert row.path.is_file() and not list((cat.data_dir / "quarantine").rglob("*.mcap"))  # (before any read)
    assert cat.count(quarantined=True) == 0 and cat.verify(ep.meta.episode_id) == ep.meta


KILLED_BEFORE_COMMIT = """
import os, signal, sys
from pathlib import Path
from storage.catalog import Catalog
kill = lambda conn: os.kill(os.getpid(), signal.SIGKILL)  # the file renamed into place, the row not committed
Catalog(sys.argv[1]).ingest_bytes(Path(sys.argv[2]).read_bytes(), in_transaction=kill)
"""


def test_an_ingest_killed_before_its_commit_leaves_a_stray_the_sweep_moves_aside(tmp_path):
    data, upload = tmp_path / "data", tmp_path / "upload.mcap"
    ep = make_episode(np.random.default_rng(5))
    upload.write_bytes(encode_episode(ep))
    cat = Catalog(data)
    done = subprocess.run([sys.executable, "-c", KILLED_BEFORE_COMMIT, str(data), str(upload)], cwd=REPO,
                          capture_output=True, text=True, timeout=60, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == -signal.SIGKILL, done.stderr
    [stray] = cat.strays().unindexed
    assert cat.find(ep.meta.episode_id) is None and stray.name == f"{ep.meta.episode_id}.mcap"
    cat.sweep_strays()
    assert not stray.exists() and (data / "orphans" / stray.parent.name / stray.name).is_file()
    assert not cat.add_episode(ep).duplicate and cat.verify(ep.meta.episode_id) == ep.meta
