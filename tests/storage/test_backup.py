"""Backups of a data directory: a consistent copy while writers go on, damaged files named, nothing half-made."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from storage.backup import backup, check_dest
from storage.catalog import Catalog
from storage.database import DB_NAME
from storage.errors import BackupError, EpisodeError, PrunedCheckpointError
from storage.models import ModelRegistry
from storage.quarantine import quarantine_path
from storage.queue import NewRequest, RequestQueue
from tests.conftest import REPO, run_cli, wait_for
from tests.storage.test_episodes import make_episode

SPLIT_PARAMS = {"image_size": 16}


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(23)


def _filled(data: Path, rng: np.random.Generator) -> dict:
    """A data directory with train and eval episodes, a pinned split, three models (one pruned) and
    a queued request; returns what to compare a backup with."""
    cat = Catalog(data)
    train = [cat.add_episode(make_episode(rng)).episode_id for _ in range(3)]
    evals = [cat.add_episode(make_episode(rng), split="eval").episode_id for _ in range(2)]
    split_hash = cat.pin_eval_split(evals, SPLIT_PARAMS)
    reg = ModelRegistry(data)
    versions = []
    for mse in (0.04, 0.03, 0.02):
        v = reg.register(f"weights {mse}".encode() * 50, {"members": 2}, {"h1_mse": mse},
                         snapshot_id="snap", eval_split_hash=split_hash)
        reg.gate(v)
        versions.append(v)
    reg.prune(keep=2)
    queue = RequestQueue(data / DB_NAME)
    queue.enqueue(NewRequest(task="push", shape="T", start_state={"shape": "T", "agent": [1.0, 2.0]}))
    queue.close()
    return {"train": train, "eval": evals, "split": split_hash, "versions": versions}


def test_a_backup_is_a_data_directory_with_everything_in_it(tmp_path, rng) -> None:
    data, dest = tmp_path / "data", tmp_path / "backups" / "b1"
    want = _filled(data, rng)

    result = backup(data, dest)

    assert result.problems == [] and result.episodes == 5 and result.models == 2
    assert result.bytes == sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())
    assert not [p for p in dest.parent.iterdir() if p.name.startswith(".")]  # no staging left
    cat = Catalog(dest)
    assert sorted(r.episode_id for r in cat.list()) == sorted(want["train"] + want["eval"])
    for row in cat.list():
        cat.verify(row.episode_id)
    assert cat.eval_split().hash == want["split"]
    reg = ModelRegistry(dest)
    first, second, third = want["versions"]
    assert reg.champion() == third and reg.load_weights(second) == b"weights 0.03" * 50
    with pytest.raises(PrunedCheckpointError):
        reg.load_weights(first)
    assert not (dest / "models" / first).exists()
    assert RequestQueue(dest / DB_NAME).counts()["queued"] == 1


def test_a_backup_taken_while_episodes_arrive_is_consistent(tmp_path, rng) -> None:
    data, dest = tmp_path / "data", tmp_path / "b"
    cat = Catalog(data)
    episodes = [make_episode(rng) for _ in range(60)]
    for ep in episodes[:20]:
        cat.add_episode(ep)
    added, stop = [20], threading.Event()

    def writer() -> None:
        for ep in episodes[20:]:
            if stop.is_set():
                return
            cat.add_episode(ep)
            added[0] += 1

    started = threading.Event()

    def progress(done: int, total: int) -> None:
        started.set()
        wait_for(lambda: added[0] > 20 or added[0] == len(episodes), message="an episode added mid-backup")

    thread = threading.Thread(target=writer)
    thread.start()
    try:
        result = backup(data, dest, progress=progress)
    finally:
        stop.set()
        thread.join()
    assert started.is_set() and result.problems == []
    copy = Catalog(dest)
    rows = copy.list()
    assert 20 <= len(rows) == result.episodes
    for row in rows:
        copy.verify(row.episode_id)
    on_disk = {p.relative_to(dest).as_posix() for p in (dest / "episodes").rglob("*.mcap")}
    assert on_disk == {r.path.relative_to(dest).as_posix() for r in rows}  # every file indexed, no stray
    assert not copy.strays().unindexed


def test_a_damaged_file_is_named_and_the_rest_is_backed_up(tmp_path, rng, capsys) -> None:
    data = tmp_path / "data"
    want = _filled(data, rng)
    bad = Catalog(data).get(want["train"][1]).path
    raw = bytearray(bad.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    bad.write_bytes(bytes(raw))
    weights = data / "models" / want["versions"][2] / "weights.pt"
    weights.write_bytes(weights.read_bytes()[:-1])

    rc, out, err = run_cli(capsys, "backup", str(tmp_path / "b"), "--data", str(data), "--json")

    assert rc == 1 and "could not be copied intact" in err
    report = json.loads(out)
    assert report["episodes"] == 4 and report["models"] == 1 and len(report["problems"]) == 2
    assert want["versions"][2] in report["problems"][0]  # the checkpoints are copied first
    assert want["train"][1] in report["problems"][1] and "sha256" in report["problems"][1]
    copy = Catalog(tmp_path / "b")
    with pytest.raises(EpisodeError, match="missing"):
        copy.verify(want["train"][1])
    copy.verify(want["train"][0])
    assert not (tmp_path / "b" / "models" / want["versions"][2]).exists()


def test_a_model_pruned_during_the_backup_is_pruned_in_it(tmp_path, rng) -> None:
    data, dest = tmp_path / "data", tmp_path / "b"
    want = _filled(data, rng)
    reg = ModelRegistry(data)
    worse = reg.register(b"worse" * 50, {}, {"h1_mse": 0.5}, snapshot_id="snap", eval_split_hash=want["split"])
    assert not reg.gate(worse).promoted
    calls = []

    def prune_once(done: int, total: int) -> None:  # after the snapshot, before the models are copied
        calls.append((done, total))
        if len(calls) == 1:
            assert reg.prune(keep=2).pruned == [worse]

    result = backup(data, dest, progress=prune_once)

    assert result.problems == [] and result.models == 2
    assert calls == [(n, 8) for n in range(9)]  # one snapshot: a model the copy does not need is no reason to retake
    copy = ModelRegistry(dest)
    assert copy.get(worse).pruned_at is not None and not (dest / "models" / worse).exists()
    assert copy.load_weights(want["versions"][2]) and copy.load_weights(want["versions"][1])


def test_a_champion_pruned_during_the_backup_is_backed_up_as_the_source_is_now(tmp_path, rng) -> None:
    """A retrain that promotes and prunes (``retrain --keep-models 1``) after the snapshot takes the
    snapshot's champion and its rollback chain away: the backup retakes it, so it serves the new champion."""
    data, dest = tmp_path / "data", tmp_path / "b"
    want = _filled(data, rng)
    reg = ModelRegistry(data)
    new = []

    def retrain_once(done: int, total: int) -> None:  # after the snapshot, before the models are copied
        if not new:
            new.append(reg.register(b"new" * 50, {}, {"h1_mse": 0.001}, snapshot_id="snap",
                                    eval_split_hash=want["split"]))
            assert reg.gate(new[0]).promoted
            assert reg.prune(keep=1).pruned == want["versions"][1:]

    result = backup(data, dest, progress=retrain_once)

    assert result.problems == [] and result.models == 1 and result.episodes == 5
    copy = ModelRegistry(dest)
    assert copy.champion() == new[0] and copy.load_weights(new[0]) == b"new" * 50
    assert copy.weights_problem(new[0]) is None
    assert all(copy.get(v).pruned_at is not None for v in want["versions"])
    assert sorted(p.name for p in (dest / "models").iterdir()) == [new[0]]


def test_a_champion_pruned_after_every_snapshot_is_named(tmp_path, rng, capsys) -> None:
    """When retrains outrun every retake, the backup says its champion cannot serve (exit 1)."""
    from storage import backup as backup_module
    data, dest = tmp_path / "data", tmp_path / "b"
    want = _filled(data, rng)
    reg = ModelRegistry(data)
    new: list[str] = []

    def retrain_while_models_wait(done: int, total: int) -> None:
        if total - done > len(want["train"] + want["eval"]):  # checkpoints are yet to be copied
            version = reg.register(f"new {len(new)}".encode() * 50, {}, {"h1_mse": 0.01 / (len(new) + 2)},
                                   snapshot_id="snap", eval_split_hash=want["split"])
            assert reg.gate(version).promoted and reg.prune(keep=1).pruned
            new.append(version)

    result = backup(data, dest, progress=retrain_while_models_wait)

    copy = ModelRegistry(dest)
    champion = copy.champion()
    assert len(result.problems) == 1 and champion in result.problems[0] and "its champion" in result.problems[0]
    assert champion == new[-2] and copy.weights_problem(champion) is not None
    assert len(new) == backup_module.SNAPSHOT_TRIES and result.models == 0 and result.episodes == 5


def test_the_destination_must_be_new_and_outside(tmp_path, rng, capsys) -> None:
    data = tmp_path / "data"
    _filled(data, rng)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("keep me")
    (tmp_path / "afile").write_text("keep me")
    for dest, why in ((tmp_path / "full", "not empty"), (tmp_path / "afile", "is a file"),
                      (data / "inside", "inside the data directory"),
                      (tmp_path / "afile" / "b" / "c", f"{tmp_path / 'afile'} is a file, so")):
        with pytest.raises(BackupError, match=why):
            check_dest(data, dest)
        rc, out, err = run_cli(capsys, "backup", str(dest), "--data", str(data))
        assert rc == 2 and why in err and err.count("\n") == 1
    assert (tmp_path / "full" / "x").read_text() == "keep me" and (tmp_path / "afile").read_text() == "keep me"
    assert not (data / "inside").exists()
    rc, _, err = run_cli(capsys, "backup", str(tmp_path / "b"), "--data", str(tmp_path / "nothing"))
    assert rc == 2 and "no catalog" in err and not (tmp_path / "b").exists()
    (tmp_path / "empty").mkdir()
    rc, out, _ = run_cli(capsys, "backup", str(tmp_path / "empty"), "--data", str(data))
    assert rc == 0 and "backed up 5 episodes and 2 checkpoints" in out
    assert Catalog(tmp_path / "empty").count() == 5


def _limit_file_size() -> None:  # in the child: writes past 64 KiB fail with EFBIG, as on a full disk
    import resource
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))


def test_a_backup_that_cannot_be_written_leaves_nothing(tmp_path, rng) -> None:
    data = tmp_path / "data"
    cat = Catalog(data)
    for _ in range(3):
        cat.add_episode(make_episode(rng, steps=40, size=32))  # ~120 KiB each: past the child's limit
    dest = tmp_path / "b"

    proc = subprocess.run([sys.executable, "-m", "orchestrator", "backup", str(dest), "--data", str(data)],
                          capture_output=True, text=True, timeout=120, preexec_fn=_limit_file_size,
                          env={**os.environ, "PYTHONPATH": str(REPO)})

    assert proc.returncode == 1, proc.stderr
    assert "backup failed, nothing written" in proc.stderr and "Traceback" not in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    for row in cat.list():
        cat.verify(row.episode_id)


def test_a_data_directory_from_before_pruning_is_backed_up_at_the_current_schema(tmp_path, rng) -> None:
    from storage.database import connection, ensure_schema
    from storage.errors import RegistryError
    from storage.models import _MIGRATIONS
    data = tmp_path / "old"
    Catalog(data).add_episode(make_episode(rng))
    weights = b"old weights" * 20
    (data / "models" / "m000001-00000000").mkdir(parents=True)
    (data / "models" / "m000001-00000000" / "weights.pt").write_bytes(weights)
    with connection(data / DB_NAME, RegistryError) as conn:  # the registry's tables as the first release made them
        ensure_schema(conn, "models", _MIGRATIONS[:1])
        conn.execute("INSERT INTO models (version, seq, status, reason, parent, snapshot_id, eval_split_hash, "
                     "weights_sha256, size_bytes, created, updated, metrics, config) VALUES "
                     "('m000001-00000000', 1, 'candidate', '', NULL, 's', 'h', ?, ?, 't', 't', '{}', '{}')",
                     (hashlib.sha256(weights).hexdigest(), len(weights)))

    result = backup(data, tmp_path / "b")

    assert result.problems == [] and (result.episodes, result.models) == (1, 1)
    assert ModelRegistry(tmp_path / "b").load_weights("m000001-00000000") == weights
    with connection(data / DB_NAME, RegistryError) as conn:  # the source itself is left as it was
        assert "pruned_at" not in {r["name"] for r in conn.execute("PRAGMA table_info(models)")}


def test_quarantined_episodes_are_backed_up_as_quarantined(tmp_path, rng) -> None:
    data, dest = tmp_path / "data", tmp_path / "b"
    want = _filled(data, rng)
    cat = Catalog(data)
    kept = cat.quarantine(want["train"][0], "operator: blurred")
    cat.get(want["train"][1]).path.unlink()
    cat.quarantine(want["train"][1], "found by a training job: missing")

    result = backup(data, dest)

    assert result.problems == [] and result.episodes == 3  # one train, two eval
    copy = Catalog(dest)
    assert {r.episode_id: r.quarantined for r in copy.list(quarantined=True)} == {
        want["train"][0]: "operator: blurred", want["train"][1]: "found by a training job: missing"}
    assert copy.restore(want["train"][0]).quarantined == "" and copy.verify(want["train"][0])
    assert not kept.path.exists()  # the source is as it was


def test_an_episode_quarantined_during_the_backup_is_quarantined_in_it(tmp_path, rng) -> None:
    data, dest = tmp_path / "data", tmp_path / "b"
    want = _filled(data, rng)
    cat = Catalog(data)
    last = max((cat.get(i) for i in want["train"]), key=lambda r: str(r.path)).episode_id

    def quarantine_once(done: int, total: int) -> None:  # after the snapshot, before that file is copied
        if done == 1:
            cat.quarantine(last, "operator: wrong object")

    result = backup(data, dest, progress=quarantine_once)

    assert result.problems == []
    copy = Catalog(dest)
    assert copy.get(last).quarantined == "operator: wrong object"
    assert copy.restore(last).quarantined == "" and copy.verify(last)


def test_a_source_that_cannot_say_whether_an_episode_is_quarantined_fails_the_backup(tmp_path, rng,
                                                                                      monkeypatch) -> None:
    """Only a catalog without a quarantine table means 'not quarantined'; a busy or failing source is not an
    answer (the copy would have put an episode quarantined during the backup back in training)."""
    import sqlite3
    from storage import backup as backup_module
    data, dest = tmp_path / "data", tmp_path / "b"
    want = _filled(data, rng)
    cat = Catalog(data)
    last = max((cat.get(i) for i in want["train"]), key=lambda r: str(r.path)).episode_id

    def locked(conn, episode_id):
        raise sqlite3.OperationalError("database is locked")

    def quarantine_once(done: int, total: int) -> None:  # after the snapshot, before that file is copied
        if done == 1:
            cat.quarantine(last, "operator: wrong object")
            # The backup's look finds the source busy (a real lock would only show after the busy timeout);
            # patched for the whole process, which is safe here: nothing else reads quarantines after this.
            monkeypatch.setattr(backup_module.quarantines, "find", locked)

    with pytest.raises(BackupError, match="database is locked"):
        backup(data, dest, progress=quarantine_once)
    assert not dest.exists()


def test_an_episode_restored_during_the_backup_is_in_training_in_it(tmp_path, rng) -> None:
    data, dest = tmp_path / "data", tmp_path / "b"
    want = _filled(data, rng)
    cat = Catalog(data)
    last = max((cat.get(i) for i in want["train"]), key=lambda r: str(r.path)).episode_id
    cat.quarantine(last, "operator: suspect")

    def restore_once(done: int, total: int) -> None:  # after the snapshot, before that file is copied
        if done == 1:
            cat.restore(last)

    result = backup(data, dest, progress=restore_once)

    assert result.problems == [] and result.episodes == 5
    copy = Catalog(dest)
    assert copy.get(last).quarantined == "" and copy.verify(last)


def test_a_file_left_in_quarantine_by_a_crash_is_backed_up(tmp_path, rng) -> None:
    from tests.storage.test_quarantine import _killed_in_quarantine
    data, dest = tmp_path / "data", tmp_path / "b"
    want = _filled(data, rng)
    cat = Catalog(data)
    _killed_in_quarantine(cat, want["train"][0])  # the file moved, its row not quarantined

    result = backup(data, dest)

    assert result.problems == [] and result.episodes == 5
    assert Catalog(dest).verify(want["train"][0])


@pytest.mark.parametrize("when", ["before", "after"])
def test_an_episode_restored_while_the_backup_looks_for_its_file_is_in_training_in_it(tmp_path, rng, monkeypatch,
                                                                                       when) -> None:
    """An episode quarantined after the snapshot, then restored while the backup looks for its file in
    ``quarantine/`` (``before`` it reads it there: it is gone; ``after``: it was there). Before, the copy had it
    quarantined with no file and no word said, or named it NOT COPIED while the source had it intact."""
    data, dest = tmp_path / "data", tmp_path / "b"
    want = _filled(data, rng)
    cat = Catalog(data)
    last = max((cat.get(i) for i in want["train"]), key=lambda r: str(r.path)).episode_id
    kept = data / quarantine_path(cat.get(last).path.relative_to(data).as_posix())
    restored, real_read = [], Path.read_bytes

    def restore_once() -> None:
        if not restored:
            restored.append(True)  # (first: the restore reads files too)
            cat.restore(last)

    def read_bytes(path: Path) -> bytes:  # the restore lands right before, or right after, that read
        if path == kept and when == "before":
            restore_once()
        data_read = real_read(path)
        if path == kept and when == "after":
            restore_once()
        return data_read

    def quarantine_once(done: int, total: int) -> None:  # after the snapshot, before that file is copied
        if done == 1:
            cat.quarantine(last, "operator: suspect")
            monkeypatch.setattr(Path, "read_bytes", read_bytes)

    result = backup(data, dest, progress=quarantine_once)

    assert restored and cat.get(last).quarantined == ""
    assert result.problems == [] and result.episodes == 5
    copy = Catalog(dest)
    assert copy.get(last).quarantined == "" and copy.verify(last)
    assert not list((dest / "quarantine").rglob("*.mcap"))


def test_a_quarantined_episode_whose_kept_file_is_missing_is_named(tmp_path, rng) -> None:
    data, dest = tmp_path / "data", tmp_path / "b"
    want = _filled(data, rng)
    cat = Catalog(data)
    kept = data / quarantine_path(cat.get(want["train"][0]).path.relative_to(data).as_posix())
    cat.quarantine(want["train"][0], "operator: blurred")
    kept.unlink()

    result = backup(data, dest)

    assert len(result.problems) == 1 and want["train"][0] in result.problems[0]
    assert f"{kept} is missing" in result.problems[0] and result.episodes == 4
    assert Catalog(dest).get(want["train"][0]).quarantined == "operator: blurred"  # as in the source
