"""The catalog: idempotent, atomic ingest; queries; the pinned eval split and snapshots."""

from __future__ import annotations

import os
import sqlite3
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from storage import episode_reader, episodes, files
from storage.catalog import Catalog
from storage.models import ModelRegistry
from storage.queue import RequestQueue
from storage.database import connect, ensure_schema, transaction
from storage.errors import (
    CatalogError,
    CorruptEpisodeError,
    EpisodeError,
    ForeignFileError,
    RegistryError,
    TruncatedEpisodeError,
)
from tests.conftest import wait_for
from tests.storage.test_episodes import assert_same, make_episode


def mcap_files(cat: Catalog) -> list[str]:
    return sorted(str(p.relative_to(cat.data_dir)) for p in cat.episodes_dir.rglob("*.mcap"))


def all_files(cat: Catalog) -> list[str]:
    return sorted(str(p.relative_to(cat.episodes_dir)) for p in cat.episodes_dir.rglob("*") if p.is_file())


def test_layout_and_wal(cat):
    assert cat.db_path == cat.data_dir / "catalog.sqlite" and cat.db_path.exists()
    assert cat.episodes_dir.is_dir()
    with connect(cat.db_path) as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        versions = dict(conn.execute("SELECT component, version FROM schema_versions").fetchall())
    assert versions == {"catalog": 3}
    Catalog(cat.data_dir)  # reopening is harmless


def test_add_and_load_round_trip(cat, rng):
    ep = make_episode(rng, steps=5, request_id="req-1", worker_id="w-1", model_version="v3")
    res = cat.add_episode(ep)
    assert not res.duplicate
    assert res.path == cat.data_dir / "episodes" / "2026-11-21" / f"{ep.meta.episode_id}.mcap"
    assert res.sha256 == files.sha256_hex(res.path.read_bytes())
    row = cat.get(ep.meta.episode_id)
    assert (row.frames, row.task, row.shape, row.split) == (5, "push", "T", "train")
    assert (row.request_id, row.worker_id, row.model_version) == ("req-1", "w-1", "v3")
    assert row.size_bytes == res.path.stat().st_size and row.path == res.path
    assert row.created == ep.meta.created
    assert_same(cat.load(ep.meta.episode_id), ep)
    assert cat.meta(ep.meta.episode_id) == ep.meta
    assert cat.verify(ep.meta.episode_id) == ep.meta


def test_ingest_is_idempotent(cat, rng, tmp_path):
    ep = make_episode(rng)
    src = tmp_path / "elsewhere.mcap"
    episodes.write_episode(src, ep)
    first = cat.ingest_file(src)
    again = cat.ingest_file(src)
    bytes_again = cat.ingest_bytes(src.read_bytes(), expected_sha256=first.sha256)
    added_again = cat.add_episode(ep)
    assert not first.duplicate and again.duplicate and bytes_again.duplicate and added_again.duplicate
    assert cat.count() == 1 and len(mcap_files(cat)) == 1


def test_same_id_different_bytes_refused(cat, rng):
    ep = make_episode(rng)
    cat.add_episode(ep)
    ep.frames[0, 0, 0, 0] ^= 1
    with pytest.raises(CatalogError, match="already indexed with sha256 .* refusing different bytes"):
        cat.add_episode(ep)
    assert cat.count() == 1


def test_same_episode_other_split_refused(cat, rng):
    ep = make_episode(rng)
    cat.add_episode(ep)
    with pytest.raises(CatalogError, match="already indexed in split 'train', not 'eval'"):
        cat.add_episode(ep, split="eval")


@pytest.mark.parametrize("damage,error", [
    (lambda d: d[: len(d) // 2], TruncatedEpisodeError),
    (lambda d: d[:100] + bytes([d[100] ^ 0x10]) + d[101:], CorruptEpisodeError),
    (lambda d: b"PK\x03\x04 a zip file, not an episode" * 4, ForeignFileError),
])
def test_bad_file_leaves_no_row_and_no_file(cat, rng, damage, error):
    data = damage(episodes.encode_episode(make_episode(rng)))
    with pytest.raises(error):
        cat.ingest_bytes(data)
    assert cat.count() == 0 and all_files(cat) == []


def test_sha_mismatch_refused(cat, rng):
    data = episodes.encode_episode(make_episode(rng))
    with pytest.raises(CorruptEpisodeError, match="sha256 mismatch: expected 00"):
        cat.ingest_bytes(data, expected_sha256="00" * 32)
    assert cat.count() == 0 and all_files(cat) == []


def test_ingest_with_caller_verified_info_indexes_the_same_row(cat, rng, tmp_path):
    data = episodes.encode_episode(make_episode(rng))
    info = episode_reader.inspect_episode(data)  # what the service learns reading an upload once
    res = cat.ingest_bytes(data, expected_sha256=files.sha256_hex(data), verified=info)
    plain_cat = Catalog(tmp_path / "plain")
    plain = plain_cat.ingest_bytes(data)  # the catalog verifies on its own
    fields = ("episode_id", "sha256", "frames", "task", "shape", "request_id", "created", "size_bytes")
    assert [getattr(cat.get(res.episode_id), f) for f in fields] == \
        [getattr(plain_cat.get(plain.episode_id), f) for f in fields]
    assert cat.meta(res.episode_id) == plain_cat.meta(plain.episode_id)
    assert_same(cat.load(res.episode_id), episode_reader.read_episode(data))
    other = episodes.encode_episode(make_episode(rng))
    with pytest.raises(CorruptEpisodeError, match="sha256 mismatch"):  # the hash is still checked
        cat.ingest_bytes(other, expected_sha256="00" * 32, verified=episode_reader.inspect_episode(other))
    assert cat.count() == 1


def test_ingest_file_errors_name_the_path(cat, rng, tmp_path):
    bad = tmp_path / "half.mcap"
    bad.write_bytes(episodes.encode_episode(make_episode(rng))[:300])
    with pytest.raises(TruncatedEpisodeError, match="half.mcap"):
        cat.ingest_file(bad)
    with pytest.raises(CatalogError, match="missing.mcap: no such file"):
        cat.ingest_file(tmp_path / "missing.mcap")


def test_in_transaction_runs_in_the_same_transaction(cat, rng):
    with connect(cat.db_path) as conn:
        conn.execute("CREATE TABLE done (episode_id TEXT)")
    seen = []

    def hook(conn: sqlite3.Connection) -> None:
        assert conn.in_transaction
        seen.append(conn.execute("SELECT COUNT(*) FROM episodes").fetchone()[0])
        conn.execute("INSERT INTO done VALUES ('x')")

    res = cat.ingest_bytes(episodes.encode_episode(make_episode(rng)), in_transaction=hook)
    assert seen == [1]  # the row is visible to the hook, inside the transaction
    with connect(cat.db_path) as conn:
        assert conn.execute("SELECT COUNT(*) FROM done").fetchone()[0] == 1
    assert res.path.exists()


def test_in_transaction_failure_rolls_everything_back(cat, rng):
    with connect(cat.db_path) as conn:
        conn.execute("CREATE TABLE done (episode_id TEXT)")

    class Refused(Exception):
        pass

    def hook(conn: sqlite3.Connection) -> None:
        conn.execute("INSERT INTO done VALUES ('x')")
        raise Refused("stale lease")

    ep = make_episode(rng)
    with pytest.raises(Refused, match="stale lease"):
        cat.ingest_bytes(episodes.encode_episode(ep), in_transaction=hook)
    assert cat.count() == 0 and all_files(cat) == []
    with connect(cat.db_path) as conn:
        assert conn.execute("SELECT COUNT(*) FROM done").fetchone()[0] == 0
    # nothing stuck: the same bytes go in afterwards
    assert not cat.add_episode(ep).duplicate


def test_duplicate_does_not_run_hook(cat, rng):
    data = episodes.encode_episode(make_episode(rng))
    calls = []
    cat.ingest_bytes(data, in_transaction=lambda conn: calls.append(1))
    assert cat.ingest_bytes(data, in_transaction=lambda conn: calls.append(2)).duplicate
    assert calls == [1]


def test_leftover_temp_files_are_ignored(cat, rng):
    ep = make_episode(rng)
    day = cat.episodes_dir / "2026-11-21"
    day.mkdir(parents=True)
    (day / f".{ep.meta.episode_id}.mcap.abc123.tmp").write_bytes(b"half a file")
    res = cat.add_episode(ep)
    assert [r.episode_id for r in cat.list()] == [ep.meta.episode_id]
    assert cat.verify(ep.meta.episode_id) == ep.meta
    assert res.path.exists()


def test_duplicate_restores_a_lost_file(cat, rng):
    ep = make_episode(rng)
    res = cat.add_episode(ep)
    res.path.unlink()
    with pytest.raises(EpisodeError, match="is missing"):
        cat.verify(ep.meta.episode_id)
    assert cat.add_episode(ep).duplicate
    assert cat.verify(ep.meta.episode_id) == ep.meta


def test_damaged_file_on_disk_detected(cat, rng):
    ep = make_episode(rng)
    res = cat.add_episode(ep)
    data = bytearray(res.path.read_bytes())
    data[200] ^= 4
    res.path.write_bytes(bytes(data))
    with pytest.raises(CorruptEpisodeError, match="sha256 is .* the catalog recorded"):
        cat.verify(ep.meta.episode_id)
    with pytest.raises(CorruptEpisodeError):
        cat.load(ep.meta.episode_id)


@pytest.mark.parametrize("episode_id", ["../../etc/passwd", "abc\n"])  # (the second passed a `$` check)
def test_unsafe_episode_id_refused(cat, rng, episode_id):
    ep = make_episode(rng)
    ep.meta.episode_id = episode_id
    with pytest.raises(CatalogError, match="not a safe file name"):
        cat.add_episode(ep)
    assert all_files(cat) == []


def test_queries(cat, rng):
    eps = [make_episode(rng, shape=s) for s in ("T", "box", "T", "disk")]
    for ep in eps[:3]:
        cat.add_episode(ep)
    cat.add_episode(eps[3], split="eval")
    ids = [e.meta.episode_id for e in eps]
    assert [r.episode_id for r in cat.list()] == ids
    assert [r.episode_id for r in cat.list(newest_first=True, limit=2)] == ids[::-1][:2]
    assert [r.episode_id for r in cat.list(shape="T")] == [ids[0], ids[2]]
    assert [r.episode_id for r in cat.list(split="eval")] == [ids[3]]
    assert cat.count() == 4 and cat.count(split="train") == 3
    assert cat.list(since="2999-01-01T00:00:00+00:00") == []
    assert cat.count(since=0.0) == 4
    assert cat.resolve(ids[1][:12]).episode_id == ids[1]
    s = cat.summary()
    assert s["episodes"] == 4 and s["by_split"] == {"train": 3, "eval": 1} and s["by_shape"]["T"] == 2
    with pytest.raises(CatalogError, match="no episode 'nope'"):
        cat.get("nope")
    with pytest.raises(CatalogError, match="unknown split 'test'"):
        cat.list(split="test")


def test_eval_split_pinned_hash_stable_and_excluded(cat, rng):
    train = [make_episode(rng) for _ in range(3)]
    evals = [make_episode(rng, shape=s) for s in ("T", "box", "L", "disk")]
    for ep in train:
        cat.add_episode(ep)
    for ep in evals:
        cat.add_episode(ep, split="eval")
    eval_ids = [e.meta.episode_id for e in evals]
    assert cat.eval_split() is None
    digest = cat.pin_eval_split(eval_ids[::-1], params={"episodes": 4, "seed": 1234})
    assert len(digest) == 64
    assert cat.pin_eval_split(eval_ids) == digest  # same set, any order: same hash
    split = cat.eval_split()
    assert split.ids == sorted(eval_ids) and split.hash == digest
    assert split.params == {"episodes": 4, "seed": 1234}
    assert Catalog(cat.data_dir).eval_split().hash == digest  # stable across processes/opens

    snap = cat.snapshot()
    assert snap.ids == sorted(e.meta.episode_id for e in train)
    assert not set(snap.ids) & set(eval_ids)
    assert cat.snapshot().snapshot_id == snap.snapshot_id
    cat.add_episode(make_episode(rng))
    assert cat.snapshot().snapshot_id != snap.snapshot_id
    assert cat.snapshot("eval").ids == sorted(eval_ids)

    with pytest.raises(CatalogError, match="already pinned"):
        cat.pin_eval_split(eval_ids[:2])


def test_eval_split_hash_is_content_hash(tmp_path, rng):
    """Two catalogs holding the same files pin the same hash."""
    evals = [make_episode(rng) for _ in range(2)]
    digests = []
    for name in ("a", "b"):
        cat = Catalog(tmp_path / name)
        for ep in evals:
            cat.add_episode(ep, split="eval")
        digests.append(cat.pin_eval_split([e.meta.episode_id for e in evals]))
    assert digests[0] == digests[1]


def test_pin_refuses_train_and_unknown(cat, rng):
    ep = make_episode(rng)
    cat.add_episode(ep)
    with pytest.raises(CatalogError, match="in split 'train'"):
        cat.pin_eval_split([ep.meta.episode_id])
    with pytest.raises(CatalogError, match="unknown episodes: ghost"):
        cat.pin_eval_split(["ghost"])
    with pytest.raises(CatalogError, match="at least one"):
        cat.pin_eval_split([])
    assert cat.eval_split() is None


def test_other_components_add_tables(cat):
    migrations = [("CREATE TABLE IF NOT EXISTS requests (id TEXT PRIMARY KEY)",),
                  ("ALTER TABLE requests ADD COLUMN status TEXT",)]
    with connect(cat.db_path) as conn:
        assert ensure_schema(conn, "queue", migrations[:1]) == 1
        assert ensure_schema(conn, "queue", migrations) == 2
        assert ensure_schema(conn, "queue", migrations) == 2  # idempotent
        conn.execute("INSERT INTO requests VALUES ('r', 'queued')")
        with pytest.raises(CatalogError, match="schema version 2, this code knows versions up to 1"):
            ensure_schema(conn, "queue", migrations[:1])
        with pytest.raises(RuntimeError):
            with transaction(conn):
                conn.execute("INSERT INTO requests VALUES ('s', 'queued')")
                raise RuntimeError("boom")
        assert conn.execute("SELECT COUNT(*) FROM requests").fetchone()[0] == 1


def test_concurrent_ingest_of_same_and_different_episodes(cat, rng):
    eps = [make_episode(rng) for _ in range(4)]
    blobs = [episodes.encode_episode(e) for e in eps] * 2  # each episode uploaded twice
    results, errors = [], []

    def worker(blob: bytes) -> None:
        try:
            results.append(cat.ingest_bytes(blob))
        except Exception as exc:  # collected and asserted on below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(b,)) for b in blobs]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert errors == []
    assert sum(not r.duplicate for r in results) == 4 and len(results) == 8
    assert cat.count() == 4 and len(mcap_files(cat)) == 4
    assert not [p for p in cat.episodes_dir.rglob("*") if p.is_file() and p.suffix != ".mcap"]
    for ep in eps:
        assert cat.verify(ep.meta.episode_id) == ep.meta


def test_catalog_files_are_plain(cat, rng):
    """The data directory holds only the database and dated episode folders."""
    cat.add_episode(make_episode(rng))
    names = set(os.listdir(cat.data_dir))
    assert {"catalog.sqlite", "episodes"} <= names
    assert names <= {"catalog.sqlite", "catalog.sqlite-wal", "catalog.sqlite-shm", "episodes"}


def test_a_damaged_database_file_is_a_storage_error_naming_the_file(tmp_path, rng):
    cat = Catalog(tmp_path)
    cat.add_episode(make_episode(rng))
    (tmp_path / "catalog.sqlite").write_bytes(b"this is not an SQLite file" * 100)
    for path in tmp_path.glob("catalog.sqlite-*"):  # WAL and shared-memory files of the old database
        path.unlink()
    with pytest.raises(CatalogError, match="catalog.sqlite.*not a database"):
        Catalog(tmp_path)
    with pytest.raises(CatalogError, match="not a database"):
        cat.count()
    with pytest.raises(RegistryError, match="catalog.sqlite.*not a database"):
        ModelRegistry(tmp_path)


def test_a_new_day_folder_is_made_durable_with_its_first_episode(tmp_path, rng, monkeypatch):
    synced: list[str] = []
    real = files.fsync_dir
    monkeypatch.setattr(files, "fsync_dir", lambda d: (synced.append(os.fspath(d)), real(d)))
    cat = Catalog(tmp_path / "data")
    res = cat.ingest_bytes(episodes.encode_episode(make_episode(rng, created="2031-05-05T10:00:00+00:00")))
    day = res.path.parent
    assert day.name == "2031-05-05"
    # The file's folder (for the rename) and the folder holding the new day's entry.
    assert os.fspath(day) in synced and os.fspath(day.parent) in synced
    synced.clear()
    cat.ingest_bytes(episodes.encode_episode(make_episode(rng, created="2031-05-05T11:00:00+00:00")))
    assert synced == [os.fspath(day)]  # the day exists now: only the rename is synced


def test_opening_current_stores_takes_no_write_lock(tmp_path, rng):
    """The dashboard opens the stores per request: it must not queue behind the service's writers."""
    cat = Catalog(tmp_path)
    ModelRegistry(tmp_path)
    RequestQueue(cat.db_path).close()
    writer = sqlite3.connect(cat.db_path, isolation_level=None)
    writer.execute("BEGIN IMMEDIATE")  # a writer holds the lock, as an ingest does
    opened: list[object] = []
    worker = threading.Thread(target=lambda: opened.extend(
        [Catalog(tmp_path).count(), ModelRegistry(tmp_path).champion(), RequestQueue(cat.db_path).counts()]))
    worker.start()
    try:
        wait_for(lambda: len(opened) == 3, timeout=10, message="the stores to open while the lock is held")
    finally:
        writer.execute("ROLLBACK")
        writer.close()
        worker.join()
    assert opened[0] == 0 and opened[1] is None


def test_files_a_crashed_ingest_left_are_found_and_swept(tmp_path, rng):
    """A SIGKILL after staging leaves a .tmp; one between rename and commit, an unindexed .mcap."""
    cat = Catalog(tmp_path)
    kept = cat.add_episode(make_episode(rng))
    day = kept.path.parent
    staged = files.stage_bytes(day / "lost.mcap", b"staged bytes")  # never renamed into place
    orphan = day / "orphan.mcap"
    orphan.write_bytes(episodes.encode_episode(make_episode(rng)))  # renamed into place, never committed
    assert cat.strays().staging == []  # a fresh staging file may belong to a live ingest: left alone
    later = time.time() + 3600
    found = cat.strays(now=later)
    assert found.staging == [staged] and found.unindexed == [orphan]
    cat.sweep_strays(now=later)
    assert not staged.exists() and not orphan.exists() and kept.path.is_file()
    assert (tmp_path / "orphans" / day.name / "orphan.mcap").is_file()  # kept for the operator
    assert cat.count() == 1 and not cat.strays(now=later)


@pytest.mark.parametrize("loss", ["missing", "empty"])
def test_a_lost_catalog_beside_its_data_is_refused_not_started_over(tmp_path, loss) -> None:
    data = tmp_path / "data"
    catalog = Catalog(data)
    row = catalog.add_episode(make_episode(np.random.default_rng(3)))
    ModelRegistry(data).register(b"weights", {}, {"h1_mse": 0.1}, "snap", "split")
    for suffix in ("", "-wal", "-shm"):
        Path(f"{catalog.db_path}{suffix}").unlink(missing_ok=True)
    if loss == "empty":
        catalog.db_path.write_bytes(b"")
    for store, error in ((Catalog, CatalogError), (ModelRegistry, RegistryError)):
        with pytest.raises(error, match=f"catalog.sqlite is {loss}, but .* holds the data it indexed"):
            store(data)
    assert row.path.is_file() and catalog.db_path.exists() == (loss == "empty")
    assert catalog.db_path.exists() is False or catalog.db_path.stat().st_size == 0


def test_a_lost_catalog_beside_only_quarantined_files_is_refused_too(tmp_path) -> None:
    data = tmp_path / "data"
    catalog = Catalog(data)
    row = catalog.quarantine(catalog.add_episode(make_episode(np.random.default_rng(3))).episode_id, "operator: x")
    for suffix in ("", "-wal", "-shm"):
        Path(f"{catalog.db_path}{suffix}").unlink(missing_ok=True)
    with pytest.raises(CatalogError, match="catalog.sqlite is missing, but .* holds the data it indexed"):
        Catalog(data)
    assert not catalog.db_path.exists() and not row.path.exists()
