"""Quarantine: episodes taken out of training with their files moved aside, brought back by a restore or by
their bytes ingested again; crashes and failed commits in between; the catalog's migration that added it."""

from __future__ import annotations

import pytest

from storage import files
from storage.catalog import Catalog
from storage.database import connect
from storage.errors import CatalogError, MissingEpisodeError
from tests.storage.test_episodes import assert_same, make_episode


def test_duplicate_bytes_repair_a_damaged_file(cat, rng):
    ep = make_episode(rng)
    res = cat.add_episode(ep)
    res.path.write_bytes(res.path.read_bytes()[:-10])
    again = cat.add_episode(ep)
    assert again.duplicate and again.restored
    assert cat.verify(ep.meta.episode_id) == ep.meta
    assert not cat.add_episode(ep).restored  # intact now: nothing to do


def test_quarantine_moves_the_file_aside_keeps_the_row_and_leaves_snapshots(cat, rng):
    eps = [make_episode(rng) for _ in range(3)]
    for ep in eps:
        cat.add_episode(ep)
    ids = [e.meta.episode_id for e in eps]
    before = cat.snapshot()
    row = cat.quarantine(ids[1], "camera\nglitch  ")
    assert row.quarantined == "camera glitch"  # one line
    assert not row.path.exists()
    kept = cat.data_dir / "quarantine" / row.path.parent.name / row.path.name
    assert files.sha256_hex(kept.read_bytes()) == row.sha256
    assert cat.snapshot().ids == sorted([ids[0], ids[2]]) == before.without([ids[1]]).ids
    assert cat.snapshot().snapshot_id == before.without([ids[1]]).snapshot_id != before.snapshot_id
    assert cat.count() == 3 and cat.count(quarantined=True) == 1 and cat.count(quarantined=False) == 2
    assert [r.episode_id for r in cat.list(quarantined=True)] == [ids[1]]
    assert cat.summary()["quarantined"] == 1
    assert cat.quarantine(ids[1], "other reason").quarantined == "camera glitch"  # the first reason stays
    with pytest.raises(MissingEpisodeError, match="quarantined .camera glitch.; .*episodes restore"):
        cat.load(ids[1])
    cat.sweep_strays(min_tmp_age_s=0)  # the moved file is not a crash's leftover: it stays where it was put
    assert kept.exists()
    restored = cat.restore(ids[1])
    assert restored.quarantined == "" and not kept.exists()
    assert cat.snapshot() == before
    assert_same(cat.load(ids[1]), eps[1])
    with pytest.raises(CatalogError, match="is not quarantined"):
        cat.restore(ids[1])


def test_a_quarantined_episode_whose_file_is_gone_comes_back_with_its_bytes(cat, rng):
    ep = make_episode(rng)
    res = cat.add_episode(ep)
    res.path.unlink()
    assert cat.quarantine(ep.meta.episode_id, "lost").quarantined == "lost"
    with pytest.raises(CatalogError, match="already missing when it was quarantined; ingest its original bytes"):
        cat.restore(ep.meta.episode_id)
    assert cat.count(quarantined=True) == 1
    again = cat.add_episode(ep)
    assert again.restored and cat.find(ep.meta.episode_id).quarantined == ""
    assert cat.verify(ep.meta.episode_id) == ep.meta


def test_restore_refuses_a_quarantined_file_that_was_damaged(cat, rng):
    ep = make_episode(rng)
    cat.add_episode(ep)
    row = cat.quarantine(ep.meta.episode_id, "suspect")
    kept = cat.data_dir / "quarantine" / row.path.parent.name / row.path.name
    kept.write_bytes(kept.read_bytes()[:-1])
    with pytest.raises(CatalogError, match="does not hold the bytes indexed"):
        cat.restore(ep.meta.episode_id)
    assert cat.find(ep.meta.episode_id).quarantined == "suspect" and not row.path.exists()


def test_the_pinned_eval_split_and_empty_reasons_cannot_be_quarantined(cat, rng):
    ep = make_episode(rng)
    cat.add_episode(ep, split="eval")
    cat.pin_eval_split([ep.meta.episode_id])
    with pytest.raises(CatalogError, match="pinned eval split, which cannot change"):
        cat.quarantine(ep.meta.episode_id, "bad")
    with pytest.raises(CatalogError, match="needs a reason"):
        cat.quarantine(ep.meta.episode_id, " \n")
    assert cat.count(quarantined=True) == 0 and cat.get(ep.meta.episode_id).path.exists()


def test_a_failed_move_quarantines_nothing(cat, rng, monkeypatch):
    ep = make_episode(rng)
    res = cat.add_episode(ep)

    def full_disk(src, dst):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr("storage.catalog_quarantine.move", full_disk)
    with pytest.raises(CatalogError, match="No space left on device"):
        cat.quarantine(ep.meta.episode_id, "bad")
    assert cat.count(quarantined=True) == 0 and res.path.exists()


def test_a_version_1_catalog_is_migrated_with_its_episodes(tmp_path, rng):
    data = tmp_path / "old"
    ep = make_episode(rng)
    Catalog(data).add_episode(ep)
    with connect(data / "catalog.sqlite") as conn:  # back to the catalog's tables as the first release made them
        conn.execute("DROP TABLE quarantine")
        conn.execute("UPDATE schema_versions SET version = 1 WHERE component = 'catalog'")
    cat = Catalog(data)
    with connect(data / "catalog.sqlite") as conn:
        assert dict(conn.execute("SELECT component, version FROM schema_versions").fetchall()) == {"catalog": 3}
    assert cat.list()[0].quarantined == "" and cat.snapshot().ids == [ep.meta.episode_id]
    assert cat.quarantine(ep.meta.episode_id, "x").quarantined == "x"


KILLED_IN_QUARANTINE = """
import os, signal, sys
import storage.catalog as catalog, storage.catalog_quarantine as quarantining, storage.files as files
def move_then_die(src, dst):  # the process is killed after the rename, before the row commits
    files.move(src, dst)
    os.kill(os.getpid(), signal.SIGKILL)
quarantining.move = move_then_die
catalog.Catalog(sys.argv[1]).quarantine(sys.argv[2], "operator: blurred")
"""


def _killed_in_quarantine(cat: Catalog, episode_id: str) -> None:
    import subprocess
    import sys
    from tests.conftest import REPO
    done = subprocess.run([sys.executable, "-c", KILLED_IN_QUARANTINE, str(cat.data_dir), episode_id], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == -9, done.stderr  # (SIGKILL)


def test_a_quarantine_killed_before_its_commit_is_healed_by_the_next_read(cat, rng):
    eps = [make_episode(rng) for _ in range(2)]
    rows = [cat.get(cat.add_episode(ep).episode_id) for ep in eps]
    for row in rows:
        _killed_in_quarantine(cat, row.episode_id)
        assert not row.path.exists() and cat.count(quarantined=True) == 0  # the file moved, the row did not
    assert_same(cat.load(rows[0].episode_id), eps[0])  # the read moves it back
    assert rows[0].path.exists() and not (cat.data_dir / "quarantine" / rows[0].path.parent.name /
                                          rows[0].path.name).exists()
    # quarantining it again takes the copy already kept; restore brings it back
    assert cat.quarantine(rows[1].episode_id, "operator: blurred").quarantined == "operator: blurred"
    assert cat.restore(rows[1].episode_id).quarantined == "" and cat.verify(rows[1].episode_id) == eps[1].meta


def test_a_quarantine_whose_commit_fails_moves_the_file_back(cat, rng, monkeypatch):
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)

    def move_then_fail(src, dst):
        files.move(src, dst)
        if dst != row.path:  # (the move back succeeds)
            raise OSError(5, "Input/output error")
    monkeypatch.setattr("storage.catalog_quarantine.move", move_then_fail)
    with pytest.raises(CatalogError, match="Input/output error"):
        cat.quarantine(ep.meta.episode_id, "bad")
    assert cat.count(quarantined=True) == 0 and cat.verify(ep.meta.episode_id) == ep.meta


def test_a_failed_commit_is_the_error_even_when_moving_the_file_back_fails(cat, rng, monkeypatch):
    from storage import quarantine
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)
    real_record = quarantine.record

    def record_then_break_the_commit(conn, *args):
        # A deferred foreign key is checked at COMMIT: this one makes the real COMMIT fail.
        conn.execute("PRAGMA defer_foreign_keys = ON")
        conn.execute("INSERT INTO eval_split_members(episode_id) VALUES ('no-such-episode')")
        return real_record(conn, *args)

    def move_back_fails(src, dst):
        if dst == row.path:  # the move back, under the write lock
            raise OSError(5, "Input/output error")
        files.move(src, dst)
    monkeypatch.setattr(quarantine, "record", record_then_break_the_commit)
    monkeypatch.setattr("storage.catalog_quarantine.move", move_back_fails)
    with pytest.raises(CatalogError, match="FOREIGN KEY constraint failed") as raised:
        cat.quarantine(ep.meta.episode_id, "bad")
    assert "cannot move" not in str(raised.value)
    assert any("could not be moved back" in note for note in getattr(raised.value, "__notes__", []))
    assert not row.path.exists() and cat.count(quarantined=True) == 0
    assert Catalog(cat.data_dir).verify(ep.meta.episode_id) == ep.meta  # the next read moves it back


def test_an_intact_kept_copy_is_never_overwritten_by_a_damaged_file(cat, rng):
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)
    good = row.path.read_bytes()
    kept = cat.data_dir / "quarantine" / row.path.parent.name / row.path.name
    kept.parent.mkdir(parents=True)
    kept.write_bytes(good)  # as a quarantine cut short leaves it
    row.path.write_bytes(good[:-5])  # and the file in place damaged since
    cat.quarantine(ep.meta.episode_id, "found by a training job: damaged")
    assert kept.read_bytes() == good
    assert cat.restore(ep.meta.episode_id).quarantined == "" and row.path.read_bytes() == good


def test_the_same_bytes_in_both_places_leave_episodes_with_the_next_quarantine(cat, rng):
    """As a move across file systems a crash cut short leaves them (test_cross_device.py): the file in place is
    moved over the intact copy, or it would stay in episodes/ while quarantined."""
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)
    kept = cat.data_dir / "quarantine" / row.path.parent.name / row.path.name
    kept.parent.mkdir(parents=True)
    kept.write_bytes(row.path.read_bytes())
    assert cat.quarantine(ep.meta.episode_id, "operator: blurred").quarantined == "operator: blurred"
    assert not row.path.exists() and files.holds(kept, row.sha256)
    assert cat.restore(ep.meta.episode_id).quarantined == "" and not kept.exists()
    assert cat.verify(ep.meta.episode_id) == ep.meta


def test_re_ingested_bytes_leave_no_copy_behind(cat, rng):
    ep = make_episode(rng)
    row = cat.quarantine(cat.add_episode(ep).episode_id, "operator: suspect")
    assert cat.add_episode(ep).restored
    assert not (cat.data_dir / "quarantine" / row.path.parent.name / row.path.name).exists()


def test_a_repair_that_came_first_wins_over_only_if_damaged(cat, rng):
    ep = make_episode(rng)
    row = cat.get(cat.add_episode(ep).episode_id)
    assert cat.quarantine(ep.meta.episode_id, "x", only_if_damaged=True).quarantined == ""  # intact: left alone
    assert row.path.exists() and cat.count(quarantined=True) == 0
    row.path.unlink()
    assert cat.quarantine(ep.meta.episode_id, "x", only_if_damaged=True).quarantined == "x"


def test_quarantine_answers_with_the_row_as_it_is_now(tmp_path, rng, monkeypatch):
    a, b = Catalog(tmp_path / "d"), Catalog(tmp_path / "d")
    episode_id = a.add_episode(make_episode(rng)).episode_id
    stale = a.get(episode_id)  # read by one process just before another quarantines it
    b.quarantine(episode_id, "first: by process B")
    real_get, calls = a.get, []
    monkeypatch.setattr(a, "get", lambda i: stale if not calls.append(i) and len(calls) == 1 else real_get(i))
    assert a.quarantine(episode_id, "second").quarantined == "first: by process B"


def test_quarantined_episodes_cannot_be_pinned(cat, rng):
    ep = make_episode(rng)
    cat.add_episode(ep, split="eval")
    cat.quarantine(ep.meta.episode_id, "operator: wrong object")
    with pytest.raises(CatalogError, match="are quarantined; restore them first"):
        cat.pin_eval_split([ep.meta.episode_id])
    assert cat.eval_split() is None
